"""Colour measurements on the SfM tracks: consistency across views (paper Table II) and
colour-board accuracy (paper Table I).

Intensity-normalised colour of an RGB value c:  n(c) = c / (R + G + B).

Consistency: every 3D point seen in at least ``min_views`` views is sampled in each view as the
mean of a ``patch_px`` x ``patch_px`` patch around its observation (pixel noise would otherwise
dominate), normalised, and the per-channel variance across its views

    var_ch(p) = 1/V sum_v (n_ch(p, v) - mean_v n_ch(p, v))^2

is averaged over points. The same points and observations are used for every image folder
(raw, corrected, in-air truth, ...): an observation counts only if its patch is valid in all of
them, so the comparison is like for like. A constant image has zero variance: report consistency
beside a fidelity measure (the board accuracy, or PSNR against in-air truth). The sampling is per
image and can run on a Dask cluster (``scheduler``, :mod:`watergan.parallel`) with the same values.

Board accuracy, per patch and view: the patch quad (corners projected from the world with the
poses and intrinsics, or given in pixels) is shrunk towards its centre by ``inset`` and the pixels
inside are averaged; then

    distance  = |n(measured) - n(true)|                        (Euclidean, intensity-normalised RGB)
    CIEDE2000 between measured and true colour in CIE Lab (D65), after one exposure factor per
              view k = sum(m . t) / sum(m . m) over the view's patches (linear RGB), so that
              lightness differences between patches count but overall exposure does not.

Values are taken in linear RGB (8/16-bit sRGB images are decoded) unless ``linear=False``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from watergan.data import srgb_to_linear
from watergan.errors import UserInputError
from watergan.io import frame_file, read_json, read_pixels


def read_rgb(path: str | Path, linear: bool = True) -> np.ndarray:
    """An 8- or 16-bit RGB image as float32 0..1 (sRGB-decoded to linear when ``linear``)."""
    raw = read_pixels(Path(path))
    if raw.ndim == 2:
        raw = np.repeat(raw[..., None], 3, axis=2)
    rgb = raw[..., 2::-1].astype(np.float32) / (65535.0 if raw.dtype == np.uint16 else 255.0)
    if linear:
        rgb = srgb_to_linear(rgb).astype(np.float32)
    return rgb


def normalise(rgb: np.ndarray) -> np.ndarray:
    """Intensity-normalised colour c / (R + G + B) along the last axis (NaN where the sum is 0)."""
    total = rgb.sum(-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, rgb / total, np.nan)


def patch_means(image: np.ndarray, xy: np.ndarray, patch_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean colour (M,3) of the ``patch_px`` square centred on the nearest pixel to each position
    (M,2) (OpenCV pixel convention) and whether the patch lies inside the image (M,)."""
    import cv2

    if patch_px < 1 or patch_px % 2 == 0:
        raise UserInputError(f"patch size must be an odd number of pixels >= 1, got {patch_px}")
    h, w = image.shape[:2]
    half = patch_px // 2
    blurred = cv2.boxFilter(image, -1, (patch_px, patch_px), normalize=True, borderType=cv2.BORDER_REPLICATE)
    ij = np.rint(xy).astype(np.int64)
    inside = (ij[:, 0] >= half) & (ij[:, 0] < w - half) & (ij[:, 1] >= half) & (ij[:, 1] < h - half)
    values = np.full((len(xy), 3), np.nan, np.float64)
    values[inside] = blurred[ij[inside, 1], ij[inside, 0]]
    return values, inside


@dataclass(frozen=True, eq=False)
class ColourJob:
    """Images to sample, with their observations' pixel positions (plain, picklable values: it may run on a
    Dask worker)."""

    paths: tuple[Path, ...]
    xy: tuple[np.ndarray, ...]
    """Per image, the (M_k,2) observation positions."""
    patch_px: int
    linear: bool


def sample_colours(job: ColourJob) -> list[np.ndarray]:
    """Per image of ``job``, the normalised patch-mean colour (M_k,3) of its observations (NaN outside)."""
    return [normalise(patch_means(read_rgb(path, job.linear), xy, job.patch_px)[0])
            for path, xy in zip(job.paths, job.xy, strict=True)]


