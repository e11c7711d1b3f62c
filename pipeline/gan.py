"""The learning stages: WaterGAN (training, then the paired set) and the restorer trained on it.

Both find their inputs in the workspace: WaterGAN the survey's frames and in-air RGB-D set (survey
stage) and the site water (water stage's ``water.json``); the restorer the paired set (gan stage),
whether the survey's navigation gives each frame's altitude (survey stage) and whether the water
stage wrote each frame's range maps (RGB-D mode). Their configurations nest the trainers' own
(:class:`watergan.train.GanConfig`, :class:`watergan.generate.GenerateConfig`,
:class:`watergan.train_restorer.RestorerConfig`), whose folders the stage fills in.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

from watergan.generate import GenerateConfig
from watergan.train import GanConfig
from watergan.train_restorer import RestorerConfig, RestorerResult

from .workspace import Workspace

#: The folder of the stage's generic in-air RGB-D set, where the survey gives none.
GENERIC_RGBD = "generic_rgbd"
#: Minutes of WaterGAN training in a workspace when neither a budget nor a count of iterations or epochs is given.
GAN_BUDGET_MIN = 4.0


def _train_gan() -> GanConfig:
    return GanConfig(rgbd_dir=Path(), underwater_dir=Path(), out_dir=Path())


def _generate() -> GenerateConfig:
    return GenerateConfig(model_dir=Path(), rgbd_dir=Path(), out_dir=Path())


@dataclass(frozen=True)
class GanStage:
    """WaterGAN's training and the rendering of the paired set: both settings enter the stage's hash. The folders
    of both are the stage's to fill (the survey's, the gan stage's folder)."""

    train: GanConfig = field(default_factory=_train_gan, metadata={"flatten": True})
    """WaterGAN's training (its options without a prefix: ``--effects``, ``--iterations``)."""
    generate: GenerateConfig = field(default_factory=_generate)
    """The rendering of the paired set (options ``--generate-...``)."""
    budget_min: float | None = None
    """Minutes of training; none: 4, or no time limit when iterations or epochs are given."""
    add: tuple[str, ...] = ()
    """Effects added to the generator's (placed by their rank), e.g. what the diagnosis found."""


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


def gan_configs(ws: Workspace, cfg: GanStage) -> tuple[GanConfig, GenerateConfig]:
    """The training's and the rendering's configurations in the workspace: the survey's frames and in-air RGB-D
    set (none given: the generic one in the stage's folder, :func:`generic_rgbd`), the water stage's estimate as the
    site water (unless ``site_water_mode`` is learned), ``add`` joined to the effects, the budget
    (:attr:`GanStage.budget_min`), the model and pairs in the stage's folder."""
    from watergan.site_water import SiteWater

    survey = ws.require("survey", "WaterGAN")
    folder = ws.stage_dir("gan")
    train = cfg.train
    limits = train.iterations is not None or train.epochs is not None
    budget = cfg.budget_min if cfg.budget_min is not None else None if limits else GAN_BUDGET_MIN
    rgbd = ws.path(survey.rgbd_dir) if survey.rgbd_dir else folder / GENERIC_RGBD
    train = dataclasses.replace(train, rgbd_dir=rgbd, underwater_dir=ws.folder("survey") / "images",
                                out_dir=folder / "model", effects=tuple(dict.fromkeys(train.effects + cfg.add)),
                                budget_min=budget)
    if train.site_water_mode != SiteWater.learned:  # the water stage's estimate, held or under its prior
        train = dataclasses.replace(train, site_water=ws.path(ws.require("water", "WaterGAN").water_json))
    generate = dataclasses.replace(cfg.generate, model_dir=folder / "model", rgbd_dir=rgbd,
                                   out_dir=folder / "generated")
    return train, generate


