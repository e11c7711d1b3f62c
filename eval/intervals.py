"""The water estimate's intervals (see :mod:`eval.water`'s docstring, "Uncertainty").

Each fitted parameter's 95 % interval: estimate +- sqrt((1.96 sd_boot)^2 + change^2 [+ (1.96 range_scale_sd
value)^2 for coefficients in 1/m]), clipped to the bounds; a component on a bound (:func:`on_bound`) gets its
parameter's whole range; pairs of components whose bootstrap correlation exceeds 0.95 are trade-offs
(:func:`describe_intervals`). The veil B_inf (1 - exp(-beta r)) at the views' median range with its interval
(:func:`veil_at_median_range`), and B_inf's interval widened along the valley the veil and beta leave it in
(:func:`cover_the_valley`). Every interval also covers each structure alternative's estimate with the estimate's
sampling spread around it (:func:`cover_the_structures`). Which measurement pins each parameter: ``PINNED_BY``.
"""

from __future__ import annotations

import numpy as np

from watergan.formation import Stack, get

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


def describe_intervals(stack: Stack, best: dict, samples: list[dict], fixed: dict, spec: dict,
                       range_scale_sd: float) -> tuple[dict, list]:
    """The parameters' entries (see :class:`WaterEstimate`) and the trade-offs. A component on a bound
    (:func:`on_bound`) gets its parameter's whole range as interval: the data pushed it out of the model, so they do
    not pin it (its bootstrap, all on the bound, would say 0 wide)."""
    params = {}
    for effect in stack.effects:
        for p in effect.params:
            key = f"{effect.name}.{p.name}"
            value = effect.param(p.name).detach().numpy()
            entry = {"value": np.round(value, 6).tolist(), "units": p.units, "fitted": key in best,
                     "pinned_by": PINNED_BY.get(key, "")}
            if key in best and samples:
                stack_s = np.stack([s[key] for s in samples])
                std = stack_s.std(0, ddof=1) if len(samples) > 1 else np.zeros_like(value)
                shift = spec.get(key, np.zeros_like(value))
                scale = range_scale_sd * np.abs(value) if p.units == "1/m" else np.zeros_like(value)
                half = np.sqrt((1.96 * std) ** 2 + shift ** 2 + (1.96 * scale) ** 2)
                bound = on_bound(key, p, value).reshape(np.shape(value))
                low = np.where(bound, p.lower, np.clip(value - half, p.lower, p.upper))
                high = np.where(bound, p.upper, np.clip(value + half, p.lower, p.upper))
                entry.update(std=np.round(std, 6).tolist(), specification=np.round(shift, 6).tolist(),
                             low=np.round(low, 6).tolist(), high=np.round(high, 6).tolist(),
                             on_bound=bound.tolist(),
                             p2_5=np.round(np.percentile(stack_s, 2.5, 0), 6).tolist(),
                             p97_5=np.round(np.percentile(stack_s, 97.5, 0), 6).tolist())
            params[key] = entry
    tradeoffs = []
    if len(samples) > 2:
        keys = sorted(best)
        cols, labels = [], []
        for key in keys:
            flat = np.stack([np.atleast_1d(s[key]).ravel() for s in samples])
            for i in range(flat.shape[1]):
                cols.append(flat[:, i])
                labels.append(f"{key}[{i}]" if flat.shape[1] > 1 else key)
        mat = np.stack(cols, 1)
        sd = mat.std(0)
        ok = sd > 1e-12
        if ok.sum() > 1:
            corr = np.corrcoef(mat[:, ok].T)
            lab = [lab for lab, keep in zip(labels, ok, strict=True) if keep]
            for i in range(len(lab)):
                for j in range(i + 1, len(lab)):
                    if abs(corr[i, j]) > 0.95:
                        tradeoffs.append([lab[i], lab[j], round(float(corr[i, j]), 3)])
    return params, tradeoffs


def cover_the_structures(stack: Stack, params: dict, structures: list[dict], range_scale_sd: float) -> None:
    """Widen each fitted parameter's interval (``params``' entries, in place) to cover every structure alternative's
    estimate (``structures``: their fits, {"effect.param": value}) with the estimate's own sampling spread around
    it: [min_k v_k - h_k, max_k v_k + h_k] over the estimate and the alternatives, h_k = sqrt((1.96 std)^2 [+ (1.96
    range_scale_sd v_k)^2 for coefficients in 1/m]), clipped to the bounds. A structure alternative is another model
    of the survey, not a perturbation of this one: where the two disagree, either may hold, each with the survey's
    sampling spread (the union of their 95 % intervals; ``structures`` in the entry: True where that widened it)."""
    for key, entry in params.items():
        if entry.get("low") is None or "std" not in entry:
            continue
        value = np.asarray(entry["value"], float)
        fits = [np.asarray(f[key], float) for f in structures if np.shape(f.get(key)) == value.shape]
        if not fits:
            continue
        name, param = key.split(".", 1)
        p = stack[name]._spec(param)
        std, per_value = np.asarray(entry["std"], float), range_scale_sd if p.units == "1/m" else 0.0
        halves = [1.96 * np.hypot(std, per_value * np.abs(v)) for v in fits]
        low = np.clip(np.min([v - h for v, h in zip(fits, halves, strict=True)], 0), p.lower, p.upper)
        high = np.clip(np.max([v + h for v, h in zip(fits, halves, strict=True)], 0), p.lower, p.upper)
        widen(entry, low, high, "structures")


def widen(entry: dict, low: np.ndarray, high: np.ndarray, flag: str) -> None:
    """Widen a parameter's interval (``entry``, in place) to cover [low, high] per component; ``entry[flag]``: True
    where that widened it."""
    old_low, old_high = np.asarray(entry["low"], float), np.asarray(entry["high"], float)
    entry.update(low=np.round(np.minimum(low, old_low), 6).tolist(),
                 high=np.round(np.maximum(high, old_high), 6).tolist(),
                 **{flag: ((low < old_low) | (high > old_high)).tolist()})


def cover_the_profiles(params: dict, key: str, profiles: list[dict]) -> None:
    """Widen parameter ``key``'s interval (its entry of ``params``, in place) to cover each of ``profiles``'
    [low, high] (per component: the values a held-out profile accepts, :func:`eval.eta_profile.eta_profile`);
    ``profile`` in the entry: True where that widened it."""
    entry = params.get(key)
    if not profiles or entry is None or entry.get("low") is None:
        return
    widen(entry, np.min([np.asarray(p["low"], float) for p in profiles], 0),
          np.max([np.asarray(p["high"], float) for p in profiles], 0), "profile")


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
    that span (``valley``: True where that widened it); nothing without the veil's or beta's interval."""
    b_inf, beta = params.get("backscatter.b_inf"), params.get("backscatter.beta_per_m")
    if not veil or veil.get("low") is None or not b_inf or not beta or b_inf.get("low") is None \
            or beta.get("low") is None:
        return
    r = veil["range_m"]
    with np.errstate(divide="ignore"):
        low = np.asarray(veil["low"]) / -np.expm1(-np.asarray(beta["high"]) * r)
        high = np.asarray(veil["high"]) / -np.expm1(-np.asarray(beta["low"]) * r)
    upper = next(p.upper for p in get("backscatter").params if p.name == "b_inf")
    widened = (low < b_inf["low"]) | (np.minimum(high, upper) > b_inf["high"])
    b_inf.update(low=np.round(np.minimum(low, b_inf["low"]), 6).tolist(),
                 high=np.round(np.minimum(np.maximum(high, b_inf["high"]), upper), 6).tolist(),
                 valley=widened.tolist())
