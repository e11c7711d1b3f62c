"""The restorer's inference over a folder of frames (``watergan correct-folder``, and the correct stage's
``restorer/``).

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

- ``rgb-d``: from ``range_dir/<stem>.png`` (16-bit millimetres, 0 = none, as the range stage writes them; a pixel
  without range takes its neighbours' or the survey's far range, :func:`watergan.correction_range.fill_range`, and a
  water's gain at the far range is held at ``far_max_gain``, :func:`watergan.correction_range.cap_gain`); an image
  without a range map is an error before any work;
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
import sys
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

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
from watergan.formation.inverse import needs_normals
from watergan.io import (
    encode_grey16_png,
    encode_image,
    levels_bits,
    output_bits,
    read_millimetres,
    read_scene_mask,
    read_stored,
    stored_as,
)
from watergan.nets.restorer import WaterFields, restore
from watergan.nets.site_depth import SiteDepthNet
from watergan.parallel import cpu_lanes, cuda_lanes, io_threads, keep_freed_memory, read_ahead
from watergan.train_restorer import load_restorer
from watergan.train_site_depth import load_site_depth

SUMMARY = "summary.json"


class ImageFormat(StrEnum):
    """The corrected frames' file format: the input's (its bit depth kept; a JPEG's as PNG: compressing a corrected
    frame again puts block artefacts where the correction brightened the signal), or PNG, TIFF (the input's bit
    depth) or JPEG (8 bits, quality ``watergan.io.JPEG_QUALITY``)."""

    input = "input"
    png = "png"
    tiff = "tiff"
    jpeg = "jpeg"


@dataclass(frozen=True, kw_only=True)
class CorrectOptions:
    """How frames are corrected: what ``watergan correct-folder`` (:class:`CorrectConfig`) and the workspace's correct
    stage (:class:`pipeline.correct.CorrectStage`) share."""

    batch_size: int = 0
    """Images per batch of the restorer; 0: one on a CPU, four on CUDA."""
    mode: CorrectMode = CorrectMode.auto
    """How the physics correction and a restorer trained in RGB-D mode get each pixel's range: auto (rgb-d where there
    are range maps, else monocular), rgb-d (the range maps), or monocular (a flat seafloor at each frame's navigation
    altitude, times the site depth net's factor where it beat the flat seafloor, as for frames without range; needs
    camera.json)."""
    image_format: ImageFormat = ImageFormat.input
    """The corrected frames' format: input (each frame's own, its bit depth kept; a JPEG's as PNG), png, tiff, or
    jpeg (8 bits, quality 95)."""
    fill_px: float = FILL_PX
    """A hole in a frame's range (a connected region of pixels without range) lying everywhere within this many
    pixels of measured range takes the range interpolated from around it; a larger one (open water, a far wall stereo
    did not match) takes the survey's far range (next)."""
    far_range_pct: float = FAR_RANGE_PCT
    """The survey's far range, this percentile of the measured ranges of every frame, is the range of pixels in holes
    larger than the fill distance (above): the veil is removed and the attenuation compensated as at that range."""
    far_max_gain: float = FAR_MAX_GAIN
    """At pixels given the far range, the correction's gain (exp(g) of J = exp(g) I + o per channel: exp(eta r) / (k V)
    for the default stack) is held at this, J = min(exp(g), G) (I - C): open water (pure backscatter, I ~ C) stays
    finite and near the scene's brightness instead of its noise being amplified by exp(eta r)."""
    scheduler: str = field(default="", metadata={"hash": False})
    """Dask scheduler address (tcp://HOST:8786) to run the restorer's per-image work on its workers (shared file
    system); empty: this machine."""


@dataclass(frozen=True)
class CorrectConfig(CorrectOptions):
    """``watergan correct-folder``: a folder of frames through a trained restorer (see :func:`correct_folder`)."""

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
    """Folder of each image's range map (<stem>.png, 16-bit millimetres; a workspace's range stage's range/), for a
    restorer trained in RGB-D mode."""
    force: bool = False
    """Redo images already corrected."""
    device: Device = Device.auto
    """auto: CUDA when available, else CPU; or cpu, cuda."""


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


