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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.io import atomic_write_bytes, atomic_write_json, read_depth, write_depth_png  # noqa: F401

DEPTH_SUFFIXES = (".png", ".npy")


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
    with_shift: bool = False
    """Fit scale and shift (True) or scale only (False)."""
    per_image: bool = True
    """Fit the alignment per image (True, monocular scale drifts per frame) or once for all images."""
    error_max_m: float = 0.0
    """Top of the error map colour scale, metres; 0: the overall 95th percentile of |error|."""
    min_valid: int = 100
    """Images with fewer pixels valid in both maps are skipped (and listed)."""


@dataclass
class DepthCompareResult:
    alignment: str
    """'scale' or 'scale+shift', and 'per image' or 'global'."""
    overall: DepthMetrics
    """All compared pixels pooled (after their alignment)."""
    per_image: dict[str, DepthMetrics]
    """Metrics of each compared image, by file stem."""
    skipped: list[str] = field(default_factory=list)
    """Images without a reference map or with too few valid pixels."""
    error_maps: list[str] = field(default_factory=list)
    """Workspace-relative (or absolute, outside a workspace) paths of the |error| PNGs."""
    table: str = ""
    """Path of metrics.json."""


def _depth_files(folder: Path) -> dict[str, Path]:
    if not folder.is_dir():
        raise UserInputError(f"depth folder {folder} does not exist")
    files = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix in DEPTH_SUFFIXES}
    if not files:
        raise UserInputError(f"no depth maps (.png in mm or .npy in m) in {folder}")
    return files


def compare_depth_folders(pred_dir: str | Path, ref_dir: str | Path, out_dir: str | Path,
                          cfg: DepthCompareConfig) -> DepthCompareResult:
    """Per-image and pooled metrics of every prediction that has a reference of the same stem;
    writes ``out_dir/errors/<stem>.png`` and ``out_dir/metrics.json``."""

    pred_files, ref_files = _depth_files(Path(pred_dir)), _depth_files(Path(ref_dir))
    out_dir = Path(out_dir)
    pairs, skipped = [], []
    for stem, path in pred_files.items():
        ref = read_depth(ref_files[stem]) if stem in ref_files else None
        if ref is None:
            skipped.append(stem)
            continue
        pairs.append((stem, read_depth(path), ref))
    if not pairs:
        raise UserInputError(f"no depth map in {pred_dir} has a reference of the same name in {ref_dir}")
    fixed = None
    if not cfg.per_image:
        pred_all = np.concatenate([p[np.isfinite(p) & np.isfinite(r)] for _, p, r in pairs])
        ref_all = np.concatenate([r[np.isfinite(p) & np.isfinite(r)] for _, p, r in pairs])
        fixed = fit_scale_shift(pred_all, ref_all, cfg.with_shift)
    per_image, errors = {}, {}
    aligned_all, ref_all, n_pixels = [], [], 0
    for stem, pred, ref in pairs:
        try:
            m, err = compare_depth(pred, ref, cfg.with_shift, cfg.min_valid, fixed)
        except UserInputError:
            skipped.append(stem)
            continue
        per_image[stem], errors[stem] = m, err
        valid = np.isfinite(err)
        aligned_all.append(ref[valid] + err[valid])
        ref_all.append(ref[valid])
        n_pixels += ref.size
    if not per_image:
        raise UserInputError(f"no image has {cfg.min_valid} pixels valid in both depth maps")
    aligned_cat, ref_cat = np.concatenate(aligned_all), np.concatenate(ref_all)
    overall = metrics(aligned_cat, ref_cat, n_pixels, float(np.median([m.scale for m in per_image.values()])),
                      float(np.median([m.shift_m for m in per_image.values()])))
    top = cfg.error_max_m or float(np.percentile(np.abs(aligned_cat - ref_cat), 95))
    maps = []
    for stem, err in errors.items():
        path = out_dir / "errors" / f"{stem}.png"
        error_map_png(path, err, top)
        maps.append(str(path))
    alignment = ("scale+shift" if cfg.with_shift else "scale") + (", per image" if cfg.per_image else ", global")
    result = DepthCompareResult(alignment=alignment, overall=overall, per_image=per_image, skipped=sorted(skipped),
                                error_maps=maps, table=str(out_dir / "metrics.json"))
    atomic_write_json(out_dir / "metrics.json", result)
    return result
