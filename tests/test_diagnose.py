"""The discovery loop on small simulated surveys: measurements, fit, residual axes, missing-effect
ranking, verdict, ledger, CLI and input errors."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from eval.diagnose import DiagnoseConfig, find_ledger, ledger_table, read_ledger, run_diagnose
from eval.diagnose_fit import FitConfig, fit_stack, make_split
from eval.diagnose_measure import MeasureConfig, measure_survey
from eval.synth import load_truth, make_config, simulate_survey
from eval.synth.rgbd import RGBDConfig
from watergan.errors import UserInputError
from watergan.formation import Stack

SMALL_RGBD = RGBDConfig(n_scenes=1, views_per_scene=2, width_px=32, height_px=24, scene_size_m=8.0,
                        grid_spacing_m=0.25)
FAST = DiagnoseConfig(measure=MeasureConfig(n_points=1200), fit=FitConfig(iterations=200), bootstrap=500)


def small_survey(out: Path, hidden: list[str], seed: int = 1) -> Path:
    """The tiny preset with 2 lines of 8 frames (160x120, 80% forward overlap), mono camera."""
    cfg = make_config("tiny", hidden=hidden, seed=seed)
    cfg = replace(cfg, rgbd=SMALL_RGBD, trajectory=replace(cfg.trajectory, frames_per_line=8, forward_overlap=0.8,
                                                           stereo=False))
    simulate_survey(out, cfg, progress=False)
    return out


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def vignetted(tmp_path_factory) -> Path:
    return small_survey(tmp_path_factory.mktemp("vig") / "survey", ["vignetting_offcentre"])


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    return small_survey(tmp_path_factory.mktemp("clean") / "survey", [])


def test_measurements_are_multiview_and_consistent(clean, tmp_path):
    m = measure_survey(clean, MeasureConfig(n_points=400))
    views = np.bincount(m.point)
    assert views.min() >= 3 and m.n_obs == views.sum()
    truth = load_truth(clean)
    # range agrees with the truth range map at the projected pixel (1 mm PNG steps, bilinear)
    k = m.frame[0]
    x, y = np.rint(m.px[0]).astype(int)
    assert abs(truth.range_m(k)[y, x] - m.range_m[0]) < 0.05
    assert np.all((m.colour > 0) & (m.colour < 1)) and np.all(m.view_angle_deg < 90)
    np.testing.assert_allclose(m.water_depth_m, 20.0 - m.height_m)
    assert m.light_distance_m.shape == (m.n_obs, 0)
    m.save(tmp_path / "m.npz")
    again = type(m).load(tmp_path / "m.npz")
    np.testing.assert_allclose(again.colour, m.colour, rtol=1e-6)
    assert again.image_wh == (160, 120) and again.frames == m.frames


def test_fit_recovers_attenuation_when_nothing_is_hidden(clean):
    m = measure_survey(clean, MeasureConfig(n_points=1200))
    visible = load_truth(clean).effects["visible"]
    true_eta = np.array(visible[0]["params"]["eta_per_m"])
    start = json.loads(json.dumps(visible))
    start[0]["params"]["eta_per_m"] = [0.3, 0.3, 0.3]
    # a nadir survey at near-constant altitude barely separates attenuation from vignetting and
    # backscatter (range follows image radius), so those are held at their known values here
    config = FitConfig(iterations=300, fixed_effects=("backscatter", "vignetting", "gain"))
    fit = fit_stack(Stack.from_config(start), m, make_split(m, config), config)
    eta = fit.params["attenuation"]["eta_per_m"]
    assert np.abs(np.array(eta["value"]) - true_eta).max() < 0.03, eta
    assert all(0 < s < 0.03 for s in eta["std"]) and fit.params["gain"]["k"]["std"] is None
    assert fit.heldout_rmse < 0.015 and fit.residual.shape == (m.n_obs, 3)


def test_finds_hidden_offcentre_vignetting(vignetted):
    result = run_diagnose(vignetted, FAST, progress=False)
    assert result.best == "vignetting_offcentre", result.verdict
    assert result.verdict.startswith("missing: vignetting_offcentre")
    top = result.ranking[0]
    assert top["change"] < -0.15 and top["significant"] and top["flattened"] == "image_position"
    assert np.abs(np.array(top["params"]["centre_uv"]["value"]) - [0.61, 0.44]).max() < 0.05
    assert result.scores["image_position"] > 5
    out = Path(result.out_dir)
    assert out == vignetted / "diagnose"
    for name in ("measurements.npz", "fit.json", "residuals.json", "residuals.npz", "residual_image_position.png",
                 "residual_range.png", "points_residual.ply", "ranking.json", "verdict.txt", "result.json"):
        assert (out / name).is_file(), name
    assert "ambient_depth" in result.skipped and "forward_scatter" in result.skipped
    records = read_ledger(find_ledger(vignetted))
    assert records[0]["kind"] == "model" and len(records) == 1 + len(result.ranking)


def test_no_hidden_effect_gives_no_verdict(clean):
    result = run_diagnose(clean, replace(FAST, plots=False), progress=False)
    assert result.best is None
    assert result.verdict.startswith("no significant missing effect"), result.verdict


def test_add_appends_a_model_version_and_cli_prints_ledger(vignetted, tmp_path):
    ws = tmp_path / "ws"
    (ws / "00_survey").parent.mkdir()
    (ws / "00_survey").symlink_to(vignetted)
    config = replace(FAST, add=("vignetting_offcentre",), candidates=("sensor_response",), plots=False)
    result = run_diagnose(ws, config, progress=False)
    assert result.stack[-2:] == ["vignetting_offcentre", "gain"] and result.out_dir == str(ws / "08_diagnose")
    assert (ws / "08_diagnose" / "result.json").is_file()
    records = read_ledger(ws / "model_ledger.jsonl")
    assert [r["kind"] for r in records] == ["model", "candidate"]
    assert "vignetting_offcentre" in ledger_table(records)
    out = subprocess.run([sys.executable, "-c", "import sys; from pipeline.cli_diagnose import cmd_ledger; "
                          "import argparse; sys.exit(cmd_ledger(argparse.Namespace(workspace=sys.argv[1])))", str(ws)],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "heldout_rmse" in out.stdout and (ws / "model_ledger.png").is_file()


def test_bad_input_is_a_clear_error(tmp_path, clean):
    with pytest.raises(UserInputError, match="does not exist"):
        run_diagnose(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserInputError, match="neither a survey folder"):
        run_diagnose(tmp_path / "empty")
    with pytest.raises(UserInputError, match="more overlap"):
        measure_survey(clean, MeasureConfig(n_points=400, min_views=30))
    with pytest.raises(UserInputError, match="no model_ledger"):
        find_ledger(tmp_path / "empty")