CPU_BATCH = 1
"""Images per batch of the restorer on a CPU (``batch_size`` 0): each lane's full-resolution passes over one frame stay
in the cache, where a batch of 4 streams through memory (measurements: benchmarks/RESULTS/speed-and-scale.md)."""
CUDA_BATCH = 4
"""Images per batch on CUDA (``batch_size`` 0)."""


def batch_for(dev: torch.device) -> int:
    """The restorer's images per batch when none is given: ``CPU_BATCH`` on a CPU, ``CUDA_BATCH`` on CUDA."""
    return CPU_BATCH if dev.type == "cpu" else CUDA_BATCH


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
        K = None if chunk.camera is None else chunk.camera.resized(*image.shape[:2]).K
        range_m, source = fill_range(range_m, chunk.far_range_m, chunk.fill_px, scene, K)
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


@dataclass(frozen=True, eq=False)
class _BatchCorrector:
    """What each lane of :func:`correct_chunk` runs: one batch of the chunk's images through the restorer, its
    outputs written."""

    chunk: CorrectChunk
    model: torch.nn.Module
    fields: WaterFields | None
    """The water's inverse fields of a restorer that starts from one."""
    dev: torch.device
    scene: np.ndarray | None
    linear: bool
    """The restorer takes the colours decoded to linear light (:attr:`Item.linear`)."""

    def stacked(self, arrays: list[np.ndarray]) -> torch.Tensor:
        return torch.from_numpy(np.stack(arrays).transpose(0, 3, 1, 2)).to(self.dev)

    def __call__(self, batch: list[Item]) -> int:
        chunk, model, fields, dev, scene = self.chunk, self.model, self.fields, self.dev, self.scene
        x = self.stacked([b.image for b in batch])
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
                                 self.stacked([b.linear for b in batch]) if self.linear else None)
        rgb_np = rgb.cpu().numpy().transpose(0, 2, 3, 1)
        depth_np = depth[:, 0].cpu().numpy()
        for k, b in enumerate(batch):
            if scene is not None:  # not the scene: the stored values as they came
                rgb_np[k][~scene] = b.image[~scene]
            _write(chunk.out_dir, b.name, chunk.image_format, rgb_np[k], depth_np[k], b.bits)
        return len(batch)


def correct_chunk(chunk: CorrectChunk, bar: tqdm | None = None, model: torch.nn.Module | None = None) -> ChunkResult:
    """Correct ``chunk.paths`` into ``chunk.out_dir`` (every file written atomically), consecutive images of one
    size ``batch_size`` at a time; the model is loaded here unless given. On a CPU, :func:`watergan.parallel.cpu_lanes`
    batches run side by side, each on one thread, and write their own outputs; on CUDA
    :func:`watergan.parallel.cuda_lanes`. :func:`watergan.parallel.io_threads`
    threads read the next batches' images meanwhile. ``bar`` (local runs): advanced per image, and unreadable images are
    reported as they come."""
    dev = pick_device(chunk.device)
    keep_freed_memory()
    model = (model if model is not None else load_restorer(chunk.model_dir)).for_inference().to(dev)
    fields = WaterFields(model.water) if model.water is not None else None
    site = load_site_depth(chunk.model_dir)[0].to(dev) if chunk.site_depth else None  # read by the readers
    scene = read_scene_mask(chunk.scene_mask)
    (chunk.out_dir / "images").mkdir(parents=True, exist_ok=True)
    (chunk.out_dir / "depth").mkdir(parents=True, exist_ok=True)
    result = ChunkResult(0, [])
    lanes = cpu_lanes() if dev.type == "cpu" else cuda_lanes()
    batch_size = chunk.batch_size or batch_for(dev)
    # a restorer without skip layers applies its fields to the decoded colours: the readers decode them by table
    linear = not model.colour_net.skip and model.colour_net.head == "affine"
    correct_batch = _BatchCorrector(chunk, model, fields, dev, scene, linear)
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
            reads = read_ahead(reader, lambda k, path: _read_one(chunk, k, path, site, linear, scene), chunk.paths,
                               2 * lanes * batch_size)
            for batch in _batches(chunk, reads, batch_size, result, bar):
                collect(lanes)
                running.append(nets.submit(correct_batch, batch))
            collect(0)
    finally:
        torch.set_num_threads(threads)
    return result


