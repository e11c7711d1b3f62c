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
    pool = Pool()
    pool.add(aligned, ref, n_pixels)
    return pool.metrics(scale, shift_m)


class Pool:
    """Running sums of aligned depths against their references, frame by frame: :meth:`metrics` gives what
    :func:`metrics` gives for all the samples at once, without holding them (a survey's frames one after another)."""

    def __init__(self) -> None:
        self.n = self.pixels = self.within = 0
        self.squared = self.relative = 0.0
        self.lo, self.hi = np.inf, -np.inf

    def add(self, aligned: np.ndarray, ref: np.ndarray, n_pixels: int) -> None:
        """One frame's valid samples (1-D) and its pixel count."""
        aligned, ref = np.asarray(aligned, np.float64), np.asarray(ref, np.float64)
        err = aligned - ref
        ratio = np.maximum(aligned / ref, ref / np.maximum(aligned, 1e-12))
        self.n += ref.size
        self.pixels += n_pixels
        self.squared += float(err @ err)
        self.relative += float(np.sum(np.abs(err) / ref))
        self.within += int(np.sum((aligned > 0) & (ratio < 1.25)))
        if ref.size:
            self.lo, self.hi = min(self.lo, float(ref.min())), max(self.hi, float(ref.max()))

    def metrics(self, scale: float, shift_m: float) -> DepthMetrics | None:
        """The pooled samples' metrics with this scale and shift recorded; None with fewer than two samples."""
        if self.n < 2:
            return None
        rmse = float(np.sqrt(self.squared / self.n))
        span = self.hi - self.lo
        return DepthMetrics(scale=scale, shift_m=shift_m, rmse_m=rmse,
                            rmse_over_range=rmse / span if span > 0 else np.nan, abs_rel=self.relative / self.n,
                            delta_125=self.within / self.n, coverage=self.n / max(self.pixels, 1), n_valid=int(self.n))


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


def _global_fit(pairs, with_shift: bool) -> tuple[float, float]:
    """Least-squares (s, t) of :func:`fit_scale_shift` over the valid pixels of every (prediction, reference) pair of
    ``pairs`` (an iterable, read one at a time), from running sums."""
    n = sp = sr = spp = spr = 0.0
    for pred, ref in pairs:
        valid = np.isfinite(pred) & np.isfinite(ref)
        p, r = pred[valid], ref[valid]
        n, sp, sr, spp, spr = n + p.size, sp + p.sum(), sr + r.sum(), spp + p @ p, spr + p @ r
    if n < 2:
        raise ValueError("need at least two valid pixels to align depth")
    if not with_shift:
        return float(spr / spp), 0.0
    s, t = np.linalg.solve(np.array([[spp, sp], [sp, n]]), np.array([spr, sr]))
    return float(s), float(t)


def _write_maps(folder: Path, errors: dict[str, np.ndarray], top: float) -> list[str]:
    for stem, err in errors.items():
        error_map_png(folder / f"{stem}.png", err.astype(np.float32), top)
    return [str(folder / f"{stem}.png") for stem in errors]


