"""The water's intervals: one rule, :func:`combine`, from the bootstrap and the alternatives' fits.

Each fitted parameter's 95 % interval starts as estimate +- sqrt((1.96 sd_boot)^2 + change^2 [+ (1.96
range_scale_sd value)^2 for coefficients in 1/m]), clipped to the bounds, where change is the largest change of the
estimate under the alternatives of rule "quadrature"; a component on a bound (:func:`on_bound`) gets its
parameter's whole range. The interval then covers each "cover" alternative's value with the same sampling spread
around it, and each "bounds" alternative's accepted span; B_inf's also the valley the veil and beta leave it in
(:func:`cover_the_valley`). Every alternative that moved an interval leaves a row (:class:`Widening`). Pairs of
components whose bootstrap correlation exceeds 0.95 are trade-offs (:func:`tradeoffs`); the veil B_inf (1 -
exp(-beta r)) at the views' median range has its own interval (:func:`veil_at_median_range`). Which measurement
pins each parameter: ``PINNED_BY``.
"""

from __future__ import annotations

import numpy as np

from watergan.formation import Stack, get
from watergan.water_record import ParamInterval, Widening

from .fields import veil_at

#: Which measurement pins each parameter of the built-in effects (for the JSON; see :mod:`eval.water`'s docstring).
PINNED_BY = {
    "attenuation.eta_per_m": "same point at several ranges (dense correspondences, tracks), altitude diversity",
    "backscatter.b_inf": "offsets that no albedo explains across ranges; dark pixels; the board (absolute level)",
    "backscatter.beta_per_m": "curvature of the offset over the survey's range span (weak)",
    "vignetting.a_margin": "same point at different image positions",
    "vignetting.b": "same point at different image positions",
    "vignetting.c": "same point at different image positions",
    "vignetting_offcentre.centre_uv": "same point at different image positions",
    "vignetting_offcentre.a_margin": "same point at different image positions; overall scale degenerate with strength",
    "vignetting_offcentre.b": "same point at different image positions; overall scale degenerate with strength",
    "vignetting_offcentre.c": "same point at different image positions; overall scale degenerate with strength",
    "vignetting_offcentre.strength": "ratios between channels only (s x polynomial: the scale is degenerate)",
    "gain.k": "the board's known colours (without a board: degenerate with the albedo scale, held fixed)",
    "artificial_light.offset_m": "declared in survey.json's lights (held)",
    "artificial_light.tilt_deg": "declared in survey.json's lights (held)",
    "artificial_light.beam_deg": "declared in survey.json's lights (held)",
    "artificial_light.power": "ratios between lights: brightness across the beams; level: degenerate with the gain "
                              "(held)",
    "artificial_light.eta_per_m": "tied to attenuation.eta_per_m (one water)",
    "artificial_light.ambient": "brightness that does not fall with the distance from the lights (other light)",
}


#: Fitted parameters whose lower bound is a physical value rather than a limit of the model: a survey in darkness
#: has no light but the declared lights (``artificial_light.ambient`` = 0 is the auv preset's truth).
PHYSICAL_LOWER_BOUNDS = ("artificial_light.ambient",)
#: A component within this fraction of its parameter's span (absolute for an unbounded side) sits on the bound.
BOUND_TOLERANCE = 1e-3


def on_bound(key: str, p, value: np.ndarray) -> np.ndarray:
    """(n,) bool per component of ``value`` (parameter ``p`` named ``key``): on a bound of its range (a lower bound
    in ``PHYSICAL_LOWER_BOUNDS`` does not count). The fit wanted to go further: the stack does not fit there."""
    value = np.atleast_1d(np.asarray(value, float)).ravel()
    span = (p.upper - p.lower) if np.isfinite(p.upper) else 1.0
    low = (np.abs(value - p.lower) <= BOUND_TOLERANCE * span) & (key not in PHYSICAL_LOWER_BOUNDS)
    return low | (np.abs(p.upper - value) <= BOUND_TOLERANCE * span)


def _rounded(a) -> list:
    return np.round(np.asarray(a, float), 6).tolist()


