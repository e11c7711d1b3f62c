"""The water stage: the site's water from the survey's own geometry.

It reads the raw frames (survey), their poses (sfm), their dense range (dense: camera z, turned into
ray length), the range stage's range maps (for the fine grid) and the colour board when there is one (the
simulator's, or ``board_json``), and estimates the formation stack with :func:`eval.water.estimate_water` (which
constraint pins which parameter, and what stays degenerate: its module docstring). Writes into the stage's folder:

    water.json              every parameter with its 95 % interval, the fitted stack, trade-offs, timings, the
                            plots it made (:class:`watergan.water_record.WaterRecord`: written and read there alone)
    observations.npz        the measurement table the estimate was fitted to (:class:`eval.observations.Observations`,
                            each view's surface normal included): the diagnose stage ranks its candidates on it
    summary.txt             one line: eta and B_inf with their intervals
    residuals.png           the fit's residuals against range and image position; fields.png, frames.png: the
                            fields over the image and the gains per frame, where the stack has them

Each pixel's range is the range stage's (:mod:`pipeline.range`): the water is fitted to a table measured on the dense
range alone; the fine grid after it (which serves the corrections) to one measured on the dense range filled with the
range stage's maps where it has none (:class:`pipeline.range.MeshFilledFrames`), so that its views reach the image's
edges, which the correction corrects.

A light rig: when the survey's ``survey.json`` declares ``lights`` (an AUV's strobes: offset_m, tilt_deg,
beam_deg per light), the stack models them with ``artificial_light``, the rig held as declared, its power held
(degenerate with the gain), its light-path attenuation tied to the water's eta (:func:`eval.water.build_stack`;
``--no-light-rig`` leaves them out); without it the strobes' fall-off with distance is read as attenuation.
The light needs each observation's point and surface normal in the camera frame: the points come from the dense
range, the normals from the dense range smoothed as the range stage records (its ``normal_smooth_px``), for the
estimate (at each sample's source pixel) as for the correction (:func:`pipeline.range.correction_normals`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from eval.observations import WaterFrame
from eval.tracks import Tracks
from eval.water import WaterConfig, WaterEstimate, reads_normals
from eval.water.estimate import stderr_line
from eval.water.fields import FIELD_EFFECT, FRAME_CARRY_PCT, GRID_EFFECT
from eval.water.intervals import on_bound
from watergan.formation.effects.image_field import ASPECT
from watergan.io import atomic_write_text
from watergan.water_record import WATER_PLOTS, write_water

from .range import MeshFilledFrames, require_dense, water_frames
from .workspace import Workspace


@dataclass(frozen=True)
class WaterStage(WaterConfig):
    """The water stage's configuration: the estimate's (:class:`eval.water.WaterConfig`) and what the stage itself
    reads and writes (the options are the same, flat)."""

    add: tuple[str, ...] = ()
    """Effects added to the stack's (as watergan run --add does: e.g. what the diagnosis found)."""
    board_json: str = ""
    """A colour-board file (per-image pixel corners of the board's patches). Empty: the simulated survey's board
    when there is one, else none (then the gain is held)."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bars."""


@dataclass
class WaterResult:
    water_json: str
    """Workspace-relative path of water.json."""
    summary: str
    """One line: eta and B_inf with their 95 % intervals."""
    stack: list[dict]
    """The estimated formation stack ({name, params} entries)."""
    board: bool
    """Whether a colour board took part (it pins the gain)."""
    at_bounds: list[str]
    """Fitted parameter components at a bound of their range ("effect.param[i]"): the stack does not fit the
    survey there (an effect is missing or has another form); read the residuals and run the diagnosis."""
    converged: bool
    """Whether the fit converged within ``max_iterations`` (if not, its estimate is where it stopped)."""
    seconds: float
    """Wall time of the stage (estimate, plots and files)."""
    estimate_seconds: float
    """Wall time of the estimate alone."""
    observations: str
    """Workspace-relative path of the measurement table the estimate was fitted to (observations.npz,
    :class:`eval.observations.Observations`; frame indices into the sfm stage's image list): the diagnose stage ranks
    its candidates on it."""
    n_observations: int
    """Views in that table (board rows not counted)."""
    n_points: int
    """Surface points in that table."""


def fine_grid_frames(frames: Sequence[WaterFrame], K: np.ndarray, range_dir: Path | None, config: WaterConfig,
                     lights: list[dict] | None = None) -> MeshFilledFrames:
    """The frames the water stage measures the fine grid's table on (:class:`pipeline.range.MeshFilledFrames`): the
    range stage's maps (in ``range_dir``) where the dense range has none, their own normals only when the stack reads
    them (:func:`eval.water.reads_normals`)."""
    smooth_px = config.measure.normal_smooth_px if reads_normals(config, len(frames), lights) else None
    return MeshFilledFrames(frames, K, range_dir if range_dir is not None and Path(range_dir).is_dir() else None,
                            smooth_px)


