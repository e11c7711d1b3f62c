"""The stage table: every stage of a workspace, declared once.

A stage is a plain function ``run(ws: Workspace, config) -> result`` with a frozen configuration
dataclass (its fields are the stage's CLI options) and a result dataclass (saved as JSON in the
stage's ``result.json``, read back typed by :meth:`Workspace.result`). ``reads`` lists the stages
whose results it uses: their result hashes enter its own (see :mod:`pipeline.workspace`), so a
rerun upstream reruns it. A stage finds its inputs in those results (an empty path option means
"the upstream stage's result"), so ``watergan run`` is a loop over this table
(:mod:`pipeline.run`) and every stage has a workspace command (:mod:`pipeline.cli_stage`).

Entries name their types and function as ``"module:attribute"`` and import them when first used:
the heavy libraries (torch, pycolmap, open3d) load only with the stage that needs them.

Adding a stage: its configuration and result dataclasses and its function (in its own module,
``pipeline/NAME.py``), and one entry here (in run order, its folder numbered so); a printer of its
result for its command where it has one (one ``add_stage_command`` call in a ``pipeline/cli_*.py``).
Its command (``watergan COMMAND --workspace WS``) and its options in ``watergan run``
(``--STAGE-FIELD``) come from the entry and the configuration.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
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
    """The stage's folder in the workspace (numbered in run order)."""
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
    command: str = ""
    """The command that runs it in a workspace (``watergan COMMAND --workspace WS``); empty: none of the
    generated kind (the stage has its own command)."""
    found: tuple[str, ...] = ()
    """Configuration fields (dotted for nested ones) the stage function fills from the workspace itself:
    options of neither its command nor ``watergan run``."""
    local: tuple[str, ...] = ()
    """Options of its command that ``watergan run`` leaves at their defaults (input folders that replace
    the upstream results, ``device``, ``resume``)."""
    run_defaults: tuple[tuple[str, Any], ...] = ()
    """(dotted field, value): where ``watergan run`` starts from another default than the configuration's."""
    check: str | Callable | None = None
    """``module:function`` of ``check(config)``: the user's files the stage reads, checked before ``watergan run``
    runs any stage (a bad one is a ``UserInputError`` naming it); None: nothing to check."""

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


#: Every stage, in the order ``watergan run`` runs them (the folders numbered so). The geometry and the water
#: come first: a survey that SfM cannot register stops before minutes of training, and the water is known before
#: WaterGAN starts.
STAGES: dict[str, Stage] = {s.name: s for s in (
    Stage("survey", "00_survey", "pipeline.survey:SurveyConfig", "pipeline.survey:SurveyResult",
          "pipeline.survey:run_survey", (), "check the survey folder and link it into the workspace", "survey",
          check="pipeline.survey:check_survey_config"),
    Stage("sfm", "01_sfm", "pipeline.sfm:SfmConfig", "pipeline.sfm:SfmResult", "pipeline.sfm:run_sfm",
          ("survey",), "structure from motion (pycolmap) on the raw frames, metric scale", "sfm",
          local=("images_dir",), check="pipeline.sfm:check_board"),
    Stage("dense", "02_dense", "pipeline.dense:DenseConfig", "pipeline.dense:DenseResult",
          "pipeline.dense:run_dense", ("sfm",), "stereo / MVS depth maps, fused points and mesh", "dense",
          local=("images_dir",)),
    Stage("range", "03_range", "pipeline.range:RangeConfig", "pipeline.range:RangeResult", "pipeline.range:run_range",
          ("sfm", "dense"), "each pixel's range: the dense range, the fused mesh's where it has none or disagrees",
          "range"),
    Stage("water", "04_water", "pipeline.water:WaterStage", "pipeline.water:WaterResult", "pipeline.water:run_water",
          ("sfm", "dense", "range"), "the site's water from the survey's geometry", "water",
          found=("measure.normal_smooth_px",), local=("range_scale_sd",), check="pipeline.evaluate:check_board"),
    Stage("gan", "05_gan", "pipeline.gan:GanStage", "pipeline.gan:GanStageResult", "pipeline.gan:run_gan_stage",
          ("survey", "water"), "train WaterGAN on the site water, then render the paired set for the restorer",
          "gan", found=("train.rgbd_dir", "train.underwater_dir", "train.out_dir", "train.site_water",
                        "train.budget_min", "generate.model_dir", "generate.rgbd_dir", "generate.out_dir"),
          local=("train.resume", "train.device", "generate.device")),
    Stage("restorer", "06_restorer", "pipeline.gan:RestorerStage", "pipeline.gan:RestorerStageResult",
          "pipeline.gan:run_restorer_stage", ("survey", "dense", "range", "gan"),
          "train the restorer (depth and colour nets) on WaterGAN's pairs, and the site depth net on the survey's "
          "dense depth", "restorer",
          found=("train.data_dir", "train.out_dir", "train.altitude", "train.range_input"),
          local=("train.resume", "train.device")),
    Stage("correct", "07_correct", "pipeline.correct:CorrectStage", "pipeline.correct:CorrectStageResult",
          "pipeline.correct:run_correct_stage", ("sfm", "dense", "range", "water", "restorer"),
          "correct every survey frame: the water's physics inverse with each pixel's range, and the restorer",
          "correct", local=("images_dir",)),
    Stage("eval", "08_eval", "eval.tables:EvaluateConfig", "eval.tables:EvaluateResult",
          "pipeline.evaluate:run_evaluate", ("sfm", "dense", "restorer", "correct"),
          "baselines and ours on the same points and board: the paper's tables", "evaluate",
          local=("survey_dir", "images_dir", "ours_dir"), check="pipeline.evaluate:check_board"),
    Stage("mesh", "09_mesh", "pipeline.mesh:MeshConfig", "pipeline.mesh:MeshResult", "pipeline.mesh:run_mesh",
          ("sfm", "dense", "correct"), "textured mesh and photomosaic from the corrected frames", "texture",
          local=("images_dir",)),
    Stage("diagnose", "10_diagnose", "eval.diagnose:DiagnoseConfig", "pipeline.diagnose:DiagnoseStageResult",
          "pipeline.diagnose:run_diagnose_stage", ("sfm", "water", "correct", "eval"),
          "the discovery loop: fit, residuals, missing effect", run_defaults=(("measure.n_points", 1500),)),
    Stage("report", "11_report", "pipeline.report:ReportConfig", "pipeline.report:ReportResult",
          "pipeline.report:run_report",
          ("survey", "sfm", "dense", "range", "water", "gan", "restorer", "correct", "eval", "mesh", "diagnose"),
          "one self-contained HTML page", "report"),
)}


def stage_folder(root: str | Path, name: str) -> Path:
    """The folder of stage ``name`` in the workspace at ``root``: ``root / STAGES[name].folder`` (not created).

    For code that holds a workspace's path rather than a :class:`pipeline.workspace.Workspace` (benchmarks, tests
    reading a finished run); with a workspace, :meth:`Workspace.folder` is the same lookup. An unknown name is a
    ``KeyError`` naming the stages."""
    if name not in STAGES:
        raise KeyError(f"unknown stage '{name}'; stages: {', '.join(STAGES)}")
    return Path(root) / STAGES[name].folder
