"""The missing effects that benchmarks/bench_forms.py draws: one draw of each family renders with the shape its
docstring states, and the gains a camera sets from each frame's own pixels are the frame's gray-world (mean
luminance) gains, which the oracle's truth then holds."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import make_state

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_forms  # noqa: E402

from watergan.formation import get  # noqa: E402

ETA_PER_M = np.array([0.45, 0.14, 0.2])
FRAMES = 4
LABELS = ("falloff_polynomial", "falloff_clipped", "falloff_gaussian", "falloff_cosine_power", "spot", "ramp",
          "frame_gain_grey", "frame_gain_colour", "auto_white_balance", "auto_exposure", "water_drift")


@pytest.fixture(scope="module")
def drawn() -> dict[str, tuple[str, dict]]:
    """{family label: (effect, parameters)}: the first draw of each label over a run of seeds."""
    bench_forms.load_forms()
    found: dict[str, tuple[str, dict]] = {}
    for k in range(500):
        family, effect, params = bench_forms.draw_effect(np.random.default_rng([7, k]), FRAMES, ETA_PER_M)
        found.setdefault(family, (effect, params))
    assert sorted(found) == sorted(LABELS)
    return found


def rendered(effect: str, params: dict, state):
    """The state after the effect alone."""
    with torch.no_grad():
        return get(effect)(**params).double()(state)


def distance(state, centre_uv) -> np.ndarray:
    """(H,W) distance of each pixel from ``centre_uv`` in half diagonals."""
    w, h = state.image_wh
    uv = state.pixel_uv[0].numpy()
    return np.hypot((uv[0] - centre_uv[0]) * w, (uv[1] - centre_uv[1]) * h) / (0.5 * math.hypot(w, h))


@pytest.mark.parametrize("label", [name for name in LABELS if name.startswith("falloff")])
def test_falloff_darkens_by_its_profile_and_strength(drawn, label):
    """V_c = 1 - s_c p(d): 1 at the centre, the drawn strength where the profile is full (beyond the ring, or
    at the farthest corner), and the stated profile everywhere."""
    effect, params = drawn[label]
    state = make_state(batch=1, height=60, width=80, range_m=2.0)
    v = (rendered(effect, params, state).direct / state.direct)[0].numpy()
    s = np.asarray(params["strength"])
    cu, cv = params["centre_uv"]
    d = distance(state, params["centre_uv"])
    far = math.hypot(max(cu, 1 - cu) * 80, max(cv, 1 - cv) * 60) / (0.5 * math.hypot(80, 60))
    profile = {"falloff_polynomial": lambda: (d / far) ** params.get("power", 0.0),
               "falloff_clipped": lambda: np.minimum(1.0, (d / params.get("width", 1.0)) ** 2),
               "falloff_gaussian": lambda: 1 - np.exp(-d * d / (2 * params.get("width", 1.0) ** 2)),
               "falloff_cosine_power": lambda: 1 - np.cos(0.5 * np.pi * np.minimum(1.0, d / params.get("width", 1.0)))
               ** params.get("power", 1.0)}[label]()
    assert np.allclose(v, 1.0 - s[:, None, None] * profile[None], atol=1e-9)
    nearest = np.unravel_index(np.argmin(d), d.shape)
    assert np.all(1.0 - v[:, nearest[0], nearest[1]] <= 0.05 * s + 1e-9)  # undarkened at its centre
    full = profile >= 1.0 - 1e-12
    if label == "falloff_polynomial":  # the darkening reaches s at the farthest corner (pixel centres: nearly)
        assert np.allclose(1.0 - v.reshape(3, -1).min(axis=1), s, rtol=0.08)
    elif full.any():
        assert np.allclose(1.0 - v[:, full], s[:, None], atol=1e-9)
    assert np.all(1.0 - v <= s[:, None, None] + 1e-9)
    narrow = {**params, "width": 0.3} if "width" in params else params  # pixels beyond the ring
    with torch.no_grad():  # as the simulator renders: float32, finite beyond the ring too
        single = get(effect)(**narrow)(state.replace(direct=state.direct.float(), pixel_uv=state.pixel_uv.float()))
    assert torch.isfinite(single.direct).all()


def test_spot_and_ramp_add_their_stated_veils(drawn):
    """The spot adds a_c at its centre and at least a_c f anywhere; the ramp adds nothing where t <= t0 and a_c
    from t >= t0 + w."""
    state = make_state(batch=1, height=60, width=80, range_m=2.0)
    effect, params = drawn["spot"]
    added = rendered(effect, params, state).backscatter[0].numpy() - state.backscatter[0].numpy()
    a, f = np.asarray(params["amplitude"]), params["floor"]
    d = distance(state, params["centre_uv"])
    expected = a[:, None, None] * (f + (1 - f) * np.exp(-d * d / (2 * params["width"] ** 2)))[None]
    assert np.allclose(added, expected, atol=1e-9)
    assert np.all(added >= a[:, None, None] * f - 1e-12) and np.all(added <= a[:, None, None] + 1e-12)
    effect, params = drawn["ramp"]
    added = rendered(effect, params, state).backscatter[0].numpy() - state.backscatter[0].numpy()
    uv = state.pixel_uv[0].numpy()
    theta = math.radians(params["angle_deg"])
    t = (uv[0] - 0.5) * math.cos(theta) + (uv[1] - 0.5) * math.sin(theta)
    a = np.asarray(params["amplitude"])[:, None]
    assert np.allclose(added[:, t <= params["start"]], 0.0)
    assert np.allclose(added[:, t >= params["start"] + params["width"]], a)
    middle = (t > params["start"]) & (t < params["start"] + params["width"])
    assert np.allclose(added[:, middle], a * (t[middle] - params["start"]) / params["width"])


def test_frame_gains_and_drift_act_per_frame(drawn):
    """A frame's signal is scaled by exp(g_f) (grey) or exp(g_fc) (per channel); the drifting water attenuates
    the direct path by exp(-delta_fc r) more."""
    state = make_state(batch=2, height=6, width=8)
    frame = state.frame_index.numpy() % FRAMES
    state = state.replace(frame_index=torch.as_tensor(frame))
    for label, shape in (("frame_gain_grey", (FRAMES, 1)), ("frame_gain_colour", (FRAMES, 3))):
        effect, params = drawn[label]
        gain = np.exp(np.asarray(params["log_gain"]).reshape(shape))[frame]
        out = rendered(effect, params, state).direct.numpy()
        assert np.allclose(out, state.direct.numpy() * gain[:, :, None, None])
    effect, params = drawn["water_drift"]
    delta = np.asarray(params["delta_eta_per_m"])[frame]
    out = rendered(effect, params, state).direct.numpy()
    assert np.allclose(out, state.direct.numpy() * np.exp(-delta[:, :, None, None] * state.range_m.numpy()))


def test_auto_gains_follow_each_frames_own_pixels(drawn):
    """The auto white balance's gain is each frame's gray-world gain (mean / channel mean)^alpha of its own
    recorded image (direct + backscatter), and the auto exposure's (Y* / Y)^alpha of its mean luminance: two frames
    of different content get different gains, and at alpha = 1 a frame's mean becomes grey (the target)."""
    state = make_state(batch=2, height=12, width=16)
    tint = torch.tensor([[1.0, 0.5, 0.3], [0.4, 0.8, 1.2]], dtype=torch.float64).view(2, 3, 1, 1)
    state = state.replace(direct=state.direct * tint, backscatter=0.02 + 0.0 * state.direct)
    image = (state.direct + state.backscatter).numpy()
    means = image.mean(axis=(2, 3))
    effect, params = drawn["auto_white_balance"]
    gains = (rendered(effect, params, state).direct / state.direct).numpy()
    expected = (means.mean(axis=1, keepdims=True) / means) ** params["alpha"]
    assert np.allclose(gains, expected[:, :, None, None])
    assert not np.allclose(expected[0], expected[1])
    full = rendered(effect, {"alpha": 1.0}, state)
    balanced = (full.direct + full.backscatter).numpy().mean(axis=(2, 3))
    assert np.allclose(balanced, balanced.mean(axis=1, keepdims=True))
    effect, params = drawn["auto_exposure"]
    luminance = (image * np.array([0.2126, 0.7152, 0.0722])[None, :, None, None]).sum(axis=1).mean(axis=(1, 2))
    gains = (rendered(effect, params, state).direct / state.direct).numpy()
    assert np.allclose(gains, ((params["target"] / luminance) ** params["alpha"])[:, None, None, None])
    exposed = rendered(effect, {"target": params["target"], "alpha": 1.0}, state)
    y = ((exposed.direct + exposed.backscatter).numpy() * np.array([0.2126, 0.7152, 0.0722])[None, :, None, None])
    assert np.allclose(y.sum(axis=1).mean(axis=(1, 2)), params["target"])


