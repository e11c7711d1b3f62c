"""Correct an image sequence with a trained restorer (``watergan correct``).

Every PNG, JPEG or TIFF directly in ``images_dir`` is corrected at its native size (padded to the
restorer's multiple and cropped back) and written as::

    OUT/images/<name>       corrected colour in the input's format and bit depth, a JPEG's as PNG
                            (``image_format``: or as PNG, TIFF or JPEG, 8 bits, quality 95)
    OUT/depth/<stem>.png    relative depth, 16-bit PNG, value = d_rel * 65535 (0..1 -> 0..65535)
    OUT/depth/<stem>.npy    relative depth, float32 (H,W), 0..1
    OUT/summary.json        counts and the files that could not be read

The restorer works on the stored (sRGB-encoded) values scaled to 0..1, so the output keeps the
input's encoding. A restorer trained with ``altitude`` also takes each image's altitude above the
seafloor (metres), the ``nav_altitude_m`` of a navigation file (:func:`watergan.data.read_nav_altitudes`;
by default the ``survey.json`` beside the images folder); an image without one is an error before any
work. A restorer trained in RGB-D mode (``range_input``) takes each pixel's range in metres, in one of two modes
(``mode``; ``auto``: RGB-D when ``range_dir`` is given, else monocular):

- ``rgb-d``: from ``range_dir/<stem>.png`` (16-bit millimetres, 0 = none, as the water stage writes them; a pixel
  without range takes its neighbours' or the survey's far range, :func:`fill_range`, and a water's gain at the far
  range is held at ``far_max_gain``, :func:`cap_gain`); an image without a range map is an error before any work;
- ``monocular``, for frames without range (a live camera, a survey without stereo overlap): the range of a flat,
  level seafloor at the frame's altitude (:func:`watergan.formation.inverse.flat_floor_range`), from the navigation's
  altitude, its attitude where it gives one (``nav_down_cam``: :func:`watergan.data.read_nav_down`; else a nadir
  camera) and the camera's intrinsics; times the site depth net's factor where the restorer's folder holds one that
  beat the flat seafloor on the survey's held-out frames (:mod:`pipeline.site_depth`; the result's ``range_source``
  and ``range_why`` say which and by how much). The restorer's own depth net cannot stand in: it never saw the site's
  range, and the eval stage's depth table shows it further from the stereo depth than the flat seafloor.

A restorer trained monocular (``--no-range-input``, the paper's) takes the image and its altitude only. A restorer
that starts from a water's inverse (:func:`watergan.nets.restorer.water_fields`) takes the images' intrinsics from
``camera.json`` in the images folder or beside it (a water with lights needs them). Images already corrected (all
three outputs present) are skipped unless ``force``. An unreadable or truncated image is reported and skipped.
Every file is written atomically; the output folder may not be (or contain) the input folder's files. With a scene
mask (``scene_mask``: :func:`watergan.io.write_scene_mask`'s file), pixels that are not the scene are written as they
came (the raw levels, in the output's format).

With ``scheduler`` (a Dask scheduler address, ``tcp://HOST:8786``) the images still to do are sent in
chunks to the cluster's workers (:mod:`watergan.parallel`), each chunk corrected with the model loaded
once on its worker (CUDA when the worker has it) and written to the shared file system; the files are
the ones a local run writes.
"""

from __future__ import annotations

import io
import json
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from watergan.data import (
    IMAGE_SUFFIXES,
    DataError,
    PinholeIntrinsics,
    atomic_write_bytes,
    index_by_stem,
    list_files,
    read_intrinsics,
    read_nav_altitudes,
    read_nav_down,
)
from watergan.device import Device, pick_device
from watergan.formation import Stack
from watergan.formation import get as get_effect
from watergan.formation.inverse import flat_floor_depth, flat_floor_range, frame_affines, needs_normals
from watergan.io import (
    encode_grey16_png,
    encode_image,
    is_jpeg,
    levels_bits,
    output_bits,
    read_millimetres,
    read_scene_mask,
    read_stored,
    srgb_levels,
    stored_as,
)
from watergan.nets.restorer import SIGNAL_FLOOR, WaterFields, restore
from watergan.nets.site_depth import SiteDepthNet
from watergan.train_restorer import load_restorer
from watergan.train_site_depth import load_site_depth

SUMMARY = "summary.json"


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


