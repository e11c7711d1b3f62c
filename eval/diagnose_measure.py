"""The diagnosis's measurement of a survey folder: 3D points seen in several views, into the one measurement table
(:class:`eval.observations.Observations`).

The geometry (which world point is seen where) comes from a geometry source; the colour and every derived quantity
are then read from the survey's images by :func:`measure`. Geometry sources are plain functions returning
:class:`Geometry`:

- :func:`geometry_from_tracks`: the SfM reconstruction (the sfm stage's ``tracks.npz``), what a real survey has.
  Points are the sparse points, observations their feature positions (within ``max_reprojection_px`` of the point's
  projection); normals from the neighbouring sparse points.
- :func:`geometry_from_truth`: the simulator's truth (depth maps and poses), for tests and simulated surveys without
  a reconstruction. Points are sampled by unprojecting random pixels of random frames and projected into every
  frame; a point is seen in a frame when it lands inside the image (with the patch margin) and the frame's true
  depth there agrees with its camera z within ``depth_tol_m``.

:func:`measure_survey` picks the source (``geometry="auto"``: the SfM tracks when given, else the truth of a
simulated survey). In a workspace where the water stage ran, the diagnosis does not measure at all: it takes the
water estimate's own table (:func:`with_survey` adds what the diagnosis reads beside it: the survey's frame names,
lights, water depths and each view's gradient energy), so the water estimate and the candidate ranking are computed
on the same views (``geometry="water"``, which ``auto`` picks there; :mod:`pipeline.diagnose`).

Observed colour: the sRGB-decoded (linear) image averaged over the same patch of *surface* in every view of a point
(``same_footprint``, the default) or over a ``patch_px`` x ``patch_px`` patch of pixels, bilinearly interpolated at
the sub-pixel projection (OpenCV pixel centres). A fixed patch of pixels averages more of the seafloor's texture in a
far view than in a near one, which biases the attenuation (see :mod:`eval.observations`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path

import cv2
import numpy as np
import torch

from eval.synth.camera import Intrinsics, project, unproject
from watergan.errors import UserInputError
from watergan.formation import state_from_rgbd
from watergan.io import read_png, srgb_to_linear
from watergan.survey_files import read_survey_json

from .observations import Observations, pca_normals
from .sampling import FootprintPyramid, bilinear


@dataclass(frozen=True)
class MeasureConfig:
    """How points are sampled and observations measured."""

    n_points: int = 3000
    """Candidate 3D points to sample (those seen in fewer than the least views, next, are dropped)."""
    min_views: int = 3
    """Frames a point must be seen in to be kept."""
    patch_px: int = 5
    """Side of the square patch whose mean is a point's observed colour, pixels (odd).
    With the same footprint (the default), the patch the farthest view of each point averages (a Gaussian of the
    same standard deviation, patch_px / sqrt(12) pixels); also the margin kept from the image border."""
    same_footprint: bool = True
    """Read every view of a point over the same patch of surface; off: the patch's box mean in every view.
    A view at camera depth d is blurred by a Gaussian of sigma = patch_px / sqrt(12) x d_far / d pixels, d_far the
    depth of the point's farthest view (sigma is interpolated between 8 blur levels 1.5x apart, so views nearer
    than d_far / 17 are blurred less than that). A box mean in pixels averages more texture in a far view, which
    biases the attenuation."""
    depth_tol_m: float = 0.02
    """Occlusion test: largest difference between a point's camera z and the frame's depth there, metres."""
    seed: int = 0
    """Seed of the point sampling."""
    max_reprojection_px: float = 2.0
    """SfM geometry: largest distance of a kept observation's feature from the point's projection, pixels."""
    normal_neighbours: int = 12
    """SfM geometry: sparse points (the point included) whose plane gives a point's normal."""


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
    scale:         where the metric scale comes from: "truth", or the SfM stage's scale_method
                   ("stereo", "board", "altitude"; "none": arbitrary units).
    water_depth_m: (P,) depth of each point below the surface, metres, when the source knows it
                   better than ``site_depth_m - z`` (SfM with navigation depths); None otherwise.
    """

    points_world: np.ndarray
    normals_world: np.ndarray
    obs_point: np.ndarray
    obs_frame: np.ndarray
    obs_px: np.ndarray
    world_from_cam: np.ndarray
    intrinsics: Intrinsics
    frames: list[str]
    scale: str = "truth"
    water_depth_m: np.ndarray | None = None


class GeometrySource(StrEnum):
    """Where the diagnosis's 3D points and views come from."""

    auto = "auto"
    truth = "truth"
    sfm = "sfm"
    water = "water"


