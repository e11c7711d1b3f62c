"""Each pixel's range for a correction, and the water's gain where that range is a guess.

A correction (the water's physics inverse, or a restorer that starts from it) needs a range at every pixel of a frame.
A range map has holes: small ones are interpolated from the measured range around them (:func:`fill_range`, a membrane
over the hole, :func:`harmonic_fill`), larger ones on the camera's side of their edge the plane through the frame's
measured points (the floor nearer than where the range map ends, :func:`frame_plane`), the others (open water, a far
wall stereo did not match) the survey's far range (:func:`survey_far_range_m`), where the water's gain is held at a
ceiling (:func:`cap_gain`). A frame without a range map takes a flat seafloor's range at its altitude, times the site
depth net's factor where one is given (:func:`monocular_range`). Each pixel's source of range is a :class:`RangeFrom`.
Both corrections (the physics inverse and the restorer) take their mode from :class:`CorrectMode` and name their
corrected frames by :func:`corrected_name`.
"""

from __future__ import annotations

import math
from enum import IntEnum, StrEnum
from pathlib import Path

import numpy as np
import torch

from watergan.data import DataError
from watergan.formation.inverse import camera_unit_rays, flat_floor_depth, flat_floor_range
from watergan.io import is_jpeg, read_millimetres
from watergan.nets.site_depth import SiteDepthNet


class CorrectMode(StrEnum):
    """How a correction gets each pixel's range: rgb-d, from the range maps; monocular, a flat seafloor's at the
    frame's altitude (:func:`monocular_range`); auto, rgb-d where there are range maps."""

    auto = "auto"
    rgbd = "rgb-d"
    monocular = "monocular"


def corrected_name(name: str, image_format: str) -> str:
    """The corrected frame's file name for input ``name``: the same name (a JPEG's stem with .png), or its stem with
    the format's suffix ("png", "tiff" or "jpeg"; anything else: the input's)."""
    own = ".png" if is_jpeg(name) else Path(name).suffix
    suffix = {"png": ".png", "tiff": ".tif", "jpeg": ".jpg"}.get(str(image_format), own)
    return f"{Path(name).stem}{suffix}"


class RangeFrom(IntEnum):
    """Where a corrected pixel's range came from: the value of each pixel of ``physics/range_from/<stem>.png``."""

    measured = 0
    """The frame's range map (the dense range, the fused mesh's where it had none)."""
    neighbours = 1
    """Inpainted from the measured range around a small hole (:func:`fill_range`)."""
    far = 2
    """The survey's far range: a large hole (open water, a far wall stereo did not match)."""
    not_scene = 3
    """Outside the scene mask: not corrected, the raw pixel passed through."""
    plane = 4
    """A large hole on the camera's side of its edge, whose ray meets the plane through the frame's measured points
    (the floor nearer than where the range map ends, :func:`fill_range`)."""


FILL_PX = 24.0
"""A hole lying everywhere within this many pixels of measured range is interpolated (:func:`fill_range`)."""
FAR_RANGE_PCT = 95.0
"""The survey's far range: this percentile of its measured ranges (:func:`survey_far_range_m`)."""
FAR_MAX_GAIN = 10.0
"""The largest gain a pixel at the far range is corrected with (:func:`cap_gain`)."""
PLANE_TOLERANCE = 0.1
"""A measured point lies on the frame's plane when its distance to it is at most this share of its range."""
PLANE_MIN_SHARE = 0.5
"""The frame's plane ranges large holes only when at least this share of its measured points lie on it."""
PLANE_SAMPLE_PX = 4
"""The plane is fitted to every this-many-th row and column of the measured pixels."""


def frame_plane(range_m: np.ndarray, measured: np.ndarray, K: np.ndarray, rounds: int = 3
                ) -> tuple[np.ndarray, float] | None:
    """The plane n . X = d (n unit, d > 0: the camera on its side n points away from) through the camera-frame points
    X = r u of the ``measured`` pixels ((H,W) bool; ``range_m`` (H,W) metres along the unit ray u of ``K``),
    every :data:`PLANE_SAMPLE_PX`-th row and column: a least-squares plane (the points' smallest principal axis),
    refitted ``rounds`` times to the points within :data:`PLANE_TOLERANCE` of their range of it. None when fewer than
    :data:`PLANE_MIN_SHARE` of the points lie on the last fit (a scene that is no plane) or there are fewer than 3."""
    sub = np.zeros_like(measured)
    sub[::PLANE_SAMPLE_PX, ::PLANE_SAMPLE_PX] = True
    ys, xs = np.nonzero(measured & sub)
    if len(ys) < 3:
        return None
    r = range_m[ys, xs].astype(np.float64)
    points = camera_unit_rays(K, *range_m.shape)[ys, xs] * r[:, None]
    keep = np.ones(len(r), bool)
    for _ in range(rounds + 1):
        if keep.sum() < 3:
            return None
        centre = points[keep].mean(axis=0)
        normal = np.linalg.svd(points[keep] - centre, full_matrices=False)[2][-1]
        d = float(normal @ centre)
        if d < 0:
            normal, d = -normal, -d
        keep = np.abs(points @ normal - d) <= PLANE_TOLERANCE * r
    if keep.mean() < PLANE_MIN_SHARE or d <= 0:
        return None
    return normal, d


