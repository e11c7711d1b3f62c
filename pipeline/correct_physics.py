"""The physics correction of a folder of frames: the water's estimate inverted at each pixel's range (the correct
stage's ``physics/``, :func:`correct_physics_folder`). A function of paths (:class:`PhysicsInputs`); the correct stage
finds them in the workspace (:func:`pipeline.correct.physics_inputs`)."""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from eval.tracks import Tracks
from watergan.correction_range import (
    FAR_MAX_GAIN,
    FAR_RANGE_PCT,
    FILL_PX,
    CorrectMode,
    RangeFrom,
    cap_gain,
    corrected_name,
    fill_range,
    monocular_range,
    survey_far_range_m,
)
from watergan.data import DataError, atomic_write_bytes, read_nav_altitudes, read_nav_down
from watergan.formation import Stack
from watergan.formation import get as get_effect
from watergan.formation.inverse import SIGNAL_FLOOR, frame_affines, linearise_image, needs_normals
from watergan.io import (
    encode_image,
    levels_bits,
    output_bits,
    read_millimetres,
    read_scene_mask,
    read_stored,
    srgb_levels,
    stored_as,
)
from watergan.nets.restorer import WaterFields
from watergan.nets.site_depth import SiteDepthNet
from watergan.parallel import cpu_lanes, keep_freed_memory
from watergan.train_site_depth import load_site_depth

from .range import correction_normals, water_frame


@dataclass(frozen=True)
class PhysicsInputs:
    """What the physics correction of a folder reads (:func:`correct_physics_folder`)."""

    images: Path
    """The frames, named as in ``tracks`` (a navigation file ``survey.json`` beside it for monocular mode)."""
    tracks: Path
    """The sfm stage's tracks (:class:`eval.tracks.Tracks`): the frames' names, intrinsics and poses."""
    stack: list[dict]
    """The water's estimate: its stack's configuration (:meth:`watergan.formation.Stack.from_config`)."""
    normal_smooth_px: float
    """The smoothing of the dense range's normals (the range stage's: :func:`pipeline.range.correction_normals`)."""
    range_dir: Path
    """Each frame's range map ``<stem>.png`` (16-bit millimetres, 0 = none: the range stage's)."""
    depth_dir: Path
    """Each frame's dense depth (the dense stage's), for the normals of a stack that reads them."""
    scene_mask: Path | None = None
    """The survey's scene mask (:func:`watergan.io.write_scene_mask`; None: every pixel is the scene)."""
    site_depth_dir: Path | None = None
    """The folder of a site depth net (the restorer stage's), for monocular mode; None: none."""


@dataclass
class PhysicsResult:
    """What :func:`correct_physics_folder` did."""

    filled_fraction: float
    """Mean over the frames of the share of the scene's pixels whose range was interpolated from their neighbours."""
    far_fraction: float
    """Mean over the frames of the share of the scene's pixels corrected at the survey's far range."""
    far_range_m: float
    """The survey's far range (:func:`survey_far_range_m`; NaN in monocular mode, where every pixel has a range)."""
    seconds: float
    """Wall time, files included."""
    range_source: str
    """"range maps" (the range stage's), "flat seafloor" or "site depth net" (monocular: :func:`monocular_range`)."""


