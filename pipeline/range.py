"""The range stage: each pixel's range along its ray, for the water's fine grid and the corrections.

It reads the frames' poses (sfm) and their dense range and fused mesh (dense: camera z, turned into ray length) and
writes into the stage's folder:

    range/<stem>.png        each pixel's range (:func:`correction_range`), 16-bit millimetres (0: none)

Range per pixel (:func:`correction_range`): the dense stage's depth map where it agrees with the dense
stage's fused mesh rendered into the view (open3d ray casting from the SfM pose, :func:`mesh_range`) within
``agreement``; the mesh's range where the depth map has none or disagrees (the mesh fuses every view, so a depth
map's outliers at relief edges do not survive it); a pixel with neither has none (0 in the map). The dense stage
writes camera z, not these.

Who reads them: the water stage measures its estimate on the dense range alone, and the fine grid after it (which
serves the corrections) on the dense range filled with these maps where it has none (:class:`MeshFilledFrames`), so
that its views reach the image's edges, which the correction corrects; the correct stage inverts the water with them
(the physics correction) and the RGB-D restorer takes them.

Normals: a stack that reads surface normals (a light rig) takes those of the dense range smoothed by
``normal_smooth_px`` (:func:`watergan.formation.inverse.normals_from_range`), for the estimate (at each sample's source
pixel) as for the correction (:func:`correction_normals`: the range map's only where the dense range has none). The
stage records the smoothing; the water stage and the correction take it from its result.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from eval.observations import DenseMeasureConfig, WaterFrame
from eval.tracks import Tracks
from watergan.errors import UserInputError
from watergan.formation.inverse import clean_range
from watergan.io import depth_within, read_depth, read_millimetres, write_depth_png, z_to_range

from .workspace import Workspace


@dataclass(frozen=True)
class RangeConfig:
    """The range maps: each pixel's range from the dense range and the fused mesh."""

    agreement: float = 0.01
    """A pixel keeps its dense range where the fused mesh agrees within this fraction; else it takes the mesh's."""
    normal_smooth_px: float = DenseMeasureConfig.normal_smooth_px
    """Smoothing (pixels) of the dense range before its surface normals are taken, for a water that reads them (a
    light rig): the water's estimate and the correction take the same."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bars."""


@dataclass
class RangeResult:
    range_dir: str
    """Workspace-relative folder of each frame's range map (<stem>.png, 16-bit millimetres, 0: none)."""
    mesh_fraction: float
    """Share of the pixels whose range came from the fused mesh."""
    range_missing: float
    """Share of the pixels with no range at all."""
    normal_smooth_px: float
    """The smoothing of the dense range's normals (the water's estimate and the correction take it)."""
    n_frames: int
    """Range maps written (one per frame of the sfm stage's image list)."""
    seconds: float
    """Wall time of the stage."""


#: Frames :class:`LazyFrames` keeps once made (about 5 MB each at 640x480): a survey of up to this many frames is
#: read once however many passes the measurement makes; a longer one is read again on each pass, in bounded memory.
CACHED_FRAMES = 64


class LazyFrames(Sequence[WaterFrame]):
    """``n`` frames made by ``make(k)`` when indexed, the last :data:`CACHED_FRAMES` kept, so that memory does not
    grow with the survey's length."""

    def __init__(self, n: int, make):
        self._n = n
        self._read = functools.lru_cache(maxsize=CACHED_FRAMES)(make)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self._n))]
        if not -self._n <= k < self._n:
            raise IndexError(k)
        return self._read(k % self._n)


class SurveyFrames(LazyFrames):
    """The survey's frames as :func:`water_frame` reads them, read when indexed (:class:`LazyFrames`)."""

    def __init__(self, tracks: Tracks, images: Path, depth_dir: Path | None):
        super().__init__(len(tracks.image_names), lambda k: water_frame(tracks, k, images, depth_dir))


def water_frames(tracks: Tracks, images: Path, depth_dir: Path | None) -> SurveyFrames:
    """Raw linear frames, their dense range (ray length; NaN = none) and SfM pose (None: not registered), read on
    demand (:class:`SurveyFrames`)."""
    return SurveyFrames(tracks, images, depth_dir)


