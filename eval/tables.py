"""The evaluation's measuring: every baseline and the restorer measured on the same SfM points and
board, and the paper's tables side by side (the baselines run over the frames: :mod:`eval.baseline_runs`; PSNR and
SSIM against the in-air truth: :mod:`eval.fidelity`). The workspace stage that chains these is
:func:`pipeline.evaluate.run_evaluate` (``watergan evaluate``); it writes under the eval stage's folder:

    baselines/<method>/<image name>   each baseline's corrected survey frames (8-bit sRGB PNG)
    consistency_points.npz            per method, the per-point variance (P,3) behind Table II
    tables.json, tables.md            the tables (best value per row or column in bold) and the verdict

Methods: the baselines of :mod:`eval.baselines` (raw, histogram equalisation, CLAHE, gray world,
Jaffe-McGlamery, Sea-thru, oracle) and "ours", the restorer's corrected frames (the correct stage's ``images/``
by default, made by ``watergan correct``). A baseline that lacks an input (range, coefficients,
simulator truth) is skipped and the tables say why. On a simulated survey the in-air truth
(``truth/inair``) is measured too, as a reference column that is never "best".

Range for Jaffe-McGlamery and Sea-thru (``range_source``): 'dense' reads the dense stage's camera
z-depth (the dense stage's ``depth/<stem>.png``, millimetres of the survey frame's units) and converts it
with the intrinsics to the ray length r = z |K^-1 (x, y, 1)|; pixels without depth take the
nearest valid pixel's range (a frame without depth: its median sparse SfM depth everywhere).
'truth' reads the simulator's ``truth/range``. 'auto': dense when the dense stage ran, else truth
when the survey is simulated.

Tables (as in the paper; lower is better unless said):
- Table I: per board patch, the mean over views of |n(measured) - n(true)| (n = c / (R + G + B)),
  their mean and the mean CIEDE2000 (:func:`eval.colour.board_accuracy`).
- Table II: per channel, the mean over SfM points of the variance of n across views
  (:func:`eval.colour.consistency`, the same points and observations for every method).
- Table III: the restorer's RMSE on its held-out synthetic split (the restorer's ``validation.json``).
- Fidelity (simulated surveys): PSNR (dB) and SSIM of the sRGB-encoded frames against the in-air
  truth (higher is better), averaged over frames.
- Depth: monocular (the restorer's relative depth, the correct stage's ``depth/``) against stereo/MVS depth
  (``depth/metrics.json`` in the eval stage's folder; computed here when both inputs exist and it is missing).
- Speed: seconds per frame of each method's correction alone, over the first ``TIMED_FRAMES``
  (:mod:`eval.baseline_runs`) frames run one at a time (files excluded; the oracle's excludes rendering the true
  geometry; ours from the correct stage's ``summary.json``, which includes file I/O).

With ``EvaluateConfig.scheduler`` (a Dask scheduler address) the baselines (chunks of frames, every
method) and the colour sampling at the SfM observations run on the cluster's workers
(:mod:`watergan.parallel`; the survey and the workspace on a file system they share); the files and
numbers are the same as a local run's. The board, fidelity and depth measurements run here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from eval.baselines import BASELINES
from eval.depth import BEST_PLANE, FLOOR, FLOOR_ALIGNED, NET
from watergan.errors import UserInputError
from watergan.io import frame_file

OURS = "ours"
PHYSICS = "physics"
INAIR = "inair"
LABELS = {**{name: b.label for name, b in BASELINES.items()}, OURS: "ours", PHYSICS: "physics (range)",
          INAIR: "in-air truth"}


class RangeChoice(StrEnum):
    """Where the range-based baselines' range comes from."""

    auto = "auto"
    truth = "truth"
    dense = "dense"


RANGE_SOURCES = tuple(RangeChoice)


