"""The diagnosis's verdict in words, and the checks that decide whether a candidate is accepted.

A candidate whose fitted values are not physical (:func:`why_implausible`), that cannot be told from the veil
(:func:`same_colour`) or whose form on image position is not the
water's fields' (:func:`form_conflict`) is not accepted; an image-position candidate that reproduces part of the
fields is accepted as a partial step, or not accepted, by :func:`fields_share_check`; a candidate that flattens the
axis of an added effect whose form does not fit (:func:`added_form_misfit`) stands in for it (:func:`stand_in`).
:func:`verdict_text` writes the verdict: its headline is the accepted candidate, else the axis that holds the largest
share of the unexplained error (on image position: :func:`unmatched_form_line`), the others after it, else none;
then the implausible candidates, the structure no candidate explains (:func:`unexplained_axes`), and the water's
fields over the image and gains per frame (water.json's, :class:`watergan.water_record.WaterRecord`).
:mod:`eval.diagnose` ranks the candidates and calls these.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from watergan.formation import get

from .water.fields import field_size

if TYPE_CHECKING:
    from .diagnose import CandidateResult, DiagnoseConfig


#: A fitted value within this fraction of its parameter's span from a bound sits on the bound.
AT_BOUND = 0.005

#: The least share of the water's fields over the image (when they carry structure) that an image-position
#: candidate must reproduce to be accepted as the missing effect: its fit has to flatten them, not only lower the
#: held-out error. A form of the library reproduces nearly all of what it left in the fields; a falloff of another
#: shape (Gaussian, clipped into a ring) is partly taken by an off-centre vignetting, which then lowers the held-out
#: error much while leaving a large share of the fields (measured: benchmarks/RESULTS/water.md, issue 52).
FIELDS_EXPLAINED_MIN = 0.8
#: Below FIELDS_EXPLAINED_MIN, the least share of the fields a candidate must reproduce, with the least cut of the
#: held-out error (PARTIAL_CHANGE_MIN), to be accepted as a partial step: the larger part of the fields' structure
#: and the larger part of the held-out error, so that what it takes is the structure at work and not a stand-in
#: that fits a little of everything (the off-centre vignetting on the Gaussian and clipped falloffs of bench_forms:
#: 59 % and 69 % of the fields; on additive fields 0 %).
FIELDS_PARTIAL_MIN = 0.5
#: The least relative cut of the held-out error of a partial step (see FIELDS_PARTIAL_MIN).
PARTIAL_CHANGE_MIN = 0.5


def fields_share_check(name: str, explained: float | None, change: float, structured: bool) -> tuple[str, bool]:
    """Whether image-position candidate ``name``, which reproduces ``explained`` of the water's fields over the image
    (:func:`eval.diagnose.fields_explained`; None: no fields, or not an image-position candidate) and changes the
    held-out error by ``change`` (relative; negative: better), may be accepted, when the fields carry structure
    (``structured``): (why not, "" when it may; whether it is a partial step). At least ``FIELDS_EXPLAINED_MIN`` of
    the fields: the missing effect. At least ``FIELDS_PARTIAL_MIN`` of them and a cut of at least
    ``PARTIAL_CHANGE_MIN`` of the held-out error: a partial step (add it; what remains is of another form). Less:
    not accepted, whatever it does to the held-out error. The other checks (significance, plausible values, the
    fields' form) apply as to any candidate."""
    if not structured or explained is None or explained >= FIELDS_EXPLAINED_MIN:
        return "", False
    if explained >= FIELDS_PARTIAL_MIN and change <= -PARTIAL_CHANGE_MIN:
        return "", True
    return (f"it flattens too little of them (under {FIELDS_EXPLAINED_MIN:.0%}, and under {FIELDS_PARTIAL_MIN:.0%} or "
            f"cutting under {PARTIAL_CHANGE_MIN:.0%} of the held-out error for a partial step): the structure on "
            f"image position has another form than {name}'s"), False


def why_implausible(name: str, params: dict) -> str:
    """Why the fitted values of candidate ``name`` (``FitResult.params[name]``) are not physical, "" when they
    are: a fitted value on a bound (within ``AT_BOUND`` of the span; the fit wanted to go further than the
    effect's form allows) or outside the parameter's declared envelope (``Param.plausible``). A bound at 0
    is no reason: there a part of the effect is off (no ambient light, no decay), which is physical."""
    reasons = []
    for p in get(name).params:
        entry = params.get(p.name)
        if entry is None or not entry["fitted"]:
            continue
        values = np.ravel(entry["value"])
        span = p.upper - p.lower if p.bounded_above else max(abs(p.lower), 1.0)
        on_bound = [v for v in values if (p.lower != 0 and v - p.lower < AT_BOUND * span)
                    or (p.bounded_above and p.upper != 0 and p.upper - v < AT_BOUND * span)]
        outside = [v for v in values if p.plausible and not p.plausible[0] <= v <= p.plausible[1]]
        units = f" {p.units}" if p.units else ""
        if outside:
            reasons.append(f"{p.name} = {outside[0]:.3g}{units} outside [{p.plausible[0]:g}, {p.plausible[1]:g}]"
                           f"{units}")
        elif on_bound:
            bound = p.lower if on_bound[0] - p.lower < AT_BOUND * span else p.upper
            reasons.append(f"{p.name} = {on_bound[0]:.3g}{units} at its bound {bound:g}")
    return "; ".join(reasons)


#: Two values per channel within this angle (degrees, in RGB) share one colour.
SAME_COLOUR_DEG = 10.0


def same_colour(name: str, params: dict) -> str:
    """Why candidate ``name`` cannot be told from another effect, "" when it can: a parameter its effect declares in
    ``same_colour_as`` fitted to the colour of the other effect's parameter there (``params``: ``FitResult.params``,
    all the fit's effects; within ``SAME_COLOUR_DEG``, either sign). A black level of the veil's colour is a share of
    the veil taken out from under the vignetting: what it cuts is the model's form on image position (the one thing
    that sets the two apart), not a camera's pedestal, whose colour is the sensor's and not the water's."""
    from watergan.formation import get

    for key, other in get(name).same_colour_as.items():
        effect, param = other.split(".", 1)
        entry, ref = params.get(name, {}).get(key), params.get(effect, {}).get(param)
        if entry is None or ref is None or not entry["fitted"]:
            continue
        b, v = np.ravel(entry["value"]).astype(float), np.ravel(ref["value"]).astype(float)
        norm = float(np.linalg.norm(b) * np.linalg.norm(v))
        if b.shape != v.shape or norm <= 0:
            continue
        angle = float(np.degrees(np.arccos(min(1.0, abs(float(b @ v)) / norm))))
        if angle <= SAME_COLOUR_DEG:
            return (f"it cannot be told from {effect}: its {key} ({', '.join(f'{x:.3f}' for x in b)}) has the colour "
                    f"of {other} ({', '.join(f'{x:.3f}' for x in v)}; {angle:.0f} degrees apart)")
    return ""


def form_conflict(name: str, form: str, fields: dict | None) -> str:
    """Why candidate ``name`` of this ``form`` (:func:`effect_form`) does not fit the water's fields over the image
    (``fields``: water.json's, :func:`eval.water.fields.field_summary`), "" when it does or there is nothing to compare:
    a candidate that would explain them (one on image position, or one whose fit flattens that axis: the caller
    decides) must have the fields' form (multiplicative or additive)."""
    if not fields or fields.get("form") not in ("multiplicative", "additive"):
        return ""
    if form in (fields["form"], "both"):
        return ""
    return (f"its form is {form} while the water's fields over the image carry {fields['form']} structure "
            f"({field_size(fields)})")


def fields_line(fields: dict | None) -> str:
    """The verdict's line on the water's fields over the image ("" without them)."""
    if not fields:
        return ""
    size = field_size(fields)
    if fields["form"] == "flat":
        return f"fields: the water's fields over the image are flat ({size}): nothing missing on image position"
    return (f"fields: the water's fields over the image carry {fields['form']} structure ({size}): an effect of that "
            f"form on image position is missing (04_water/fields.png)")


def frames_line(frames: dict | None) -> str:
    """The verdict's line on the water's gains per frame (water.json's ``frames``; "" without them)."""
    if not frames:
        return ""
    size = f"up to {max(frames['largest_pct']):.0f} %"
    if frames["flat"]:
        return f"frames: the water's gains per frame are flat ({size}): nothing missing from frame to frame"
    kept = "" if frames.get("carried", True) else "; small enough that the water is fitted without them"
    return (f"frames: the water's gains per frame carry {size} beyond what the frames' ranges explain: something "
            f"changes from frame to frame (exposure, white balance, the water along the survey; 04_water/frames.png)"
            + kept)


def unexplained_axes(final_scores: dict, structure: dict, config: DiagnoseConfig) -> list[str]:
    """Axes with structure score > ``structure_threshold`` and amplitude >= ``structure_fraction`` of the RMSE."""
    return [a for a, s in final_scores.items()
            if s > config.structure_threshold and structure.get(a, 0.0) >= config.structure_fraction]


def _short_params(params: dict) -> str:
    """The first fitted parameter, e.g. "centre_uv (0.61, 0.44)", or its range when it has more than
    ``SHORT_VALUES`` values (one per frame): "log_gain (16 values, -0.33 to 0.27)"."""
    for pname, p in params.items():
        if p["fitted"]:
            value = np.ravel(p["value"])
            if len(value) > SHORT_VALUES:
                return f"{pname} ({len(value)} values, {value.min():.2f} to {value.max():.2f})"
            text = f"({', '.join(f'{v:.2f}' for v in value)})" if isinstance(p["value"], list) else f"{value[0]:.3g}"
            return f"{pname} {text}"
    return ""


#: Values of a parameter the verdict lists one by one; more are summarised by their range.
SHORT_VALUES = 6


def verdict_text(ranking: list[CandidateResult], unexplained: list[str], final_scores: dict,
                 final_structure: dict | None = None, misfit: str = "", fields: dict | None = None,
                 frames: dict | None = None) -> str:
    """The verdict, its headline first: the accepted candidate (:func:`accepted_line`; a partial step says what
    remains), else the axis that holds the largest share of the unexplained error (``final_structure``: the
    structure's amplitude over the RMSE per axis; image position when the water's ``fields`` carry structure that a
    candidate cut but no library form reproduces, :func:`unmatched_form_line`, the others from ``unexplained``) with
    the others after it, else none; then a line per candidate that would explain enough but is implausible;
    ``misfit`` (:func:`added_form_misfit`); a line on the unexplained structure not in the headline; a line on the
    water's ``fields`` over the image (:func:`fields_line`) and one on its gains per frame (:func:`frames_line`)."""
    size = final_structure or {}

    def share(axis: str) -> str:
        part = f", {size[axis]:.0%} of the RMSE" if axis in size else ""
        return f"{axis} (score {final_scores[axis]:.1f}{part})" if axis in final_scores else axis

    best = next((r for r in ranking if r.significant), None)
    unmatched = unmatched_form_line(ranking, fields) if best is None else ""
    axes = sorted(unexplained, key=lambda a: -size.get(a, 0.0))
    lead = axes[0] if best is None and axes else None
    if lead is not None and unmatched and (lead == "image_position"
                                           or size.get(lead, 0.0) <= size.get("image_position", 0.0)):
        lead = None  # image position holds the most: the unmatched form leads
    if best is not None:
        line = accepted_line(best, fields)
    elif lead is not None:
        line = (f"missing: structure along {share(lead)}, the largest share of the unexplained error — no registered "
                f"candidate explains it; an effect whose signature lies on this axis is missing (write one and pass "
                f"--plugin FILE.py)")
        axes.remove(lead)
        if unmatched:
            line += "\nthen " + unmatched.removeprefix("missing: ")
        if ranking:
            line += f"\n{no_candidate_line(ranking, 'no library candidate accepted')}"
    elif unmatched:
        line = unmatched
    else:
        line = no_candidate_line(ranking)
    for r in ranking:
        if r.implausible and r.p < 0.05 and r.change < 0:
            part = (f" and reproduces {r.fields_explained:.0%} of the water's fields over the image"
                    if r.fields_explained is not None else "")
            line += (f"\nimplausible: {r.name} explains {-r.change:.0%} of the held-out error{part}, but "
                     f"{r.implausible}; not accepted")
    if misfit:
        line += f"\n{misfit}"
    if axes:
        line += (f"\nunexplained structure along: {', '.join(share(a) for a in axes)} — no registered candidate "
                 f"explains it; an effect whose signature lies on this axis is missing (write one and pass "
                 f"--plugin FILE.py)")
    for extra in (fields_line(fields), frames_line(frames)):
        line += f"\n{extra}" if extra else ""
    return line


def accepted_line(best: CandidateResult, fields: dict | None) -> str:
    """The headline naming the accepted candidate ``best``, its held-out change, first value and the axis it
    flattens, and (when the water's ``fields`` carry structure) the share of them it reproduces; for a partial step
    (``best.partial``), that the rest of the fields' structure is of another form."""
    structured = best.fields_explained is not None and bool(fields) and fields.get("form") != "flat"
    line = (f"missing: {best.name} — held-out error {best.change * 100:+.0f}% "
            f"(95% CI {best.ci95[0] * 100:+.0f}% to {best.ci95[1] * 100:+.0f}%), {_short_params(best.params)}; "
            f"flattens the {best.flattened} axis"
            + (f"; reproduces {best.fields_explained:.0%} of the water's fields over the image" if structured else ""))
    if best.partial and structured:
        line += (f": a partial step — add it; what remains is of another form (the fields still carry "
                 f"{1 - best.fields_explained:.0%} of their structure, {field_size(fields)}, which no library "
                 f"effect's form explains: write that form and pass --plugin FILE.py)")
    return line


def no_candidate_line(ranking: list[CandidateResult], head: str = "no significant missing effect") -> str:
    """``head``, with the best candidate's held-out change and p."""
    if not ranking:
        return head
    top = ranking[0]
    return f"{head} (best candidate {top.name}: held-out error {top.change * 100:+.1f}%, p = {top.p:.2f})"


def unmatched_form_line(ranking: list[CandidateResult], fields: dict | None) -> str:
    """When no candidate is accepted while the water's fields over the image carry structure (``fields``' form not
    "flat") and an image-position candidate (one that says how much of them it reproduces) would have cut the
    held-out error (p < 0.05, change < 0) but was not accepted (its form, its share of the fields, or its values):
    the line naming the axis, with the first such candidate; "" otherwise. The structure is real (the fields and
    the held-out error both say so), but its form is not a library effect's."""
    if not fields or fields.get("form", "flat") == "flat":
        return ""
    turned = next((r for r in ranking if r.fields_explained is not None and r.implausible and r.p < 0.05
                   and r.change < 0), None)
    if turned is None:
        return ""
    return (f"missing: structure on image position of a form not in the library — the water's fields over the image "
            f"carry {fields['form']} structure ({field_size(fields)}); the closest library effect, {turned.name}, "
            f"cuts the held-out error by {-turned.change:.0%} and reproduces {turned.fields_explained:.0%} of them, "
            f"not accepted (write that form and pass --plugin FILE.py)")


def added_form_misfit(added: tuple[str, ...], model_scores: dict, structure: dict, config: DiagnoseConfig) -> str:
    """When the model's structure (``model_scores``, ``structure``: of the fit with the added effects) is still
    unexplained (:func:`unexplained_axes`) along the axis of the effect added last (``added[-1]``), a line
    saying that the added effect's form does not fit and where its residual map is; else ""."""
    if not added:
        return ""
    name = added[-1]
    axis = get(name).axis
    if axis not in unexplained_axes(model_scores, structure, config):
        return ""
    return (f"the added effect's form does not fit: with {name} in the model, structure remains along its own "
            f"axis, {axis} (score {model_scores[axis]:.1f}, {structure[axis]:.0%} of the RMSE; residual_{axis}.png): "
            f"the effect at work has another shape than {name}'s (write that form and pass --plugin FILE.py)")


def stand_in(r: CandidateResult, added: str) -> CandidateResult:
    """When the form of the effect ``added`` last does not fit (:func:`added_form_misfit`), a candidate that
    flattens that effect's axis without it being its own (a sensor curve flattening image position) stands in
    for the missing form rather than being a missing effect: not significant, with the reason."""
    axis = get(added).axis
    if r.flattened != axis or get(r.name).axis == axis:
        return r
    reason = f"it flattens {axis}, the axis of {added} whose form does not fit, not its own axis ({get(r.name).axis})"
    return replace(r, significant=False, implausible="; ".join(filter(None, (r.implausible, reason))))