def test_realised_white_balance_is_what_the_frames_received(tmp_path):
    """On a tiny survey with the full auto white balance hidden, each recorded frame's mean is grey (to noise and
    quantisation), and the oracle with the realised gains (the truth's ``frame_colour_gain``) returns the in-air
    frame."""
    from dataclasses import replace

    from eval.baseline_runs import OracleGeometry
    from eval.baselines import oracle
    from eval.colour import read_rgb
    from eval.synth import make_config, simulate_survey

    bench_forms.load_forms()
    cfg = make_config("tiny", seed=3)
    cfg = replace(cfg, formation=replace(cfg.formation, hidden=({"name": "auto_white_balance",
                                                                 "params": {"alpha": 1.0}},)))
    survey = tmp_path / "survey"
    simulate_survey(survey, cfg, force=True, progress=False)
    log_gains = np.asarray(bench_forms.realise_content_gains(survey, "auto_white_balance"))
    assert log_gains.shape == (6, 3) and np.ptp(log_gains, axis=1).min() > 0.1  # a tint undone, per frame
    geometry = OracleGeometry(survey)
    assert "frame_colour_gain" in geometry.stack.names and "auto_white_balance" not in geometry.stack.names
    for name in geometry.truth.frames[:2]:
        recorded = read_rgb(survey / "images" / name)
        means = recorded.reshape(-1, 3).mean(axis=0)
        assert np.allclose(means, means.mean(), rtol=0.02)
        inair = read_rgb(survey / "truth" / "inair_linear" / name, linear=False)
        restored = oracle(recorded.astype(np.float64), geometry.state(name), geometry.stack)
        assert np.median(np.abs(restored - inair)) < 0.01


def test_the_summary_counts_partial_steps_apart_from_false_acceptances():
    """A library effect accepted as the missing one is a false acceptance; one accepted as a partial step (the
    diagnosis's partial flag) is counted apart; a record written before the flag existed counts as full."""
    correction = {k: {"psnr_db": 20.0} for k in ("raw", "physics", "oracle")}

    def record(diagnosis):
        return {"params": {}, "correction": correction, "diagnosis": diagnosis}

    records = [record({"accepted": "vignetting_offcentre", "partial": True}),
               record({"accepted": "vignetting_offcentre", "partial": False}),
               record({"accepted": "black_level"}),
               record({"accepted": None, "partial": False}), record(None), record({"accepted": None, "error": ["x"]})]
    summary = bench_forms.summarise(records)
    assert (summary["false_acceptances"], summary["partial_steps"], summary["diagnosed"]) == (2, 1, 4), summary
    assert [bench_forms.acceptance(r["diagnosis"]) for r in records] == ["partial", "full", "full", "", "", ""]
