"""The evaluation's measuring: every baseline and the restorer measured on the same SfM points and
board, and the paper's tables side by side. The workspace stage that chains these is
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
- Speed: seconds per frame of each method's correction alone, over the first ``TIMED_FRAMES`` frames run one at
  a time (files excluded; the oracle's excludes rendering the true geometry; ours from the correct stage's
  ``summary.json``, which includes file I/O).

With ``EvaluateConfig.scheduler`` (a Dask scheduler address) the baselines (chunks of frames, every
method) and the colour sampling at the SfM observations run on the cluster's workers
(:mod:`watergan.parallel`; the survey and the workspace on a file system they share); the files and
numbers are the same as a local run's. The board, fidelity and depth measurements run here.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from eval.baselines import BASELINES, jaffe_coefficients
from eval.depth import BEST_PLANE, FLOOR, FLOOR_ALIGNED, NET
from watergan.errors import UserInputError
from watergan.io import frame_file, z_to_range

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
    """The raw frames SfM ran on; empty: ``<survey>/images``."""
    methods: tuple[str, ...] = tuple(BASELINES)
    """Baselines to run (names of eval.baselines.BASELINES)."""
    ours_dir: str = ""
    """The restorer's corrected frames; empty: the correct stage's images when it ran."""
    range_source: RangeChoice = RangeChoice.auto
    """Range for Jaffe-McGlamery and Sea-thru: 'dense', 'truth' or 'auto' (dense, else truth)."""
    jaffe_stack: str = ""
    """A formation-stack JSON ([{name, params}]) with the Jaffe-McGlamery coefficients.
    Empty: the simulated survey's true (full) stack."""
    board_json: str = ""
    """A board file with per-image pixel corners (eval.colour.load_board_json).
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


def _camera_K(survey: Path, tracks) -> np.ndarray:
    from watergan.survey_files import read_camera_json

    cam = read_camera_json(survey / "camera.json")
    if cam is None:
        return np.asarray(tracks.K, float)
    return np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])


def fill_nearest(values: np.ndarray) -> np.ndarray:
    """Non-finite entries of (H,W) replaced by the nearest finite one (all NaN: unchanged)."""
    from scipy.ndimage import distance_transform_edt

    bad = ~np.isfinite(values)
    if not bad.any() or bad.all():
        return values
    idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
    return values[tuple(idx)]


class RangeSource:
    """Range (H,W) metres per frame name from the dense stage or the simulator's truth."""

    def __init__(self, kind: str, dense_dir: Path | None, survey: Path, tracks) -> None:
        self.kind = kind
        self.dense_dir = Path(dense_dir).resolve() if dense_dir else None  # absolute: also read on a cluster's workers
        self.truth_dir = (survey / "truth" / "range").resolve()
        self.K = _camera_K(survey, tracks)
        self.fallback: list[str] = []
        depths = tracks.depths()
        names = [str(n) for n in tracks.image_names]
        self.sparse_m = {names[k]: float(np.median(depths[tracks.obs_image == k]))
                         for k in np.unique(tracks.obs_image)}
        self.sparse_all_m = float(np.median(depths)) if len(depths) else 1.0

    @staticmethod
    def choose(requested: str, dense_dir: Path | None, survey: Path) -> str:
        """The range source to use; ``dense_dir``: the dense stage's depth maps (None: it did not run)."""
        if requested not in RANGE_SOURCES:
            raise UserInputError(f"range source must be one of {', '.join(RANGE_SOURCES)}, got '{requested}'")
        dense = dense_dir is not None and Path(dense_dir).is_dir() and any(Path(dense_dir).glob("*.png"))
        truth = (survey / "truth" / "range").is_dir()
        if requested == "dense" and not dense:
            raise UserInputError(f"no dense depth maps ({dense_dir or 'the dense stage did not run'}): run "
                                 f"`watergan dense` first or use --range-source truth on a simulated survey")
        if requested == "truth" and not truth:
            raise UserInputError(f"no simulator range in {survey / 'truth' / 'range'}: --range-source truth needs a "
                                 f"simulated survey; use --range-source dense")
        if requested == "auto":
            return "dense" if dense else "truth" if truth else "none"
        return requested

    def __call__(self, name: str, shape: tuple[int, int]) -> np.ndarray:
        from watergan.io import read_depth

        if self.kind == "truth":
            r = read_depth(frame_file(self.truth_dir, name))
        else:
            path = self.dense_dir / f"{Path(name).stem}.png"
            z = read_depth(path) if path.is_file() else np.full(shape, np.nan)
            if z.shape != shape:
                raise UserInputError(f"dense depth {path} is {z.shape}, the image {shape}")
            r = z_to_range(z, self.K)
        if np.isfinite(r).mean() < 0.01:  # no usable depth: the frame's median sparse depth, everywhere
            self.fallback.append(name)
            return np.full(shape, self.sparse_m.get(name, self.sparse_all_m))
        return fill_nearest(r)


