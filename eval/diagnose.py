"""The discovery loop: fit the formation model to multi-view measurements, show where it fails,
name the missing effect, and keep a ledger of model versions.

    from eval.diagnose import DiagnoseConfig, run_diagnose
    result = run_diagnose("WORKSPACE_OR_SURVEY", DiagnoseConfig(effects=("attenuation", ...)))
    print(result.verdict)

Pieces (each usable alone):

- :mod:`eval.diagnose_measure`: the measurement table (points seen in >= 3 views).
- :mod:`eval.diagnose_fit`: fit a stack with per-point albedos; held-out error; Laplace uncertainties.
- :mod:`eval.diagnose_residuals`: residuals binned along every axis, structure scores, plots, PLY.
- this module: candidate ranking, verdict, ledger, and :func:`run_diagnose` (the stage).

Candidate ranking: every registered effect not in the stack is a candidate unless it needs whole
images (``needs_image``), has learned layers, needs a state field the measurements lack, or acts
identically on every view of a point (then the per-point albedo absorbs it and multi-view colour
cannot see it). Each candidate is inserted by ``rank`` into the model *as configured* and the
whole stack is refitted (albedos start from the base fit). Relative held-out change
d = RMSE_candidate / RMSE_base - 1; its significance is a paired bootstrap over held-out points
(p = fraction of resamples with d >= 0). A candidate is accepted when p < ``alpha`` and
d <= -``min_improvement``; the best accepted one is the verdict.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pipeline.workspace import Workspace, atomic_write_json, atomic_write_text
from watergan.errors import UserInputError
from watergan.formation import MissingInputError, Stack, available, get

from .diagnose_fit import FitConfig, FitResult, copy_stack, fit_stack, insert_by_rank, make_split, observation_state
from .diagnose_measure import MeasureConfig, Measurements, measure_survey, resolve_survey
from .diagnose_residuals import ResidualConfig, analyse, plot_residuals, scores, write_residual_ply

DEFAULT_EFFECTS = ("attenuation", "backscatter", "vignetting", "gain")
LEDGER_NAME = "model_ledger.jsonl"
#: Parameters of ``artificial_light`` that survey.json declares (the rig is known, not fitted).
LIGHT_GEOMETRY = ("offset_m", "tilt_deg", "beam_deg")


@dataclass(frozen=True)
class DiagnoseConfig:
    """The diagnose stage."""

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
    """Structure score above which an axis is reported as unexplained."""
    plots: bool = True
    """Write residual plots and the PLY."""


@dataclass(frozen=True)
class CandidateResult:
    """One candidate's refit. ``change``: relative held-out RMSE change (negative = better);
    ``ci95``: bootstrap 95% interval of it; ``p``: fraction of resamples with no improvement;
    ``flattened``: the axis whose structure score dropped most, with the drop."""

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
    seconds: float


@dataclass(frozen=True)
class DiagnoseResult:
    """What the diagnose stage wrote (``out_dir``, absolute) and found: the model, its held-out
    RMSE, the verdict, the best significant candidate (or None), the ranking, the skipped effects
    with reasons, axes with unexplained structure, the base model's structure scores, wall time."""

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
    seconds: float


def default_stack(survey: Path, effects: tuple[str, ...]) -> Stack:
    """The model to diagnose: the named effects (initial values), or the survey's visible stack with
    its parameters when simulated, or attenuation, backscatter, vignetting and gain."""
    if effects:
        for name in effects:
            get(name)
        return Stack.from_config(sorted(({"name": n} for n in effects), key=lambda e: get(e["name"]).rank))
    truth_effects = survey / "truth" / "effects.json"
    if truth_effects.is_file():
        return Stack.from_config(json.loads(truth_effects.read_text())["visible"])
    return Stack.from_names(list(DEFAULT_EFFECTS))


def light_settings(meas: Measurements) -> dict:
    """Initial values of ``artificial_light`` from the lights survey.json declares (empty if none)."""
    if not meas.lights:
        return {}
    settings = {key: [light[key] for light in meas.lights] for key in LIGHT_GEOMETRY
                if all(key in light for light in meas.lights)}
    power = next(p for p in get("artificial_light").params if p.name == "power")
    return settings | {"power": [power.init[0]] * len(meas.lights)}