def correct_physics_folder(inputs: PhysicsInputs, out: Path, progress: bool = True, image_format: str = "input",
                           mode: str = CorrectMode.rgbd, fill_px: float = FILL_PX, far_range_pct: float = FAR_RANGE_PCT,
                           far_max_gain: float = FAR_MAX_GAIN) -> PhysicsResult:
    """Every frame the tracks list through the inverse of the water's estimate; writes ``out/images/<name>`` (sRGB,
    the input's bit depth, in ``image_format``: :func:`watergan.correction_range.corrected_name`; pixels outside the
    scene mask: the raw levels), ``out/mask/<stem>.png`` (255: corrected at its measured range; 0: range filled, or
    not the scene) and ``out/range_from/<stem>.png`` (each pixel's :class:`RangeFrom`).

    Each pixel's range (:func:`frame_ranges`): ``mode`` rgb-d (and auto), the range maps, a pixel without range
    ranged by :func:`fill_range` (small holes interpolated within ``fill_px``, larger ones at the survey's far range,
    the ``far_range_pct`` percentile of its measured ranges, with the gain held at ``far_max_gain``:
    :func:`cap_gain`); monocular, for frames without range, a flat seafloor's at the frame's navigation altitude and
    attitude (``survey.json`` beside ``inputs.images``), times the site depth net's factor where
    ``inputs.site_depth_dir`` holds one that beat the flat seafloor (:func:`monocular_range`). A stack that reads
    surface normals takes :func:`pipeline.range.correction_normals` (in monocular mode those of the range used).
    Pixels outside the scene count in no share.

    The frames stream through :func:`watergan.parallel.cpu_lanes` threads, each reading, correcting and writing
    one frame at a time on one torch thread, so memory does not grow with the survey (:class:`FrameInverse`)."""
    from watergan.device import single_torch_thread
    from watergan.io import write_png

    began = time.perf_counter()
    keep_freed_memory()
    tracks = Tracks.load(inputs.tracks)
    scene = read_scene_mask(inputs.scene_mask)
    K = np.asarray(tracks.K, float)
    names = [str(n) for n in tracks.image_names]
    monocular = mode == CorrectMode.monocular
    inverse = FrameInverse(inputs, tracks, K, monocular, far_max_gain)
    ranges = frame_ranges(inputs, names, K, scene, monocular, fill_px, far_range_pct)

    def correct_frame(k: int) -> tuple[float, float]:
        name = names[k]
        levels = read_stored(inputs.images / name)
        r, source = ranges(name, levels)
        corrected = inverse(k, levels, r, source == RangeFrom.far)
        write_corrected(out / "images" / corrected_name(name, image_format), corrected, levels, scene)
        stem = Path(name).stem
        write_png(out / "mask" / f"{stem}.png", np.where(source == RangeFrom.measured, 255, 0).astype(np.uint8))
        write_png(out / "range_from" / f"{stem}.png", source)
        in_scene = max(int(np.count_nonzero(source != RangeFrom.not_scene)), 1)
        return (np.count_nonzero(source == RangeFrom.neighbours) / in_scene,
                np.count_nonzero(source == RangeFrom.far) / in_scene)

    lanes = cpu_lanes()
    with single_torch_thread(), ThreadPoolExecutor(lanes) as pool:
        shares = list(tqdm(pool.map(correct_frame, range(len(names))), total=len(names),
                           desc="physics correction", unit="frame", disable=not progress))
    filled, far = np.mean(shares, axis=0) if shares else (0.0, 0.0)
    return PhysicsResult(float(filled), float(far), ranges.far_range_m, time.perf_counter() - began, ranges.source)


