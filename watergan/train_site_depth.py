"""Training the site depth net (:mod:`watergan.nets.site_depth`) on the survey's frames that have range.

Data (:class:`SiteFrame`): each frame's linear image (values 0..1, as ``correct`` reads it), its flat seafloor's
camera-z depth (navigation altitude and attitude) and its reference depth (camera-z metres, the dense stage's
stereo/MVS depth; NaN where there is none). Target: t = log(z_ref / z_floor) at the net's size (area-averaged; a
net pixel whose area is not all covered by reference depth is left out of the loss).

Split: every ``hold_out_every``-th frame (index k with k % n == n // 2) is held out: never trained on, and what
the comparison with the planes is measured on (:func:`split`). With fewer than two training frames there is
nothing to learn from and training is refused.

Loss: the mean squared error in t over the valid pixels of a batch of ``batch`` training frames drawn with
replacement, each flipped left-right and up-down at random together with its target. The colours are not jittered:
a frame's brightness and colour are what tell its distance through the water. Adam at ``lr``, a tenth of it for the last
third of the steps. One thread per core; the frames' small images and targets are held in memory (44 frames of
640x480 at scale 16: 0.7 MB).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import UserInputError
from .io import atomic_write_json, read_json
from .nets.site_depth import SiteDepthNet
from .progress import TrainingBar
from .training import load_torch, save_torch

MODEL = "site_depth.pt"
RECORD = "site_depth.json"


@dataclass(frozen=True)
class SiteDepthConfig:
    """Options of the site depth net's training."""

    steps: int = 5000
    """Optimiser steps."""
    batch: int = 8
    """Frames per step."""
    lr: float = 1e-3
    """Adam's learning rate."""
    scale: int = 16
    """The net sees the image at 1/scale of its size."""
    hold_out_every: int = 4
    """Every n-th frame is held out for the comparison with the planes."""
    seed: int = 0
    """Seed of the weights, batches and augmentation."""


@dataclass
class SiteFrame:
    name: str
    image: np.ndarray
    """(H,W,3) linear values 0..1."""
    floor_z: np.ndarray
    """(H,W) the flat seafloor's camera-z depth, metres."""
    ref_z: np.ndarray | None
    """(H,W) reference camera-z depth, metres (NaN: none); None: the frame has none."""


def split(names: list[str], hold_out_every: int) -> tuple[list[str], list[str]]:
    """(training, held-out) names: frame k is held out when k % n == n // 2."""
    n = max(int(hold_out_every), 2)
    held = [name for k, name in enumerate(names) if k % n == n // 2]
    return [name for name in names if name not in held], held


def _area_mean(z: np.ndarray, h: int, w: int) -> np.ndarray:
    """``z`` (NaN = none) area-averaged to h x w; NaN where a cell is not all covered."""
    import cv2

    valid = np.isfinite(z)
    total = cv2.resize(np.where(valid, z, 0.0), (w, h), interpolation=cv2.INTER_AREA)
    cover = cv2.resize(valid.astype(np.float64), (w, h), interpolation=cv2.INTER_AREA)
    return np.where(cover > 0.999, total / np.maximum(cover, 1e-12), np.nan)


def train_site_depth(frames: list[SiteFrame], config: SiteDepthConfig = SiteDepthConfig(),
                     progress: bool = True) -> tuple[SiteDepthNet, dict]:
    """The net trained on the frames outside the held-out split that have reference depth; returns it and a record
    (training and held-out names, steps, seconds, the last 50 steps' mean loss)."""
    train_names, held = split([f.name for f in frames], config.hold_out_every)
    training = [f for f in frames if f.name in train_names and f.ref_z is not None]
    if len(training) < 2:
        raise UserInputError(f"the site depth net needs at least two frames with range to train on, "
                             f"{len(training)} of the {len(frames)} have it outside the held-out frames")
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    net = SiteDepthNet(scale=config.scale)
    x = torch.cat([net.small(f.image, f.floor_z) for f in training])
    net.normalise(x)
    h, w = x.shape[-2:]
    t = torch.from_numpy(np.stack([np.log(_area_mean(f.ref_z, h, w) / _area_mean(f.floor_z, h, w))
                                   for f in training])[:, None].astype(np.float32))
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr)
    bar = TrainingBar("site depth net", config.steps, 0, None, progress)
    began, losses = time.perf_counter(), []
    net.train()
    for step in range(config.steps):
        if step == (2 * config.steps) // 3:
            for group in optimiser.param_groups:
                group["lr"] = config.lr / 10
        pick = rng.integers(0, len(training), config.batch)
        xb, tb = x[pick], t[pick]
        if rng.random() < 0.5:
            xb, tb = xb.flip(-1), tb.flip(-1)
        if rng.random() < 0.5:
            xb, tb = xb.flip(-2), tb.flip(-2)
        valid = torch.isfinite(tb)
        loss = ((net(xb) - torch.nan_to_num(tb))[valid] ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
        bar.update(step + 1, time.perf_counter() - began, loss=f"{losses[-1]:.4f}")
    bar.close()
    net.eval()
    return net, {"train": [f.name for f in training], "held_out": held, "steps": config.steps,
                 "seconds": time.perf_counter() - began, "loss": float(np.mean(losses[-50:]))}


def save_site_depth(model_dir: Path, net: SiteDepthNet, record: dict) -> None:
    """``model_dir/site_depth.pt`` and ``site_depth.json`` (the record: training, the held-out comparison with the
    flat seafloor and ``use``, whether monocular correction takes the net), each atomically."""
    save_torch(Path(model_dir) / MODEL, net.to_checkpoint())
    atomic_write_json(Path(model_dir) / RECORD, record)


def load_site_depth(model_dir: Path) -> tuple[SiteDepthNet | None, dict | None]:
    """The site depth net of a restorer's folder when its record says to use it (else None) and the record (None
    when none was trained)."""
    record_path = Path(model_dir) / RECORD
    if not record_path.is_file():
        return None, None
    record = read_json(record_path, "site depth record")
    if not record.get("use"):
        return None, record
    missing = f"{Path(model_dir) / MODEL} is missing beside its record: train the restorer again"
    return SiteDepthNet.from_checkpoint(load_torch(Path(model_dir) / MODEL, missing)), record
