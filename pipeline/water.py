"""The water stage: the site's water from the survey's own geometry, and each pixel's range.

It reads the raw frames (survey), their poses (sfm), their dense range (dense: camera z, turned into
ray length) and the colour board when there is one (the simulator's, or ``board_json``), and estimates
the formation stack with :func:`eval.water.estimate_water` (which constraint pins which parameter, and
what stays degenerate: its module docstring). Writes into the stage's folder:

    water.json              every parameter with its 95 % interval, the fitted stack, trade-offs, timings, the
                            plots it made (:class:`watergan.water_record.WaterRecord`: written and read there alone)
    observations.npz        the measurement table the estimate was fitted to (:class:`eval.observations.Observations`,
                            each view's surface normal included): the diagnose stage ranks its candidates on it
    summary.txt             one line: eta and B_inf with their intervals
    residuals.png           the fit's residuals against range and image position; fields.png, frames.png: the
                            fields over the image and the gains per frame, where the stack has them
    range/<stem>.png        each pixel's range (:func:`correction_range`), 16-bit millimetres (0: none)

The range maps are this stage's (the dense stage writes camera z, not these): the correct stage inverts
the estimate with them (the physics correction) and the RGB-D restorer takes them.

Range per pixel (:func:`correction_range`): the dense stage's depth map where it agrees with the dense
stage's fused mesh rendered into the view (open3d ray casting from the SfM pose) within ``range_agreement``;
the mesh's range where the depth map has none or disagrees (the mesh fuses every view, so a depth map's
outliers at relief edges do not survive it); a pixel with neither has none (0 in the map). The water is fitted to
a table measured on the dense range alone; the fine grid after it (which serves the corrections) to one measured with
the mesh's range where the dense range has none (:class:`MeshFilledFrames`), so that its views reach the image's
edges, which the correction corrects.

A light rig: when the survey's ``survey.json`` declares ``lights`` (an AUV's strobes: offset_m, tilt_deg,
beam_deg per light), the stack models them with ``artificial_light``, the rig held as declared, its power held
(degenerate with the gain), its light-path attenuation tied to the water's eta (:func:`eval.water.build_stack`;
``--no-light-rig`` leaves them out); without it the strobes' fall-off with distance is read as attenuation.
The light needs each observation's point and surface normal in the camera frame: the points come from the dense
range, the normals from the dense range smoothed by ``normal_smooth_px``
(:func:`watergan.formation.inverse.normals_from_range`), for the estimate (at each sample's source pixel) as for
the correction (:func:`correction_normals`: the range map only where the dense range has none).
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from eval.fields import FIELD_EFFECT, FRAME_CARRY_PCT, GRID_EFFECT
from eval.intervals import on_bound
from eval.observations import WaterFrame
from eval.tracks import Tracks
from eval.water import WaterConfig, WaterEstimate, reads_normals
from watergan.errors import UserInputError
from watergan.formation.effects.image_field import ASPECT
from watergan.formation.inverse import clean_range
from watergan.io import (
    atomic_write_text,
    depth_within,
    read_depth,
    write_depth_png,
    z_to_range,
)
from watergan.water_record import WATER_PLOTS, write_water

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
    range_agreement: float = 0.01
    """The range maps: a pixel keeps its dense range where the fused mesh agrees within this fraction.
    Else it takes the mesh's (the estimate itself reads the dense range)."""
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
    range_dir: str
    """Workspace-relative folder of each frame's range map (<stem>.png, 16-bit millimetres, 0: none)."""
    mesh_fraction: float
    """Share of the pixels whose range came from the fused mesh."""
    range_missing: float
    """Share of the pixels with no range at all."""
    normal_smooth_px: float
    """The smoothing of the dense range's normals the estimate took (the correction takes the same)."""
    board: bool
    """Whether a colour board took part (it pins the gain)."""
    at_bounds: list[str]
    """Fitted parameter components at a bound of their range ("effect.param[i]"): the stack does not fit the
    survey there (an effect is missing or has another form); read the residuals and run the diagnosis."""
    converged: bool
    """Whether the fit converged within ``max_iterations`` (if not, its estimate is where it stopped)."""
    seconds: float
    """Wall time of the stage (estimate and range maps)."""
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