def survey_lights(survey: Path) -> list[dict]:
    """The light rig the survey's ``survey.json`` declares (empty without one)."""
    from watergan.survey_files import read_survey_json

    path = survey / "survey.json"
    return list(read_survey_json(path).get("lights") or []) if path.is_file() else []


def _board(ws: Workspace, cfg: WaterStage, survey: Path):
    from eval.colour import board_for_images, load_board_json, truth_board
    from watergan.data import IMAGE_SUFFIXES, list_files

    images = [p.name for p in list_files(survey / "images", IMAGE_SUFFIXES)]
    if cfg.board_json:
        return board_for_images(load_board_json(cfg.board_json), images, cfg.board_json)
    if (survey / "truth" / "board.json").is_file():
        return board_for_images(truth_board(survey), images, str(survey / "truth" / "board.json"))
    return None


def _plot_residuals(estimate: WaterEstimate, path: Path) -> bool:
    """Residual (observed - fitted, linear) against range and against the distance from the image centre; False
    (nothing written) without the estimate's residuals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = estimate.residuals
    if res is None:
        return False
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
    for ax, key, label in ((axes[0], "range_m", "range (m)"), (axes[1], "radius", "distance from the image centre "
                                                                                  "(normalised)")):
        x = res[key]
        edges = np.quantile(x, np.linspace(0, 1, 16))
        centres = 0.5 * (edges[1:] + edges[:-1])
        for c, colour in enumerate("rgb"):
            which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(centres) - 1)
            means = np.array([res["residual"][which == b, c].mean() if (which == b).any() else np.nan
                              for b in range(len(centres))])
            ax.plot(centres, means, "-o", color=colour, ms=3, label="RGB"[c])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(label)
    axes[0].set_ylabel("mean residual (linear)")
    axes[0].legend(fontsize=8)
    fig.suptitle("water fit: residuals binned (flat at 0: nothing left along the axis)", fontsize=9)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return True


def total_fields(stack, cols: int, rows: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(F, G) (rows, cols, 3) of everything the stack carries on image position beyond its physics: the fields
    fitted beside the water (``image_field``) and the fine grid fitted after it (``image_grid``), composed as they
    apply (F = F_field F_grid, G = F_grid G_field + G_grid); None when it carries neither."""
    if FIELD_EFFECT not in stack.names and GRID_EFFECT not in stack.names:
        return None
    f, g = np.ones((rows, cols, 3)), np.zeros((rows, cols, 3))
    if FIELD_EFFECT in stack.names:
        f, g = stack[FIELD_EFFECT].on_grid(cols, rows)
    if GRID_EFFECT in stack.names:
        f_grid, g_grid = stack[GRID_EFFECT].on_grid(cols, rows)
        f, g = f * f_grid, g * f_grid + g_grid
    return f, g


def _plot_fields(estimate: WaterEstimate, path: Path, grid: int = 49) -> bool:
    """The fields over the image per channel (:func:`total_fields`): F (top, 1 = nothing) and G (bottom,
    0 = nothing); False (nothing written) when the stack has none."""
    fields = total_fields(estimate.stack, grid, int(round(grid * ASPECT)))
    if fields is None:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f, g = fields
    fig, axes = plt.subplots(2, 3, figsize=(10, 5))
    f_span = max(float(np.abs(f - 1).max()), 0.02)
    g_span = max(float(np.abs(g).max()), 0.002)
    for c, name in enumerate(("red", "green", "blue")):
        top = axes[0, c].imshow(f[..., c], cmap="RdBu_r", vmin=1 - f_span, vmax=1 + f_span)
        bottom = axes[1, c].imshow(g[..., c], cmap="PuOr_r", vmin=-g_span, vmax=g_span)
        axes[0, c].set_title(f"{name}: F {f[..., c].min():.3f} to {f[..., c].max():.3f}", fontsize=8)
        axes[1, c].set_title(f"{name}: G {g[..., c].min():+.4f} to {g[..., c].max():+.4f}", fontsize=8)
        for ax in axes[:, c]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.colorbar(top, ax=axes[0].tolist(), fraction=0.02, label="multiplicative F")
    fig.colorbar(bottom, ax=axes[1].tolist(), fraction=0.02, label="additive G (linear)")
    fine = " and the fine grid after it" if GRID_EFFECT in estimate.stack.names else ""
    fig.suptitle(f"what the stack lacks on image position: the fields fitted beside the water{fine} (flat: nothing)",
                 fontsize=9)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return True