def _batches(chunk: CorrectChunk, reads: Iterator[tuple[int, Path, Future]], batch_size: int, result: ChunkResult,
             bar: tqdm | None) -> Iterator[list[Item]]:
    """The images of ``reads`` (:func:`watergan.parallel.read_ahead`) in order, as batches of at most ``batch_size``
    consecutive images of one size; an unreadable image is added to ``result.failed`` (and reported on ``bar``)."""
    batch: list[Item] = []
    for k, path, read in reads:
        try:
            image, bits, range_m, decoded, far = read.result()
        except DataError as exc:
            result.failed.append(str(exc))
            if bar is not None:
                tqdm.write(f"correct: skipped {exc}", file=sys.stderr)
                bar.update(1)
            continue
        if batch and batch[0].image.shape != image.shape:
            yield batch
            batch = []
        batch.append(Item(path.name, image, bits, chunk.altitude_m[k] if chunk.altitude_m is not None else 0.0,
                          range_m, decoded, far))
        if len(batch) == batch_size:
            yield batch
            batch = []
    if batch:
        yield batch


def correct_folder(model_dir: str | Path, images_dir: str | Path, out_dir: str | Path, force: bool = False,
                   batch_size: int = 0, device: str = "auto", progress: bool = True, scheduler=None,
                   chunk_size: int = 64, navigation: str | Path | None = None,
                   range_dir: str | Path | None = None, mode: str = "auto",
                   image_format: str = "input", scene_mask: str | Path | None = None, far_range_m: float | None = None,
                   fill_px: float = FILL_PX, far_max_gain: float = FAR_MAX_GAIN,
                   far_range_pct: float = FAR_RANGE_PCT) -> CorrectResult:
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
    are ranged by :func:`watergan.correction_range.fill_range` (``fill_px``; ``far_range_m``, None:
    :func:`watergan.correction_range.survey_far_range_m`, the ``far_range_pct`` percentile of the images' range
    maps), the water's gain held at ``far_max_gain`` where they take the far range
    (:func:`watergan.correction_range.cap_gain`)."""
    from watergan.parallel import is_distributed

    began = time.perf_counter()
    images_dir, out = Path(images_dir), Path(out_dir)
    files = _images_to_correct(images_dir, out, batch_size, mode, image_format)
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
    altitudes, downs = _navigation(model, model_dir, images_dir, files, navigation, flat_floor)
    ranges = Path(range_dir) if (model.range_input and mode == CorrectMode.rgbd) else None
    if ranges is not None:
        _check_range_maps(model_dir, files, ranges)
    if model.water is not None and camera is None and needs_normals(Stack.from_config(model.water)):
        raise DataError(f"the restorer in {model_dir} inverts a water with lights, which needs the camera's "
                        f"intrinsics: put the survey's camera.json in {images_dir} or beside it")
    scene = read_scene_mask(scene_mask)
    if ranges is not None and far_range_m is None:
        far_range_m = survey_far_range_m([ranges / f"{p.stem}.png" for p in files], far_range_pct, scene=scene)
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
    template = CorrectChunk(Path(model_dir), (), out, batch_size, device, None, ranges, camera, flat_floor, None,
                            str(image_format), site_depth, far_range_m, fill_px, far_max_gain,
                            Path(scene_mask) if scene_mask else None)
    parts = _correct_chunks(template, todo, altitudes, downs, model, scheduler, chunk_size, progress,
                            (len(files), result.already_done))
    result.corrected = sum(part.corrected for part in parts)
    result.failed = [m for part in parts for m in part.failed]
    result.seconds = time.perf_counter() - began
    summary = {"images_dir": str(images_dir), "model_dir": str(model_dir), "total": len(files),
               "corrected": result.corrected, "already_done": result.already_done,
               "failed": len(result.failed), "failed_files": result.failed, "seconds": round(result.seconds, 3),
               "mode": result.mode, "range_source": result.range_source, "range_why": result.range_why}
    atomic_write_bytes(out / SUMMARY, (json.dumps(summary, indent=2) + "\n").encode())
    return result


def _images_to_correct(images_dir: Path, out: Path, batch_size: int, mode: str, image_format: str) -> list[Path]:
    """The images of ``images_dir`` (:func:`correct_folder`'s arguments checked first); a DataError says what is
    wrong."""
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
    return files


def _navigation(model: torch.nn.Module, model_dir: str | Path, images_dir: Path, files: list[Path],
                navigation: str | Path | None, flat_floor: bool
                ) -> tuple[dict[str, float] | None, dict[str, np.ndarray] | None]:
    """Each image's altitude above the seafloor (metres, by name) for a restorer that takes it or a flat seafloor's
    range (``flat_floor``), else None; and with ``flat_floor`` its "down" in the camera frame where the navigation
    gives its attitude (:func:`watergan.data.read_nav_down`), else None. A DataError when one is missing."""
    if not (model.altitude or flat_floor):
        return None, None
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
    return altitudes, downs


def _check_range_maps(model_dir: str | Path, files: list[Path], ranges: Path) -> None:
    """A DataError unless every image has its range map ``ranges/<stem>.png``."""
    lacking = [p.name for p in files if not (ranges / f"{p.stem}.png").is_file()]
    if lacking:
        raise DataError(f"the restorer in {model_dir} takes each pixel's range (RGB-D mode), and "
                        f"{len(lacking)} of the {len(files)} images have no range map (e.g. {lacking[0]} in "
                        f"{ranges}): give the range stage's range/ of these frames, or correct every frame in "
                        f"monocular mode (--mode monocular: a flat seafloor at the navigation's altitude)")


def _correct_chunks(template: CorrectChunk, todo: list[Path], altitudes: dict[str, float] | None,
                    downs: dict[str, np.ndarray] | None, model: torch.nn.Module, scheduler, chunk_size: int,
                    progress: bool, counts: tuple[int, int]) -> list[ChunkResult]:
    """The images ``todo`` corrected as ``template`` says: here in one chunk with the loaded ``model``, or on the
    cluster of ``scheduler`` in chunks of ``chunk_size`` (rounded up to whole batches) with their paths made absolute
    (:func:`correct_folder`). ``counts``: the folder's images, and those already done (the progress bar's)."""
    from watergan.parallel import chunks, is_distributed, map_tasks, shared_path

    def for_paths(paths: list[Path]) -> CorrectChunk:
        return replace(template, paths=tuple(paths),
                       altitude_m=tuple(altitudes[p.name] for p in paths) if altitudes is not None else None,
                       down_cam=tuple(tuple(downs[p.name]) for p in paths) if downs else None)

    if not is_distributed(scheduler):
        with tqdm(total=counts[0], initial=counts[1], disable=not progress, desc="correct", unit="img") as bar:
            return [correct_chunk(for_paths(todo), bar, model)]
    step = template.batch_size or CUDA_BATCH  # a whole number of batches on either device
    size = -(-max(chunk_size, 1) // step) * step
    jobs = [replace(for_paths(part), model_dir=shared_path(template.model_dir), paths=tuple(map(shared_path, part)),
                    out_dir=shared_path(template.out_dir),
                    range_dir=shared_path(template.range_dir) if template.range_dir else None,
                    scene_mask=shared_path(template.scene_mask) if template.scene_mask else None)
            for part in chunks(todo, size)]
    parts = map_tasks(correct_chunk, jobs, scheduler, desc="correct", progress=progress, unit="chunk")
    for message in (m for part in parts for m in part.failed):
        print(f"correct: skipped {message}", file=sys.stderr)
    return parts