def frozen_settings(stack: Stack, meas: Measurements) -> dict[str, tuple[str, ...]]:
    """Known settings that are not fitted: the declared light rig."""
    if meas.lights and "artificial_light" in stack.names:
        return {"artificial_light": tuple(k for k in LIGHT_GEOMETRY if all(k in light for light in meas.lights))}
    return {}


def make_effect(name: str, meas: Measurements):
    """A candidate effect at its initial values (the declared light rig for artificial_light)."""
    cls = get(name)
    return cls(**light_settings(meas)) if name == "artificial_light" else cls()


def candidate_names(stack: Stack, meas: Measurements, only: tuple[str, ...] = ()) -> tuple[list[str], dict[str, str]]:
    """Candidates to try and {name: reason} for the registered effects that are skipped."""
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
        if cls.needs_image:
            skipped[name] = "acts on whole images (needs_image), not on per-point observations"
            continue
        effect = make_effect(name, meas)
        if any(not n.startswith("raw.") for n, _ in effect.named_parameters()):
            skipped[name] = "has learned layers (no physical parameters to fit)"
            continue
        try:
            absorbed = _absorbed_by_albedo(stack, insert_by_rank(stack, effect), state, meas.point[obs])
        except MissingInputError as exc:
            skipped[name] = f"input missing: {exc}"
            continue
        if absorbed:
            skipped[name] = ("acts the same on every view of a point: the per-point albedo absorbs it, so "
                             "multi-view colour cannot detect it (e.g. light that depends on the point alone)")
            continue
        keep.append(name)
    return keep, skipped


def _absorbed_by_albedo(stack: Stack, trial: Stack, state, point: np.ndarray) -> bool:
    """True when adding the effect only rescales each point's direct signal by a factor common to
    all its views and leaves the veiling light unchanged: with T = F(1) - F(0) and B = F(0), the
    log ratio of T with and without the effect is constant within every point and B is unchanged."""
    renders = []
    for s in (copy_stack(stack).to(torch.float64), trial.to(torch.float64)):
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


def paired_bootstrap(base: FitResult, cand: FitResult, n: int, seed: int) -> tuple[float, tuple[float, float], float]:
    """Relative change d = RMSE_cand / RMSE_base - 1 on the held-out points, its bootstrap 95% interval
    and p = fraction of resamples (points drawn with replacement) with d >= 0."""
    rng = np.random.default_rng([seed, 13])
    h = len(base.heldout_count)
    idx = rng.integers(0, h, (n, h))
    count = base.heldout_count[idx].sum(1)
    rb = np.sqrt(base.heldout_sq_sum[idx].sum(1) / count)
    rc = np.sqrt(cand.heldout_sq_sum[idx].sum(1) / count)
    d = rc / rb - 1.0
    change = cand.heldout_rmse / base.heldout_rmse - 1.0
    return float(change), (float(np.quantile(d, 0.025)), float(np.quantile(d, 0.975))), float(np.mean(d >= 0))


def rank_candidates(stack: Stack, meas: Measurements, base: FitResult, base_scores: dict, config: DiagnoseConfig,
                    split, names: list[str], progress: bool | None = None) -> list[CandidateResult]:
    """Refit with each candidate added; sorted by held-out change (best first)."""
    results = []
    for name in tqdm(names, desc="candidates", unit="fit", disable=None if progress is None else not progress):
        trial = insert_by_rank(stack, make_effect(name, meas))
        fit = fit_stack(trial, meas, split, config.fit, frozen_settings(trial, meas), init_albedo=base.albedo)
        change, ci, p = paired_bootstrap(base, fit, config.bootstrap, config.fit.seed)
        cand_scores = scores(analyse(meas, fit.predicted, fit.residual, config.residuals))
        drops = {a: base_scores[a] - cand_scores.get(a, 0.0) for a in base_scores}
        flattened = max(drops, key=drops.get)
        results.append(CandidateResult(
            name=name, heldout_rmse=fit.heldout_rmse, change=change, ci95=ci, p=p,
            significant=p < config.alpha and change <= -config.min_improvement, flattened=flattened,
            flattened_drop=round(drops[flattened], 3), params=fit.params[name], scores=cand_scores,
            seconds=fit.seconds))
    return sorted(results, key=lambda r: r.change)