FILL_PX = 24.0
"""A hole lying everywhere within this many pixels of measured range is interpolated (:func:`fill_range`)."""
FAR_RANGE_PCT = 95.0
"""The survey's far range: this percentile of its measured ranges (:func:`survey_far_range_m`)."""
FAR_MAX_GAIN = 10.0
"""The largest gain a pixel at the far range is corrected with (:func:`cap_gain`)."""


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
               scene: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel's range for the correction, (H,W) float32 metres, and where it came from, (H,W) uint8 of
    :class:`RangeFrom`. A scene pixel with a measured range (finite, > 0) keeps it. A hole (a connected region of scene
    pixels without range, 8-connected) that lies everywhere within ``fill_px`` pixels of measured range takes the
    range interpolated from around it (:func:`harmonic_fill`; a neighbour without range, outside the scene, is given
    its nearest measured pixel's range first); a larger hole (open water, a far wall),
    and every hole of a frame without any measured range, takes ``far_range_m``. Pixels outside ``scene`` ((H,W)
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
    if not np.isfinite(far_range_m) and (source == RangeFrom.far).any():
        raise ValueError("pixels without a measured range near them need the survey's far range, and it is not known")
    return out, source


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


@dataclass
class CorrectResult:
    """What ``correct_folder`` did."""

    out_dir: Path
    corrected: int
    """Images corrected in this run."""
    already_done: int
    """Images skipped because their outputs existed (no ``force``)."""
    failed: list[str] = field(default_factory=list)
    """"path: reason" for each image that could not be read."""
    seconds: float = 0.0
    mode: str = "monocular"
    """"rgb-d" (each pixel's range from its range map) or "monocular" (see the module docstring)."""
    range_source: str = ""
    """Where an RGB-D restorer's range came from: "range maps", "flat seafloor" or "site depth net" (monocular mode:
    the net beside the restorer when it beat the flat seafloor on held-out frames); "" for a monocular restorer."""
    range_why: str = ""
    """Why monocular mode took the site depth net or kept the flat seafloor (the net's record), when one was trained."""


class ImageFormat(StrEnum):
    """The corrected frames' file format: the input's (its bit depth kept; a JPEG's as PNG: compressing a corrected
    frame again puts block artefacts where the correction brightened the signal), or PNG, TIFF (the input's bit
    depth) or JPEG (8 bits, quality ``watergan.io.JPEG_QUALITY``)."""

    input = "input"
    png = "png"
    tiff = "tiff"
    jpeg = "jpeg"


def corrected_name(name: str, image_format: str) -> str:
    """The corrected frame's file name for input ``name``: the same name (a JPEG's stem with .png), or its stem with
    the format's suffix."""
    own = ".png" if is_jpeg(name) else Path(name).suffix
    suffix = {"png": ".png", "tiff": ".tif", "jpeg": ".jpg"}.get(str(image_format), own)
    return f"{Path(name).stem}{suffix}"


def _outputs(out: Path, name: str, image_format: str) -> tuple[Path, Path, Path]:
    stem = Path(name).stem
    return (out / "images" / corrected_name(name, image_format), out / "depth" / f"{stem}.png",
            out / "depth" / f"{stem}.npy")


def _write_image(image_path: Path, rgb: np.ndarray, bits: int) -> None:
    """An (H,W,3) 0..1 array as the corrected frame ``image_path`` (the input's ``bits`` where its format keeps
    them), atomically."""
    top, dtype = (65535.0, np.uint16) if output_bits(image_path, bits) == 16 else (255.0, np.uint8)
    atomic_write_bytes(image_path, encode_image(image_path.suffix, np.rint(rgb * top).astype(dtype)))


def _write(out: Path, name: str, image_format: str, rgb: np.ndarray, depth: np.ndarray, bits: int) -> None:
    """(H,W,3) and (H,W) 0..1 arrays to the three output files of input ``name``, atomically."""
    image_path, depth_png, depth_npy = _outputs(out, name, image_format)
    _write_image(image_path, rgb, bits)
    atomic_write_bytes(depth_png, encode_grey16_png(np.rint(depth * 65535.0).astype(np.uint16)))
    buffer = io.BytesIO()
    np.save(buffer, depth.astype(np.float32))
    atomic_write_bytes(depth_npy, buffer.getvalue())


@dataclass(frozen=True)
class CorrectChunk:
    """One task of ``correct_folder``: images to correct with one loaded model (plain, picklable values)."""

    model_dir: Path
    paths: tuple[Path, ...]
    out_dir: Path
    batch_size: int
    """Images per batch (0: :func:`batch_for` the device)."""
    device: str
    altitude_m: tuple[float, ...] | None = None
    """Per path, the altitude above the seafloor in metres (None: the model does not take it)."""
    range_dir: Path | None = None
    """Folder of each path's range map ``<stem>.png`` (None: no range maps)."""
    camera: PinholeIntrinsics | None = None
    """The images' intrinsics, for a restorer that starts from a water (None: depth = range, no points)."""
    flat_floor: bool = False
    """An RGB-D restorer in monocular mode: each image's range is a flat seafloor's at its altitude (needs
    ``altitude_m`` and ``camera``)."""
    down_cam: tuple[tuple[float, float, float], ...] | None = None
    """Per path, "down" in the camera frame from the navigation's attitude (None: nadir cameras)."""
    image_format: str = "input"
    """The corrected frames' format (:class:`ImageFormat`)."""
    site_depth: bool = False
    """Monocular mode: each image's range is the flat seafloor's times the site depth net's factor (the net in
    ``model_dir``, :mod:`watergan.nets.site_depth`)."""
    far_range_m: float = math.nan
    """The survey's far range (:func:`survey_far_range_m`), for pixels of a range map without range near them."""
    fill_px: float = FILL_PX
    """Holes of a range map within this many pixels of measured range are interpolated (:func:`fill_range`)."""
    far_max_gain: float = FAR_MAX_GAIN
    """The water's gain at pixels given the far range is held at this (:func:`cap_gain`)."""
    scene_mask: Path | None = None
    """The survey's scene mask (:func:`watergan.io.write_scene_mask`): pixels outside it are written raw."""


@dataclass
class ChunkResult:
    corrected: int
    failed: list[str]
    """"path: reason" for each unreadable image."""


IO_THREADS = 2
"""Threads that read the next images while the nets run on a CPU (OpenCV's PNG codecs and file I/O release the GIL,
so they overlap the nets)."""


def io_threads(dev: torch.device) -> int:
    """Threads that read the next images: ``IO_THREADS`` on a CPU, where the lanes take the cores; on CUDA, where
    the nets leave the cores to decoding and encoding, :func:`cuda_lanes` of them."""
    return IO_THREADS if dev.type == "cpu" else cuda_lanes()


def cpu_lanes() -> int:
    """Batches the nets correct at once on a CPU: one per intra-op thread torch would use, each lane running its
    batch on one thread. The restorer's convolutions are narrow (3-16 channels at full resolution) and split poorly
    across threads; whole batches side by side keep every core busy, and a lane whose core is taken by another job
    waits alone instead of stalling the other thread at every layer."""
    return max(1, torch.get_num_threads())


def keep_freed_memory() -> bool:
    """glibc's allocator told to serve blocks of up to 32 MiB from its heap and to keep what is freed (mallopt
    M_MMAP_THRESHOLD and M_TRIM_THRESHOLD), for the rest of the process. By default each frame's full-resolution
    tensors are mapped afresh and unmapped when freed, and every page of every one is faulted in again, which costs
    the correction's element-wise steps more than their arithmetic; the heap then holds what one batch needs
    (benchmarks/RESULTS/restorer.md). False where the C library is not glibc."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(mallopt(m_mmap_threshold, 32 * 2**20)) and bool(mallopt(m_trim_threshold, 2**30))


CPU_BATCH = 1
"""Images per batch of the restorer on a CPU (``batch_size`` 0): each lane's full-resolution passes over one frame stay
in the cache, where a batch of 4 streams through memory (measurements: benchmarks/RESULTS/speed-and-scale.md)."""
CUDA_BATCH = 4
"""Images per batch on CUDA (``batch_size`` 0)."""


def batch_for(dev: torch.device) -> int:
    """The restorer's images per batch when none is given: ``CPU_BATCH`` on a CPU, ``CUDA_BATCH`` on CUDA."""
    return CPU_BATCH if dev.type == "cpu" else CUDA_BATCH


CUDA_LANES = 4
"""The fewest batches in flight on a GPU (:func:`cuda_lanes`)."""


def cuda_lanes() -> int:
    """Batches in flight on a GPU: one on the GPU while the others' outputs are encoded and written (PNG encoding,
    not the nets, bounds a GPU's frames per second), half the machine's cores and at least ``CUDA_LANES``
    (benchmarks/bench_gpu.py sweeps the lanes and readers)."""
    return max(CUDA_LANES, (os.cpu_count() or 1) // 2)


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


def _read_one(chunk: CorrectChunk, k: int, path: Path, site: SiteDepthNet | None = None, linear: bool = False,
              scene: np.ndarray | None = None
              ) -> tuple[np.ndarray, int, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The chunk's k-th image to correct (stored values 0..1, float32), its bit depth, for an RGB-D restorer its
    range (float32 metres: its range map with every pixel ranged (:func:`fill_range`, ``scene`` the scene mask), or a
    flat seafloor's (``chunk.flat_floor``), times the site depth net's factor exp(D) with ``site``), with
    ``linear`` its colours decoded to linear light (float32, from the same decoded levels), and where a range map's
    pixels took the far range, (H,W) bool (else None); a DataError names what is wrong. Runs in the I/O threads, off
    the nets' thread."""
    levels = read_stored(path)
    image, bits = stored_as(levels, "linear", np.float32), levels_bits(levels)
    decoded = stored_as(levels, "srgb", np.float32) if linear else None
    if scene is not None and scene.shape != image.shape[:2]:
        raise DataError(f"image {path} is {image.shape[1]}x{image.shape[0]}, the scene mask {scene.shape[1]}x"
                        f"{scene.shape[0]}")
    range_m = far = None
    if chunk.flat_floor:
        range_m = monocular_range(image, chunk.altitude_m[k], chunk.camera.resized(*image.shape[:2]).K,
                                  chunk.down_cam[k] if chunk.down_cam is not None else None, site)
    elif chunk.range_dir is not None:
        range_path = chunk.range_dir / f"{path.stem}.png"
        range_m = (read_millimetres(range_path) / 1000.0).astype(np.float32)
        if range_m.shape != image.shape[:2]:
            raise DataError(f"range map {range_path} is {range_m.shape[1]}x{range_m.shape[0]}, the image "
                            f"{image.shape[1]}x{image.shape[0]}")
        range_m, source = fill_range(range_m, chunk.far_range_m, chunk.fill_px, scene)
        far = source == RangeFrom.far
        far = far if far.any() else None
    return image, bits, range_m, decoded, far


class Item(NamedTuple):
    """One image to correct."""

    name: str
    image: np.ndarray
    """(H,W,3) stored values 0..1."""
    bits: int
    altitude_m: float
    """0 when not used."""
    range_m: np.ndarray | None
    linear: np.ndarray | None
    """(H,W,3) the colours decoded to linear light, for a restorer that takes them (:func:`restore`)."""
    far: np.ndarray | None
    """(H,W) bool: pixels at the survey's far range (the water's gain held there, :func:`cap_gain`); None: none."""


def correct_chunk(chunk: CorrectChunk, bar: tqdm | None = None, model: torch.nn.Module | None = None) -> ChunkResult:
    """Correct ``chunk.paths`` into ``chunk.out_dir`` (every file written atomically), consecutive images of one
    size ``batch_size`` at a time; the model is loaded here unless given. On a CPU, :func:`cpu_lanes` batches run
    side by side, each on one thread, and write their own outputs; on CUDA :func:`cuda_lanes`. :func:`io_threads`
    threads read the next batches' images meanwhile. ``bar`` (local runs): advanced per image, and unreadable images are
    reported as they come."""
    dev = pick_device(chunk.device)
    keep_freed_memory()
    model = (model if model is not None else load_restorer(chunk.model_dir)).for_inference().to(dev)
    fields = WaterFields(model.water) if model.water is not None else None
    site = load_site_depth(chunk.model_dir)[0].to(dev) if chunk.site_depth else None  # read by the readers
    scene = read_scene_mask(chunk.scene_mask)
    out = chunk.out_dir
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    result = ChunkResult(0, [])
    lanes = cpu_lanes() if dev.type == "cpu" else cuda_lanes()
    batch_size = chunk.batch_size or batch_for(dev)
    # a restorer without skip layers applies its fields to the decoded colours: the readers decode them by table
    linear = not model.colour_net.skip and model.colour_net.head == "affine"

    def stacked(arrays: list[np.ndarray]) -> torch.Tensor:
        return torch.from_numpy(np.stack(arrays).transpose(0, 3, 1, 2)).to(dev)

    def correct_batch(batch: list[Item]) -> int:
        x = stacked([b.image for b in batch])
        altitude = torch.tensor([b.altitude_m for b in batch], device=dev) if model.altitude else None
        range_m = None
        if batch[0].range_m is not None:
            range_m = torch.from_numpy(np.stack([b.range_m for b in batch])[:, None]).to(dev)
        intrinsics = None if chunk.camera is None else chunk.camera.resized(*x.shape[-2:]).as_tuple()
        with torch.no_grad():
            water = fields(range_m, intrinsics) if fields is not None else None
            if water is not None and any(b.far is not None for b in batch):
                far = np.stack([b.far if b.far is not None else np.zeros(b.image.shape[:2], bool) for b in batch])
                water = cap_gain(water, torch.from_numpy(far[:, None]).to(dev), chunk.far_max_gain)
            rgb, depth = restore(model, x, altitude, range_m, intrinsics, water,
                                 stacked([b.linear for b in batch]) if linear else None)
        rgb_np = rgb.cpu().numpy().transpose(0, 2, 3, 1)
        depth_np = depth[:, 0].cpu().numpy()
        for k, b in enumerate(batch):
            if scene is not None:  # not the scene: the stored values as they came
                rgb_np[k][~scene] = b.image[~scene]
            _write(out, b.name, chunk.image_format, rgb_np[k], depth_np[k], b.bits)
        return len(batch)

    running: deque[Future] = deque()

    def collect(keep: int) -> None:
        """Wait for the oldest batches until at most ``keep`` are running (memory stays bounded)."""
        while len(running) > keep:
            done = running.popleft().result()
            result.corrected += done
            if bar is not None:
                bar.update(done)

    threads = torch.get_num_threads()
    if dev.type != "cpu" or lanes > 1:
        torch.set_num_threads(1)  # each lane runs its batch on one thread; on CUDA the readers' small work
    try:
        with ThreadPoolExecutor(io_threads(dev)) as reader, ThreadPoolExecutor(lanes) as nets:
            batch: list[Item] = []

            def submit() -> None:
                collect(lanes)
                running.append(nets.submit(correct_batch, list(batch)))
                batch.clear()

            for k, path, read in _read_ahead(reader, chunk, 2 * lanes * batch_size, site, linear, scene):
                try:
                    image, bits, range_m, decoded, far = read.result()
                except DataError as exc:
                    result.failed.append(str(exc))
                    if bar is not None:
                        tqdm.write(f"correct: skipped {exc}", file=sys.stderr)
                        bar.update(1)
                    continue
                if batch and batch[0].image.shape != image.shape:
                    submit()
                batch.append(Item(path.name, image, bits,
                                  chunk.altitude_m[k] if chunk.altitude_m is not None else 0.0, range_m, decoded,
                                  far))
                if len(batch) == batch_size:
                    submit()
            if batch:
                submit()
            collect(0)
    finally:
        torch.set_num_threads(threads)
    return result


def _read_ahead(pool: ThreadPoolExecutor, chunk: CorrectChunk, ahead: int, site: SiteDepthNet | None = None,
                linear: bool = False, scene: np.ndarray | None = None) -> Iterator[tuple[int, Path, Future]]:
    """(index, path, the future of :func:`_read_one`) of each path in order, with up to ``ahead`` reads
    submitted before the one yielded."""
    reads: deque[tuple[int, Path, Future]] = deque()
    for k, path in enumerate(chunk.paths):
        reads.append((k, path, pool.submit(_read_one, chunk, k, path, site, linear, scene)))
        if len(reads) > ahead:
            yield reads.popleft()
    yield from reads


class CorrectMode(StrEnum):
    """How an RGB-D restorer gets each pixel's range (see the module docstring)."""

    auto = "auto"
    rgbd = "rgb-d"
    monocular = "monocular"


def correct_folder(model_dir: str | Path, images_dir: str | Path, out_dir: str | Path, force: bool = False,
                   batch_size: int = 0, device: str = "auto", progress: bool = True, scheduler=None,
                   chunk_size: int = 64, navigation: str | Path | None = None,
                   range_dir: str | Path | None = None, mode: str = "auto",
                   image_format: str = "input", scene_mask: str | Path | None = None, far_range_m: float | None = None,
                   fill_px: float = FILL_PX, far_max_gain: float = FAR_MAX_GAIN) -> CorrectResult:
    """Correct every image of ``images_dir`` into ``out_dir`` (see the module docstring). Consecutive
    images of the same size are corrected together, ``batch_size`` at a time (0: :func:`batch_for` the device).

    ``scheduler``: empty or None corrects here, in one pass with the model loaded once; a Dask scheduler
    address (``tcp://HOST:8786``) or ``distributed.Client`` sends chunks of ``chunk_size`` images (rounded up
    to a multiple of the batch) to the cluster's workers, each loading the model once per chunk and
    writing to ``out_dir`` on the shared file system (:mod:`watergan.parallel`). Same files either way.

    ``navigation``: the survey file with each image's ``nav_altitude_m`` (None: ``survey.json`` beside
    ``images_dir``), read for a restorer trained with ``altitude`` and in monocular mode. ``range_dir``: the folder
    of each image's range map, for a restorer trained with ``range_input`` in RGB-D mode. ``mode``: a
    :class:`CorrectMode` (auto: RGB-D when ``range_dir`` is given). ``image_format``: an :class:`ImageFormat`.
    ``scene_mask``: the survey's scene mask file (None: every pixel is the scene). A range map's pixels without range
    are ranged by :func:`fill_range` (``fill_px``; ``far_range_m``, None: :func:`survey_far_range_m` of the images'
    range maps), the water's gain held at ``far_max_gain`` where they take the far range (:func:`cap_gain`)."""
    from watergan.parallel import chunks, is_distributed, map_tasks, shared_path

    began = time.perf_counter()
    images_dir, out = Path(images_dir), Path(out_dir)
    if not images_dir.is_dir():
        raise DataError(f"image folder {images_dir} does not exist")
    if batch_size < 0:
        raise DataError(f"batch_size must be at least 1 (or 0: by device), got {batch_size}")
    if mode not in tuple(CorrectMode):
        raise DataError(f"mode must be one of {', '.join(CorrectMode)}, not '{mode}'")
    if image_format not in tuple(ImageFormat):
        raise DataError(f"image_format must be one of {', '.join(ImageFormat)}, not '{image_format}'")
    targets = {p.resolve() for p in (out, out / "images", out / "depth")}
    if images_dir.resolve() in targets:
        raise DataError(f"the output folder {out} would write into the input folder {images_dir}: choose another")
    files = list_files(images_dir, IMAGE_SUFFIXES)
    if not files:
        raise DataError(f"image folder {images_dir} holds no PNG, JPEG or TIFF images")
    index_by_stem(files, "image")  # refuses two inputs with one stem: the depth outputs are <stem>.png
    distributed = is_distributed(scheduler)
    if not distributed or device not in ("auto", "cpu", "cuda"):
        pick_device(device)  # a bad device name fails here (a cluster's workers may have CUDA where this has none)
    model = load_restorer(model_dir)  # a missing or torn model fails here, before any work is sent
    if not model.range_input and mode == CorrectMode.rgbd:
        raise DataError(f"the restorer in {model_dir} was trained monocular (no range input): it has no RGB-D mode; "
                        f"correct with --mode monocular, or train one with --range-input")
    if mode == CorrectMode.auto:
        mode = CorrectMode.rgbd if (model.range_input and range_dir) else CorrectMode.monocular
    flat_floor = model.range_input and mode == CorrectMode.monocular
    camera = read_intrinsics(images_dir) if (model.water is not None or flat_floor) else None
    if flat_floor and camera is None:
        raise DataError(f"the restorer in {model_dir} takes each pixel's range; without range maps (monocular mode) "
                        f"it takes a flat seafloor's at each frame's altitude, which needs the camera's intrinsics: "
                        f"put the survey's camera.json in {images_dir} or beside it, or give --range-dir")
    downs = None
    if model.altitude or flat_floor:
        nav = Path(navigation) if navigation else images_dir.parent / "survey.json"
        needs = "takes each image's altitude above the seafloor" if model.altitude else \
            "takes each pixel's range, and without range maps (monocular mode) a flat seafloor's at the altitude"
        if not nav.is_file():
            raise DataError(f"the restorer in {model_dir} {needs}, and there is no navigation file {nav}: give one "
                            f"with nav_altitude_m per frame (--navigation)"
                            + (", or give each frame's range map (--range-dir)" if flat_floor else
                               ", or train a restorer with --no-altitude"))
        altitudes = read_nav_altitudes(nav, [p.name for p in files])
        downs = read_nav_down(nav, [p.name for p in files]) if flat_floor else None
        lacking = [p.name for p in files if p.name not in altitudes]
        if lacking:
            raise DataError(f"the navigation has no altitude for {len(lacking)} of the {len(files)} images "
                            f"(e.g. {lacking[0]}): the restorer in {model_dir} needs one per image")
    ranges = Path(range_dir) if (model.range_input and mode == CorrectMode.rgbd) else None
    if ranges is not None:
        lacking = [p.name for p in files if not (ranges / f"{p.stem}.png").is_file()]
        if lacking:
            raise DataError(f"the restorer in {model_dir} takes each pixel's range (RGB-D mode), and "
                            f"{len(lacking)} of the {len(files)} images have no range map (e.g. {lacking[0]} in "
                            f"{ranges}): give the water stage's range/ of these frames, or correct every frame in "
                            f"monocular mode (--mode monocular: a flat seafloor at the navigation's altitude)")
    if model.water is not None and camera is None and needs_normals(Stack.from_config(model.water)):
        raise DataError(f"the restorer in {model_dir} inverts a water with lights, which needs the camera's "
                        f"intrinsics: put the survey's camera.json in {images_dir} or beside it")
    scene = read_scene_mask(scene_mask)
    if ranges is not None and far_range_m is None:
        far_range_m = survey_far_range_m([ranges / f"{p.stem}.png" for p in files], scene=scene)
    far_range_m = math.nan if far_range_m is None else far_range_m
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)

    site_net, site_record = load_site_depth(model_dir) if flat_floor else (None, None)
    site_depth = site_net is not None
    result = CorrectResult(out, 0, 0, mode=str(mode),
                           range_source="" if not model.range_input else "range maps" if ranges is not None
                           else "site depth net" if site_depth else "flat seafloor",
                           range_why=(site_record or {}).get("why", ""))
    todo = [p for p in files if force or not all(o.is_file() for o in _outputs(out, p.name, image_format))]
    result.already_done = len(files) - len(todo)

    def altitude_of(paths: list[Path]) -> tuple[float, ...] | None:
        return tuple(altitudes[p.name] for p in paths) if (model.altitude or flat_floor) else None

    def down_of(paths: list[Path]) -> tuple[tuple[float, float, float], ...] | None:
        return tuple(tuple(downs[p.name]) for p in paths) if downs else None

    if not distributed:
        with tqdm(total=len(files), initial=result.already_done, disable=not progress, desc="correct",
                  unit="img") as bar:
            done = correct_chunk(CorrectChunk(Path(model_dir), tuple(todo), out, batch_size, device,
                                              altitude_of(todo), ranges, camera, flat_floor, down_of(todo),
                                              str(image_format), site_depth, far_range_m, fill_px, far_max_gain,
                                              Path(scene_mask) if scene_mask else None), bar, model)
        parts = [done]
    else:
        step = batch_size or CUDA_BATCH  # a whole number of batches on either device
        size = -(-max(chunk_size, 1) // step) * step
        jobs = [CorrectChunk(shared_path(model_dir), tuple(shared_path(p) for p in part), shared_path(out),
                             batch_size, device, altitude_of(part), shared_path(ranges) if ranges else None, camera,
                             flat_floor, down_of(part), str(image_format), site_depth, far_range_m, fill_px,
                             far_max_gain, shared_path(scene_mask) if scene_mask else None)
                for part in chunks(todo, size)]
        parts = map_tasks(correct_chunk, jobs, scheduler, desc="correct", progress=progress, unit="chunk")
        for message in (m for part in parts for m in part.failed):
            print(f"correct: skipped {message}", file=sys.stderr)
    result.corrected = sum(part.corrected for part in parts)
    result.failed = [m for part in parts for m in part.failed]
    result.seconds = time.perf_counter() - began
    summary = {"images_dir": str(images_dir), "model_dir": str(model_dir), "total": len(files),
               "corrected": result.corrected, "already_done": result.already_done,
               "failed": len(result.failed), "failed_files": result.failed, "seconds": round(result.seconds, 3),
               "mode": result.mode, "range_source": result.range_source, "range_why": result.range_why}
    atomic_write_bytes(out / SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())
    return result


@dataclass(frozen=True)
class CorrectStage:
    """The workspace's correct stage: every survey frame through the water's physics inverse (``physics/``) and
    through the restorer the restorer stage trained (``restorer/``)."""

    images_dir: str = ""
    """Frames to correct (SfM's names); empty: the survey's images."""
    batch_size: int = 0
    """Images per batch of the restorer; 0: one on a CPU, four on CUDA (:func:`batch_for`)."""
    mode: CorrectMode = CorrectMode.auto
    """How the physics correction and an RGB-D restorer get each pixel's range: auto (the water stage's range maps
    when it wrote them, else monocular), rgb-d, or monocular (a flat seafloor at each frame's altitude, times the site
    depth net's factor where it beat the flat seafloor, as for frames without range)."""
    image_format: ImageFormat = ImageFormat.input
    """The corrected frames' format: input (the survey's own, its bit depth kept; a JPEG survey's as PNG), png,
    tiff, or jpeg (8 bits, quality 95)."""
    fill_px: float = FILL_PX
    """A hole in a frame's range (a connected region of pixels without range) lying everywhere within this many
    pixels of measured range takes the range interpolated from around it; a larger one (open water, a far wall stereo
    did not match) takes the survey's far range (``far_range_pct``)."""
    far_range_pct: float = FAR_RANGE_PCT
    """The survey's far range, this percentile of the measured ranges of every frame, is the range of pixels in holes
    larger than ``fill_px``: the veil is removed and the attenuation compensated as at that range."""
    far_max_gain: float = FAR_MAX_GAIN
    """At pixels given the far range, the correction's gain (exp(g) of J = exp(g) I + o per channel: exp(eta r) / (k V)
    for the default stack) is held at this, J = min(exp(g), G) (I - C): open water (pure backscatter, I ~ C) stays
    finite and near the scene's brightness instead of its noise being amplified by exp(eta r)."""
    scheduler: str = field(default="", metadata={"hash": False})
    """Dask scheduler address (tcp://HOST:8786) for the restorer's per-image work; empty: this machine."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bars."""


@dataclass
class CorrectStageResult:
    physics: str
    """Workspace-relative folder of the physics correction (images/, mask/, range_from/); empty: the water stage has
    not run."""
    physics_images: str
    """Its corrected frames: sRGB, the input's bit depth; every pixel corrected (:func:`fill_range`), but those
    outside the scene mask, written raw."""
    physics_mask: str
    """Its masks: 255 where the pixel was corrected at its measured range, 0 where its range was filled (from its
    neighbours or the far range) or it is not the scene (what the evaluation scores: measured range only)."""
    filled_fraction: float
    """Share of the scene's pixels whose range the physics correction interpolated from their neighbours."""
    far_fraction: float
    """Share of the scene's pixels the physics correction corrected at the survey's far range."""
    physics_seconds: float
    """Wall time of the physics correction (files included)."""
    restorer: str
    """Workspace-relative folder of the restorer's correction (images/, depth/, summary.json); empty: the restorer
    stage has not run."""
    images: str
    """The restorer's corrected frames."""
    depth: str
    """The restorer's relative depth maps."""
    corrected: int
    """Frames the restorer corrected."""
    failed: list[str]
    """Frames it could not read."""
    seconds: float
    """Wall time of the restorer's correction (files and model loading included)."""
    fps: float
    """The restorer's frames per second, file I/O and model loading included."""
    mode: str
    """"rgb-d" (each pixel's range from the water stage), "monocular" (the image and, when the restorer takes
    them, the altitude and a flat seafloor's range at it), or "" (no restorer)."""
    mesh_images: str
    """The corrected frames the mesh stage textures with: the physics correction's when every scene pixel of it had
    a measured range (or there is no restorer), else the restorer's."""
    range_source: str = ""
    """The restorer's range: "range maps", "flat seafloor" or "site depth net" (:class:`CorrectResult`)."""
    range_why: str = ""
    """Why monocular mode took the site depth net or kept the flat seafloor."""
    physics_range_source: str = ""
    """The physics correction's range: "range maps", "flat seafloor" or "site depth net" (:class:`PhysicsResult`)."""
    physics_range_from: str = ""
    """Its per-pixel sources of range: ``range_from/<stem>.png``, :class:`RangeFrom` (0 measured, 1 from the
    neighbours, 2 the far range, 3 not the scene)."""
    far_range_m: float = 0.0
    """The survey's far range (metres; 0: no pixel needed it, or monocular mode)."""


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
    """"range maps" (the water stage's), "flat seafloor" or "site depth net" (monocular: :func:`monocular_range`)."""


def correct_physics_folder(ws, images: Path, out: Path, progress: bool = True, image_format: str = "input",
                           mode: str = CorrectMode.rgbd, fill_px: float = FILL_PX, far_range_pct: float = FAR_RANGE_PCT,
                           far_max_gain: float = FAR_MAX_GAIN) -> PhysicsResult:
    """Every frame the sfm stage lists through the inverse of the water stage's estimate; writes
    ``out/images/<name>`` (sRGB, the input's bit depth, in ``image_format``: :func:`corrected_name`; pixels outside
    the sfm stage's scene mask: the raw levels), ``out/mask/<stem>.png`` (255: corrected at its measured range; 0:
    range filled, or not the scene) and ``out/range_from/<stem>.png`` (each pixel's :class:`RangeFrom`).

    Each pixel's range: ``mode`` rgb-d (and auto), the water stage's range maps, a pixel without range ranged by
    :func:`fill_range` (small holes interpolated within ``fill_px``, larger ones at the survey's far range, the
    ``far_range_pct`` percentile of its measured ranges, with the gain held at ``far_max_gain``: :func:`cap_gain`);
    monocular, for frames without range, a flat seafloor's at the frame's navigation altitude and attitude (the
    survey's ``survey.json`` beside ``images``), times the site depth net's factor where the restorer stage trained
    one that beat the flat seafloor (:func:`monocular_range`). A stack that reads surface normals takes
    :func:`pipeline.water.correction_normals` (in monocular mode those of the range used). Pixels outside the scene
    count in no share.

    The frames stream through :func:`cpu_lanes` threads, each reading, correcting and writing one frame at a time on
    one torch thread, so memory does not grow with the survey. A stack that does not read surface normals is inverted
    with the interpolated fields of :class:`watergan.nets.restorer.WaterFields` in float32 (:func:`invert_with_fields`)
    of its effects without a value per frame, each frame's image first freed of the others by the affine map they
    apply to it (:func:`watergan.formation.inverse.frame_affines`: a gain or exposure per frame); otherwise (or for a
    frame whose effects are no such map) each frame's exact fields (:func:`invert_exact`, float64)."""
    from eval.tracks import Tracks
    from watergan.device import single_torch_thread
    from watergan.io import write_png

    from .water import correction_normals, water_frame

    began = time.perf_counter()
    keep_freed_memory()
    water = ws.require("water", "the physics correction")
    dense = ws.require("dense", "the physics correction")
    sfm = ws.require("sfm", "the physics correction")
    tracks = Tracks.load(ws.path(sfm.tracks))
    scene = read_scene_mask(ws.path(sfm.scene_mask) if getattr(sfm, "scene_mask", "") else None)
    K = np.asarray(tracks.K, float)
    stack = Stack.from_config(water.stack)
    with_normals = needs_normals(stack)
    # effects with a value per frame (a gain, an exposure) are taken as an affine map of each frame's image, measured
    # on a probe (frame_affines), and the rest of the stack from one table of fields for every frame
    base = [e for e in water.stack if not get_effect(e["name"]).varies_by_frame()]
    per_frame = Stack.from_config(base) if len(base) < len(water.stack) else None
    fields = None if with_normals else WaterFields(base)
    names = [str(n) for n in tracks.image_names]
    monocular = mode == CorrectMode.monocular
    # the dense range only feeds the normals (the correction's range is the water stage's map)
    depth_dir = ws.path(dense.depth_dir) if with_normals and not monocular else None
    range_dir = ws.path(water.range_dir)
    site, source, far_range_m = None, "range maps", math.nan
    if monocular:
        nav = images.parent / "survey.json"
        if not nav.is_file():
            raise DataError(f"the physics correction in monocular mode takes each frame's range from a flat seafloor "
                            f"at its altitude, and there is no navigation file {nav} with nav_altitude_m per frame: "
                            f"add one, or correct with the water stage's range maps (--mode rgb-d)")
        altitudes, downs = read_nav_altitudes(nav, names), read_nav_down(nav, names)
        lacking = [n for n in names if n not in altitudes]
        if lacking:
            raise DataError(f"the navigation {nav} has no altitude for {len(lacking)} of the {len(names)} frames "
                            f"(e.g. {lacking[0]}): the monocular physics correction needs one per frame")
        site = load_site_depth(ws.folder("restorer"))[0] if ws.result("restorer") is not None else None
        source = "site depth net" if site is not None else "flat seafloor"
    else:
        lacking = [n for n in names if not (range_dir / f"{Path(n).stem}.png").is_file()]
        if lacking:
            raise DataError(f"the water stage wrote no range map for {len(lacking)} of the {len(names)} frames (e.g. "
                            f"{lacking[0]} in {range_dir}): rerun it (`watergan water --workspace WS --force`)")
        far_range_m = survey_far_range_m([range_dir / f"{Path(n).stem}.png" for n in names], far_range_pct, scene)

    def frame_range(name: str, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frame's range, every scene pixel ranged, and where each pixel's came from (:func:`fill_range`)."""
        if monocular:  # the site depth net reads the stored values (levels: the frame's, decoded once)
            stored = stored_as(levels, "linear", np.float32) if site is not None else \
                np.empty((*levels.shape[:2], 3), np.float32)
            r = monocular_range(stored, altitudes[name], K, downs[name] if downs else None, site)
        else:
            r = read_millimetres(range_dir / f"{Path(name).stem}.png") / 1000.0  # metres, 0 = none
        return fill_range(r, far_range_m, fill_px, scene)

    affines: dict[tuple[int, int], list] = {}  # per image size, every frame's affine map (frame_affines)
    affines_lock = threading.Lock()

    def frame_map(k: int, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
        with affines_lock:
            if size_hw not in affines:
                affines[size_hw] = frame_affines(stack, per_frame, range(len(names)), K, *size_hw)
        return affines[size_hw][k]

    def correct_frame(k: int) -> tuple[float, float]:
        name = names[k]
        levels, corrected = read_stored(images / name), None
        r, source = frame_range(name, levels)
        far = source == RangeFrom.far
        if fields is not None:
            image = stored_as(levels, "srgb", np.float32)
            affine = None if per_frame is None else frame_map(k, image.shape[:2])
            if affine is not None:  # the frame's own gain or exposure taken off first
                s, t = affine
                image = (image - t.astype(np.float32)) / s.astype(np.float32)
            if per_frame is None or affine is not None:
                corrected, _ = invert_with_fields(image, r, fields, K, far, far_max_gain)
        if corrected is None:  # the stack reads normals, or the frame's effects are no affine map of its image
            f = water_frame(tracks, k, images, depth_dir)
            normals = correction_normals(f, r, K, water.normal_smooth_px) if with_normals else None
            corrected = invert_exact(f.image, r, stack, K, k, normals, far, far_max_gain)
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
    return PhysicsResult(float(filled), float(far), far_range_m, time.perf_counter() - began, source)


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
    """J = max(exp(g) I + o, s exp(g) I) (:data:`~watergan.nets.restorer.SIGNAL_FLOOR`), the physics inverse
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
    """J = max(I - C, s I) / A (:data:`~watergan.nets.restorer.SIGNAL_FLOOR`) with the stack's exact fields A, C at
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
    image = np.asarray(image, np.float64)
    out = np.maximum(image - c, SIGNAL_FLOOR * image) * gain
    out[~valid] = np.nan
    return out.astype(np.float32)


def run_correct_stage(ws, cfg: CorrectStage) -> CorrectStageResult:
    """Correct the survey's frames into the stage's folder: ``physics/`` with the water stage's estimate and range
    maps (:func:`correct_physics_folder`) when the water stage ran, ``restorer/`` with the restorer stage's model
    when it ran (a restorer in RGB-D mode takes the water stage's range maps, ``cfg.mode``); at least one of them.
    Names the set the mesh textures with (``mesh_images``)."""
    water, restorer = ws.result("water"), ws.result("restorer")
    if water is None and restorer is None:
        raise DataError(f"the correction needs the water stage or the restorer stage in {ws.root}: run "
                        f"{ws.stage('water').how_to_run()} or {ws.stage('restorer').how_to_run()} first")
    images = Path(cfg.images_dir) if cfg.images_dir else ws.folder("survey") / "images"
    folder = ws.stage_dir("correct")
    physics = restored = physics_source = ""
    filled = far = physics_s = 0.0
    far_range_m = None
    sfm = ws.result("sfm")
    scene_mask = ws.path(sfm.scene_mask) if sfm is not None and getattr(sfm, "scene_mask", "") else None
    if water is not None:
        done = correct_physics_folder(ws, images, folder / "physics", cfg.progress, str(cfg.image_format),
                                      CorrectMode.monocular if cfg.mode == CorrectMode.monocular else CorrectMode.rgbd,
                                      cfg.fill_px, cfg.far_range_pct, cfg.far_max_gain)
        filled, far, physics_s, physics_source = done.filled_fraction, done.far_fraction, done.seconds, \
            done.range_source
        far_range_m = done.far_range_m if np.isfinite(done.far_range_m) else None
        physics = ws.relative(folder / "physics")
    result = CorrectResult(folder / "restorer", 0, 0, mode="")
    if restorer is not None:
        ranges = ws.path(water.range_dir) if water is not None else None
        result = correct_folder(restorer.out_dir, images, folder / "restorer", force=True, batch_size=cfg.batch_size,
                                progress=cfg.progress, scheduler=cfg.scheduler or None, range_dir=ranges,
                                mode=str(cfg.mode), image_format=str(cfg.image_format), scene_mask=scene_mask,
                                far_range_m=far_range_m, fill_px=cfg.fill_px, far_max_gain=cfg.far_max_gain)
        restored = ws.relative(folder / "restorer")
    measured = filled == 0.0 and far == 0.0
    mesh = f"{physics}/images" if physics and (measured or not restored) else f"{restored}/images"
    return CorrectStageResult(
        physics=physics, physics_images=f"{physics}/images" if physics else "",
        physics_mask=f"{physics}/mask" if physics else "", filled_fraction=filled, far_fraction=far,
        physics_seconds=physics_s, restorer=restored, images=f"{restored}/images" if restored else "",
        depth=f"{restored}/depth" if restored else "", corrected=result.corrected, failed=result.failed,
        seconds=result.seconds, fps=result.corrected / max(result.seconds, 1e-9), mode=result.mode,
        mesh_images=mesh, range_source=result.range_source, range_why=result.range_why,
        physics_range_source=physics_source, physics_range_from=f"{physics}/range_from" if physics else "",
        far_range_m=far_range_m or 0.0)


@dataclass(frozen=True)
class CorrectConfig:
    """``watergan correct``: a folder of frames through a trained restorer (see :func:`correct_folder`)."""

    model_dir: Path
    """The train-restorer output folder."""
    images_dir: Path
    """Folder of images to correct (PNG, JPEG, TIFF)."""
    out_dir: Path
    """Output folder (images/, depth/, summary.json)."""
    navigation: Path | None = None
    """Survey file with nav_altitude_m per frame, for a restorer that takes altitude (default: survey.json
    beside the images folder)."""
    range_dir: Path | None = None
    """Folder of each image's range map (<stem>.png, 16-bit millimetres; a workspace's 03_water/range), for a
    restorer trained in RGB-D mode."""
    mode: CorrectMode = CorrectMode.auto
    """How a restorer trained in RGB-D mode gets each pixel's range: auto (rgb-d with --range-dir, else monocular),
    rgb-d (the range maps), or monocular (a flat seafloor at each frame's navigation altitude; needs camera.json)."""
    image_format: ImageFormat = ImageFormat.input
    """The corrected frames' format: input (each frame's own, its bit depth kept; a JPEG's as PNG), png, tiff, or
    jpeg (8 bits, quality 95)."""
    force: bool = False
    """Redo images already corrected."""
    batch_size: int = 0
    """Images per batch; 0: one on a CPU, four on CUDA."""
    device: Device = Device.auto
    """auto: CUDA when available, else CPU; or cpu, cuda."""
    scheduler: str = ""
    """Dask scheduler address (tcp://HOST:8786) to run the per-image work on its workers (shared file system)."""
