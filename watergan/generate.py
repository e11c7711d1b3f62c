"""Full-resolution synthetic underwater images from a trained WaterGAN: the restorer's training data.

The learned stack runs at the resolution of the in-air images (e.g. 480x640) although it was
trained at 48x64:

- ``backscatter_conv`` computes its mask at 48x64 (from z and the area-averaged range) and
  upsamples it bicubically, as in the paper;
- ``vignetting`` V = 1 + a r^2 + b r^4 + c r^6 is analytic in the normalised radius r (1 at a
  corner at any resolution), so it is evaluated at every full-resolution pixel: the same function
  the paper gets by upsampling its 48x64 mask, and smoother (no interpolation ripple);
- per-pixel effects (attenuation, gain, ...) act on each full-resolution pixel with its own range.

Batch norm uses its running statistics (the generator in inference mode), so each image depends
only on its own input and noise z (uniform in [-1, 1], one vector per image, seeded).

``recolour_fraction`` of the in-air images are recoloured before rendering (:func:`recolour`): an
in-air set chosen to resemble a sediment site holds few saturated colours, and a restorer trained on
it alone learns to return sediment colours whatever it sees (measurements: benchmarks/RESULTS/gan.md).

Output folder::

    OUT/inair/<stem>.png        in-air image as used, 8-bit sRGB
    OUT/depth/<stem>.png        its depth, 16-bit PNG of millimetres (0 = no value)
    OUT/range/<stem>.png        the range the generator used (the ray length from camera.json's intrinsics,
                                else the depth), 16-bit PNG of millimetres (0 = no value): the RGB-D
                                restorer's input
    OUT/underwater/<stem>.png   the generated underwater image, 8-bit sRGB
    OUT/manifest.json           model, size, seed, stack, and one entry per image (with the intrinsics it was
                                rendered with, fx, fy, cx, cy in pixels, or null)
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from .data import (
    DataError,
    atomic_write_bytes,
    find_rgbd_pairs,
    read_intrinsics,
    read_pair,
    resize_depth,
    resize_image,
    write_depth_png,
    write_srgb8,
)
from .device import Device, pick_device
from .errors import UserInputError
from .io import Encoding
from .nets.generator import WaterGenerator
from .train import CHECKPOINT, STACK_JSON, load_checkpoint

MANIFEST = "manifest.json"


@dataclass(frozen=True)
class GenerateConfig:
    """Options of ``generate`` (and of ``watergan generate``)."""

    model_dir: Path
    """A watergan train-gan output folder (checkpoint.pt and stack.json)."""
    rgbd_dir: Path
    """In-air RGB-D folder (rgb/ + depth/, the same names in each)."""
    out_dir: Path
    """Where the paired dataset is written."""
    size_hw: tuple[int, int] | None = None
    """Output size (height, width), pixels; None: each in-air image's own size."""
    seed: int = 0
    """Seed of the noise vectors."""
    encoding: Encoding = Encoding.srgb
    """Encoding of the in-air image files: "srgb" or "linear"."""
    use_intrinsics: bool = True
    """Use camera.json beside the RGB-D data when present (range from the rays); else range = depth."""
    skip_bad: bool = False
    """Skip (and report) bad or unpaired files instead of stopping with an error."""
    recolour_fraction: float = 0.5
    """Fraction of the in-air images recoloured (a random, seeded change of their colours) before rendering; 0:
    none."""
    device: Device = field(default=Device.auto, metadata={"hash": False})
    """"auto" (CUDA when available, else CPU), "cpu" or "cuda"."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Show a progress bar."""


def _smooth_field(rng: np.random.Generator, size_hw: tuple[int, int], cells: int = 3) -> np.ndarray:
    """A smooth random field in [-1, 1]: a (cells+1)^2 grid of uniform values, bicubically upsampled."""
    grid = rng.uniform(-1.0, 1.0, (cells + 1, cells + 1)).astype(np.float32)
    return np.clip(cv2.resize(grid, (size_hw[1], size_hw[0]), interpolation=cv2.INTER_CUBIC), -1.0, 1.0)


