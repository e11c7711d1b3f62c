"""Labelled objects of one colour seen at several ranges, and how constant a method keeps their colour.

A labels file (JSON) names objects whose reflectance does not change while their range does (a white board, a red
cone, a dark block, a patch of tiles), each with one region per frame in which it is seen::

    {"source": "...", "notice": "...", "image_size_px": [W, H],
     "objects": [{"name": "board", "kind": "white", "description": "...",
                  "frames": {"frame_01.jpg": {"box_px": [x0, y0, x1, y1]},
                             "frame_02.jpg": {"polygon_px": [[x, y], [x, y], [x, y], ...]}}}]}

Coordinates are pixels of the frames as given (before any undistortion or resizing), pixel (i, j) covering
[i, i + 1] x [j, j + 1] (a frame spans 0..W, 0..H); a region holds the pixels whose centres lie inside it (a box
[x0, y0, x1, y1]: columns x0 .. x1 - 1 for integer corners). ``kind`` is one of :data:`KINDS`.
:func:`load_object_labels` refuses a file with a region outside the frame, an empty box, an unknown kind or frame
name, with a one-line message naming the object and the frame.

Measures, per object and method, from the method's frames (linear RGB) and, where there is one, each frame's range
map (metres, NaN or 0 = none), both in the frames' geometry after the labels are mapped into it
(:func:`object_pixels`):

- the mean linear colour per frame, m_f = mean over the region's pixels (pixels at 0 in every channel, which a
  correction writes where it corrected nothing, and non-finite ones left out), and its chromaticity
  c_f = m_f / (m_f,R + m_f,G + m_f,B);
- the region's median range per frame r_f, and the object's median range, the median over its frames of r_f;
- the chromaticity spread across its frames, S = sum over channels k of (max_f c_f,k - min_f c_f,k): 0 for a
  method that keeps the object's colour at every range (and for one that makes every image grey: read it beside a
  fidelity measure);
- the slope of each channel's chromaticity against ln r_f (least squares over the frames with a range; None with
  fewer than two distinct ranges): per unit of ln r, so a factor e in range changes c_k by the slope;
- over objects, the median of S (:func:`objects_median_spread`).
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.io import read_json

#: The object kinds a labels file may name: what the object's reflectance is.
KINDS = ("white", "red", "yellow", "cyan", "dark", "tiles_wall", "tiles_floor")


@dataclass(frozen=True)
class LabelledObject:
    """One object of a labels file."""

    name: str
    kind: str
    """One of :data:`KINDS`."""
    description: str
    regions: dict[str, np.ndarray]
    """Frame file name -> (N,2) polygon corners in pixels of the labelled frames (a box as its four corners; pixel
    (i, j) covers [i, i + 1] x [j, j + 1])."""


@dataclass(frozen=True)
class ObjectLabels:
    """A labels file's contents (:func:`load_object_labels`)."""

    source: str
    notice: str
    width: int
    """Width of the frames the labels were drawn on, pixels."""
    height: int
    objects: list[LabelledObject]

    def frames(self) -> list[str]:
        """Every frame some object is labelled in, sorted."""
        return sorted({f for o in self.objects for f in o.regions})

    def n_object_frames(self) -> int:
        return sum(len(o.regions) for o in self.objects)


def _refuse(where: str, what: str) -> UserInputError:
    return UserInputError(f"labels file {where}: {what}")


def _region(entry, where: str, label: str, width: int, height: int) -> np.ndarray:
    """The (N,2) polygon of one frame's entry, checked (see the module docstring)."""
    if not isinstance(entry, dict) or len(set(entry) & {"box_px", "polygon_px"}) != 1:
        raise _refuse(where, f"{label} must hold exactly one of 'box_px' [x0, y0, x1, y1] or 'polygon_px' "
                             f"[[x, y], ...], got {entry!r}")
    try:
        if "box_px" in entry:
            box = np.asarray(entry["box_px"], float)
            if box.shape != (4,):
                raise ValueError("a box is 4 numbers")
            x0, y0, x1, y1 = box
            if not (x0 < x1 and y0 < y1):
                raise _refuse(where, f"{label}: box {entry['box_px']} must have x0 < x1 and y0 < y1")
            polygon = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        else:
            polygon = np.asarray(entry["polygon_px"], float)
            if polygon.ndim != 2 or polygon.shape[1] != 2 or len(polygon) < 3:
                raise ValueError("a polygon is 3 or more [x, y] points")
    except (TypeError, ValueError) as exc:
        raise _refuse(where, f"{label}: {exc} (got {next(iter(entry.values()))!r})") from exc
    if not np.isfinite(polygon).all():
        raise _refuse(where, f"{label}: coordinates must be finite numbers")
    if polygon[:, 0].min() < 0 or polygon[:, 1].min() < 0 or polygon[:, 0].max() > width or \
            polygon[:, 1].max() > height:
        raise _refuse(where, f"{label}: region {polygon.round(1).tolist()} leaves the {width}x{height} frame")
    x, y = polygon[:, 0], polygon[:, 1]
    if abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))) / 2 < 1.0:
        raise _refuse(where, f"{label}: polygon encloses less than one pixel")
    return polygon


