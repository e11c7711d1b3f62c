"""The discovery loop: fit the formation model to multi-view measurements, show where it fails,
name the missing effect, and keep a ledger of model versions.

    from pipeline.diagnose import run_diagnose       # a workspace or a survey folder
    result = run_diagnose("WORKSPACE_OR_SURVEY", DiagnoseConfig(effects=("attenuation", ...)))
    print(result.verdict)

Pieces (each usable alone):

- :mod:`eval.diagnose_measure`: the measurement table (:mod:`eval.observations`: points seen in >= 3 views),
  geometry from the SfM tracks of a workspace or from the simulator's truth; or, in a workspace where the water
  stage ran, the water estimate's own table (:func:`eval.diagnose_measure.with_survey`), so the water and the
  ranking are judged on the same views.
- :mod:`eval.fit`: the one fitter (the water's too): a stack with per-point albedos; held-out error; Laplace
  uncertainties and bootstrap intervals.
- :mod:`eval.diagnose_residuals`: residuals binned along every axis, structure scores, plots, PLY.
- this module: candidate ranking, verdict, ledger, and :func:`diagnose` (all of it on one survey);
  the workspace stage is :func:`pipeline.diagnose.run_diagnose_stage`.

Candidate ranking: every registered effect not in the stack is a candidate unless it needs whole
images (``needs_image``), has learned layers, needs a state field the measurements lack, or acts
identically on every view of a point at its initial values and at random values inside its bounds
(then the per-point albedo absorbs it and multi-view colour cannot see it; an effect named with
``--candidates`` is fitted anyway, and the skip says so). Each candidate is inserted by ``rank``
into the model *as configured* and the whole stack is refitted (albedos start from the base fit; a
declared light rig is held; effects with many local minima start from the best point of the grid
their class declares, ``start_grid``, also when added with ``--add``). Relative held-out change
d = RMSE_candidate / RMSE_base - 1; its significance is a paired bootstrap over held-out points
(p = fraction of resamples with d >= 0). A candidate is accepted when p < ``alpha`` and
d <= -``min_improvement``; the best accepted one is the verdict. Axes whose structure score
exceeds ``structure_threshold`` and whose structure is at least ``structure_fraction`` of the
residual RMSE after the verdict's model are reported as unexplained.

Ledger (:mod:`eval.ledger`; ``model_ledger.jsonl`` in the diagnose stage's folder, or SURVEY/diagnose/): one JSON
record per fit with time, kind ("model" or "candidate"), stack, fitted values, held-out and training RMSE, the
number of observations and the geometry source; model records of a workspace also carry what the eval stage
measured of the raw frames, the physics correction and the restorer: each one's colour consistency (mean over
points of the per-channel variance of c / (R + G + B) across views) and colour-board error (mean CIEDE2000 over
patches), so a model version can be read beside what its corrected images achieve.
"""

from __future__ import annotations

import itertools
import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from watergan.formation import Counts, Effect, MissingInputError, Stack, available, get
from watergan.formation.inverse import affine_images
from watergan.formation.rig import declared_rig, held_rig, rig_settings
from watergan.io import atomic_write_json, atomic_write_text

from .bootstrap import paired_rmse_change
from .diagnose_measure import GeometrySource, MeasureConfig, check_survey_folder, measure_survey
from .diagnose_residuals import (
    ResidualConfig,
    amplitudes,
    analyse,
    orientations_line,
    plot_residuals,
    scores,
    surface_orientations,
    write_residual_ply,
)
from .diagnose_verdict import (
    added_form_misfit,
    fields_share_check,
    form_conflict,
    same_colour,
    stand_in,
    unexplained_axes,
    verdict_text,
    why_implausible,
)
from .fit import (
    DEFAULT_EFFECTS,
    FitConfig,
    copy_stack,
    insert_by_rank,
    observation_state,
    soft_l1,
)
from .heldout import FitResult, fit_stack, make_split
from .ledger import LEDGER_NAME, append_ledger, plot_ledger, read_ledger
from .observations import Observations

#: Training observations on which the start grid is evaluated.
START_GRID_OBS = 300


