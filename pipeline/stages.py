"""The stage table: every stage of a workspace, declared once.

A stage is a plain function ``run(ws: Workspace, config) -> result`` with a frozen configuration
dataclass (its fields are the stage's CLI options) and a result dataclass (saved as JSON in the
stage's ``result.json``, read back typed by :meth:`Workspace.result`). ``reads`` lists the stages
whose results it uses: their result hashes enter its own (see :mod:`pipeline.workspace`), so a
rerun upstream reruns it.

Entries name their types and function as ``"module:attribute"`` and import them when first used:
the heavy libraries (torch, pycolmap, open3d) load only with the stage that needs them.

Adding a stage: one entry here (in run order), its config and result dataclasses, its function,
and a command line for it (:func:`pipeline.cli_stage.add_stage_command`, one call); its options in
``watergan run`` and in its own command come from the config.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


def _load(ref: Any) -> Any:
    """The object ``"module:attribute"`` names (anything else is taken as the object itself)."""
    if not isinstance(ref, str):
        return ref
    module, _, attribute = ref.partition(":")
    return getattr(importlib.import_module(module), attribute)


@dataclass(frozen=True)
class Stage:
    name: str
    """Name on the command line (``watergan run --force NAME``) and in the table."""
    folder: str
    """The stage's folder in the workspace."""
    config: str | type
    """``module:Class`` of the configuration dataclass."""
    result: str | type
    """``module:Class`` of the result dataclass."""
    run: str | Callable
    """``module:function`` of ``run(ws, config) -> result``."""
    reads: tuple[str, ...]
    """Stages whose results it reads (their hashes enter its own)."""
    help: str
    """One line: what the stage does."""
    run_sets: tuple[str, ...] = ()
    """Configuration fields that are not options of ``watergan run``: those it sets itself (inputs from
    earlier results; its common ``seed``, ``progress``, ``scheduler``) and those it leaves at their defaults
    (``device``, ``resume``, other input folders). Dotted for nested fields."""
    command: str = ""
    """The stand-alone command that runs it in a workspace (empty: only ``watergan run``)."""

    def how_to_run(self) -> str:
        """What to type to run the stage in a workspace."""
        return (f"`watergan {self.command} --workspace WS` (or `watergan run`)" if self.command
                else "`watergan run SURVEY --workspace WS`")

    @property
    def config_type(self) -> type:
        return _load(self.config)

    @property
    def result_type(self) -> type:
        return _load(self.result)

    @property
    def fn(self) -> Callable:
        return _load(self.run)


#: Every stage, in the order ``watergan run`` runs them. The geometry and the water come first: a survey that
#: SfM cannot register stops before minutes of training, and the water is known before WaterGAN starts. (The
#: folders keep the numbers they had before, so earlier workspaces stay valid.)
STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("survey", "00_survey", "pipeline.survey:SurveyConfig", "pipeline.survey:SurveyResult",
          "pipeline.survey:run_survey", (), "check the survey folder and link it into the workspace",
          ("survey_dir", "rgbd_dir", "seed")),
    Stage("sfm", "04_sfm", "pipeline.sfm:SfmConfig", "pipeline.sfm:SfmResult", "pipeline.sfm:run_sfm",
          ("survey",), "structure from motion (pycolmap) on the raw frames, metric scale",
          ("images_dir", "seed", "progress"),
          "sfm"),
    Stage("dense", "05_dense", "pipeline.dense:DenseConfig", "pipeline.dense:DenseResult",
          "pipeline.dense:run_dense", ("sfm",), "stereo / MVS depth maps, fused points and mesh",
          ("images_dir", "scheduler", "progress"), "dense"),
    Stage("water", "06_water", "eval.water:WaterConfig", "pipeline.water:WaterResult", "pipeline.water:run_water",
          ("sfm", "dense"), "the site's water from the survey's geometry, and the physics correction with each "
          "pixel's range", ("range_scale_sd", "measure.seed", "fit.seed", "progress"), "water"),
    Stage("gan", "01_gan", "pipeline.gan:GanStage", "pipeline.gan:GanStageResult",
          "pipeline.gan:run_gan_stage", ("survey", "water"),
          "train WaterGAN on the site water, then render the paired set for the restorer"),
    Stage("restorer", "02_restorer", "watergan.train_restorer:RestorerConfig",
          "watergan.train_restorer:RestorerResult", "pipeline.gan:run_restorer_stage", ("gan",),
          "train the restorer (depth and colour nets) on WaterGAN's pairs",
          ("data_dir", "out_dir", "seed", "resume", "device", "progress")),
    Stage("correct", "03_correct", "pipeline.correct:CorrectStage", "pipeline.correct:CorrectStageResult",
          "pipeline.correct:run_correct_stage", ("restorer", "water"),
          "correct every survey frame with the restorer (RGB-D: with the water stage's range maps)",
          ("images_dir", "scheduler", "progress")),
    Stage("eval", "07_eval", "eval.tables:EvaluateConfig", "eval.tables:EvaluateResult",
          "pipeline.evaluate:run_evaluate", ("sfm", "correct", "dense", "water", "restorer"),
          "baselines and ours on the same points and board: the paper's tables",
          ("survey_dir", "images_dir", "ours_dir", "scheduler", "progress"), "evaluate"),
    Stage("mesh", "08_mesh", "pipeline.mesh:MeshConfig", "pipeline.mesh:MeshResult", "pipeline.mesh:run_mesh",
          ("sfm", "correct", "dense", "water"), "textured mesh and photomosaic from the corrected frames",
          ("images_dir", "progress"), "texture"),
    Stage("diagnose", "09_diagnose", "eval.diagnose:DiagnoseConfig", "eval.diagnose:DiagnoseResult",
          "pipeline.diagnose:run_diagnose_stage", ("sfm", "water", "eval"),
          "the discovery loop: fit, residuals, missing effect",
          ("add", "progress", "measure.seed", "fit.seed")),
    Stage("report", "report", "pipeline.report:ReportConfig", "pipeline.report:ReportResult",
          "pipeline.report:run_report",
          ("gan", "restorer", "correct", "sfm", "dense", "water", "eval", "mesh", "diagnose"),
          "one self-contained HTML page"),
)}
