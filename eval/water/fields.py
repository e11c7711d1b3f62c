"""The nuisances the water's fit carries beside the stack, so that what the stack lacks bends them and not the water.

- the smooth fields over the image (``FIELD_EFFECT``, :mod:`watergan.formation.effects.image_field`): multiplicative
  F and additive G per channel, kept uncorrelated with range where image position explains most of it
  (:func:`decorrelate_fields`); an effect on image position in the stack is fitted before them (:func:`stack_first`);
  their size and form (:func:`field_summary`); a light fixed in the image taken out of the veil
  (:func:`set_light_level`).
- the gains per frame (``FRAME_EFFECT``, :mod:`watergan.formation.effects.frame_gain`): kept off the constant and the
  frames' mean ranges (:func:`decorrelate_frames`), measured first and carried only where a frame's exceeds
  ``FRAME_CARRY_PCT`` (:func:`measure_frame_gains`, :func:`frame_summary`).
- the fine fields for the corrections (``GRID_EFFECT``, :mod:`watergan.formation.effects.image_grid`), fitted after
  the water with every other parameter held (:func:`fit_correction_grid`).

Why each is there and what it pins: docs/water.md. They are fitted by the one fitter (:mod:`eval.fit`);
:func:`eval.water.fit_water.fit_water` calls them in order.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
import torch

from watergan.formation import Stack, get
from watergan.formation.effects.image_field import field_basis

from ..fit import FitConfig, Problem, insert_by_rank
from ..observations import Observations

if TYPE_CHECKING:
    from .config import WaterConfig

#: The nuisance fields over the image (``WaterConfig.field_degree``).
FIELD_EFFECT = "image_field"
#: The nuisance gain per frame (``WaterConfig.frame_gain``).
FRAME_EFFECT = "frame_gain"
#: The fine fields over the image for the corrections (``WaterConfig.correction_grid``).
GRID_EFFECT = "image_grid"


def decorrelate_fields(stack: Stack, obs: Observations, max_r2: float) -> float:
    """The fraction R^2 of the views' range variance that the fields' basis (and a constant) explains; when it
    exceeds ``max_r2``, set the stack's ``image_field.orthogonal_to`` (in place, unless given) to the unit covariance
    of each monomial with range over the views, so that the fields cannot take what is linear in range (see
    :mod:`watergan.formation.effects.image_field`). Below it the frames' altitudes and the relief separate range
    from image position, and the fields stay free."""
    if FIELD_EFFECT not in stack.names:
        return 0.0
    effect = stack[FIELD_EFFECT]
    basis = field_basis(torch.from_numpy(obs.pixel_uv).reshape(-1, 2, 1, 1), effect.degree)[:, :, 0, 0].numpy()
    centred, r = basis - basis.mean(0), obs.range_m - obs.range_m.mean()
    fitted = centred @ np.linalg.lstsq(centred, r, rcond=None)[0]
    r2 = float(1.0 - np.var(r - fitted) / max(np.var(r), 1e-12))
    if r2 > max_r2 and effect.param("orthogonal_to").abs().max() == 0:
        q = centred.T @ r / len(r)
        effect.set_values(orthogonal_to=q / max(np.linalg.norm(q), 1e-12))
    return r2


def decorrelate_frames(stack: Stack, obs: Observations, off_range: bool = True) -> None:
    """Set the stack's ``frame_gain.orthogonal_to`` (in place, unless given) to orthonormal columns spanning the
    constant and (``off_range``) each frame's mean range over its views (frames without views at the survey's mean),
    so that the gains per frame have no mean and cannot take what is linear in the frames' ranges (see
    :mod:`watergan.formation.effects.frame_gain`)."""
    if FRAME_EFFECT not in stack.names:
        return
    effect = stack[FRAME_EFFECT]
    if effect.param("orthogonal_to").abs().max() > 0:
        return
    n = effect.param("log_gain").shape[0]
    views = np.bincount(obs.frame, minlength=n)[:n]
    mean_range = np.bincount(obs.frame, weights=obs.range_m, minlength=n)[:n] / np.maximum(views, 1)
    mean_range[views == 0] = obs.range_m.mean()
    columns = np.stack([np.ones(n), (mean_range - mean_range.mean()) * off_range], 1)
    q, r = np.linalg.qr(columns)
    q[:, np.abs(np.diag(r)) < 1e-9 * np.sqrt(n)] = 0.0  # every frame at one range: the constant alone
    effect.set_values(orthogonal_to=q)

def veil_at(b_inf, beta_per_m, range_m: float) -> np.ndarray:
    """The veil B_inf (1 - exp(-beta r)) at range ``range_m`` (per channel, numpy)."""
    return np.asarray(b_inf) * -np.expm1(-np.asarray(beta_per_m) * range_m)

def stack_first(stack: Stack, obs: Observations, fit: FitConfig, names: list[str], float32: bool = False) -> int:
    """When the stack holds an effect on image position besides the centred ``vignetting`` and the fields over the
    image (smooth and fine: one added after the diagnosis named it), fit the stack first with the fields held flat
    (in place; coarse start, then on all points), so that the named effect takes what its form explains and the
    fields, freed afterwards, only the rest: ``--add`` of the right effect flattens them. ``float32``: as
    :func:`eval.water.fit_water.fit_water`'s. Returns the iterations spent (0: nothing to do)."""
    fields = (FIELD_EFFECT, GRID_EFFECT)
    if FIELD_EFFECT not in stack.names or not any(
            e.axis == "image_position" and e.name not in ("vignetting", *fields) for e in stack.effects):
        return 0
    first = Problem(stack, obs, fit, [n for n in names if stack.effects[int(n.split(".")[1])].name not in fields],
                    float32=float32)
    return first.coarse_start(trust_region_names(stack, first.names)) + first.converge()[0]


