"""The report's first screen: what the run found, one line each (the water and how far to trust it, the camera and
the scale, the fields and gains the water carries, the diagnosis's verdict, the corrections), and the command to run
next."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from watergan.water_record import WaterRecord, read_water

from .workspace import Workspace


class NotRun(Exception):
    """A section's stage has not run; the message says what to run."""


def load_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def stage_result(ws: Workspace, stage: str):
    """The stage's typed result, or NotRun."""
    result = ws.result(stage)
    if result is None:
        raise NotRun(f"not run: no {ws.stage(stage).folder}/result.json (run {ws.stage(stage).how_to_run()})")
    return result


def eval_tables(ws: Workspace) -> dict:
    """The eval stage's tables.json (the file its result names)."""
    data = load_json(ws.path(stage_result(ws, "eval").tables_json))
    if data is None:
        raise NotRun("not run: no tables.json (run `watergan evaluate --workspace WS`)")
    return data


def intervals_at_bounds(params: dict) -> dict[str, list[int]]:
    """{parameter: channels whose 95 % interval reaches one of its bounds} among the water's fitted per-channel
    parameters (``water.json``'s ``params``)."""
    from watergan.formation import get

    out = {}
    for key, entry in params.items():
        name, param = key.split(".", 1)
        if not entry.fitted or entry.low is None or not isinstance(entry.value, list):
            continue
        try:
            spec = next(p for p in get(name).params if p.name == param)
        except (KeyError, StopIteration, ValueError):
            continue
        low, high = np.ravel(entry.low), np.ravel(entry.high)
        channels = [c for c in range(len(low)) if low[c] <= spec.lower or high[c] >= spec.upper]
        if channels and len(low) == 3:
            out[key] = channels
    return out


def unpinned_note(params: dict, veil: dict | None) -> str:
    """What the survey cannot pin, said where an interval of the water's ``params`` reaches its parameter's bound
    (B_inf's where the survey's ranges are short next to the veil's fall), and what it pins instead (the ``veil`` at
    the median range; water.json's, :class:`watergan.water_record.WaterRecord`)."""
    reached = intervals_at_bounds(params)
    if not reached:
        return ""
    names = "; ".join(f"{key.split('.', 1)[1]} in {'/'.join('RGB'[c] for c in channels)}"
                      for key, channels in reached.items())
    pinned = (f" What it pins is the veil over its ranges: {' / '.join(f'{v:.3f}' for v in veil['value'])} at "
              f"{veil['range_m']:.1f} m." if veil and any(k.startswith("backscatter.") for k in reached) else "")
    return (f" Not pinned by this survey (intervals reaching a bound): {names}; its ranges are too short, next to "
            f"the water's attenuation length, to separate them from what they trade with.{pinned}")


#: An alternative moves eta "more than the noise" when its change exceeds this many times the bootstrap's 95 %
#: half-width in some channel.
STRUCTURE_OVER_NOISE = 2.0


def structure_note(record: WaterRecord) -> str:
    """How far to trust the water's attenuation where the survey prefers another structure: an alternative whose
    held-out test says the survey predicts its views better with it and whose change of eta exceeds
    ``STRUCTURE_OVER_NOISE`` times the bootstrap's 95 % half-width in some channel, in the alternative's own words;
    "" otherwise."""
    eta = record.params.get("attenuation.eta_per_m")
    preferred = [a for a in record.alternatives if a.preferred and eta is not None and eta.widening(a.key)]
    if not preferred or eta.std is None:
        return ""
    value = np.maximum(np.abs(np.asarray(eta.value, float)), 1e-9)
    noise = 1.96 * np.asarray(eta.std, float)
    best = min(preferred, key=lambda a: a.heldout_change_pct)
    change = np.asarray(eta.widening(best.key).change, float)
    if not (change > STRUCTURE_OVER_NOISE * noise).any():
        return ""
    return (f" This survey predicts its views {-best.heldout_change_pct:.0f} % better with {best.words} (held-out "
            f"points), and eta then moves by {' / '.join(f'{100 * c:.0f}' for c in change / value)} % (R / G / B), "
            f"against +- {' / '.join(f'{100 * n:.0f}' for n in noise / value)} % from resampling: its intervals "
            f"include that change" + (f"; {best.pinned_by} pins it." if best.pinned_by else "."))