class OracleGeometry:
    """The simulator's true geometry and full stack: one formation state per frame (re-rendered)."""

    def __init__(self, survey: Path) -> None:
        from eval.synth import load_truth
        from eval.synth.camera import intrinsics_for
        from eval.synth.render import make_raycaster
        from eval.synth.scene import build_scene
        from watergan.formation import Stack

        self.survey = Path(survey)
        self.truth = load_truth(survey)
        cfg = self.truth.config
        self.scene = build_scene(cfg.scene, cfg.seed)
        self.caster = make_raycaster(self.scene)
        self.intr = intrinsics_for(cfg.camera)
        self.stack = Stack.from_config(self.truth.effects["full"])
        self.index = {name: k for k, name in enumerate(self.truth.frames)}
        self.stems = {Path(name).stem: k for k, name in enumerate(self.truth.frames)}  # a survey in another format

    def state(self, name: str):
        from eval.synth.render import frame_state, render_view

        cfg = self.truth.config
        k = self.index.get(name, self.stems.get(Path(name).stem))
        if k is None:
            raise UserInputError(f"frame {name} is not in the simulator's truth of {self.truth.root}")
        view = render_view(self.caster, self.scene, self.intr, self.truth.world_from_cam[k], cfg.render)
        return frame_state(view, k, cfg.render.site_depth_m)


def _write_srgb8(path: Path, linear: np.ndarray) -> None:
    """A baseline's frame as an 8-bit sRGB PNG (``path``'s stem; lossless whatever the survey's format: a JPEG's
    block artefacts would be measured as the method's)."""
    from watergan.io import write_srgb8

    write_srgb8(path.with_suffix(".png"), linear)


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


SSIM_WINDOW_PX = 7
"""Side of SSIM's uniform window: scikit-image's default, which these tables have always used (Wang et al. 2004 weigh
an 11x11 window by a Gaussian instead)."""