def generic_rgbd(out: Path, seed: int) -> None:
    """A generic seafloor in-air RGB-D set (the demo preset's, :func:`eval.synth.rgbd.write_rgbd_set`, seeded by
    ``seed``) rendered into ``out`` (replaced), for a survey that gives none."""
    from eval.synth.presets import PRESETS
    from eval.synth.rgbd import write_rgbd_set

    if out.exists():
        shutil.rmtree(out)
    print(f"gan: the survey gives no in-air RGB-D set: rendering a generic seafloor set into {out}", file=sys.stderr)
    write_rgbd_set(out, PRESETS["demo"].rgbd, seed)


def run_gan_stage(ws: Workspace, cfg: GanStage) -> GanStageResult:
    """Train WaterGAN (:func:`gan_configs`), then render the paired set (in-air, depth, underwater) for the
    restorer."""
    from watergan.generate import generate
    from watergan.train import train_gan

    train, pairs = gan_configs(ws, cfg)
    if not ws.require("survey", "WaterGAN").rgbd_dir:
        generic_rgbd(train.rgbd_dir, train.seed)
    result = train_gan(train)
    gen = generate(pairs)
    return GanStageResult(train=result.to_json(), model=ws.relative(train.out_dir),
                          generated=ws.relative(pairs.out_dir), generated_count=gen.count,
                          generate_seconds=gen.seconds)


def _train_restorer() -> RestorerConfig:
    return RestorerConfig(data_dir=Path(), out_dir=Path(), budget_min=0.5, stage1_min_iterations=60,
                          stage2_min_iterations=120)


@dataclass(frozen=True)
class RestorerStage:
    """The restorer's training on the gan stage's pairs, into the stage's folder."""

    train: RestorerConfig = field(default_factory=_train_restorer, metadata={"flatten": True})
    """The restorer's training (its options without a prefix; a budget of half a minute, and at least 60 and
    120 iterations of its two stages)."""
    altitude: bool | None = None
    """The colour net takes each image's altitude; auto: when the survey's navigation gives it (nav_altitude_m)."""
    range_input: bool | None = None
    """RGB-D mode (each pixel's range); auto: when the range stage wrote each frame's range maps."""
    site_depth_steps: int = 2000
    """Steps of the site depth net (monocular depth learned from the survey's dense depth,
    taken by monocular correction where it beats the flat seafloor on held-out frames); 0: none."""


@dataclass
class RestorerStageResult(RestorerResult):
    site_depth: dict = field(default_factory=dict)
    """The site depth net's record (``site_depth.json`` in the restorer's folder): held-out comparison with the flat
    seafloor, ``use`` and ``why``; {} when not trained."""


def restorer_config(ws: Workspace, cfg: RestorerStage) -> RestorerConfig:
    """The restorer's training configuration in the workspace: the gan stage's pairs, the stage's folder, and
    ``altitude`` and ``range_input`` resolved (:class:`RestorerStage`)."""
    pairs = ws.require("gan", "the restorer")
    survey = ws.result("survey")
    ranges = ws.result("range")
    altitude = cfg.altitude if cfg.altitude is not None else survey is not None and survey.navigation
    range_input = cfg.range_input if cfg.range_input is not None else ranges is not None and bool(ranges.range_dir)
    return dataclasses.replace(cfg.train, data_dir=ws.path(pairs.generated), out_dir=ws.stage_dir("restorer"),
                               altitude=altitude, range_input=range_input)


def run_restorer_stage(ws: Workspace, cfg: RestorerStage) -> RestorerStageResult:
    """Train the restorer on the paired set (:func:`restorer_config`), then the site depth net beside it
    (:func:`pipeline.site_depth.fit_site_depth`, unless ``site_depth_steps`` is 0)."""
    from watergan.train_restorer import train_restorer
    from watergan.train_site_depth import SiteDepthConfig

    from .site_depth import fit_site_depth

    config = restorer_config(ws, cfg)
    result = train_restorer(config)
    site = {}
    if cfg.site_depth_steps > 0:
        site = fit_site_depth(ws, SiteDepthConfig(steps=cfg.site_depth_steps, seed=config.seed), config.out_dir,
                              config.progress)
    return RestorerStageResult(**{f.name: getattr(result, f.name) for f in dataclasses.fields(result)},
                               site_depth=site)