@dataclass(frozen=True, eq=False)
class FrameRanges:
    """Each frame's range for the physics correction, every scene pixel ranged, and where each pixel's came from
    (:func:`fill_range`): from its range map, or in monocular mode (``altitudes`` given) a flat seafloor's at its
    altitude (:func:`monocular_range`)."""

    range_dir: Path
    far_range_m: float
    """The survey's far range (NaN in monocular mode)."""
    fill_px: float
    scene: np.ndarray | None
    K: np.ndarray
    source: str
    """"range maps", "flat seafloor" or "site depth net"."""
    altitudes: dict[str, float] | None = None
    """Monocular mode: each frame's navigation altitude (metres, by name)."""
    downs: dict[str, np.ndarray] | None = None
    """Monocular mode: each frame's "down" in the camera frame, where the navigation gives it."""
    site: SiteDepthNet | None = None

    def __call__(self, name: str, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The range of frame ``name`` (``levels``: its stored values, decoded once) and each pixel's source."""
        if self.altitudes is not None:  # the site depth net reads the stored values
            stored = stored_as(levels, "linear", np.float32) if self.site is not None else \
                np.empty((*levels.shape[:2], 3), np.float32)
            r = monocular_range(stored, self.altitudes[name], self.K, self.downs[name] if self.downs else None,
                                self.site)
        else:
            r = read_millimetres(self.range_dir / f"{Path(name).stem}.png") / 1000.0  # metres, 0 = none
        return fill_range(r, self.far_range_m, self.fill_px, self.scene, self.K)


def frame_ranges(inputs: PhysicsInputs, names: list[str], K: np.ndarray, scene: np.ndarray | None, monocular: bool,
                 fill_px: float, far_range_pct: float) -> FrameRanges:
    """The frames' ranges (:class:`FrameRanges`) with what they need checked first: in monocular mode a navigation
    altitude for every frame (``survey.json`` beside the images) and the site depth net of ``inputs.site_depth_dir``
    where it holds one; else every frame's range map, and the survey's far range (:func:`survey_far_range_m`)."""
    range_dir = inputs.range_dir
    if not monocular:
        lacking = [n for n in names if not (range_dir / f"{Path(n).stem}.png").is_file()]
        if lacking:
            raise DataError(f"the range stage wrote no range map for {len(lacking)} of the {len(names)} frames (e.g. "
                            f"{lacking[0]} in {range_dir}): rerun it (`watergan range --workspace WS --force`)")
        far_range_m = survey_far_range_m([range_dir / f"{Path(n).stem}.png" for n in names], far_range_pct, scene)
        return FrameRanges(range_dir, far_range_m, fill_px, scene, K, "range maps")
    nav = inputs.images.parent / "survey.json"
    if not nav.is_file():
        raise DataError(f"the physics correction in monocular mode takes each frame's range from a flat seafloor "
                        f"at its altitude, and there is no navigation file {nav} with nav_altitude_m per frame: "
                        f"add one, or correct with the range stage's maps (--mode rgb-d)")
    altitudes, downs = read_nav_altitudes(nav, names), read_nav_down(nav, names)
    lacking = [n for n in names if n not in altitudes]
    if lacking:
        raise DataError(f"the navigation {nav} has no altitude for {len(lacking)} of the {len(names)} frames "
                        f"(e.g. {lacking[0]}): the monocular physics correction needs one per frame")
    site = load_site_depth(inputs.site_depth_dir)[0] if inputs.site_depth_dir is not None else None
    return FrameRanges(range_dir, math.nan, fill_px, scene, K, "site depth net" if site is not None else
                       "flat seafloor", altitudes, downs, site)


class FrameInverse:
    """One frame through the inverse of the water's estimate. A stack that does not read surface normals is inverted
    with the interpolated fields of :class:`watergan.nets.restorer.WaterFields` in float32 (:func:`invert_with_fields`)
    of its effects without a value per frame, each frame's image first freed of the others by the affine map they
    apply to it (:func:`watergan.formation.inverse.frame_affines`: a gain or exposure per frame, measured on a probe
    once per image size); otherwise (or for a frame whose effects are no such map) with each frame's exact fields
    (:func:`invert_exact`, float64). A stack ending in an output map (a camera's tone curve) has each image
    linearised by its inverse first (:func:`watergan.formation.inverse.linearise_image`). Called from several
    threads."""

    def __init__(self, inputs: PhysicsInputs, tracks: Tracks, K: np.ndarray, monocular: bool, max_gain: float):
        self.inputs, self.tracks, self.K, self.max_gain = inputs, tracks, K, max_gain
        self.stack = Stack.from_config(inputs.stack)
        self.with_normals = needs_normals(self.stack)
        base = [e for e in inputs.stack if not get_effect(e["name"]).varies_by_frame()]
        self.per_frame = Stack.from_config(base).output_map()[0] if len(base) < len(inputs.stack) else None
        self.fields = None if self.with_normals else WaterFields(base)
        # the dense range only feeds the normals (the correction's range is the range stage's map)
        self.depth_dir = inputs.depth_dir if self.with_normals and not monocular else None
        self.affines: dict[tuple[int, int], list] = {}  # per image size, every frame's affine map (frame_affines)
        self.affines_lock = threading.Lock()

    def frame_map(self, k: int, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
        """Frame ``k``'s affine map at image size ``size_hw`` (None: its effects are no such map)."""
        with self.affines_lock:
            if size_hw not in self.affines:
                frames = range(len(self.tracks.image_names))
                self.affines[size_hw] = frame_affines(self.stack.output_map()[0], self.per_frame, frames, self.K,
                                                      *size_hw)
        return self.affines[size_hw][k]

    def __call__(self, k: int, levels: np.ndarray, range_m: np.ndarray, far: np.ndarray) -> np.ndarray:
        """Frame ``k`` (``levels``: its stored values) corrected at ``range_m`` ((H,W) metres), the gain held where
        ``far``: (H,W,3) float32 linear, unclipped."""
        corrected = None
        if self.fields is not None:
            image = linearise_image(stored_as(levels, "srgb", np.float32), self.stack).astype(np.float32)
            affine = None if self.per_frame is None else self.frame_map(k, image.shape[:2])
            if affine is not None:  # the frame's own gain or exposure taken off first
                s, t = affine
                image = (image - t.astype(np.float32)) / s.astype(np.float32)
            if self.per_frame is None or affine is not None:
                corrected, _ = invert_with_fields(image, range_m, self.fields, self.K, far, self.max_gain)
        if corrected is None:  # the stack reads normals, or the frame's effects are no affine map of its image
            f = water_frame(self.tracks, k, self.inputs.images, self.depth_dir)
            normals = correction_normals(f, range_m, self.K, self.inputs.normal_smooth_px) if self.with_normals \
                else None
            corrected = invert_exact(f.image, range_m, self.stack, self.K, k, normals, far, self.max_gain)
        return corrected


def write_corrected(path: Path, linear_rgb: np.ndarray, levels: np.ndarray, scene: np.ndarray | None) -> None:
    """A corrected frame (linear (H,W,3), clipped to 0..1) as ``path`` in its format at the bits of the input's
    ``levels`` (:func:`watergan.io.read_stored`; 8 for a JPEG), atomically; pixels outside ``scene`` ((H,W) bool,
    None: every pixel is the scene) take the input's levels as they are (a 16-bit input's rounded to 8 bits for a
    JPEG)."""
    rgb = srgb_levels(linear_rgb, output_bits(path, levels_bits(levels)))
    if scene is not None:
        raw = levels[..., ::-1]
        rgb[~scene] = raw[~scene] if raw.dtype == rgb.dtype else np.rint(raw[~scene] / 257.0).astype(rgb.dtype)
    atomic_write_bytes(path, encode_image(path.suffix, rgb))


def invert_with_fields(image: np.ndarray, range_m: np.ndarray, fields: WaterFields, K: np.ndarray | None,
                       capped: np.ndarray | None = None, max_gain: float = FAR_MAX_GAIN
                       ) -> tuple[np.ndarray, np.ndarray]:
    """J = max(exp(g) I + o, s exp(g) I) (:data:`~watergan.formation.inverse.SIGNAL_FLOOR`), the physics inverse
    J = (I - C) / A with the log gain g = -ln A and offset o = -C / A of
    ``fields`` at each pixel's range (holes take the frame's farthest range, which the table covers, then are
    marked), the gain held at ``max_gain`` where ``capped`` ((H,W) bool, None: nowhere; :func:`cap_gain`), as
    :func:`watergan.formation.inverse.correct_physics` returns it: (J (H,W,3) float32 linear, unclipped, NaN where
    the map has no range; valid (H,W) bool). ``image``: (H,W,3) raw linear RGB; ``range_m``: (H,W) metres along the
    ray, NaN or <= 0 = none (:func:`fill_range` ranges every pixel); ``K``: the frames' intrinsics (3x3, None:
    depth = range)."""
    r = np.asarray(range_m, np.float32)
    valid = np.isfinite(r) & (r > 0)
    if not valid.any():
        return np.full(image.shape, np.nan, np.float32), valid
    filled = np.where(valid, r, r[valid].max())  # any range the frame holds: the table need not grow for holes
    intrinsics = None if K is None else (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    with torch.no_grad():
        g_o = fields(torch.from_numpy(filled)[None, None], intrinsics)[0]
        if capped is not None and capped.any():
            g_o = cap_gain(g_o, torch.from_numpy(capped)[None], max_gain)
        rgb = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)
        gained = rgb * g_o[:3].exp()
        out = torch.maximum(gained + g_o[3:], SIGNAL_FLOOR * gained).permute(1, 2, 0).contiguous().numpy()
    out[~valid] = np.nan
    return out, valid


def invert_exact(image: np.ndarray, range_m: np.ndarray, stack: Stack, K: np.ndarray, frame_index: int,
                 normals_cam: np.ndarray | None, capped: np.ndarray, max_gain: float = FAR_MAX_GAIN) -> np.ndarray:
    """J = max(I - C, s I) / A (:data:`~watergan.formation.inverse.SIGNAL_FLOOR`) with the stack's exact fields A, C at
    each pixel's range
    (:func:`watergan.formation.inverse.inverse_fields`, float64: strobes, a per-frame effect; ``frame_index``: the
    frame's row of the per-frame parameters; ``normals_cam``: (H,W,3) camera-frame normals or None), the gain 1 / A
    held at ``max_gain`` where ``capped`` ((H,W) bool; :func:`cap_gain`): (H,W,3) float32 linear, unclipped, NaN
    where ``range_m`` (H,W metres) has no range. ``image``: (H,W,3) raw linear RGB."""
    from watergan.formation.inverse import inverse_fields

    a, c, valid = inverse_fields(range_m, stack, K, frame_index, normals_cam)
    a, c = a[0].permute(1, 2, 0).numpy(), c[0].permute(1, 2, 0).numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = 1.0 / a
    gain[capped] = np.minimum(gain[capped], max_gain)
    image = linearise_image(image, stack)
    out = np.maximum(image - c, SIGNAL_FLOOR * image) * gain
    out[~valid] = np.nan
    return out.astype(np.float32)