def trust_region_names(stack: Stack, names: list[str]) -> list[str]:
    """The fitted raw parameters ``names`` that the coarse start's trust region refines: all but the gains per frame
    and the fine grid (hundreds of columns each, which L-BFGS alone moves); the trust region follows the water's
    flat directions."""
    return [n for n in names if stack.effects[int(n.split(".")[1])].name not in (FRAME_EFFECT, GRID_EFFECT)]


#: Fields whose multiplicative and additive parts both stay under this (per cent of the signal) read as flat.
FIELD_FLAT_PCT = 5.0
#: The water carries the gains per frame when a frame's exceeds this (per cent). Below it they are reported and
#: held at 1: a stack that lacks an effect on image position leaves gains of up to 6 % where nothing changes from
#: frame to frame (a clipped falloff, benchmarks/RESULTS/water.md), and carrying them bent eta by 8 %.
FRAME_CARRY_PCT = 10.0
#: The fine grid fitted on the coarse fraction of the points (``FitConfig.coarse_fraction``) is taken as flat, without
#: the fit on all points, when its size stays under this (per cent; the flat of ``FIELD_FLAT_PCT`` with a margin for
#: the sampling of a quarter of the points): :func:`fit_correction_grid`.
GRID_COARSE_FLAT_PCT = 3.0


def field_form(multiplicative_pct: list[float], additive_pct: list[float]) -> str:
    """"flat", "multiplicative", "additive" or "both": which part of the fields exceeds ``FIELD_FLAT_PCT`` in some
    channel (both: each does, and neither is under half the other)."""
    m, a = max(multiplicative_pct), max(additive_pct)
    if max(m, a) < FIELD_FLAT_PCT:
        return "flat"
    if min(m, a) >= max(FIELD_FLAT_PCT, 0.5 * max(m, a)):
        return "both"
    return "multiplicative" if m > a else "additive"


def field_size(fields: dict) -> str:
    """The fields' size in words, from :func:`field_summary`'s entry: the largest multiplicative and additive part."""
    return (f"multiplicative up to {max(fields['multiplicative_pct']):.0f} %, additive up to "
            f"{max(fields['additive_pct']):.1f} % of the signal")


def field_extent(f: np.ndarray, g: np.ndarray, mean_signal: np.ndarray) -> dict:
    """JSON-ready size of fields (F, G) sampled over the image ((..., 3) each): per channel max |F - 1| and max |G|
    over the views' ``mean_signal`` (3,) in per cent, their form (:func:`field_form`), F's and G's least and largest
    values."""
    f, g = f.reshape(-1, 3), g.reshape(-1, 3)
    multiplicative = (100 * np.abs(f - 1).max(0)).round(2).tolist()
    additive = (100 * np.abs(g).max(0) / np.maximum(mean_signal, 1e-6)).round(2).tolist()
    return {"multiplicative_pct": multiplicative, "additive_pct": additive,
            "form": field_form(multiplicative, additive), "F_min": np.round(f.min(0), 4).tolist(),
            "F_max": np.round(f.max(0), 4).tolist(), "G_min": np.round(g.min(0), 5).tolist(),
            "G_max": np.round(g.max(0), 5).tolist()}


