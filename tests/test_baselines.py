"""Every baseline on small synthetic images with a known answer."""

import numpy as np
import pytest
import torch

from eval.baselines import (
    BASELINES,
    clahe,
    gray_world,
    histogram_equalisation,
    jaffe_coefficients,
    jaffe_mcglamery,
    oracle,
    raw,
    seathru,
)
from watergan.errors import UserInputError
from watergan.formation import Stack, state_from_rgbd

ETA = np.array([0.45, 0.14, 0.2])
B_INF = np.array([0.03, 0.16, 0.19])
BETA = np.array([0.45, 0.32, 0.32])
K = np.array([1.5, 1.5, 1.5])


def _scene(h: int = 96, w: int = 128, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """In-air linear image J (gray on average, textured, some shadows) and a range ramp 1.5..4.5 m."""
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.05, 0.9, (h, w, 3))
    shade = np.where(rng.random((h, w, 1)) < 0.05, 0.05, 1.0)
    range_m = np.broadcast_to(np.linspace(1.5, 4.5, w)[None, :], (h, w)) + 0.2 * rng.random((h, w))
    return albedo * shade, np.ascontiguousarray(range_m)


def _underwater(j: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    r = range_m[..., None]
    return np.clip(K * (j * np.exp(-ETA * r) + B_INF * -np.expm1(-BETA * r)), 0, 1)


def _scaled_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """RMSE after the least-squares single scale (a baseline cannot know the exposure)."""
    s = float((estimate * truth).sum() / max((estimate * estimate).sum(), 1e-12))
    return float(np.sqrt(np.mean((s * estimate - truth) ** 2)))


def test_raw_is_identity_and_shape_is_checked():
    j, _ = _scene(8, 8)
    assert np.array_equal(raw(j), j)
    with pytest.raises(UserInputError, match="H,W,3"):
        raw(j[..., 0])


def test_gray_world_equalises_channel_means_of_a_cast_image():
    j, _ = _scene()
    cast = j * np.array([0.2, 0.6, 0.7])
    means = cast.reshape(-1, 3).mean(0)
    assert np.ptp(means) > 0.2
    out = gray_world(cast)
    assert np.allclose(out.reshape(-1, 3).mean(0), means.mean(), rtol=1e-6)


def test_histogram_equalisation_and_clahe_stay_in_range_and_raise_contrast():
    j, _ = _scene()
    dull = 0.2 + 0.1 * j  # a low-contrast image
    for fn in (histogram_equalisation, clahe):
        out = fn(dull)
        assert out.shape == dull.shape and out.min() >= 0 and out.max() <= 1
        assert out[..., 1].std() > 2 * dull[..., 1].std(), fn.__name__
    # per-channel equalisation flattens each channel's histogram: all three means end up alike
    eq = histogram_equalisation(dull * np.array([0.3, 1.0, 1.0]))
    assert np.ptp(eq.reshape(-1, 3).mean(0)) < 0.03
    # CLAHE works on lightness only: a cast stays a cast
    cl = clahe(dull * np.array([0.3, 1.0, 1.0]))
    means = cl.reshape(-1, 3).mean(0)
    assert means[0] < 0.7 * means[1]


def test_jaffe_with_ideal_coefficients_recovers_the_scene():
    j, range_m = _scene()
    image = _underwater(j, range_m)
    out = jaffe_mcglamery(image, range_m, ETA, B_INF, BETA, K)
    ok = image < 1  # unclipped pixels
    assert np.abs(out - j)[ok].max() < 1e-6
    assert np.abs(image - j).mean() > 0.1  # the water did change the image
    with pytest.raises(UserInputError, match="range"):
        jaffe_mcglamery(image, None, ETA, B_INF, BETA, K)


def test_jaffe_coefficients_come_from_the_stack():
    config = [{"name": "attenuation", "params": {"eta_per_m": ETA.tolist()}},
              {"name": "backscatter", "params": {"b_inf": B_INF.tolist(), "beta_per_m": BETA.tolist()}},
              {"name": "vignetting"}, {"name": "gain", "params": {"k": [1.5]}}]
    c = jaffe_coefficients(config)
    assert np.allclose(c["eta_per_m"], ETA) and np.allclose(c["b_inf"], B_INF)
    assert np.allclose(c["beta_per_m"], BETA) and np.allclose(c["k"], [1.5] * 3)
    assert jaffe_coefficients([])["k"] == [1.0] * 3


def test_seathru_reduces_error_on_a_range_dependent_image():
    j, range_m = _scene(120, 160)
    image = _underwater(j, range_m)
    out = seathru(image, range_m)
    assert out.shape == image.shape and out.min() >= 0 and out.max() <= 1
    raw_error, fit_error = _scaled_error(image, j), _scaled_error(out, j)
    assert fit_error < 0.6 * raw_error, (raw_error, fit_error)
    # the red channel fades fastest with range: after Sea-thru, far and near red agree much better
    near, far = range_m < 2.2, range_m > 3.8
    ratio = lambda im: im[far][:, 0].mean() / im[near][:, 0].mean()  # noqa: E731
    assert abs(ratio(out) - 1) < 0.5 * abs(ratio(image) - 1)


def _truth_state(j: np.ndarray, depth_m: float = 2.5):
    h, w = j.shape[:2]
    rgb = torch.from_numpy(j.transpose(2, 0, 1)[None].astype(np.float32))
    depth = torch.full((1, 1, h, w), depth_m)
    return state_from_rgbd(rgb, depth, fx=0.8 * w, fy=0.8 * w, cx=w / 2, cy=h / 2)


@pytest.mark.parametrize("extra", [[], [{"name": "vignetting_offcentre"}],
                                   [{"name": "sensor_response", "params": {"gamma": 1.4, "saturation": 0.8}}]])
def test_oracle_recovers_the_truth_to_noise_level(extra):
    j, _ = _scene(48, 64)
    state = _truth_state(j)
    stack = Stack.ordered([
        {"name": "attenuation", "params": {"eta_per_m": ETA.tolist()}},
        {"name": "backscatter", "params": {"b_inf": B_INF.tolist(), "beta_per_m": BETA.tolist()}},
        {"name": "vignetting", "params": {"a_margin": 0.35, "b": 0.0, "c": 0.05}},
        {"name": "gain", "params": {"k": [0.9]}}, *extra])
    with torch.no_grad():
        clean = stack.render(state)[0].permute(1, 2, 0).double().numpy()
    assert clean.max() < 0.75  # nothing saturates (the sensor curve's saturation is 0.8): J is recoverable
    noise = 0.002
    noisy = np.clip(clean + np.random.default_rng(1).normal(0, noise, clean.shape), 0, 1)
    out = oracle(noisy, state, stack)
    error = np.sqrt(np.mean((out - j) ** 2))
    assert error < 0.03, error  # noise 0.002 amplified by 1 / (k exp(-eta r) V) ~ 2 to 5 (and the sensor curve)
    assert np.sqrt(np.mean((raw(noisy) - j) ** 2)) > 5 * error


def test_registry_lists_every_baseline_with_its_needs():
    assert list(BASELINES) == ["raw", "histeq", "clahe", "gray_world", "jaffe", "seathru", "oracle"]
    assert BASELINES["seathru"].needs_range and not BASELINES["seathru"].needs_truth
    assert BASELINES["oracle"].needs_truth and BASELINES["jaffe"].needs_range
    assert not any(BASELINES[n].needs_range for n in ("raw", "histeq", "clahe", "gray_world"))
