"""The evaluation stage (every method on the same points and board, the paper's tables: ``watergan
evaluate``), and the stand-alone colour-consistency and depth comparisons of any folders
(``watergan consistency``, ``watergan depth-compare``: they read a workspace's tracks and dense depth
and write where they are told, never into a stage's folder). The measuring itself is
:mod:`eval.tables`, :mod:`eval.colour` and :mod:`eval.depth`; this module finds the inputs through
the earlier stages' results (the corrections in the correct stage's) and writes into the eval
stage's folder, every file named in its result (the depth comparison in ``depth/``).
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eval.baseline_runs import TIMED_FRAMES, method_inputs, run_baselines
from eval.baselines import BASELINES
from eval.colour import ColourEvalConfig, ColourEvalResult
from eval.depth import DepthCompareConfig, DepthCompareResult, Navigation, compare_depth_folders
from eval.fidelity import frame_fidelities, marked_share
from eval.tables import (
    INAIR,
    LABELS,
    OURS,
    PHYSICS,
    EvaluateConfig,
    EvaluateResult,
    board_table,
    consistency_table,
    depth_table,
    example_frames,
    make_table,
    measure_board,
    missing_files,
    ours_seconds,
    point_variances,
    restorer_table,
    table_markdown,
    verdict_lines,
)
from eval.tracks import Tracks
from watergan.errors import UserInputError
from watergan.io import atomic_write_bytes, atomic_write_json, atomic_write_text
from watergan.survey_files import image_files

from .site_depth import site_depth_metrics
from .workspace import Workspace


@dataclass
class _Folders:
    """Every method's frames (baselines, ours, oracle; the in-air truth as a reference)."""

    folders: dict[str, Path]
    methods: list[str]
    reference: tuple[str, ...]
    skipped: dict[str, str]
    per_frame_s: dict[str, float | None]
    masks: dict[str, tuple[Path, float]] = field(default_factory=dict)
    """Per method that marks pixels it did not correct (the physics correction: no range), its mask folder and the
    share of the frames' pixels marked."""


def check_board(cfg) -> None:
    """The water's and the eval stage's input check: the board file the configuration names, when it names one
    (:func:`eval.colour.load_board_json`)."""
    from eval.colour import load_board_json

    if cfg.board_json:
        load_board_json(cfg.board_json)


def _survey_dirs(ws: Workspace, cfg: EvaluateConfig) -> tuple[Path, Path]:
    survey = Path(cfg.survey_dir) if cfg.survey_dir else ws.stage_dir("survey")
    return survey, Path(cfg.images_dir) if cfg.images_dir else survey / "images"


def _dense_depth_dir(ws: Workspace) -> Path | None:
    dense = ws.result("dense")
    return ws.path(dense.depth_dir) if dense is not None else None


def _correct_dirs(ws: Workspace, cfg: EvaluateConfig) -> tuple[Path | None, Path | None]:
    """(the restorer's correction folder, its corrected frames): ``ours_dir`` when given, else the correct stage's."""
    if cfg.ours_dir:
        return Path(cfg.ours_dir).parent, Path(cfg.ours_dir)
    correct = ws.result("correct")
    if correct is None or not correct.restorer:
        return None, None
    return ws.path(correct.restorer), ws.path(correct.images)