def field_summary(stack: Stack, range_r2: float, mean_signal: np.ndarray, grid: int = 33) -> dict | None:
    """JSON-ready: the stack's ``image_field`` (degree; its size, :func:`field_extent`, over a grid of the image;
    ``range_r2`` of :func:`decorrelate_fields` and whether the fields were kept off range); None when the stack has
    none."""
    if FIELD_EFFECT not in stack.names:
        return None
    field_effect = stack[FIELD_EFFECT]
    return {"degree": field_effect.degree, **field_extent(*field_effect.on_grid(grid, grid), mean_signal),
            "range_r2": round(range_r2, 3), "off_range": bool(field_effect.param("orthogonal_to").abs().max() > 0)}


def set_light_level(stack: Stack, obs: Observations, form: str, range_m: float) -> np.ndarray | None:
    """When the fields over the image carry additive structure alone (``form``, :func:`field_form`: a light fixed
    in the image, a reflection in the port, a flare), split the veil between the water and the light (``stack``, in
    place): the light's level l (``image_field.additive_level``) is set so that the additive field G is least, 0,
    at one of the table's views ``obs``, and B_inf is scaled so that the veil at the views' median range
    ``range_m`` drops by l (beta kept). Why: a constant G is the backscatter's level (over a survey's range span a
    constant light and a larger B_inf differ by little), so the fit, which holds G at 0 at the image's centre, leaves
    the light's level there in the veil. A light is non-negative, and a spot or a reflection fades away from where it
    falls: the least level that keeps G >= 0 where the survey looks is the light's, the rest of the veil the water's.
    Not refitted: the split is an assumption the data cannot check, and the stack's prediction changes by
    l (1 - B(r) / B(range_m)) over the views' ranges. Returns B_inf's factor per channel (None, nothing changed,
    when the form is another)."""
    if form != "additive" or "backscatter" not in stack.names:
        return None
    field, back = stack[FIELD_EFFECT], stack["backscatter"]
    level = np.clip(-field.at(torch.from_numpy(obs.pixel_uv))[1].numpy().min(0), 0.0, None)
    b_inf = back.param("b_inf").detach().numpy()
    veil = veil_at(b_inf, back.param("beta_per_m").detach().numpy(), range_m)
    factor = np.clip(1.0 - level / np.maximum(veil, 1e-12), 0.0, 1.0)
    field.set_values(additive_level=level)
    back.set_values(b_inf=b_inf * factor)
    return factor


def split_light(stack: Stack, obs: Observations, range_r2: float) -> np.ndarray | None:
    """:func:`set_light_level` where the fields' form (:func:`field_summary`) says a light fixed in the image, at the
    views' median range (``stack`` in place). Returns B_inf's factor per channel, None where nothing changed."""
    fields = field_summary(stack, range_r2, obs.colour.mean(0))
    if not fields:
        return None
    return set_light_level(stack, obs, fields["form"], float(np.median(obs.range_m)))


