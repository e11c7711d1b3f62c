"""``water.json``: the water stage's estimate on disk, written and read here alone.

The water stage (``pipeline/water.py``) writes the record of :func:`eval.water.estimate_water`'s estimate
(:meth:`eval.water.WaterEstimate.to_record`) with :func:`write_water`; WaterGAN's site water
(:mod:`watergan.site_water`), the diagnosis and the report read it with :func:`read_water`. The file is the
record's fields as JSON keys; keys are added, never renamed, so a file written before a field existed reads with its
default.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from .errors import UserInputError
from .io import atomic_write_json, read_json

#: The plots the water stage writes beside water.json ({file name: what it shows}). A water.json written before its
#: ``plots`` named them reads with these (the readers show the ones that exist).
WATER_PLOTS = {"residuals.png": "water fit residuals", "fields.png": "fields over the image",
               "frames.png": "gains per frame"}


@dataclass
class Widening:
    """What one alternative did to a parameter's interval.

    alternative: the alternative's key (its record in ``WaterRecord.alternatives`` gives its words).
    rule:        how it counts: "quadrature" (its change adds, the largest of them, in quadrature to the
                 bootstrap's half-width), "cover" (the interval covers its value with the bootstrap's spread),
                 "bounds" (the interval covers the values it accepts), "valley" (B_inf along the valley the veil
                 and beta leave it in).
    change:      |its value - the estimate| per component (for "bounds" and "valley": how far its span reaches
                 past the estimate).
    widened:     per component, whether it moved the interval.
    """

    alternative: str
    rule: str
    change: list
    widened: list


@dataclass
class ParamInterval:
    """One parameter of the fitted stack: its value and, when fitted, its 95 % interval and what widened it.

    value, units, fitted, pinned_by: the estimate, its units, whether the water fitted it, what measurement pins it.
    low, high:     the 95 % interval (None: not fitted, or no bootstrap).
    std:           the bootstrap's standard deviation; ``p2_5``, ``p97_5``: its percentiles.
    specification: the largest change under the "quadrature" alternatives (what the half-width adds).
    on_bound:      per component, on a bound of the parameter's range (the interval is then that range).
    widenings:     each alternative's row (:class:`Widening`).
    """

    value: list | float
    units: str = ""
    fitted: bool = False
    pinned_by: str = ""
    low: list | None = None
    high: list | None = None
    std: list | None = None
    specification: list | None = None
    on_bound: list | None = None
    p2_5: list | None = None
    p97_5: list | None = None
    widenings: list[Widening] = field(default_factory=list)

    def widening(self, alternative: str) -> Widening | None:
        """The row of the alternative keyed ``alternative`` (None: it did not move this parameter)."""
        return next((w for w in self.widenings if w.alternative == alternative), None)

    def to_json(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}

    @classmethod
    def from_json(cls, data: dict) -> ParamInterval:
        known = {f.name for f in dataclasses.fields(cls)}
        rows = [Widening(**{k: w[k] for k in ("alternative", "rule", "change", "widened")})
                for w in data.get("widenings", []) if isinstance(w, dict) and "alternative" in w]
        return cls(**{**{k: v for k, v in data.items() if k in known}, "widenings": rows})


@dataclass
class AlternativeRecord:
    """One alternative the intervals took in, in its own words.

    key:        its name (the :class:`Widening` rows refer to it).
    words:      what it is, for the report ("the gains per frame free to follow the frames' ranges").
    pinned_by:  what kind of survey would tell it from the estimate ("" where that is not a question of the survey).
    values:     its estimate of the fitted parameters of up to nine components ({"effect.param": value}).
    heldout_change_pct, ci95_pct, preferred: its held-out test, where it has one: the change of the held-out
                views' RMSE against the estimate's structure, its 95 % interval, and whether the whole interval
                is below -0.1 % (the survey predicts its unseen views better with it); ``rejected``: the whole
                interval above +0.1 % (it predicts them worse: its values are its fit's on the training points).
    profile:    a profile's accepted span ({"param", "eta_per_m", "low", "high", "open_low", "open_high", "steps"}).
    seconds:    its wall time.
    """

    key: str
    words: str
    pinned_by: str = ""
    values: dict = field(default_factory=dict)
    heldout_change_pct: float | None = None
    ci95_pct: list | None = None
    preferred: bool | None = None
    rejected: bool | None = None
    profile: dict | None = None
    seconds: float = 0.0

    def to_json(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}

    @classmethod
    def from_json(cls, data: dict) -> AlternativeRecord:
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


@dataclass
class WaterRecord:
    """The site water as ``water.json`` holds it.

    stack:     the fitted formation stack, {name, params} entries (:meth:`watergan.formation.Stack.to_config`).
    params:    {"effect.param": :class:`ParamInterval`}: the estimate and its 95 % intervals.
    fixed:     effects held at their values and why; ``held``: {"effect.param": why} held inside fitted effects.
    tradeoffs: [a, b, correlation] parameter components whose bootstrap |correlation| exceeds 0.95.
    n_points, n_observations, n_board, n_frames: sizes of the measurement table; ``rmse``: RMS residual of the
               views (linear colour); ``seconds``: wall time per pass.
    iterations, converged: the main fit's L-BFGS iterations and whether it converged.
    fields, frames, grid, veil: the fields over the image, the gains per frame, the fine grid and the veil at the
               views' median range; None: none.
    alternatives: each alternative the intervals took in (:class:`AlternativeRecord`).
    interval:  how the intervals were made, in words.
    plots:     {file name beside water.json: what it shows} of the plots the stage wrote; None: not named (not in
               the file; :func:`read_water` gives a file without them ``WATER_PLOTS``).
    """

    stack: list[dict]
    params: dict[str, ParamInterval] = field(default_factory=dict)
    fixed: dict = field(default_factory=dict)
    held: dict = field(default_factory=dict)
    tradeoffs: list = field(default_factory=list)
    n_points: int = 0
    n_observations: int = 0
    n_board: int = 0
    n_frames: int = 0
    rmse: float = 0.0
    seconds: dict = field(default_factory=dict)
    iterations: int = 0
    converged: bool = True
    fields: dict | None = None
    frames: dict | None = None
    grid: dict | None = None
    veil: dict | None = None
    alternatives: list[AlternativeRecord] = field(default_factory=list)
    interval: str = ""
    plots: dict[str, str] | None = None

    def __post_init__(self) -> None:
        """Parameters and alternatives given as JSON (a file, a test's literal) become their typed records."""
        self.params = {key: p if isinstance(p, ParamInterval) else ParamInterval.from_json(p)
                       for key, p in self.params.items() if isinstance(p, dict | ParamInterval)}
        self.alternatives = [a if isinstance(a, AlternativeRecord) else AlternativeRecord.from_json(a)
                             for a in self.alternatives if isinstance(a, dict | AlternativeRecord)]

    def alternative(self, key: str) -> AlternativeRecord | None:
        """The alternative keyed ``key`` (None: not taken in)."""
        return next((a for a in self.alternatives if a.key == key), None)

    def to_json(self) -> dict:
        """The file's JSON: every field in order, the optional parts (fields, frames, grid, veil, plots) only when
        set."""
        optional = ("fields", "frames", "grid", "veil", "plots")
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name not in optional or getattr(self, f.name) is not None}
        out["params"] = {key: p.to_json() for key, p in self.params.items()}
        out["alternatives"] = [a.to_json() for a in self.alternatives]
        return out


def write_water(path: str | Path, record: WaterRecord) -> None:
    """Write ``record`` as ``path`` (atomically)."""
    atomic_write_json(Path(path), record.to_json())


def read_water(path: str | Path) -> WaterRecord:
    """The record of a ``water.json``; a missing or malformed file is an error naming it (a file without a stack
    list is not the water stage's). Keys the record does not know are ignored; a file that names no plots (written
    before the record named them) gets ``WATER_PLOTS``."""
    path = Path(path)
    data = read_json(path, "water file")
    if not isinstance(data, dict) or not isinstance(data.get("stack"), list) \
            or not isinstance(data.get("params", {}), dict):
        raise UserInputError(f"water file {path} has no stack: is it the water stage's water.json?")
    known = {f.name for f in dataclasses.fields(WaterRecord)}
    record = WaterRecord(**{key: value for key, value in data.items() if key in known})
    if record.plots is None:
        record.plots = dict(WATER_PLOTS)
    return record