def _method_folders(ws: Workspace, cfg: EvaluateConfig, survey: Path, images: Path, tracks: Tracks,
                    names: list[str], simulated: bool) -> tuple[_Folders, object]:
    """Run the baselines and collect every method's folder; returns them and the range source."""
    out = ws.stage_dir("eval")
    methods, skipped, ranges, coefficients, geometry = method_inputs(cfg, survey, tracks, simulated,
                                                                     _dense_depth_dir(ws))
    per_frame = run_baselines(names, images, methods, out / "baselines", ranges, coefficients, geometry,
                              cfg.scheduler or None, progress=cfg.progress)
    folders = {m: out / "baselines" / m for m in methods}
    masks: dict[str, tuple[Path, float]] = {}
    correct_dir, ours_dir = _correct_dirs(ws, cfg)
    if ours_dir is None or not ours_dir.is_dir():
        skipped[OURS] = (f"no corrected images in {ours_dir or 'the correct stage'} (run the restorer and "
                         f"`watergan correct --workspace WS`)")
    elif missing_files(ours_dir, names):
        skipped[OURS] = (f"{ours_dir} lacks {len(missing_files(ours_dir, names))} of the SfM images "
                         f"(e.g. {missing_files(ours_dir, names)[0]})")
    else:
        folders[OURS] = ours_dir
        per_frame[OURS] = ours_seconds(correct_dir)
    correct = ws.result("correct")
    if correct is not None and correct.physics and not missing_files(ws.path(correct.physics_images), names):
        folders[PHYSICS] = ws.path(correct.physics_images)
        per_frame[PHYSICS] = correct.physics_seconds / max(len(names), 1)
        mask = ws.path(correct.physics_mask)
        if not missing_files(mask, [f"{Path(n).stem}.png" for n in names]):
            masks[PHYSICS] = (mask, marked_share(mask, names))
    methods = [m for m in [*methods, OURS, PHYSICS] if m != "oracle" and m in folders] + \
        (["oracle"] if "oracle" in folders else [])
    reference: tuple[str, ...] = ()
    if simulated and (survey / "truth" / "inair").is_dir():
        folders[INAIR] = survey / "truth" / "inair"
        reference = (INAIR,)
    folders = {m: folders[m] for m in [*methods, *reference]}
    return _Folders(folders, methods, reference, skipped, per_frame, masks), ranges


def measured_views(tracks, mask_dir: Path) -> np.ndarray:
    """(M,) bool: whether each observation of ``tracks`` falls on a pixel the physics correction corrected at its
    measured range (nonzero in ``mask_dir/<stem>.png``; nearest pixel)."""
    from watergan.io import DataError, read_grey8
    from watergan.parallel import rows_by_label

    keep = np.zeros(len(tracks.obs_xy), bool)
    images = np.unique(tracks.obs_image)
    for k, rows in zip(images, rows_by_label(tracks.obs_image, images), strict=True):
        try:
            mask = read_grey8(mask_dir / f"{Path(str(tracks.image_names[k])).stem}.png", "mask")
        except DataError:  # no measured range for this frame
            continue
        ij = np.rint(tracks.obs_xy[rows]).astype(int)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < mask.shape[1]) & (ij[:, 1] >= 0) & (ij[:, 1] < mask.shape[0])
        keep[rows[inside]] = mask[ij[inside, 1], ij[inside, 0]] > 0
    return keep


def _depth_compare(ws: Workspace, correct_dir: Path | None) -> tuple[str, str]:
    """Run the restorer's depth against the dense stage's (again: the restorer may have changed) when both exist,
    into the stage's ``depth/``: (its workspace-relative folder or "", why it failed or "")."""
    dense = _dense_depth_dir(ws)
    if correct_dir is None or not (correct_dir / "depth").is_dir() or dense is None or not dense.is_dir():
        return "", ""
    out = ws.stage_dir("eval") / "depth"
    try:
        compare_depth_folders(correct_dir / "depth", dense, out,
                              DepthCompareConfig(pred_dir=str(correct_dir / "depth")),
                              Navigation.from_survey(ws.stage_dir("survey") / "survey.json"))
    except UserInputError as exc:
        return "", f"depth comparison failed: {exc}"
    return ws.relative(out), ""


