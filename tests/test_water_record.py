"""water.json's record (watergan/water_record.py): written and read in one place, old files still read."""

from __future__ import annotations

import json

import pytest

from watergan.errors import UserInputError
from watergan.io import DataError
from watergan.water_record import (
    WATER_PLOTS,
    AlternativeRecord,
    ParamInterval,
    WaterRecord,
    Widening,
    read_water,
    write_water,
)

STACK = [{"name": "attenuation", "params": {"eta_per_m": [0.3, 0.1, 0.2]}}]
PARAMS = {"attenuation.eta_per_m": {"value": [0.3, 0.1, 0.2], "low": [0.2, 0.05, 0.1], "high": [0.4, 0.2, 0.3],
                                    "units": "1/m", "fitted": True}}
INTERVALS = {"attenuation.eta_per_m": ParamInterval(
    [0.3, 0.1, 0.2], "1/m", True, low=[0.2, 0.05, 0.1], high=[0.4, 0.2, 0.3],
    widenings=[Widening("free_gains", "cover", [0.05, 0.0, 0.01], [True, False, False])])}
ALTERNATIVES = [AlternativeRecord("free_gains", "the gains per frame free", values={"a.b": [1.0]},
                                  heldout_change_pct=-3.0, ci95_pct=[-4.0, -2.0], preferred=True)]


def test_a_record_reads_back_as_written_with_the_plots_it_names(tmp_path):
    record = WaterRecord(stack=STACK, params=INTERVALS, n_points=12, rmse=0.01, veil={"range_m": 2.0, "value": [0.1]},
                         alternatives=ALTERNATIVES, plots={"residuals.png": "water fit residuals"})
    write_water(tmp_path / "water.json", record)
    assert read_water(tmp_path / "water.json") == record
    on_disk = json.loads((tmp_path / "water.json").read_text())
    assert "fields" not in on_disk and on_disk["veil"] == record.veil  # the optional parts only when set
    assert set(on_disk) == {"stack", "params", "fixed", "held", "tradeoffs", "n_points", "n_observations", "n_board",
                            "n_frames", "rmse", "seconds", "iterations", "converged", "veil", "alternatives",
                            "interval", "plots"}
    back = read_water(tmp_path / "water.json")  # typed throughout: the widening rows and the alternatives' words
    assert back.params["attenuation.eta_per_m"].widening("free_gains").widened == [True, False, False]
    assert back.alternative("free_gains").preferred and back.alternative("other") is None


def test_a_water_json_written_before_the_record_named_its_plots_reads_with_the_stage_plots(tmp_path):
    """The keys of a file the water stage wrote before the record existed (no ``plots``, keys it does not know
    ignored): read as before, with the plots the stage wrote beside it then."""
    (tmp_path / "water.json").write_text(json.dumps({"stack": STACK, "params": PARAMS, "converged": False,
                                                     "interval": "95 %", "unknown": 1}))
    record = read_water(tmp_path / "water.json")
    assert record.stack == STACK and not record.converged
    assert record.params == {key: ParamInterval(**p) for key, p in PARAMS.items()}
    assert record.plots == WATER_PLOTS and record.fields is None


def test_a_file_that_is_not_a_water_json_is_an_error_naming_it(tmp_path):
    (tmp_path / "other.json").write_text(json.dumps({"params": {}}))
    with pytest.raises(UserInputError, match="other.json has no stack"):
        read_water(tmp_path / "other.json")
    with pytest.raises(DataError, match="does not exist"):
        read_water(tmp_path / "missing.json")