def recolour(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A linear (H,W,3) image with smoothly varying hue and saturation: per pixel, the colour's
    distance from grey g = mean(c) is scaled by s = 2 ** (1.5 f1) (0.35x to 2.8x) and rotated about the
    grey axis by pi f2 (Rodrigues' formula), with f1, f2 smooth random fields in [-1, 1]; clipped to
    0..1. Grey stays grey, so brightness and texture are kept and only chroma changes."""
    hw = rgb.shape[:2]
    saturation = 2.0 ** (1.5 * _smooth_field(rng, hw))[..., None]
    angle = np.pi * _smooth_field(rng, hw)[..., None]
    grey = rgb.mean(axis=2, keepdims=True)
    v = (rgb - grey) * saturation
    axis = np.full(3, 1 / np.sqrt(3.0))
    cross = np.cross(axis, v)  # k x v; k . v = 0 for a chroma vector
    rotated = v * np.cos(angle) + cross * np.sin(angle)
    return np.clip(grey + rotated, 0.0, 1.0)


@dataclass
class GenerateResult:
    """What ``generate`` wrote."""

    out_dir: Path
    count: int
    """Image triplets written."""
    seconds: float
    skipped: list[str]
    """Files left out with ``skip_bad``."""
    manifest: str = MANIFEST


def load_generator(model_dir: str | Path) -> WaterGenerator:
    """The trained generator of a ``train_gan`` folder, in inference mode on the CPU."""
    model_dir = Path(model_dir)
    stack_path = model_dir / STACK_JSON
    if not stack_path.is_file():
        raise UserInputError(f"{model_dir} has no {STACK_JSON}: is it a train-gan output folder?")
    generator = WaterGenerator.from_config(stack_path.read_text())
    checkpoint = load_checkpoint(model_dir / CHECKPOINT)
    try:
        generator.load_state_dict(checkpoint["generator"])
    except RuntimeError as exc:
        raise UserInputError(f"{model_dir}: {CHECKPOINT} does not match {STACK_JSON} ({exc})") from exc
    return generator.eval()


def generate(config: GenerateConfig) -> GenerateResult:
    """Render the paired in-air / depth / underwater dataset (see the module docstring)."""
    if not 0.0 <= config.recolour_fraction <= 1.0:
        raise UserInputError(f"recolour_fraction must be in [0, 1], got {config.recolour_fraction}")
    began = time.perf_counter()
    device = pick_device(config.device)
    generator = load_generator(config.model_dir).to(device)
    pairs, skipped = find_rgbd_pairs(config.rgbd_dir, config.skip_bad)
    camera = read_intrinsics(config.rgbd_dir) if config.use_intrinsics else None
    out = Path(config.out_dir)
    for sub in ("inair", "depth", "range", "underwater"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    noise = torch.Generator().manual_seed(config.seed)
    colours = np.random.default_rng([config.seed, 7])
    items = []
    for pair in tqdm(pairs, disable=not config.progress, desc="generate", unit="img"):
        z = torch.rand(1, generator.z_dim, generator=noise) * 2 - 1  # drawn first: a skipped pair shifts no other noise
        recoloured = bool(colours.random() < config.recolour_fraction)
        colour_rng = np.random.default_rng(colours.integers(2**63))
        try:
            rgb, depth = read_pair(pair, config.encoding)
        except DataError as exc:
            if not config.skip_bad:
                raise
            skipped.append(str(exc))
            continue
        native_hw = depth.shape
        size_hw = config.size_hw or native_hw
        rgb, depth = resize_image(rgb, size_hw).clip(0.0, 1.0), resize_depth(depth, size_hw)
        if recoloured:
            rgb = recolour(rgb, colour_rng)
        intrinsics = None
        if camera is not None:
            if (camera.height, camera.width) != native_hw:
                raise DataError(f"camera.json describes {camera.width}x{camera.height} images but {pair.rgb} "
                                f"is {native_hw[1]}x{native_hw[0]}")
            intrinsics = camera.resized(*size_hw).as_tuple()
        rgb_t = torch.from_numpy(rgb.transpose(2, 0, 1)).float()[None].to(device)
        depth_t = torch.from_numpy(depth).float()[None, None].to(device)
        with torch.no_grad():
            state = generator.state(rgb_t, depth_t, z.to(device), intrinsics)
            underwater = generator.render(state)[0].cpu().double().numpy()
        name = f"{pair.stem}.png"
        write_srgb8(out / "inair" / name, rgb)
        write_depth_png(out / "depth" / name, depth)
        write_depth_png(out / "range" / name, np.where(depth > 0, state.range_m[0, 0].cpu().double().numpy(), 0.0))
        write_srgb8(out / "underwater" / name, underwater.transpose(1, 2, 0))
        items.append({"stem": pair.stem, "inair": f"inair/{name}", "depth": f"depth/{name}", "range": f"range/{name}",
                      "underwater": f"underwater/{name}", "source_rgb": str(pair.rgb),
                      "source_depth": str(pair.depth), "height": size_hw[0], "width": size_hw[1],
                      "recoloured": recoloured, "intrinsics": None if intrinsics is None else list(intrinsics)})
    manifest = {"model_dir": str(config.model_dir), "rgbd_dir": str(config.rgbd_dir), "seed": config.seed,
                "recolour_fraction": config.recolour_fraction,
                "size_hw": list(config.size_hw) if config.size_hw else None,
                "range_from": "camera rays" if camera is not None else "depth",
                "encoding": {"inair": "srgb 8-bit", "depth": "uint16 millimetres", "range": "uint16 millimetres",
                             "underwater": "srgb 8-bit"},
                "stack": generator.to_config(), "count": len(items), "skipped": skipped, "items": items}
    atomic_write_bytes(out / MANIFEST, (json.dumps(manifest, indent=2) + "\n").encode())
    return GenerateResult(out, len(items), time.perf_counter() - began, skipped)