def _tables(ws: Workspace, f: _Folders, cons, board_results: dict, board_note: str, fid: dict,
            n_frames: int) -> list[dict]:
    methods = f.methods
    restorer = ws.result("restorer")
    tables = [board_table(board_results, methods, f.reference) if board_results else
              make_table("table1", "Table I: colour-board accuracy", [], [], status=f"not measured: {board_note}"),
              consistency_table(cons, methods, f.reference),
              restorer_table(Path(restorer.out_dir) if restorer else ws.folder("restorer"))]
    if fid:
        tables.append(make_table("fidelity", "Fidelity against the in-air truth (higher is better)", methods, [
            {"label": "PSNR (dB)", "values": [fid[m][0] for m in methods], "better": "higher"},
            {"label": "SSIM", "values": [fid[m][1] for m in methods], "better": "higher"}], "row",
            note=f"sRGB-encoded frames against truth/inair, mean over {n_frames} frames. Methods that cannot "
                 f"know the exposure (all but Jaffe-McGlamery and the oracle) are not rescaled." +
                 "".join(f" {LABELS.get(m, m)}: over the pixels it corrected ({100 * f.masks[m][1]:.1f} % marked "
                         f"as without range, written black)." for m in methods if m in f.masks)))
    else:
        tables.append(make_table("fidelity", "Fidelity against the in-air truth", [], [],
                                 status="not measured: not a simulated survey (no truth/inair)"))
    tables.append(depth_table(ws.stage_dir("eval") / "depth", site_depth_metrics(ws)))
    tables.append(make_table("speed", "Seconds per frame (lower is better)", methods, [
        {"label": "seconds per frame", "values": [f.per_frame_s.get(m) for m in methods], "better": "lower"}], "row",
        note=f"The correction alone, files excluded, over the first {TIMED_FRAMES} frames corrected one at a time "
             f"(on a cluster: every frame); the oracle's excludes rendering the true geometry; ours is "
             "the restorer's wall time per corrected frame, model loading and files included; physics is the "
             "correct stage's physics inverse per frame (files included, the estimate and the range maps excluded)."))
    return tables


def _verdict(ws: Workspace, f: _Folders, cons, board_results: dict, fid: dict, ranges, items: dict) -> list[str]:
    """The verdict's sentences (:func:`eval.tables.verdict_lines`), each measurement with the per-item values it is
    the mean of (``items``: "points", each point's variance; "frames", each frame's PSNR and SSIM; the board's
    patches), so that a difference within their spread reads as a tie."""
    methods, skipped = f.methods, f.skipped
    points, frames = items.get("points", {}), items.get("frames", {})
    metrics = []
    if board_results:
        patches = {key: {m: [getattr(p, key) for p in board_results[m].patches] for m in methods}
                   for key in ("distance", "ciede2000")}
        metrics += [("mean board distance", {m: board_results[m].mean_distance for m in methods}, "lower",
                     patches["distance"]),
                    ("mean board CIEDE2000", {m: board_results[m].mean_ciede2000 for m in methods}, "lower",
                     patches["ciede2000"])]
    metrics += [(f"{ch} consistency", {m: cons.scores[m].variance[k] for m in methods}, "lower",
                 {m: points[m][:, k] for m in methods if m in points}) for k, ch in enumerate("RGB")]
    if fid:
        metrics += [("PSNR", {m: fid[m][0] for m in methods}, "higher", {m: frames[m][:, 0] for m in frames}),
                    ("SSIM", {m: fid[m][1] for m in methods}, "higher", {m: frames[m][:, 1] for m in frames})]
    verdict = verdict_lines(metrics, methods)
    if OURS in skipped:
        verdict.insert(0, f"ours not measured: {skipped[OURS]}")
    elif board_results and "oracle" in board_results:
        ratio = board_results[OURS].mean_distance / max(board_results["oracle"].mean_distance, 1e-12)
        verdict.append(f"ours' mean board distance is {ratio:.2f}x the oracle's "
                       f"({'within' if ratio <= 2 else 'more than'} 2x)")
    sfm = ws.result("sfm")
    if ranges is not None and ranges.kind == "dense" and sfm is not None and sfm.scale_method == "none":
        verdict.append("the dense depth is not metric (SfM found no scale): Jaffe-McGlamery's coefficients (1/m) "
                       "and Sea-thru's fitted ones are in survey units")
    if ranges is not None and ranges.fallback:
        verdict.append(f"{len(ranges.fallback)} frames had no {ranges.kind} range; the range baselines used a "
                       f"constant range there (the frame's median SfM depth)")
    verdict += [f"{LABELS.get(m, m)} not run: {why}" for m, why in skipped.items() if m != OURS]
    return verdict


