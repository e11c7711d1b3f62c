"""Where a fitted model fails: residuals binned along every axis, structure scores, plots, a PLY.

Axes (``Effect.AXES``): image_position (a 2-D grid over the pixel fraction u, v), range (metres),
intensity (predicted grey level, mean over channels), light_distance (distance to the nearest
declared light, metres; only when the survey declares lights), height (world z, metres),
spatial_frequency (log10 gradient energy of the patch), frame (frame index, one bin per frame).

Structure score of an axis: per channel c and bin b with at least ``min_count`` observations, the
bin mean m_bc, its standard error se_bc = std_bc / sqrt(n_b) and the inverse-variance weighted
mean m_c of the bin means; score = sqrt(mean_bc ((m_bc - m_c) / se_bc)^2). It is about 1 when the
residual does not depend on the axis and grows with systematic structure. Residuals of one point
share its fitted albedo, so the score of pure noise is somewhat below or above 1, not exactly 1.

Amplitude of an axis: sqrt(mean_bc (m_bc - m_c)^2), linear colour units: how large the structure
is. With tens of thousands of observations a score above 3 can come from bin means a few 1e-4 apart
(e.g. the darkest patches, where 8-bit quantisation and noise clipped at 0 bias the mean), so the
diagnosis reports an axis only when its amplitude is also a sizeable fraction of the residual RMSE.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .observations import Observations


@dataclass(frozen=True)
class ResidualConfig:
    """How residuals are binned."""

    n_bins: int = 10
    """Bins of a continuous axis (quantiles of the axis values)."""
    grid_uv: tuple[int, int] = (8, 6)
    """Bins across (u) and down (v) the image for the image-position heat map."""
    min_count: int = 10
    """Observations a bin needs to count in the structure score."""


def axis_values(meas: Observations, predicted: np.ndarray) -> dict[str, np.ndarray]:
    """The value of each 1-D axis per observation (image_position is handled as 2-D)."""
    values = {
        "range": meas.range_m,
        "intensity": predicted.mean(1),
        "height": meas.height_m[meas.point],
        "spatial_frequency": np.log10(meas.grad_energy + 1e-9),
        "frame": meas.frame.astype(np.float64),
    }
    if meas.light_distance_m.shape[1]:
        values["light_distance"] = meas.light_distance_m.min(1)
    if meas.normals_cam is not None:
        values["incidence_angle"] = incidence_angle_deg(meas.points_cam, meas.normals_cam)
    return values


def incidence_angle_deg(points_cam: np.ndarray, normals_cam: np.ndarray) -> np.ndarray:
    """(N,) acos(|n . X| / |X|) in degrees: the angle between each view's unit normal n and the ray from its point X
    (camera frame) back to the camera; 0 head-on, 90 grazing (the normal's sign does not matter)."""
    cosine = np.abs((normals_cam * points_cam).sum(1)) / np.maximum(np.linalg.norm(points_cam, axis=1), 1e-9)
    return np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))


#: Edges (degrees from up) of the histogram of the surfaces' orientations.
ORIENTATION_EDGES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0, 105.0, 120.0, 135.0, 150.0, 165.0, 180.0)
#: Angle from up (degrees) of the floor-like, wall-like and ceiling-like classes: [lo, hi).
ORIENTATION_CLASSES = {"floor": (0.0, 30.0), "wall": (60.0, 120.0), "ceiling": (150.0, 180.1)}


