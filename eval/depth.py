"""Monocular (relative) depth against stereo/MVS depth.

A monocular network predicts depth up to an unknown scale (and, for some nets, shift). Before any
error is computed the prediction ``p`` is aligned to the reference ``r`` by least squares over the
pixels where both are valid:

    scale only:       s = sum(p r) / sum(p^2),                       d = s p
    scale and shift:  (s, t) = argmin sum (s p + t - r)^2,           d = s p + t

and the record says which was used. On the aligned depth ``d`` (metres, as the reference):

    RMSE        = sqrt(mean((d - r)^2))                     metres
    RMSE / range = RMSE / (max(r) - min(r))                 unitless, comparable across sites
    AbsRel      = mean(|d - r| / r)
    delta<1.25  = fraction of pixels with max(d / r, r / d) < 1.25
    coverage    = valid pixels (both maps) / all pixels

Depth maps are read from 16-bit PNGs in millimetres (0 = no value, the simulator's and the dense
stage's format) or ``.npy`` float arrays in metres (0 = no value), read by :func:`watergan.io.read_depth`
(NaN in memory marks no value).

A depth net is only worth its cost where it beats a plane, so beside it the comparison measures, with the
camera matrix (and the navigation, where the survey has one), planes that know nothing of the image:

- the flat seafloor at each frame's navigation altitude and attitude
  (:func:`watergan.formation.inverse.flat_floor_depth`), as monocular
  ``correct`` uses it: metric, no alignment; and the same plane aligned to the reference as the net is (its
  shape alone);
- the best plane: the plane through the frame's reference points with the least squared distances (total least
  squares, :func:`best_plane`), an upper bound for any plane however it is found, so a reference column.

Errors are pooled over all compared pixels and over *relief pixels*: those more than ``RELIEF_M`` (5 cm) from
their frame's best plane (rocks, mounds, coral), where a plane is wrong by construction and where the colour
correction needs the range. ``relief_rmse_ratio`` is the net's RMSE on relief pixels over the plane's under the
same alignment (the flat seafloor's; the best plane's without navigation). A metric prediction (``metric``: a net
scaled by the altimeter) is compared as it is, beside the flat seafloor as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from watergan.errors import UserInputError
from watergan.formation.inverse import flat_floor_depth, rays_cam
from watergan.io import atomic_write_bytes, atomic_write_json, read_depth, write_depth_png  # noqa: F401

if TYPE_CHECKING:
    from watergan.data import PinholeIntrinsics

DEPTH_SUFFIXES = (".png", ".npy")
RELIEF_M = 0.05
"""A relief pixel lies more than this (metres) from its frame's best plane."""
NET = "depth net"
FLOOR = "flat seafloor"
FLOOR_ALIGNED = "flat seafloor, aligned"
BEST_PLANE = "best plane"


@dataclass(frozen=True)
class DepthMetrics:
    """Errors of one aligned depth map (or of all pixels pooled)."""

    scale: float
    """Least-squares scale s applied to the prediction."""
    shift_m: float
    """Least-squares shift t, metres (0 when only scale was fitted)."""
    rmse_m: float
    """Root-mean-square error of the aligned depth, metres."""
    rmse_over_range: float
    """RMSE divided by the reference depth range (max - min over valid pixels)."""
    abs_rel: float
    """Mean of |d - r| / r."""
    delta_125: float
    """Fraction of valid pixels with max(d/r, r/d) < 1.25."""
    coverage: float
    """Pixels valid in both maps / all pixels."""
    n_valid: int
    """Number of pixels compared."""


def fit_scale_shift(pred: np.ndarray, ref: np.ndarray, with_shift: bool) -> tuple[float, float]:
    """Least-squares (s, t) with s pred + t ~ ref over the given 1-D samples (t = 0 without shift)."""
    pred = np.asarray(pred, np.float64)
    ref = np.asarray(ref, np.float64)
    if pred.size < 2:
        raise ValueError("need at least two valid pixels to align depth")
    if with_shift:
        a = np.stack([pred, np.ones_like(pred)], 1)
        (s, t), *_ = np.linalg.lstsq(a, ref, rcond=None)
        return float(s), float(t)
    return float(pred @ ref / (pred @ pred)), 0.0