@dataclass(frozen=True)
class EvaluateConfig:
    """Baselines and the restorer measured on the same SfM points and colour board."""

    survey_dir: str = ""
    """The survey folder (images/, camera.json, and truth/ when simulated); empty: the workspace's survey."""
    images_dir: str = ""
    """The raw frames SfM ran on; empty: the survey's images/ folder."""
    methods: tuple[str, ...] = tuple(BASELINES)
    """Baselines to run (the default: every one)."""
    ours_dir: str = ""
    """The restorer's corrected frames; empty: the correct stage's images when it ran."""
    range_source: RangeChoice = RangeChoice.auto
    """Range for Jaffe-McGlamery and Sea-thru: 'dense', 'truth' or 'auto' (dense, else truth)."""
    jaffe_stack: str = ""
    """A formation-stack JSON ([{name, params}]) with the Jaffe-McGlamery coefficients.
    Empty: the simulated survey's true (full) stack."""
    board_json: str = ""
    """A board file with per-image pixel corners of the board's patches (docs/water.md, the colour board).
    Empty: the simulated survey's board."""
    patch_px: int = 5
    """Side of the square patch averaged at each SfM observation, pixels (odd)."""
    min_views: int = 3
    """Points with fewer valid views are left out of the consistency."""
    board_inset: float = 0.2
    """Fraction by which each board patch is shrunk towards its centre before averaging."""
    example_frames: int = 3
    """Frames the report shows side by side (those with the most board patches first)."""
    scheduler: str = field(default="", metadata={"hash": False})
    """A Dask scheduler address (tcp://HOST:8786) to run the baselines and colour sampling on; empty: here.
    The workers need a shared file system. The outputs are the same either way."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Show progress bars."""


@dataclass
class EvaluateResult:
    tables_json: str
    """Workspace-relative path of tables.json."""
    tables_md: str
    baselines_dir: str
    methods: list[str]
    """Methods measured (baselines run, then ours when present)."""
    skipped: dict[str, str]
    """Method -> why it was not measured."""
    range_source: str
    """'dense', 'truth' or 'none'."""
    mean_board_distance: dict[str, float] = field(default_factory=dict)
    mean_board_ciede2000: dict[str, float] = field(default_factory=dict)
    """Per method, the colour board's mean CIEDE2000 over patches (after one exposure factor per view)."""
    consistency_variance: dict[str, list[float]] = field(default_factory=dict)
    verdict: list[str] = field(default_factory=list)
    example_frames: list[str] = field(default_factory=list)
    seconds: float = 0.0
    consistency_points: str = ""
    """Workspace-relative path of consistency_points.npz (per method, each point's variance across views)."""
    depth: str = ""
    """Workspace-relative folder of the depth comparison (the restorer's depth against the dense stage's:
    metrics.json, error maps); empty: not run."""


# ---------------------------------------------------------------------------------------- inputs


def missing_files(folder: Path, names: list[str]) -> list[str]:
    """The frames ``names`` that ``folder`` holds in no image format (:func:`watergan.io.frame_file`)."""
    return [n for n in names if not frame_file(folder, n).is_file()]


# ---------------------------------------------------------------------------------- measurement