def surface_orientations(meas: Observations) -> dict:
    """The orientations of the surfaces the table's points lie on: {"edges_deg", "count"} (the histogram of each
    point's world normal's angle from up, ``ORIENTATION_EDGES_DEG``), the points per class of
    ``ORIENTATION_CLASSES`` and their share, "other" for the rest; {} when the table holds no world normals."""
    if meas.normals_world is None or not len(meas.normals_world):
        return {}
    up = np.degrees(np.arccos(np.clip(meas.normals_world[:, 2], -1.0, 1.0)))
    count, _ = np.histogram(up, bins=np.asarray(ORIENTATION_EDGES_DEG))
    classes = {name: int(((up >= lo) & (up < hi)).sum()) for name, (lo, hi) in ORIENTATION_CLASSES.items()}
    classes["other"] = len(up) - sum(classes.values())
    return {"edges_deg": list(ORIENTATION_EDGES_DEG), "count": count.tolist(), "points": classes,
            "share": {k: round(v / len(up), 3) for k, v in classes.items()}}


def orientations_line(orientations: dict) -> str:
    """One line on the surfaces seen, e.g. "surfaces: 97% floor-like, 2% wall-like, 0% ceiling-like (normals within
    30 degrees of up; 60-120 degrees)"; "" without normals."""
    if not orientations:
        return ""
    share = orientations["share"]
    return (f"surfaces: {share['floor']:.0%} floor-like, {share['wall']:.0%} wall-like, {share['ceiling']:.0%} "
            f"ceiling-like, {share['other']:.0%} other (normals within 30 degrees of up, 60-120, beyond 150) of "
            f"{sum(orientations['points'].values())} points")