def best_plane(ref: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plane closest to a frame's reference points (camera-z depth ``ref``, NaN = none, lifted to
    X = z K^-1 (x, y, 1)): through their centroid c, normal n the direction of least spread (the last right
    singular vector of X - c). Returns its depth along each pixel's ray, z = (c . n) / (d . n) for d = K^-1 (x, y, 1)
    (NaN where the ray misses it or meets it behind the camera), and each valid pixel's distance |(X - c) . n|
    (metres, NaN without reference)."""
    K = np.asarray(K, np.float64)
    rays = rays_cam(K, *ref.shape)
    valid = np.isfinite(ref) & (ref > 0)
    points = rays[valid] * ref[valid][:, None]
    centre = points.mean(0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    along = rays @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (centre @ normal) / along
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    distance = np.full(ref.shape, np.nan)
    distance[valid] = np.abs((points - centre) @ normal)
    return depth, distance


def metrics(aligned: np.ndarray, ref: np.ndarray, n_pixels: int, scale: float, shift_m: float) -> DepthMetrics:
    """Errors of aligned depths against reference depths (1-D arrays of valid samples)."""
    err = aligned - ref
    rmse = float(np.sqrt(np.mean(err**2)))
    span = float(ref.max() - ref.min())
    ratio = np.maximum(aligned / ref, ref / np.maximum(aligned, 1e-12))
    return DepthMetrics(scale=scale, shift_m=shift_m, rmse_m=rmse, rmse_over_range=rmse / span if span > 0 else np.nan,
                        abs_rel=float(np.mean(np.abs(err) / ref)),
                        delta_125=float(np.mean((aligned > 0) & (ratio < 1.25))),
                        coverage=ref.size / n_pixels, n_valid=int(ref.size))


def compare_depth(pred: np.ndarray, ref: np.ndarray, with_shift: bool = False, min_valid: int = 100,
                  fixed: tuple[float, float] | None = None) -> tuple[DepthMetrics, np.ndarray]:
    """Align ``pred`` to ``ref`` (both (H,W), NaN = no value) and measure; also returns the
    signed error map d - r (metres, NaN outside the valid pixels). ``fixed`` = (s, t) skips the fit
    (an alignment found elsewhere, e.g. over all images)."""
    if pred.shape != ref.shape:
        raise UserInputError(f"depth maps differ in size: prediction {pred.shape}, reference {ref.shape}")
    valid = np.isfinite(pred) & np.isfinite(ref) & (ref > 0)
    if valid.sum() < min_valid:
        raise UserInputError(f"only {int(valid.sum())} pixels are valid in both depth maps "
                             f"(need {min_valid}): check that the maps belong to the same images")
    s, t = fixed if fixed is not None else fit_scale_shift(pred[valid], ref[valid], with_shift)
    aligned = s * pred + t
    error = np.full(ref.shape, np.nan)
    error[valid] = aligned[valid] - ref[valid]
    return metrics(aligned[valid], ref[valid], ref.size, s, t), error


def error_map_png(path: str | Path, error_m: np.ndarray, max_abs_m: float) -> None:
    """|error| as a colour image (matplotlib 'magma', 0 .. ``max_abs_m``), black where no value."""
    import cv2
    from matplotlib import colormaps


    valid = np.isfinite(error_m)
    level = np.clip(np.abs(np.where(valid, error_m, 0)) / max(max_abs_m, 1e-9), 0, 1)
    rgb = (colormaps["magma"](level)[..., :3] * 255).astype(np.uint8)
    rgb[~valid] = 0
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise OSError(f"could not encode error map {path}")
    atomic_write_bytes(Path(path), data.tobytes())


@dataclass(frozen=True)
class DepthCompareConfig:
    """Compare a folder of monocular depth maps with a folder of stereo/MVS depth maps."""

    pred_dir: str
    """Folder of predicted (relative) depth maps: 16-bit PNG in mm or .npy in metres, named like the images."""
    ref_dir: str = ""
    """Folder of reference depth maps; empty: the dense stage's depth maps in the workspace."""
    navigation: str = ""
    """Survey file with each frame's nav_altitude_m (and nav_down_cam) and camera.json beside it, for the flat
    seafloor; empty: the workspace's survey (none: the planes are left out)."""
    metric: bool = False
    """The predictions are metric camera-z depth (a net scaled by the altimeter): compared as they are, and the
    ratios divide by the flat seafloor as it is."""
    with_shift: bool = False
    """Fit scale and shift (True) or scale only (False)."""
    per_image: bool = True
    """Fit the alignment per image (True, monocular scale drifts per frame) or once for all images."""
    error_max_m: float = 0.0
    """Top of the error map colour scale, metres; 0: the overall 95th percentile of the net's |error|."""
    min_valid: int = 100
    """Images with fewer pixels valid in both maps are skipped (and listed)."""