def compare_depth_folders(pred_dir: str | Path, ref_dir: str | Path, out_dir: str | Path,
                          cfg: DepthCompareConfig, navigation: Navigation | None = None) -> DepthCompareResult:
    """Per-image and pooled metrics of every prediction that has a reference of the same stem and, with
    ``navigation``, of the planes on the same frames (over all and over relief pixels); writes
    ``out_dir/errors/<stem>.png`` (the net), ``out_dir/errors_floor/<stem>.png`` (the flat seafloor) and
    ``out_dir/metrics.json``. The frames are read one at a time and pooled as running sums (:class:`Pool`), so memory
    does not grow with the survey beyond the error maps kept for the figures (half precision)."""

    pred_files, ref_files = _depth_files(Path(pred_dir)), _depth_files(Path(ref_dir))
    out_dir = Path(out_dir)
    stems = [stem for stem in pred_files if stem in ref_files]
    skipped = [stem for stem in pred_files if stem not in ref_files]
    if not stems:
        raise UserInputError(f"no depth map in {pred_dir} has a reference of the same name in {ref_dir}")

    def read(stem: str) -> tuple[np.ndarray, np.ndarray]:
        return read_depth(pred_files[stem]), read_depth(ref_files[stem])

    have_nav = navigation is not None and all(stem in navigation.altitude_m for stem in stems)

    def floor_of(stem: str, shape: tuple[int, int]) -> np.ndarray:
        return flat_floor_depth(navigation.altitude_m[stem], navigation.K_for(*shape), *shape,
                                navigation.down_cam.get(stem))

    alignment = "none" if cfg.metric else (
        ("scale+shift" if cfg.with_shift else "scale") + (", per image" if cfg.per_image else ", global"))
    fixed_net = fixed_floor = (1.0, 0.0) if cfg.metric else None
    if not cfg.metric and not cfg.per_image:  # one alignment over every frame: a first pass of running sums
        fixed_net = _global_fit((read(stem) for stem in stems), cfg.with_shift)
        if have_nav:
            fixed_floor = _global_fit(((floor_of(stem, ref.shape), ref) for stem in stems
                                       for ref in [read_depth(ref_files[stem])]), cfg.with_shift)
    pools: dict[str, tuple[Pool, Pool]] = {}
    fits: dict[str, list[tuple[float, float]]] = {}
    per_image: dict[str, DepthMetrics] = {}
    errors, floor_errors = {}, {}
    for stem in stems:
        pred, ref = read(stem)
        try:
            per_image[stem], err = compare_depth(pred, ref, cfg.with_shift, cfg.min_valid, fixed_net)
        except UserInputError:
            skipped.append(stem)
            continue
        compared = {NET: (per_image[stem], err)}
        relief = None
        if navigation is not None:
            plane, distance = best_plane(ref, navigation.K_for(*ref.shape))
            relief = distance > RELIEF_M
            planes = {}
            if have_nav:
                floor = floor_of(stem, ref.shape)
                planes = {FLOOR: (floor, (1.0, 0.0)), **({} if cfg.metric else {FLOOR_ALIGNED: (floor, fixed_floor)})}
            for name, (depth, fixed) in {**planes, BEST_PLANE: (plane, (1.0, 0.0))}.items():
                try:
                    compared[name] = compare_depth(depth, ref, cfg.with_shift, cfg.min_valid, fixed)
                except UserInputError:
                    continue
        for name, (m, e) in compared.items():
            everywhere, on_relief = pools.setdefault(name, (Pool(), Pool()))
            keep = np.isfinite(e)
            everywhere.add(ref[keep] + e[keep], ref[keep], e.size)
            if relief is not None:
                keep &= relief
                on_relief.add(ref[keep] + e[keep], ref[keep], e.size)
            fits.setdefault(name, []).append((m.scale, m.shift_m))
        errors[stem] = err.astype(np.float16)
        if FLOOR in compared:
            floor_errors[stem] = compared[FLOOR][1].astype(np.float16)
    if not per_image:
        raise UserInputError(f"no image has {cfg.min_valid} pixels valid in both depth maps")

    def pooled(name: str, pool: Pool) -> DepthMetrics | None:
        scale, shift = np.median(np.array(fits[name]), axis=0)
        return pool.metrics(float(scale), float(shift))

    how = {NET: alignment, FLOOR: "none", FLOOR_ALIGNED: alignment, BEST_PLANE: "none"}
    sources = {name: SourceMetrics(how[name], pooled(name, pools[name][0]),
                                   pooled(name, pools[name][1]) if navigation is not None else None)
               for name in (NET, FLOOR, FLOOR_ALIGNED, BEST_PLANE) if name in pools}
    overall = sources[NET].all
    top = cfg.error_max_m or float(np.nanpercentile(
        np.abs(np.concatenate([e.ravel() for e in errors.values()]).astype(np.float32)), 95))
    result = DepthCompareResult(alignment=alignment, overall=overall, per_image=per_image, skipped=sorted(skipped),
                                error_maps=_write_maps(out_dir / "errors", errors, top),
                                table=str(out_dir / "metrics.json"), sources=sources,
                                floor_error_maps=_write_maps(out_dir / "errors_floor", floor_errors, top))
    if navigation is not None:
        result.relief_fraction = pools[NET][1].n / max(overall.n_valid, 1)
        result.ratio_to = next(name for name in (FLOOR_ALIGNED, FLOOR, BEST_PLANE)
                               if name in sources and (name != FLOOR or cfg.metric))
        plane = sources[result.ratio_to]
        result.all_rmse_ratio = overall.rmse_m / plane.all.rmse_m
        if sources[NET].relief is not None and plane.relief is not None:
            result.relief_rmse_ratio = sources[NET].relief.rmse_m / plane.relief.rmse_m
    atomic_write_json(out_dir / "metrics.json", result)
    return result
