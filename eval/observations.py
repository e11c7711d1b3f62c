"""The one measurement table of a survey: every view of a surface point, and the board's patches.

One row per *view* (a surface point seen in a frame): its linear colour, range, camera depth, image position,
camera-frame point and normal, point and frame; per *point* its world position and normal; optionally per view the
patch's gradient energy, per point the water depth from navigation, and per frame the image names; and *board
rows* (a colour board's patch seen in a frame: its mean colour and its known albedo). The water estimate
(:mod:`eval.water`) and the diagnosis (:mod:`eval.diagnose`) fit the same table with the same fitter
(:mod:`eval.fit`).

Two builders fill it:

- :func:`measure_frames` (this module): from the frames' images, poses and dense range maps (the water stage);
- :func:`eval.diagnose_measure.measure_survey`: from a survey folder's SfM tracks or the simulator's truth
  (the diagnosis of a survey folder), which also adds the survey's annotations to a saved table
  (:func:`eval.diagnose_measure.annotate`).

Dense correspondences (:func:`measure_frames`): ``samples_per_frame`` pixels of every frame with range (fewer on a
survey long enough to pass ``max_points`` in all; a ``dark_fraction`` of them among the frame's darkest 5 %: the
dark-pixel prior) are lifted to 3D with the range and the pose and projected into every other frame; a projection is
a view of the same surface point when it lands inside the image and that frame's own range agrees with the point's
distance within ``range_tolerance`` (occlusion test). Colours are read (bilinear) from the image blurred by a fixed
footprint on the surface (``footprint_m``): a fixed blur in pixels averages more texture in a far view than in a
near one, which biases the ratio of near to far views and with it the attenuation. Views with a channel at or above
0.98 (clipped) or at or below 0.002 are dropped, and points left with fewer than two views. SfM tracks (optional)
add their own observations at the feature positions. The board (optional, :class:`eval.colour.Board`) adds per frame
and visible patch the mean colour inside the shrunk quad, with its known linear colour and the median range there.

Bad input (too few frames with a pose and range, too little range, too few points seen at different ranges) raises
:class:`WaterInputError`, saying what to give.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from watergan.errors import UserInputError
from watergan.formation.inverse import clean_range, normals_from_range, rays_cam

from .sampling import FootprintPyramid


class WaterInputError(UserInputError):
    """The survey does not hold what the water estimate needs; the message says what to give."""


@dataclass(frozen=True)
class WaterFrame:
    """One survey frame as the estimator sees it.

    name:           the image's file name (the board's quads are keyed by it).
    image:          (H,W,3) raw linear RGB, 0..1 (sRGB-decoded).
    range_m:        (H,W) ray length from the camera centre to the scene, metres; NaN or <= 0 = no value.
                    (The dense stage writes camera z in millimetres; r = z |K^-1 (x, y, 1)|.)
    world_from_cam: (4,4) camera-to-world pose (OpenCV camera axes), same metric frame for every frame;
                    None: the frame has no pose (it takes no part).
    normals_cam:    optional (H,W,3) unit surface normals in the camera frame (e.g. of a fused mesh), read by
                    effects that need them (``artificial_light``); None: :func:`normals_from_range` of
                    ``range_m``.
    """

    name: str
    image: np.ndarray
    range_m: np.ndarray
    world_from_cam: np.ndarray | None
    normals_cam: np.ndarray | None = None


@dataclass(frozen=True)
class SparseTracks:
    """SfM points and their observations. ``obs_frame`` indexes the ``frames`` list given to estimate_water
    (map SfM image indices to it first); xy in pixels, OpenCV centres."""

    xyz: np.ndarray        # (P,3) world, same frame as the poses
    obs_point: np.ndarray  # (M,)
    obs_frame: np.ndarray  # (M,)
    obs_xy: np.ndarray     # (M,2)



#: Levels of the blur pyramid colours are read through (:class:`eval.sampling.FootprintPyramid`).
PYRAMID_LEVELS = 6


@dataclass(frozen=True)
class DenseMeasureConfig:
    """How the table is measured from the frames' dense range (:func:`measure_frames`)."""

    samples_per_frame: int = 300
    """Pixels lifted to 3D per frame (dense correspondences)."""
    max_points: int = 20000
    """Pixels lifted to 3D over the whole survey at most: a survey with more usable frames than this over the samples
    per frame lifts this over its frame count per frame (at least one), so that the table, and the fit and the
    diagnosis that read it, stay bounded as the survey grows while every frame still takes part."""
    dark_fraction: float = 0.25
    """Fraction of those samples drawn among the frame's darkest 5 % of pixels (the dark-pixel prior)."""
    blur_px: float = 1.0
    """Smallest Gaussian blur (sigma, pixels) of the images colours are read from (0: no blur)."""
    footprint_m: float = 0.015
    """Sigma on the surface (metres) of the blur colours are read through; 0: blur_px everywhere.
    That is fx x this / depth pixels, clamped to the blur pyramid (the blur in pixels x 1.5^0..5)."""
    margin_px: int = 6
    """Projections closer than this to the image border are not used."""
    range_tolerance: float = 0.02
    """Occlusion test: |frame's range - point distance| <= this x the distance."""
    max_views: int = 12
    """Views per point at most (the nearest frames in index order are kept first)."""
    board_inset: float = 0.3
    """Board patch quads are shrunk towards their centre by this fraction before averaging."""
    normal_smooth_px: float = 24.0
    """Gaussian sigma (pixels) by which a range map is smoothed before surface normals are taken from it."""
    min_frames: int = 4
    """Frames with a pose and range needed."""
    min_range_coverage: float = 0.2
    """Mean fraction of pixels with range needed."""
    min_points: int = 200
    """Points seen in two views whose ranges differ by >= 0.1 m needed."""
    seed: int = 0
    """Seed of the pixel sampling."""