def fit_correction_grid(stack: Stack, obs: Observations, config: WaterConfig,
                        range_r2: float = 0.0) -> tuple[Stack, dict | None]:
    """The fine fields over the image (``image_grid`` on ``config.correction_grid`` nodes) fitted to the table with
    every parameter of the fitted ``stack`` held, for the corrections: what the water's smooth fields leave on image
    position (a falloff clipped into a ring, a veil in a spot). Fitted after the water and its intervals, they cannot
    move them. They are fitted on ``config.fit.coarse_fraction`` of the points first; where they stay under
    ``GRID_COARSE_FLAT_PCT`` there, that fit decides (flat), else the fit on all points starts from it. Returns (a
    copy of ``stack`` with them when they exceed ``FIELD_FLAT_PCT`` (carried), else ``stack``; their size,
    :func:`field_extent`, with ``nodes``, ``points_fraction`` (of the fit that decided), ``carried`` and
    ``seconds``), or (``stack``, None) when the configuration has none. Where nothing is missing they stay flat and
    the corrections are those of the water. Where image position explains more than ``config.field_max_range_r2``
    of the views' range variance (``range_r2``: a camera looking ahead over a floor, its rows its ranges) the grid is
    measured but not carried (``range_r2`` in the summary): there it would take the water's fall with range."""
    if config.correction_grid is None or GRID_EFFECT in stack.names:  # none, or fitted with the water
        return stack, None
    rows, cols = config.correction_grid
    t0 = time.perf_counter()
    zeros = np.zeros((3, rows, cols)).tolist()
    refined = insert_by_rank(stack, get(GRID_EFFECT)(multiplicative=zeros, additive=zeros)).to(torch.float64)
    index = refined.names.index(GRID_EFFECT)
    names = [f"effects.{index}.raw.multiplicative", f"effects.{index}.raw.additive"]
    problem = Problem(refined, obs, config.fit, names, float32=True)

    def extent(fraction: float) -> dict:
        with torch.no_grad():
            size = field_extent(*refined[GRID_EFFECT].on_grid(65, 49), obs.colour.mean(0))
        return {"nodes": [rows, cols], **size, "points_fraction": fraction}

    coarse = problem.coarse()
    summary = None
    if coarse is not None:  # the grid on the coarse fraction of the points decides alone where it is clearly flat
        coarse.converge()
        summary = extent(config.fit.coarse_fraction)
        if max(summary["multiplicative_pct"] + summary["additive_pct"]) >= GRID_COARSE_FLAT_PCT:
            summary = None
            problem.take_gradients()
    if summary is None:  # on all points, from the coarse fit's grid where there was one
        problem.converge()
        summary = extent(1.0)
    for p in refined.parameters():
        p.requires_grad_(False)
    on_range = range_r2 > config.field_max_range_r2
    summary.update(carried=summary["form"] != "flat" and not on_range, seconds=round(time.perf_counter() - t0, 2),
                   **({"range_r2": round(range_r2, 3)} if on_range else {}))
    return (refined if summary["carried"] else stack), summary


def frame_summary(stack: Stack, frames: np.ndarray, carried: bool | None = None) -> dict:
    """JSON-ready: the stack's gains per frame g' (``frame_gain``) over the ``frames`` with views: per channel the
    largest |exp(g') - 1| and the standard deviation of g' in per cent, whether that is flat (under
    ``FIELD_FLAT_PCT``), whether the water carries them (``carried``; default: whether a frame's reaches
    ``FRAME_CARRY_PCT``, the rule :func:`eval.water.fit_water.cold_start` carries them by), the frames and each
    one's gain exp(g')."""
    with torch.no_grad():
        gains = stack[FRAME_EFFECT].gains().numpy()[frames]
    largest = 100 * np.abs(np.expm1(gains)).max(0)
    flat = bool(largest.max() < FIELD_FLAT_PCT)
    return {"largest_pct": largest.round(2).tolist(), "sd_pct": (100 * gains.std(0)).round(2).tolist(), "flat": flat,
            "carried": bool(largest.max() >= FRAME_CARRY_PCT) if carried is None else carried,
            "frames": frames.tolist(),
            "gain": np.exp(gains).round(4).tolist()}


def measure_frame_gains(problem: Problem, names: list[str], frames: np.ndarray) -> dict:
    """The gains per frame the ``frames`` with views want (:func:`frame_summary`): the gains ``names`` fitted alone,
    every other parameter held where ``problem``'s (coarse) fit left it, on its coarse points
    (:meth:`eval.fit.Problem.coarse`). Where they stay under ``FRAME_CARRY_PCT`` they are set back to 0: the survey
    keeps the water it had without them."""
    probe = problem.coarse(names) or Problem(problem.stack, problem.obs, problem.config, names, float32=True)
    probe.converge()
    problem.take_gradients()
    measured = frame_summary(problem.stack, frames)
    if not measured["carried"]:
        raw = problem.stack[FRAME_EFFECT].raw["log_gain"]
        with torch.no_grad():
            raw.copy_(problem.stack[FRAME_EFFECT]._spec("log_gain").to_raw(torch.zeros_like(raw)))
    return measured