#: Frames :class:`LazyFrames` keeps once made (about 5 MB each at 640x480): a survey of up to this many frames is
#: read once however many passes the measurement makes; a longer one is read again on each pass, in bounded memory.
CACHED_FRAMES = 64


class LazyFrames(Sequence[WaterFrame]):
    """``n`` frames made by ``make(k)`` when indexed, the last :data:`CACHED_FRAMES` kept, so that the water stage's
    memory does not grow with the survey's length."""

    def __init__(self, n: int, make):
        self._n = n
        self._read = functools.lru_cache(maxsize=CACHED_FRAMES)(make)

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(self._n))]
        if not -self._n <= k < self._n:
            raise IndexError(k)
        return self._read(k % self._n)


class SurveyFrames(LazyFrames):
    """The survey's frames as :func:`water_frame` reads them, read when indexed (:class:`LazyFrames`)."""

    def __init__(self, tracks: Tracks, images: Path, depth_dir: Path | None):
        super().__init__(len(tracks.image_names), lambda k: water_frame(tracks, k, images, depth_dir))


def water_frames(tracks: Tracks, images: Path, depth_dir: Path | None) -> SurveyFrames:
    """Raw linear frames, their dense range (ray length; NaN = none) and SfM pose (None: not registered), read on
    demand (:class:`SurveyFrames`)."""
    return SurveyFrames(tracks, images, depth_dir)


def water_frame(tracks: Tracks, k: int, images: Path, depth_dir: Path | None) -> WaterFrame:
    """The k-th frame of :func:`water_frames`."""
    from watergan.data import read_image

    K = np.asarray(tracks.K, float)
    name = str(tracks.image_names[k])
    image = read_image(images / name).astype(np.float32)
    path = depth_dir / f"{Path(name).stem}.png" if depth_dir is not None else None
    if path is not None and path.is_file():
        range_m = z_to_range(read_depth(path), K).astype(np.float32)
    else:
        range_m = np.full(image.shape[:2], np.nan, np.float32)
    return WaterFrame(name=name, image=image, range_m=range_m,
                      world_from_cam=tracks.world_from_cam[k] if tracks.registered[k] else None)


class MeshFilledFrames(LazyFrames):
    """The frames the fine grid's table is measured on: each frame's dense range, and the fused mesh's range
    (:func:`mesh_range`) where the dense range has none; with ``smooth_px``, normals as the correction takes them
    (:func:`correction_normals`; None: none of their own, for a stack that reads none). A stereo pair's dense range
    stops short of the image's edges (the left edge the right camera does not see, a margin on the right) where the
    correction still corrects (from the mesh): without the mesh the table has no views there, and the grid is
    extrapolated into them. Made when indexed (:class:`LazyFrames`); frames without a pose, or ``mesh_ply`` None,
    as they are."""

    def __init__(self, frames: Sequence[WaterFrame], K: np.ndarray, mesh_ply: Path | None, smooth_px: float | None):
        self._frames, self._K, self._mesh, self._smooth = frames, np.asarray(K, float), mesh_ply, smooth_px
        self._scene = None
        super().__init__(len(frames), self._fill)

    @property
    def scene(self):
        """The mesh's ray-casting scene (:func:`mesh_range`) once a frame was filled; None before."""
        return self._scene

    def _fill(self, k: int) -> WaterFrame:
        frame = self._frames[k]
        missing = np.isnan(clean_range(frame.range_m))
        if self._mesh is None or frame.world_from_cam is None or not missing.any():
            return frame
        meshed, self._scene = mesh_range(self._mesh, frame, self._K, self._scene, where=missing)
        range_m = np.where(missing, meshed, frame.range_m).astype(np.float32)
        if self._smooth is None:
            return replace(frame, range_m=range_m)
        return replace(frame, range_m=range_m, normals_cam=correction_normals(frame, range_m, self._K, self._smooth))