def harmonic_fill(values: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """The values (H,W) at the ``unknown`` pixels ((H,W) bool) that solve the discrete Laplace equation (each the mean
    of its 4 neighbours) with every other pixel's value held: a membrane over each hole, exact for a plane's values
    (a ramp). Neighbours beyond the image's edge are left out. Returns (H,W) float64 with the filled values (the
    rest as given); a sparse solve over the unknown pixels alone."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    h, w = values.shape
    out = np.asarray(values, np.float64).copy()
    ys, xs = np.nonzero(unknown)
    n = len(ys)
    if n == 0:
        return out
    index = np.full((h, w), -1, np.int64)
    index[ys, xs] = np.arange(n)
    rows, cols, b, degree = [], [], np.zeros(n), np.zeros(n)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        ny, nx = ys + dy, xs + dx
        inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
        degree += inside
        at, ny, nx = np.flatnonzero(inside), ny[inside], nx[inside]
        other = index[ny, nx]
        free = other >= 0
        rows.append(at[free])
        cols.append(other[free])
        np.add.at(b, at[~free], out[ny[~free], nx[~free]])
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    data = np.concatenate([-np.ones(sum(len(r) for r in rows[:-1])), degree])
    matrix = coo_matrix((data, (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsc()
    out[ys, xs] = spsolve(matrix, b)
    return out


def fill_range(range_m: np.ndarray, far_range_m: float, fill_px: float = FILL_PX,
               scene: np.ndarray | None = None, K: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel's range for the correction, (H,W) float32 metres, and where it came from, (H,W) uint8 of
    :class:`RangeFrom`. A scene pixel with a measured range (finite, > 0) keeps it. A hole (a connected region of scene
    pixels without range, 8-connected) that lies everywhere within ``fill_px`` pixels of measured range takes the
    range interpolated from around it (:func:`harmonic_fill`; a neighbour without range, outside the scene, is given
    its nearest measured pixel's range first). In a larger hole, with the intrinsics ``K`` (3x3) given, a pixel whose
    ray meets the plane through the frame's measured points (:func:`frame_plane`) in front of the camera nearer than
    ``far_range_m`` takes that distance when the hole lies on the camera's side of its edge (its median range on the
    plane below the median measured range along its edge: the floor nearer than where the range map ends, as in a
    forward camera's bottom rows; open water past a drop-off or above a floor lies beyond its edge). Every other pixel
    of a larger hole (open water, a far wall), and every hole of a frame without any measured range, takes
    ``far_range_m``. Pixels
    outside ``scene`` ((H,W)
    bool, True = scene; None: every pixel) are marked not the scene and keep their range (``far_range_m`` where they
    have none). ``range_m``: (H,W) metres, NaN, inf or <= 0 = none. A hole that needs ``far_range_m`` when it is not
    finite is a ValueError."""
    import cv2

    r = np.asarray(range_m, np.float32)
    if scene is not None and scene.shape != r.shape:
        raise DataError(f"the scene mask is {scene.shape[1]}x{scene.shape[0]}, the range map {r.shape[1]}x{r.shape[0]}")
    in_scene = np.ones(r.shape, bool) if scene is None else scene
    with np.errstate(invalid="ignore"):
        ranged = np.isfinite(r) & (r > 0)
    measured = ranged & in_scene
    source = np.where(in_scene, np.uint8(RangeFrom.far), np.uint8(RangeFrom.not_scene))
    source[measured] = RangeFrom.measured
    out = np.where(ranged, r, np.float32(far_range_m)).astype(np.float32)
    holes = in_scene & ~measured
    if holes.any() and measured.any():
        dist, nearest = cv2.distanceTransformWithLabels((~measured).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5,
                                                        labelType=cv2.DIST_LABEL_PIXEL)
        count, label = cv2.connectedComponents(holes.astype(np.uint8), connectivity=8)
        large = np.zeros(count, bool)
        large[label[holes & (dist > fill_px)]] = True
        small = holes & ~large[label]
        if small.any():
            values = np.zeros(int(nearest.max()) + 1, np.float32)  # each measured pixel's label -> its range
            values[nearest[measured]] = r[measured]
            out[small] = harmonic_fill(values[nearest], small)[small]
            source[small] = RangeFrom.neighbours
        plane = frame_plane(r, measured, K) if K is not None and (source == RangeFrom.far).any() else None
        if plane is not None:
            _range_near_holes_on_plane(out, source, label, measured, r, K, plane, far_range_m)
    if not np.isfinite(far_range_m) and (source == RangeFrom.far).any():
        raise ValueError("pixels without a measured range near them need the survey's far range, and it is not known")
    return out, source


def _range_near_holes_on_plane(out: np.ndarray, source: np.ndarray, label: np.ndarray, measured: np.ndarray,
                               r: np.ndarray, K: np.ndarray, plane: tuple[np.ndarray, float],
                               far_range_m: float) -> None:
    """In place: each large hole (a component of ``label`` whose pixels ``source`` marks far) that lies on the
    camera's side of its edge, its median range on ``plane`` below the median measured range on its edge (the pixels
    of ``measured`` next to it), takes the plane's range at each pixel nearer than ``far_range_m``."""
    import cv2

    for component in np.unique(label[source == RangeFrom.far]):
        hole = label == component
        edge = cv2.dilate(hole.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & measured
        if not edge.any():
            continue
        ys, xs = np.nonzero(hole)
        facing = camera_unit_rays(K, *hole.shape)[ys, xs] @ plane[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(facing > 0, plane[1] / facing, np.inf)
        if not np.median(t) < np.median(r[edge]):
            continue  # the plane puts the hole beyond its edge: open water past a drop-off, a far wall
        meets = t <= far_range_m
        out[ys[meets], xs[meets]] = t[meets]
        source[ys[meets], xs[meets]] = RangeFrom.plane


def survey_far_range_m(range_maps: list[Path], pct: float = FAR_RANGE_PCT, scene: np.ndarray | None = None) -> float:
    """The survey's far range: the ``pct`` percentile (to the millimetre) of the measured ranges of every range map's
    scene pixels (16-bit millimetres, 0 = none; ``scene``: (H,W) bool, None: every pixel), counted in a histogram of
    millimetres so that memory does not grow with the survey. No measured range in any of them is a DataError."""
    counts = np.zeros(65536, np.int64)
    for path in range_maps:
        mm = read_millimetres(path)
        if scene is not None and scene.shape != mm.shape:
            raise DataError(f"the scene mask is {scene.shape[1]}x{scene.shape[0]}, the range map {path} "
                            f"{mm.shape[1]}x{mm.shape[0]}")
        counts += np.bincount((mm if scene is None else mm[scene]).ravel(), minlength=65536)
    counts[0] = 0
    total = int(counts.sum())
    if total == 0:
        raise DataError(f"none of the {len(range_maps)} range maps (e.g. {range_maps[0] if range_maps else '-'}) "
                        f"holds a range: rerun the dense and water stages, or correct in monocular mode")
    return int(np.searchsorted(np.cumsum(counts), pct / 100.0 * total)) / 1000.0


def cap_gain(fields: torch.Tensor, capped: torch.Tensor, max_gain: float) -> torch.Tensor:
    """The fields (...,6,H,W) (log gain g, offset o per channel) of J = exp(g) I + o = exp(g) (I - C), C = -o exp(-g),
    with the gain held at ``max_gain`` where ``capped`` ((...,1,H,W) or (H,W) bool): J = min(exp(g), G) (I - C), so
    g' = min(g, ln G) and o' = o exp(g' - g). The veil C is still removed in full; only its remainder is amplified
    less. A pixel at the far range in open water (pure backscatter, I ~ C) would otherwise have its noise and any
    error of the veil multiplied by exp(eta r) without bound."""
    g, o = fields[..., :3, :, :], fields[..., 3:, :, :]
    held = torch.where(capped, g.clamp_max(math.log(max_gain)), g)
    return torch.cat([held, o * torch.exp(held - g)], dim=-3)


def monocular_range(image: np.ndarray, altitude_m: float, K: np.ndarray, down_cam: np.ndarray | None = None,
                    site: SiteDepthNet | None = None) -> np.ndarray:
    """(H,W) float32 range (metres) of a frame without a range map: a flat seafloor's at the navigation's
    ``altitude_m`` below the camera (:func:`watergan.formation.inverse.flat_floor_range`; ``down_cam``: "down" in the
    camera frame, None: a nadir camera), times the site depth net's factor exp(D) with ``site``
    (:meth:`watergan.nets.site_depth.SiteDepthNet.factor`, which reads ``image``: (H,W,3), the stored values 0..1).
    ``K``: the frame's intrinsics at its size."""
    h, w = image.shape[:2]
    range_m = flat_floor_range(altitude_m, K, h, w, down_cam)
    if site is not None:
        range_m = range_m * site.factor(image, flat_floor_depth(altitude_m, K, h, w, down_cam, range_m))
    return range_m.astype(np.float32)