@dataclass(frozen=True)
class DiagnoseConfig:
    """The diagnose stage."""

    geometry: GeometrySource = GeometrySource.auto
    """Where the 3D points and their views come from: "water" (the water stage's measurement table, the
    one its estimate was fitted to: a workspace only), "sfm" (the sfm stage's tracks, sampled and measured
    here), "truth" (the simulator's depth maps and poses) or "auto" (water when the workspace's water stage
    saved its table, else sfm when the workspace has tracks, else truth when the survey is simulated). On the
    water's table the measurement options other than the patch's size (the gradient-energy patch) do not apply."""
    effects: tuple[str, ...] = ()
    """Effects of the current model (empty: the survey's visible stack from truth/effects.json when
    simulated, with its parameters as the starting point, else attenuation,backscatter,vignetting,gain)."""
    add: tuple[str, ...] = ()
    """Effects added to the model (by rank) before fitting: the next model version."""
    candidates: tuple[str, ...] = ()
    """Candidate effects to try (empty: every registered effect that qualifies)."""
    measure: MeasureConfig = field(default_factory=MeasureConfig)
    """Point sampling and patch measurement."""
    fit: FitConfig = field(default_factory=FitConfig)
    """Fitting."""
    residuals: ResidualConfig = field(default_factory=ResidualConfig)
    """Residual binning."""
    min_improvement: float = 0.03
    """Smallest relative held-out error drop that counts as an improvement."""
    alpha: float = 0.05
    """Significance level of the paired bootstrap."""
    bootstrap: int = 2000
    """Bootstrap resamples of the held-out points."""
    structure_threshold: float = 3.0
    """Structure score above which an axis is reported as unexplained (with the structure fraction, next)."""
    structure_fraction: float = 0.1
    """... and the least amplitude of the structure (RMS of the bin means about their centre) as a
    fraction of the residual RMSE: with many observations tiny biases (a few 1e-4 in the darkest
    patches) score above 3 without mattering."""
    plots: bool = True
    """Write residual plots and the PLY."""
    progress: bool | None = field(default=None, metadata={"hash": False})
    """Progress bars (None: when the output is a terminal)."""


@dataclass(frozen=True)
class CandidateResult:
    """One candidate's refit. ``change``: relative held-out RMSE change (negative = better);
    ``ci95``: bootstrap 95% interval of it; ``p``: fraction of resamples with no improvement;
    ``flattened``: the axis whose structure score dropped most, with the drop; ``scores`` and
    ``structure`` (amplitude / residual RMSE) per axis after the refit; ``implausible``: why its fitted
    values are not physical (see :func:`why_implausible`; "" when they are): such a candidate is never
    significant, however much it explains."""

    name: str
    heldout_rmse: float
    change: float
    ci95: tuple[float, float]
    p: float
    significant: bool
    flattened: str
    flattened_drop: float
    params: dict
    scores: dict
    structure: dict
    seconds: float
    implausible: str = ""
    fields_explained: float | None = None
    """The share of the water's fields over the image it reproduces (:func:`fields_explained`); None: no fields,
    or not an image-position candidate."""
    partial: bool = False
    """Accepted (when significant) as a partial step: it reproduces part of the water's fields over the image, and
    what remains is of another form (:func:`eval.diagnose_verdict.fields_share_check`)."""


@dataclass(frozen=True)
class DiagnoseResult:
    """What the diagnose stage wrote (``out_dir``, absolute) and found: the model, its held-out
    RMSE, the verdict, the best significant candidate (or None), the ranking, the skipped effects
    with reasons, axes with unexplained structure, the base model's structure scores, the geometry
    source ("truth", "sfm (scale: METHOD)" or "water stage (scale: METHOD)"), wall time, and which
    measurements were used."""

    out_dir: str
    stack: list[str]
    heldout_rmse: float
    n_points: int
    n_obs: int
    verdict: str
    best: str | None
    ranking: list[dict]
    skipped: dict[str, str]
    unexplained_axes: list[str]
    scores: dict[str, float]
    geometry: str
    seconds: float
    measurements: str = ""
    """Which measurement table the fit and the ranking used, with its size (e.g. "water stage (scale: stereo)
    (04_water/observations.npz): 25403 observations of 4560 points; its 214 board rows not used ...")."""
    surfaces: dict = field(default_factory=dict)
    """The orientations of the surfaces the points lie on (:func:`eval.diagnose_residuals.surface_orientations`;
    {} when the table holds no normals)."""


#: Hidden parameters of the small survey other than the effects' ``simulation_params``: caustics' cell
#: size and drift away from the effect's initial values (0.4 m, 0.07 m/frame), so that the fit has to
#: find them.
SMALL_SURVEY_HIDDEN = {"caustics": {"wavelength_m": 0.6, "drift_m_per_frame": 0.05}}