@dataclass(frozen=True)
class Navigation:
    """What the planes need: the camera and, by image stem, the navigation's altitude (metres) and "down"
    in the camera frame (absent: a nadir camera). Without altitudes only the best plane is measured."""

    camera: PinholeIntrinsics
    """The camera (depth maps of another size than its image take it resized to theirs)."""
    altitude_m: dict[str, float] = field(default_factory=dict)
    down_cam: dict[str, np.ndarray] = field(default_factory=dict)

    def K_for(self, h: int, w: int) -> np.ndarray:
        """The camera matrix for maps of h x w pixels."""
        return self.camera.resized(h, w).K

    @classmethod
    def from_survey(cls, survey_json: Path) -> Navigation | None:
        """The planes' inputs of a survey: ``camera.json`` beside its survey file (None without one) and, by image
        stem, the file's ``nav_altitude_m`` and ``nav_down_cam`` where it has them."""
        from watergan.data import DataError, read_intrinsics, read_nav_altitudes, read_nav_down

        camera = read_intrinsics(survey_json.parent)
        if camera is None:
            return None
        if not survey_json.is_file():
            return cls(camera)
        try:
            altitudes = read_nav_altitudes(survey_json)
        except DataError:
            return cls(camera)
        downs = read_nav_down(survey_json, list(altitudes)) or {}
        return cls(camera, {Path(name).stem: a for name, a in altitudes.items()},
                   {Path(name).stem: d for name, d in downs.items()})


@dataclass(frozen=True)
class SourceMetrics:
    """One depth source's errors, pooled over the compared frames."""

    alignment: str
    """How it met the reference: 'scale' or 'scale+shift' and 'per image' or 'global', or 'none' (metric)."""
    all: DepthMetrics
    """Over every compared pixel."""
    relief: DepthMetrics | None
    """Over the relief pixels (more than RELIEF_M from the frame's best plane); None without any."""