GEOMETRY_SOURCES = tuple(GeometrySource)


def check_survey_folder(survey: str | Path) -> Path:
    """``survey`` as a Path when it is a survey folder (camera.json + images/), else a clear error."""
    root = Path(survey)
    if not root.is_dir():
        raise UserInputError(f"{root} does not exist or is not a folder: give a workspace or a survey folder")
    if (root / "camera.json").is_file() and (root / "images").is_dir():
        return root
    raise UserInputError(f"{root} is neither a survey folder (camera.json + images/) nor a workspace with a "
                         f"survey: simulate one with `watergan simulate` or run `watergan run` on it")


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


def _keep_multiview(points, normals, obs_point, obs_frame, obs_px, poses, intr, frames, min_views,
                    scale: str = "truth") -> Geometry:
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
                    obs_px=obs_px[sel][order], world_from_cam=poses, intrinsics=intr, frames=list(frames),
                    scale=scale)


def drop_observations(geometry: Geometry, keep: np.ndarray, min_views: int) -> tuple[Geometry, np.ndarray]:
    """The geometry without the observations where ``keep`` (N,) is False, less the points left with
    fewer than ``min_views`` views (renumbered), and the indices of the kept observations (in the
    new order, which is the old one: observations stay sorted by point, then frame)."""
    index = np.flatnonzero(keep)
    views = np.bincount(geometry.obs_point[index], minlength=len(geometry.points_world))
    ok = views >= min_views
    if ok.sum() < 20:
        raise UserInputError(f"only {int(ok.sum())} points keep at least {min_views} views without clipped pixels: "
                             f"the survey is over- or under-exposed")
    index = index[ok[geometry.obs_point[index]]]
    new_point = np.cumsum(ok) - 1
    depth = geometry.water_depth_m[ok] if geometry.water_depth_m is not None else None
    return replace(geometry, points_world=geometry.points_world[ok], normals_world=geometry.normals_world[ok],
                   obs_point=new_point[geometry.obs_point[index]], obs_frame=geometry.obs_frame[index],
                   obs_px=geometry.obs_px[index], water_depth_m=depth), index


def geometry_from_tracks(tracks_path: str | Path, survey: Path, config: MeasureConfig,
                         scale: str = "unknown") -> Geometry:
    """Points and their views from the SfM reconstruction (:class:`eval.tracks.Tracks`).

    ``tracks_path``: the sfm stage's tracks.npz; ``scale``: its ``scale_method``. An observation of sparse point X
    in registered image k at feature pixel x_f is kept when the patch fits inside the image and
    |x_f - pi_k(X)| <= ``max_reprojection_px`` (pi_k the projection). Of the points with at least
    ``min_views`` kept observations, ``n_points`` are drawn at random (all when fewer). Normals:
    :func:`pca_normals` over every sparse point, towards the mean centre of the point's cameras.
    Water depth, when survey.json has the navigation depth d_k of each camera: the median over the
    point's views of d_k + (C_k - X) . z (the survey frame's z is up, metric when the SfM scale is);
    else site_depth_m - z. The scale (``Geometry.scale``) is the SfM stage's ``scale_method``.
    """
    from eval.tracks import Tracks

    tracks = Tracks.load(tracks_path)
    K = np.asarray(tracks.K, float)
    intr = Intrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                      width=int(tracks.width), height=int(tracks.height))
    poses = np.asarray(tracks.world_from_cam, float)
    frames = [str(n) for n in tracks.image_names]
    obs_point, obs_frame = tracks.obs_point.astype(np.int64), tracks.obs_image.astype(np.int64)
    px = tracks.obs_xy.astype(np.float64)
    margin = config.patch_px // 2 + 1
    ok = tracks.registered[obs_frame] & (px[:, 0] >= margin) & (px[:, 0] <= intr.width - 1 - margin) \
        & (px[:, 1] >= margin) & (px[:, 1] <= intr.height - 1 - margin)
    pose = np.where(ok[:, None, None], poses[obs_frame], np.eye(4))
    pc = np.einsum("nji,nj->ni", pose[:, :3, :3], tracks.xyz[obs_point] - pose[:, :3, 3])
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = np.stack([intr.fx * pc[:, 0] / pc[:, 2] + intr.cx, intr.fy * pc[:, 1] / pc[:, 2] + intr.cy], 1)
    ok &= (pc[:, 2] > 0) & (np.linalg.norm(proj - px, axis=1) <= config.max_reprojection_px)

    views = np.bincount(obs_point[ok], minlength=len(tracks.xyz))
    eligible = np.flatnonzero(views >= config.min_views)
    rng = np.random.default_rng([config.seed, 7])
    chosen = np.sort(rng.permutation(eligible)[:config.n_points])
    take = np.zeros(len(tracks.xyz), bool)
    take[chosen] = True
    ok &= take[obs_point]

    centre_sum = np.zeros((len(tracks.xyz), 3))
    np.add.at(centre_sum, obs_point, poses[obs_frame, :3, 3])  # tracks observe registered images only
    seen = np.maximum(np.bincount(obs_point, minlength=len(tracks.xyz)), 1)[:, None]
    normals = pca_normals(tracks.xyz, centre_sum / seen, config.normal_neighbours)

    geometry = _keep_multiview(tracks.xyz, normals, obs_point[ok], obs_frame[ok], px[ok], poses, intr, frames,
                               config.min_views, scale=scale)
    return replace(geometry, water_depth_m=_navigation_water_depth(survey, geometry))


