"""Dense depth per image from rectified pairs (OpenCV SGBM), then TSDF fusion (open3d).

Pairs: the stereo rig's left/right frames when the survey has them (right pose = left pose moved
``baseline_m`` along the left camera's x; the SfM frame must be metric), else for each image the
registered neighbour whose baseline b to it is closest to ``target_baseline_ratio`` x the median
sparse depth (and within ``[min_baseline_ratio, max_baseline_ratio]``).

Rectification (works for any baseline direction, e.g. along-track neighbours whose baseline
runs along the image's y): a common rectified frame with x along the baseline (left centre to
right centre), z the mean optical axis made orthogonal to x, y = z x x; each image is warped with
the homography H = K' R_rect R_wc K^-1 (R_wc: camera-to-world rotation, K' = K shifted to frame the
warped left image). Disparity d = x_l - x_r gives the rectified depth z_rect = f b / d, and for
the original pixel with ray r = K^-1 (u, v, 1), camera depth z = z_rect / (R_rect R_wc r)_z.

SGBM's disparity range comes from the image's sparse depths (z in [z_min, z_max], widened by
``depth_margin``): d in [f b / z_max, f b / z_min]. A left-right check (disparity of the right
image computed on the mirrored pair) keeps pixels with |d_l(x) - d_r(x - d_l(x))| <= ``lr_max_px``.

Sub-pixel refinement: SGBM's sub-pixel estimate is locked towards integer disparities (errors of
~0.2 px, i.e. ~2 cm at 2.5 m with a 12 cm baseline and f = 457 px). Each disparity is refined by
Gauss-Newton (Lucas-Kanade along the epipolar line) on the colour rectified images: with the right
image warped by the current disparity, R_w(x) = R(x - d(x)), and its x-gradient g, the update is

    delta = -sum_w(r g) / sum_w(g g),   r = L - R_w,

summed over the colour channels in a Gaussian window w (sigma ``subpixel_sigma``), with L, R_w and g
made zero-mean in the same window (robust to a gain/offset between the views); a few iterations.
The window treats the disparity as constant: d_i = sum_j w_ij (g_j^2 d_j - r_j g_j) / sum_j w_ij g_j^2
(only SGBM-valid pixels take part). R is warped bicubically: bilinear warping blurs by an amount that
depends on the sub-pixel phase and biases the result (0.04 px at a fractional disparity of 0.3).
Pixels that move more than ``subpixel_max_shift_px`` from SGBM's value or have no texture are dropped.
The refined disparity is carried back to the original pixels by (validity-normalised) bilinear
interpolation.

Forward motion: a neighbour pair whose baseline runs within ``forward_max_angle_deg`` of the view direction (a
crawler or ROV looking ahead) has its epipoles in the frames, so rectification fails; such a frame takes its depth
from the sparse points it sees instead (:func:`pipeline.sparse_depth.sparse_depth`).

Method: ``method="auto"`` uses pycolmap's patch-match MVS when pycolmap was built with CUDA
(``pycolmap.has_cuda``), else this SGBM path; 'patch_match' without CUDA is an error. Patch-match
runs on an undistorted COLMAP workspace (``02_dense/mvs``: ``pycolmap.undistort_images`` of the
SfM model in the survey frame, then ``pycolmap.patch_match_stereo`` with geometric consistency); its
geometric depth maps (camera z in survey units; the PINHOLE camera undistorts to itself, so the
pixels are the original ones) are read back and written and fused like SGBM's.

Plausible depths only: a depth beyond the frame's far limit, ``far_limit_ratio`` x the 99th percentile of the
sparse depths the frame sees (the survey's, for a frame with fewer than 10 sparse points; never more than the
16-bit millimetre PNG holds, 65.535 units), is dropped as no value and counted (``too_far_fraction``): a match on
the untextured water above a far wall, or a disparity near 0 from an overlay both views share, gives such depths,
and SGBM searches no farther than the sparse range widened by ``depth_margin`` anyway. NaN, infinite or
non-positive depths are no value too, as are pixels outside the survey's scene mask (the sfm stage's
``scene_mask``: a burned-in timestamp, the vehicle's frame).

Outputs (``02_dense/``): ``depth/<stem>.png`` 16-bit millimetres (0 = invalid) in the survey frame's
units, ``fused_points.ply`` and ``fused_mesh.ply`` (TSDF fusion with the tensor VoxelBlockGrid).

Scale: with ``DenseConfig.scheduler`` (a Dask scheduler address) the SGBM depth of each image runs on the
cluster's workers (:func:`pair_depth`, one task per image; the images and ``02_dense`` on a file system
the workers share) and the depth maps come back here for the fusion; the files are the same as a local
run's. Patch-match and the fusion run here.
"""