def water_frame(tracks: Tracks, k: int, images: Path, depth_dir: Path | None) -> WaterFrame:
    """The k-th frame of :func:`water_frames`."""
    from watergan.data import read_image

    K = np.asarray(tracks.K, float)
    name = str(tracks.image_names[k])
    image = read_image(images / name).astype(np.float32)
    path = depth_dir / f"{Path(name).stem}.png" if depth_dir is not None else None
    if path is not None and path.is_file():
        range_m = z_to_range(read_depth(path), K).astype(np.float32)
    else:
        range_m = np.full(image.shape[:2], np.nan, np.float32)
    return WaterFrame(name=name, image=image, range_m=range_m,
                      world_from_cam=tracks.world_from_cam[k] if tracks.registered[k] else None)


class MeshFilledFrames(LazyFrames):
    """The frames the water's fine grid is measured on: each frame's dense range, and its range map's (the fused
    mesh's range, :func:`correction_range`) where the dense range has none; with ``smooth_px``, normals as the
    correction takes them (:func:`correction_normals`; None: none of their own, for a stack that reads none). A stereo
    pair's dense range stops short of the image's edges (the left edge the right camera does not see, a margin on the
    right) where the correction still corrects (from the mesh): without the mesh the table has no views there, and the
    grid is extrapolated into them. Made when indexed (:class:`LazyFrames`); frames without a pose, without a range
    map in ``range_dir`` (None: none), or whose range map fills nothing, as they are."""

    def __init__(self, frames: Sequence[WaterFrame], K: np.ndarray, range_dir: Path | None, smooth_px: float | None):
        self._frames, self._K, self._ranges, self._smooth = frames, np.asarray(K, float), range_dir, smooth_px
        super().__init__(len(frames), self._fill)

    def _fill(self, k: int) -> WaterFrame:
        frame = self._frames[k]
        path = self._ranges / f"{Path(frame.name).stem}.png" if self._ranges is not None else None
        missing = np.isnan(clean_range(frame.range_m))
        if path is None or frame.world_from_cam is None or not missing.any() or not path.is_file():
            return frame
        mapped = read_millimetres(path) / 1000.0  # metres, 0 = none
        filled = missing & (mapped > 0)
        if not filled.any():
            return frame
        range_m = np.where(filled, mapped, frame.range_m).astype(np.float32)
        if self._smooth is None:
            return replace(frame, range_m=range_m)
        return replace(frame, range_m=range_m, normals_cam=correction_normals(frame, range_m, self._K, self._smooth))


def mesh_range(mesh_ply: Path, frame: WaterFrame, K: np.ndarray, scene=None, where: np.ndarray | None = None):
    """(range (H,W) metres along each pixel's ray to the fused mesh, NaN where it misses and outside ``where`` (an
    (H,W) mask of the pixels to cast; None: all); the ray-casting scene for the next frame)."""
    import open3d as o3d

    if scene is None:
        mesh = o3d.io.read_triangle_mesh(str(mesh_ply))
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    h, w = frame.range_m.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) if where is None else np.nonzero(where)
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones(np.shape(xs))], -1)
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True) @ frame.world_from_cam[:3, :3].T
    origin = np.broadcast_to(frame.world_from_cam[:3, 3], rays.shape)
    hits = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, rays], -1).astype(np.float32)))
    t = hits["t_hit"].numpy().astype(np.float64)
    t = np.where(np.isfinite(t), t, np.nan)
    if where is None:
        return t, scene
    out = np.full((h, w), np.nan)
    out[where] = t
    return out, scene