def _navigation_water_depth(survey: Path, geometry: Geometry) -> np.ndarray | None:
    """Per point, median over its views of nav_depth_k + (C_k - X) . z; None without navigation depths."""
    path = survey / "survey.json"
    info = read_survey_json(path) if path.is_file() else {}
    if "nav_depth_m" not in info:
        return None
    by_name = dict(zip(info.get("frames", geometry.frames), info["nav_depth_m"], strict=False))
    nav = np.array([by_name.get(name, np.nan) for name in geometry.frames], float)
    per_obs = nav[geometry.obs_frame] + geometry.world_from_cam[geometry.obs_frame, 2, 3] \
        - geometry.points_world[geometry.obs_point, 2]
    if not np.isfinite(per_obs).all():
        return None
    # observations are grouped by point (see _keep_multiview)
    groups = np.split(per_obs, np.cumsum(np.bincount(geometry.obs_point))[:-1])
    return np.array([np.median(g) for g in groups])


#: Blur levels of the footprint pyramid colours are read through (:class:`eval.sampling.FootprintPyramid`):
#: sigma_0 x 1.5^j, j = 0 .. FOOTPRINT_LEVELS - 1, sigma_0 the least footprint of the frame's views.
FOOTPRINT_LEVELS = 8


def footprint_sigmas(geometry: Geometry, patch_px: int) -> np.ndarray:
    """(N,) Gaussian blur of each observation, pixels, so that every view of a point averages the same patch of
    surface: sigma_o = s d_far / d_o, s = patch_px / sqrt(12) (the standard deviation of a patch_px box), d_o the
    observation's camera depth and d_far the largest over the point's views (a pixel's footprint on the surface
    grows as d / f)."""
    poses = geometry.world_from_cam[geometry.obs_frame]
    xw = geometry.points_world[geometry.obs_point]
    depth = np.einsum("ni,ni->n", poses[:, :3, 2], xw - poses[:, :3, 3])
    far = np.zeros(len(geometry.points_world))
    np.maximum.at(far, geometry.obs_point, depth)
    return patch_px / math.sqrt(12.0) * far[geometry.obs_point] / np.maximum(depth, 1e-9)


def patch_energy(linear: np.ndarray, patch_px: int) -> np.ndarray:
    """(H,W) variance of the Laplacian of the grey (channel mean) linear image over a ``patch_px`` square."""
    k_size = (patch_px, patch_px)
    lap = cv2.Laplacian(linear.mean(axis=2), cv2.CV_32F)
    mean_lap = cv2.blur(lap, k_size)
    return cv2.blur(lap * lap, k_size) - mean_lap * mean_lap


def _linear_image(path: Path, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray, int]:
    """(sRGB-decoded linear float32 image, the raw image, its full-scale value)."""
    image = read_png(path)
    if image.ndim != 3 or image.shape[:2] != (intr.height, intr.width):
        raise UserInputError(f"image {path} is not a {intr.width}x{intr.height} RGB image")
    top = 255 if image.dtype == np.uint8 else 65535
    return srgb_to_linear(image / float(top)).astype(np.float32), image, top