def _maybe_relative(ws: Workspace, path: Path) -> str:
    try:
        return ws.relative(path)
    except ValueError:
        return str(Path(path).resolve())


def run_evaluate(ws: Workspace, cfg: EvaluateConfig) -> EvaluateResult:
    """Workspace stage (see :mod:`eval.tables`): baselines, then every method measured on the same SfM
    points, observations and board, then the tables, the verdict and their files."""
    from eval.colour import consistency, observation_colours

    began = time.perf_counter()
    unknown = [m for m in cfg.methods if m not in BASELINES]
    if unknown:
        raise UserInputError(f"unknown method(s) {unknown}; choose from {', '.join(BASELINES)}")
    survey, images = _survey_dirs(ws, cfg)
    tracks = Tracks.load(ws.path(ws.require("sfm", "the evaluation").tracks))
    names = [str(n) for n in tracks.image_names]  # the frames SfM ran on: what every method is measured on
    image_files(images)
    if missing_files(images, names):
        raise UserInputError(f"{images} lacks SfM images (e.g. {missing_files(images, names)[0]}): give the folder "
                             f"SfM ran on with --images-dir")
    simulated = (survey / "truth" / "effects.json").is_file()
    out = ws.stage_dir("eval")
    f, ranges = _method_folders(ws, cfg, survey, images, tracks, names, simulated)

    colours = {m: observation_colours(tracks, p, cfg.patch_px, progress=cfg.progress, scheduler=cfg.scheduler or None)
               for m, p in f.folders.items()}  # sampled once for both
    if PHYSICS in f.masks:  # like for like: a view the physics correction gave no measured range is left out of all
        unmeasured = ~measured_views(tracks, f.masks[PHYSICS][0])
        for values in colours.values():
            values[unmeasured] = np.nan
    cons = consistency(tracks, f.folders, cfg.patch_px, cfg.min_views, colours=colours)
    variances = point_variances(tracks, f.folders, cfg.patch_px, cfg.min_views, colours)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **{m: v.astype(np.float32) for m, v in variances.items()})
    atomic_write_bytes(out / "consistency_points.npz", buffer.getvalue())
    board, board_results, board_note = measure_board(cfg, survey, f.folders)
    per_frame = frame_fidelities({m: f.folders[m] for m in f.methods}, f.folders[INAIR], names,
                                 {m: f.masks[m][0] for m in f.methods if m in f.masks}) if f.reference else {}
    fid = {m: (float(np.mean(v[:, 0])), float(np.mean(v[:, 1]))) for m, v in per_frame.items()}
    depth_dir, depth_note = _depth_compare(ws, _correct_dirs(ws, cfg)[0])
    if depth_note:
        f.skipped["depth comparison"] = depth_note

    tables = _tables(ws, f, cons, board_results, board_note, fid, len(names))
    verdict = _verdict(ws, f, cons, board_results, fid, ranges, {"points": variances, "frames": per_frame})
    range_kind = ranges.kind if ranges is not None else "none"
    examples = example_frames(names, board, cfg.example_frames)
    correct = ws.result("correct") if not cfg.ours_dir else None
    ours_mode = correct.mode if correct is not None else "unknown"
    data = {"methods": f.methods, "ours_mode": ours_mode,
            "labels": {m: LABELS.get(m, m) for m in [*f.methods, *f.reference]},
            "reference": list(f.reference), "folders": {m: _maybe_relative(ws, p) for m, p in f.folders.items()},
            "skipped": f.skipped, "range_source": range_kind, "simulated": simulated, "example_frames": examples,
            "tables": tables, "verdict": verdict}
    atomic_write_json(out / "tables.json", data)
    md = ["# Evaluation", "", f"Methods: {', '.join(LABELS.get(m, m) for m in f.methods)}; range from {range_kind}; "
          f"ours: the restorer, {OURS_MODES.get(ours_mode, ours_mode)}.", ""]
    md += [table_markdown(t) for t in tables] + ["## Verdict", ""] + [f"- {line}" for line in verdict]
    atomic_write_text(out / "tables.md", "\n".join(md) + "\n")
    return EvaluateResult(
        tables_json=ws.relative(out / "tables.json"), tables_md=ws.relative(out / "tables.md"),
        baselines_dir=ws.relative(out / "baselines"), methods=f.methods, skipped=f.skipped, range_source=range_kind,
        mean_board_distance={m: r.mean_distance for m, r in board_results.items()},
        mean_board_ciede2000={m: r.mean_ciede2000 for m, r in board_results.items()},
        consistency_variance={m: s.variance for m, s in cons.scores.items()}, verdict=verdict,
        example_frames=examples, seconds=time.perf_counter() - began,
        consistency_points=ws.relative(out / "consistency_points.npz"), depth=depth_dir)