@dataclass
class DepthCompareResult:
    alignment: str
    """The net's: 'scale' or 'scale+shift', and 'per image' or 'global'; 'none' for metric predictions."""
    overall: DepthMetrics
    """The net's errors, all compared pixels pooled (after their alignment)."""
    per_image: dict[str, DepthMetrics]
    """The net's metrics of each compared image, by file stem."""
    skipped: list[str] = field(default_factory=list)
    """Images without a reference map or with too few valid pixels."""
    error_maps: list[str] = field(default_factory=list)
    """Workspace-relative (or absolute, outside a workspace) paths of the net's |error| PNGs (errors/)."""
    table: str = ""
    """Path of metrics.json."""
    sources: dict[str, SourceMetrics] = field(default_factory=dict)
    """The net and the planes (``NET``, ``FLOOR``, ``FLOOR_ALIGNED``, ``BEST_PLANE``), each pooled over all and
    over relief pixels; only the net without a camera."""
    relief_fraction: float = float("nan")
    """Share of the compared pixels that are relief pixels."""
    relief_rmse_ratio: float = float("nan")
    """The net's RMSE on relief pixels over the plane's under the same alignment (``ratio_to``: the flat seafloor,
    aligned as the net is or as it is for metric predictions; the best plane without navigation)."""
    all_rmse_ratio: float = float("nan")
    """The same over all compared pixels."""
    ratio_to: str = ""
    """The plane the ratios divide by."""
    floor_error_maps: list[str] = field(default_factory=list)
    """The flat seafloor's |error| PNGs (errors_floor/, the net's colour scale), same frames."""


def _depth_files(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        raise UserInputError(f"depth folder {folder} does not exist")
    files = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix in DEPTH_SUFFIXES}
    if not files:
        raise UserInputError(f"no depth maps (.png in mm or .npy in m) in {folder}")
    return files


def _global_fit(maps: dict[str, np.ndarray], refs: dict[str, np.ndarray], with_shift: bool) -> tuple[float, float]:
    pred = np.concatenate([maps[k][np.isfinite(maps[k]) & np.isfinite(refs[k])] for k in maps])
    ref = np.concatenate([refs[k][np.isfinite(maps[k]) & np.isfinite(refs[k])] for k in maps])
    return fit_scale_shift(pred, ref, with_shift)


def _compare_source(maps: dict[str, np.ndarray], refs: dict[str, np.ndarray], cfg: DepthCompareConfig,
                    aligned: bool) -> tuple[dict[str, DepthMetrics], dict[str, np.ndarray]]:
    """Each map against its reference, aligned as ``cfg`` says (``aligned``) or as it is: per-image metrics and
    signed error maps; frames with too few valid pixels are left out."""
    fixed = (1.0, 0.0) if not aligned else None if cfg.per_image else _global_fit(maps, refs, cfg.with_shift)
    per_image, errors = {}, {}
    for stem, pred in maps.items():
        try:
            per_image[stem], errors[stem] = compare_depth(pred, refs[stem], cfg.with_shift, cfg.min_valid, fixed)
        except UserInputError:
            continue
    return per_image, errors


def _pooled(per_image: dict[str, DepthMetrics], errors: dict[str, np.ndarray], refs: dict[str, np.ndarray],
            mask: dict[str, np.ndarray] | None = None) -> DepthMetrics | None:
    """The metrics of every compared pixel (inside ``mask`` when given) of the frames, their alignments' medians
    as its scale and shift; None when no pixel is left."""
    aligned, ref, n_pixels = [], [], 0
    for stem, err in errors.items():
        keep = np.isfinite(err) & (mask[stem] if mask is not None else True)
        aligned.append(refs[stem][keep] + err[keep])
        ref.append(refs[stem][keep])
        n_pixels += err.size
    if sum(a.size for a in aligned) < 2:
        return None
    return metrics(np.concatenate(aligned), np.concatenate(ref), n_pixels,
                   float(np.median([m.scale for m in per_image.values()])),
                   float(np.median([m.shift_m for m in per_image.values()])))


def _write_maps(folder: Path, errors: dict[str, np.ndarray], top: float) -> list[str]:
    for stem, err in errors.items():
        error_map_png(folder / f"{stem}.png", err, top)
    return [str(folder / f"{stem}.png") for stem in errors]