def _empty(*shape: int, dtype=np.float64):
    return field(default_factory=lambda: np.zeros(shape, dtype))


@dataclass
class Observations:
    """The measurement table (see the module docstring). Views are sorted by point, then frame.

    Per view (N rows): colour (N,3) linear; range_m, depth_m (N,) metres (camera z); pixel_uv (N,2)
    ((x + 0.5)/W, (y + 0.5)/H); points_cam (N,3) metres; point, frame (N,) indices; normals_cam (N,3) unit normal in
    the camera frame (None: not measured); grad_energy (N,) variance of the Laplacian of the grey linear image in a
    ``patch_px`` patch (None: not measured).
    Per point (P rows): points_world, normals_world (P,3) (None: not measured); nav_water_depth_m (P,) depth below
    the surface from navigation (None: ``site_depth_m`` - z, see :attr:`water_depth_m`).
    Board rows (B): board_colour, board_albedo (B,3) observed and known linear colour; board_range_m,
    board_depth_m, board_pixel_uv, board_points_cam, board_normals_cam as per view; board_frame, board_patch (B,).
    Scalars: n_points, image_wh, n_frames (frames of the survey: sizes per-frame parameters), frames (image names by
    frame index, when known), lights (survey.json's), site_depth_m, source (what measured it), patch_px,
    clipped_obs (views dropped for a clipped pixel)."""

    colour: np.ndarray
    range_m: np.ndarray
    depth_m: np.ndarray
    pixel_uv: np.ndarray
    points_cam: np.ndarray
    point: np.ndarray
    frame: np.ndarray
    n_points: int
    image_wh: tuple[int, int]
    n_frames: int = 0
    normals_cam: np.ndarray | None = None
    grad_energy: np.ndarray | None = None
    points_world: np.ndarray | None = None
    normals_world: np.ndarray | None = None
    nav_water_depth_m: np.ndarray | None = None
    board_colour: np.ndarray = _empty(0, 3)
    board_albedo: np.ndarray = _empty(0, 3)
    board_range_m: np.ndarray = _empty(0)
    board_depth_m: np.ndarray = _empty(0)
    board_pixel_uv: np.ndarray = _empty(0, 2)
    board_points_cam: np.ndarray = _empty(0, 3)
    board_normals_cam: np.ndarray | None = None
    board_frame: np.ndarray = _empty(0, dtype=np.int64)
    board_patch: np.ndarray = _empty(0, dtype=np.int64)
    frames: list[str] = field(default_factory=list)
    lights: list[dict] = field(default_factory=list)
    site_depth_m: float = 0.0
    source: str = ""
    patch_px: int = 0
    clipped_obs: int = 0

    @property
    def n_obs(self) -> int:
        return len(self.point)

    @property
    def px(self) -> np.ndarray:
        """(N,2) pixel coordinates (x, y), OpenCV centres."""
        return self.pixel_uv * np.asarray(self.image_wh, np.float64) - 0.5

    @property
    def radius(self) -> np.ndarray:
        """(N,) distance from the image centre over the half diagonal."""
        w, h = self.image_wh
        return np.hypot((self.pixel_uv[:, 0] - 0.5) * w, (self.pixel_uv[:, 1] - 0.5) * h) / (0.5 * math.hypot(w, h))

    @property
    def view_angle_deg(self) -> np.ndarray:
        """(N,) angle between the surface normal and the direction to the camera, acos(-n . X / |X|)."""
        cos_view = -(self.normals_cam * self.points_cam).sum(1) / self.range_m
        return np.degrees(np.arccos(np.clip(cos_view, -1.0, 1.0)))

    @property
    def light_distance_m(self) -> np.ndarray:
        """(N,L) distance from each declared light (camera frame ``offset_m``) to the point."""
        if not self.lights:
            return np.zeros((self.n_obs, 0))
        return np.stack([np.linalg.norm(np.asarray(light["offset_m"], float) - self.points_cam, axis=1)
                         for light in self.lights], 1)

    @property
    def height_m(self) -> np.ndarray:
        """(P,) each point's world z."""
        return self.points_world[:, 2]

    @property
    def water_depth_m(self) -> np.ndarray:
        """(P,) each point's depth below the surface: from navigation when known, else ``site_depth_m`` - z."""
        return self.nav_water_depth_m if self.nav_water_depth_m is not None else self.site_depth_m - self.height_m

    def save(self, path) -> None:
        """An npz of every array (float64, as fitted; fields that are None left out) and the scalars as one JSON
        string, written atomically."""
        from watergan.io import atomic_write_bytes

        arrays, meta = {}, {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                arrays[f.name] = value
            elif value is not None:
                meta[f.name] = value
        buffer = io.BytesIO()
        np.savez_compressed(buffer, meta=np.array(json.dumps(meta)), **arrays)
        atomic_write_bytes(path, buffer.getvalue())

    @classmethod
    def load(cls, path) -> Observations:
        """The table :meth:`save` wrote; a file of another layout is a :class:`UserInputError` saying to remeasure."""
        with np.load(path) as data:
            if "meta" not in data.files:
                raise UserInputError(f"{path} is a measurement table of an earlier version: rerun the stage that "
                                     f"wrote it (e.g. `watergan water --workspace WS --force`)")
            meta = json.loads(str(data["meta"]))
            arrays = {k: data[k] for k in data.files if k != "meta"}
        meta["image_wh"] = tuple(int(v) for v in meta["image_wh"])
        return cls(**arrays, **meta)

    def take_points(self, points: np.ndarray) -> Observations:
        """The table of the points ``points`` (sorted indices) with all their views, renumbered; board rows kept."""
        from dataclasses import replace

        rows = np.flatnonzero(np.isin(self.point, points))
        new = np.full(self.n_points, -1, np.int64)
        new[points] = np.arange(len(points))
        per_view = {k: getattr(self, k)[rows] for k in ("colour", "range_m", "depth_m", "pixel_uv", "points_cam",
                                                        "frame", "normals_cam", "grad_energy")
                    if getattr(self, k) is not None}
        per_point = {k: getattr(self, k)[points] for k in ("points_world", "normals_world", "nav_water_depth_m")
                     if getattr(self, k) is not None}
        return replace(self, **per_view, **per_point, point=new[self.point[rows]], n_points=len(points))



def pca_normals(points: np.ndarray, centres: np.ndarray, neighbours: int) -> np.ndarray:
    """(P,3) unit normals of a point cloud: the direction of least variance of each point's
    ``neighbours`` nearest points (the eigenvector of the smallest eigenvalue of their covariance),
    turned towards ``centres`` (P,3), e.g. the mean centre of the cameras that see the point:
    n . (c - X) > 0."""
    from scipy.spatial import cKDTree

    k = int(min(max(neighbours, 3), len(points)))
    _, idx = cKDTree(points).query(points, k=k)
    local = points[idx] - points[idx].mean(1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("pki,pkj->pij", local, local))
    normals = vectors[:, :, 0]
    flip = ((centres - points) * normals).sum(1) < 0
    normals[flip] *= -1.0
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def frame_normals(frame: WaterFrame, K: np.ndarray, smooth_px: float) -> np.ndarray:
    """(H,W,3) the frame's camera-frame normals: its own (``frame.normals_cam``), else those of its range smoothed by
    ``smooth_px`` (:func:`normals_from_range`; NaN where it has no range). A new array either way."""
    if frame.normals_cam is not None:
        return np.array(frame.normals_cam, np.float64)
    return normals_from_range(frame.range_m, K, smooth_px)


def _check_inputs(frames: Sequence[WaterFrame], K: np.ndarray, config: DenseMeasureConfig) -> list[int]:
    usable, coverage = [], []
    for k, f in enumerate(frames):
        if f.image.ndim != 3 or f.image.shape[2] != 3:
            raise WaterInputError(f"frame {f.name}: image must be (H,W,3) linear RGB, got {f.image.shape}")
        if f.range_m.shape != f.image.shape[:2]:
            raise WaterInputError(f"frame {f.name}: range map {f.range_m.shape} and image {f.image.shape[:2]} differ")
        cover = float(np.mean(np.isfinite(f.range_m) & (f.range_m > 0)))
        if f.world_from_cam is not None and np.isfinite(f.world_from_cam).all() and cover > 0:
            usable.append(k)
            coverage.append(cover)
    if len(usable) < config.min_frames:
        raise WaterInputError(
            f"only {len(usable)} of {len(frames)} frames have both an SfM pose and a dense range map (need "
            f"{config.min_frames}): give stereo frames (right/ with baseline_m in camera.json) or more overlap "
            f"between frames so SfM registers them, and nav_altitude_m in survey.json for a monocular survey's scale")
    if float(np.mean(coverage)) < config.min_range_coverage:
        raise WaterInputError(
            f"dense range covers {100 * np.mean(coverage):.0f} % of the pixels of the registered frames (need "
            f"{100 * config.min_range_coverage:.0f} %): give stereo frames, more overlap, or textured scenes the "
            f"dense stage can match")
    return usable


def measure_frames(frames: Sequence[WaterFrame], K: np.ndarray, tracks: SparseTracks | None = None, board=None,
                   config: DenseMeasureConfig = DenseMeasureConfig(), normals: bool = False) -> Observations:
    """The measurement table of the module docstring (dense correspondences, tracks, board) of ``frames`` with
    intrinsics ``K`` (3,3); with ``normals`` each view's surface normal in its camera frame too (for effects that
    read them, e.g. ``artificial_light``) and each point's in the world frame."""
    K = np.asarray(K, np.float64)
    usable = _check_inputs(frames, K, config)
    h, w = frames[usable[0]].image.shape[:2]
    rays = rays_cam(K, h, w)
    ray_norm = np.linalg.norm(rays, axis=-1)
    rng = np.random.default_rng([config.seed, 17])
    m = config.margin_px
    inner = np.zeros((h, w), bool)
    inner[m:h - m, m:w - m] = True
    per_frame = max(1, min(config.samples_per_frame, config.max_points // len(usable)))

    # 1. lift samples of every frame to world points (with their surface normals, world frame)
    points, point_normals = [], []
    for k in usable:
        f = frames[k]
        r = clean_range(f.range_m)
        ok = inner & np.isfinite(r)
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            continue
        n = min(per_frame, len(idx))
        n_dark = int(round(config.dark_fraction * n))
        lum = f.image.reshape(-1, 3)[idx].sum(1)
        dark = idx[lum <= np.quantile(lum, 0.05)]
        chosen = np.concatenate([rng.choice(idx, n - n_dark, replace=False),
                                 rng.choice(dark, min(n_dark, len(dark)), replace=False)])
        yy, xx = np.unravel_index(chosen, (h, w))
        pc = rays[yy, xx] / ray_norm[yy, xx, None] * r[yy, xx, None]
        pose = np.asarray(f.world_from_cam, np.float64)
        points.append(pc @ pose[:3, :3].T + pose[:3, 3])
        point_normals.append(frame_normals(f, K, config.normal_smooth_px)[yy, xx] @ pose[:3, :3].T if normals
                             else np.zeros((len(yy), 3)))
    if not points:
        raise WaterInputError("no frame has a pixel with range inside the image margin")
    xyz = np.concatenate(points)
    normals_world = np.concatenate(point_normals)

    # 2. views of every point in every frame (occlusion test with that frame's own range)
    rows = {key: [] for key in ("colour", "range", "depth", "uv", "pc", "nc", "point", "frame")}
    fx = float(K[0, 0])
    cache: dict[int, FootprintPyramid] = {}

    def sample(k: int, xy: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Colour at xy blurred by the footprint's size in pixels (:class:`eval.sampling.FootprintPyramid`)."""
        if k not in cache:
            cache.clear()
            cache[k] = FootprintPyramid(np.asarray(frames[k].image, np.float32), config.blur_px,
                                        PYRAMID_LEVELS if config.blur_px > 0 else 1)
        want = config.footprint_m * fx / depth if config.footprint_m > 0 else np.full(len(xy), config.blur_px)
        return cache[k].sample(xy, want)

    def add(k: int, pid: np.ndarray, pc: np.ndarray, xy: np.ndarray, nw: np.ndarray) -> None:
        rows["colour"].append(sample(k, xy, pc[:, 2]))
        rows["nc"].append(nw @ np.asarray(frames[k].world_from_cam, np.float64)[:3, :3])
        rows["range"].append(np.linalg.norm(pc, axis=1))
        rows["depth"].append(pc[:, 2])
        rows["uv"].append(np.stack([(xy[:, 0] + 0.5) / w, (xy[:, 1] + 0.5) / h], 1))
        rows["pc"].append(pc)
        rows["point"].append(pid)
        rows["frame"].append(np.full(len(pid), k, np.int64))

    for k in usable:
        f = frames[k]
        pose = np.asarray(f.world_from_cam, np.float64)
        pc = (xyz - pose[:3, 3]) @ pose[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = K[0, 0] * pc[:, 0] / z + K[0, 2]
            y = K[1, 1] * pc[:, 1] / z + K[1, 2]
        inside = (z > 0) & (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)
        sel = np.flatnonzero(inside)
        if len(sel) == 0:
            continue
        xy = np.stack([x[sel], y[sel]], 1)
        dist = np.linalg.norm(pc[sel], axis=1)
        r_map = clean_range(f.range_m)[np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)]
        seen = np.abs(r_map - dist) <= config.range_tolerance * dist
        sel, xy = sel[seen], xy[seen]
        if len(sel):
            add(k, sel, pc[sel], xy, normals_world[sel])

    n_dense = len(xyz)
    # 3. SfM tracks: their own observations (points appended after the dense ones); normals of the sparse cloud
    # (:func:`pca_normals`, turned towards the mean centre of the frames that see a point)
    if tracks is not None and len(tracks.xyz):
        use = np.isin(tracks.obs_frame, usable)
        centres = np.zeros((len(tracks.xyz), 3))
        seen = np.zeros(len(tracks.xyz))
        for k in np.unique(tracks.obs_frame[use]):
            sel = tracks.obs_point[use & (tracks.obs_frame == k)]
            centres[sel] += np.asarray(frames[k].world_from_cam, np.float64)[:3, 3]
            seen[sel] += 1
        track_normals = pca_normals(np.asarray(tracks.xyz, np.float64), centres / np.maximum(seen, 1)[:, None], 12) \
            if normals else np.zeros((len(tracks.xyz), 3))
        for k in np.unique(tracks.obs_frame[use]):
            sel = np.flatnonzero(use & (tracks.obs_frame == k))
            pose = np.asarray(frames[k].world_from_cam, np.float64)
            pc = (np.asarray(tracks.xyz, np.float64)[tracks.obs_point[sel]] - pose[:3, 3]) @ pose[:3, :3]
            xy = np.asarray(tracks.obs_xy[sel], np.float64)
            ok = (pc[:, 2] > 0) & (xy[:, 0] >= m) & (xy[:, 0] <= w - 1 - m) & (xy[:, 1] >= m) & (xy[:, 1] <= h - 1 - m)
            if ok.any():
                add(int(k), n_dense + tracks.obs_point[sel][ok], pc[ok], xy[ok],
                    track_normals[tracks.obs_point[sel][ok]])
        n_total = n_dense + len(tracks.xyz)
        xyz = np.concatenate([xyz, np.asarray(tracks.xyz, np.float64)])
        normals_world = np.concatenate([normals_world, track_normals])
    else:
        n_total = n_dense
    cache.clear()

    cat = {key: np.concatenate(v) for key, v in rows.items()}
    # keep points with >= 2 views, at most max_views each; drop views with clipped colour
    good = (cat["colour"] > 0.002).all(1) & (cat["colour"] < 0.98).all(1)
    order = np.lexsort((cat["frame"], cat["point"]))
    order = order[good[order]]
    pts = cat["point"][order]
    first = np.r_[0, np.flatnonzero(np.diff(pts)) + 1]
    rank = np.arange(len(pts)) - np.repeat(first, np.diff(np.r_[first, len(pts)]))
    order = order[rank < config.max_views]
    counts = np.bincount(cat["point"][order], minlength=n_total)
    order = order[counts[cat["point"][order]] >= 2]
    remap = np.full(n_total, -1, np.int64)
    used = np.unique(cat["point"][order])
    remap[used] = np.arange(len(used))
    obs = Observations(colour=cat["colour"][order], range_m=cat["range"][order], depth_m=cat["depth"][order],
                       pixel_uv=cat["uv"][order], points_cam=cat["pc"][order],
                       normals_cam=cat["nc"][order] if normals else None,
                       point=remap[cat["point"][order]],
                       frame=cat["frame"][order], n_points=len(used), image_wh=(w, h), n_frames=len(frames),
                       frames=[f.name for f in frames], source="dense correspondences",
                       points_world=xyz[used], normals_world=normals_world[used] if normals else None)
    if board is not None:
        _add_board(obs, frames, usable, board, K, rays, ray_norm, config, normals)
    _check_diversity(obs, config)
    return obs


def _add_board(obs: Observations, frames: Sequence[WaterFrame], usable: list[int], board, K: np.ndarray,
               rays: np.ndarray, ray_norm: np.ndarray, config: DenseMeasureConfig, normals: bool = False) -> None:
    """Board rows: per frame and visible patch, the mean raw colour inside the shrunk quad, its centroid and
    the median range there (patches with range on fewer than half their pixels are skipped)."""
    import cv2

    w, h = obs.image_wh
    rows = {key: [] for key in ("colour", "albedo", "range", "depth", "uv", "pc", "nc", "frame", "patch")}
    for k in usable:
        f = frames[k]
        quads = board.quads.get(f.name)
        if quads is None:
            continue
        r = clean_range(f.range_m)
        normal_map = frame_normals(f, K, config.normal_smooth_px) if normals else None
        for p, quad in enumerate(np.asarray(quads, np.float64)):
            if not np.isfinite(quad).all():
                continue
            centre = quad.mean(0)
            shrunk = centre + (1 - config.board_inset) * (quad - centre)
            mask = np.zeros((h, w), np.uint8)
            cv2.fillConvexPoly(mask, np.rint(shrunk * 16).astype(np.int32), 1, shift=4)
            inside = mask.astype(bool)
            if inside.sum() < 9 or np.isfinite(r[inside]).mean() < 0.5:
                continue
            colour = f.image[inside].mean(0)
            if (colour >= 0.98).any():
                continue
            ys, xs = np.nonzero(inside)
            xc, yc = xs.mean(), ys.mean()
            rr = float(np.nanmedian(r[inside]))
            ray = np.array([(xc - K[0, 2]) / K[0, 0], (yc - K[1, 2]) / K[1, 1], 1.0])
            pc = ray / np.linalg.norm(ray) * rr
            if normal_map is not None:
                n = np.nanmean(normal_map[inside], 0)
                rows["nc"].append(n / max(float(np.linalg.norm(n)), 1e-12))
            rows["colour"].append(colour)
            rows["albedo"].append(board.true_linear_rgb[p])
            rows["range"].append(rr)
            rows["depth"].append(pc[2])
            rows["uv"].append([(xc + 0.5) / w, (yc + 0.5) / h])
            rows["pc"].append(pc)
            rows["frame"].append(k)
            rows["patch"].append(p)
    if rows["colour"]:
        obs.board_colour = np.array(rows["colour"], np.float64)
        obs.board_albedo = np.array(rows["albedo"], np.float64)
        obs.board_range_m = np.array(rows["range"], np.float64)
        obs.board_depth_m = np.array(rows["depth"], np.float64)
        obs.board_pixel_uv = np.array(rows["uv"], np.float64)
        obs.board_points_cam = np.array(rows["pc"], np.float64)
        obs.board_normals_cam = np.array(rows["nc"], np.float64) if normals else None
        obs.board_frame = np.array(rows["frame"], np.int64)
        obs.board_patch = np.array(rows["patch"], np.int64)


def _check_diversity(obs: Observations, config: DenseMeasureConfig) -> None:
    lo = np.full(obs.n_points, np.inf)
    hi = np.full(obs.n_points, -np.inf)
    np.minimum.at(lo, obs.point, obs.range_m)
    np.maximum.at(hi, obs.point, obs.range_m)
    n = int(((hi - lo) >= 0.1).sum())
    if n < config.min_points:
        raise WaterInputError(
            f"only {n} surface points are seen from ranges 0.1 m or more apart (need {config.min_points}): the "
            f"attenuation cannot be told from the albedo. Give more overlap between frames, frames at several "
            f"altitudes, or stereo frames so more pixels have range")


# ------------------------------------------------------------------------------------------ fit