def describe(stack: Stack, best: dict, samples: list[dict], spec: dict, range_scale_sd: float) -> dict:
    """{"effect.param": :class:`ParamInterval`} of every parameter of ``stack``: the fitted ones (``best``) with
    the bootstrap ``samples`` and the largest "quadrature" change ``spec`` (see the module docstring)."""
    params = {}
    for effect in stack.effects:
        for p in effect.params:
            key = f"{effect.name}.{p.name}"
            value = effect.param(p.name).detach().numpy()
            entry = ParamInterval(value=_rounded(value), units=p.units, fitted=key in best,
                                  pinned_by=PINNED_BY.get(key, ""))
            if key in best and samples:
                stacked = np.stack([s[key] for s in samples])
                std = stacked.std(0, ddof=1) if len(samples) > 1 else np.zeros_like(value)
                shift = spec.get(key, np.zeros_like(value))
                scale = range_scale_sd * np.abs(value) if p.units == "1/m" else np.zeros_like(value)
                half = np.sqrt((1.96 * std) ** 2 + shift ** 2 + (1.96 * scale) ** 2)
                bound = on_bound(key, p, value).reshape(np.shape(value))
                entry.low = _rounded(np.where(bound, p.lower, np.clip(value - half, p.lower, p.upper)))
                entry.high = _rounded(np.where(bound, p.upper, np.clip(value + half, p.lower, p.upper)))
                entry.std, entry.specification, entry.on_bound = _rounded(std), _rounded(shift), bound.tolist()
                entry.p2_5 = _rounded(np.percentile(stacked, 2.5, 0))
                entry.p97_5 = _rounded(np.percentile(stacked, 97.5, 0))
            params[key] = entry
    return params


def tradeoffs(best: dict, samples: list[dict]) -> list:
    """[a, b, correlation] of the fitted parameter components whose bootstrap |correlation| exceeds 0.95."""
    if len(samples) <= 2:
        return []
    cols, labels = [], []
    for key in sorted(best):
        flat = np.stack([np.atleast_1d(s[key]).ravel() for s in samples])
        for i in range(flat.shape[1]):
            cols.append(flat[:, i])
            labels.append(f"{key}[{i}]" if flat.shape[1] > 1 else key)
    mat = np.stack(cols, 1)
    ok = mat.std(0) > 1e-12
    if ok.sum() <= 1:
        return []
    corr = np.corrcoef(mat[:, ok].T)
    lab = [label for label, keep in zip(labels, ok, strict=True) if keep]
    return [[lab[i], lab[j], round(float(corr[i, j]), 3)] for i in range(len(lab)) for j in range(i + 1, len(lab))
            if abs(corr[i, j]) > 0.95]


def widen(entry: ParamInterval, low: np.ndarray, high: np.ndarray, alternative: str, rule: str,
          change: np.ndarray) -> None:
    """Widen ``entry``'s interval (in place) to cover [low, high] per component, with a :class:`Widening` row."""
    old_low, old_high = np.asarray(entry.low, float), np.asarray(entry.high, float)
    widened = (low < old_low - 1e-6) | (high > old_high + 1e-6)
    entry.low, entry.high = _rounded(np.minimum(low, old_low)), _rounded(np.maximum(high, old_high))
    entry.widenings.append(Widening(alternative, rule, _rounded(change), np.atleast_1d(widened).tolist()))


def combine(stack: Stack, best: dict, samples: list[dict], results: list, range_scale_sd: float,
            range_m: float) -> tuple[dict, list, dict | None]:
    """(params, trade-offs, veil): the intervals of the fitted ``best`` ({"effect.param": value}) from the bootstrap
    ``samples`` and the alternatives' fits ``results`` (:class:`eval.water.alternatives.AlternativeFit`, each with its
    alternative's ``rules``), as the module docstring says; the veil at the views' median range ``range_m``."""
    def by_rule(rule: str) -> list:
        return [r for r in results if rule in r.alternative.rules]

    def shape_ok(r, key):
        return key in r.values and np.shape(r.values[key]) == np.shape(best[key])

    quadrature = by_rule("quadrature")
    spec = {key: np.max([np.abs(r.values[key] - v) for r in quadrature if shape_ok(r, key)], 0, initial=0.0)
            for key, v in best.items()}
    params = describe(stack, best, samples, spec, range_scale_sd)
    for key, entry in params.items():
        if entry.low is None:
            continue
        value = np.asarray(best[key], float)
        for r in quadrature:
            if shape_ok(r, key):
                change = np.abs(r.values[key] - value)
                entry.widenings.append(Widening(r.alternative.key, "quadrature", _rounded(change),
                                                np.atleast_1d((change > 0) & (change >= spec[key])).tolist()))
        name, param = key.split(".", 1)
        p = stack[name]._spec(param)
        per_value = range_scale_sd if p.units == "1/m" else 0.0
        for r in by_rule("cover"):
            if shape_ok(r, key):
                v = np.asarray(r.values[key], float)
                half = 1.96 * np.hypot(np.asarray(entry.std, float), per_value * np.abs(v))
                widen(entry, np.clip(v - half, p.lower, p.upper), np.clip(v + half, p.lower, p.upper),
                      r.alternative.key, "cover", np.abs(v - value))
        for r in by_rule("bounds"):
            if r.profile and r.profile.get("param") == key:
                low, high = np.asarray(r.profile["low"], float), np.asarray(r.profile["high"], float)
                widen(entry, low, high, r.alternative.key, "bounds", np.maximum(value - low, high - value))
    light = next((r.values for r in results if r.alternative.key == "light_level"), None)
    veil = veil_at_median_range(stack, samples, range_m, tuple(r.values for r in quadrature), light,
                                tuple(r.values for r in by_rule("cover")))
    cover_the_valley(params, veil)
    return params, tradeoffs(best, samples), veil