def correction_range(frame: WaterFrame, K: np.ndarray, mesh_ply: Path | None, agreement: float, scene=None):
    """(range (H,W) metres, NaN = none; the mask of pixels that took the mesh's range; the ray-casting scene):
    the frame's dense range where the fused mesh misses or agrees within ``agreement`` (relative), else the
    mesh's range (frames without a pose keep their dense range)."""
    r = np.asarray(frame.range_m, np.float64)
    if mesh_ply is None or frame.world_from_cam is None:
        return r, np.zeros(r.shape, bool), scene
    meshed, scene = mesh_range(mesh_ply, frame, K, scene)
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = np.isfinite(r) & (~np.isfinite(meshed) | (np.abs(r / meshed - 1.0) <= agreement))
    from_mesh = ~keep & np.isfinite(meshed)
    return np.where(keep, r, meshed), from_mesh, scene


def correction_normals(frame: WaterFrame, range_m: np.ndarray, K: np.ndarray, smooth_px: float) -> np.ndarray:
    """(H,W,3) camera-frame surface normals for the correction, as the estimate takes them: the frame's own
    (``frame.normals_cam``) when it has them, else those of its dense range smoothed by ``smooth_px``
    (:func:`watergan.formation.inverse.normals_from_range`); and those of the correction's range ``range_m``
    (:func:`correction_range`) where the dense range has none. Not the correction's range throughout: where it
    switches between the dense range and the mesh's, a step of a percent or two tilts the smoothed normals along the
    seam (measurements: benchmarks/RESULTS/3d.md)."""
    from eval.observations import frame_normals
    from watergan.formation.inverse import normals_from_range

    normals = frame_normals(frame, K, smooth_px)
    missing = ~np.isfinite(normals).all(axis=-1)
    if missing.any():
        normals[missing] = normals_from_range(range_m, K, smooth_px)[missing]
    return normals


def write_range_maps(out: Path, frames: Sequence[WaterFrame], K: np.ndarray, mesh_ply: Path | None, agreement: float,
                     progress: bool) -> tuple[float, float]:
    """Each frame's :func:`correction_range` as ``out/<stem>.png`` (16-bit millimetres); returns (share of the
    pixels ranged from the mesh, share with no range)."""
    from tqdm import tqdm

    from_mesh, missing, scene = [], [], None
    for f in tqdm(frames, desc="range maps", unit="frame", disable=not progress):
        r, meshed, scene = correction_range(f, K, mesh_ply, agreement, scene)
        r, _ = depth_within(r)  # a long mesh ray or a corner's range beyond what the millimetre PNG holds: no range
        from_mesh.append(float(np.mean(meshed)))
        missing.append(float(np.mean(~(np.isfinite(r) & (r > 0)))))
        write_depth_png(out / f"{Path(f.name).stem}.png", r)
    return (float(np.mean(from_mesh)), float(np.mean(missing))) if frames else (0.0, 1.0)


def require_dense(ws: Workspace, what: str):
    """The dense stage's result, which ``what`` needs; else an error saying how to make it."""
    dense = ws.result("dense")
    if dense is None:
        raise UserInputError(f"{what} need each pixel's dense range: run the dense stage first (`watergan dense "
                             "--workspace WS`), with stereo frames (right/) or enough overlap for MVS")
    return dense


def run_range(ws: Workspace, cfg: RangeConfig) -> RangeResult:
    """Workspace stage (see the module docstring): a range map per frame of the sfm stage's image list."""
    began = time.perf_counter()
    sfm = ws.require("sfm", "the range maps")
    dense = require_dense(ws, "the range maps")
    tracks = Tracks.load(ws.path(sfm.tracks))
    K = np.asarray(tracks.K, float)
    frames = water_frames(tracks, ws.stage_dir("survey") / "images", ws.path(dense.depth_dir))
    mesh_ply = ws.path(dense.mesh_ply) if dense.mesh_ply else None
    out = ws.stage_dir("range") / "range"
    mesh_share, missing = write_range_maps(out, frames, K, mesh_ply if mesh_ply is not None and mesh_ply.is_file()
                                           else None, cfg.agreement, cfg.progress)
    return RangeResult(range_dir=ws.relative(out), mesh_fraction=mesh_share, range_missing=missing,
                       normal_smooth_px=cfg.normal_smooth_px, n_frames=len(frames),
                       seconds=time.perf_counter() - began)