def _plot_frames(estimate: WaterEstimate, path: Path) -> bool:
    """The gains per frame (``frame_gain``) per channel against the frame's index (1 = nothing); False (nothing
    written) when the stack has none."""
    if estimate.frames is None:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames, gain = np.asarray(estimate.frames["frames"]), np.asarray(estimate.frames["gain"])
    fig, ax = plt.subplots(figsize=(8, 3))
    ax.axhline(1.0, color="0.6", lw=0.8)
    for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(frames, gain[:, c], ".-", color=colour, lw=0.8, ms=4)
    ax.set_xlabel("frame index")
    ax.set_ylabel("gain exp(g)")
    carried = ("fitted beside the water" if estimate.frames["carried"] else
               f"measured, not carried (under {FRAME_CARRY_PCT:.0f} %: the water is fitted without them)")
    ax.set_title("what the stack lacks from frame to frame (exposure, white balance, a drifting water):\n"
                 f"the gains per frame, {carried} (flat at 1: nothing)", fontsize=8)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return True


def at_bounds(estimate: WaterEstimate) -> list[str]:
    """The fitted parameter components on a bound of their range (:func:`eval.water.intervals.on_bound`)."""
    out = []
    for effect in estimate.stack.effects:
        for p in effect.params:
            key = f"{effect.name}.{p.name}"
            if (entry := estimate.params.get(key)) is not None and entry.fitted:
                near = on_bound(key, p, effect.param(p.name).detach().numpy())
                out += [f"{key}[{i}]" if near.size > 1 else key for i in np.flatnonzero(near)]
    return out


def range_settings(ws: Workspace, cfg: WaterStage) -> WaterStage:
    """``cfg`` with the range stage's smoothing of the dense range's normals (the correction takes the same); a clear
    error before the range stage ran."""
    ranges = ws.require("range", "the water estimate")
    return replace(cfg, measure=replace(cfg.measure, normal_smooth_px=ranges.normal_smooth_px))


def run_water(ws: Workspace, cfg: WaterStage) -> WaterResult:
    """Workspace stage (see the module docstring)."""
    from eval.water import estimate_water

    began = time.perf_counter()
    sfm = ws.require("sfm", "the water estimate")
    dense = require_dense(ws, "the water estimate and its range maps")
    cfg = range_settings(ws, cfg)
    survey = ws.stage_dir("survey")
    tracks = Tracks.load(ws.path(sfm.tracks))
    K = np.asarray(tracks.K, float)
    frames = water_frames(tracks, survey / "images", ws.path(dense.depth_dir))
    board = _board(ws, cfg, survey)
    cfg = replace(cfg, range_scale_sd=max(cfg.range_scale_sd, float(sfm.scale_spread)),
                  effects=tuple(dict.fromkeys(cfg.effects + cfg.add)))
    if sfm.scale_method == "none":
        print("water: the SfM model has no metric scale: attenuation and backscatter coefficients are per SfM "
              "unit, not per metre (give a stereo rig, a board or nav_altitude_m)", file=sys.stderr)
    lights = survey_lights(survey)
    grid_frames = fine_grid_frames(frames, K, ws.path(ws.result("range").range_dir), cfg, lights)
    estimate = estimate_water(frames, K, board=board, config=cfg, lights=lights, normals=True,
                              grid_frames=grid_frames, say=stderr_line if cfg.progress else None)
    estimate_s = time.perf_counter() - began
    out = ws.stage_dir("water")
    estimate.observations.save(out / "observations.npz")
    atomic_write_text(out / "summary.txt", estimate.summary() + "\n")
    plotted = {name: plot(estimate, out / name) for name, plot in
               (("residuals.png", _plot_residuals), ("fields.png", _plot_fields), ("frames.png", _plot_frames))}
    write_water(out / "water.json", estimate.to_record({name: WATER_PLOTS[name] for name, made in plotted.items()
                                                        if made}))
    print(estimate.summary(), flush=True)
    if not estimate.converged:
        print(f"water: the fit had not converged after {estimate.iterations} iterations (raise "
              "`--fit-max-iterations`, `--water-fit-max-iterations` in `watergan run`); "
              "its parameters are where it stopped", file=sys.stderr)
    bounds = at_bounds(estimate)
    if bounds:
        print(f"water: {', '.join(bounds)} at a bound of their range: the stack does not fit this survey (an effect "
              f"is missing or has another form); see {ws.relative(out / 'residuals.png')} and run the diagnosis",
              file=sys.stderr)
    return WaterResult(water_json=ws.relative(out / "water.json"), summary=estimate.summary(),
                       stack=estimate.stack.to_config(), board=board is not None, at_bounds=bounds,
                       converged=estimate.converged,
                       seconds=time.perf_counter() - began, estimate_seconds=estimate_s,
                       observations=ws.relative(out / "observations.npz"),
                       n_observations=int(len(estimate.observations.colour)),
                       n_points=int(estimate.observations.n_points))