def measure(survey: Path, geometry: Geometry, config: MeasureConfig, source: str) -> Observations:
    """Observed colour and every per-observation quantity for the points of ``geometry``.

    Observations whose patch holds a clipped pixel (a channel at 0 or at full scale) are dropped
    (then points left with fewer than ``min_views`` views): a clipped value is not what the model
    predicts, and a few of them (a white board patch) would otherwise make a sensor curve with a
    saturation level look like a missing effect.

    colour = bilinear sample of the sRGB-decoded image blurred by the point's footprint (``same_footprint``:
    :func:`footprint_sigmas`, interpolated between blur levels), else by the ``patch_px`` box filter;
    grad_energy = E[L^2] - E[L]^2 over the patch, L the Laplacian of the grey linear image;
    view angle = acos(n . (c - X)/|c - X|), c the camera centre.
    """
    survey_json = read_survey_json(survey / "survey.json") if (survey / "survey.json").is_file() else {}
    intr = geometry.intrinsics
    n_obs = len(geometry.obs_point)
    colour = np.zeros((n_obs, 3))
    grad = np.zeros(n_obs)
    clipped = np.zeros(n_obs, bool)
    k_size = (config.patch_px, config.patch_px)
    sigma = footprint_sigmas(geometry, config.patch_px) if config.same_footprint else None
    for k in np.unique(geometry.obs_frame):
        linear, image, top = _linear_image(survey / "images" / geometry.frames[k], intr)
        at_limit = ((image == 0) | (image == top)).any(axis=2).astype(np.float32)
        near = cv2.blur(at_limit, (config.patch_px + 2, config.patch_px + 2))  # > 0 within the sampled pixels
        energy = patch_energy(linear, config.patch_px)
        sel = geometry.obs_frame == k
        if sigma is None:
            colour[sel] = bilinear(cv2.blur(linear, k_size).astype(np.float64), geometry.obs_px[sel])
        else:
            pyramid = FootprintPyramid(linear, sigma[sel].min(), FOOTPRINT_LEVELS)
            colour[sel] = pyramid.sample(geometry.obs_px[sel], sigma[sel])
        grad[sel] = bilinear(energy[..., None].astype(np.float64), geometry.obs_px[sel])[:, 0]
        clipped[sel] = bilinear(near[..., None].astype(np.float64), geometry.obs_px[sel])[:, 0] > 0

    if clipped.any():
        geometry, index = drop_observations(geometry, ~clipped, config.min_views)
        colour, grad, n_obs = colour[index], grad[index], len(index)

    poses = geometry.world_from_cam[geometry.obs_frame]
    xw = geometry.points_world[geometry.obs_point]
    nw = geometry.normals_world[geometry.obs_point]
    rot = poses[:, :3, :3]
    pc = np.einsum("nji,nj->ni", rot, xw - poses[:, :3, 3])
    nc = np.einsum("nji,nj->ni", rot, nw)
    return _table(geometry, colour, grad, pc, nc, survey_json, config.patch_px, source, int(clipped.sum()))


def _table(geometry: Geometry, colour: np.ndarray, grad: np.ndarray, pc: np.ndarray, nc: np.ndarray,
           survey_json: dict, patch_px: int, source: str, clipped_obs: int) -> Observations:
    """The measurement table from the geometry and each view's colour, patch gradient energy, camera-frame point and
    normal (range, image position, lights and water depths follow from them: :class:`Observations`)."""
    intr = geometry.intrinsics
    return Observations(
        colour=colour, range_m=np.linalg.norm(pc, axis=1), depth_m=pc[:, 2],
        pixel_uv=(geometry.obs_px + 0.5) / np.array([intr.width, intr.height]), points_cam=pc,
        point=geometry.obs_point.astype(np.int64), frame=geometry.obs_frame.astype(np.int64),
        n_points=len(geometry.points_world), image_wh=(intr.width, intr.height), n_frames=len(geometry.frames),
        normals_cam=nc, grad_energy=np.maximum(grad, 0.0), points_world=geometry.points_world,
        normals_world=geometry.normals_world, nav_water_depth_m=geometry.water_depth_m,
        frames=list(geometry.frames), lights=list(survey_json.get("lights") or []),
        site_depth_m=float(survey_json.get("site_depth_m", 0.0)), source=source, patch_px=patch_px,
        clipped_obs=clipped_obs)