def ssim_map(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> np.ndarray:
    """(H,W,C) float32 SSIM of (H,W,C) images at each pixel, channel by channel, as scikit-image's
    ``structural_similarity(b, a, channel_axis=2, full=True)`` computes it: local means, sample variances and
    covariance over a 7x7 uniform window (edges mirrored), S = (2 u_a u_b + C1)(2 s_ab + C2) / ((u_a^2 + u_b^2 + C1)
    (s_a^2 + s_b^2 + C2)) with C1 = (0.01 L)^2, C2 = (0.03 L)^2 and L = ``data_range``. OpenCV's box filter does the
    windows in float32, as scikit-image does with SciPy's (benchmarks/RESULTS/restorer.md compares the two)."""
    import cv2

    def mean(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, -1, (SSIM_WINDOW_PX, SSIM_WINDOW_PX), normalize=True, borderType=cv2.BORDER_REFLECT)

    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    n = SSIM_WINDOW_PX * SSIM_WINDOW_PX
    cov_norm = n / (n - 1)
    ua, ub = mean(a), mean(b)
    va = cov_norm * (mean(a * a) - ua * ua)
    vb = cov_norm * (mean(b * b) - ub * ub)
    vab = cov_norm * (mean(a * b) - ua * ub)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    return (2 * ua * ub + c1) * (2 * vab + c2) / ((ua * ua + ub * ub + c1) * (va + vb + c2))


def ssim(a: np.ndarray, b: np.ndarray, data_range: float = 1.0) -> float:
    """Mean SSIM of (H,W,C) images (:func:`ssim_map`) over the pixels whose window lies inside the image, as
    scikit-image's ``structural_similarity`` averages it."""
    pad = (SSIM_WINDOW_PX - 1) // 2
    return float(ssim_map(a, b, data_range)[pad:-pad, pad:-pad].mean(dtype=np.float64))


def fidelity(folder: Path, truth_dir: Path, names: list[str], mask_dir: Path | None = None) -> tuple[float, float]:
    """Mean over frames of PSNR (dB) and SSIM of the sRGB-encoded frames against the in-air truth. With
    ``mask_dir`` (``<stem>.png``, 0 = a pixel the method marked as not corrected, e.g. the physics correction's
    pixels without range) both are taken over the pixels the method corrected: PSNR = 10 log10(1 / MSE) over them,
    and the mean of the SSIM map over them (a mark is not a guess; the share marked is reported beside)."""
    return fidelities({"method": folder}, truth_dir, names, {"method": mask_dir})["method"]


def fidelities(folders: dict[str, Path], truth_dir: Path, names: list[str],
               mask_dirs: dict[str, Path | None] | None = None, threads: int = 2) -> dict[str, tuple[float, float]]:
    """:func:`fidelity` of each method's folder, each truth frame read once, ``threads`` frames at a time (OpenCV's
    decoding and filters release the GIL)."""
    from concurrent.futures import ThreadPoolExecutor

    from eval.colour import read_rgb

    mask_dirs = mask_dirs or {}

    def frame(name: str) -> dict[str, tuple[float, float]]:
        truth = read_rgb(frame_file(truth_dir, name), linear=False)
        out = {}
        for method, folder in folders.items():
            image = read_rgb(frame_file(folder, name), linear=False)
            mask_dir = mask_dirs.get(method)
            keep = _mask(mask_dir / f"{Path(name).stem}.png", image.shape[:2]) if mask_dir is not None else None
            if keep is None:
                mse = float(np.mean((image.astype(np.float64) - truth) ** 2))
                out[method] = (10.0 * np.log10(1.0 / max(mse, 1e-12)), ssim(truth, image))
                continue
            mse = float(np.mean((image[keep] - truth[keep]) ** 2)) if keep.any() else float("nan")
            out[method] = (10.0 * np.log10(1.0 / max(mse, 1e-12)),
                           float(ssim_map(truth, image)[keep].mean()) if keep.any() else float("nan"))
        return out

    with ThreadPoolExecutor(max(1, threads)) as pool:
        per_frame = list(pool.map(frame, names))
    return {m: (float(np.mean([f[m][0] for f in per_frame])), float(np.mean([f[m][1] for f in per_frame])))
            for m in folders}


def marked_share(mask_dir: Path, names: list[str]) -> float:
    """The share of the frames' pixels a method marked as not corrected (0 in ``mask_dir/<stem>.png``)."""
    shares = [1.0 - float(_mask(mask_dir / f"{Path(name).stem}.png", None).mean()) for name in names]
    return float(np.mean(shares)) if shares else 0.0


def _mask(path: Path, hw: tuple[int, int] | None) -> np.ndarray:
    import cv2

    mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise FileNotFoundError(f"mask {path} is missing or unreadable")
    if hw is not None and mask.shape != hw:
        raise ValueError(f"mask {path} is {mask.shape[1]}x{mask.shape[0]}, the frame {hw[1]}x{hw[0]}")
    return mask > 0


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


def verdict_lines(metrics: list[tuple[str, dict[str, float], str]], methods: list[str]) -> list[str]:
    """Plain sentences: each metric on which ours loses to another method, then what ours beats.
    ``metrics``: (name, method -> value, 'lower' | 'higher')."""
    if OURS not in methods:
        return []
    losses, wins = [], []
    for name, values, better in metrics:
        mine = values.get(OURS)
        if mine is None or not np.isfinite(mine):
            continue
        beaten = []
        for m in methods:
            v = values.get(m)
            if m == OURS or v is None or not np.isfinite(v):
                continue
            worse = mine > v if better == "lower" else mine < v
            if worse:
                losses.append(f"ours loses to {LABELS.get(m, m)} on {name}: {mine:.3g} vs {v:.3g}")
            elif v != mine:
                beaten.append(LABELS.get(m, m))
        if beaten:
            wins.append(f"ours beats {', '.join(beaten)} on {name} ({mine:.3g})")
    return losses + wins


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


# ------------------------------------------------------------------------------------------ stage


@dataclass(frozen=True, eq=False)
class BaselineChunk:
    """Frames to correct with every method (plain, picklable values: it may run on a Dask worker)."""

    names: tuple[str, ...]
    images: Path
    methods: tuple[str, ...]
    out_dir: Path
    ranges: RangeSource | None
    """Range per frame (plain data; the frames that fell back to a constant range are returned)."""
    coefficients: dict | None
    oracle_survey: Path | None
    """The simulated survey whose true geometry the oracle re-renders (built once per chunk)."""


#: Frames of a local run that every baseline corrects one at a time, timed, before the rest run two at a time: the
#: speed table's seconds per frame are theirs, each method alone on the machine.
TIMED_FRAMES = 8
#: Frames corrected at once after the timed ones in a local run (the methods and the file I/O release the GIL in
#: OpenCV, NumPy and torch; each lane on one torch thread).
BASELINE_LANES = 2


def baseline_chunk(job: BaselineChunk, geometry=None, progress: bool = False, timed: int | None = None
                   ) -> tuple[dict[str, float], int, list[str]]:
    """Every frame of ``job`` through every method into ``out_dir/<method>/<name>`` (8-bit sRGB, atomically).
    Returns each method's correction seconds summed over the first ``timed`` frames (None: all), which run one at a
    time, the number of those frames, and the frames without a usable range (in ``job.names`` order); the frames
    after them run ``BASELINE_LANES`` at a time, untimed. ``geometry``: the oracle's, when already built (local
    runs); else built here from ``oracle_survey``."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from watergan.device import single_torch_thread

    seconds = dict.fromkeys(job.methods, 0.0)
    if "oracle" in job.methods and geometry is None:
        geometry = OracleGeometry(job.oracle_survey)
    before = len(job.ranges.fallback) if job.ranges is not None else 0
    timed = len(job.names) if timed is None else min(timed, len(job.names))

    def correct(name: str, spent: dict[str, float]) -> None:
        _correct_frame(name, job.images, list(job.methods), job.out_dir, spent, job.ranges, job.coefficients,
                       geometry)
        bar.update(1)

    with single_torch_thread(), tqdm(total=len(job.names), desc="baselines", unit="frame",
                                     disable=not progress) as bar:  # the oracle's renders: torch's pool contends
        for name in job.names[:timed]:
            correct(name, seconds)
        with ThreadPoolExecutor(BASELINE_LANES) as pool:
            list(pool.map(lambda name: correct(name, dict.fromkeys(job.methods, 0.0)), job.names[timed:]))
    fallback = set(job.ranges.fallback[before:]) if job.ranges is not None else set()
    return seconds, timed, [n for n in job.names if n in fallback]


def run_baselines(names: list[str], images: Path, methods: list[str], out_dir: Path, ranges=None,
                  coefficients: dict | None = None, geometry=None, scheduler=None,
                  chunk_size: int = 8, progress: bool = True) -> dict[str, float]:
    """Correct every frame with every method into ``out_dir/<method>/<name>`` (8-bit sRGB); returns
    the seconds per frame of each method's correction alone.

    ``scheduler``: empty or None runs here: the first ``TIMED_FRAMES`` frames one at a time (the seconds per frame
    are theirs), the rest ``BASELINE_LANES`` at a time; a Dask scheduler address or ``distributed.Client`` sends
    ``chunk_size`` frames per task to the cluster (:mod:`watergan.parallel`; folders on a file system the workers
    share; the oracle's geometry is rebuilt once per chunk; every frame timed). The files are the same either way.
    ``ranges.fallback`` lists the frames that had no usable range."""
    from watergan.parallel import chunks, is_distributed, map_tasks, shared_path

    needs_range = any(BASELINES[m].needs_range for m in methods)
    frame_ranges = ranges if needs_range else None
    if not is_distributed(scheduler):
        results = [baseline_chunk(BaselineChunk(tuple(names), images, tuple(methods), out_dir, frame_ranges,
                                                coefficients, None), geometry, progress, TIMED_FRAMES)]
    else:
        survey = shared_path(geometry.survey) if geometry is not None else None
        jobs = [BaselineChunk(tuple(part), shared_path(images), tuple(methods), shared_path(out_dir), frame_ranges,
                              coefficients, survey) for part in chunks(names, chunk_size)]
        results = map_tasks(baseline_chunk, jobs, scheduler, desc="baselines", unit="chunk", progress=progress)
    if frame_ranges is not None:
        frame_ranges.fallback = [n for *_, fell_back in results for n in fell_back]
    seconds = {m: sum(part[m] for part, *_ in results) for m in methods}
    timed = sum(count for _, count, _ in results)
    return {m: s / max(timed, 1) for m, s in seconds.items()}


def _correct_frame(name: str, images: Path, methods: list[str], out_dir: Path, seconds: dict[str, float], ranges,
                   coefficients: dict | None, geometry) -> None:
    """One frame through every method (adds each method's correction time to ``seconds``)."""
    from eval.colour import read_rgb

    image = read_rgb(images / name)
    range_m = ranges(name, image.shape[:2]) if ranges is not None else None
    state = geometry.state(name) if "oracle" in methods else None
    for m in methods:
        start = time.perf_counter()
        if m == "jaffe":
            corrected = BASELINES[m].fn(image, range_m, **coefficients)
        elif m == "oracle":
            corrected = BASELINES[m].fn(image, state, geometry.stack)
        elif BASELINES[m].needs_range:
            corrected = BASELINES[m].fn(image, range_m)
        else:
            corrected = BASELINES[m].fn(image)
        seconds[m] += time.perf_counter() - start
        _write_srgb8(out_dir / m / name, corrected)


def method_inputs(cfg: EvaluateConfig, survey: Path, tracks, simulated: bool, dense_dir: Path | None):
    """(methods that can run, skipped method -> why, range source or None, Jaffe coefficients, oracle geometry).
    ``dense_dir``: the dense stage's depth maps, None when it did not run."""
    skipped: dict[str, str] = {}
    range_kind = RangeSource.choose(cfg.range_source, dense_dir, survey)
    ranges = RangeSource(range_kind, dense_dir, survey, tracks) if range_kind != "none" else None
    coefficients = None
    if "jaffe" in cfg.methods:
        if cfg.jaffe_stack:
            path = Path(cfg.jaffe_stack)
            if not path.is_file():
                raise UserInputError(f"Jaffe-McGlamery stack file {path} does not exist")
            coefficients = jaffe_coefficients(json.loads(path.read_text()))
        elif simulated:
            coefficients = jaffe_coefficients(json.loads((survey / "truth" / "effects.json").read_text())["full"])
        else:
            skipped["jaffe"] = "no coefficients: give a formation-stack JSON with --jaffe-stack"
    geometry = None
    if "oracle" in cfg.methods:
        if simulated:
            geometry = OracleGeometry(survey)
        else:
            skipped["oracle"] = "needs the simulator's truth (not a simulated survey)"
    methods = []
    for m in cfg.methods:
        if m in skipped:
            continue
        if BASELINES[m].needs_range and ranges is None:
            skipped[m] = "no range: run the dense stage (or --range-source truth on a simulated survey)"
            continue
        methods.append(m)
    return methods, skipped, ranges, coefficients, geometry


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