def _short_params(params: dict) -> str:
    """The first fitted parameter, e.g. "centre_uv (0.61, 0.44)"."""
    for pname, p in params.items():
        if p["fitted"]:
            value = p["value"]
            text = f"({', '.join(f'{v:.2f}' for v in np.ravel(value))})" if isinstance(value, list) else f"{value:.3g}"
            return f"{pname} {text}"
    return ""


def verdict_text(ranking: list[CandidateResult], unexplained: list[str], final_scores: dict) -> str:
    """One line naming the missing effect (or none), plus a line on unexplained structure."""
    best = next((r for r in ranking if r.significant), None)
    if best is not None:
        line = (f"missing: {best.name} — held-out error {best.change * 100:+.0f}% "
                f"(95% CI {best.ci95[0] * 100:+.0f}% to {best.ci95[1] * 100:+.0f}%), {_short_params(best.params)}; "
                f"flattens the {best.flattened} axis")
    else:
        line = "no significant missing effect"
        if ranking:
            top = ranking[0]
            line += f" (best candidate {top.name}: held-out error {top.change * 100:+.1f}%, p = {top.p:.2f})"
    if unexplained:
        listed = ", ".join(f"{a} (score {final_scores[a]:.1f})" for a in unexplained)
        line += (f"\nunexplained structure along: {listed} — no registered candidate explains it; an effect "
                 f"whose signature lies on this axis is missing (write one and pass --plugin FILE.py)")
    return line


def output_dir(target: str | Path) -> tuple[Path, Path]:
    """(output folder, ledger folder): WORKSPACE/08_diagnose and WORKSPACE for a workspace,
    SURVEY/diagnose for a bare survey folder."""
    root = Path(target)
    survey = resolve_survey(root)
    if survey != root:
        return Workspace(root).stage_dir("diagnose"), root
    out = root / "diagnose"
    out.mkdir(exist_ok=True)
    return out, out


def append_ledger(folder: Path, record: dict) -> None:
    """Append one JSON line to ``folder/model_ledger.jsonl``."""
    with open(folder / LEDGER_NAME, "a") as f:
        f.write(json.dumps(record) + "\n")


def find_ledger(target: str | Path) -> Path:
    """The ledger of a workspace (or of a bare survey's diagnose/ folder)."""
    root = Path(target)
    for path in (root / LEDGER_NAME, root / "diagnose" / LEDGER_NAME):
        if path.is_file():
            return path
    raise UserInputError(f"no {LEDGER_NAME} in {root}: run `watergan diagnose {root}` first")


def read_ledger(path: Path) -> list[dict]:
    """Every record of a ledger file."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def ledger_table(records: list[dict]) -> str:
    """A plain-text table: version, time, kind, held-out RMSE, change from the previous model, stack."""
    lines = [f"{'ver':>3}  {'time':19}  {'kind':9}  {'heldout_rmse':>12}  {'change':>7}  stack"]
    previous = None
    for i, r in enumerate(records):
        change = "" if previous is None or r["kind"] != "model" else f"{(r['heldout_rmse'] / previous - 1) * 100:+.1f}%"
        lines.append(f"{i:>3}  {r['time']:19}  {r['kind']:9}  {r['heldout_rmse']:12.5f}  {change:>7}  "
                     f"{','.join(r['stack'])}")
        if r["kind"] == "model":
            previous = r["heldout_rmse"]
    return "\n".join(lines)


def plot_ledger(records: list[dict], path: Path) -> None:
    """Held-out RMSE per ledger entry: model versions joined by a line, candidate trials as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    model = [(i, r["heldout_rmse"]) for i, r in enumerate(records) if r["kind"] == "model"]
    trials = [(i, r["heldout_rmse"]) for i, r in enumerate(records) if r["kind"] != "model"]
    if trials:
        ax.scatter(*zip(*trials, strict=True), s=12, color="0.6", label="candidate trial")
    if model:
        ax.plot(*zip(*model, strict=True), "o-", color="tab:blue", label="model version")
        for i, r in enumerate(records):
            if r["kind"] == "model":
                ax.annotate("+".join(r["stack"][-1:]), (i, r["heldout_rmse"]), fontsize=7,
                            textcoords="offset points", xytext=(3, 4))
    ax.set_xlabel("ledger entry")
    ax.set_ylabel("held-out RMSE (linear)")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def _ledger_record(fit: FitResult, kind: str, n_obs: int) -> dict:
    return {"time": time.strftime("%Y-%m-%d %H:%M:%S"), "kind": kind, "stack": fit.stack.names,
            "params": {e: {p: v["value"] for p, v in d.items()} for e, d in fit.params.items()},
            "heldout_rmse": fit.heldout_rmse, "train_rmse": fit.train_rmse, "n_obs": n_obs,
            "seconds": round(fit.seconds, 3)}


