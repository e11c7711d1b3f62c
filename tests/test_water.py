"""eval.water: the site-water estimator recovers the parameters it rendered with, and the physics correction
inverts a rendered image exactly.

The survey is made here: a flat seafloor with a smooth albedo (and a colour board of known patches), seen
straight down from 12 frames at altitudes 1.8-3.2 m, rendered with the effect library at known parameters."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eval.colour import Board
from eval.fit import DEFAULT_EFFECTS as DEFAULT_WATER_EFFECTS
from eval.fit import FitConfig
from eval.observations import DenseMeasureConfig, SparseTracks, WaterFrame, WaterInputError, measure_frames
from eval.water import ALTERNATIVE_PRESETS, build_stack, estimate_water
from pipeline.stages import STAGES
from pipeline.water import WaterStage
from watergan.formation import FormationState, Stack, pixel_grid
from watergan.formation.inverse import correct_physics, inverse_fields
from watergan.water_record import read_water

W, H, F = 96, 72, 60.0
K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
TRUE = [
    {"name": "attenuation", "params": {"eta_per_m": [0.45, 0.14, 0.2]}},
    {"name": "backscatter", "params": {"b_inf": [0.03, 0.16, 0.19], "beta_per_m": [0.45, 0.32, 0.32]}},
    {"name": "vignetting", "params": {"a_margin": 0.35, "b": 0.0, "c": 0.05}},
    {"name": "gain", "params": {"k": [1.5, 1.5, 1.5]}},
]
BOARD_ORIGIN, PATCH = np.array([-0.75, -0.5]), 0.25  # board: 6 x 4 patches of 0.25 m from this corner (world x, y)
#: Colours are read at a 6 cm footprint (1.1-2 px here): every view of a point then averages the same patch of
#: the seafloor. A footprint below the 1 px blur gives far views more blur than near ones, which biases eta by
#: several % on the board's sharp patch edges.
FOOTPRINT_M = 0.06
BOARD_RGB = np.random.default_rng(3).uniform(0.03, 0.9, (24, 3))


def water_config(base: WaterStage | None = None, **flat) -> WaterStage:
    """``base`` (default: the water stage's own configuration with the "fast" set of alternatives and without the
    fine grid after the water: the fine fields fitted with the water and eta's profile are five fits more in every
    estimate, the file's largest cost, and the grid serves the corrections alone; the tests that check them ask for
    them) changed by flat field names: those of the measurement (:class:`DenseMeasureConfig`) and of the fit
    (:class:`FitConfig`) go to its nested configurations."""
    from dataclasses import fields, replace

    base = base or WaterStage(correction_grid=None, alternatives=ALTERNATIVE_PRESETS["fast"])
    nested = {}
    for name, cls in (("measure", DenseMeasureConfig), ("fit", FitConfig)):
        own = {k: flat.pop(k) for k in [f.name for f in fields(cls)] if k in flat}
        nested[name] = replace(getattr(base, name), **own)
    return replace(base, **flat, **nested)



def albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth in-air colour (..., 3) of the seafloor, 0.02-0.75, with the board's patches at the origin."""
    out = np.stack([0.38 + 0.3 * np.sin(2.1 * x + 0.3) * np.cos(1.7 * y) + 0.05 * np.sin(5 * x - 3 * y + c)
                    for c in (0.0, 1.3, 2.6)], -1)
    i = np.floor((x - BOARD_ORIGIN[0]) / PATCH).astype(int)
    j = np.floor((y - BOARD_ORIGIN[1]) / PATCH).astype(int)
    on = (i >= 0) & (i < 6) & (j >= 0) & (j < 4)
    out[on] = BOARD_RGB[(j * 6 + i)[on]]
    return out


def pose(cx: float, cy: float, altitude: float) -> np.ndarray:
    """A camera looking straight down (camera x = world x, camera y = world -y)."""
    m = np.eye(4)
    m[:3, :3] = np.diag([1.0, -1.0, -1.0])
    m[:3, 3] = [cx, cy, altitude]
    return m


