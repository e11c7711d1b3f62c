"""The WaterGAN trainer's pictures (see :mod:`watergan.train`): sample grids of in-air, generated and
real images, and ``training.png`` (losses and learned parameters over training, colour histograms)."""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .gan_statistics import render_eval
from .io import atomic_write_bytes, encode_png, linear_to_srgb, quantise
from .training import TrainingLog

if TYPE_CHECKING:
    from .train import GanRun

SAMPLES = "samples"
SAMPLE_COUNT = 8


def _srgb8(linear: torch.Tensor) -> np.ndarray:
    """(B,3,H,W) linear -> (B,H,W,3) uint8 sRGB."""
    array = linear.detach().cpu().double().numpy().transpose(0, 2, 3, 1)
    return quantise(linear_to_srgb(array), 8)


def sample_grid(rows: list[torch.Tensor]) -> np.ndarray:
    """Rows of (B,3,H,W) images tiled into one uint8 sRGB picture with 2-pixel gaps."""
    tiles = [_srgb8(r) for r in rows]
    n, h, w = max(t.shape[0] for t in tiles), tiles[0].shape[1], tiles[0].shape[2]
    grid = np.full((len(tiles) * (h + 2), n * (w + 2), 3), 255, np.uint8)
    for i, row in enumerate(tiles):
        for j, image in enumerate(row):
            grid[i * (h + 2):i * (h + 2) + h, j * (w + 2):j * (w + 2) + w] = image
    return grid


def plot_training(log_path: Path, generated: torch.Tensor, real: torch.Tensor, out_path: Path) -> None:
    """One figure: losses and every learned parameter over training, and per-channel histograms of
    generated vs real images (sRGB-encoded values, as viewed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = TrainingLog(log_path, ("step",)).rows()
    names = list(rows[0]["params"]) if rows else []
    panels = 2 + len(names)
    cols = 3
    fig, axes = plt.subplots(math.ceil(panels / cols), cols, figsize=(4.2 * cols, 3.0 * math.ceil(panels / cols)),
                             squeeze=False)
    axes = axes.ravel()
    steps = [r["step"] for r in rows]
    axes[0].plot(steps, [r["d_loss"] for r in rows], label="discriminator")
    axes[0].plot(steps, [r["g_loss"] for r in rows], label="generator")
    axes[0].set(title="losses", xlabel="iteration")
    axes[0].legend()
    for ax, name in zip(axes[1:], names, strict=False):
        values = np.array([r["params"][name] for r in rows], dtype=float).reshape(len(rows), -1)
        labels = ["R", "G", "B"] if values.shape[1] == 3 else [name.split(".")[-1]] * values.shape[1]
        colours = ["tab:red", "tab:green", "tab:blue"] if values.shape[1] == 3 else [None] * values.shape[1]
        for k in range(values.shape[1]):
            ax.plot(steps, values[:, k], label=labels[k], color=colours[k])
        ax.set(title=name, xlabel="iteration")
        if values.shape[1] == 3:
            ax.legend()
    ax = axes[1 + len(names)]
    bins = np.linspace(0, 1, 51)
    for k, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        g = linear_to_srgb(generated[:, k].detach().cpu().double().numpy().ravel())
        r = linear_to_srgb(real[:, k].detach().cpu().double().numpy().ravel())
        ax.hist(r, bins, histtype="stepfilled", alpha=0.25, color=colour, density=True)
        ax.hist(g, bins, histtype="step", color=colour, density=True)
    ax.set(title="colour histograms: real (filled), generated (line)", xlabel="sRGB value")
    for extra in axes[2 + len(names):]:
        extra.axis("off")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(out_path, buffer.getvalue())


def write_gan_samples(run: GanRun, step: int) -> None:
    """Write ``samples/step_NNNNNN.png``: rows of the first ``SAMPLE_COUNT`` in-air views, the generator's
    output for them (inference mode; fixed noise vectors drawn from ``seed + 1``) and the first real frames."""
    sample_z = torch.rand(SAMPLE_COUNT, run.generator.z_dim,
                          generator=torch.Generator().manual_seed(run.config.seed + 1))
    sample_z = sample_z.mul(2).sub(1).to(run.device)
    sample_air, sample_depth = run.air[:SAMPLE_COUNT], run.depth[:SAMPLE_COUNT]
    fake = render_eval(run.generator, sample_air, sample_depth, sample_z[:sample_air.shape[0]], run.intrinsics)
    atomic_write_bytes(run.out / SAMPLES / f"step_{step:06d}.png",
                       encode_png(sample_grid([sample_air, fake, run.real[:SAMPLE_COUNT]])))
