"""Measurements for the diagnosis: 3D points seen in several views and what each view records.

A measurement table has one row per *observation* (a point seen in a frame) and one row per
*point*. The geometry (which world point is seen where) comes from a geometry source; the colour
and every derived quantity are then read from the survey's images by :func:`measure`.

Geometry sources are plain functions returning :class:`Geometry`:

- :func:`geometry_from_truth`: the simulator's truth (depth maps and poses), for tests and
  simulated surveys. Points are sampled by unprojecting random pixels of random frames and
  projected into every frame; a point is seen in a frame when it lands inside the image (with the
  patch margin) and the frame's true depth there agrees with its camera z within ``depth_tol_m``.

A second source (for instance COLMAP tracks from ``04_sfm``) is a second function returning the
same :class:`Geometry`; :func:`measure` needs nothing else.

Observed colour is the mean of a ``patch_px`` x ``patch_px`` patch of the sRGB-decoded (linear)
image, bilinearly interpolated at the sub-pixel projection (OpenCV pixel centres: pixel (i, j)
is centred at (i, j)).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np
import torch

from eval.synth.camera import Intrinsics, project, unproject
from eval.synth.io import read_png, srgb_decode
from watergan.errors import UserInputError
from watergan.formation import state_from_rgbd


@dataclass(frozen=True)
class MeasureConfig:
    """How points are sampled and observations measured."""

    n_points: int = 3000
    """Candidate 3D points to sample (those seen in fewer than ``min_views`` frames are dropped)."""
    min_views: int = 3
    """Frames a point must be seen in to be kept."""
    patch_px: int = 5
    """Side of the square patch whose mean is a point's observed colour, pixels (odd)."""
    depth_tol_m: float = 0.02
    """Largest difference between a point's camera z and the frame's depth there for it to count
    as seen (occlusion test), metres."""
    seed: int = 0
    """Seed of the point sampling."""


@dataclass(frozen=True)
class Geometry:
    """Where each point is seen: the output of a geometry source.

    points_world:  (P,3) world points, metres (z up).
    normals_world: (P,3) unit surface normals in the world frame.
    obs_point:     (N,) index of the point of each observation.
    obs_frame:     (N,) index of the frame of each observation.
    obs_px:        (N,2) pixel coordinates (x, y) of the projection, OpenCV centres.
    world_from_cam:(F,4,4) camera poses.
    intrinsics:    the camera.
    frames:        (F,) image file names.
    """

    points_world: np.ndarray
    normals_world: np.ndarray
    obs_point: np.ndarray
    obs_frame: np.ndarray
    obs_px: np.ndarray
    world_from_cam: np.ndarray
    intrinsics: Intrinsics
    frames: list[str]