def render(world_from_cam: np.ndarray, stack: Stack,
           frame_index: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(raw linear image, range, in-air J) of the flat seafloor z = 0 (its normal faces straight up: in the frame
    of a camera looking straight down, (0, 0, -1)), as survey frame ``frame_index``."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(xs - K[0, 2]) / F, (ys - K[1, 2]) / F, np.ones_like(xs)], -1) @ world_from_cam[:3, :3].T
    t = -world_from_cam[2, 3] / rays[..., 2]
    points = world_from_cam[:3, 3] + t[..., None] * rays
    rng = np.linalg.norm(points - world_from_cam[:3, 3], axis=-1)
    j = albedo(points[..., 0], points[..., 1])
    pc = (points - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]
    normals = np.broadcast_to(np.array([0.0, 0.0, 1.0]) @ world_from_cam[:3, :3], pc.shape)
    state = FormationState(direct=torch.from_numpy(j.transpose(2, 0, 1)[None].copy()),
                           range_m=torch.from_numpy(rng[None, None].copy()),
                           pixel_uv=pixel_grid(H, W, 1, torch.float64), image_wh=(W, H),
                           depth_m=torch.from_numpy(pc[..., 2][None, None].copy()),
                           points_cam=torch.from_numpy(pc.transpose(2, 0, 1)[None].copy()),
                           normals_cam=torch.from_numpy(normals.transpose(2, 0, 1)[None].copy()),
                           frame_index=torch.tensor([frame_index]))
    with torch.no_grad():
        image = stack.to(torch.float64).render(state)[0].permute(1, 2, 0).numpy()
    return image, rng, j


def board_quads(world_from_cam: np.ndarray) -> np.ndarray:
    quads = np.full((24, 4, 2), np.nan)
    for p in range(24):
        i, j = p % 6, p // 6
        x0, y0 = BOARD_ORIGIN + PATCH * np.array([i, j])
        corners = np.array([[x0, y0, 0], [x0 + PATCH, y0, 0], [x0 + PATCH, y0 + PATCH, 0], [x0, y0 + PATCH, 0]])
        pc = (corners - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]
        uv = np.stack([F * pc[:, 0] / pc[:, 2] + K[0, 2], F * pc[:, 1] / pc[:, 2] + K[1, 2]], -1)
        if (uv >= 2).all() and (uv[:, 0] <= W - 3).all() and (uv[:, 1] <= H - 3).all():
            quads[p] = uv
    return quads


def make_survey(truth: list[dict] = TRUE):
    stack = Stack.from_config(truth)
    rng = np.random.default_rng(0)
    frames, quads = [], {}
    for k, (cx, cy) in enumerate([(x, y) for y in (-0.5, 0.0, 0.5) for x in (-0.9, -0.3, 0.3, 0.9)]):
        m = pose(cx, cy, 1.8 + 1.4 * ((k * 5) % 12) / 11)
        image, r, _ = render(m, stack)
        image = np.clip(image + rng.normal(0, 0.002, image.shape), 0, 1).astype(np.float32)
        name = f"{k:06d}.png"
        frames.append(WaterFrame(name=name, image=image, range_m=r.astype(np.float32), world_from_cam=m))
        quads[name] = board_quads(m)
    board = Board(names=[f"p{i}" for i in range(24)], true_linear_rgb=BOARD_RGB, quads=quads)
    return frames, board


@pytest.fixture(scope="module")
def survey():
    return make_survey()


def falloff_error(fitted: Stack, truth: Stack) -> np.ndarray:
    """(3,H,W) |A_fitted / A_truth - 1| of the direct signal's gain A at 2 m over the image, each normalised at the
    image centre (the gain's level is the board's business)."""
    flat_m = np.full((H, W), 2.0)
    ratio = inverse_fields(flat_m, fitted, K)[0][0].numpy() / inverse_fields(flat_m, truth, K)[0][0].numpy()
    return np.abs(ratio / ratio[:, H // 2, W // 2][:, None, None] - 1)


def _value(estimate, key):
    return np.asarray(estimate.params[key].value, float)


def test_estimate_recovers_the_rendered_water(survey):
    frames, board = survey
    config = water_config(samples_per_frame=250, margin_px=4, footprint_m=FOOTPRINT_M)
    est = estimate_water(frames, K, board=board, config=config)
    assert est.stack.names == ["attenuation", "backscatter", "vignetting", "image_field", "gain", "frame_gain"]
    assert est.n_board > 20 and est.n_frames == 12
    np.testing.assert_allclose(_value(est, "attenuation.eta_per_m"), [0.45, 0.14, 0.2], rtol=0.05)
    np.testing.assert_allclose(_value(est, "backscatter.b_inf"), [0.03, 0.16, 0.19], rtol=0.15)
    np.testing.assert_allclose(_value(est, "gain.k"), [1.5] * 3, rtol=0.03)
    # the falloff over the image (the vignetting's coefficients trade among themselves and with the fields)
    assert falloff_error(est.stack, Stack.from_config(TRUE)).max() < 0.02
    eta = est.params["attenuation.eta_per_m"]
    assert all(lo <= v <= hi for lo, v, hi in zip(eta.low, eta.value, eta.high, strict=True))
    assert all(h > lo for lo, h in zip(eta.low, eta.high, strict=True))
    # the coarse start's trust region takes red B_inf along its valley with beta to the floor: the intervals cover
    # the truth (measured without it, coarse_refine_evaluations=0: red B_inf +7 % and beta -13 %, both missed)
    assert est.converged
    for key, truth in (("backscatter.b_inf", [0.03, 0.16, 0.19]), ("backscatter.beta_per_m", [0.45, 0.32, 0.32])):
        p = est.params[key]
        assert all(lo <= t <= hi for lo, t, hi in zip(p.low, truth, p.high, strict=True)), (key, p)
    assert set(est.fixed) == {"frame_gain"} and not est.frames["carried"]  # the frames differ by nothing
    assert "eta" in est.summary()


def test_without_a_board_the_gain_is_held_and_said(survey):
    frames, _ = survey
    config = water_config(samples_per_frame=150, bootstrap=0, margin_px=4, iterations=80, footprint_m=FOOTPRINT_M,
                         initial=({"name": "gain", "params": {"k": [1.5, 1.5, 1.5]}},),
                         alternatives=ALTERNATIVE_PRESETS["none"])  # the gain held and eta's value: no intervals
    est = estimate_water(frames, K, config=config)
    assert "gain" in est.fixed and not est.params["gain.k"].fitted
    np.testing.assert_allclose(_value(est, "attenuation.eta_per_m"), [0.45, 0.14, 0.2], rtol=0.05)


def test_tracks_add_points(survey):
    frames, board = survey
    # two world points seen by every frame that sees them, at their true projections
    xyz = np.array([[0.2, 0.1, 0.0], [-0.5, 0.3, 0.0]])
    obs_point, obs_frame, obs_xy = [], [], []
    for k, f in enumerate(frames):
        pc = (xyz - f.world_from_cam[:3, 3]) @ f.world_from_cam[:3, :3]
        uv = np.stack([F * pc[:, 0] / pc[:, 2] + K[0, 2], F * pc[:, 1] / pc[:, 2] + K[1, 2]], -1)
        for p in np.flatnonzero((uv[:, 0] > 8) & (uv[:, 0] < W - 9) & (uv[:, 1] > 8) & (uv[:, 1] < H - 9)):
            obs_point.append(p)
            obs_frame.append(k)
            obs_xy.append(uv[p])
    tracks = SparseTracks(xyz=xyz, obs_point=np.array(obs_point), obs_frame=np.array(obs_frame),
                          obs_xy=np.array(obs_xy))

    config = water_config(samples_per_frame=50, margin_px=4)
    with_tracks = measure_frames(frames, K, tracks, board, config.measure)
    without = measure_frames(frames, K, None, board, config.measure)
    assert with_tracks.n_points == without.n_points + 2


def test_correct_physics_inverts_the_stack_exactly(survey):
    frames, _ = survey
    stack = Stack.from_config(TRUE)
    image, r, j = render(pose(0.1, -0.2, 2.6), stack)
    r = r.copy()
    r[:5, :7] = np.nan
    r[10, 10] = 0.0
    corrected, valid = correct_physics(image, r, stack, K)
    assert corrected.dtype == np.float32 and valid.shape == (H, W)
    assert not valid[:5, :7].any() and not valid[10, 10] and valid.sum() == H * W - 36
    assert np.isnan(corrected[~valid]).all()
    np.testing.assert_allclose(corrected[valid], j[valid], atol=1e-5)
    # the configuration form gives the same
    again, _ = correct_physics(image, r, TRUE)
    np.testing.assert_allclose(again[valid], corrected[valid], atol=1e-6)


def test_the_fields_inverse_with_a_gain_per_frame_matches_the_exact_one(survey):
    """The correct stage's inverse (one table of fields for the effects without a value per frame; each frame's image
    first freed of its gain by the affine map measured on a probe) is the exact inverse of a stack with
    ``frame_gain`` within 5e-4 of the in-air colour (an eighth of an 8-bit level: the table's interpolation; a gain
    left in place would be off by up to 20 %); the probe refuses a difference that varies over the image."""
    from pipeline.correct_physics import invert_with_fields
    from watergan.formation.inverse import frame_affines
    from watergan.nets.restorer import WaterFields

    gains = [[0.1, -0.05, 0.02], [-0.2, 0.15, 0.0], [0.0, 0.0, 0.0]]
    full = Stack.from_config([*TRUE, {"name": "frame_gain", "params": {"log_gain": gains,
                                                                        "orthogonal_to": [[0.0, 0.0]] * 3}}])
    base = Stack.from_config(TRUE)
    fields = WaterFields(TRUE)
    affines = frame_affines(full, base, [2, 0, 1], K, H, W)  # every frame in one batch, in any order
    for k, (s, t) in zip([2, 0, 1], affines, strict=True):
        image, r, j = render(pose(0.1 * k, -0.2, 2.2 + 0.4 * k), full, frame_index=k)
        np.testing.assert_allclose(s, np.exp(gains[k]), rtol=1e-9)
        np.testing.assert_allclose(t, 0.0, atol=1e-12)
        corrected, valid = invert_with_fields((image - t) / s, r, fields, K)
        assert valid.all() and np.abs(corrected - j).max() < 5e-4
    no_falloff = Stack.from_config([e for e in TRUE if e["name"] != "vignetting"])
    assert frame_affines(base, no_falloff, [0], K, H, W) == [None]  # a falloff is no gain of the whole frame


def test_too_little_input_is_refused_with_what_to_give(survey):
    frames, _ = survey
    no_pose = [WaterFrame(f.name, f.image, f.range_m, None) for f in frames[:10]] + frames[10:]
    with pytest.raises(WaterInputError, match="stereo frames"):
        estimate_water(no_pose, K, config=water_config(bootstrap=0))
    sparse_range = [WaterFrame(f.name, f.image, np.where(np.random.default_rng(0).random(f.range_m.shape) < 0.05,
                                                         f.range_m, np.nan), f.world_from_cam) for f in frames]
    with pytest.raises(WaterInputError, match="dense range covers"):
        estimate_water(sparse_range, K, config=water_config(bootstrap=0))


# ------------------------------------------------------------------------------- the pipeline's stage
@pytest.fixture(scope="module")
def water_workspace():
    """The session's small simulated stereo survey (tests/test_sfm.py: 10 frames of 320x240, real pycolmap SfM)
    with the dense, range and water stages run on it."""
    from test_sfm import survey_and_sfm

    from pipeline.dense import DenseConfig
    from pipeline.range import RangeConfig

    survey, ws, _ = survey_and_sfm()
    ws.run("dense", DenseConfig(progress=False))
    ws.run("range", RangeConfig(progress=False))
    return survey, ws, ws.run("water", water_config(bootstrap=8, progress=False))


def test_the_water_stage_estimates_and_corrects_from_the_workspace(water_workspace, capsys):
    """The water stage estimates the water; `watergan correct --workspace WS` (the correct stage, here without a
    restorer) inverts the estimate with the range stage's maps into its physics/ folder."""
    import argparse
    import json

    import cv2

    from pipeline.cli_restorer import add_commands

    survey, ws, result = water_workspace
    water = read_water(ws.path(result.water_json))
    truth = {f"{e['name']}.{k}": v for e in json.loads((survey / "truth" / "effects.json").read_text())["full"]
             for k, v in e["params"].items()}
    for key in ("attenuation.eta_per_m", "backscatter.b_inf"):
        p = water.params[key]
        assert all(lo < v < hi for lo, v, hi in zip(p.low, p.value, p.high, strict=True)), key
        # 10 frames of 320x240 at one altitude, with the fields over the image: measured 8-23 % off for eta and 26-32 %
        # for red B_inf over runs (along its valley with beta, which this survey's range span hardly pins; SfM's points
        # differ from run to run; the demo: <= 2 % and 15 %); WaterGAN's eta was 43 % off in green on the demo. What
        # the survey pins is the veil, checked below.
        rtol = np.array([0.4, 0.3, 0.3] if key == "backscatter.b_inf" else [0.3, 0.3, 0.3])
        assert (np.abs(np.array(p.value) / truth[key] - 1) <= rtol).all(), (key, p.value, truth[key])
    veil = water.veil  # what the survey pins of the backscatter: the veil at its median range, within 10 %
    true_veil = np.array(truth["backscatter.b_inf"]) * -np.expm1(-np.array(truth["backscatter.beta_per_m"])
                                                                   * veil["range_m"])
    np.testing.assert_allclose(veil["value"], true_veil, rtol=0.15)
    ranges = ws.result("range")
    assert result.board and result.summary.startswith("water: eta_per_m") and ranges.range_missing < 0.2
    assert result.at_bounds == []  # nothing hidden: the stack fits
    from eval.observations import Observations  # the table the estimate was fitted to, for the diagnosis

    obs = Observations.load(ws.path(result.observations))
    assert len(obs.colour) == result.n_observations == water.n_observations and obs.n_points == water.n_points
    assert obs.points_world.shape == obs.normals_world.shape == (obs.n_points, 3) and obs.normals_cam is not None
    names = sorted(p.name for p in (survey / "images").iterdir())
    assert sorted(p.name for p in ws.path(ranges.range_dir).iterdir()) == names  # the range maps: the range stage's
    assert (ws.path(result.water_json).parent / "residuals.png").stat().st_size > 0 and "residuals.png" in water.plots

    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(dest="command", required=True), [])
    args = parser.parse_args(["correct", "--workspace", str(ws.root), "--no-progress"])
    assert args.func(args) == 0
    correct = ws.result("correct")
    assert f"physics: {ws.path(correct.physics_images)}" in capsys.readouterr().out
    assert correct.physics == f"{STAGES['correct'].folder}/physics" and correct.restorer == "" and correct.mode == ""
    assert correct.mesh_images == correct.physics_images  # no restorer: the physics correction
    # no range: ranged from the neighbours or at the far limit
    assert ranges.range_missing == pytest.approx(correct.filled_fraction + correct.far_fraction, abs=1e-6)
    assert correct.far_fraction < 0.2
    assert sorted(p.name for p in ws.path(correct.physics_images).iterdir()) == names
    frame = cv2.imread(str(ws.path(correct.physics_images) / names[0]), cv2.IMREAD_UNCHANGED)
    mask = cv2.imread(str(ws.path(correct.physics_mask) / names[0]), cv2.IMREAD_UNCHANGED)
    assert frame.dtype == np.uint8 and frame.shape[:2] == mask.shape  # the input's bit depth
    assert set(np.unique(mask)) <= {0, 255}  # no range: masked, and corrected (black only as the scene's dark specks)
    assert np.mean(frame[mask == 0].max(axis=1) == 0) < 0.01 and (mask == 0).any()


def test_the_evaluation_measures_the_physics_correction(water_workspace):
    from eval.tables import EvaluateConfig

    _, ws, _ = water_workspace
    from pipeline.correct import CorrectStage

    ws.run("correct", CorrectStage(progress=False))  # done by the test above (the same configuration) when it ran
    result = ws.run("eval", EvaluateConfig(methods=("raw", "oracle"), range_source="truth", progress=False))
    assert "physics" in result.methods
    assert result.mean_board_distance["physics"] < 0.5 * result.mean_board_distance["raw"]


def test_the_veils_interval_holds_its_bootstrap_spread_and_the_specification_change():
    """The veil at the median range: B_inf (1 - exp(-beta r)); its interval's half width is the bootstrap's 1.96 sd
    and the largest change under the specification alternatives in quadrature (as every parameter's)."""
    from eval.water.intervals import veil_at_median_range

    stack = Stack.from_config(TRUE)
    b_inf, beta, r = np.array(TRUE[1]["params"]["b_inf"]), np.array(TRUE[1]["params"]["beta_per_m"]), 3.0
    veil = b_inf * -np.expm1(-beta * r)
    rng = np.random.default_rng(0)
    samples = [{"backscatter.b_inf": b_inf * (1 + 0.01 * rng.normal(size=3)), "backscatter.beta_per_m": beta}
               for _ in range(30)]
    spread = 1.96 * np.std([s["backscatter.b_inf"] * -np.expm1(-beta * r) for s in samples], 0, ddof=1)
    alone = veil_at_median_range(stack, samples, r)
    np.testing.assert_allclose(alone["value"], veil, rtol=1e-5)
    np.testing.assert_allclose(np.array(alone["high"]) - veil, spread, rtol=1e-3, atol=2e-6)
    shifted = [{"backscatter.b_inf": b_inf * 1.05, "backscatter.beta_per_m": beta},
               {"backscatter.b_inf": b_inf, "backscatter.beta_per_m": beta * 0.9}]
    change = np.maximum(0.05 * veil, np.abs(b_inf * -np.expm1(-0.9 * beta * r) - veil))
    wider = veil_at_median_range(stack, samples, r, tuple(shifted))
    np.testing.assert_allclose(np.array(wider["high"]) - veil, np.hypot(spread, change), rtol=1e-3, atol=2e-6)
    # a structure alternative 20 % higher: the interval reaches its veil plus the bootstrap's spread
    other = {"backscatter.b_inf": b_inf * 1.2, "backscatter.beta_per_m": beta}
    covered = veil_at_median_range(stack, samples, r, tuple(shifted), structures=(other,))
    np.testing.assert_allclose(covered["high"], 1.2 * veil + spread, rtol=1e-3, atol=2e-6)
    np.testing.assert_allclose(covered["low"], wider["low"], rtol=1e-6)


def _alternative_fit(alternative, values=None, profile=None):
    from eval.water.alternatives import AlternativeFit

    return AlternativeFit(alternative, {k: np.asarray(v, float) for k, v in (values or {}).items()}, profile=profile)


def _eta_interval(stack, results, std=0.01, range_scale_sd=0.0):
    """combine() on a stack at TRUE's eta with 30 replicates of spread ``std`` about it, and ``results``."""
    from eval.water.intervals import combine

    eta = np.array([0.45, 0.14, 0.2])
    rng = np.random.default_rng(0)
    draws = rng.normal(size=(30, 3))
    draws = (draws - draws.mean(0)) / draws.std(0, ddof=1)
    samples = [{"attenuation.eta_per_m": eta + std * d} for d in draws]
    params, _, _ = combine(stack, {"attenuation.eta_per_m": eta}, samples, results, range_scale_sd, 2.0)
    return params["attenuation.eta_per_m"]


def test_one_rule_widens_the_interval_by_each_alternatives_rule_and_names_it():
    """combine(): a "quadrature" alternative's change adds in quadrature to the bootstrap's 1.96 sd; a "cover" one's
    estimate outside the interval is reached plus the bootstrap's 1.96 sd (and the range scale's term for 1/m) on
    its side, the other side kept, inside the parameter's bounds; a "bounds" one's accepted span is covered; each
    alternative leaves a row saying where it widened the interval."""
    from eval.water.alternatives import BoardWeight, FineFields, Profile

    stack = Stack.from_config(TRUE)
    eta = np.array([0.45, 0.14, 0.2])
    alone = _eta_interval(stack, [])
    np.testing.assert_allclose(np.array(alone.high) - eta, 1.96 * 0.01, atol=2e-6)
    assert alone.widenings == []
    weighted = _eta_interval(stack, [_alternative_fit(BoardWeight(), {"attenuation.eta_per_m": eta + 0.03})])
    np.testing.assert_allclose(np.array(weighted.high) - eta, np.hypot(1.96 * 0.01, 0.03), atol=2e-6)
    (row,) = weighted.widenings
    assert (row.alternative, row.rule, row.widened) == ("board_weight", "quadrature", [True] * 3)

    other = np.array([0.3, 0.14, 0.3])  # a structure alternative: in quadrature and covered
    covered = _eta_interval(stack, [_alternative_fit(FineFields(), {"attenuation.eta_per_m": other})], 0.01, 0.05)
    half = np.hypot(1.96 * 0.01, 1.96 * 0.05 * other)
    assert covered.low[0] == pytest.approx(0.3 - half[0], abs=2e-6)
    assert covered.high[2] == pytest.approx(0.3 + half[2], abs=2e-6)
    cover = covered.widening("fine_fields")
    assert cover.rule == "quadrature" and [w.rule for w in covered.widenings] == ["quadrature", "cover"]
    assert covered.widenings[1].widened == [True, False, True]  # green's alternative is the estimate itself
    low_bound = stack["attenuation"]._spec("eta_per_m").lower
    floor = _eta_interval(stack, [_alternative_fit(FineFields(), {"attenuation.eta_per_m": [0.001, 0.14, 0.2]})])
    assert floor.low[0] >= low_bound

    profile = {"param": "attenuation.eta_per_m", "low": [0.3, 0.13, 0.19], "high": [0.5, 0.15, 0.3]}
    profiled = _eta_interval(stack, [_alternative_fit(Profile(), profile=profile)])
    assert profiled.low == [0.3, pytest.approx(0.14 - 1.96 * 0.01, abs=2e-6), pytest.approx(0.2 - 1.96 * 0.01,
                                                                                              abs=2e-6)]
    assert profiled.high[2] == 0.3 and profiled.widening("eta_profile").widened == [True, False, True]


def test_a_structure_fit_stopped_above_the_estimates_training_loss_is_fitted_again_from_it(survey):
    """A structure holds the estimate's, so its fit to the training points must reach that structure's training
    loss: one stopped above it (here cut short at 3 iterations) is fitted again from the estimate's structure's
    training fit, the lower of the two kept, its seconds both fits'."""
    from dataclasses import replace

    from eval.water.alternatives import NESTED_LOSS_TOLERANCE, Context, FineFields, training_loss
    from eval.water.fields import GRID_EFFECT
    from eval.water.fit_water import fit_water

    frames, board = survey
    obs = measure_frames(frames, K, board=board)
    config = water_config(alternatives=(FineFields(),))
    ctx = Context(fit_water(obs, config), obs, config, None, [], None)
    ctx.prefit([])
    floor = training_loss(ctx.trained[""]) * (1 + NESTED_LOSS_TOLERANCE)
    short = replace(config.fit, iterations=3, max_iterations=3, coarse_refine_evaluations=0, refine_evaluations=0)
    cut = fit_water(ctx.train, replace(FineFields().changed(config), fit=short), None, float32=True)
    assert training_loss(cut) > floor  # the case the rule is for
    ctx.trained[FineFields.key] = cut
    lines = []
    ctx.announce = lines.append
    ctx.prefit([FineFields()])
    again = ctx.trained[FineFields.key]
    assert len(lines) == 1 and lines[0].startswith("fine_fields: its fit stopped") and "fitted again" in lines[0]
    assert again is not cut and training_loss(again) <= floor
    assert again.seconds > cut.seconds and GRID_EFFECT in again.stack.names


def test_a_structures_values_are_its_training_fits_whatever_its_held_out_test_says(survey):
    """A structure's one fit on the training points gives its held-out test and its values: rejected (the whole
    interval above +0.1 %), tied or preferred, the values are that fit's and the record says which it was."""
    from eval.water.alternatives import AlternativeFit, Context, FreeGains
    from eval.water.fit_water import fit_water

    frames, board = survey
    obs = measure_frames(frames, K, board=board)
    config = water_config(alternatives=(FreeGains(),))
    trained = fit_water(obs.take_points(np.arange(obs.n_points // 2)), config)  # told apart from the estimate
    estimate = fit_water(obs, config)
    for ci, verdict in (((0.004, 0.016), "rejected"), ((-0.0005, 0.0015), None), ((-0.016, -0.004), "preferred")):
        ctx = Context(estimate, obs, config, None, [], None)
        ctx.tests[FreeGains.key] = AlternativeFit(FreeGains(), {}, change=sum(ci) / 2, ci=ci, fit=trained)
        result = FreeGains().refit(ctx)
        assert (result.rejected, result.preferred) == (verdict == "rejected", verdict == "preferred")
        assert result.record().rejected == (verdict == "rejected")
        np.testing.assert_allclose(result.values["attenuation.eta_per_m"], trained.values()["attenuation.eta_per_m"])
        assert np.abs(result.values["attenuation.eta_per_m"] - estimate.values()["attenuation.eta_per_m"]).max() > 0


def test_the_profiles_bound_is_where_the_changes_lower_bound_reaches_zero():
    """A rejected step's bound: with the held-out change d = a (f - 1)^2 and its interval's half-width b |f - 1|,
    lo = d - b |f - 1| reaches 0 at |f - 1| = b / a, read from the one step (no nearer 1 than the step before it)."""
    from eval.water.profile import bound

    a, b = 40.0, 3.0  # lo = 0 at |f - 1| = 0.075
    for factor in (0.8, 0.6, 1.25, 1.6):
        d = a * (factor - 1) ** 2
        assert bound(factor, d, d - b * abs(factor - 1), 1.0) == pytest.approx(1 + np.sign(factor - 1) * b / a)
    assert bound(1.6, a * 0.36, a * 0.36 - b * 0.6, 1.25) == 1.25  # the step before was accepted: no nearer


def test_held_out_sums_per_channel_add_up_to_the_sums_over_the_channels():
    """point_sums per channel: (H, 3) sums whose rows add to the summed version's, and each point's views (the
    summed version counts the three components)."""
    from types import SimpleNamespace

    from eval.heldout import Split, point_sums

    rng = np.random.default_rng(0)
    obs = SimpleNamespace(point=np.array([0, 0, 1, 2, 2, 2, 5]))  # point_sums reads the views' points alone
    split = Split(train_obs=np.array([], int), holdout_fit_obs=np.array([], int),
                  holdout_test_obs=np.arange(7), holdout_points=np.array([0, 1, 2, 5]))
    residual = rng.normal(size=(7, 3))
    total, count = point_sums(obs, split, residual)
    per, views = point_sums(obs, split, residual, per_channel=True)
    np.testing.assert_allclose(per.sum(1), total)
    np.testing.assert_array_equal(views * 3, count)
    np.testing.assert_allclose(per[2], (residual[3:6] ** 2).sum(0))


def test_b_infs_interval_covers_the_valley_the_veil_and_beta_leave_it_in():
    """B_inf's interval widens to B_inf = V / (1 - exp(-beta r)) over the veil V's interval and beta's: a narrow
    bootstrap interval of B_inf in a wide valley of beta becomes the valley's span; with beta's interval reaching 0
    it reaches B_inf's upper bound; where the valley is narrower than B_inf's own interval nothing changes."""
    from eval.water.intervals import cover_the_valley
    from watergan.water_record import ParamInterval

    r = 3.0
    veil = {"range_m": r, "low": [0.02, 0.09, 0.115], "high": [0.024, 0.1, 0.118]}
    params = {"backscatter.b_inf": ParamInterval([0.03, 0.16, 0.19], low=[0.028, 0.15, 0.18], high=[0.032, 0.17, 0.2]),
              "backscatter.beta_per_m": ParamInterval([0.4, 0.2, 0.32], low=[0.2, 0.0, 0.31], high=[0.6, 0.4, 0.33])}
    cover_the_valley(params, veil)
    b_inf = params["backscatter.b_inf"]
    np.testing.assert_allclose(b_inf.low, [0.02 / -np.expm1(-0.6 * r), 0.09 / -np.expm1(-0.4 * r), 0.18],
                               rtol=1e-4)
    np.testing.assert_allclose(b_inf.high, [0.024 / -np.expm1(-0.2 * r), 1.0, 0.2], rtol=1e-4)
    assert b_inf.widening("valley").widened == [True, True, False]


def test_a_parameter_at_a_bound_is_reported(survey):
    """A stack without attenuation on frames whose colour falls with range: the backscatter's beta runs to the
    top of its range (5 /m, measured), and at_bounds names it; its interval is the parameter's whole range, never the
    zero-width one that its bootstrap (every replicate on the bound) gives; the full stack has nothing at a bound.
    (No nuisance fields or gains per frame here: they would take part of what the missing attenuation leaves.)"""
    from pipeline.water import at_bounds

    frames, board = survey
    wrong = estimate_water(frames, K, board=board,  # no alternatives: a component on its bound gets the bounds
                           config=water_config(effects=("backscatter", "vignetting", "gain"), bootstrap=3,
                                               field_degree=0, frame_gain=False,
                                               alternatives=ALTERNATIVE_PRESETS["none"]))
    assert "backscatter.beta_per_m[1]" in at_bounds(wrong)
    beta = wrong.params["backscatter.beta_per_m"]
    assert beta.on_bound[1] and (beta.low[1], beta.high[1]) == (0.0, 5.0)
    full = water_config(bootstrap=0, alternatives=ALTERNATIVE_PRESETS["none"])  # at_bounds reads the estimate alone
    assert at_bounds(estimate_water(frames, K, board=board, config=full)) == []


def test_the_water_stage_needs_the_dense_range(tmp_path):
    from pipeline.sfm import SfmConfig, SfmResult
    from pipeline.workspace import Workspace
    from watergan.errors import UserInputError

    ws = Workspace(tmp_path / "ws")
    ws.save("sfm", SfmConfig(), SfmResult(model_dir="", tracks=f"{STAGES['sfm'].folder}/tracks.npz", n_images=3,
                                          n_registered=3, n_points=0, mean_track_length=0.0,
                                          mean_reprojection_error_px=0.0,
                                          matching="", scale_method="stereo", scale_factor=1.0, scale_spread=0.0,
                                          seconds=0.0))
    with pytest.raises(UserInputError, match="run the dense stage first"):
        ws.run("water", water_config())


def test_board_patches_are_bootstrap_units(survey):
    """Every board row names its patch (the bootstrap weighs each patch's views together)."""

    frames, board = survey
    obs = measure_frames(frames, K, board=board, config=DenseMeasureConfig(samples_per_frame=50, margin_px=4))
    assert len(obs.board_patch) == len(obs.board_colour) > 20
    np.testing.assert_array_equal(obs.board_albedo, BOARD_RGB[obs.board_patch])


def test_a_long_survey_lifts_a_bounded_number_of_points_from_every_frame(survey):
    """``max_points`` bounds the points over the survey: each of the 12 frames lifts max_points / 12 (not
    ``samples_per_frame``), and every frame still takes part."""
    frames, _ = survey
    full = measure_frames(frames, K, config=DenseMeasureConfig(samples_per_frame=50, margin_px=4, min_points=20))
    bounded = measure_frames(frames, K, config=DenseMeasureConfig(samples_per_frame=50, max_points=240, margin_px=4,
                                                                 min_points=20))
    assert 200 <= bounded.n_points <= 240 < full.n_points
    assert len(np.unique(bounded.frame)) == len(frames)


def test_a_fit_stopped_before_convergence_says_so(survey):
    """Rounds of L-BFGS run until one gains less than convergence_rtol; a fit cut short by max_iterations is
    reported as not converged (in the estimate and its summary line), one given room converges. (The fit cut short
    has no alternatives: refitted from where it stopped, they would measure the stop, not the survey.)"""
    frames, board = survey
    short = estimate_water(frames, K, board=board, config=water_config(iterations=2, max_iterations=3, bootstrap=0,
                                                                      margin_px=4, footprint_m=FOOTPRINT_M,
                                                                      coarse_fraction=0.0,
                                                                      alternatives=ALTERNATIVE_PRESETS["none"]))
    assert not short.converged and short.iterations == 2 and "not converged in 2 iterations" in short.summary()
    full = estimate_water(frames, K, board=board, config=water_config(bootstrap=0, margin_px=4,  # the fit's own
                                                                     footprint_m=FOOTPRINT_M,
                                                                     alternatives=ALTERNATIVE_PRESETS["none"]))
    assert full.converged and 200 <= full.iterations <= 1200 and "not converged" not in full.summary()
    assert full.to_json()["converged"] is True


def test_a_per_frame_effect_is_sized_by_the_survey_and_inverted_frame_by_frame(survey):
    """An auto-exposure plugin (one log-gain per frame, ``Param(per="frame")``, neutral start) added to the water:
    the stack gets one row per frame from the survey, the fit recovers the frames' relative exposures, and the
    correction takes each frame's own row (``frame_index``). Attenuation is held at its value here: with every
    frame at its own altitude a per-frame gain and exp(-eta r) at that frame's range nearly coincide."""
    from dataclasses import replace

    from watergan.formation import RANK_SENSOR, Effect, Param, register

    @register
    class WaterTestExposure(Effect):
        name = "water_test_exposure"
        summary = "each frame's signal scaled by its own gain exp(g_k)"
        axis = "frame"
        rank = RANK_SENSOR
        params = (Param("log_gain", 0.0, -1.0, 1.0, "", "log of the frame's exposure gain", per="frame"),)

        def forward(self, state):
            gain = torch.exp(self.per_frame("log_gain", state)).view(-1, 1, 1, 1)
            return state.replace(direct=state.direct * gain, backscatter=state.backscatter * gain)

    frames, board = survey
    log_gain = np.array([0.12, -0.1, 0.05, -0.14, 0.0, 0.1, -0.06, 0.14, -0.12, 0.08, -0.02, 0.03])
    exposed = [replace(f, image=np.clip(f.image * np.exp(g), 0, 1).astype(np.float32))
               for f, g in zip(frames, log_gain, strict=True)]
    config = water_config(effects=(*DEFAULT_WATER_EFFECTS, "water_test_exposure"), fixed_effects=("attenuation",),
                         initial=(TRUE[0],), samples_per_frame=250, bootstrap=0, margin_px=4,
                         footprint_m=FOOTPRINT_M)
    est = estimate_water(exposed, K, board=board, config=config)
    fitted = np.asarray(est.params["water_test_exposure.log_gain"].value, float)
    assert fitted.shape == (12,)
    np.testing.assert_allclose(fitted - fitted.mean(), log_gain - log_gain.mean(), atol=0.02)
    k = int(np.argmax(log_gain))
    _, r, j = render(exposed[k].world_from_cam, Stack.from_config(TRUE))
    own, _ = correct_physics(exposed[k].image, r, est.stack, K, frame_index=k)
    other, _ = correct_physics(exposed[k].image, r, est.stack, K, frame_index=int(np.argmin(log_gain)))
    assert np.median(np.abs(own / j - 1)) < 0.03  # its own exposure undone
    assert np.median(other / j) > 1.2  # another frame's row leaves exp(0.14 + 0.14) = 1.32 in it


# ------------------------------------------------------------------------------- a declared strobe rig
#: Two strobes beside the camera, aimed 10 degrees inwards (as survey.json declares them), in darkness.


def test_the_hessian_perturbs_the_three_channels_of_a_parameter_together(survey):
    """The loss is a sum over the colour channels, so perturbing the three channels of eta, B_inf, the fields and
    the gains per frame together gives the Hessian that perturbing each entry gives (to the finite differences'
    accuracy) from a third of the gradients; a stack that mixes the channels is differentiated entry by entry."""
    from eval.fit import Problem, channels_separate, fitted_names, start_inside_bounds
    from eval.water.fields import decorrelate_frames
    from watergan.formation import RANK_SENSOR, Effect, register

    frames, board = survey
    config = water_config(samples_per_frame=60, margin_px=4, footprint_m=FOOTPRINT_M)
    obs = measure_frames(frames, K, None, board, config.measure)
    stack = build_stack(config, len(frames))
    names = fitted_names(stack, (), {})
    decorrelate_frames(stack, obs)
    start_inside_bounds(stack, names)
    problem = Problem(stack, obs, config.fit, names)
    problem.minimise(30)
    groups, channel = problem.channel_groups()
    assert (channel >= 0).sum() > 0.8 * len(channel) and len(groups) < 0.4 * len(channel)
    grouped = problem.hessian()
    problem.separate = False
    single = problem.hessian()
    np.testing.assert_allclose(grouped, single, atol=2e-3 * float(single.abs().max()))

    probe = FormationState(direct=torch.full((4, 3, 1, 1), 0.5, dtype=torch.float64),
                           range_m=torch.full((4, 1, 1, 1), 2.0, dtype=torch.float64),
                           pixel_uv=torch.full((4, 2, 1, 1), 0.5, dtype=torch.float64), image_wh=(W, H))
    assert channels_separate(Stack.ordered(TRUE), probe)

    @register
    class WaterTestCrossTalk(Effect):
        name = "water_test_cross_talk"
        summary = "a tenth of each channel leaks into the next (a colour matrix)"
        axis = "intensity"
        rank = RANK_SENSOR

        def forward(self, state):
            return state.replace(direct=state.direct + 0.1 * state.direct.roll(1, dims=1))

    assert not channels_separate(Stack.ordered([*TRUE, {"name": "water_test_cross_talk"}]), probe)
