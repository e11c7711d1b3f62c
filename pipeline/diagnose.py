"""The diagnose stage: the discovery loop (:mod:`eval.diagnose`) on a workspace or a survey folder.

In a workspace where the water stage ran, the diagnosis starts from the water stage's estimate and ranks
its candidates on the water stage's own measurement table (``04_water/observations.npz``, with the survey's
annotations added by :func:`eval.diagnose_measure.with_survey`): one model and one set of measurements for the
correction and the diagnosis, so ``--add EFFECT`` refits the water with the effect on the views the
ranking judged it on. Without a water stage it samples and measures its own points on the SfM tracks
(``--geometry sfm`` asks for it; the simulator's truth when there are no tracks either). It writes into
the stage's folder, the model ledger (``model_ledger.jsonl``, one record per fit, kept across reruns)
included, named in its result; each model record carries what the eval stage measured of the corrected
frames (:func:`corrected_summary`). On a bare survey folder it measures the survey itself and writes into
``SURVEY/diagnose/`` (ledger there too).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from eval.diagnose import DiagnoseConfig, DiagnoseResult, describe_measurements, diagnose
from eval.diagnose_measure import (
    GeometrySource,
    MeasureConfig,
    check_survey_folder,
    measure_survey,
    with_survey,
)
from eval.ledger import LEDGER_NAME
from eval.observations import Observations
from watergan.errors import UserInputError
from watergan.io import atomic_write_json
from watergan.water_record import read_water

from .workspace import Workspace


def is_workspace(target: str | Path) -> bool:
    """Whether ``target`` is a workspace holding a survey (its survey stage's folder has images and a camera)."""
    from .stages import STAGES

    survey = Path(target) / STAGES["survey"].folder
    return (survey / "camera.json").is_file() and (survey / "images").is_dir()


@dataclass(frozen=True)
class DiagnoseStageResult(DiagnoseResult):
    """The diagnosis (:class:`eval.diagnose.DiagnoseResult`) in a workspace, and its ledger."""

    ledger: str = ""
    """Workspace-relative path of the model ledger (``model_ledger.jsonl`` in the stage's folder)."""


#: The eval stage's methods the ledger records for each model version: the corrected frames users texture with,
#: and the in-air truth of a simulated survey (the floor they approach).
LEDGER_METHODS = {"raw": "raw", "physics": "physics (range)", "ours": "ours", "inair": "inair"}


def corrected_summary(ws: Workspace) -> dict:
    """From the eval stage's result, for the raw frames, the physics correction, the restorer ("ours (rgb-d)" or
    "ours (monocular)", by the correct stage's mode) and the in-air truth: the colour consistency (mean over R, G,
    B of the normalised-colour variance across views) and the board's mean CIEDE2000. Empty without an eval
    result."""
    result = ws.result("eval")
    if result is None:
        return {}
    correct = ws.result("correct")
    names = {**LEDGER_METHODS, "ours": f"ours ({correct.mode if correct is not None and correct.mode else 'unknown'})"}
    out: dict[str, dict] = {"consistency": {}, "board_ciede2000": {}}
    for method, name in names.items():
        if method in result.consistency_variance:
            out["consistency"][name] = float(sum(result.consistency_variance[method]) / 3)
        if method in result.mean_board_ciede2000:
            out["board_ciede2000"][name] = float(result.mean_board_ciede2000[method])
    return {k: v for k, v in out.items() if v}


def _sfm_tracks(ws: Workspace) -> tuple[Path | None, str]:
    sfm = ws.result("sfm")
    return (ws.path(sfm.tracks), sfm.scale_method) if sfm is not None else (None, "unknown")


def water_measurements(ws: Workspace, geometry: str = "auto", config: MeasureConfig | None = None
                       ) -> tuple[Observations, str] | None:
    """(the water stage's measurement table with the survey's annotations, at most ``config.n_points`` of its
    points with all their views (:func:`with_survey`), one line saying so) when ``geometry`` is
    "water", or "auto" and the water stage saved its table; None otherwise (the diagnosis then measures the survey
    itself). "water" without a saved table is an error saying what to run."""
    if geometry not in (GeometrySource.auto, GeometrySource.water):
        return None
    water = ws.result("water")
    tracks, scale = _sfm_tracks(ws)
    path = ws.path(water.observations) if water is not None and water.observations else None
    if path is None or tracks is None or not path.is_file():
        if geometry == GeometrySource.water:
            raise UserInputError("the workspace has no water-stage observations: run `watergan water --workspace WS` "
                                 "(or `watergan run`) first, or diagnose with --geometry sfm")
        return None
    obs = Observations.load(path)
    meas = with_survey(obs, ws.stage_dir("survey"), tracks, scale, config or MeasureConfig())
    whole = meas.n_points == obs.n_points
    note = "" if whole else f" (drawn from its {len(obs.point)} observations of {obs.n_points} points: " \
                            f"--measure-n-points)"
    board = len(obs.board_colour)
    note += f"; its {board} board rows not used (known albedo: the diagnosis fits one per point)" if board else ""
    return meas, describe_measurements(meas, ws.relative(path)) + note


def run_diagnose_stage(ws: Workspace, cfg: DiagnoseConfig) -> DiagnoseStageResult:
    """Workspace stage (see the module docstring). The model starts from the site water the water stage
    estimated (its stack and values) when it ran and ``cfg.effects`` names none, and is fitted and ranked on the
    water stage's measurement table (:func:`water_measurements`) unless ``cfg.geometry`` asks for another."""
    tracks, scale = _sfm_tracks(ws)
    water = ws.result("water")
    measured = water_measurements(ws, cfg.geometry, cfg.measure)
    meas, described = measured if measured is not None else (None, "")
    out = ws.stage_dir("diagnose")
    record = read_water(ws.path(water.water_json)) if water is not None else None
    result = diagnose(ws.folder("survey"), out, out, cfg, tracks, scale, corrected_summary(ws),
                      model=water.stack if water is not None else None, measurements=meas, described=described,
                      fields=record.fields if record else None, frames=record.frames if record else None)
    fields = {f.name: getattr(result, f.name) for f in dataclasses.fields(result)}
    return DiagnoseStageResult(**fields, ledger=ws.relative(out / LEDGER_NAME))


def ledger_path(target: str | Path) -> Path:
    """The model ledger of a workspace (its diagnose stage's, named in its result) or of a survey folder."""
    from eval.ledger import find_ledger

    if is_workspace(target):
        result = Workspace(target).require("diagnose", "the ledger")
        return Workspace(target).path(result.ledger)
    return find_ledger(target)


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
                   ) -> Observations:
    """The diagnosis's measurements of a workspace (the water stage's table when it saved one, else its survey
    on the sfm stage's tracks when it ran) or of a survey folder."""
    config = config or MeasureConfig()
    if is_workspace(target):
        ws = Workspace(target)
        measured = water_measurements(ws, geometry, config)
        if measured is not None:
            return measured[0]
        tracks, scale = _sfm_tracks(ws)
        return measure_survey(ws.stage_dir("survey"), config, geometry, tracks, scale)
    return measure_survey(target, config, geometry)