@dataclass(frozen=True)
class Measurements:
    """The measurement table. Per observation (N rows):

    point:            (N,) point index; frame: (N,) frame index.
    colour:           (N,3) observed linear RGB (patch mean, 0..1).
    px:               (N,2) pixel coordinates (x, y), OpenCV centres.
    pixel_uv:         (N,2) pixel centre as a fraction of the image: ((x + 0.5)/W, (y + 0.5)/H).
    radius:           (N,) distance from the image centre / half diagonal.
    range_m:          (N,) camera-to-point distance, metres; depth_m: (N,) camera z, metres.
    points_cam:       (N,3) point in the camera frame, metres; normals_cam: (N,3) its normal.
    view_angle_deg:   (N,) angle between the surface normal and the direction to the camera.
    light_distance_m: (N,L) distance from each declared light to the point (L = 0 without lights).
    grad_energy:      (N,) variance of the Laplacian of the linear grey image in the patch.

    Per point (P rows): points_world, normals_world, height_m (world z), water_depth_m
    (site depth - z). Scalars: image_wh, site_depth_m, patch_px; lights as declared in survey.json;
    frames (file names); source (which geometry source made it).
    """

    point: np.ndarray
    frame: np.ndarray
    colour: np.ndarray
    px: np.ndarray
    pixel_uv: np.ndarray
    radius: np.ndarray
    range_m: np.ndarray
    depth_m: np.ndarray
    points_cam: np.ndarray
    normals_cam: np.ndarray
    view_angle_deg: np.ndarray
    light_distance_m: np.ndarray
    grad_energy: np.ndarray
    points_world: np.ndarray
    normals_world: np.ndarray
    height_m: np.ndarray
    water_depth_m: np.ndarray
    image_wh: tuple[int, int]
    site_depth_m: float
    patch_px: int
    lights: list[dict]
    frames: list[str]
    source: str

    @property
    def n_obs(self) -> int:
        return len(self.point)

    @property
    def n_points(self) -> int:
        return len(self.points_world)

    def save(self, path: str | Path) -> None:
        """Compact npz (float32 arrays; metadata as one JSON string)."""
        arrays, meta = {}, {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                arrays[f.name] = value.astype(np.float32) if value.dtype == np.float64 else value
            else:
                meta[f.name] = value
        np.savez_compressed(path, meta=np.array(json.dumps(meta)), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Measurements:
        with np.load(path) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {k: data[k].astype(np.float64) if data[k].dtype == np.float32 else data[k]
                      for k in data.files if k != "meta"}
        meta["image_wh"] = tuple(meta["image_wh"])
        return cls(**arrays, **meta)


def resolve_survey(target: str | Path) -> Path:
    """The survey folder of a workspace (``WORKSPACE/00_survey``) or a bare survey folder."""
    root = Path(target)
    if not root.is_dir():
        raise UserInputError(f"{root} does not exist or is not a folder: give a workspace or a survey folder")
    for candidate in (root / "00_survey", root):
        if (candidate / "camera.json").is_file() and (candidate / "images").is_dir():
            return candidate
    raise UserInputError(f"{root} is neither a survey folder (camera.json + images/) nor a workspace with "
                         f"00_survey/: simulate one with `watergan simulate` or copy the survey there")


def geometry_from_truth(survey: Path, config: MeasureConfig) -> Geometry:
    """Points and their views from the simulator's truth (depth maps and poses).

    A point X = unproject(pixel, depth) of a random pixel of a random frame (inside the patch
    margin); it is seen in frame k when its projection lies inside the margin and
    |z_k(X) - depth_k(projection)| < depth_tol_m (depth bilinearly interpolated). Normals come
    from the source frame's depth map (central differences, as ``state_from_rgbd``).
    """
    from eval.synth import load_truth

    try:
        truth = load_truth(survey)
    except FileNotFoundError as exc:
        raise UserInputError(f"{survey} has no simulator truth (truth/poses.json): this geometry source needs a "
                             f"simulated survey") from exc
    intr = truth.intrinsics
    poses = truth.world_from_cam
    depths = np.stack([truth.depth_m(k) for k in range(len(truth.frames))])
    n_frames, h, w = depths.shape
    margin = config.patch_px // 2 + 1
    if w <= 2 * margin + 1 or h <= 2 * margin + 1:
        raise UserInputError(f"images of {w}x{h} are too small for a {config.patch_px}-pixel patch")
    rng = np.random.default_rng([config.seed, 7])
    src = rng.integers(0, n_frames, config.n_points)
    xs = rng.integers(margin, w - margin, config.n_points)
    ys = rng.integers(margin, h - margin, config.n_points)
    z = depths[src, ys, xs]
    keep = z > 0
    src, xs, ys, z = src[keep], xs[keep], ys[keep], z[keep]
    points = np.stack([unproject(np.array([x, y], float), d, poses[k], intr)
                        for k, x, y, d in zip(src, xs, ys, z, strict=True)]) if len(src) else np.zeros((0, 3))

    normals = np.zeros_like(points)
    for k in np.unique(src):
        sel = src == k
        state = state_from_rgbd(torch.zeros(1, 3, h, w, dtype=torch.float64), torch.from_numpy(depths[k])[None, None],
                                intr.fx, intr.fy, intr.cx, intr.cy)
        n_cam = state.normals_cam[0].permute(1, 2, 0).numpy()[ys[sel], xs[sel]]
        normals[sel] = n_cam @ poses[k][:3, :3].T

    obs_point, obs_frame, obs_px = [], [], []
    for k in range(n_frames):
        uv, zc = project(points, poses[k], intr)
        inside = np.isfinite(uv).all(1) & (uv[:, 0] >= margin) & (uv[:, 0] <= w - 1 - margin) \
            & (uv[:, 1] >= margin) & (uv[:, 1] <= h - 1 - margin)
        idx = np.nonzero(inside)[0]
        d = bilinear(depths[k][..., None], uv[idx])[:, 0]
        seen = (d > 0) & (np.abs(d - zc[idx]) < config.depth_tol_m)
        obs_point.append(idx[seen])
        obs_frame.append(np.full(seen.sum(), k))
        obs_px.append(uv[idx[seen]])
    return _keep_multiview(points, normals, np.concatenate(obs_point), np.concatenate(obs_frame),
                           np.concatenate(obs_px), poses, intr, truth.frames, config.min_views)


def _keep_multiview(points, normals, obs_point, obs_frame, obs_px, poses, intr, frames, min_views) -> Geometry:
    """Drop points seen in fewer than ``min_views`` frames and renumber the rest."""
    views = np.bincount(obs_point, minlength=len(points))
    keep = views >= min_views
    if keep.sum() < 20:
        raise UserInputError(f"only {int(keep.sum())} points are seen in at least {min_views} frames: the survey "
                             f"needs more overlap between frames (or more frames) for a diagnosis")
    new_index = np.cumsum(keep) - 1
    sel = keep[obs_point]
    order = np.lexsort((obs_frame[sel], new_index[obs_point[sel]]))
    return Geometry(points_world=points[keep], normals_world=normals[keep],
                    obs_point=new_index[obs_point[sel]][order], obs_frame=obs_frame[sel][order],
                    obs_px=obs_px[sel][order], world_from_cam=poses, intrinsics=intr, frames=list(frames))


def bilinear(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """(N,C) values of an (H,W,C) image at pixel coordinates (N,2) (x, y), OpenCV centres;
    coordinates must lie within [0, W-1] x [0, H-1]."""
    h, w = image.shape[:2]
    x = np.clip(px[:, 0], 0, w - 1)
    y = np.clip(px[:, 1], 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), w - 2)
    y0 = np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fx) * (1 - fy) * image[y0, x0] + fx * (1 - fy) * image[y0, x0 + 1]
            + (1 - fx) * fy * image[y0 + 1, x0] + fx * fy * image[y0 + 1, x0 + 1])