def observation_colours(tracks, folder: str | Path, patch_px: int = 5, linear: bool = True,
                        progress: bool = False, scheduler=None, chunk_size: int = 16) -> np.ndarray:
    """Normalised patch-mean colour (M,3) of every observation of ``tracks`` in the images of
    ``folder`` (same file names as the SfM images); NaN where the patch leaves the image.

    ``scheduler``: empty or None samples here, image by image; a Dask scheduler address or
    ``distributed.Client`` samples ``chunk_size`` images per task on the cluster (:mod:`watergan.parallel`;
    the images must be on a file system the workers share). The values are the same either way."""
    from watergan.parallel import chunks, is_distributed, map_tasks, rows_by_label, shared_path

    folder = Path(folder)
    out = np.full((len(tracks.obs_xy), 3), np.nan)
    images = np.unique(tracks.obs_image)
    located = [frame_file(folder, str(tracks.image_names[k])) for k in images]
    missing = [path.name for path in located if not path.is_file()]
    if missing:
        raise UserInputError(f"{folder} lacks {len(missing)} of the SfM images (e.g. {missing[0]}): "
                             f"every folder must hold the same frames as the images SfM ran on")
    if patch_px < 1 or patch_px % 2 == 0:  # before any work is sent
        raise UserInputError(f"patch size must be an odd number of pixels >= 1, got {patch_px}")
    distributed = is_distributed(scheduler)
    rows = rows_by_label(tracks.obs_image, images)
    paths = [shared_path(path) if distributed else path for path in located]
    parts = chunks(list(range(len(images))), chunk_size if distributed else 1)
    jobs = [ColourJob(tuple(paths[i] for i in part), tuple(tracks.obs_xy[rows[i]] for i in part), patch_px, linear)
            for part in parts]
    results = map_tasks(sample_colours, jobs, scheduler, desc=f"colours {folder.name}",
                        progress=progress, unit="task" if distributed else "image")
    for part, values in zip(parts, results, strict=True):
        for i, v in zip(part, values, strict=True):
            out[rows[i]] = v
    return out


@dataclass
class ConsistencyScore:
    variance: list[float]
    """Mean over points of the per-channel variance of the normalised colour across views (R, G, B)."""
    mean_variance: float
    """Mean of the three channels."""


@dataclass
class ConsistencyResult:
    scores: dict[str, ConsistencyScore]
    """Per image folder (by the name given)."""
    n_points: int
    """Points with at least ``min_views`` views valid in every folder."""
    n_observations: int
    """Observations of those points used."""
    patch_px: int
    """Side of the sampled patch, pixels."""
    min_views: int
    linear: bool


def consistency(tracks, folders: dict[str, str | Path], patch_px: int = 5, min_views: int = 3,
                linear: bool = True, progress: bool = False, scheduler=None,
                colours: dict[str, np.ndarray] | None = None) -> ConsistencyResult:
    """Colour consistency of the tracks' points in each folder (see the module docstring). The colours are
    sampled with :func:`observation_colours` (on ``scheduler`` when given), unless ``colours`` holds them
    already (folder name -> (M,3), sampled with the same ``patch_px`` and ``linear``)."""
    if not folders:
        raise UserInputError("give at least one image folder to measure")
    given = colours or {}
    colours = {name: given[name] if name in given else
               observation_colours(tracks, path, patch_px, linear, progress, scheduler)
               for name, path in folders.items()}
    valid = np.logical_and.reduce([np.isfinite(c).all(1) for c in colours.values()])
    counts = np.bincount(tracks.obs_point[valid], minlength=len(tracks.xyz))
    use = valid & (counts[tracks.obs_point] >= min_views)
    n_points = int((counts >= min_views).sum())
    if n_points == 0:
        raise UserInputError(f"no 3D point has {min_views} valid views: lower --min-views or use a smaller patch")
    point = tracks.obs_point[use]
    scores = {}
    for name, c in colours.items():
        c = c[use]
        n = np.bincount(point, minlength=len(tracks.xyz)).astype(float)
        keep = n >= min_views
        variance = []
        for ch in range(3):
            s1 = np.bincount(point, c[:, ch], minlength=len(n))
            s2 = np.bincount(point, c[:, ch] ** 2, minlength=len(n))
            var = np.maximum(s2[keep] / n[keep] - (s1[keep] / n[keep]) ** 2, 0.0)
            variance.append(float(var.mean()))
        scores[name] = ConsistencyScore(variance=variance, mean_variance=float(np.mean(variance)))
    return ConsistencyResult(scores=scores, n_points=n_points, n_observations=int(use.sum()), patch_px=patch_px,
                             min_views=min_views, linear=linear)


@dataclass(frozen=True)
class Board:
    """A colour board: patch names, true colours and, per image, the patch quads in pixels."""

    names: list[str]
    true_linear_rgb: np.ndarray
    """(P,3) true linear RGB of each patch."""
    quads: dict[str, np.ndarray]
    """Image file name -> (P,4,2) patch corners in pixels (OpenCV convention); NaN rows: not visible."""