def veil_at_median_range(stack: Stack, samples: list[dict], range_m: float,
                         alternatives: tuple[dict, ...] = (), light_at_centre: dict | None = None,
                         structures: tuple[dict, ...] = ()) -> dict | None:
    """The veil B(r) = B_inf (1 - exp(-beta r)) at the views' median range ``range_m`` per channel, with a 95 %
    interval from the bootstrap replicates ``samples`` ({"effect.param": value}) of B_inf and beta jointly (what a
    survey pins when its range span leaves B_inf and beta trading: the veil over its ranges) and, as every
    parameter's, the largest change under the specification ``alternatives`` (their fits, {"effect.param": value})
    added in quadrature (no range-scale term: the veil at a measured range is a level of colour, whatever the
    range's scale); with ``light_at_centre`` (the fit before :func:`set_light_level`) also the veil it had. The
    interval then covers each structure alternative's veil (``structures``: their fits) with the bootstrap's spread
    around it, as :func:`cover_the_structures` does the parameters'. None without the ``backscatter`` effect. Without
    replicates the interval is None."""
    if "backscatter" not in stack.names:
        return None
    effect = stack["backscatter"]
    keys = ("backscatter.b_inf", "backscatter.beta_per_m")

    def veil(b_inf, beta):
        return veil_at(b_inf, beta, range_m)

    value = veil(effect.param("b_inf").detach().numpy(), effect.param("beta_per_m").detach().numpy())
    entry = {"range_m": round(range_m, 3), "value": np.round(value, 6).tolist(), "low": None, "high": None}
    if light_at_centre is not None and all(k in light_at_centre for k in keys):
        entry["light_at_centre"] = np.round(veil(*(light_at_centre[k] for k in keys)), 6).tolist()
    if len(samples) > 1 and all(k in samples[0] for k in keys):
        values = np.stack([veil(s[keys[0]], s[keys[1]]) for s in samples])
        shifts = [np.abs(veil(a[keys[0]], a[keys[1]]) - value) for a in alternatives if all(k in a for k in keys)]
        shift = np.max(shifts, 0) if shifts else np.zeros_like(value)
        spread = 1.96 * values.std(0, ddof=1)
        half = np.sqrt(spread ** 2 + shift ** 2)
        others = [veil(a[keys[0]], a[keys[1]]) for a in structures if all(k in a for k in keys)]
        low = np.min([value - half, *(v - spread for v in others)], 0)
        high = np.max([value + half, *(v + spread for v in others)], 0)
        entry.update(low=np.round(np.clip(low, 0, None), 6).tolist(), high=np.round(high, 6).tolist())
    return entry


def cover_the_valley(params: dict, veil: dict | None) -> None:
    """Widen B_inf's interval (``params``' entry, in place) to the valley the survey leaves it in: where its range
    span pins the veil V at the median range r but hardly beta, B_inf = V / (1 - exp(-beta r)) runs along the
    valley; over the veil's interval and beta's (each 95 %), B_inf spans [V_low / (1 - exp(-beta_high r)),
    V_high / (1 - exp(-beta_low r))] (beta_low at 0: up to B_inf's bound). The interval becomes its union with
    that span (a "valley" row); nothing without the veil's or beta's interval."""
    b_inf, beta = params.get("backscatter.b_inf"), params.get("backscatter.beta_per_m")
    if not veil or veil.get("low") is None or b_inf is None or beta is None or b_inf.low is None or beta.low is None:
        return
    r = veil["range_m"]
    with np.errstate(divide="ignore"):
        low = np.asarray(veil["low"]) / -np.expm1(-np.asarray(beta.high) * r)
        high = np.asarray(veil["high"]) / -np.expm1(-np.asarray(beta.low) * r)
    upper = next(p.upper for p in get("backscatter").params if p.name == "b_inf")
    value = np.asarray(b_inf.value, float)
    high = np.minimum(high, upper)
    widen(b_inf, low, high, "valley", "valley", np.maximum(value - low, high - value))