def measure(survey: Path, geometry: Geometry, config: MeasureConfig, source: str) -> Measurements:
    """Observed colour and every per-observation quantity for the points of ``geometry``.

    colour = bilinear sample of the patch-mean (box filter) of the sRGB-decoded image;
    grad_energy = E[L^2] - E[L]^2 over the patch, L the Laplacian of the grey linear image;
    view angle = acos(n . (c - X)/|c - X|), c the camera centre.
    """
    survey_json = json.loads((survey / "survey.json").read_text()) if (survey / "survey.json").is_file() else {}
    lights = list(survey_json.get("lights") or [])
    site_depth = float(survey_json.get("site_depth_m", 0.0))
    intr = geometry.intrinsics
    n_obs = len(geometry.obs_point)
    colour = np.zeros((n_obs, 3))
    grad = np.zeros(n_obs)
    k_size = (config.patch_px, config.patch_px)
    for k in np.unique(geometry.obs_frame):
        path = survey / "images" / geometry.frames[k]
        image = read_png(path)
        if image.ndim != 3 or image.shape[:2] != (intr.height, intr.width):
            raise UserInputError(f"image {path} is not a {intr.width}x{intr.height} RGB image")
        top = 255.0 if image.dtype == np.uint8 else 65535.0
        linear = srgb_decode(image / top).astype(np.float32)
        lap = cv2.Laplacian(linear.mean(axis=2), cv2.CV_32F)
        mean_lap = cv2.blur(lap, k_size)
        energy = cv2.blur(lap * lap, k_size) - mean_lap * mean_lap
        sel = geometry.obs_frame == k
        colour[sel] = bilinear(cv2.blur(linear, k_size).astype(np.float64), geometry.obs_px[sel])
        grad[sel] = bilinear(energy[..., None].astype(np.float64), geometry.obs_px[sel])[:, 0]

    poses = geometry.world_from_cam[geometry.obs_frame]
    xw = geometry.points_world[geometry.obs_point]
    nw = geometry.normals_world[geometry.obs_point]
    rot = poses[:, :3, :3]
    pc = np.einsum("nji,nj->ni", rot, xw - poses[:, :3, 3])
    nc = np.einsum("nji,nj->ni", rot, nw)
    rng_m = np.linalg.norm(pc, axis=1)
    cos_view = np.clip(-(nc * pc).sum(1) / rng_m, -1.0, 1.0)
    w, h = intr.width, intr.height
    uv = (geometry.obs_px + 0.5) / np.array([w, h])
    radius = np.hypot((uv[:, 0] - 0.5) * w, (uv[:, 1] - 0.5) * h) / (0.5 * math.hypot(w, h))
    light_d = np.stack([np.linalg.norm(np.asarray(light["offset_m"], float) - pc, axis=1) for light in lights], 1) \
        if lights else np.zeros((n_obs, 0))
    return Measurements(
        point=geometry.obs_point.astype(np.int64), frame=geometry.obs_frame.astype(np.int64), colour=colour,
        px=geometry.obs_px, pixel_uv=uv, radius=radius, range_m=rng_m, depth_m=pc[:, 2], points_cam=pc,
        normals_cam=nc, view_angle_deg=np.degrees(np.arccos(cos_view)), light_distance_m=light_d,
        grad_energy=np.maximum(grad, 0.0), points_world=geometry.points_world,
        normals_world=geometry.normals_world, height_m=geometry.points_world[:, 2],
        water_depth_m=site_depth - geometry.points_world[:, 2], image_wh=(w, h), site_depth_m=site_depth,
        patch_px=config.patch_px, lights=lights, frames=list(geometry.frames), source=source)


def measure_survey(target: str | Path, config: MeasureConfig = MeasureConfig()) -> Measurements:
    """Measurements of a survey folder or a workspace's ``00_survey`` (geometry from the simulator's truth)."""
    if config.patch_px < 1 or config.patch_px % 2 == 0:
        raise UserInputError(f"patch_px must be a positive odd number of pixels, got {config.patch_px}")
    survey = resolve_survey(target)
    return measure(survey, geometry_from_truth(survey, config), config, source="truth")