def _bin_stats(index: np.ndarray, n_bins: int, residual: np.ndarray) -> dict:
    """Per bin: count (B,), mean (B,3), standard error (B,3)."""
    count = np.bincount(index, minlength=n_bins).astype(np.float64)
    total = np.stack([np.bincount(index, residual[:, c], minlength=n_bins) for c in range(3)], 1)
    total2 = np.stack([np.bincount(index, residual[:, c] ** 2, minlength=n_bins) for c in range(3)], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count[:, None]
        var = np.maximum(total2 / count[:, None] - mean ** 2, 0.0) * count[:, None] / np.maximum(count[:, None] - 1, 1)
        se = np.sqrt(var / count[:, None])
    return {"count": count, "mean": mean, "se": se}


def _bin_deviations(stats: dict, min_count: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(m_bc - m_c, se_bc) over bins with at least ``min_count`` observations, m_c the
    inverse-variance weighted mean over those bins; None when fewer than 2 bins qualify."""
    ok = stats["count"] >= min_count
    if ok.sum() < 2:
        return None
    m, se = stats["mean"][ok], np.maximum(stats["se"][ok], 1e-9)
    w = 1.0 / se ** 2
    return m - (w * m).sum(0) / w.sum(0), se


def structure_score(stats: dict, min_count: int) -> float:
    """sqrt(mean over bins and channels of ((m_bc - m_c)/se_bc)^2), m_c the weighted mean (see module)."""
    dev = _bin_deviations(stats, min_count)
    return 0.0 if dev is None else float(np.sqrt(np.mean((dev[0] / dev[1]) ** 2)))


def structure_amplitude(stats: dict, min_count: int) -> float:
    """sqrt(mean over bins and channels of (m_bc - m_c)^2), m_c the inverse-variance weighted mean."""
    dev = _bin_deviations(stats, min_count)
    return 0.0 if dev is None else float(np.sqrt(np.mean(dev[0] ** 2)))


def analyse(meas: Observations, predicted: np.ndarray, residual: np.ndarray,
            config: ResidualConfig = ResidualConfig()) -> dict:
    """{axis: {"edges" or "grid", "count", "mean", "se", "score", "amplitude"}} (JSON-ready lists)."""
    out = {}
    nu, nv = config.grid_uv
    iu = np.clip((meas.pixel_uv[:, 0] * nu).astype(int), 0, nu - 1)
    iv = np.clip((meas.pixel_uv[:, 1] * nv).astype(int), 0, nv - 1)
    stats = _bin_stats(iv * nu + iu, nu * nv, residual)
    out["image_position"] = {"grid_uv": [nu, nv], **_jsonable(stats), "score": structure_score(stats, config.min_count),
                             "amplitude": structure_amplitude(stats, config.min_count)}
    for axis, values in axis_values(meas, predicted).items():
        if axis == "frame":
            edges = np.arange(int(values.max()) + 2) - 0.5
        else:
            edges = np.unique(np.quantile(values, np.linspace(0, 1, config.n_bins + 1)))
        if len(edges) < 3:
            continue
        index = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
        stats = _bin_stats(index, len(edges) - 1, residual)
        out[axis] = {"edges": edges.tolist(), **_jsonable(stats), "score": structure_score(stats, config.min_count),
                     "amplitude": structure_amplitude(stats, config.min_count)}
    return out


def _jsonable(stats: dict) -> dict:
    return {k: np.where(np.isfinite(v), v, np.nan).round(6).tolist() for k, v in stats.items()}


def scores(analysis: dict) -> dict[str, float]:
    return {axis: round(a["score"], 3) for axis, a in analysis.items()}


def amplitudes(analysis: dict) -> dict[str, float]:
    return {axis: a["amplitude"] for axis, a in analysis.items()}


AXIS_LABELS = {"range": "range (m)", "intensity": "predicted intensity (linear)", "height": "world height z (m)",
               "spatial_frequency": "log10 gradient energy", "frame": "frame index",
               "light_distance": "distance to nearest light (m)",
               "incidence_angle": "incidence angle at the surface (degrees)"}


def plot_residuals(analysis: dict, out_dir: Path, title: str) -> list[Path]:
    """One PNG per axis: bin means with standard errors per channel; image position as R, G, B heat maps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for axis, a in analysis.items():
        path = out_dir / f"residual_{axis}.png"
        mean = np.array(a["mean"], dtype=float)
        if axis == "image_position":
            nu, nv = a["grid_uv"]
            lim = np.nanmax(np.abs(mean)) if np.isfinite(mean).any() else 1.0
            fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
            for c, (ax, name) in enumerate(zip(axes, "RGB", strict=True)):
                im = ax.imshow(mean[:, c].reshape(nv, nu), cmap="coolwarm", vmin=-lim, vmax=lim,
                               extent=(0, 1, 1, 0))
                ax.set_title(f"{name} mean residual")
                ax.set_xlabel("u (image fraction)")
                ax.set_ylabel("v")
            fig.colorbar(im, ax=axes, shrink=0.8, label="observed - predicted (linear)")
        else:
            edges = np.array(a["edges"])
            centres = 0.5 * (edges[:-1] + edges[1:])
            se = np.array(a["se"], dtype=float)
            fig, ax = plt.subplots(figsize=(6, 3.6))
            for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
                ax.errorbar(centres, mean[:, c], yerr=se[:, c], color=colour, marker="o", ms=3, capsize=2)
            ax.axhline(0.0, color="k", lw=0.8)
            ax.set_xlabel(AXIS_LABELS.get(axis, axis))
            ax.set_ylabel("mean residual (linear)")
        fig.suptitle(f"{title}: {axis} (structure score {a['score']:.2f})")
        fig.savefig(path, dpi=90, bbox_inches="tight")
        plt.close(fig)
        paths.append(path)
    return paths


def write_residual_ply(meas: Observations, residual: np.ndarray, path: Path) -> None:
    """The points coloured by their mean residual (grey level, mean over views and channels) on a
    diverging map: blue = observed darker than predicted, red = brighter; limits +-98th percentile."""
    import matplotlib
    import trimesh

    per_point = np.bincount(meas.point, residual.mean(1), minlength=meas.n_points) / \
        np.maximum(np.bincount(meas.point, minlength=meas.n_points), 1)
    lim = max(float(np.quantile(np.abs(per_point), 0.98)), 1e-9)
    rgba = matplotlib.colormaps["coolwarm"](0.5 + 0.5 * np.clip(per_point / lim, -1, 1))
    trimesh.PointCloud(meas.points_world, colors=(rgba * 255).astype(np.uint8)).export(path)