def small_survey_config(hidden: list | tuple = (), seed: int = 1, width_px: int = 160):
    """The small simulated survey the diagnosis is tested and benchmarked on: the ``tiny`` preset
    with 2 lines of 8 frames (``width_px`` x 3/4, 70 degrees wide, 80% forward overlap), one
    camera, a 2-view RGB-D set, and 40 mm texels. ``hidden``: effect names (parameters from the
    class's ``simulation_params``, then SMALL_SURVEY_HIDDEN) or ``{"name", "params"}`` entries.

    Why 40 mm texels: the renderer casts one ray per pixel, so the preset's 5 mm texels seen at
    ~22 mm per pixel alias, a view-dependent colour noise (held-out RMSE about 0.01 on a survey with
    nothing hidden) that a real camera, which integrates over each pixel, does not record; at
    40 mm the floor is about 0.003, near the sensor noise."""
    from eval.synth import make_config
    from eval.synth.camera import CameraConfig
    from eval.synth.rgbd import RGBDConfig

    entries = tuple({"name": h, "params": {**get(h).simulation_params, **SMALL_SURVEY_HIDDEN.get(h, {})}}
                    if isinstance(h, str) else dict(h) for h in hidden)
    for entry in entries:
        get(entry["name"])
    cfg = make_config("tiny", seed=seed)
    return replace(cfg, camera=CameraConfig(width_px=width_px, height_px=width_px * 3 // 4, hfov_deg=70.0),
                   scene=replace(cfg.scene, texel_m=0.04),
                   trajectory=replace(cfg.trajectory, frames_per_line=8, forward_overlap=0.8, stereo=False),
                   rgbd=RGBDConfig(n_scenes=1, views_per_scene=2, width_px=32, height_px=24, scene_size_m=8.0,
                                   grid_spacing_m=0.25),
                   formation=replace(cfg.formation, hidden=entries))


def default_stack(survey: Path, effects: tuple[str, ...], model: list[dict] | None = None,
                  counts: Counts | None = None) -> Stack:
    """The model to diagnose: the named effects (initial values; ``counts`` sizes their per-frame and
    per-light parameters), or ``model`` (a stack configuration: the site water the water stage estimated, less
    its nuisance fields, whose content is what the diagnosis looks for), or the survey's visible stack with its
    parameters when simulated, or attenuation, backscatter, vignetting and gain."""
    if effects:
        return Stack.ordered(list(effects), counts)
    if model:
        return Stack.from_config([e for e in model if not get(e["name"]).nuisance], counts)
    truth_effects = survey / "truth" / "effects.json"
    if truth_effects.is_file():
        return Stack.from_config(json.loads(truth_effects.read_text())["visible"], counts)
    return Stack.from_names(list(DEFAULT_EFFECTS), counts)


def survey_counts(meas: Observations) -> Counts:
    """The survey's frames and declared lights: the rows of per-frame and per-light parameters."""
    return Counts(frames=len(meas.frames), lights=len(meas.lights) or None)


def frozen_settings(stack: Stack, meas: Observations) -> dict[str, tuple[str, ...]]:
    """Known settings that are not fitted: the declared light rig (``rig_params``, :func:`held_rig`)."""
    return held_rig(stack, meas.lights)


def make_effect(name: str, meas: Observations):
    """A candidate effect at its initial values for this survey (one row per frame or light of its per-frame
    and per-light parameters; the declared light rig for one with ``rig_params``)."""
    cls = get(name)
    return cls(counts=survey_counts(meas), **rig_settings(cls, meas.lights))


def grid_start(trial: Stack, name: str, base: FitResult, meas: Observations, split, config: DiagnoseConfig) -> None:
    """Set the starting values of candidate ``name`` in ``trial`` (in place) to the best point of its
    start grid (``start_grid`` of the class; nothing without one): each combination
    is scored by the soft-L1 loss of the base fit (parameters and albedos) with the candidate added,
    on ``START_GRID_OBS`` random training observations; the lowest wins. See :func:`grid_losses`."""
    grid = get(name).start_grid
    if not grid:
        return
    rng = np.random.default_rng([config.fit.seed, 17])
    obs = np.sort(rng.permutation(split.train_obs)[:START_GRID_OBS])
    albedo = torch.from_numpy(base.albedo[meas.point[obs]]).view(-1, 3, 1, 1)
    state = observation_state(meas, obs).replace(direct=albedo)
    probe = insert_by_rank(base.stack, make_effect(name, meas)).to(torch.float64)
    values = {k: np.asarray(v, float) for k, v in grid.items()}
    losses = grid_losses(probe, name, state, torch.from_numpy(meas.colour[obs]), values, config.fit.loss_scale)
    best = np.unravel_index(int(np.argmin(losses)), losses.shape)
    trial[name].set_values(**{k: float(v[i]) for (k, v), i in zip(values.items(), best, strict=True)})


def grid_losses(probe: Stack, name: str, state, y: torch.Tensor, grid: dict[str, np.ndarray],
                scale: float) -> np.ndarray:
    """Mean soft-L1 loss of ``probe`` with the scalar parameters of effect ``name`` set to every
    combination of the values in ``grid`` ({param: values}); shape: one axis per parameter.

    Fast path, when the effect multiplies the direct signal by a factor g that does not depend on it
    and the effects after it are affine in the direct signal: with J the direct signal reaching the
    effect, T = S(1) - S(0) and B = S(0) for the effects S after it, the prediction is T g J + B, so
    each combination costs one evaluation of the effect alone. Otherwise the whole stack is rendered
    per combination."""
    index = probe.names.index(name)
    effect = probe.effects[index]

    def run(effects, st):
        for e in effects:
            st = e(st)
        return st

    with torch.no_grad():
        before = run(probe.effects[:index], state)
        ones = before.replace(direct=torch.ones_like(before.direct))
        after = effect(before)
        g = effect(ones).direct
        rest = probe.effects[index + 1:]
        s0, s1, s2 = (run(rest, after.replace(direct=k * after.direct)).image for k in (0.0, 1.0, 2.0))
        fast = (torch.allclose(after.direct, before.direct * g, atol=1e-10)
                and torch.allclose(after.backscatter, before.backscatter, atol=1e-10)
                and torch.allclose(s2 - s1, s1 - s0, atol=1e-9))
        if fast:
            t = (run(rest, after.replace(direct=torch.ones_like(after.direct))).image - s0)[:, :, 0, 0]
            b = s0[:, :, 0, 0]
            j = before.direct[:, :, 0, 0]
        raws = [effect._spec(k).to_raw(torch.from_numpy(v)) for k, v in grid.items()]
        losses = np.zeros([len(v) for v in grid.values()])
        for index in itertools.product(*(range(len(v)) for v in grid.values())):
            for k, raw, i in zip(grid, raws, index, strict=True):
                effect.raw[k].copy_(raw[i])
            pred = t * effect(ones).direct[:, :, 0, 0] * j + b if fast else probe.render(state)[:, :, 0, 0]
            losses[index] = float(soft_l1(pred - y, scale).sum(1).mean())
    return losses


def start_added(stack: Stack, added: list[str], meas: Observations, split, config: DiagnoseConfig) -> None:
    """Starting values of the effects just added to the model (``--add``) that have a start grid, as
    a candidate gets them: the grid is scored against a fit of the model without them (one more fit),
    in place. Without this an added caustics effect would start from its initial cell size and drift
    and stay in the wrong minimum."""
    gridded = [n for n in added if get(n).start_grid]
    if not gridded:
        return
    without = Stack([e for e in copy_stack(stack).effects if e.name not in gridded])
    prior = fit_stack(without, meas, split, replace(config.fit, bootstrap=0), frozen_settings(without, meas))
    for name in gridded:
        grid_start(stack, name, prior, meas, split, config)


def candidate_names(stack: Stack, meas: Observations, only: tuple[str, ...] = ()) -> tuple[list[str], dict[str, str]]:
    """Candidates to try and {name: reason} for the registered effects that are skipped. Effects named in
    ``only`` are tried even when the per-point albedo seems to absorb them (the screen of
    :func:`absorbed_by_albedo` is a judgement; the other reasons are things the fit cannot do)."""
    names = list(only) if only else [n for n in available() if n not in stack.names]
    keep, skipped = [], {}
    probe = np.unique(meas.point)[:200]
    obs = np.nonzero(np.isin(meas.point, probe))[0]
    state = observation_state(meas, obs)
    for name in names:
        cls = get(name)
        if name in stack.names:
            skipped[name] = "already in the model"
            continue
        if cls.nuisance:
            skipped[name] = "a nuisance field that stands in for what the stack lacks, not a physical candidate"
            continue
        if cls.needs_image:
            skipped[name] = "acts on whole images (needs_image), not on per-point observations"
            continue
        effect = make_effect(name, meas)
        if any(not n.startswith("raw.") for n, _ in effect.named_parameters()):
            skipped[name] = "has learned layers (no physical parameters to fit)"
            continue
        try:
            absorbed = absorbed_by_albedo(stack, name, effect, state, meas.point[obs],
                                          declared_rig(effect, meas.lights))
        except MissingInputError as exc:
            skipped[name] = f"input missing: {exc}"
            continue
        if absorbed and name not in only:
            skipped[name] = (f"acts the same on every view of a point at each of {SCREEN_PROBES + 1} parameter "
                             f"values tried: the per-point albedo absorbs it, so multi-view colour cannot detect it "
                             f"(e.g. light that depends on the point alone); fit it anyway with --candidates {name}")
            continue
        keep.append(name)
    return keep, skipped


#: Random parameter values at which :func:`absorbed_by_albedo` probes a candidate, besides its initial ones.
SCREEN_PROBES = 3


def absorbed_by_albedo(stack: Stack, name: str, effect, state, point: np.ndarray, held: tuple[str, ...] = (),
                       seed: int = 19) -> bool:
    """True when adding ``effect`` (named ``name``) only rescales each point's direct signal by a factor
    common to all its views and leaves the veiling light unchanged, at its initial values and at
    ``SCREEN_PROBES`` random values inside its bounds: with T = F(1) - F(0) and B = F(0), the log ratio of
    T with and without the effect is constant within every point and B is unchanged at every probe.

    The random values matter: an effect whose initial values are neutral (a per-frame exposure starting
    at gain 1 in every frame) is the identity there, which every albedo absorbs. Each learnable
    parameter not in ``held`` (a declared rig) gets raw values drawn uniformly in [-2, 2], element by
    element (12-88 % of a bounded span, 0.13-2.1 above a lower bound), so per-frame values differ."""
    rng = torch.Generator().manual_seed(seed)
    trial = insert_by_rank(stack, effect).to(torch.float64)
    probe = trial[name]
    learnable = [p.name for p in probe.params if p.learnable and p.name not in held]
    for k in range(SCREEN_PROBES + 1):
        if k:
            with torch.no_grad():
                for pname in learnable:
                    raw = probe.raw[pname]
                    raw.copy_(torch.rand(raw.shape, generator=rng, dtype=raw.dtype) * 4.0 - 2.0)
        if not _absorbed_at(stack, trial, state, point):
            return False
    return True


def _absorbed_at(stack: Stack, trial: Stack, state, point: np.ndarray) -> bool:
    """:func:`absorbed_by_albedo` at the trial stack's current values."""
    renders = []
    for s in (copy_stack(stack).to(torch.float64), trial):
        with torch.no_grad():
            zero = s.render(state.replace(direct=torch.zeros_like(state.direct)))[:, :, 0, 0]
            renders.append((s.render(state)[:, :, 0, 0] - zero, zero))
    (t0, b0), (t1, b1) = renders
    if (b1 - b0).abs().max() > 1e-9:
        return False
    log_ratio = torch.log(t1.clamp_min(1e-12) / t0.clamp_min(1e-12)).numpy()
    _, inv = np.unique(point, return_inverse=True)
    count = np.bincount(inv)[:, None]
    mean = np.stack([np.bincount(inv, log_ratio[:, c]) for c in range(3)], 1) / count
    return float(np.abs(log_ratio - mean[inv]).max()) < 1e-6


def affine_change(stack: Stack, reference: Stack, state) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(A / A_ref, C, C_ref) (each (N,3,1,1), float64) at the views of ``state``: A, C of y = A J + C
    (:func:`watergan.formation.inverse.affine_images`) of ``stack`` and of ``reference``."""
    with torch.no_grad():
        (a1, c1), (a0, c0) = (affine_images(s.to(torch.float64), state) for s in (stack, reference))
    return a1 / a0.clamp_min(1e-12), c1, c0


def effect_form(stack: Stack, name: str, state) -> str:
    """How effect ``name`` of a fitted ``stack`` acts at the views of ``state``, against the same stack without it
    (:func:`affine_change`): "multiplicative" (A / A_without varies over the views), "additive" (C changes, and not
    by the factor A / A_without: light added, not scaled), "both" or "neither"."""
    ratio, c1, c0 = affine_change(stack, Stack([e for e in stack.effects if e.name != name]), state)
    log_ratio = torch.log(ratio.clamp_min(1e-12))
    multiplicative = float((log_ratio - log_ratio.mean((0, 2, 3), keepdim=True)).abs().max()) > 1e-3
    additive = min(float((c1 - c0).abs().max()), float((c1 - c0 * ratio).abs().max())) > 1e-4
    return {(True, True): "both", (True, False): "multiplicative", (False, True): "additive"}.get(
        (multiplicative, additive), "neither")


def water_field(model: list[dict] | None) -> Effect | None:
    """The fitted fields over the image (``image_field``) of a water stack configuration, None without them."""
    entry = next((e for e in model or [] if e["name"] == "image_field"), None)
    return None if entry is None else Stack.from_config([entry]).to(torch.float64)["image_field"]


def fields_explained(stack: Stack, reference: Stack, fitted: Effect, state) -> float:
    """The share of the water's fields over the image (``fitted``, an ``image_field``) that a fitted ``stack``
    reproduces at the views of ``state`` beyond the ``reference`` (the water's stack the fields were fitted beside,
    without them): 1 - |d - d_c|^2 / |d|^2, d = (log F, G / G_SCALE) the fields at the views and d_c =
    (log(A / A_ref), (C - C_ref A / A_ref) / G_SCALE) what the fit does differently there (:func:`affine_change`;
    the other effects refitted with the candidate count too: the water's centred vignetting took its share of a
    falloff before the fields took the rest), each with its mean over the views removed per channel (a constant is
    the gain's or the backscatter's); 0 when it explains nothing or makes it worse."""
    from watergan.formation.effects.image_field import G_SCALE

    ratio, c1, c0 = affine_change(stack, reference, state)
    f, g = fitted.at(state.pixel_uv[:, :, 0, 0])
    fields = torch.cat([torch.log(f), g / G_SCALE], 1)
    candidate = torch.cat([torch.log(ratio.clamp_min(1e-12)), (c1 - c0 * ratio) / G_SCALE], 1)[:, :, 0, 0]
    fields, candidate = (t - t.mean(0, keepdim=True) for t in (fields, candidate))
    norm = float((fields ** 2).sum())
    return 0.0 if norm <= 0 else max(0.0, 1.0 - float(((fields - candidate) ** 2).sum()) / norm)


def rank_candidates(stack: Stack, meas: Observations, base: FitResult, base_scores: dict, config: DiagnoseConfig,
                    split, names: list[str], progress: bool | None = None,
                    fields: dict | None = None, fitted_fields: Effect | None = None) -> list[CandidateResult]:
    """Refit with each candidate added; sorted by held-out change (best first), the image-position candidates among
    their places by how much of the water's fields they reproduce (:func:`order_by_fields`). ``fields``: the water's
    fields over the image; a candidate on image position, or one whose fit flattens that axis most (a light's
    spot), of another form (:func:`form_conflict`), or an image-position one that reproduces too little of structured
    fields (:func:`eval.diagnose_verdict.fields_share_check`: under 80 % it is at most a partial step), is not accepted
    (a light's share of them is no measure: its pattern moves with the range and the surface). ``fitted_fields``: the
    fields themselves (:func:`water_field`; ``stack`` is then the water's without them): each image-position
    candidate says how much of them its fit reproduces (:func:`fields_explained`)."""
    results = []
    structured = bool(fields) and fields.get("form") in ("multiplicative", "additive", "both")
    probe = observation_state(meas, np.arange(min(meas.n_obs, 2000)))
    for name in tqdm(names, desc="candidates", unit="fit", disable=None if progress is None else not progress):
        trial = insert_by_rank(stack, make_effect(name, meas))
        grid_start(trial, name, base, meas, split, config)
        fit = fit_stack(trial, meas, split, replace(config.fit, bootstrap=0), frozen_settings(trial, meas),
                        init_albedo=base.albedo)
        change, ci, p = paired_rmse_change(base.heldout_sq_sum, fit.heldout_sq_sum, base.heldout_count,
                                           config.bootstrap, config.fit.seed)
        cand_analysis = analyse(meas, fit.predicted, fit.residual, config.residuals)
        cand_scores = scores(cand_analysis)
        drops = {a: base_scores[a] - cand_scores.get(a, 0.0) for a in base_scores}
        flattened = max(drops, key=drops.get)
        implausible = why_implausible(name, fit.params[name]) or same_colour(name, fit.params)
        on_image = get(name).axis == "image_position" or flattened == "image_position"
        if not implausible and fields and on_image:
            implausible = form_conflict(name, effect_form(fit.stack, name, probe), fields)
        explained = (fields_explained(fit.stack, stack, fitted_fields, probe)
                     if fitted_fields is not None and get(name).axis == "image_position" else None)
        share_reason, partial = fields_share_check(name, explained, change, structured)
        implausible = implausible or share_reason
        results.append(CandidateResult(
            name=name, heldout_rmse=fit.heldout_rmse, change=change, ci95=ci, p=p,
            significant=p < config.alpha and change <= -config.min_improvement and not implausible,
            flattened=flattened, flattened_drop=round(drops[flattened], 3), params=fit.params[name],
            scores=cand_scores, structure=relative_amplitudes(cand_analysis, fit), seconds=fit.seconds,
            implausible=implausible, fields_explained=explained, partial=partial and not implausible))
    return order_by_fields(sorted(results, key=lambda r: r.change))


def order_by_fields(ranked: list[CandidateResult]) -> list[CandidateResult]:
    """``ranked`` (by held-out change) with the candidates that say how much of the water's fields they reproduce
    (``fields_explained``: the image-position ones) reordered among their own places, most reproduced first (ties
    by held-out change): on image position the candidate that flattens the fields is the better answer, whatever
    else lowers the held-out error."""
    places = [i for i, r in enumerate(ranked) if r.fields_explained is not None]
    by_share = sorted((ranked[i] for i in places), key=lambda r: (-r.fields_explained, r.change))
    ordered = list(ranked)
    for i, r in zip(places, by_share, strict=True):
        ordered[i] = r
    return ordered


def relative_amplitudes(analysis: dict, fit: FitResult) -> dict[str, float]:
    """Structure amplitude per axis over the RMSE of all the fit's residuals."""
    rms = float(np.sqrt(np.mean(fit.residual ** 2))) + 1e-12
    return {axis: round(a / rms, 3) for axis, a in amplitudes(analysis).items()}


def _ledger_record(fit: FitResult, kind: str, meas: Observations, colour: dict) -> dict:
    return {"time": time.strftime("%Y-%m-%d %H:%M:%S"), "kind": kind, "stack": fit.stack.names,
            "params": {e: {p: v["value"] for p, v in d.items()} for e, d in fit.params.items()},
            "heldout_rmse": fit.heldout_rmse, "train_rmse": fit.train_rmse, "n_obs": meas.n_obs,
            "geometry": meas.source, "seconds": round(fit.seconds, 3), **colour}


def diagnose(survey: Path, out: Path, ledger_dir: Path, config: DiagnoseConfig = DiagnoseConfig(),
             tracks: Path | None = None, scale: str = "unknown", colour: dict | None = None,
             model: list[dict] | None = None, measurements: Observations | None = None,
             described: str = "", fields: dict | None = None, frames: dict | None = None) -> DiagnoseResult:
    """Measure the survey (SfM ``tracks`` with their ``scale`` method, else the simulator's truth), or take
    ``measurements`` as given (the workspace stage passes the water stage's table, :func:`eval.diagnose_measure.
    with_survey`; ``described`` says where it came from), fit the model, analyse residuals, rank
    candidates, write everything to ``out`` and append the fits to the ledger in ``ledger_dir`` (with ``colour``,
    the image folders' consistency and board error when they were measured). ``model``: the stack to start from
    (the water stage's estimate; see :func:`default_stack`); ``fields``: its fields over the image (water.json's;
    the verdict reads them and an image-position candidate of another form is not accepted), ``frames`` its gains
    per frame (water.json's; the verdict reads them). Torch runs on one
    thread: the tensors are small (observations x 3), and a thread pool competing with other processes for the
    cores slows a fit many times."""
    from watergan.device import single_torch_thread

    with single_torch_thread():
        return _diagnose(survey, out, ledger_dir, config, tracks, scale, colour or {}, model, measurements, described,
                         fields, frames)


def describe_measurements(meas: Observations, where: str = "") -> str:
    """One line: the measurement table's source (and ``where`` it was read from), observations and points."""
    return (f"{meas.source}{f' ({where})' if where else ''}: {meas.n_obs} observations of {meas.n_points} points"
            + ("" if meas.source.startswith("water") else f", {meas.patch_px} px patches"))


def _diagnose(survey: Path, out: Path, ledger_dir: Path, config: DiagnoseConfig, tracks: Path | None, scale: str,
              colour: dict, model: list[dict] | None, measurements: Observations | None = None,
              described: str = "", fields: dict | None = None, frames: dict | None = None) -> DiagnoseResult:
    start = time.perf_counter()
    progress = config.progress
    survey = check_survey_folder(survey)
    for name in (*config.effects, *config.add):
        get(name)
    out.mkdir(parents=True, exist_ok=True)
    meas = measurements if measurements is not None else measure_survey(survey, config.measure, config.geometry,
                                                                        tracks, scale)
    described = described or describe_measurements(meas)
    stack = default_stack(survey, config.effects, model, survey_counts(meas))
    added = [name for name in config.add if name not in stack.names]
    for name in added:
        stack = insert_by_rank(stack, make_effect(name, meas))
    meas.save(out / "measurements.npz")
    split = make_split(meas, config.fit)
    start_added(stack, added, meas, split, config)
    base = fit_stack(stack, meas, split, config.fit, frozen_settings(stack, meas))
    analysis = analyse(meas, base.predicted, base.residual, config.residuals)
    base_scores = scores(analysis)
    surfaces = surface_orientations(meas)
    atomic_write_json(out / "fit.json", {**base.summary(), "n_points": meas.n_points, "n_obs": meas.n_obs,
                                         "patch_px": meas.patch_px, "geometry_source": meas.source,
                                         "measurements": described,
                                         "clipped_obs_dropped": meas.clipped_obs, "surfaces": surfaces,
                                         "degeneracy": f"effects {list(config.fit.fixed_effects)} are held at "
                                                       f"their configured values: a gain and the albedos' "
                                                       f"scale are exactly degenerate"})
    np.savez_compressed(out / "residuals.npz", residual=base.residual.astype(np.float32),
                        predicted=base.predicted.astype(np.float32), role=base.role,
                        albedo=base.albedo.astype(np.float32))
    atomic_write_json(out / "residuals.json", analysis)
    if config.plots:
        plot_residuals(analysis, out, f"{'+'.join(stack.names)}")
        write_residual_ply(meas, base.residual, out / "points_residual.ply")
    append_ledger(ledger_dir, _ledger_record(base, "model", meas, colour))

    names, skipped = candidate_names(stack, meas, config.candidates)
    ranking = rank_candidates(stack, meas, base, base_scores, config, split, names, progress, fields,
                              None if config.effects else water_field(model))  # the stack is the water's
    misfit = added_form_misfit(config.add, base_scores, relative_amplitudes(analysis, base), config)
    if misfit:
        ranking = [stand_in(r, config.add[-1]) for r in ranking]
    for r in ranking:
        append_ledger(ledger_dir, {"time": time.strftime("%Y-%m-%d %H:%M:%S"), "kind": "candidate",
                                   "stack": [*stack.names, r.name], "params": {r.name: {
                                       p: v["value"] for p, v in r.params.items()}},
                                   "heldout_rmse": r.heldout_rmse, "geometry": meas.source,
                                   "seconds": round(r.seconds, 3)})
    best = next((r for r in ranking if r.significant), None)
    final_scores = best.scores if best is not None else base_scores
    final_structure = best.structure if best is not None else relative_amplitudes(analysis, base)
    unexplained = unexplained_axes(final_scores, final_structure, config)
    verdict = verdict_text(ranking, unexplained, final_scores, final_structure, misfit, fields, frames)
    if meas.source.endswith("(scale: none)"):
        verdict += ("\nnote: the reconstruction has no metric scale (sfm scale 'none'): ranges are in SfM units, so "
                    "per-metre parameters and the declared light positions are not physical; give sfm a stereo rig, "
                    "a board or navigation altitudes")
    if surfaces:
        verdict += f"\n{orientations_line(surfaces)}"
    ranking_json = [{**r.__dict__, "ci95": list(r.ci95)} for r in ranking]
    atomic_write_json(out / "ranking.json", {"measurements": described,
                                             "base_heldout_rmse": base.heldout_rmse, "base_scores": base_scores,
                                             "base_structure": relative_amplitudes(analysis, base),
                                             "candidates": ranking_json, "skipped": skipped})
    atomic_write_text(out / "verdict.txt", verdict + "\n")
    plot_ledger(read_ledger(ledger_dir / LEDGER_NAME), out / "ledger.png")
    return DiagnoseResult(out_dir=str(out), stack=stack.names, heldout_rmse=base.heldout_rmse,
                          n_points=meas.n_points, n_obs=meas.n_obs, verdict=verdict,
                          best=best.name if best else None, ranking=ranking_json, skipped=skipped,
                          unexplained_axes=unexplained, scores=base_scores, geometry=meas.source,
                          seconds=time.perf_counter() - start, measurements=described, surfaces=surfaces)