def fine_grid_frames(frames: Sequence[WaterFrame], K: np.ndarray, mesh_ply: Path | None, config: WaterConfig,
                     lights: list[dict] | None = None) -> MeshFilledFrames:
    """The frames the water stage measures the fine grid's table on (:class:`MeshFilledFrames`): the fused mesh's
    range where ``mesh_ply`` is a file, their own normals only when the stack reads them
    (:func:`eval.water.reads_normals`)."""
    smooth_px = config.measure.normal_smooth_px if reads_normals(config, len(frames), lights) else None
    return MeshFilledFrames(frames, K, mesh_ply if mesh_ply is not None and Path(mesh_ply).is_file() else None,
                            smooth_px)


def mesh_range(mesh_ply: Path, frame: WaterFrame, K: np.ndarray, scene=None, where: np.ndarray | None = None):
    """(range (H,W) metres along each pixel's ray to the fused mesh, NaN where it misses and outside ``where`` (an
    (H,W) mask of the pixels to cast; None: all); the ray-casting scene for the next frame)."""
    import open3d as o3d

    if scene is None:
        mesh = o3d.io.read_triangle_mesh(str(mesh_ply))
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    h, w = frame.range_m.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) if where is None else np.nonzero(where)
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones(np.shape(xs))], -1)
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True) @ frame.world_from_cam[:3, :3].T
    origin = np.broadcast_to(frame.world_from_cam[:3, 3], rays.shape)
    hits = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, rays], -1).astype(np.float32)))
    t = hits["t_hit"].numpy().astype(np.float64)
    t = np.where(np.isfinite(t), t, np.nan)
    if where is None:
        return t, scene
    out = np.full((h, w), np.nan)
    out[where] = t
    return out, scene


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


def correction_range(frame: WaterFrame, K: np.ndarray, mesh_ply: Path | None, agreement: float, scene=None):
    """(range (H,W) metres, NaN = none; the mask of pixels that took the mesh's range; the ray-casting scene):
    the frame's dense range where the fused mesh misses or agrees within ``agreement`` (relative), else the
    mesh's range (frames without a pose keep their dense range)."""
    r = np.asarray(frame.range_m, np.float64)
    if mesh_ply is None or frame.world_from_cam is None:
        return r, np.zeros(r.shape, bool), scene
    meshed, scene = mesh_range(mesh_ply, frame, K, scene)
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = np.isfinite(r) & (~np.isfinite(meshed) | (np.abs(r / meshed - 1.0) <= agreement))
    from_mesh = ~keep & np.isfinite(meshed)
    return np.where(keep, r, meshed), from_mesh, scene


def correction_normals(frame: WaterFrame, range_m: np.ndarray, K: np.ndarray, smooth_px: float) -> np.ndarray:
    """(H,W,3) camera-frame surface normals for the correction, as the estimate takes them: the frame's own
    (``frame.normals_cam``) when it has them, else those of its dense range smoothed by ``smooth_px``
    (:func:`watergan.formation.inverse.normals_from_range`); and those of the correction's range ``range_m``
    (:func:`correction_range`) where the dense range has none. Not the correction's range throughout: where it
    switches between the dense range and the mesh's, a step of a percent or two tilts the smoothed normals along the
    seam. On the auv preset (seed 0, 47 % of the pixels ranged from the mesh) the normals' error against the truth
    went from a median of 5.3 to 2.3 degrees (p90 21.9 to 7.8) and the board's CIEDE2000 from 1.35 to 1.25 (1.22
    with the true normals); on seed 1 (26 % from the mesh) the error stayed as it was (mean 3.2 degrees) and the
    board went from 1.37 to 1.39 (1.37 with the true normals): ``benchmarks/RESULTS/3d.md``."""
    from eval.observations import frame_normals
    from watergan.formation.inverse import normals_from_range

    normals = frame_normals(frame, K, smooth_px)
    missing = ~np.isfinite(normals).all(axis=-1)
    if missing.any():
        normals[missing] = normals_from_range(range_m, K, smooth_px)[missing]
    return normals