def point_variances(tracks, folders: dict[str, Path], patch_px: int, min_views: int,
                    colours: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Per method, the per-point variance across views of the normalised colour (P',3), on the points
    and observations :func:`eval.colour.consistency` uses (valid in every folder, >= ``min_views``).
    ``colours``: the folders' :func:`eval.colour.observation_colours` when already sampled."""
    from eval.colour import observation_colours

    given = colours or {}
    colours = {name: given[name] if name in given else observation_colours(tracks, path, patch_px)
               for name, path in folders.items()}
    valid = np.logical_and.reduce([np.isfinite(c).all(1) for c in colours.values()])
    counts = np.bincount(tracks.obs_point[valid], minlength=len(tracks.xyz))
    use = valid & (counts[tracks.obs_point] >= min_views)
    point = tracks.obs_point[use]
    n = np.bincount(point, minlength=len(tracks.xyz)).astype(float)
    keep = n >= min_views
    out = {}
    for name, c in colours.items():
        c = c[use]
        s1 = np.stack([np.bincount(point, c[:, ch], minlength=len(n)) for ch in range(3)], 1)
        s2 = np.stack([np.bincount(point, c[:, ch] ** 2, minlength=len(n)) for ch in range(3)], 1)
        out[name] = np.maximum(s2[keep] / n[keep, None] - (s1[keep] / n[keep, None]) ** 2, 0.0)
    return out


def ours_seconds(correct_dir: Path) -> float | None:
    """Seconds per frame of ``watergan correct`` (its summary.json: wall time / frames corrected)."""
    for path in (correct_dir / "summary.json", correct_dir / "result.json"):
        if path.is_file():
            data = json.loads(path.read_text())
            data = data.get("result", data)
            n = data.get("corrected") or data.get("n_images") or 0
            if n and data.get("seconds"):
                return float(data["seconds"]) / n
    return None


def example_frames(names: list[str], board, count: int) -> list[str]:
    """The frame with the most visible board patches, then frames spread evenly over the rest."""
    if count <= 0 or not names:
        return []
    order = list(names)
    chosen = []
    if board is not None:
        seen = {n: int(np.isfinite(q).all(axis=(1, 2)).sum()) for n, q in board.quads.items() if n in names}
        if seen:
            chosen.append(max(sorted(seen), key=lambda n: seen[n]))
    rest = [n for n in order if n not in chosen]
    need = count - len(chosen)
    if need > 0 and rest:
        picks = np.linspace(0, len(rest) - 1, min(need, len(rest)) + 2)[1:-1] if len(rest) > need else \
            np.arange(len(rest))
        chosen += [rest[int(round(i))] for i in picks]
    return sorted(dict.fromkeys(chosen), key=order.index)[:count]


# ----------------------------------------------------------------------------------------- tables


def make_table(table_id: str, title: str, columns: list[str], rows: list[dict], bold: str = "row",
               reference: tuple[str, ...] = (), note: str = "", status: str = "ok") -> dict:
    """A table as plain data: ``rows`` are ``{"label", "values" (one per column, None = no value),
    "better": "lower" | "higher" | ""}``; ``bold`` marks the best value per 'row' or per 'column'
    ('none': nothing) among the non-reference columns."""
    return {"id": table_id, "title": title, "columns": columns, "labels": {c: LABELS.get(c, c) for c in columns},
            "rows": rows, "bold": bold, "reference": [c for c in reference if c in columns], "note": note,
            "status": status}


def best_cells(table: dict) -> set[tuple[int, int]]:
    """(row, column) indices of the best values (ties all count)."""
    out = set()
    cols = [j for j, c in enumerate(table["columns"]) if c not in table.get("reference", [])]
    rows = table["rows"]
    if table.get("bold") == "row":
        groups = [[(i, j) for j in cols] for i in range(len(rows))]
    elif table.get("bold") == "column":
        groups = [[(i, j) for i in range(len(rows))] for j in cols]
    else:
        return out
    for group in groups:
        cells = [(i, j, rows[i]["values"][j]) for i, j in group
                 if rows[i].get("better") and rows[i]["values"][j] is not None and np.isfinite(rows[i]["values"][j])]
        if len(cells) < 2:
            continue
        sign = -1.0 if rows[cells[0][0]]["better"] == "higher" else 1.0
        top = min(sign * v for _, _, v in cells)
        out |= {(i, j) for i, j, v in cells if sign * v <= top + 1e-12 * max(abs(top), 1e-300)}
    return out


def format_value(value) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "-"
    if isinstance(value, str):
        return value
    if isinstance(value, int):
        return str(value)
    a = abs(value)
    return f"{value:.3e}" if 0 < a < 1e-3 else f"{value:.4f}" if a < 10 else f"{value:.2f}"


def table_markdown(table: dict) -> str:
    """The table in Markdown, best values in bold."""
    lines = [f"### {table['title']}", ""]
    if table["status"] != "ok":
        return "\n".join([*lines, f"{table['status']}", ""])
    best = best_cells(table)
    labels = [table["labels"].get(c, c) + (" (reference)" if c in table["reference"] else "")
              for c in table["columns"]]
    lines += ["| | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
    for i, row in enumerate(table["rows"]):
        cells = [f"**{format_value(v)}**" if (i, j) in best else format_value(v) for j, v in enumerate(row["values"])]
        lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
    if table["note"]:
        lines += ["", table["note"]]
    return "\n".join(lines) + "\n"


def table_html(table: dict) -> str:
    """The table as an HTML fragment, best values in bold."""
    from html import escape

    title = f"<h3>{escape(table['title'])}</h3>"
    if table["status"] != "ok":
        return f"{title}<p class='missing'>{escape(table['status'])}</p>"
    best = best_cells(table)
    head = "".join(f"<th>{escape(table['labels'].get(c, c))}{' (ref.)' if c in table['reference'] else ''}</th>"
                   for c in table["columns"])
    body = []
    for i, row in enumerate(table["rows"]):
        cells = "".join(f"<td><b>{format_value(v)}</b></td>" if (i, j) in best else f"<td>{format_value(v)}</td>"
                        for j, v in enumerate(row["values"]))
        body.append(f"<tr><th>{escape(str(row['label']))}</th>{cells}</tr>")
    note = f"<p class='note'>{escape(table['note'])}</p>" if table["note"] else ""
    return f"{title}<table><tr><th></th>{head}</tr>{''.join(body)}</table>{note}"


#: Two methods tie on a measurement when their paired difference (item by item: a point, a patch, a frame) lies
#: within this many standard errors of its mean from 0 (95 %).
TIE_STANDARD_ERRORS = 1.96
#: Without items to pair (a single number per method), values within this share of the larger one tie.
TIE_RELATIVE = 0.01


def within_noise(mine: float, other: float, paired: np.ndarray | None = None) -> bool:
    """Whether ``mine`` and ``other`` tie: |mean d| <= ``TIE_STANDARD_ERRORS`` sd(d) / sqrt(n) over the paired items'
    differences d (``paired``, NaN left out; at least 3), else |mine - other| <= ``TIE_RELATIVE`` max(|mine|,
    |other|)."""
    if paired is not None:
        d = np.asarray(paired, float).ravel()
        d = d[np.isfinite(d)]
        if len(d) >= 3:
            return bool(abs(d.mean()) <= TIE_STANDARD_ERRORS * d.std(ddof=1) / np.sqrt(len(d)))
    return abs(mine - other) <= TIE_RELATIVE * max(abs(mine), abs(other))


def verdict_lines(metrics: list[tuple], methods: list[str]) -> list[str]:
    """Plain sentences: each metric on which ours loses to another method, those on which it ties with others
    (:func:`within_noise`: the difference is within the measurement's own spread), then what ours beats.
    ``metrics``: (name, method -> value, 'lower' | 'higher'[, method -> the per-item values the value is the mean
    of, paired across methods]); a difference within the spread is a tie, neither a loss nor a win."""
    if OURS not in methods:
        return []
    losses, ties, wins = [], [], []
    for name, values, better, *items in metrics:
        samples = items[0] if items else {}
        mine = values.get(OURS)
        if mine is None or not np.isfinite(mine):
            continue
        beaten, tied = [], []
        for m in methods:
            v = values.get(m)
            if m == OURS or v is None or not np.isfinite(v):
                continue
            paired = (np.asarray(samples[OURS], float) - np.asarray(samples[m], float)
                      if OURS in samples and m in samples else None)
            if v == mine or within_noise(mine, v, paired):
                tied.append(f"{LABELS.get(m, m)} ({v:.3g})")
            elif (mine > v) if better == "lower" else (mine < v):
                losses.append(f"ours loses to {LABELS.get(m, m)} on {name}: {mine:.3g} vs {v:.3g}")
            else:
                beaten.append(LABELS.get(m, m))
        if tied:
            spread = "the measurement's own spread" if samples else f"{100 * TIE_RELATIVE:g} %"
            ties.append(f"ours ties with {', '.join(tied)} on {name} ({mine:.3g}: a difference within {spread})")
        if beaten:
            wins.append(f"ours beats {', '.join(beaten)} on {name} ({mine:.3g})")
    return losses + ties + wins


def board_table(board_results: dict, methods: list[str], reference: tuple[str, ...]) -> dict:
    columns = [m for m in [*methods, *reference] if m in board_results]
    names = [p.name for p in next(iter(board_results.values())).patches]
    rows = []
    for p, name in enumerate(names):
        values = [board_results[m].patches[p].distance for m in columns]
        rows.append({"label": name, "values": [v if np.isfinite(v) else None for v in values], "better": "lower"})
    rows.append({"label": "mean distance", "values": [board_results[m].mean_distance for m in columns],
                 "better": "lower"})
    rows.append({"label": "mean CIEDE2000", "values": [board_results[m].mean_ciede2000 for m in columns],
                 "better": "lower"})
    first = next(iter(board_results.values()))
    return make_table("table1", "Table I: colour-board accuracy (distance of intensity-normalised RGB, lower is "
                      "better)", columns, rows, "row", reference,
                      f"Per patch: mean over views of |n(measured) - n(true)|, n = c / (R + G + B); CIEDE2000 after "
                      f"one exposure factor per view; {first.n_images} images, patches shrunk by "
                      f"{first.inset:.0%}.")


def consistency_table(result, methods: list[str], reference: tuple[str, ...]) -> dict:
    columns = [m for m in [*methods, *reference] if m in result.scores]
    rows = [{"label": ch, "values": [result.scores[m].variance[k] for m in columns], "better": "lower"}
            for k, ch in enumerate("RGB")]
    rows.append({"label": "mean", "values": [result.scores[m].mean_variance for m in columns], "better": "lower"})
    return make_table("table2", "Table II: colour consistency across views (variance of normalised colour, lower is "
                      "better)", columns, rows, "row", reference,
                      f"{result.n_points} SfM points, {result.n_observations} observations, {result.patch_px}x"
                      f"{result.patch_px} px patch means, >= {result.min_views} views, "
                      f"{'linear' if result.linear else 'encoded'} RGB. A constant image has zero variance: read "
                      f"this beside Table I.")


def restorer_table(restorer_dir: Path) -> dict:
    """Table III from ``validation.json`` (or a 'not run' table)."""
    path = restorer_dir / "validation.json"
    title = "Table III: restorer RMSE on its held-out synthetic split (lower is better)"
    if not path.is_file():
        return make_table("table3", title, [], [], status=f"not run: no {path.parent.name}/validation.json "
                          f"(train the restorer: `watergan run`, or `watergan train-restorer`)")
    data = json.loads(path.read_text())
    rmse = data["rmse"]
    rows = [{"label": {"raw": "raw (uncorrected)", "restorer": "restorer"}.get(k, k),
             "values": [rmse[k].get(c) for c in ("R", "G", "B", "depth")], "better": "lower"} for k in rmse]
    table = make_table("table3", title, ["R", "G", "B", "depth"], rows, "column",
                       note=f"{data.get('val_count', '?')} held-out frames; {data.get('units', '')}.")
    return table


RESTORER_NET = "restorer's depth net"
SITE_NET = "site depth net (held-out)"


def depth_table(depth_dir: Path, site_metrics: Path | None = None) -> dict:
    """Monocular vs stereo depth from ``depth_dir/metrics.json`` (or a 'not run' table): the restorer's depth net
    beside the planes that know nothing of the image (:mod:`eval.depth`), over all and over relief pixels; the best
    plane is a reference column (an upper bound for any plane). With ``site_metrics`` (the site depth net's held-out
    comparison, :mod:`pipeline.site_depth`) a column of the site net, metric, on its held-out frames."""
    path = depth_dir / "metrics.json"
    title = "Depth: monocular vs stereo/MVS, beside planes"
    if not path.is_file():
        return make_table("depth", title, [], [], status=f"not run: no {depth_dir}/metrics.json (needs the "
                          "restorer's relative depth and the dense stage, or `watergan depth-compare`)")
    data = json.loads(path.read_text())
    sources = data.get("sources") or {NET: {"alignment": data.get("alignment", "?"), "all": data["overall"],
                                            "relief": None}}
    order = (NET, FLOOR, FLOOR_ALIGNED, BEST_PLANE)  # metrics.json sorts its keys
    sources = {name: sources[name] for name in sorted(sources, key=lambda n: order.index(n) if n in order else 9)}
    site = json.loads(site_metrics.read_text()) if site_metrics is not None and site_metrics.is_file() else None
    sources = {(RESTORER_NET if name == NET else name): value for name, value in sources.items()}
    if site is not None:
        sources = {**sources, SITE_NET: site["sources"][NET]}
    columns = list(sources)
    value = lambda part, key: [(sources[c][part] or {}).get(key) for c in columns]  # noqa: E731
    rows = [{"label": "RMSE (m)", "values": value("all", "rmse_m"), "better": "lower"},
            {"label": "RMSE, relief pixels (m)", "values": value("relief", "rmse_m"), "better": "lower"},
            {"label": "RMSE / depth range (the paper's)", "values": value("all", "rmse_over_range"), "better": "lower"},
            {"label": "AbsRel", "values": value("all", "abs_rel"), "better": "lower"},
            {"label": "delta < 1.25", "values": value("all", "delta_125"), "better": "higher"},
            {"label": "median scale", "values": value("all", "scale"), "better": ""}]
    alignments = "; ".join(f"{c}: {sources[c]['alignment']}" for c in columns)
    ratio = data.get("relief_rmse_ratio")
    verdict = (f" The restorer's net's RMSE on relief pixels is {ratio:.2f}x that of the {data['ratio_to']}"
               f" ({data['all_rmse_ratio']:.2f}x over all pixels): "
               + ("it beats the plane where the plane is wrong." if ratio < 1 else "a plane does better.")
               if ratio is not None and np.isfinite(ratio) else "")
    if site is not None:
        verdict += (f" The site depth net (trained on the survey's dense depth, metric) on its "
                    f"{len(site['per_image'])} held-out frames: {site['relief_rmse_ratio']:.2f}x the flat seafloor's "
                    f"RMSE on relief pixels, {site['all_rmse_ratio']:.2f}x over all pixels.")
    relief = data.get("relief_fraction")
    relief_note = (f" Relief pixels: more than 5 cm from the frame's best plane ({100 * relief:.0f} % of the pixels)."
                   if relief is not None and np.isfinite(relief) else "")
    return make_table("depth", title, columns, rows, "row", reference=(BEST_PLANE,),
                      note=f"{len(data.get('per_image', {}))} frames, {len(data.get('skipped', []))} skipped; "
                           f"the restorer's net was not trained on the survey's frames. Alignment: {alignments}."
                           f"{relief_note}{verdict}")


# ------------------------------------------------------------------------------------------ board


def measure_board(cfg: EvaluateConfig, survey: Path, folders: dict[str, Path]) -> tuple[object, dict, str]:
    """(board or None, method -> BoardResult, why there is none)."""
    from eval.colour import board_accuracy, board_for_images, load_board_json, truth_board
    from watergan.data import IMAGE_SUFFIXES, list_files

    images = [p.name for p in list_files(survey / "images", IMAGE_SUFFIXES)]
    if cfg.board_json:
        board = board_for_images(load_board_json(cfg.board_json), images, cfg.board_json)
    elif (survey / "truth" / "board.json").is_file():
        try:
            board = board_for_images(truth_board(survey), images, str(survey / "truth" / "board.json"))
        except UserInputError as exc:
            return None, {}, str(exc)
    else:
        return None, {}, "no board (give --board-json FILE with pixel corners)"
    try:
        return board, {m: board_accuracy(p, board, cfg.board_inset) for m, p in folders.items()}, ""
    except UserInputError as exc:
        return board, {}, str(exc)