def run_diagnose(target: str | Path, config: DiagnoseConfig = DiagnoseConfig(),
                 progress: bool | None = None) -> DiagnoseResult:
    """Measure, fit the model, analyse residuals, rank candidates, write everything to the output
    folder (see :func:`output_dir`) and append the fits to the ledger."""
    start = time.perf_counter()
    survey = resolve_survey(target)
    stack = default_stack(survey, config.effects)
    for name in config.add:
        if name not in stack.names:
            stack = insert_by_rank(stack, get(name)())
    out, ledger_dir = output_dir(target)
    meas = measure_survey(survey, config.measure)
    meas.save(out / "measurements.npz")
    split = make_split(meas, config.fit)
    base = fit_stack(stack, meas, split, config.fit, frozen_settings(stack, meas))
    analysis = analyse(meas, base.predicted, base.residual, config.residuals)
    base_scores = scores(analysis)
    atomic_write_json(out / "fit.json", {**base.summary(), "n_points": meas.n_points, "n_obs": meas.n_obs,
                                         "patch_px": meas.patch_px, "geometry_source": meas.source,
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
    append_ledger(ledger_dir, _ledger_record(base, "model", meas.n_obs))

    names, skipped = candidate_names(stack, meas, config.candidates)
    ranking = rank_candidates(stack, meas, base, base_scores, config, split, names, progress)
    for r in ranking:
        append_ledger(ledger_dir, {"time": time.strftime("%Y-%m-%d %H:%M:%S"), "kind": "candidate",
                                   "stack": [*stack.names, r.name], "params": {r.name: {
                                       p: v["value"] for p, v in r.params.items()}},
                                   "heldout_rmse": r.heldout_rmse, "seconds": round(r.seconds, 3)})
    best = next((r for r in ranking if r.significant), None)
    final_scores = best.scores if best is not None else base_scores
    unexplained = [a for a, s in final_scores.items() if s > config.structure_threshold]
    verdict = verdict_text(ranking, unexplained, final_scores)
    ranking_json = [{**r.__dict__, "ci95": list(r.ci95)} for r in ranking]
    atomic_write_json(out / "ranking.json", {"base_heldout_rmse": base.heldout_rmse, "base_scores": base_scores,
                                             "candidates": ranking_json, "skipped": skipped})
    atomic_write_text(out / "verdict.txt", verdict + "\n")
    plot_ledger(read_ledger(ledger_dir / LEDGER_NAME), out / "ledger.png")
    result = DiagnoseResult(out_dir=str(out), stack=stack.names, heldout_rmse=base.heldout_rmse,
                            n_points=meas.n_points, n_obs=meas.n_obs, verdict=verdict,
                            best=best.name if best else None, ranking=ranking_json, skipped=skipped,
                            unexplained_axes=unexplained, scores=base_scores, seconds=time.perf_counter() - start)
    if ledger_dir != out:
        Workspace(ledger_dir).save("diagnose", config, replace(result, ranking=[]))
    else:
        atomic_write_json(out / "result.json", replace(result, ranking=[]))
    return result