def with_survey(obs: Observations, survey: str | Path, tracks_path: str | Path, scale: str = "unknown",
                config: MeasureConfig = MeasureConfig()) -> Observations:
    """The water stage's table (frame indices into the sfm stage's image list ``tracks_path``) with what the diagnosis
    reads beside the fitted views: the frames' names, survey.json's ``lights`` and ``site_depth_m``, each point's
    water depth from the navigation depths (else ``site_depth_m`` - z) and each view's gradient energy (the
    ``spatial_frequency`` axis) from the raw image in a ``config.patch_px`` patch; ``source`` says where it came from.
    The views, colours and geometry are the water's, unchanged. Of ``config``, ``n_points`` bounds the points taken
    (all when the table has no more; else that many drawn with ``seed``, every view of each kept) and ``patch_px``
    sizes the gradient patch; the sampling options belong to :func:`measure_survey` and do not apply."""
    from eval.tracks import Tracks

    survey = check_survey_folder(survey)
    if obs.points_world is None or obs.normals_cam is None or obs.normals_world is None:
        raise UserInputError("the water stage's observations lack the points' world positions or normals: rerun the "
                             "water stage (`watergan water --workspace WS --force`)")
    if config.patch_px < 1 or config.patch_px % 2 == 0:
        raise UserInputError(f"patch_px must be a positive odd number of pixels, got {config.patch_px}")
    if obs.n_points > config.n_points:
        obs = obs.take_points(np.sort(np.random.default_rng([config.seed, 7]).permutation(obs.n_points)
                                      [:config.n_points]))
    tracks = Tracks.load(tracks_path)
    K = np.asarray(tracks.K, float)
    intr = Intrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                      width=int(tracks.width), height=int(tracks.height))
    if tuple(obs.image_wh) != (intr.width, intr.height):
        raise UserInputError(f"the water stage's observations are of {obs.image_wh[0]}x{obs.image_wh[1]} images, the "
                             f"sfm stage's of {intr.width}x{intr.height}: rerun the water stage")
    geometry = Geometry(points_world=np.asarray(obs.points_world, float), normals_world=np.asarray(obs.normals_world),
                        obs_point=obs.point, obs_frame=obs.frame.astype(np.int64), obs_px=obs.px,
                        world_from_cam=np.asarray(tracks.world_from_cam, float), intrinsics=intr,
                        frames=[str(n) for n in tracks.image_names], scale=scale)
    grad = np.zeros(obs.n_obs)
    for k in np.unique(obs.frame):
        linear, _, _ = _linear_image(survey / "images" / geometry.frames[k], intr)
        sel = obs.frame == k
        grad[sel] = bilinear(patch_energy(linear, config.patch_px)[..., None].astype(np.float64), obs.px[sel])[:, 0]
    survey_json = read_survey_json(survey / "survey.json") if (survey / "survey.json").is_file() else {}
    return replace(obs, grad_energy=np.maximum(grad, 0.0), nav_water_depth_m=_navigation_water_depth(survey, geometry),
                   frames=list(geometry.frames), n_frames=max(obs.n_frames, len(geometry.frames)),
                   lights=list(survey_json.get("lights") or []),
                   site_depth_m=float(survey_json.get("site_depth_m", 0.0)),
                   source=f"water stage (scale: {scale})", patch_px=config.patch_px, clipped_obs=0)


def choose_geometry(survey: Path, geometry: str = "auto", tracks: Path | None = None) -> str:
    """"truth" or "sfm" for ``geometry`` = "auto" | "truth" | "sfm": auto takes the SfM ``tracks`` when
    given, else the simulator's truth when the survey has it."""
    if geometry not in GEOMETRY_SOURCES:
        raise UserInputError(f"geometry must be one of {', '.join(GEOMETRY_SOURCES)}, not '{geometry}'")
    if geometry == "water":
        raise UserInputError("the water stage's observations are in a workspace: run `watergan water --workspace WS` "
                             "and diagnose the workspace (a survey folder is measured on its tracks or its truth)")
    if geometry == "sfm" and tracks is None:
        raise UserInputError("no SfM tracks: run `watergan sfm --workspace WORKSPACE` first and diagnose the "
                             "workspace, or diagnose on the simulator's truth (--geometry truth)")
    if geometry != "auto":
        return geometry
    if tracks is not None:
        return "sfm"
    if (survey / "truth" / "poses.json").is_file():
        return "truth"
    raise UserInputError(f"{survey} has no reconstruction and no simulator truth: run `watergan sfm --workspace "
                         f"WORKSPACE` on it (its survey is linked into the workspace) and diagnose the workspace")


def measure_survey(survey: str | Path, config: MeasureConfig = MeasureConfig(), geometry: str = "auto",
                   tracks: str | Path | None = None, scale: str = "unknown") -> Observations:
    """Measurements of a survey folder, the geometry from the source :func:`choose_geometry` picks
    (``tracks``: the SfM stage's tracks.npz, ``scale`` its ``scale_method``)."""
    if config.patch_px < 1 or config.patch_px % 2 == 0:
        raise UserInputError(f"patch_px must be a positive odd number of pixels, got {config.patch_px}")
    survey = check_survey_folder(survey)
    tracks = Path(tracks) if tracks is not None else None
    if choose_geometry(survey, geometry, tracks) == "sfm":
        geo = geometry_from_tracks(tracks, survey, config, scale)
        return measure(survey, geo, config, source=f"sfm (scale: {geo.scale})")
    return measure(survey, geometry_from_truth(survey, config), config, source="truth")