def compare_depth_folders(pred_dir: str | Path, ref_dir: str | Path, out_dir: str | Path,
                          cfg: DepthCompareConfig, navigation: Navigation | None = None) -> DepthCompareResult:
    """Per-image and pooled metrics of every prediction that has a reference of the same stem and, with
    ``navigation``, of the planes on the same frames (over all and over relief pixels); writes
    ``out_dir/errors/<stem>.png`` (the net), ``out_dir/errors_floor/<stem>.png`` (the flat seafloor) and
    ``out_dir/metrics.json``."""

    pred_files, ref_files = _depth_files(Path(pred_dir)), _depth_files(Path(ref_dir))
    out_dir = Path(out_dir)
    preds, refs, skipped = {}, {}, []
    for stem, path in pred_files.items():
        if stem not in ref_files:
            skipped.append(stem)
            continue
        preds[stem], refs[stem] = read_depth(path), read_depth(ref_files[stem])
    if not preds:
        raise UserInputError(f"no depth map in {pred_dir} has a reference of the same name in {ref_dir}")
    per_image, errors = _compare_source(preds, refs, cfg, aligned=not cfg.metric)
    if not per_image:
        raise UserInputError(f"no image has {cfg.min_valid} pixels valid in both depth maps")
    skipped += [stem for stem in preds if stem not in per_image]
    refs = {stem: refs[stem] for stem in per_image}
    alignment = "none" if cfg.metric else (
        ("scale+shift" if cfg.with_shift else "scale") + (", per image" if cfg.per_image else ", global"))
    sources: dict[str, SourceMetrics] = {}
    floor_errors: dict[str, np.ndarray] = {}
    relief = None
    if navigation is not None:
        planes = {stem: best_plane(ref, navigation.K_for(*ref.shape)) for stem, ref in refs.items()}
        relief = {stem: distance > RELIEF_M for stem, (_, distance) in planes.items()}
        compared = {BEST_PLANE: ("none", {stem: depth for stem, (depth, _) in planes.items()})}
        have_nav = all(stem in navigation.altitude_m for stem in refs)
        if have_nav:
            floors = {stem: flat_floor_depth(navigation.altitude_m[stem], navigation.K_for(*ref.shape), *ref.shape,
                                             navigation.down_cam.get(stem)) for stem, ref in refs.items()}
            aligned_floor = {} if cfg.metric else {FLOOR_ALIGNED: (alignment, floors)}
            compared = {FLOOR: ("none", floors), **aligned_floor, **compared}
        for name, (how, maps) in compared.items():
            m, e = _compare_source(maps, refs, cfg, aligned=how != "none")
            sources[name] = SourceMetrics(how, _pooled(m, e, refs), _pooled(m, e, refs, relief))
            if name == FLOOR:
                floor_errors = e
    sources = {NET: SourceMetrics(alignment, _pooled(per_image, errors, refs),
                                  _pooled(per_image, errors, refs, relief) if relief else None), **sources}
    overall = sources[NET].all
    top = cfg.error_max_m or float(np.nanpercentile(np.abs(np.concatenate([e.ravel() for e in errors.values()])), 95))
    result = DepthCompareResult(alignment=alignment, overall=overall, per_image=per_image, skipped=sorted(skipped),
                                error_maps=_write_maps(out_dir / "errors", errors, top),
                                table=str(out_dir / "metrics.json"), sources=sources,
                                floor_error_maps=_write_maps(out_dir / "errors_floor", floor_errors, top))
    if relief:
        n_relief = sum(int((relief[s] & np.isfinite(errors[s])).sum()) for s in errors)
        result.relief_fraction = n_relief / max(overall.n_valid, 1)
        result.ratio_to = next(name for name in (FLOOR_ALIGNED, FLOOR, BEST_PLANE)
                               if name in sources and (name != FLOOR or cfg.metric))
        plane = sources[result.ratio_to]
        result.all_rmse_ratio = overall.rmse_m / plane.all.rmse_m
        if sources[NET].relief is not None and plane.relief is not None:
            result.relief_rmse_ratio = sources[NET].relief.rmse_m / plane.relief.rmse_m
    atomic_write_json(out_dir / "metrics.json", result)
    return result