def project_board(names: list[str], corners_world: np.ndarray, true_linear_rgb: np.ndarray,
                  image_names: list[str], world_from_cam: np.ndarray, K: np.ndarray, width: int, height: int,
                  margin_px: float = 2.0) -> Board:
    """Board quads by projecting world corners (P,4,3): p_c = R^T (p_w - t), u = K p_c / z. A patch
    counts as visible in an image when all four corners are in front and inside by ``margin_px``."""
    corners_world = np.asarray(corners_world, float)
    quads = {}
    for name, pose in zip(image_names, world_from_cam, strict=True):
        if not np.isfinite(pose).all():
            continue
        pc = (corners_world - pose[:3, 3]) @ pose[:3, :3]
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([K[0, 0] * pc[..., 0] / z + K[0, 2], K[1, 1] * pc[..., 1] / z + K[1, 2]], -1)
        ok = (z > 0).all(1) & (uv[..., 0] >= margin_px).all(1) & (uv[..., 0] <= width - 1 - margin_px).all(1) \
            & (uv[..., 1] >= margin_px).all(1) & (uv[..., 1] <= height - 1 - margin_px).all(1)
        if ok.any():
            uv[~ok] = np.nan
            quads[name] = uv
    return Board(names=list(names), true_linear_rgb=np.asarray(true_linear_rgb, float), quads=quads)


def load_board_json(path: str | Path) -> Board:
    """A user's board file: ``{"patches": [{"name", "linear_rgb" | "srgb"}...], "images": {file name:
    [[[x, y] x 4] per patch, or null]}}`` with corners in pixels (OpenCV convention)."""
    data = read_json(path, "board file")
    try:
        patches = data["patches"]
        names = [p["name"] for p in patches]
        colours = []
        for p in patches:
            if "linear_rgb" in p:
                colours.append(p["linear_rgb"])
            else:
                v = np.asarray(p["srgb"], float)
                colours.append(srgb_to_linear(v))
        quads = {name: np.array([q if q is not None else np.full((4, 2), np.nan) for q in per], float)
                 for name, per in data["images"].items()}
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UserInputError(f"board file {path} must have 'patches' (name, linear_rgb or srgb) and 'images' "
                             f"(file name -> per patch 4 pixel corners): {exc}") from exc
    return Board(names=names, true_linear_rgb=np.array(colours, float), quads=quads)


def board_for_images(board: Board, images: list[str], where: str) -> Board:
    """``board`` with its frames (the board file's ``images`` keys) named as the survey's ``images`` where only the
    suffix differs (a board marked on the JPEG originals of a PNG survey, or the simulator's truth of a survey
    converted to JPEG or TIFF). Refuses a board whose frames name none of the images: it would take part with no
    rows. Frames that match no image are named on stderr and left out."""
    import sys

    by_stem = {Path(name).stem: name for name in images}
    quads = {(name if name in images else by_stem.get(Path(name).stem, name)): q for name, q in board.quads.items()}
    marked = [name for name, q in quads.items() if np.isfinite(q).any()]
    matched = [name for name in marked if name in by_stem.values()]
    if marked and not matched:
        raise UserInputError(f"board file {where}: none of its {len(marked)} frames is an image of the survey (e.g. "
                             f"{marked[0]!r}; the survey's are like {images[0]!r}): its 'images' keys must be the "
                             f"survey's file names")
    if len(matched) < len(marked):
        print(f"board file {where}: {len(marked) - len(matched)} of its frames are not images of the survey; "
              f"they are left out", file=sys.stderr)
    return Board(names=board.names, true_linear_rgb=board.true_linear_rgb,
                 quads={name: q for name, q in quads.items() if name in matched})


@dataclass
class PatchAccuracy:
    name: str
    distance: float
    """Mean over views of |n(measured) - n(true)|."""
    ciede2000: float
    """Mean over views of CIEDE2000 (exposure-matched per view)."""
    n_views: int


@dataclass
class BoardResult:
    patches: list[PatchAccuracy]
    mean_distance: float
    """Mean over patches seen at least once."""
    mean_ciede2000: float
    n_images: int
    """Images in which at least one patch was measured."""
    inset: float


def _linear_to_lab(rgb: np.ndarray) -> np.ndarray:
    import colour

    xyz = colour.RGB_to_XYZ(rgb, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
    return colour.XYZ_to_Lab(xyz, colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])