#: How the correct stage's restorer corrected the frames (its result's ``mode``).
OURS_MODES = {"rgb-d": "RGB-D mode (each pixel's range from the water stage)",
              "monocular": "monocular mode (the image, and the altitude when the restorer takes it; a restorer trained "
                           "with range takes a flat seafloor's at the altitude)",
              "unknown": "frames given with ours_dir (mode not recorded)"}


def run_colour_eval(ws: Workspace, cfg: ColourEvalConfig, out: Path) -> ColourEvalResult:
    """``watergan consistency``: tracks from the workspace's sfm stage; writes ``out/colour.json``."""
    from eval.colour import board_accuracy, consistency, load_board_json, parse_folders, truth_board

    tracks = Tracks.load(ws.path(ws.require("sfm", "the colour consistency").tracks))
    folders = parse_folders(cfg.folders)
    result = ColourEvalResult(consistency=consistency(tracks, folders, cfg.patch_px, cfg.min_views, cfg.linear,
                                                      progress=True, scheduler=cfg.scheduler or None))
    board = load_board_json(cfg.board_json) if cfg.board_json else truth_board(cfg.truth_dir) if cfg.truth_dir \
        else None
    if board is not None:
        result.board = {name: board_accuracy(path, board, cfg.board_inset, linear=cfg.linear)
                        for name, path in folders.items()}
    atomic_write_json(Path(out) / "colour.json", result)
    result.table = str(Path(out) / "colour.json")
    return result


def run_depth_compare(ws: Workspace | None, cfg: DepthCompareConfig, out: Path) -> DepthCompareResult:
    """``watergan depth-compare``: ``cfg.pred_dir`` against ``cfg.ref_dir`` (empty: the workspace's dense depth
    maps), outputs in ``out``."""
    ref_dir = Path(cfg.ref_dir) if cfg.ref_dir else _dense_depth_dir(ws) if ws is not None else None
    if ref_dir is None:
        raise UserInputError("no reference depth: give --ref-dir, or a --workspace whose dense stage ran")
    survey = Path(cfg.navigation) if cfg.navigation else ws.stage_dir("survey") / "survey.json" if ws else None
    if cfg.navigation and not survey.is_file():
        raise UserInputError(f"navigation file {survey} does not exist")
    return compare_depth_folders(cfg.pred_dir, ref_dir, out, cfg, Navigation.from_survey(survey) if survey else None)