from __future__ import annotations

import errno
import os
import shutil
import time
import zlib  # noqa: F401  must load before pycolmap (see pipeline.sfm)
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.io import (
    MAX_DEPTH_PNG_M,
    DataError,
    depth_within,
    read_bgr8,
    read_scene_mask,
    write_depth_png,
    write_failed,
)
from watergan.survey_files import read_camera_json

from .sparse_depth import pair_is_forward, sparse_depth


class DenseMethod(StrEnum):
    """How the dense depth maps are computed."""

    auto = "auto"
    sgbm = "sgbm"
    patch_match = "patch_match"


class PairSource(StrEnum):
    """Which frames pair for stereo."""

    auto = "auto"
    rig = "rig"
    neighbours = "neighbours"


@dataclass(frozen=True)
class DenseConfig:
    """Dense depth and fusion options."""

    images_dir: str = ""
    """Images to match (raw or corrected; same names as SfM's); empty: the workspace's survey images."""
    right_dir: str = ""
    """The stereo rig's right frames; empty: right/ beside the images folder when it exists."""
    method: DenseMethod = DenseMethod.auto
    """'sgbm' (OpenCV, CPU), 'patch_match' (pycolmap, needs CUDA) or 'auto' (patch_match when pycolmap has CUDA)."""
    pairs: PairSource = PairSource.auto
    """'rig' (stereo rig pairs), 'neighbours' (SfM neighbours) or 'auto' (rig when present)."""
    target_baseline_ratio: float = 0.12
    """Neighbour pairs: preferred baseline / median sparse depth."""
    min_baseline_ratio: float = 0.03
    """Neighbour pairs: smallest usable baseline / median depth."""
    max_baseline_ratio: float = 0.35
    """Neighbour pairs: largest usable baseline / median depth."""
    depth_margin: float = 0.3
    """Sparse depth range widened by this fraction each way before it sets the disparity range."""
    block_size: int = 5
    """SGBM matching block side, pixels (odd)."""
    uniqueness_ratio: int = 10
    """SGBM uniqueness margin, percent."""
    lr_max_px: float = 1.0
    """Left-right consistency threshold, pixels."""
    subpixel_sigma: float = 2.5
    """Sub-pixel refinement of SGBM's disparity: Gaussian window sigma, pixels (0: no refinement)."""
    subpixel_iterations: int = 3
    """Sub-pixel refinement: Gauss-Newton iterations."""
    subpixel_max_shift_px: float = 1.0
    """Sub-pixel refinement: pixels whose refined disparity moved further from SGBM's are dropped."""
    forward_max_angle_deg: float = 45.0
    """Neighbour pairs whose baseline lies within this angle of the frame's view direction (a camera moving along its
    view: the epipole in the frame, nothing for rectified stereo to match along) take the frame's depth from the
    sparse points it sees instead; 0: never."""
    far_limit_ratio: float = 3.0
    """A depth beyond this multiple of the 99th percentile of the sparse depths the frame sees (the survey's for a
    frame with fewer than 10 sparse points; at most 65.535, what the 16-bit millimetre PNG holds) is dropped as no
    value (a match on open water or a far wall's untextured tiles); the result counts them."""
    fuse: bool = True
    """Fuse the depth maps into a point cloud and mesh (TSDF)."""
    voxel_m: float = 0.0
    """TSDF voxel size in survey units (metres when scaled); 0: median depth / 100."""
    weight_threshold: float = 1.0
    """Fusion: voxels observed by fewer (weighted) views are not extracted."""
    scheduler: str = field(default="", metadata={"hash": False})
    """A Dask scheduler address (tcp://HOST:8786) to compute the per-image SGBM depth on its workers (shared
    file system); empty: here. Not used by patch_match. The outputs are the same either way."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Show progress bars."""


@dataclass
class DenseResult:
    depth_dir: str
    """Folder of 16-bit millimetre depth maps (0 = invalid)."""
    pairs: dict[str, str]
    """Image -> partner image name, 'rig', or 'sparse' (interpolated from the sparse points: a forward pair)."""
    coverage: dict[str, float]
    """Image -> fraction of its scene pixels with a valid depth."""
    mean_coverage: float
    skipped: list[str] = field(default_factory=list)
    """Registered images without a usable partner or with no valid depth."""
    far_limit_m: dict[str, float] = field(default_factory=dict)
    """Image -> its far limit (survey units: metres when scaled): depths beyond it were dropped."""
    too_far_fraction: dict[str, float] = field(default_factory=dict)
    """Image -> fraction of its scene pixels whose depth was dropped as beyond the far limit."""
    mean_too_far_fraction: float = 0.0
    """The mean of ``too_far_fraction`` over the images with a depth map."""
    points_ply: str = ""
    mesh_ply: str = ""
    n_fused_points: int = 0
    seconds: float = 0.0