def profile_note(record: WaterRecord) -> str:
    """Where an alternative profiled eta: the eta the held-out views accept, in the alternative's words; ""
    otherwise."""
    profiled = next((a for a in record.alternatives if a.profile), None)
    if profiled is None:
        return ""
    p = profiled.profile
    spans = [f"{'<=' if open_low else ''}{low:.3f}-{high:.3f}{'+' if open_high else ''}"
             for low, high, open_low, open_high in zip(p["low"], p["high"], p["open_low"], p["open_high"], strict=True)]
    return (f" Under {profiled.words.removeprefix('eta as far as the held-out views accept it with ')}, only the "
            f"range differences within the points that frames share pin eta: the held-out views accept "
            f"{' / '.join(spans)} 1/m (R / G / B; <= and +: accepted as far as the profile went), and its intervals "
            f"include that.")


def camera_and_scale_lines(survey, sfm) -> list[str]:
    """The first screen's lines on a camera calibrated on the survey and on where the scale came from (or that there is
    none: everything in SfM units)."""
    lines = []
    calibration = survey.self_calibration if survey is not None else {}
    if calibration:
        lines.append(f"Camera: calibrated on the survey ({calibration['model']}, {calibration['registered']} frames, "
                     f"reprojection {calibration['reprojection_px']:.2f} px); the two halves' focal lengths differ by "
                     f"{calibration['halves']['focal_diff_pct']:.1f} %.")
    if sfm is not None:
        if sfm.scale_method == "none":
            lines.append("Scale: unscaled. No stereo rig, board, altitude, position track or camera height: lengths, "
                         "ranges and the water's coefficients are in SfM units (1 = the median sparse depth).")
        elif sfm.scale_method == "track":
            detail = sfm.scale_detail
            halves = detail.get("halves", {})
            steps = (f"its straight steps: its errors accumulate, Durbin-Watson {detail['durbin_watson']:.2f}; "
                     if detail.get("estimator") == "steps" else "")
            lines.append(f"Scale: from the position track ({steps}{detail['kept']} of {detail['used']} frames, "
                         f"residual {detail['residual_m']:.3f} m, spread "
                         f"{100 * sfm.scale_spread:.1f} %"
                         + (f"; the two halves' scales differ by {halves['heldout_pct']:.1f} %" if halves else "")
                         + ").")
        elif sfm.scale_method == "height":
            halves = sfm.scale_detail.get("halves", {})
            lines.append(f"Scale: from the camera's height over the floor (spread {100 * sfm.scale_spread:.1f} %"
                         + (f"; the two halves' scales differ by {halves['heldout_pct']:.1f} %" if halves else "")
                         + ").")
    return lines