def write_range_maps(out: Path, frames: Sequence[WaterFrame], K: np.ndarray, mesh_ply: Path | None, agreement: float,
                     progress: bool, scene=None) -> tuple[float, float]:
    """Each frame's :func:`correction_range` as ``out/<stem>.png`` (16-bit millimetres); returns (share of the
    pixels ranged from the mesh, share with no range). ``scene``: the mesh's ray-casting scene when already made."""
    from tqdm import tqdm

    from_mesh, missing = [], []
    for f in tqdm(frames, desc="range maps", unit="frame", disable=not progress):
        r, meshed, scene = correction_range(f, K, mesh_ply, agreement, scene)
        r, _ = depth_within(r)  # a long mesh ray or a corner's range beyond what the millimetre PNG holds: no range
        from_mesh.append(float(np.mean(meshed)))
        missing.append(float(np.mean(~(np.isfinite(r) & (r > 0)))))
        write_depth_png(out / f"{Path(f.name).stem}.png", r)
    return float(np.mean(from_mesh)), float(np.mean(missing))


def at_bounds(estimate: WaterEstimate) -> list[str]:
    """The fitted parameter components on a bound of their range (:func:`eval.intervals.on_bound`)."""
    out = []
    for effect in estimate.stack.effects:
        for p in effect.params:
            key = f"{effect.name}.{p.name}"
            if estimate.params.get(key, {}).get("fitted"):
                near = on_bound(key, p, effect.param(p.name).detach().numpy())
                out += [f"{key}[{i}]" if near.size > 1 else key for i in np.flatnonzero(near)]
    return out


def run_water(ws: Workspace, cfg: WaterStage) -> WaterResult:
    """Workspace stage (see the module docstring)."""
    from eval.water import estimate_water

    began = time.perf_counter()
    sfm = ws.require("sfm", "the water estimate")
    dense = ws.result("dense")
    if dense is None:
        raise UserInputError("the water estimate needs each pixel's range: run the dense stage first (`watergan "
                             "dense --workspace WS`), with stereo frames (right/) or enough overlap for MVS")
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
    mesh_ply = ws.path(dense.mesh_ply) if dense.mesh_ply else None
    grid_frames = fine_grid_frames(frames, K, mesh_ply, cfg, lights)
    estimate = estimate_water(frames, K, board=board, config=cfg, lights=lights, normals=True,
                              grid_frames=grid_frames)
    estimate_s = time.perf_counter() - began
    out = ws.stage_dir("water")
    estimate.observations.save(out / "observations.npz")
    atomic_write_text(out / "summary.txt", estimate.summary() + "\n")
    plotted = {name: plot(estimate, out / name) for name, plot in
               (("residuals.png", _plot_residuals), ("fields.png", _plot_fields), ("frames.png", _plot_frames))}
    write_water(out / "water.json", estimate.to_record({name: WATER_PLOTS[name] for name, made in plotted.items()
                                                        if made}))
    mesh_share, missing = write_range_maps(out / "range", frames, K, mesh_ply, cfg.range_agreement, cfg.progress,
                                           grid_frames.scene)
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
                       stack=estimate.stack.to_config(), range_dir=ws.relative(out / "range"),
                       mesh_fraction=mesh_share, range_missing=missing, normal_smooth_px=cfg.measure.normal_smooth_px,
                       board=board is not None, at_bounds=bounds, converged=estimate.converged,
                       seconds=time.perf_counter() - began, estimate_seconds=estimate_s,
                       observations=ws.relative(out / "observations.npz"),
                       n_observations=int(len(estimate.observations.colour)),
                       n_points=int(estimate.observations.n_points))