def rectifying_rotation(world_from_left: np.ndarray, world_from_right: np.ndarray) -> tuple[np.ndarray, float]:
    """R_rect (rows: rectified axes in world) and baseline b = |C_r - C_l| (see module docstring)."""
    base = world_from_right[:3, 3] - world_from_left[:3, 3]
    b = float(np.linalg.norm(base))
    if b <= 0:
        raise ValueError("the two cameras share a centre: no stereo baseline")
    x = base / b
    z = world_from_left[:3, 2] + world_from_right[:3, 2]
    z = z - (z @ x) * x
    z /= np.linalg.norm(z)
    y = np.cross(z, x)
    return np.stack([x, y, z]), b


def _corners(w: int, h: int) -> np.ndarray:
    return np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)


def rectified_pair_depth(left: np.ndarray, right: np.ndarray, K: np.ndarray, world_from_left: np.ndarray,
                         world_from_right: np.ndarray, depth_range: tuple[float, float], cfg: DenseConfig
                         ) -> np.ndarray:
    """Camera-z depth (H,W) of the left image (NaN = invalid) from an arbitrary calibrated pair."""
    import cv2

    h, w = left.shape[:2]
    R_rect, b = rectifying_rotation(world_from_left, world_from_right)
    K_inv = np.linalg.inv(K)
    rot_l = R_rect @ world_from_left[:3, :3]
    rot_r = R_rect @ world_from_right[:3, :3]
    f = float(K[0, 0])
    H_l0 = np.diag([f, f, 1.0]) @ rot_l @ K_inv
    warped = H_l0 @ _corners(w, h).T
    warped = warped[:2] / warped[2]
    lo, hi = warped.min(1), warped.max(1)
    size = np.minimum(np.ceil(hi - lo).astype(int) + 1, [3 * w, 3 * h])
    K_new = np.array([[f, 0, -lo[0]], [0, f, -lo[1]], [0, 0, 1.0]])
    H_l, H_r = K_new @ rot_l @ K_inv, K_new @ rot_r @ K_inv
    dsize = (int(size[0]), int(size[1]))
    colour_l = cv2.warpPerspective(left.astype(np.float32), H_l, dsize, flags=cv2.INTER_LINEAR)
    colour_r = cv2.warpPerspective(right.astype(np.float32), H_r, dsize, flags=cv2.INTER_LINEAR)
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (left, right)]
    rect_l = cv2.warpPerspective(grey[0], H_l, dsize, flags=cv2.INTER_LINEAR)
    rect_r = cv2.warpPerspective(grey[1], H_r, dsize, flags=cv2.INTER_LINEAR)

    z_lo, z_hi = depth_range
    d_min = max(int(np.floor(f * b / (z_hi * (1 + cfg.depth_margin)))), 0)
    d_max = int(np.ceil(f * b / max(z_lo * (1 - cfg.depth_margin), 1e-6)))
    n_disp = max(16, int(np.ceil((d_max - d_min + 1) / 16)) * 16)
    bs = cfg.block_size
    sgbm = cv2.StereoSGBM_create(minDisparity=d_min, numDisparities=n_disp, blockSize=bs, P1=8 * bs * bs,
                                 P2=32 * bs * bs, disp12MaxDiff=-1, uniquenessRatio=cfg.uniqueness_ratio,
                                 speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp_l = sgbm.compute(rect_l, rect_r).astype(np.float32) / 16.0
    disp_r = sgbm.compute(rect_r[:, ::-1].copy(), rect_l[:, ::-1].copy()).astype(np.float32)[:, ::-1] / 16.0
    valid = disp_l >= max(d_min, 0.5)
    ys, xs = np.nonzero(valid)
    xr = np.rint(xs - disp_l[ys, xs]).astype(int)
    inside = (xr >= 0) & (xr < disp_l.shape[1])
    agree = np.zeros(len(xs), bool)
    agree[inside] = np.abs(disp_l[ys[inside], xs[inside]] - disp_r[ys[inside], xr[inside]]) <= cfg.lr_max_px
    valid[ys[~agree], xs[~agree]] = False
    disp_l[~valid] = np.nan
    if cfg.subpixel_sigma > 0:
        disp_l = refine_disparity(colour_l, colour_r, disp_l, cfg.subpixel_sigma, cfg.subpixel_iterations,
                                  cfg.subpixel_max_shift_px)

    # back to the original pixels: rectified position and ray of each pixel
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], -1)
    rect = pix @ H_l.T
    map_x = (rect[..., 0] / rect[..., 2]).astype(np.float32)
    map_y = (rect[..., 1] / rect[..., 2]).astype(np.float32)
    d = _remap_valid(disp_l, map_x, map_y)
    ray_rect_z = (pix @ (rot_l @ K_inv).T)[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = f * b / d / ray_rect_z
    depth[~np.isfinite(depth) | (depth <= 0)] = np.nan
    return depth


def _remap_valid(values: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear remap of a map with NaN holes: the interpolation weights of valid neighbours are
    renormalised; NaN where valid neighbours carry less than half the weight."""
    import cv2

    valid = np.isfinite(values)
    kw = dict(borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    total = cv2.remap(np.where(valid, values, 0).astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, **kw)
    weight = cv2.remap(valid.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, **kw)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(weight > 0.5, total / weight, np.nan).astype(np.float32)


def refine_disparity(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, sigma: float,
                     iterations: int = 3, max_shift_px: float = 1.0) -> np.ndarray:
    """Sub-pixel Gauss-Newton refinement of a rectified disparity map (NaN = invalid) on float images
    (H,W) or (H,W,C); see the module docstring. Returns the refined map (NaN = invalid)."""
    import cv2

    left = left.astype(np.float32).reshape(*left.shape[:2], -1)
    right = right.astype(np.float32).reshape(*right.shape[:2], -1)
    h, w = disparity.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    valid = np.isfinite(disparity)
    start = np.where(valid, disparity, 0).astype(np.float32)
    d = start.copy()

    def window(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)

    def warp(shift: float) -> np.ndarray:
        out = cv2.remap(right, xs - d + shift, ys, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        return out.reshape(h, w, -1)

    zero_mean_l = left - window(left).reshape(left.shape)
    mask = valid.astype(np.float32)
    den = np.zeros((h, w), np.float32)
    for _ in range(iterations):
        warped, grad = warp(0.0), warp(0.5) - warp(-0.5)
        warped -= window(warped).reshape(warped.shape)
        grad -= window(grad).reshape(grad.shape)
        g2 = mask * (grad * grad).sum(-1)
        den = window(g2)
        # window-constant disparity: d_i = sum_j w_ij (g_j^2 d_j - r_j g_j) / sum_j w_ij g_j^2
        num = window(g2 * d - mask * ((zero_mean_l - warped) * grad).sum(-1))
        target = num / np.maximum(den, 1e-6)
        d = np.where(valid, d + np.clip(target - d, -0.5, 0.5), d).astype(np.float32)
    textured = den > 1e-3 * max(float(np.median(den[valid])) if valid.any() else 0.0, 1e-6)
    keep = valid & textured & (np.abs(d - start) <= max_shift_px)
    return np.where(keep, d, np.nan).astype(np.float32)


def choose_neighbour(k: int, tracks, median_depth: float, cfg: DenseConfig,
                     rows: list[np.ndarray] | None = None) -> int | None:
    """The registered image whose baseline / median depth is nearest the target (within bounds),
    preferring images that share more sparse points with image k. ``rows``: per image, its observations'
    indices (``watergan.parallel.rows_by_label(tracks.obs_image, range(n_images))``), to avoid rescanning."""
    def observations(i: int) -> np.ndarray:
        return rows[i] if rows is not None else np.flatnonzero(tracks.obs_image == i)

    reg = np.flatnonzero(tracks.registered)
    centres = tracks.world_from_cam[:, :3, 3]
    ratios = np.linalg.norm(centres[reg] - centres[k], axis=1) / median_depth
    near = (reg != k) & (ratios >= cfg.min_baseline_ratio) & (ratios <= cfg.max_baseline_ratio)
    mine = np.zeros(len(tracks.xyz), bool)
    mine[tracks.obs_point[observations(k)]] = True
    best, best_cost = None, np.inf
    for j, ratio in zip(reg[near], ratios[near], strict=True):
        shared = mine[tracks.obs_point[observations(j)]].sum() / max(mine.sum(), 1)
        if shared < 0.3:
            continue
        cost = abs(np.log(ratio / cfg.target_baseline_ratio)) - shared
        if cost < best_cost:
            best, best_cost = int(j), cost
    return best


def frame_far_limit(frame_depths_m: np.ndarray, survey_depths_m: np.ndarray, ratio: float) -> float:
    """A frame's far limit: ``ratio`` x the 99th percentile of the sparse depths it sees (``frame_depths_m``; the
    survey's ``survey_depths_m`` when it sees fewer than 10), at most ``MAX_DEPTH_PNG_M``."""
    depths = frame_depths_m if len(frame_depths_m) >= 10 else survey_depths_m
    return float(min(ratio * np.percentile(depths, 99), MAX_DEPTH_PNG_M))


def write_frame_depth(path: Path, depth_m: np.ndarray, far_limit_m: float,
                      scene: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """A frame's depth map kept where plausible and written as ``path`` (16-bit millimetres, atomically) when any
    pixel has a depth: no value (NaN) where it is NaN, infinite, <= 0, beyond ``far_limit_m`` (survey units) or outside
    ``scene`` ((H,W) bool, True = scene; None: every pixel). Returns (the kept depth, float32; coverage: the share
    of the scene's pixels with a depth; the share of them dropped as beyond the far limit); nothing is written when
    the coverage is 0."""
    kept, too_far = depth_within(depth_m, far_limit_m)
    if scene is not None:
        kept[~scene] = np.nan
        too_far &= scene
    pixels = max(int(scene.sum()) if scene is not None else kept.size, 1)
    coverage = float(np.isfinite(kept).sum() / pixels)
    if coverage > 0:
        write_depth_png(path, kept)
    return kept.astype(np.float32), coverage, float(too_far.sum() / pixels)


@dataclass(frozen=True, eq=False)
class PairJob:
    """One image's depth task (plain, picklable values: it may run on a Dask worker)."""

    name: str
    left: Path
    right: Path
    partner: str
    """The partner image's name, or 'rig'."""
    K: np.ndarray
    world_from_left: np.ndarray
    world_from_right: np.ndarray
    depth_range: tuple[float, float]
    cfg: DenseConfig
    depth_png: Path
    """Where the 16-bit millimetre depth map goes (written atomically)."""
    far_limit_m: float = MAX_DEPTH_PNG_M
    """Depths beyond it are dropped (:func:`frame_far_limit`)."""
    scene_mask: Path | None = None
    """The survey's scene mask (:func:`watergan.io.write_scene_mask`); None: every pixel is the scene."""


#: A frame whose depth comes from the sparse points (a forward-moving pair).
SPARSE = "sparse"


def pair_depth(job: PairJob) -> tuple[float, float, np.ndarray | None]:
    """Depth of ``job.left`` from its pair, kept and written by :func:`write_frame_depth` to ``job.depth_png``:
    (coverage, share dropped as too far, depth (H,W), NaN = invalid); (0, share, None) when the rig's right frame is
    unreadable or no pixel got a depth (nothing written)."""
    left = read_bgr8(job.left)
    try:
        right = read_bgr8(job.right)
    except DataError:
        if job.partner == "rig":
            return 0.0, 0.0, None
        raise
    depth = rectified_pair_depth(left[..., ::-1], right[..., ::-1], job.K, job.world_from_left,
                                 job.world_from_right, job.depth_range, job.cfg)
    depth, cover, too_far = write_frame_depth(job.depth_png, depth, job.far_limit_m, read_scene_mask(job.scene_mask))
    return cover, too_far, depth if cover > 0 else None


def run_dense_folder(tracks, images_dir: str | Path, out_dir: str | Path, cfg: DenseConfig,
                     baseline_m: float | None = None, right_dir: Path | None = None,
                     scene_mask: Path | None = None) -> DenseResult:
    """Depth maps for the registered images of ``tracks`` and their fusion (see module docstring); ``scene_mask``:
    the survey's scene mask file (None: every pixel is the scene). With ``cfg.scheduler`` the per-image depth runs
    on that Dask cluster (:mod:`watergan.parallel`); the fusion runs here."""
    from watergan.parallel import map_tasks, rows_by_label, shared_path

    start = time.perf_counter()
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    use_rig = cfg.pairs == "rig" or (cfg.pairs == "auto" and right_dir is not None and baseline_m)
    if cfg.pairs not in ("auto", "rig", "neighbours"):
        raise UserInputError(f"pairs must be 'auto', 'rig' or 'neighbours', not '{cfg.pairs}'")
    if use_rig and (right_dir is None or not right_dir.is_dir() or not baseline_m):
        raise UserInputError("rig pairs need a right/ folder and baseline_m in camera.json; use --pairs neighbours")
    depth_dir = out_dir / "depth"
    depth_dir.mkdir(parents=True, exist_ok=True)
    obs_depth = tracks.depths()
    median_depth = float(np.median(obs_depth))
    K = np.asarray(tracks.K, float)
    rows = rows_by_label(tracks.obs_image, range(len(tracks.image_names)))
    order: list[tuple[str, PairJob | None]] = []  # every registered image, None: no partner
    limits: dict[str, float] = {}
    for k in np.flatnonzero(tracks.registered):
        name = str(tracks.image_names[k])
        mine = obs_depth[rows[k]]
        limits[name] = frame_far_limit(mine, obs_depth, cfg.far_limit_ratio)
        z_range = (float(np.percentile(mine, 1)), float(np.percentile(mine, 99))) if len(mine) >= 10 else \
            (0.5 * median_depth, 2 * median_depth)
        if use_rig:
            offset = np.eye(4)
            offset[0, 3] = baseline_m
            right, pose_r, partner = right_dir / name, tracks.world_from_cam[k] @ offset, "rig"
        else:
            j = choose_neighbour(k, tracks, median_depth, cfg, rows)
            if j is None:
                order.append((name, None))
                continue
            if cfg.forward_max_angle_deg > 0 and pair_is_forward(tracks.world_from_cam[k], tracks.world_from_cam[j],
                                                                 cfg.forward_max_angle_deg):
                order.append((name, SPARSE))
                continue
            partner = str(tracks.image_names[j])
            right, pose_r = images_dir / partner, tracks.world_from_cam[j]
        order.append((name, PairJob(name, shared_path(images_dir / name), shared_path(right), partner, K,
                                    np.array(tracks.world_from_cam[k], float), np.array(pose_r, float), z_range,
                                    cfg, shared_path(depth_dir / f"{Path(name).stem}.png"), limits[name],
                                    shared_path(scene_mask) if scene_mask is not None else None)))
    jobs = [job for _, job in order if isinstance(job, PairJob)]
    done = dict(zip((job.name for job in jobs), map_tasks(pair_depth, jobs, cfg.scheduler or None, desc="dense",
                                                           progress=cfg.progress, unit="image"), strict=True))
    mask = read_scene_mask(scene_mask) if scene_mask is not None else None
    index = {str(n): i for i, n in enumerate(tracks.image_names)}
    for name, job in order:
        if job is SPARSE:  # interpolated from the depths of the sparse points the frame observes
            mine = rows[index[name]]
            depth = sparse_depth(tracks.obs_xy[mine].astype(float), obs_depth[mine], int(tracks.width),
                                 int(tracks.height))
            depth, cover, dropped = write_frame_depth(depth_dir / f"{Path(name).stem}.png", depth, limits[name], mask)
            done[name] = (cover, dropped, depth if cover > 0 else None)
    pairs, coverage, too_far, skipped, depths = {}, {}, {}, [], {}
    for name, job in order:
        cover, dropped, depth = done[name] if job is not None else (0.0, 0.0, None)
        if depth is None:
            skipped.append(name)
            continue
        partner = "sparse" if job is SPARSE else job.partner
        pairs[name], coverage[name], too_far[name], depths[name] = partner, cover, dropped, depth
    if not depths:
        raise UserInputError("no image got a dense depth map: check the pairs (--pairs) and the SfM result")
    return _finish(depths, pairs, coverage, skipped, depth_dir, tracks, images_dir, out_dir, cfg, start,
                   {n: limits[n] for n in depths}, too_far)


def _finish(depths: dict[str, np.ndarray], pairs: dict[str, str], coverage: dict[str, float], skipped: list[str],
            depth_dir: Path, tracks, images_dir: Path, out_dir: Path, cfg: DenseConfig, start: float,
            limits: dict[str, float], too_far: dict[str, float]) -> DenseResult:
    """The result of either depth method, with the depth maps fused (TSDF) when ``cfg.fuse``: voxel
    ``cfg.voxel_m`` or the median sparse depth / 100, depth cut at 2.5x the 99th sparse percentile."""
    result = DenseResult(depth_dir=str(depth_dir), pairs=pairs, coverage=coverage,
                         mean_coverage=float(np.mean(list(coverage.values()))), skipped=skipped, far_limit_m=limits,
                         too_far_fraction=too_far, mean_too_far_fraction=float(np.mean(list(too_far.values()))))
    if cfg.fuse:
        index = {str(n): i for i, n in enumerate(tracks.image_names)}
        obs_depth = tracks.depths()
        result.points_ply, result.mesh_ply, result.n_fused_points = fuse_depths(
            depths, {n: tracks.world_from_cam[index[n]] for n in depths}, tracks.K, images_dir, out_dir,
            cfg.voxel_m or float(np.median(obs_depth)) / 100, cfg.weight_threshold,
            2.5 * float(np.percentile(obs_depth, 99)))
    result.seconds = time.perf_counter() - start
    return result


def fuse_depths(depths: dict[str, np.ndarray], poses: dict[str, np.ndarray], K: np.ndarray, images_dir: Path,
                out_dir: Path, voxel: float, weight_threshold: float, depth_max: float) -> tuple[str, str, int]:
    """TSDF fusion of coloured depth maps with open3d's tensor VoxelBlockGrid (truncation 4 voxels);
    writes ``fused_points.ply`` and ``fused_mesh.ply``. Returns their paths and the point count."""
    import open3d as o3d

    device = o3d.core.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                         attr_dtypes=(o3d.core.float32, o3d.core.float32, o3d.core.float32),
                                         attr_channels=((1,), (1,), (3,)), voxel_size=voxel, block_resolution=16,
                                         block_count=50000, device=device)
    intrinsic = o3d.core.Tensor(K, o3d.core.float64)
    for name, depth in depths.items():
        depth_img = o3d.t.geometry.Image(np.nan_to_num(depth, nan=0.0).astype(np.float32))
        colour = read_bgr8(images_dir / name)[..., ::-1].astype(np.float32) / 255.0
        colour_img = o3d.t.geometry.Image(np.ascontiguousarray(colour))
        extrinsic = o3d.core.Tensor(np.linalg.inv(poses[name]), o3d.core.float64)
        blocks = grid.compute_unique_block_coordinates(depth_img, intrinsic, extrinsic, 1.0, depth_max, 4.0)
        grid.integrate(blocks, depth_img, colour_img, intrinsic, extrinsic, 1.0, depth_max, 4.0)
    cloud = grid.extract_point_cloud(weight_threshold)
    mesh = grid.extract_triangle_mesh(weight_threshold)
    points_path, mesh_path = out_dir / "fused_points.ply", out_dir / "fused_mesh.ply"
    write_checked(points_path, cloud, o3d.t.io.write_point_cloud)
    write_checked(mesh_path, mesh, o3d.t.io.write_triangle_mesh)
    return str(points_path), str(mesh_path), int(cloud.point.positions.shape[0])


def write_checked(path: Path, geometry, write) -> None:
    """Write an open3d tensor point cloud or triangle mesh to ``path`` as PLY through a temporary file beside it and
    rename it into place only when the file is as long as its header says (:func:`ply_complete`): open3d reports a
    file cut short by a full disk as written, and reads one back with whatever memory held. Raises
    :class:`watergan.io.WriteError` naming the path otherwise."""
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    try:
        if not write(str(tmp), geometry) or not ply_complete(tmp):
            raise OSError(errno.EIO, "open3d's file is shorter than its header says (a full disk?)")
        os.replace(tmp, path)  # open3d creates it with the umask's mode
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise write_failed(path, exc) from exc


#: Bytes of each PLY scalar type.
PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
             "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def ply_complete(path: Path) -> bool:
    """Whether a binary PLY file holds every element its header declares (lists taken as triangles, as open3d
    writes them); an ASCII PLY counts as complete when it has its header."""
    data = path.read_bytes() if path.is_file() else b""
    end = data.find(b"end_header\n")
    if end < 0:
        return False
    header = data[:end].decode("ascii", "replace").splitlines()
    if not any(line.startswith("format binary") for line in header):
        return True
    size = end + len("end_header\n")
    elements: list[list] = []
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            elements.append([int(parts[2]), 0])
        elif parts[:1] == ["property"] and elements:
            elements[-1][1] += (PLY_SIZES[parts[2]] + 3 * PLY_SIZES[parts[3]] if parts[1] == "list"
                                else PLY_SIZES[parts[1]])
    return size + sum(count * row for count, row in elements) == len(data)


def dense_method(method: str) -> str:
    """The depth method to use for ``DenseConfig.method`` (see the module docstring)."""
    import pycolmap

    if method not in ("auto", "sgbm", "patch_match"):
        raise UserInputError(f"method must be 'auto', 'sgbm' or 'patch_match', not '{method}'")
    has_cuda = bool(getattr(pycolmap, "has_cuda", False))
    if method == "patch_match" and not has_cuda:
        raise UserInputError("patch_match needs pycolmap built with CUDA (pycolmap.has_cuda is false here): "
                             "use --method sgbm (or auto)")
    return "patch_match" if method == "patch_match" or (method == "auto" and has_cuda) else "sgbm"


def read_colmap_array(path: Path) -> np.ndarray:
    """A COLMAP dense array file: text header 'width&height&channels&', then float32 with x varying fastest,
    then y, then the channel (COLMAP's read_write_dense.py: Fortran-order reshape to (width, height, channels))."""
    data = path.read_bytes()
    ends = [i for i, c in enumerate(data) if c == ord("&")][:3]
    width, height, channels = (int(x) for x in data[:ends[2]].split(b"&"))
    values = np.frombuffer(data[ends[2] + 1:], np.float32, count=width * height * channels)
    return values.reshape((width, height, channels), order="F").transpose(1, 0, 2).squeeze()


def run_patch_match_folder(tracks, model_dir: Path, images_dir: Path, out_dir: Path, cfg: DenseConfig,
                           scene_mask: Path | None = None) -> DenseResult:
    """pycolmap patch-match depth maps (CUDA) for the registered images, kept, written and fused like SGBM's
    (``scene_mask``: the survey's scene mask file, None: every pixel is the scene)."""
    import pycolmap

    from pipeline.colmap import colmap_errors_only
    from watergan.parallel import rows_by_label

    start = time.perf_counter()
    mvs, depth_dir = out_dir / "mvs", out_dir / "depth"
    shutil.rmtree(mvs, ignore_errors=True)
    depth_dir.mkdir(parents=True, exist_ok=True)
    options = pycolmap.PatchMatchOptions()
    options.geom_consistency = True
    with colmap_errors_only():  # else a few hundred INFO lines per view
        pycolmap.undistort_images(mvs, model_dir, images_dir)
        pycolmap.patch_match_stereo(mvs, options=options)
    obs_depth = tracks.depths()
    rows = rows_by_label(tracks.obs_image, range(len(tracks.image_names)))
    scene = read_scene_mask(scene_mask)
    pairs, coverage, too_far, limits, skipped, depths = {}, {}, {}, {}, [], {}
    for k in np.flatnonzero(tracks.registered):
        name = str(tracks.image_names[k])
        path = mvs / "stereo" / "depth_maps" / f"{name}.geometric.bin"
        depth = read_colmap_array(path) if path.is_file() else None
        if depth is None or depth.shape != (tracks.height, tracks.width):
            skipped.append(name)
            continue
        limit = frame_far_limit(obs_depth[rows[k]], obs_depth, cfg.far_limit_ratio)
        depth, cover, dropped = write_frame_depth(depth_dir / f"{Path(name).stem}.png", depth, limit, scene)
        if cover == 0:
            skipped.append(name)
            continue
        pairs[name], coverage[name], too_far[name], limits[name], depths[name] = \
            "patch_match", cover, dropped, limit, depth
    if not depths:
        raise UserInputError("patch-match gave no depth map: check the SfM result")
    return _finish(depths, pairs, coverage, skipped, depth_dir, tracks, images_dir, out_dir, cfg, start, limits,
                   too_far)


def run_dense(ws, cfg: DenseConfig) -> DenseResult:
    """Workspace stage: tracks and model from the sfm stage's result; outputs in the stage's folder."""
    from eval.tracks import Tracks

    method = dense_method(cfg.method)
    sfm = ws.require("sfm", "dense")
    tracks = Tracks.load(ws.path(sfm.tracks))
    images_dir = Path(cfg.images_dir) if cfg.images_dir else ws.stage_dir("survey") / "images"
    right_dir = Path(cfg.right_dir) if cfg.right_dir else images_dir.parent / "right"
    scene_mask = ws.path(sfm.scene_mask) if getattr(sfm, "scene_mask", "") else None
    if method == "patch_match":
        result = run_patch_match_folder(tracks, ws.path(sfm.model_dir), images_dir, ws.stage_dir("dense"), cfg,
                                        scene_mask)
        result.depth_dir = ws.relative(result.depth_dir)
        if result.points_ply:
            result.points_ply, result.mesh_ply = ws.relative(result.points_ply), ws.relative(result.mesh_ply)
        return result
    camera_path = images_dir.parent / "camera.json"
    baseline_m = (read_camera_json(camera_path) or {}).get("baseline_m")
    if baseline_m and cfg.pairs != "neighbours" and sfm.scale_method == "none":
        raise UserInputError("the SfM model has no metric scale, so the rig baseline cannot be placed in it: "
                             "rerun sfm with --scale stereo/altitude or use --pairs neighbours")
    result = run_dense_folder(tracks, images_dir, ws.stage_dir("dense"), cfg, baseline_m,
                              right_dir if right_dir.is_dir() else None, scene_mask)
    result.depth_dir = ws.relative(result.depth_dir)
    if result.points_ply:
        result.points_ply, result.mesh_ply = ws.relative(result.points_ply), ws.relative(result.mesh_ply)
    return result