def parse_object_labels(data, where: str, frame_names: Iterable[str] | None = None) -> ObjectLabels:
    """The labels of a parsed labels file (see the module docstring), checked; ``frame_names``: the frames that
    exist (a region in another frame is refused), None: not checked. ``where`` names the file in messages."""
    if not isinstance(data, dict) or not isinstance(data.get("objects"), list) or not data["objects"]:
        raise _refuse(where, "must be a JSON object with a non-empty list 'objects'")
    size = data.get("image_size_px")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise _refuse(where, f"'image_size_px' must be [width, height] of the labelled frames, got {size!r}")
    width, height = size
    known = set(frame_names) if frame_names is not None else None
    by_stem = {Path(n).stem for n in known} if known is not None else None
    objects, names = [], set()
    for i, item in enumerate(data["objects"]):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str) or not item["name"]:
            raise _refuse(where, f"object {i} needs a 'name'")
        name = item["name"]
        if name in names:
            raise _refuse(where, f"object name {name!r} is used twice")
        names.add(name)
        if item.get("kind") not in KINDS:
            raise _refuse(where, f"object {name!r}: 'kind' must be one of {', '.join(KINDS)}, got "
                                 f"{item.get('kind')!r}")
        frames = item.get("frames")
        if not isinstance(frames, dict) or not frames:
            raise _refuse(where, f"object {name!r} needs 'frames': frame file name -> region")
        regions = {}
        for frame, entry in frames.items():
            if known is not None and frame not in known and Path(frame).stem not in by_stem:
                raise _refuse(where, f"object {name!r}: frame {frame!r} is not a frame of the survey (e.g. "
                                     f"{min(known)!r})")
            regions[frame] = _region(entry, where, f"object {name!r}, frame {frame!r}", width, height)
        objects.append(LabelledObject(name, item["kind"], str(item.get("description", "")), regions))
    return ObjectLabels(str(data.get("source", "")), str(data.get("notice", "")), width, height, objects)


def load_object_labels(path: str | Path, frame_names: Iterable[str] | None = None) -> ObjectLabels:
    """A labels file (see the module docstring), checked; ``frame_names``: the frames that exist, or None."""
    return parse_object_labels(read_json(path, "labels file"), str(path), frame_names)


def apparent_size_ratio(obj: LabelledObject) -> float:
    """Max over min across the object's frames of the square root of its region's area: how much nearer the nearest
    view is than the farthest, read from the image alone (a proxy for the range ratio, which the workspace's range
    measures: a region cut by the frame's edge reads smaller than the object is)."""
    def area(p: np.ndarray) -> float:
        return abs(float(np.dot(p[:, 0], np.roll(p[:, 1], 1)) - np.dot(p[:, 1], np.roll(p[:, 0], 1)))) / 2

    sides = [np.sqrt(area(p)) for p in obj.regions.values()]
    return max(sides) / min(sides)


def region_mask(polygon: np.ndarray, shape_hw: tuple[int, int], scale_xy: tuple[float, float] = (1.0, 1.0)
                ) -> np.ndarray:
    """(H,W) bool: the pixels whose centres (i + 0.5, j + 0.5) lie inside ``polygon`` (pixels) scaled by
    ``scale_xy``."""
    from matplotlib.path import Path as Outline

    h, w = shape_hw
    points = np.asarray(polygon, float) * np.asarray(scale_xy, float)
    mask = np.zeros((h, w), bool)
    x0, y0 = np.maximum(np.floor(points.min(0)).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(points.max(0)).astype(int), [w, h])
    if x1 <= x0 or y1 <= y0:
        return mask
    jj, ii = np.mgrid[y0:y1, x0:x1]
    centres = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], 1)
    mask[y0:y1, x0:x1] = Outline(points).contains_points(centres).reshape(jj.shape)
    return mask


