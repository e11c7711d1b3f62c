"""The learning stages: WaterGAN (training, then the paired set) and the restorer trained on it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .workspace import Workspace


@dataclass(frozen=True)
class GanStage:
    """WaterGAN's training and the rendering of the paired set: both settings enter the stage's hash."""

    train: Any
    """A :class:`watergan.train.GanConfig`."""
    generate: Any
    """A :class:`watergan.generate.GenerateConfig` (its model folder is the training's output)."""


@dataclass
class GanStageResult:
    train: dict
    """:class:`watergan.train.GanResult` as JSON (steps, seconds, losses, learned parameters)."""
    model: str
    """Workspace-relative model folder (stack.json, checkpoint.pt)."""
    generated: str
    """Workspace-relative folder of the paired set (inair/, depth/, underwater/, manifest.json)."""
    generated_count: int
    generate_seconds: float


def run_gan_stage(ws: Workspace, cfg: GanStage) -> GanStageResult:
    """Train WaterGAN, then render the paired set (in-air, depth, underwater) for the restorer."""
    from watergan.generate import generate
    from watergan.train import train_gan

    result = train_gan(cfg.train)
    gen = generate(cfg.generate)
    return GanStageResult(train=result.to_json(), model=ws.relative(Path(cfg.train.out_dir)),
                          generated=ws.relative(Path(cfg.generate.out_dir)), generated_count=gen.count,
                          generate_seconds=gen.seconds)


def run_restorer_stage(ws: Workspace, cfg):
    """Train the restorer on the paired set (a :class:`watergan.train_restorer.RestorerConfig`)."""
    from watergan.train_restorer import train_restorer

    return train_restorer(cfg)
