"""The discovery loop on small simulated surveys: measurements (truth and SfM geometry), fit,
residual axes, missing-effect ranking for every effect the simulator can hide, two effects found
one per round, a plugin found from its file, the ledger with colour measurements, CLI and input
errors.

Surveys: eval.diagnose.small_survey_config (16 frames of 160x120, 40 mm texels), 600 sampled
points, 60 L-BFGS iterations per fit. Numbers quoted in xfail reasons come from
``.venv/bin/python benchmarks/bench_diagnose.py --survey small`` on the same surveys."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from eval.diagnose import (
    DiagnoseConfig,
    candidate_names,
    default_stack,
    effect_form,
    small_survey_config,
    survey_counts,
)
from eval.diagnose_measure import MeasureConfig, geometry_from_truth, measure_survey
from eval.diagnose_verdict import form_conflict, verdict_text, why_implausible
from eval.fit import FitConfig
from eval.heldout import fit_stack, make_split
from eval.ledger import find_ledger, ledger_table, read_ledger
from eval.synth import load_truth, simulate_survey
from eval.synth.config import default_visible_stack
from eval.synth.presets import NOT_SIMULATED
from pipeline.diagnose import measure_target, run_diagnose
from pipeline.stages import STAGES, stage_folder
from pipeline.workspace import Workspace
from watergan.errors import UserInputError
from watergan.formation import Stack, available

#: Candidates: the effects registered when the tests are collected (a plugin that another test module
#: registers later in the same process must not join the ranking), less ambient_depth: the screen skips
#: it (the albedo absorbs it, test_the_screen_skips_what_the_albedo_absorbs_and_says_how_to_force_it), but
#: a named candidate is fitted anyway.
BUILTIN = tuple(n for n, cls in available().items() if not cls.nuisance)
FAST = DiagnoseConfig(candidates=tuple(n for n in BUILTIN if n != "ambient_depth"),
                      measure=MeasureConfig(n_points=600), fit=FitConfig(iterations=60, bootstrap=0), bootstrap=500,
                      plots=False)
#: Every effect the simulator can hide (the visible stack's effects are in the model already).
HIDEABLE = sorted(set(BUILTIN) - {e["name"] for e in default_visible_stack()} - set(NOT_SIMULATED))
#: Effects that the diagnosis cannot find from multi-view colour at their simulated strength, and why
#: (measured on the surveys of test_hidden_effect_is_found; "view-dependent change": RMS of the change
#: the effect makes to each observation's colour less its mean over the point's views, i.e. what a
#: per-point albedo cannot absorb; the floor: held-out RMSE 0.0035 on the survey with nothing hidden).
NOT_IDENTIFIABLE = {
    "sensor_response": "found (ranks first, significant) but the cut is -41% (0.0059 -> 0.0035), not -50%: "
                       "refitted albedos, attenuation and vignetting absorb most of a gamma curve on a "
                       "multiplicative model, and the true model with its true values does no better (0.0033, "
                       "-44%): no model can cut half on this survey",
    "backscatter_coefficient": "its view-dependent change is 0.0022 RMS, below the 0.0035 floor: over the survey's "
                               "ranges (2.4-3.2 m, 0.37 m between a point's views) a veil saturating at rho beta_D "
                               "is the refitted backscatter; the true model with its true values changes the "
                               "held-out error by +0%, the candidate by -0%",
    "wideband_attenuation": "its view-dependent change is 0.0026 RMS, below the 0.0035 floor: over 2.4-3.2 m a "
                            "range-dependent beta(r) is a refitted eta; the true model with its true values changes "
                            "the held-out error by +1%, the candidate by +1% (rank 4)",
    "forward_scatter": "not a candidate (needs whole images): a blur keeps patch means, its view-dependent change is "
                       "0.0008 RMS against the 0.0035 floor; its signature is texture contrast, not colour",
    "ambient_depth": "not a candidate: the light reaching a point is the same in all its views, so the per-point "
                     "albedo absorbs it (view-dependent change 0.0006 RMS); it needs known albedos (a board at "
                     "several heights), not multi-view colour",
    "tone_curve": "found (ranks first, significant) but the cut is -32%, not -50%: on one exposure per frame the "
                  "refitted albedos, attenuation and backscatter take most of a curve between the sensor and the "
                  "sRGB written, as they take sensor_response's gamma; exposures that change from frame to frame "
                  "pin a curve, and this survey's camera has one exposure",
    "black_level": "-1.1% (not significant): an offset per channel at the sensor is the refitted backscatter's veil, "
                   "which has saturated at the survey's ranges (beta up to 5 /m over 2.4-3.2 m); only the vignetting, "
                   "which scales the veil and not the offset, tells them apart",
    "specular_gloss": "found (ranks first, significant, flattens the incidence_angle axis) but the cut is -41%, not "
                      "-50%: the held-out error falls from 0.0058 to 0.0034, the survey's floor (0.0035), so no model "
                      "cuts half; the fitted gloss (0.03, 0.08, 0.07) is below the hidden 0.15 (the views' normals "
                      "from the depth maps and the 5 px patches blur the lobe, and the refitted water takes part)",
    "marine_snow": "not a candidate (needs whole images): particles are random per frame, not a function of the "
                   "geometry (view-dependent change 0.0036 RMS); with patches holding clipped pixels dropped they "
                   "leave a held-out error of 0.0041 and structure along spatial_frequency (see "
                   "test_marine_snow_leaves_structure_along_spatial_frequency)",
}


def small_survey(out: Path, hidden: list, seed: int = 1, **kwargs) -> Path:
    simulate_survey(out, small_survey_config(hidden, seed=seed, **kwargs), progress=False)
    return out


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def surveys(tmp_path_factory):
    """Simulated surveys by hidden effects (each simulated once per module)."""
    cache: dict[tuple[str, ...], Path] = {}

    def get(*names: str) -> Path:
        if names not in cache:
            folder = tmp_path_factory.mktemp("-".join(names) or "clean") / "survey"
            cache[names] = small_survey(folder, list(names))
        return cache[names]

    return get


@pytest.fixture(scope="module")
def diagnosed(surveys):
    """The diagnosis (FAST, with plots for vignetting_offcentre) of the survey hiding ``names``, once."""
    cache = {}

    def get(*names: str):
        if names not in cache:
            cache[names] = run_diagnose(surveys(*names), replace(FAST, plots=names == ("vignetting_offcentre",)),
                                        progress=False)
        return cache[names]

    return get


@pytest.fixture(scope="module")
def clean(surveys) -> Path:
    return surveys()


def test_measurements_are_multiview_and_consistent(clean, tmp_path):
    m = measure_survey(clean, MeasureConfig(n_points=400))
    assert m.source == "truth"
    views = np.bincount(m.point)
    assert views.min() >= 3 and m.n_obs == views.sum()
    truth = load_truth(clean)
    # range agrees with the truth range map at the projected pixel (1 mm PNG steps, bilinear)
    k = m.frame[0]
    x, y = np.rint(m.px[0]).astype(int)
    assert abs(truth.range_m(k)[y, x] - m.range_m[0]) < 0.05
    assert np.all((m.colour > 0) & (m.colour <= 1)) and np.all(m.view_angle_deg < 90)  # 1: clipped white
    np.testing.assert_allclose(m.water_depth_m, 20.0 - m.height_m)
    assert m.light_distance_m.shape == (m.n_obs, 0)
    m.save(tmp_path / "m.npz")
    again = type(m).load(tmp_path / "m.npz")
    np.testing.assert_allclose(again.colour, m.colour, rtol=1e-6)
    assert again.image_wh == (160, 120) and again.frames == m.frames


def _tracks_from_truth(survey: Path, ws: Path, scale_method: str = "stereo"):
    """A tracks.npz (and the sfm stage's record) in ``ws`` holding the truth geometry's points and views,
    as pipeline.sfm writes them: what an ideal reconstruction would give."""
    from eval.tracks import Tracks
    from pipeline.sfm import SfmConfig, SfmResult

    geo = geometry_from_truth(survey, MeasureConfig(n_points=800))
    n = len(geo.points_world)
    tracks = Tracks(image_names=np.array(geo.frames), registered=np.ones(len(geo.frames), bool),
                    world_from_cam=geo.world_from_cam, K=geo.intrinsics.K, width=geo.intrinsics.width,
                    height=geo.intrinsics.height, point_id=np.arange(n), xyz=geo.points_world,
                    rgb=np.zeros((n, 3), np.uint8), obs_point=geo.obs_point, obs_image=geo.obs_frame.astype(np.int32),
                    obs_xy=geo.obs_px.astype(np.float32))
    workspace = Workspace(ws)
    sfm = workspace.stage_dir("sfm")
    tracks.save(sfm / "tracks.npz")
    workspace.save("sfm", SfmConfig(), SfmResult(
        model_dir=workspace.relative(sfm), tracks=workspace.relative(sfm / "tracks.npz"), n_images=len(geo.frames),
        n_registered=len(geo.frames), n_points=n, mean_track_length=len(geo.obs_point) / n,
        mean_reprojection_error_px=0.0, matching="truth", scale_method=scale_method, scale_factor=1.0,
        scale_spread=0.0, seconds=0.0))
    return geo


def test_tracks_geometry_reads_the_reconstruction(clean, tmp_path):
    ws = tmp_path / "ws"
    Workspace(ws)
    stage_folder(ws, "survey").symlink_to(clean)
    geo = _tracks_from_truth(clean, ws)
    m = measure_target(ws, MeasureConfig(n_points=800))  # auto: the workspace has tracks
    assert m.source == "sfm (scale: stereo)"
    truth = measure_survey(clean, MeasureConfig(n_points=800))  # the same points and views, from truth
    assert m.n_points == truth.n_points and m.n_obs == truth.n_obs
    np.testing.assert_allclose(m.colour, truth.colour, atol=1e-5)  # tracks store pixels as float32
    np.testing.assert_allclose(m.range_m, truth.range_m, atol=1e-6)
    # normals from the neighbouring sparse points (~15 cm apart) against the depth maps' normals
    index = {tuple(p): i for i, p in enumerate(geo.points_world)}
    true_normals = geo.normals_world[[index[tuple(p)] for p in m.points_world]]
    cos = np.clip((m.normals_world * true_normals).sum(1), -1, 1)
    assert np.median(np.degrees(np.arccos(cos))) < 8.0
    # water depth from the navigation depths (10 mm noise) against the site datum
    assert np.abs(m.water_depth_m - (20.0 - m.height_m)).max() < 0.05
    assert measure_target(ws, MeasureConfig(n_points=400), geometry="truth").source == "truth"


def test_fit_recovers_attenuation_when_nothing_is_hidden(clean):
    m = measure_survey(clean, MeasureConfig(n_points=800))
    visible = load_truth(clean).effects["visible"]
    true_eta = np.array(visible[0]["params"]["eta_per_m"])
    start = json.loads(json.dumps(visible))
    start[0]["params"]["eta_per_m"] = [0.3, 0.3, 0.3]
    # a nadir survey at near-constant altitude barely separates attenuation from vignetting and
    # backscatter (range follows image radius), so those are held at their known values here
    config = FitConfig(fixed_effects=("backscatter", "vignetting", "gain"))
    fit = fit_stack(Stack.from_config(start), m, make_split(m, config), config)
    eta = fit.params["attenuation"]["eta_per_m"]
    assert np.abs(np.array(eta["value"]) - true_eta).max() < 0.03, eta
    assert all(0 < s < 0.03 for s in eta["std"]) and fit.params["gain"]["k"]["std"] is None
    low, high = (np.array(b) for b in eta["ci95"])  # the two-way bootstrap's interval (albedos refitted)
    assert ((low <= true_eta) & (true_eta <= high)).all() and (high - low > 2 * 1.96 * np.array(eta["std"])).all(), eta
    assert fit.heldout_rmse < 0.005 and fit.residual.shape == (m.n_obs, 3)


@pytest.mark.parametrize("hidden", [
    pytest.param(name, marks=[pytest.mark.slow, pytest.mark.xfail(strict=True, reason=NOT_IDENTIFIABLE[name])])
    if name in NOT_IDENTIFIABLE else name for name in HIDEABLE])
def test_hidden_effect_is_found(hidden, diagnosed):
    """Hidden at its simulated strength, diagnosed from the visible stack: the hidden effect ranks
    first among all candidates and adding it cuts the held-out error by at least half."""
    result = diagnosed(hidden)
    names = [r["name"] for r in result.ranking]
    where = f"rank {names.index(hidden) + 1}" if hidden in names else f"skipped: {result.skipped.get(hidden)}"
    assert names[0] == hidden, f"{hidden} {where}; {result.verdict}"
    top = result.ranking[0]
    assert top["significant"] and top["change"] <= -0.5, result.verdict
    assert result.best == hidden and result.verdict.startswith(f"missing: {hidden}")


def test_offcentre_vignetting_outputs(diagnosed, surveys):
    result = diagnosed("vignetting_offcentre")
    top = result.ranking[0]
    assert top["flattened"] == "image_position" and result.scores["image_position"] > 5
    assert np.abs(np.array(top["params"]["centre_uv"]["value"]) - [0.61, 0.44]).max() < 0.03
    out = Path(result.out_dir)
    assert out == surveys("vignetting_offcentre") / "diagnose"
    for name in ("measurements.npz", "fit.json", "residuals.json", "residuals.npz", "residual_image_position.png",
                 "residual_range.png", "points_residual.ply", "ranking.json", "verdict.txt", "result.json"):
        assert (out / name).is_file(), name
    assert "forward_scatter" in result.skipped
    records = read_ledger(find_ledger(out.parent))
    assert records[0]["kind"] == "model" and records[0]["geometry"] == "truth"
    assert len(records) == 1 + len(result.ranking)


def test_artificial_light_is_fitted_with_the_declared_rig(diagnosed):
    """The rig (offset, tilt, beam) is known from survey.json and held; power and ambient start off
    their bounds (ambient's initial 0 is a bound the sigmoid cannot leave: the old wrong verdict)."""
    top = diagnosed("artificial_light").ranking[0]
    assert top["name"] == "artificial_light" and top["flattened"] in ("light_distance", "image_position")
    assert not top["params"]["offset_m"]["fitted"] and top["params"]["offset_m"]["value"] == [[0.35, 0.0, 0.0]]
    # the albedos absorb the overall scale, so only power / ambient is identifiable (true 6 / 0.3 = 20)
    ratio = top["params"]["power"]["value"][0] / top["params"]["ambient"]["value"]
    assert 10 < ratio < 40, top["params"]


@pytest.mark.slow
def test_an_undeclared_strobe_is_placed_on_its_side_with_an_interval(tmp_path):
    """A strobe 0.35 m to the right of the camera, its rig not declared in survey.json: added to the model,
    its fitted position and the bootstrap's 95 % interval hold the truth and not the mirrored side
    (measured: x 0.40 in [0.25, 0.55] m, y in [-0.08, 0.07], z in [-0.50, 0.31]; the Laplace std of x, 0.007 m,
    would have excluded the truth)."""
    survey = small_survey(tmp_path / "survey", ["artificial_light"])
    info = json.loads((survey / "survey.json").read_text())
    (survey / "survey.json").write_text(json.dumps({**info, "lights": []}))
    result = run_diagnose(survey, replace(FAST, add=("artificial_light",), candidates=("sensor_response",),
                                          fit=FitConfig(iterations=60)), progress=False)
    offset = json.loads((Path(result.out_dir) / "fit.json").read_text())["params"]["artificial_light"]["offset_m"]
    assert offset["fitted"]
    value, low, high = (np.ravel(x) for x in (offset["value"], *offset["ci95"]))
    truth = np.array([0.35, 0.0, 0.0])
    assert ((low <= truth) & (truth <= high)).all(), offset
    assert low[0] > 0 and value[0] > 0.2, offset  # right of the camera, not left


def test_caustics_pattern_is_found_away_from_its_initial_values(diagnosed):
    params = diagnosed("caustics").ranking[0]["params"]
    assert params["wavelength_m"]["value"] == pytest.approx(0.6, abs=0.01)
    assert params["drift_m_per_frame"]["value"] == pytest.approx(0.05, abs=0.005)


@pytest.mark.slow
def test_marine_snow_leaves_structure_along_spatial_frequency(diagnosed):
    """Not a candidate (random per frame), but its particles leave structure along the spatial-frequency
    axis (score 3.2, amplitude 36% of the RMSE; 1.0-1.4 and 6-9% on the surveys without snow), and no
    candidate is blamed for it."""
    result, clean = diagnosed("marine_snow"), diagnosed()
    assert result.best is None, result.verdict
    size = json.loads((Path(result.out_dir) / "ranking.json").read_text())["base_structure"]["spatial_frequency"]
    assert result.scores["spatial_frequency"] > 2.5 and size > 0.2, (result.scores, size)
    assert clean.scores["spatial_frequency"] < 2.0 and not clean.unexplained_axes, clean.verdict


def test_no_hidden_effect_gives_no_verdict(diagnosed):
    result = diagnosed()
    assert result.best is None
    assert result.verdict.startswith("no significant missing effect"), result.verdict


def test_no_gloss_is_accepted_without_gloss_and_the_angle_axis_is_binned(diagnosed):
    """On the survey with nothing hidden the glossy-surface candidate is fitted (its inputs, the views' points and
    normals, are in the table) and not accepted; the residuals are binned along the incidence angle, without
    structure, and the surfaces seen are the floor."""
    result = diagnosed()
    gloss = next(r for r in result.ranking if r["name"] == "specular_gloss")
    assert not gloss["significant"] and gloss["change"] > -0.03, result.verdict
    assert 0 < result.scores["incidence_angle"] < 3, result.scores
    assert result.surfaces["share"]["floor"] > 0.9 and "surfaces: " in result.verdict


def test_hidden_gloss_is_found_on_the_incidence_angle_axis(diagnosed):
    """A glossy floor (specular_gloss at its simulated strength) ranks first, significant, and flattens the angle axis
    (that it does not cut half: NOT_IDENTIFIABLE)."""
    result = diagnosed("specular_gloss")
    top = result.ranking[0]
    assert top["name"] == "specular_gloss" and top["significant"] and top["change"] < -0.3, result.verdict
    assert top["flattened"] == "incidence_angle" and result.scores["incidence_angle"] > 5, result.scores
    assert result.verdict.startswith("missing: specular_gloss"), result.verdict


def test_two_hidden_effects_are_found_one_per_round(surveys):
    survey = surveys("vignetting_offcentre", "caustics")
    first = run_diagnose(survey, FAST, progress=False)
    assert first.best in ("vignetting_offcentre", "caustics"), first.verdict
    assert first.ranking[0]["change"] <= -0.5
    second = run_diagnose(survey, replace(FAST, add=(first.best,)), progress=False)
    other = ({"vignetting_offcentre", "caustics"} - {first.best}).pop()
    assert first.best in second.stack and second.best == other, second.verdict
    assert second.ranking[0]["change"] <= -0.5 and second.heldout_rmse < 0.6 * first.heldout_rmse
    records = read_ledger(find_ledger(survey))
    models = [r for r in records if r["kind"] == "model"]
    assert len(models) == 2 and models[1]["stack"] == second.stack


#: The documented example of a user's effect (docs/discovery.md's ``my_effect.py``, loaded with ``--plugin``),
#: found by the loop below.
PLUGIN = '''\
# my_effect.py: brightness that changes linearly across the frame
from watergan.formation import Effect, Param, register


def brightness_gradient(direct, pixel_uv, slope):
    """D = J (1 + s_u (u - 1/2) + s_v (v - 1/2)), u and v the pixel position as image fractions."""
    return direct * (1 + (slope.view(1, 2, 1, 1) * (pixel_uv - 0.5)).sum(1, keepdim=True))


@register
class BrightnessGradient(Effect):
    name = "brightness_gradient"
    summary = "brightness changing linearly across the frame (a strobe aimed off-axis, a tilted port)"
    signature = "image position: one side of every frame brighter than the other"
    axis = "image_position"
    rank = 50  # optics, beside vignetting
    params = (Param("slope", (0.3, 0.0), -1.5, 1.5, "", "relative change across the frame (u, v)"),)
    neutral = {"slope": (0.0, 0.0)}

    def forward(self, state):
        slope = self.param("slope", state.direct)
        return state.replace(direct=brightness_gradient(state.direct, state.need("pixel_uv", self.name), slope))
'''


def test_plugin_effect_is_found_from_its_file(tmp_path):
    """A user's effect hidden in the simulation (other values than its initial ones) is found by
    ``watergan --plugin my_effect.py diagnose``."""
    plugin = tmp_path / "my_effect.py"
    plugin.write_text(PLUGIN)
    survey = tmp_path / "survey"
    simulate = textwrap.dedent("""
        import sys
        from eval.diagnose import small_survey_config
        from eval.synth import simulate_survey
        from watergan.formation import load_plugin
        assert load_plugin(sys.argv[1]) == ["brightness_gradient"]
        hidden = [{"name": "brightness_gradient", "params": {"slope": [-0.25, 0.2]}}]
        simulate_survey(sys.argv[2], small_survey_config(hidden), progress=False)
        """)
    subprocess.run([sys.executable, "-c", simulate, str(plugin), str(survey)], check=True, capture_output=True,
                   env={**os.environ, "OMP_NUM_THREADS": "1"})
    out = subprocess.run([sys.executable, "-m", "pipeline.cli", "--plugin", str(plugin), "diagnose", str(survey),
                          "--measure-n-points", "600", "--fit-iterations", "60", "--no-plots"],
                         capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0, out.stderr
    assert "\nmissing: brightness_gradient" in out.stdout, out.stdout
    ranking = json.loads((survey / "diagnose" / "ranking.json").read_text())["candidates"]
    top = ranking[0]
    assert top["name"] == "brightness_gradient" and top["change"] <= -0.5, out.stdout
    np.testing.assert_allclose(top["params"]["slope"]["value"], [-0.25, 0.2], atol=0.03)


def test_the_screen_skips_what_the_albedo_absorbs_and_says_how_to_force_it(clean):
    meas = measure_target(clean, MeasureConfig(n_points=200))
    stack = default_stack(clean, (), None, survey_counts(meas))
    names, skipped = candidate_names(stack, meas)
    assert "ambient_depth" not in names and "--candidates ambient_depth" in skipped["ambient_depth"]
    assert "vignetting_offcentre" in names
    names, skipped = candidate_names(stack, meas, ("ambient_depth", "forward_scatter"))
    assert names == ["ambient_depth"] and "needs_image" in skipped["forward_scatter"]


def docs_plugin(marker: str) -> str:
    """The Python block of docs/discovery.md that contains ``marker``."""
    readme = (Path(__file__).resolve().parents[1] / "docs" / "discovery.md").read_text()
    return next(b for b in re.findall(r"```python\n(.*?)```", readme, flags=re.S) if marker in b)


@pytest.mark.slow
def test_per_frame_plugin_with_neutral_start_is_found(tmp_path):
    """The documented auto-exposure plugin (docs/discovery.md: one log-gain per frame, sized by the survey; initial
    values 0, where it is the identity) hidden in a small survey by its simulation_params (a pattern of 7 repeated
    over the 16 frames) ranks first with the held-out error at least halved."""
    plugin = tmp_path / "frame_exposure.py"
    plugin.write_text(docs_plugin('per="frame"'))
    survey = tmp_path / "survey"
    simulate = textwrap.dedent("""
        import sys
        from eval.diagnose import small_survey_config
        from eval.synth import simulate_survey
        from watergan.formation import load_plugin
        assert load_plugin(sys.argv[1]) == ["frame_exposure"]
        simulate_survey(sys.argv[2], small_survey_config(["frame_exposure"]), progress=False)
        """)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", simulate, str(plugin), str(survey)], check=True, capture_output=True, env=env)
    hidden = json.loads((survey / "truth" / "effects.json").read_text())["hidden"][0]["params"]["log_gain"]
    assert len(hidden) == 16 and hidden[7:14] == hidden[:7] and len(set(hidden)) == 7
    out = subprocess.run([sys.executable, "-m", "pipeline.cli", "--plugin", str(plugin), "diagnose", str(survey),
                          "--measure-n-points", "600", "--fit-iterations", "60", "--no-plots", "--no-progress"],
                         capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    top = json.loads((survey / "diagnose" / "ranking.json").read_text())["candidates"][0]
    assert top["name"] == "frame_exposure" and top["significant"] and top["change"] <= -0.5, out.stdout
    assert top["flattened"] == "frame" and "log_gain (16 values" in out.stdout, out.stdout
    fitted = np.array(top["params"]["log_gain"]["value"])
    offset = np.mean(fitted - hidden)  # a common log-gain is the albedos' scale
    assert np.abs(fitted - offset - hidden).max() < 0.03, (fitted, hidden)


#: A falloff of another shape than vignetting's polynomial (linear in the radius, off-centre): hidden, it has
#: no candidate of its form, so vignetting_offcentre is found in round 1 and leaves structure in round 2.
LINEAR_FALLOFF = '''\
from watergan.formation import RANK_OPTICS, Effect, Param, normalised_radius, register


@register
class LinearFalloff(Effect):
    name = "linear_falloff"
    summary = "darkening linear in the distance from an off-centre point"
    signature = "image position: darkening that grows linearly away from a point"
    axis = "image_position"
    rank = RANK_OPTICS
    params = (Param("centre_uv", (0.62, 0.42), 0.0, 1.0, "image fraction", "falloff centre"),
              Param("slope", 0.6, 0.0, 0.95, "", "relative darkening per unit radius"))
    neutral = {"slope": 0.0}

    def forward(self, state):
        like = state.direct
        f = 1.0 - self.param("slope", like) * normalised_radius(state.pixel_uv, state.image_wh,
                                                                self.param("centre_uv", like))
        return state.replace(direct=state.direct * f, backscatter=state.backscatter * f)
'''


@pytest.mark.slow
def test_a_falloff_of_another_shape_does_not_make_round_2_accept_a_stand_in(tmp_path):
    """Round 1 finds vignetting_offcentre for a hidden linear falloff and calls artificial_light, which
    fits it with a light farther than a rig holds, implausible; round 2 (--add vignetting_offcentre) says
    the added effect's form does not fit and accepts nothing, and no candidate that is not implausible explains
    3 % or more (measured on colours read at one surface footprint, eval.diagnose_measure.same_footprint:
    sensor_response +0.3 %, p 0.56; on the former fixed-pixel patches sensor_response -6 % and caustics -6 % with
    its cell size at its 5 m bound, which the patch's range bias made look like image-position structure)."""
    plugin = tmp_path / "linear_falloff.py"
    plugin.write_text(LINEAR_FALLOFF)
    survey = tmp_path / "survey"
    simulate = textwrap.dedent("""
        import sys
        from eval.diagnose import small_survey_config
        from eval.synth import simulate_survey
        from watergan.formation import load_plugin
        load_plugin(sys.argv[1])
        simulate_survey(sys.argv[2], small_survey_config(["linear_falloff"]), progress=False)
        """)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", simulate, str(plugin), str(survey)], check=True, capture_output=True, env=env)
    first = run_diagnose(survey, FAST, progress=False)
    assert first.best == "vignetting_offcentre", first.verdict
    light = next(r for r in first.ranking if r["name"] == "artificial_light")
    assert light["implausible"] and not light["significant"] and light["change"] < -0.3, first.verdict
    assert "implausible: artificial_light explains" in first.verdict
    second = run_diagnose(survey, replace(FAST, add=("vignetting_offcentre",), plots=True), progress=False)
    assert second.best is None, second.verdict
    assert "the added effect's form does not fit" in second.verdict and "residual_image_position.png" in second.verdict
    assert (Path(second.out_dir) / "residual_image_position.png").is_file()
    assert all(not r["significant"] for r in second.ranking)
    assert all(r["implausible"] for r in second.ranking if r["p"] < 0.05 and r["change"] <= -0.03), second.verdict


def test_why_implausible_names_a_bound_or_the_envelope():
    def fitted(**values):
        return {k: {"value": v, "fitted": True} for k, v in values.items()}

    assert why_implausible("vignetting_offcentre", fitted(centre_uv=[0.6, 0.44], strength=[1.0, 0.0, 0.5])) == ""
    assert "centre_uv = 0.995 image fraction outside [0.02, 0.98]" in why_implausible(
        "vignetting_offcentre", fitted(centre_uv=[0.995, 0.5]))
    assert "wavelength_m = 4.99 m at its bound 5" == why_implausible("caustics", fitted(wavelength_m=4.99))
    assert why_implausible("artificial_light", fitted(ambient=0.0, power=[5.0])) == ""  # off at 0: physical
    held = {"offset_m": {"value": [[2.9, 0.0, 0.0]], "fitted": False}}
    assert why_implausible("artificial_light", held) == ""  # a declared rig is not a fit


def _eval_record(ws: Path) -> None:
    """The eval stage's record as it saves it: the raw frames' and the restorer's colour (the restorer without a
    correct stage: its mode unknown)."""
    from eval.tables import EvaluateConfig, EvaluateResult

    Workspace(ws).save("eval", EvaluateConfig(), EvaluateResult(
        tables_json="", tables_md="", baselines_dir="", methods=["raw", "ours"], skipped={}, range_source="none",
        mean_board_ciede2000={"ours": 4.25},
        consistency_variance={"raw": [3e-4, 2e-4, 1e-4], "ours": [6e-5, 5e-5, 4e-5]}))


def test_add_appends_a_model_version_and_cli_prints_ledger(surveys, tmp_path):
    ws = tmp_path / "ws"
    ws.mkdir()
    stage_folder(ws, "survey").symlink_to(surveys("vignetting_offcentre"))
    _eval_record(ws)
    config = replace(FAST, add=("vignetting_offcentre",), candidates=("sensor_response",))
    result = run_diagnose(ws, config, progress=False)
    assert result.stack[-2:] == ["vignetting_offcentre", "gain"] and result.out_dir == str(stage_folder(ws, "diagnose"))
    assert (stage_folder(ws, "diagnose") / "result.json").is_file()
    # in the stage's folder, named in its result
    assert result.ledger == f"{STAGES['diagnose'].folder}/model_ledger.jsonl"
    records = read_ledger(ws / result.ledger)
    assert [r["kind"] for r in records] == ["model", "candidate"]
    assert records[0]["consistency"] == {"raw": 2e-4, "ours (unknown)": 5e-5}
    assert records[0]["board_ciede2000"] == {"ours (unknown)": 4.25} and "consistency" not in records[1]
    table = ledger_table(records)
    assert "vignetting_offcentre" in table and "4.25" in table and "5.000e-05" in table
    out = subprocess.run([sys.executable, "-m", "pipeline.cli", "ledger", str(ws)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "heldout_rmse" in out.stdout and "ours (unknown)" in out.stdout
    assert (stage_folder(ws, "diagnose") / "ledger.png").is_file() and not (ws / "model_ledger.png").exists()


@pytest.mark.slow
def test_end_to_end_on_sfm_geometry(tmp_path):
    """Simulate -> SfM (pycolmap, altitude scale) -> evaluation of the raw frames -> diagnose on the tracks:
    the hidden effect is found from the reconstruction alone, and the ledger carries the colour."""
    from eval.tables import EvaluateConfig
    from pipeline.sfm import SfmConfig

    ws = Workspace(tmp_path / "ws")
    survey = small_survey(ws.stage_dir("survey"), ["vignetting_offcentre"], width_px=320)
    sfm = ws.run("sfm", SfmConfig())
    assert sfm.n_registered == 16 and sfm.scale_method == "altitude"
    assert survey.is_dir()
    ws.run("eval", EvaluateConfig(methods=("raw",), progress=False))  # raw and the in-air truth, on the board too
    result = run_diagnose(ws.root, replace(FAST, measure=MeasureConfig(n_points=3000)), progress=False)
    assert result.geometry == "sfm (scale: altitude)" and result.n_points > 200
    assert result.best == "vignetting_offcentre", result.verdict
    assert result.ranking[0]["change"] <= -0.5
    record = read_ledger(ws.path(result.ledger))[0]
    assert record["geometry"] == "sfm (scale: altitude)"
    assert record["consistency"]["inair"] < record["consistency"]["raw"] and set(record["board_ciede2000"]) == {
        "raw", "inair"}


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
    with pytest.raises(UserInputError, match="no SfM tracks"):
        measure_survey(clean, MeasureConfig(n_points=400), geometry="sfm")
    with pytest.raises(UserInputError, match="geometry must be one of"):
        measure_survey(clean, geometry="colmap")
    with pytest.raises(UserInputError, match="in a workspace"):  # a survey folder has no water stage
        measure_survey(clean, geometry="water")


# ------------------------------------------------------------ the workspace: the water stage's measurements
@pytest.fixture(scope="module")
def water_ws(surveys, tmp_path_factory):
    """A workspace on the small survey hiding off-centre vignetting: the sfm stage's record holding the truth's
    tracks (:func:`_tracks_from_truth`), the dense stage's the true depth maps, and the range and water stages run
    on them (the water with no bootstrap, 150 samples per frame)."""
    from test_water import water_config

    from eval.water import ALTERNATIVE_PRESETS
    from pipeline.dense import DenseConfig, DenseResult
    from pipeline.range import RangeConfig
    from watergan.io import write_depth_png

    root = tmp_path_factory.mktemp("water-ws") / "ws"
    ws = Workspace(root)
    survey = surveys("vignetting_offcentre")
    stage_folder(root, "survey").symlink_to(survey)
    _tracks_from_truth(survey, root)
    truth = load_truth(survey)
    depth = ws.stage_dir("dense") / "depth"
    for k, name in enumerate(truth.frames):
        write_depth_png(depth / f"{Path(name).stem}.png", truth.depth_m(k))
    ws.save("dense", DenseConfig(), DenseResult(depth_dir=ws.relative(depth), pairs={}, coverage={}, mean_coverage=1.0))
    ws.run("range", RangeConfig(progress=False))
    # the diagnosis reads the water's stack, fields, gains and table, not its intervals: no alternatives
    return ws, ws.run("water", water_config(bootstrap=0, samples_per_frame=150, progress=False,
                                            alternatives=ALTERNATIVE_PRESETS["none"]))


def water_board_rows(ws: Workspace) -> int:
    from eval.observations import Observations

    return len(Observations.load(ws.path(ws.result("water").observations)).board_colour)


def test_the_diagnosis_of_a_workspace_takes_the_water_stages_observations(water_ws):
    from eval.observations import Observations
    from eval.tracks import Tracks

    ws, water = water_ws
    obs = Observations.load(ws.path(water.observations))
    assert water.observations == f"{STAGES['water'].folder}/observations.npz"
    assert len(obs.colour) == water.n_observations
    m = measure_target(ws.root, MeasureConfig(n_points=10 ** 6))  # auto: the water stage's table, all of it
    assert m.source == "water stage (scale: stereo)" and (m.n_obs, m.n_points) == (len(obs.colour), obs.n_points)
    for name in ("colour", "range_m", "depth_m", "pixel_uv", "points_cam", "normals_cam", "point", "frame"):
        np.testing.assert_array_equal(getattr(m, name), getattr(obs, name), err_msg=name)  # the same rows
    # each row's point, in the world, is where its view saw it (the table's world points are the fitted ones)
    poses = Tracks.load(ws.path(ws.result("sfm").tracks)).world_from_cam[m.frame]
    pc = np.einsum("nji,nj->ni", poses[:, :3, :3], m.points_world[m.point] - poses[:, :3, 3])
    np.testing.assert_allclose(pc, m.points_cam, atol=1e-9)
    assert (m.grad_energy > 0).mean() > 0.9 and np.isfinite(m.view_angle_deg).all()
    assert np.abs(m.water_depth_m - (20.0 - m.height_m)).max() < 0.05  # from the navigation depths
    # --measure-n-points bounds the points: every view of each point drawn, the same rows
    few = measure_target(ws.root, MeasureConfig(n_points=100))
    assert few.n_points == 100 and set(map(tuple, few.colour)) <= set(map(tuple, obs.colour))
    assert measure_target(ws.root, MeasureConfig(n_points=100), geometry="sfm").source == "sfm (scale: stereo)"


def test_the_workspace_diagnosis_finds_the_hidden_effect_on_the_water_stages_observations(water_ws):
    """On all of the water's table (colours read at the water's footprint, points seen twice kept) off-centre
    vignetting ranks first and cuts the held-out error by about half."""
    ws, water = water_ws
    result = run_diagnose(ws.root, replace(FAST, measure=MeasureConfig(n_points=10 ** 6)), progress=False)
    assert result.geometry == "water stage (scale: stereo)" and result.n_obs == water.n_observations
    assert result.measurements == (f"water stage (scale: stereo) (04_water/observations.npz): {water.n_observations} "
                                   f"observations of {water.n_points} points; its {water_board_rows(ws)} board rows "
                                   f"not used (known albedo: the diagnosis fits one per point)")
    assert json.loads((ws.folder("diagnose") / "ranking.json").read_text())["measurements"] == result.measurements
    top = result.ranking[0]
    assert result.best == top["name"] == "vignetting_offcentre", result.verdict
    assert top["significant"] and top["change"] <= -0.4, result.verdict


@pytest.mark.slow
def test_add_refits_the_water_and_the_diagnosis_ranks_on_the_refit(water_ws, tmp_path):
    """What `watergan run --add vignetting_offcentre` does to these two stages: the water is refitted with the
    effect on the same table, and the diagnosis starts from that water, on the same rows."""
    import shutil

    from test_water import water_config

    from eval.fit import DEFAULT_EFFECTS as DEFAULT_WATER_EFFECTS
    from eval.water import ALTERNATIVE_PRESETS

    ws, water = water_ws
    copy = tmp_path / "ws"
    shutil.copytree(ws.root, copy, symlinks=True)
    ws = Workspace(copy)
    every = replace(FAST, measure=MeasureConfig(n_points=10 ** 6))  # all of the water's table
    before = run_diagnose(ws.root, every, progress=False)
    added = ws.run("water", water_config(effects=(*DEFAULT_WATER_EFFECTS, "vignetting_offcentre"), bootstrap=0,
                                        samples_per_frame=150, progress=False,
                                        alternatives=ALTERNATIVE_PRESETS["none"]))  # as the workspace's water
    assert added.n_observations == water.n_observations  # the same table, refitted
    after = run_diagnose(ws.root, replace(every, add=("vignetting_offcentre",)), progress=False)
    assert "vignetting_offcentre" in after.stack and after.n_obs == before.n_obs == water.n_observations
    assert after.heldout_rmse < 0.6 * before.heldout_rmse and after.best is None, after.verdict
    assert [r["kind"] for r in read_ledger(ws.path(after.ledger))].count("model") == 2


def test_a_candidate_of_another_form_than_the_fields_is_not_accepted():
    """The water's fields over the image say which form is missing: an off-centre falloff is multiplicative, so it
    cannot explain additive fields (a veil fixed in the image), and is accepted against multiplicative ones."""
    from watergan.formation import FormationState, get, pixel_grid

    state = FormationState(direct=torch.ones(1, 3, 8, 8, dtype=torch.float64),
                           range_m=torch.full((1, 1, 8, 8), 2.0, dtype=torch.float64),
                           depth_m=torch.full((1, 1, 8, 8), 2.0, dtype=torch.float64),
                           pixel_uv=pixel_grid(8, 8, 1, torch.float64), image_wh=(8, 8))
    base = [{"name": "attenuation"}, {"name": "backscatter"}, {"name": "vignetting"}, {"name": "gain"}]
    falloff = {"name": "vignetting_offcentre", "params": get("vignetting_offcentre").simulation_params}
    veil = {"name": "image_field", "params": {"additive": [[0.01] * 5] * 3}}
    assert effect_form(Stack.ordered([*base, falloff]), "vignetting_offcentre", state) == "multiplicative"
    assert effect_form(Stack.ordered([*base, veil]), "image_field", state) == "additive"
    assert effect_form(Stack.ordered(base), "backscatter", state) == "additive"
    assert effect_form(Stack.ordered(base), "attenuation", state) == "neither"  # the same at every view here
    additive = {"form": "additive", "multiplicative_pct": [0.4, 0.3, 0.2], "additive_pct": [3.0, 4.5, 6.1]}
    reason = form_conflict("vignetting_offcentre", "multiplicative", additive)
    assert "multiplicative while the water's fields over the image carry additive" in reason and "6.1 %" in reason
    assert form_conflict("vignetting_offcentre", "multiplicative", {**additive, "form": "multiplicative"}) == ""
    assert form_conflict("vignetting_offcentre", "multiplicative", None) == ""
    assert form_conflict("artificial_light", "both", additive) == ""  # a form that has the fields' part
    assert "multiplicative while" in form_conflict("artificial_light", "multiplicative", additive)


def test_the_verdict_reads_the_water_gains_per_frame():
    """The water's gains per frame (water.json's ``frames``) are the frame axis's measurement: the verdict says
    whether something changes from frame to frame and by how much."""
    flat = {"largest_pct": [1.2, 0.8, 2.0], "sd_pct": [0.5, 0.4, 0.9], "flat": True}
    varying = {"largest_pct": [21.0, 19.5, 20.2], "sd_pct": [11.0, 10.1, 10.6], "flat": False}
    assert verdict_text([], [], {}, frames=flat).splitlines()[-1].startswith("frames: the water's gains per frame "
                                                                             "are flat (up to 2 %)")
    line = verdict_text([], [], {}, frames=varying).splitlines()[-1]
    assert "up to 21 %" in line and "changes from frame to frame" in line
    assert verdict_text([], [], {}) == "no significant missing effect"


def test_the_verdict_names_the_axis_when_no_library_form_reproduces_the_fields():
    """When the water's fields over the image carry structure and the image-position candidate that cuts the
    held-out error is not accepted for them, the headline names the axis and a form not in the library, not "no
    significant missing effect"; flat fields, or an accepted candidate, keep their headlines."""
    from eval.diagnose import CandidateResult

    fields = {"form": "multiplicative", "multiplicative_pct": [20.0, 31.0, 25.0], "additive_pct": [1.0, 2.0, 1.5]}
    turned = CandidateResult(name="vignetting_offcentre", heldout_rmse=0.01, change=-0.5, ci95=(-0.6, -0.4), p=0.0,
                             significant=False, flattened="image_position", flattened_drop=1.0, params={}, scores={},
                             structure={}, seconds=0.0, implausible="it flattens too little of them",
                             fields_explained=0.6)
    headline = verdict_text([turned], [], {}, fields=fields).splitlines()[0]
    assert headline.startswith("missing: structure on image position of a form not in the library"), headline
    assert "vignetting_offcentre" in headline and "by 50%" in headline and "60% of them" in headline
    assert "multiplicative up to 31 %" in headline
    flat = verdict_text([turned], [], {}, fields={**fields, "form": "flat"})
    assert flat.startswith("no significant missing effect (best candidate vignetting_offcentre"), flat
    accepted = replace(turned, significant=True, implausible="")
    assert verdict_text([accepted], [], {}, fields=fields).startswith("missing: vignetting_offcentre —")
    assert verdict_text([replace(turned, p=0.2)], [], {}, fields=fields).startswith("no significant missing effect")


def test_a_candidate_says_how_much_of_the_water_fields_it_reproduces():
    """What a candidate's fit changes at the views, against the fit without it, is compared with the water's fields
    over the image: the fields themselves reproduce all of them; an off-centre falloff reproduces most of a
    multiplicative field fitted to it and none of an additive veil."""
    from eval.diagnose import fields_explained, water_field
    from watergan.formation import FormationState, get, pixel_grid

    state = FormationState(direct=torch.ones(64, 3, 1, 1, dtype=torch.float64),
                           range_m=torch.full((64, 1, 1, 1), 2.0, dtype=torch.float64),
                           depth_m=torch.full((64, 1, 1, 1), 2.0, dtype=torch.float64),
                           pixel_uv=pixel_grid(8, 8, 1, torch.float64).permute(0, 2, 3, 1).reshape(64, 2, 1, 1),
                           image_wh=(8, 8))
    base = [{"name": "attenuation"}, {"name": "backscatter"}, {"name": "vignetting"}, {"name": "gain"}]
    veil = {"name": "image_field", "params": {"additive": [[0.01, -0.02, 0.0, 0.01, 0.0]] * 3}}
    without = Stack.ordered(base)
    assert fields_explained(Stack.ordered([*base, veil]), without, water_field([veil]), state) > 0.999
    falloff = {"name": "vignetting_offcentre", "params": get("vignetting_offcentre").simulation_params}
    with_falloff = Stack.ordered([*base, falloff])
    assert fields_explained(with_falloff, without, water_field([veil]), state) == 0.0
    # a multiplicative field of degree 2 fitted (least squares) to the falloff's log at the views
    from watergan.formation.effects.image_field import field_basis
    from watergan.formation.inverse import affine_images

    with torch.no_grad():
        log_ratio = torch.log(affine_images(with_falloff, state)[0] / affine_images(without, state)[0])[:, :, 0, 0]
    basis = field_basis(state.pixel_uv, 2)[:, :, 0, 0]
    centred = log_ratio - log_ratio.mean(0)
    coefficients = torch.linalg.lstsq(basis - basis.mean(0), centred).solution.T
    fitted = {"name": "image_field", "params": {"multiplicative": coefficients.tolist()}}
    share = fields_explained(with_falloff, without, water_field([fitted]), state)
    assert 0.8 < share < 1.0


def test_image_position_candidates_rank_by_how_much_of_the_fields_they_flatten():
    """Among their own places in the ranking (held-out change), the candidates that reproduce the water's fields over
    the image come most-reproduced first; the others keep their places."""
    from eval.diagnose import CandidateResult, order_by_fields

    def candidate(name: str, change: float, share: float | None) -> CandidateResult:
        return CandidateResult(name=name, heldout_rmse=0.01, change=change, ci95=(change - 0.01, change + 0.01),
                               p=0.0, significant=True, flattened="image_position", flattened_drop=1.0, params={},
                               scores={}, structure={}, seconds=0.0, fields_explained=share)

    ranked = [candidate("wide_falloff", -0.40, 0.55), candidate("frame_thing", -0.30, None),
              candidate("right_falloff", -0.20, 0.93), candidate("other", -0.10, None),
              candidate("tie_b", -0.05, 0.55)]
    ordered = order_by_fields(ranked)
    assert [r.name for r in ordered] == ["right_falloff", "frame_thing", "wide_falloff", "other", "tie_b"]
    assert order_by_fields([]) == []


def test_the_grouped_jacobian_is_scipys_forward_differences(clean):
    """The bootstrap's least squares moves a per-channel parameter's three channels together (the residuals of one
    channel depend on that channel's entries alone): the Jacobian equals scipy's one-entry-at-a-time forward
    differences, for fewer residual evaluations; with the fields over the image in the stack, their penalty rows
    (which need no render) are differenced an entry at a time."""
    from scipy.optimize._numdiff import approx_derivative

    from eval.diagnose import DEFAULT_EFFECTS
    from eval.fit import Problem, fitted_names
    from eval.solvers import grouped_jacobian

    meas = measure_survey(clean, MeasureConfig(n_points=150))
    q = np.array([0.3, -0.2, 0.5, 0.1, 0.4])
    field = {"name": "image_field", "params": {"orthogonal_to": (q / np.linalg.norm(q)).tolist()}}
    for effects in ([{"name": n} for n in DEFAULT_EFFECTS], [*({"name": n} for n in DEFAULT_EFFECTS), field]):
        stack = Stack.ordered(effects).to(torch.float64)
        problem = Problem(stack, meas, FitConfig(), fitted_names(stack, ("gain",), {}))
        groups, channel = problem.channel_groups()
        x = problem.flat().numpy() + 0.05  # off the effects' start values

        def fun(v: np.ndarray, problem=problem) -> np.ndarray:
            problem.set_flat(torch.from_numpy(v))
            with torch.no_grad():
                return problem.residuals().numpy()

        def penalty(v: np.ndarray, problem=problem) -> np.ndarray:
            problem.set_flat(torch.from_numpy(v))
            return problem.penalty().detach().numpy()

        f0 = fun(x)
        grouped = grouped_jacobian(fun, x, f0, [(g, channel[g]) for g in groups], penalty)
        scipy_jacobian = approx_derivative(fun, x, method="2-point", f0=f0)
        assert len(groups) <= len(x) / 2 and np.abs(scipy_jacobian).max() > 0
        assert len(problem.penalty()) == (2 * 3 * 5 if effects[-1] is field else 0)  # F and G, 3 channels, 5 terms
        np.testing.assert_allclose(grouped, scipy_jacobian, rtol=0, atol=1e-12 * np.abs(scipy_jacobian).max())