def board_accuracy(folder: str | Path, board: Board, inset: float = 0.2, min_pixels: int = 9,
                   linear: bool = True) -> BoardResult:
    """Per-patch accuracy of the images in ``folder`` against the board's true colours."""
    import colour
    import cv2

    folder = Path(folder)
    n_patches = len(board.names)
    dist = [[] for _ in range(n_patches)]
    de = [[] for _ in range(n_patches)]
    n_images = 0
    for name, quads in sorted(board.quads.items()):
        path = frame_file(folder, name)
        if not path.is_file():
            continue
        image = read_rgb(path, linear)
        measured = np.full((n_patches, 3), np.nan)
        for p, quad in enumerate(quads):
            if not np.isfinite(quad).all():
                continue
            centre = quad.mean(0)
            shrunk = centre + (1 - inset) * (quad - centre)
            mask = np.zeros(image.shape[:2], np.uint8)
            cv2.fillConvexPoly(mask, np.rint(shrunk * 16).astype(np.int32), 1, shift=4)
            if mask.sum() >= min_pixels:
                measured[p] = image[mask.astype(bool)].mean(0)
        seen = np.isfinite(measured).all(1)
        if not seen.any():
            continue
        n_images += 1
        m, t = measured[seen], board.true_linear_rgb[seen]
        k = float((m * t).sum() / max((m * m).sum(), 1e-12))
        delta = colour.delta_E(_linear_to_lab(np.clip(k * m, 0, None)), _linear_to_lab(t), method="CIE 2000")
        distance = np.linalg.norm(normalise(m) - normalise(t), axis=1)
        for j, p in enumerate(np.flatnonzero(seen)):
            dist[p].append(float(distance[j]))
            de[p].append(float(np.atleast_1d(delta)[j]))
    if n_images == 0:
        raise UserInputError(f"no board patch is visible in the images of {folder}")
    patches = [PatchAccuracy(name=board.names[p], distance=float(np.mean(dist[p])) if dist[p] else float("nan"),
                             ciede2000=float(np.mean(de[p])) if de[p] else float("nan"), n_views=len(dist[p]))
               for p in range(n_patches)]
    seen = [p for p in patches if p.n_views]
    return BoardResult(patches=patches, mean_distance=float(np.mean([p.distance for p in seen])),
                       mean_ciede2000=float(np.mean([p.ciede2000 for p in seen])), n_images=n_images, inset=inset)


def truth_board(survey_dir: str | Path) -> Board:
    """The simulated survey's board projected with its true poses and intrinsics (evaluation only)."""
    survey_dir = Path(survey_dir)
    path = survey_dir / "truth" / "board.json"
    if not path.is_file():
        raise UserInputError(f"no board truth at {path}: give a board file with pixel corners instead")
    board = json.loads(path.read_text())
    poses = json.loads((survey_dir / "truth" / "poses.json").read_text())["frames"]
    cam = json.loads((survey_dir / "camera.json").read_text())
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    patches = board["patches"]
    if not patches:
        raise UserInputError(f"the survey in {survey_dir} has no colour board")
    return project_board([p["name"] for p in patches], [p["corners_world"] for p in patches],
                         [p["linear_rgb"] for p in patches], [f["name"] for f in poses],
                         np.array([f["world_from_cam"] for f in poses]), K, int(cam["width"]), int(cam["height"]))


@dataclass(frozen=True)
class ColourEvalConfig:
    """Consistency (and board accuracy) of one or more image folders on the SfM points."""

    folders: tuple[str, ...]
    """Image folders as NAME=PATH (e.g. raw=survey/images, inair=survey/truth/inair)."""
    patch_px: int = 5
    """Side of the square patch averaged at each observation, pixels (odd)."""
    min_views: int = 3
    """Points seen in fewer valid views are left out."""
    linear: bool = True
    """Measure on linear RGB (sRGB images decoded) rather than the encoded values."""
    board_json: str = ""
    """A board file with pixel corners (see load_board_json); empty: none."""
    truth_dir: str = ""
    """A simulated survey whose truth board is projected with the true poses; empty: none."""
    board_inset: float = 0.2
    """Fraction by which each board patch is shrunk towards its centre before averaging."""
    scheduler: str = field(default="", metadata={"hash": False})
    """A Dask scheduler address (tcp://HOST:8786) to sample the colours on its workers; empty: here.
    The workers need a shared file system. The numbers are the same either way."""


@dataclass
class ColourEvalResult:
    consistency: ConsistencyResult
    board: dict[str, BoardResult] = field(default_factory=dict)
    """Board accuracy per folder (when a board was given)."""
    table: str = ""
    """Path of colour.json."""


def parse_folders(items: tuple[str, ...] | list[str]) -> dict[str, str]:
    """NAME=PATH items as a dict (a bare PATH is named after its folder)."""
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).name, item
        if not Path(path).is_dir():
            raise UserInputError(f"image folder {path} (for '{name}') does not exist")
        out[name] = path
    return out