def found_lines(ws: Workspace) -> tuple[list[str], str]:
    """(what the run found, one line each: the water and how far to trust it, what the fields over the image
    carry, the diagnosis's verdict, how the corrections compare; the command to run next, or "")."""
    from eval.water.fields import field_size

    lines, command = [], ""
    sfm = ws.result("sfm")
    if sfm is not None and sfm.looks_distorted:  # before the water: it carries the distortion's error
        from .sfm import distortion_warning

        lines.append("Lens: " + distortion_warning(sfm.lens_k1, sfm.lens_source).removeprefix("sfm: ") + ".")
    if sfm is not None and sfm.still_features:
        from .overlay import overlay_warning

        lines.append("Overlay: " + overlay_warning(sfm.still_features).removeprefix("sfm: ") + ".")
    lines += camera_and_scale_lines(ws.result("survey"), sfm)
    water = ws.result("water")
    if water is not None:
        record = read_water(ws.path(water.water_json))
        trust = ("its intervals are 95 %" if not water.at_bounds else
                 f"not pinned: {', '.join(water.at_bounds)} on a bound (their intervals are the whole range)")
        line = (f"Water: {water.summary.removeprefix('water: ')}; {trust}." + unpinned_note(record.params, record.veil)
                + structure_note(record) + profile_note(record))
        lines.append(in_sfm_units(line) if sfm is not None and sfm.scale_method == "none" else line)
        fields = record.fields
        if fields:
            size = field_size(fields)
            lines.append("Fields over the image: flat, nothing the stack lacks on image position (" + size + ")."
                         if fields["form"] == "flat" else
                         f"Fields over the image: the stack lacks a {fields['form']} structure on image position "
                         f"({size}); the water and the corrections carry it in the fields (see the water section).")
            if fields["form"] != "flat":
                command = f"watergan diagnose {ws.root}"
        grid = record.grid
        if grid and grid["carried"]:
            rows, cols = grid["nodes"]
            lines.append(f"Finer structure on image position than the fields follow ({field_size(grid)}): the "
                         f"corrections carry it on a {rows} x {cols} grid fitted with the water held.")
            command = command or f"watergan diagnose {ws.root}"
        frames = record.frames
        if frames:
            size = f"up to {max(frames['largest_pct']):.0f} %, sd " + " / ".join(f"{v:.1f}" for v in frames["sd_pct"])
            carry = ("the water and the corrections carry it in the gains" if frames.get("carried", True) else
                     "too little for the water to carry them")
            lines.append(f"Gains per frame: flat, nothing the stack lacks from frame to frame ({size} %)."
                         if frames["flat"] else
                         f"Gains per frame: the frames differ by more than the water explains ({size} % per "
                         f"channel: exposure, white balance or a water that changes along the survey); {carry} "
                         f"(see the water section).")
            if not frames["flat"]:
                command = command or f"watergan diagnose {ws.root}"
    diagnosed = ws.result("diagnose")
    if diagnosed is not None:
        verdict = Path(diagnosed.out_dir) / "verdict.txt"
        if verdict.is_file():
            lines.append("Diagnosis: " + verdict.read_text().strip().splitlines()[0])
        command = after_diagnosis(command, diagnosed, ws.root)
    try:
        verdict_lines = eval_tables(ws).get("verdict", [])
    except NotRun:
        verdict_lines = []
    if verdict_lines:
        lose = [line for line in verdict_lines if " loses to " in line]
        tie = [line for line in verdict_lines if " ties with " in line]
        lines.append(f"Comparisons: {len(verdict_lines) - len(lose) - len(tie)} of {len(verdict_lines)} hold"
                     + (f"; {len(tie)} tie (within the measurement's spread)" if tie else "")
                     + (f"; {len(lose)} lose (listed under Verdict)." if lose else "."))
    if sfm is not None and sfm.looks_distorted and not sfm.lens_source:  # the lens first: every stage after SfM
        survey = ws.result("survey")  # carries its error; what already ran is not proposed again
        folder = survey.survey_dir if survey else "SURVEY"
        command = (f"watergan run {folder} --workspace {ws.root}  # with \"calibrated\": false in its camera.json, "
                   f"so that SfM calibrates the camera")
    return lines, command


def after_diagnosis(command: str, diagnosed, root: Path) -> str:
    """The next step once the diagnosis ran (``diagnosed``, its result), never the diagnosis again: add the effect
    it found; else, where the water still carries structure (``command``, what the first screen would advise without
    the diagnosis) or the diagnosis names axes no effect explains, write that effect and add it; else nothing."""
    if diagnosed.best:
        return f"watergan run --workspace {root} --add {diagnosed.best}"
    if command or diagnosed.unexplained_axes:
        return (f"watergan --plugin FILE.py run --workspace {root} --add NAME  # no library effect explains it: write "
                f"the effect NAME in FILE.py (docs/discovery.md) and add it")
    return ""


def in_sfm_units(line: str) -> str:
    """A first-screen line of a run without a metric scale in the units it is in: eta per SfM unit, lengths in SfM
    units (1 = the median sparse depth), not per metre and metres."""
    line = line.replace("eta_per_m", "eta per SfM unit").replace(" 1/m", " per SfM unit")
    return re.sub(r"(\d) m\b", r"\1 SfM units", line)
