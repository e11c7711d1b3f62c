"""``water.json``: the water stage's estimate on disk, written and read here alone.

The water stage (``pipeline/water.py``) writes the record of :func:`eval.water.estimate_water`'s estimate
(:meth:`eval.water.WaterEstimate.to_record`) with :func:`write_water`; WaterGAN's site water
(:mod:`watergan.site_water`), the diagnosis and the report read it with :func:`read_water`. The file is the
record's fields as JSON keys; keys are added, never renamed, so a file written before a field existed reads with its
default.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from .errors import UserInputError
from .io import atomic_write_json, read_json

#: The plots the water stage writes beside water.json ({file name: what it shows}). A water.json written before its
#: ``plots`` named them reads with these (the readers show the ones that exist).
WATER_PLOTS = {"residuals.png": "water fit residuals", "fields.png": "fields over the image",
               "frames.png": "gains per frame"}


@dataclass
class WaterRecord:
    """The site water as ``water.json`` holds it (JSON values throughout).

    stack:     the fitted formation stack, {name, params} entries (:meth:`watergan.formation.Stack.to_config`).
    params:    {"effect.param": {"value", "units", "fitted", "pinned_by"; fitted ones also "low", "high", "std",
               "specification", "specification_by" (each alternative, as JSON, with its change), "on_bound", "p2_5",
               "p97_5"}}: the 95 % intervals (:class:`eval.water.WaterEstimate`).
    fixed:     effects held at their values and why; ``held``: {"effect.param": why} held inside fitted effects.
    tradeoffs: [a, b, correlation] parameter components whose bootstrap |correlation| exceeds 0.95.
    n_points, n_observations, n_board, n_frames: sizes of the measurement table; ``rmse``: RMS residual of the
               views (linear colour); ``seconds``: wall time per part.
    iterations, converged: the main fit's L-BFGS iterations and whether it converged.
    fields, frames, grid, veil: the fields over the image, the gains per frame, the fine grid and the veil at the
               views' median range (:mod:`eval.fields`, :func:`eval.intervals.veil_at_median_range`); None: none.
    structure: each structure alternative's held-out test and attenuation ({"alternative", "eta_per_m",
               "heldout_change_pct", "ci95_pct", "preferred"}, and "eta_profile" where the survey prefers gains
               per frame free of the ranges: :func:`eval.water.structure_fits`); None: none tried.
    interval:  how the intervals were made, in words.
    plots:     {file name beside water.json: what it shows} of the plots the stage wrote; None: not named (not in
               the file; :func:`read_water` gives a file without them ``WATER_PLOTS``).
    """

    stack: list[dict]
    params: dict = field(default_factory=dict)
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
    structure: list | None = None
    interval: str = ""
    plots: dict[str, str] | None = None

    def to_json(self) -> dict:
        """The file's JSON: every field in order, the optional parts (fields, frames, grid, veil, structure, plots)
        only when set."""
        optional = ("fields", "frames", "grid", "veil", "structure", "plots")
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in optional or getattr(self, f.name) is not None}


def alternative_key(change: dict) -> str:
    """The label of a specification or structure alternative (a change of the water's configuration) in
    water.json's ``specification_by``: its JSON, keys sorted."""
    return json.dumps(dict(change), sort_keys=True)


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
