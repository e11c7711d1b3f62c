"""The diagnose stage: the discovery loop (:mod:`eval.diagnose`) on a workspace or a survey folder.

In a workspace it measures the survey on the sfm stage's tracks (when it ran; else the simulator's
truth), starts from the water stage's estimate (one site water for the correction and the diagnosis),
writes into the stage's folder and keeps the model ledger (``model_ledger.jsonl``) at the
workspace's root, with the colour of the image folders ``watergan consistency`` measured. On a bare
survey folder it writes into ``SURVEY/diagnose/`` (ledger there too).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from eval.diagnose import DiagnoseConfig, DiagnoseResult, diagnose
from eval.diagnose_measure import MeasureConfig, Measurements, check_survey_folder, measure_survey
from watergan.io import atomic_write_json, read_json

from .workspace import Workspace


def is_workspace(target: str | Path) -> bool:
    """Whether ``target`` is a workspace holding a survey (its survey stage's folder has images and a camera)."""
    from .stages import STAGES

    survey = Path(target) / STAGES["survey"].folder
    return (survey / "camera.json").is_file() and (survey / "images").is_dir()


def colour_summary(ws: Workspace) -> dict:
    """From the eval stage's ``colour.json`` (``watergan consistency``), per image folder: the colour
    consistency (mean normalised-colour variance across views) and, when a board was measured, its
    mean CIEDE2000. Empty without the file."""
    path = ws.folder("eval") / "colour.json"
    if not path.is_file():
        return {}
    out = {}
    try:
        data = read_json(path)
        scores = (data.get("consistency") or {}).get("scores") or {}
        if scores:
            out["consistency"] = {name: float(s["mean_variance"]) for name, s in scores.items()}
        board = data.get("board") or {}
        if board:
            out["board_ciede2000"] = {name: float(b["mean_ciede2000"]) for name, b in board.items()}
    except (ValueError, KeyError, TypeError, AttributeError):
        return {}  # another layout: the ledger simply goes without the colour fields
    return out


def _sfm_tracks(ws: Workspace) -> tuple[Path | None, str]:
    sfm = ws.result("sfm")
    return (ws.path(sfm.tracks), sfm.scale_method) if sfm is not None else (None, "unknown")


def run_diagnose_stage(ws: Workspace, cfg: DiagnoseConfig) -> DiagnoseResult:
    """Workspace stage (see the module docstring). The model starts from the site water the water stage
    estimated (its stack and values) when it ran and ``cfg.effects`` names none."""
    tracks, scale = _sfm_tracks(ws)
    water = ws.result("water")
    return diagnose(ws.stage_dir("survey"), ws.stage_dir("diagnose"), ws.root, cfg, tracks, scale, colour_summary(ws),
                    model=water.stack if water is not None else None)


def run_diagnose(target: str | Path, config: DiagnoseConfig | None = None, progress: bool | None = None,
                 force: bool = False) -> DiagnoseResult:
    """``watergan diagnose TARGET``: the workspace stage when ``target`` is a workspace (skipped when done
    with the same configuration unless ``force``), else the diagnosis of a bare survey folder into
    ``SURVEY/diagnose/`` (its ``result.json`` written there)."""
    config = config or DiagnoseConfig()
    if progress is not None:
        config = dataclasses.replace(config, progress=progress)
    if is_workspace(target):
        return Workspace(target).run("diagnose", config, force=force)
    survey = check_survey_folder(target)
    out = survey / "diagnose"
    result = diagnose(survey, out, out, config)
    atomic_write_json(out / "result.json", result)
    return result


def measure_target(target: str | Path, config: MeasureConfig | None = None, geometry: str = "auto"
                   ) -> Measurements:
    """The diagnosis's measurements of a workspace (its survey, on the sfm stage's tracks when it ran) or
    of a survey folder."""
    config = config or MeasureConfig()
    if is_workspace(target):
        ws = Workspace(target)
        tracks, scale = _sfm_tracks(ws)
        return measure_survey(ws.stage_dir("survey"), config, geometry, tracks, scale)
    return measure_survey(target, config, geometry)