def object_pixels(labels: ObjectLabels, shape_hw: tuple[int, int], frame_names: Iterable[str] | None = None,
                  warp: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Per object, per frame, the flat indices of its region's pixels in frames of size ``shape_hw`` (the labels
    scaled from their frame size), after ``warp`` (a bool mask in the labelled geometry at ``shape_hw`` -> the
    same in the measured frames', e.g. undistortion) when given. ``frame_names``: the measured frames' names
    (matched by stem, so a JPEG label finds a PNG frame); None: the labels' names. Regions warped to no pixel are
    left out."""
    h, w = shape_hw
    scale = (w / labels.width, h / labels.height)
    by_stem = {Path(n).stem: n for n in frame_names} if frame_names is not None else None
    out: dict[str, dict[str, np.ndarray]] = {}
    for obj in labels.objects:
        regions = {}
        for frame, polygon in obj.regions.items():
            name = frame if by_stem is None else by_stem.get(Path(frame).stem)
            if name is None:
                continue
            mask = region_mask(polygon, shape_hw, scale)
            if warp is not None:
                mask = warp(mask)
            if mask.any():
                regions[name] = np.flatnonzero(mask)
        out[obj.name] = regions
    return out


@dataclass
class ObjectSeries:
    """One object's colour and range in each frame it is measured in."""

    frames: list[str]
    rgb: np.ndarray
    """(F,3) mean linear colour of its region per frame."""
    range_m: np.ndarray
    """(F,) median range of its region per frame (NaN: no range there)."""
    pixels: np.ndarray
    """(F,) pixels averaged per frame."""


def object_colours(images: Mapping[str, np.ndarray], pixels: dict[str, dict[str, np.ndarray]],
                   ranges: Mapping[str, np.ndarray | None] | None = None) -> dict[str, ObjectSeries]:
    """Per object, its mean colour and median range in each frame of ``pixels`` (:func:`object_pixels`) that
    ``images`` holds (frame name -> (H,W,3) linear RGB; a lazy mapping reads each frame once: the frames are
    visited in order and every object's region read from it). ``ranges``: frame name -> (H,W) metres (NaN or
    <= 0: none), or None. A frame where every pixel of the region is 0 or non-finite is left out."""
    frames = sorted({f for regions in pixels.values() for f in regions})
    rows: dict[str, list] = {name: [] for name in pixels}
    for frame in frames:
        if frame not in images:
            continue
        image = np.asarray(images[frame], np.float64).reshape(-1, 3)
        range_map = ranges.get(frame) if ranges is not None else None
        flat_range = np.asarray(range_map, np.float64).ravel() if range_map is not None else None
        for name, regions in pixels.items():
            if frame not in regions:
                continue
            values = image[regions[frame]]
            keep = np.isfinite(values).all(1) & (values > 0).any(1)
            if not keep.any():
                continue
            r = np.nan
            if flat_range is not None:
                rr = flat_range[regions[frame]]
                rr = rr[np.isfinite(rr) & (rr > 0)]
                r = float(np.median(rr)) if rr.size else np.nan
            rows[name].append((frame, values[keep].mean(0), r, int(keep.sum())))
    return {name: ObjectSeries([f for f, *_ in row], np.array([m for _, m, _, _ in row]).reshape(-1, 3),
                               np.array([r for _, _, r, _ in row], float), np.array([n for *_, n in row], int))
            for name, row in rows.items()}


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """c = rgb / (R + G + B) along the last axis (NaN where the sum is not positive)."""
    rgb = np.asarray(rgb, np.float64)
    total = rgb.sum(-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, rgb / total, np.nan)


def chromaticity_spread(rgb: np.ndarray) -> float:
    """S = sum over channels of (max - min) over the rows of the chromaticity of ``rgb`` (F,3); NaN with no row."""
    c = chromaticity(rgb)
    c = c[np.isfinite(c).all(1)]
    return float((c.max(0) - c.min(0)).sum()) if len(c) else float("nan")


def log_range_slope(rgb: np.ndarray, range_m: np.ndarray) -> list[float] | None:
    """Per channel, the least-squares slope of the chromaticity of ``rgb`` (F,3) against ln ``range_m`` (F,) over
    the rows with a positive range; None with fewer than two distinct ranges."""
    c = chromaticity(rgb)
    r = np.asarray(range_m, float)
    ok = np.isfinite(r) & (r > 0) & np.isfinite(c).all(1)
    if len(np.unique(r[ok])) < 2:
        return None
    x = np.log(r[ok]) - np.log(r[ok]).mean()
    y = c[ok] - c[ok].mean(0)
    return [float(v) for v in (x @ y) / (x @ x)]


def object_constancy(series: ObjectSeries, kind: str = "") -> dict:
    """The measures of the module docstring for one object's series (JSON-ready: rounded lists and numbers; None
    where not measurable)."""
    finite = series.range_m[np.isfinite(series.range_m)]
    slope = log_range_slope(series.rgb, series.range_m)
    return {"kind": kind, "frames": series.frames,
            "mean_linear_rgb": np.round(series.rgb, 6).tolist(),
            "chromaticity": np.round(chromaticity(series.rgb), 5).tolist(),
            "range_m": [None if not np.isfinite(r) else round(float(r), 4) for r in series.range_m],
            "pixels": series.pixels.tolist(),
            "median_range_m": round(float(np.median(finite)), 4) if finite.size else None,
            "range_ratio": round(float(finite.max() / finite.min()), 3) if finite.size else None,
            "object_chromaticity_spread": round(chromaticity_spread(series.rgb), 5) if len(series.frames) else None,
            "chromaticity_slope_per_log_range": None if slope is None else [round(v, 5) for v in slope]}


def objects_median_spread(per_object: Mapping[str, dict]) -> float | None:
    """The median over objects of their ``object_chromaticity_spread`` (objects seen in fewer than two frames left
    out); None when none is left."""
    values = [o["object_chromaticity_spread"] for o in per_object.values()
              if o.get("object_chromaticity_spread") is not None and len(o["frames"]) >= 2]
    return round(float(np.median(values)), 5) if values else None


def measure_objects(images: Mapping[str, np.ndarray], labels: ObjectLabels,
                    pixels: dict[str, dict[str, np.ndarray]] | None = None,
                    ranges: Mapping[str, np.ndarray | None] | None = None) -> dict:
    """Every object's :func:`object_constancy` in ``images`` (frame name -> linear RGB; the regions from
    ``pixels``, or :func:`object_pixels` at the first labelled image's size without a warp) and
    ``objects_median_spread`` over them: ``{"objects": {name: {...}}, "objects_median_spread": S}``."""
    if pixels is None:
        first = next((f for f in labels.frames() if f in images), None)
        if first is None:
            raise UserInputError("none of the labelled frames is among the images measured")
        pixels = object_pixels(labels, np.shape(images[first])[:2], list(images))
    kinds = {o.name: o.kind for o in labels.objects}
    series = object_colours(images, pixels, ranges)
    per_object = {name: object_constancy(s, kinds.get(name, "")) for name, s in series.items()}
    return {"objects": per_object, "objects_median_spread": objects_median_spread(per_object)}


def chromaticity_figure(per_method: Mapping[str, Mapping[str, dict]], path: str | Path, title: str = "",
                        note: str = "") -> None:
    """A PNG of each object's chromaticity (red share above, blue share below) against its range (log axis), one
    column per method (``per_method``: method -> :func:`measure_objects`' ``objects``), raw first: a method that
    keeps an object's colour draws it flat. Frames without a range are left out of the figure. ``note``: a line
    written under it (the data's notice)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    from watergan.io import atomic_write_bytes

    methods = list(per_method)
    fig, axes = plt.subplots(2, len(methods), figsize=(max(3.2 * len(methods), 6.4), 6.2), sharex=True, sharey="row",
                             squeeze=False)
    names = sorted({n for objects in per_method.values() for n, e in objects.items()
                    if any(r is not None for r in e["range_m"])})
    colours = plt.get_cmap("tab10")
    for j, method in enumerate(methods):
        for i, name in enumerate(names):
            entry = per_method[method].get(name)
            if entry is None:
                continue
            r = np.array([np.nan if v is None else v for v in entry["range_m"]], float)
            c = np.asarray(entry["chromaticity"], float).reshape(-1, 3)
            order = np.argsort(r)
            ok = np.isfinite(r[order])
            for row, ch in enumerate((0, 2)):
                axes[row, j].plot(r[order][ok], c[order][ok, ch], "o-", ms=3, lw=1, color=colours(i % 10),
                                  label=name if j == 0 and row == 0 else None)
        axes[0, j].set_title(method)
        axes[1, j].set_xlabel("range (m)")
        for row in range(2):
            axes[row, j].set_xscale("log")
            axes[row, j].xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axes[row, j].xaxis.set_major_formatter(FormatStrFormatter("%g"))
            axes[row, j].xaxis.set_minor_formatter(NullFormatter())
            axes[row, j].grid(alpha=0.3)
    axes[0, 0].set_ylabel("R / (R+G+B)")
    axes[1, 0].set_ylabel("B / (R+G+B)")
    if names:
        fig.legend(loc="lower center", bbox_to_anchor=(0.5, 0.03), ncol=min(len(names), 5), fontsize=7)
    fig.suptitle(title or "Labelled objects' chromaticity against range (flat: the colour kept)", fontsize=9)
    if note:
        fig.text(0.5, 0.005, note, ha="center", va="bottom", fontsize=6)
    fig.tight_layout(rect=(0, 0.16, 1, 0.96))
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())


def additive_term(range_m, b_inf: Mapping, beta_per_m: Mapping, gain: Mapping | None = None) -> dict:
    """The water's additive term at each range of ``range_m`` (F,), per channel, at the image centre:

        C(r) = k B_inf (1 - exp(-beta r))

    (the veil of the ``backscatter`` effect through the sensor gain ``k``; at the centre the vignetting is 1). Left
    out: the gains per frame (taken as 1), the fitted additive field over the image and any black level or tone curve
    of the stack, so C is the stack's own veil, not all that the fit adds to a dark pixel. ``b_inf``, ``beta_per_m``,
    ``gain``: {"value", "low", "high"} (per channel or one value; low/high None: no interval; ``gain`` None: k = 1).
    C rises with each of k, B_inf and beta, so over the box of their intervals its least value is at the three
    lows and its greatest at the three highs: ``low``/``high`` (F,3), None when a parameter has no interval. The box
    ignores the correlation the bootstrap finds between B_inf and beta (the valley), so it is wider than the joint
    interval of the veil at one range. Returns {"value", "low", "high"} as (F,3) arrays (or None)."""
    r = np.asarray(range_m, np.float64).reshape(-1, 1)
    gain = gain or {"value": 1.0, "low": 1.0, "high": 1.0}

    def at(which: str):
        parts = [p.get(which) for p in (gain, b_inf, beta_per_m)]
        if any(v is None for v in parts):
            return None
        k, b, beta = (np.broadcast_to(np.asarray(v, np.float64).reshape(-1), (3,)) for v in parts)
        return k * b * -np.expm1(-beta * r)

    return {"value": at("value"), "low": at("low"), "high": at("high")}


def dark_object_veil(per_object: Mapping[str, dict], b_inf: Mapping, beta_per_m: Mapping,
                     gain: Mapping | None = None) -> dict:
    """The dark objects (kind "dark") of :func:`measure_objects`' ``objects`` (raw frames: each frame's mean linear
    colour m_f and its region's median range r_f) beside the water's additive term C(r_f) of :func:`additive_term`:
    a near-black object holds little but the veil, so m_f should lie within [C_low, C_high] (or a little above it,
    by the object's own small reflectance). Per object and frame: range, radiance, C's value, low and high,
    ``inside`` per channel (None without an interval or a range) and ``excess`` m_f - C(r_f); per object its median
    range and the share of its channel-frames inside; over all, ``inside_fraction``. Frames without a range are
    listed with C None."""
    out, inside_all = {}, []
    for name, entry in per_object.items():
        if entry.get("kind") != "dark":
            continue
        r = np.array([np.nan if v is None else v for v in entry["range_m"]], float)
        rgb = np.asarray(entry["mean_linear_rgb"], float).reshape(-1, 3)
        term = additive_term(np.where(np.isfinite(r), r, 0.0), b_inf, beta_per_m, gain)
        rows, inside_object = [], []
        for f, frame in enumerate(entry["frames"]):
            row = {"frame": frame, "range_m": None if not np.isfinite(r[f]) else round(float(r[f]), 4),
                   "radiance": np.round(rgb[f], 6).tolist(), "veil": None, "veil_low": None, "veil_high": None,
                   "inside": None, "excess": None}
            if np.isfinite(r[f]) and term["value"] is not None:
                row["veil"] = np.round(term["value"][f], 6).tolist()
                row["excess"] = np.round(rgb[f] - term["value"][f], 6).tolist()
                if term["low"] is not None and term["high"] is not None:
                    row["veil_low"] = np.round(term["low"][f], 6).tolist()
                    row["veil_high"] = np.round(term["high"][f], 6).tolist()
                    inside = (rgb[f] >= term["low"][f]) & (rgb[f] <= term["high"][f])
                    row["inside"] = [bool(v) for v in inside]
                    inside_object += row["inside"]
            rows.append(row)
        inside_all += inside_object
        out[name] = {"median_range_m": entry.get("median_range_m"), "frames": rows,
                     "inside_fraction": round(float(np.mean(inside_object)), 4) if inside_object else None}
    return {"objects": out, "inside_fraction": round(float(np.mean(inside_all)), 4) if inside_all else None,
            "form": "C(r) = k B_inf (1 - exp(-beta r)) at the image centre; gains per frame 1, the additive field, "
                    "black level and tone curve left out; interval: the box of k, B_inf and beta's intervals"}


class LazyFrames(Mapping):
    """Frame name -> array, read on access by ``read(name)`` (:func:`object_colours` visits each frame once)."""

    def __init__(self, names: Iterable[str], read: Callable[[str], np.ndarray | None]):
        self.names, self.read = list(names), read

    def __getitem__(self, name: str):
        if name not in self.names:
            raise KeyError(name)
        return self.read(name)

    def __contains__(self, name) -> bool:
        return name in self.names

    def __iter__(self):
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)


def undistortion_warp(camera: Mapping) -> Callable[[np.ndarray], np.ndarray] | None:
    """The labels' masks (drawn on the original frames) into a workspace's undistorted frames: the lens its
    ``camera.json`` (``camera``) records as removed (``undistorted``) applied to the mask as to the frames
    (:func:`watergan.lens.undistort_image`); None without one."""
    from watergan.lens import camera_matrix, distortion_of, undistort_image

    lens = distortion_of(camera.get("undistorted", {})) if camera.get("undistorted") else None
    if lens is None:
        return None
    K = camera_matrix(dict(camera))
    return lambda mask: undistort_image(mask.astype(np.uint8) * 255, K, lens) > 127


def range_frames(folder: Path, names: Iterable[str]) -> LazyFrames:
    """Each frame's range (metres, NaN: none) from a folder of range maps (``<stem>.png``, 16-bit millimetres, 0:
    none, as the range stage writes them); None for a frame without a map."""
    from watergan.io import read_millimetres

    def read(name: str) -> np.ndarray | None:
        path = Path(folder) / f"{Path(name).stem}.png"
        if not path.is_file():
            return None
        r = read_millimetres(path) / 1000.0
        return np.where(r > 0, r, np.nan)

    return LazyFrames(names, read)


def spread_table(per_method: Mapping[str, Mapping[str, dict]]) -> dict:
    """Per object, its kind, frames, range span and each method's chromaticity spread with its ratio to raw's
    (``per_method``: method -> :func:`measure_objects`' ``objects``, raw among them for the ratios), and the median
    over objects: {"methods": [...], "rows": [{"name", "kind", "frames", "range_m": [min, max] or None,
    "spread": {method: S}, "over_raw": {method: S / S_raw}}], "median": {method: S}}."""
    methods = list(per_method)
    names = sorted({n for objects in per_method.values() for n in objects})
    rows = []
    for name in names:
        entries = {m: per_method[m][name] for m in methods if name in per_method[m]}
        first = next(iter(entries.values()))
        ranges = [r for r in first["range_m"] if r is not None]
        spread = {m: e.get("object_chromaticity_spread") for m, e in entries.items()}
        raw = spread.get("raw")
        rows.append({"name": name, "kind": first.get("kind", ""), "frames": len(first["frames"]),
                     "range_m": [min(ranges), max(ranges)] if ranges else None, "spread": spread,
                     "over_raw": {m: round(v / raw, 4) for m, v in spread.items() if v is not None and raw}})
    return {"methods": methods, "rows": rows, "median": {m: objects_median_spread(per_method[m]) for m in methods}}
