"""The camera's own response (tone_curve, black_level), the glossy surface (specular_gloss) and the diagnosis's
incidence-angle axis: equations against hand computations, monotone curves over the whole parameter range, finite
gradients, how the fitter takes them, and the angle axis binned on a tiny table."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import make_state

from eval.diagnose_residuals import (
    ResidualConfig,
    analyse,
    incidence_angle_deg,
    orientations_line,
    surface_orientations,
)
from eval.fit import (
    FitConfig,
    Problem,
    board_state,
    copy_stack,
    fitted_names,
    is_affine_in_albedo,
    observation_state,
    render_albedo,
    start_inside_bounds,
)
from eval.observations import Observations
from watergan.formation import Counts, FormationState, MissingInputError, Stack, get, pixel_grid
from watergan.formation.effects.specular_gloss import add_gloss, incidence_cosine
from watergan.formation.effects.tone_curve import SEGMENTS, remap, slog3_encode, srgb_encode, tone_curve
from watergan.formation.inverse import correct_physics, inverse_fields

F64 = torch.float64


def one_pixel(colour, points_cam=(0.0, 0.0, 2.0), normals_cam=(0.0, 0.0, -1.0)) -> FormationState:
    """A 1x1 state of linear ``colour`` (3,) at a camera-frame point and normal."""
    column = lambda v: torch.tensor(v, dtype=F64).view(1, -1, 1, 1)  # noqa: E731
    return FormationState(direct=column(colour), range_m=column([math.dist(points_cam, (0, 0, 0))]),
                          pixel_uv=pixel_grid(1, 1, 1, F64), image_wh=(1, 1), points_cam=column(points_cam),
                          normals_cam=column(normals_cam))


def srgb_by_hand(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def decode_by_hand(v: float) -> float:
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def test_tone_curve_against_a_hand_computation():
    """l = (ln 3, 0, ..., 0): softmax 3/10 then 1/10, slopes 2.4 then 0.8 on segments of 1/8; M(0.05) = 2.4 x 0.05,
    M(0.5) = (2.4 + 3 x 0.8) / 8 = 0.6, M(1) = 1."""
    l = torch.tensor([math.log(3.0)] + [0.0] * (SEGMENTS - 1), dtype=F64)
    x = torch.tensor([decode_by_hand(0.05), decode_by_hand(0.5), 1.0, 0.0], dtype=F64)
    y = tone_curve(x, l, torch.tensor(0.0, dtype=F64))
    expected = [decode_by_hand(2.4 * 0.05), decode_by_hand(0.6), 1.0, 0.0]
    np.testing.assert_allclose(y.detach().numpy(), expected, rtol=1e-12, atol=1e-15)
    # sRGB by hand on both sides of its linear toe, and S-Log3's middle grey: code value 420 of 1023
    for v in (0.002, 0.2, 0.9):
        assert float(srgb_encode(torch.tensor(v, dtype=F64))) == pytest.approx(srgb_by_hand(v), rel=1e-12)
    grey = tone_curve(torch.tensor(0.18, dtype=F64), torch.zeros(SEGMENTS, dtype=F64), torch.tensor(1.0, dtype=F64))
    assert float(grey) == pytest.approx(decode_by_hand(420 / 1023), rel=1e-12)
    assert float(slog3_encode(torch.tensor(0.0, dtype=F64))) == pytest.approx(95 / 1023, rel=1e-12)


def test_tone_curve_is_the_identity_at_neutral_and_sits_last_on_the_sum():
    state = make_state()
    effect = get("tone_curve")().double()
    effect.make_neutral()
    assert torch.allclose(effect(state).image, state.image, atol=1e-12)
    stack = Stack.ordered(["tone_curve", "gain", "black_level", "frame_gain", "sensor_response", "backscatter"],
                          Counts(frames=2))
    assert stack.names[-1] == "tone_curve" and stack.names.index("black_level") > stack.names.index("gain")
    effect = get("tone_curve")().double()
    expected = tone_curve(state.image, effect.param("log_slope"), effect.param("log_profile"))
    out = effect(state)
    assert torch.allclose(out.direct, expected) and not out.backscatter.any()


RAW_DRAWS = 40


@pytest.mark.parametrize("profile", [0.0, 0.5, 1.0])
def test_tone_curve_is_monotone_over_its_whole_parameter_range(profile):
    """Strictly increasing on 0..1.5 for raw log-slopes anywhere (the sigmoid's whole range, including the bounds
    +-3 themselves and alternating extremes), and M(0) = 0, M(1) = 1 for each."""
    g = torch.Generator().manual_seed(3)
    x = torch.linspace(0.0, 1.5, 3001, dtype=F64)
    effect = get("tone_curve")(log_profile=profile).double()
    extremes = [torch.full((SEGMENTS,), 3.0), torch.full((SEGMENTS,), -3.0),
                torch.tensor([3.0, -3.0] * (SEGMENTS // 2)), torch.tensor([-3.0] * (SEGMENTS - 1) + [3.0])]
    for i in range(RAW_DRAWS + len(extremes)):
        if i < len(extremes):
            effect.set_values(log_slope=extremes[i] * (1 - 1e-9))
        else:
            with torch.no_grad():
                effect.raw["log_slope"].copy_(torch.randn(SEGMENTS, generator=g, dtype=F64) * 30)
        l = effect.param("log_slope")
        y = tone_curve(x, l, torch.tensor(profile, dtype=F64))
        assert bool((torch.diff(y) > 0).all()), (profile, l)
        v = torch.tensor([0.0, 1.0], dtype=F64)
        np.testing.assert_allclose(remap(v, l).detach().numpy(), [0.0, 1.0], atol=1e-12)


def test_tone_curve_gradients_are_finite_at_its_joins():
    """At 0, at the sRGB toe's join, at the remap's knots, at 1 and past it: finite gradients in the signal and in
    every log-slope, and torch's gradient is the finite difference's."""
    x = torch.tensor([0.0, 0.0031308, decode_by_hand(0.25), decode_by_hand(0.5), 0.3, 1.0, 1.3], dtype=F64,
                     requires_grad=True)
    l = torch.linspace(-1.0, 1.0, SEGMENTS, dtype=F64).requires_grad_()
    for profile in (0.0, 1.0):
        y = tone_curve(x, l, torch.tensor(profile, dtype=F64)).sum()
        gx, gl = torch.autograd.grad(y, (x, l))
        assert torch.isfinite(gx).all() and torch.isfinite(gl).all() and (gx > 0).all(), (gx, gl)
    away = torch.tensor([0.02, 0.1, 0.4, 0.8], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: tone_curve(a, b, torch.tensor(0.3, dtype=F64)), (away, l))


def test_black_level_against_a_hand_computation():
    """I = k (S + B) + b: added after the gain (not scaled by it), to the additive part."""
    state = one_pixel([0.2, 0.3, 0.4])
    stack = Stack.from_config([{"name": "backscatter", "params": {"b_inf": [0.1, 0.1, 0.1], "beta_per_m": [5, 5, 5]}},
                               {"name": "gain", "params": {"k": [2.0]}},
                               {"name": "black_level", "params": {"offset": [0.01, -0.02, 0.03]}}]).double()
    out = stack(state)
    b = 0.1 * (1 - math.exp(-10.0))
    np.testing.assert_allclose(out.image.flatten().detach().numpy(), [2 * (0.2 + b) + 0.01, 2 * (0.3 + b) - 0.02,
                                                             2 * (0.4 + b) + 0.03], rtol=1e-12)
    np.testing.assert_allclose(out.direct.flatten().detach().numpy(), [0.4, 0.6, 0.8], rtol=1e-12)
    level = get("black_level")().double()
    level.make_neutral()
    assert torch.allclose(level(state).image, state.image, atol=1e-12)


def test_specular_gloss_against_a_hand_computation():
    """A point 2 m ahead on a surface tilted 60 degrees from the ray: cos theta = 1/2, D = J + a (1/2)^p; the
    normal's sign does not matter; seen head-on nothing is added; without normals, a clear error."""
    tilted = (0.0, -math.sin(math.radians(60)), -math.cos(math.radians(60)))
    effect = get("specular_gloss")(gloss=(0.1, 0.2, 0.3), exponent=2.0).double()
    for normal in (tilted, tuple(-n for n in tilted)):
        out = effect(one_pixel([0.2, 0.3, 0.4], normals_cam=normal))
        np.testing.assert_allclose(out.direct.flatten().detach().numpy(), [0.2 + 0.1 / 4, 0.3 + 0.2 / 4, 0.4 + 0.3 / 4],
                                   rtol=1e-12)
    head_on = effect(one_pixel([0.2, 0.3, 0.4]))
    np.testing.assert_allclose(head_on.direct.flatten().detach().numpy(), [0.2, 0.3, 0.4], atol=1e-12)
    cos = incidence_cosine(torch.tensor([3.0, 0.0, 4.0], dtype=F64).view(1, 3, 1, 1),
                           torch.tensor([0.0, 0.0, -1.0], dtype=F64).view(1, 3, 1, 1))
    assert float(cos) == pytest.approx(0.8)
    neutral = get("specular_gloss")().double()
    neutral.make_neutral()
    state = make_state()
    assert torch.allclose(neutral(state).image, state.image, atol=1e-8)  # 0 is a bound: the sigmoid stays 5e-10 off it
    with pytest.raises(MissingInputError, match="normals_cam"):
        effect(state.replace(normals_cam=None))


def test_specular_gloss_gradients_are_finite_head_on_and_at_grazing():
    a = torch.tensor([0.1, 0.2, 0.3], dtype=F64, requires_grad=True)
    for p in (0.5, 1.0, 5.0):
        exponent = torch.tensor(p, dtype=F64, requires_grad=True)
        cos = torch.tensor([1.0, 0.0, 0.5], dtype=F64).view(3, 1, 1, 1)
        y = add_gloss(torch.full((3, 3, 1, 1), 0.2, dtype=F64), cos, a, exponent).sum()
        grads = torch.autograd.grad(y, (a, exponent))
        assert all(torch.isfinite(g).all() for g in grads), (p, grads)


def tiny_table(angles_deg: np.ndarray, world_up_deg: np.ndarray | None = None) -> Observations:
    """Views of points 2 m ahead on surfaces seen at ``angles_deg`` (the normal tilted about x), one point each, in
    one frame; world normals at ``world_up_deg`` from up (default: floor)."""
    n = len(angles_deg)
    t = np.radians(angles_deg)
    points = np.tile([0.0, 0.0, 2.0], (n, 1))
    normals = np.stack([np.zeros(n), -np.sin(t), -np.cos(t)], 1)
    up = np.radians(np.zeros(n) if world_up_deg is None else world_up_deg)
    return Observations(colour=np.full((n, 3), 0.3), range_m=np.full(n, 2.0), depth_m=np.full(n, 2.0),
                        pixel_uv=np.full((n, 2), 0.5), points_cam=points, point=np.arange(n), frame=np.zeros(n, int),
                        n_points=n, image_wh=(8, 6), normals_cam=normals, grad_energy=np.ones(n),
                        points_world=np.zeros((n, 3)), normals_world=np.stack([np.sin(up), np.zeros(n), np.cos(up)], 1))


def test_the_incidence_angle_axis_bins_the_residuals_by_the_angle_seen():
    """200 views at 0-80 degrees with a residual of +0.01 beyond 40 degrees: ten quantile bins of the angle, the
    lower five at 0 and the upper five at 0.01, and a structure far above noise; no normals, no axis."""
    angles = np.linspace(0.0, 80.0, 200)
    meas = tiny_table(angles)
    np.testing.assert_allclose(incidence_angle_deg(meas.points_cam, meas.normals_cam), angles, atol=1e-9)
    np.testing.assert_allclose(meas.view_angle_deg, angles, atol=1e-9)  # the table's own angle agrees
    rng = np.random.default_rng(0)
    residual = np.where(angles[:, None] > 40.0, 0.01, 0.0) + rng.normal(0, 1e-4, (200, 3))
    analysis = analyse(meas, np.full((200, 3), 0.3), residual, ResidualConfig(n_bins=10))
    axis = analysis["incidence_angle"]
    np.testing.assert_allclose(axis["edges"], np.linspace(0.0, 80.0, 11), atol=1e-9)
    assert axis["count"] == [20.0] * 10
    means = np.array(axis["mean"])
    np.testing.assert_allclose(means[:5], 0.0, atol=1e-4)
    np.testing.assert_allclose(means[5:], 0.01, atol=1e-4)
    assert axis["score"] > 50
    flat = analyse(meas, np.full((200, 3), 0.3), rng.normal(0, 1e-4, (200, 3)), ResidualConfig(n_bins=10))
    assert flat["incidence_angle"]["score"] < 3
    from dataclasses import replace

    assert "incidence_angle" not in analyse(replace(meas, normals_cam=None), np.full((200, 3), 0.3), residual)


def test_the_surfaces_orientations_count_floors_and_walls():
    up = np.array([0.0, 10.0, 25.0, 45.0, 80.0, 90.0, 100.0, 170.0])
    orientations = surface_orientations(tiny_table(np.zeros(8), up))
    assert orientations["points"] == {"floor": 3, "wall": 3, "ceiling": 1, "other": 1}
    assert sum(orientations["count"]) == 8 and orientations["count"][0] == 2
    assert orientations_line(orientations).startswith("surfaces: 38% floor-like, 38% wall-like, 12% ceiling-like")
    from dataclasses import replace

    assert surface_orientations(replace(tiny_table(np.zeros(8)), normals_world=None)) == {}


def test_the_fitter_takes_the_tone_curve_as_not_affine_and_the_black_level_as_affine():
    """A black level keeps a stack affine in the albedos (it adds to C of y = A J + C), a tone curve away from the
    identity does not; the fitter's Problem takes the curve as an output map and tests the rest (closed form)."""
    meas = tiny_table(np.linspace(0.0, 60.0, 12))
    state = observation_state(meas, np.arange(meas.n_obs))
    base = ["attenuation", "backscatter", "vignetting", "gain"]
    assert is_affine_in_albedo(Stack.ordered([*base, "black_level", "specular_gloss"]).double(), state)
    assert not is_affine_in_albedo(Stack.ordered([*base, "tone_curve"]).double(), state)
    neutral = Stack.ordered([*base, "tone_curve"]).double()
    neutral["tone_curve"].make_neutral()
    assert is_affine_in_albedo(neutral, state)  # why the effect starts away from its identity
    curved = Stack.ordered([*base, "tone_curve", "specular_gloss"]).double()
    assert Problem(curved, meas, FitConfig(), []).affine and Problem(neutral, meas, FitConfig(), []).affine


def test_an_output_map_is_the_stacks_last_effect():
    assert Stack.from_names(["tone_curve", "gain"]).output_map()[1] is None  # elsewhere: an ordinary effect
    rest, curve = Stack.ordered(["tone_curve", "gain"]).output_map()
    assert rest.names == ["gain"] and curve.name == "tone_curve"
    assert Stack.from_names(["gain"]).output_map()[1] is None


S_CURVE = (-0.6, -0.1, 0.35, 0.45, 0.3, 0.0, -0.3, -0.5)


@pytest.mark.parametrize("profile", [0.0, 0.4, 1.0])
def test_the_correction_inverts_a_stack_ending_in_a_tone_curve_exactly(profile):
    """correct_physics linearises the image with the curve's exact inverse, then inverts the affine rest: the
    in-air colour comes back to 1e-5 (sRGB, a mixed profile, S-Log3), where the affine fields alone miss it."""
    state = make_state(batch=1, height=6, width=8)
    stack = Stack.ordered(["attenuation", "backscatter", "vignetting", "gain",
                           {"name": "tone_curve", "params": {"log_slope": S_CURVE, "log_profile": profile}}]).double()
    with torch.no_grad():
        image = stack.render(state)[0].permute(1, 2, 0).numpy()
    range_m = state.range_m[0, 0].numpy()
    truth = state.direct[0].permute(1, 2, 0).numpy()
    corrected, valid = correct_physics(image, range_m, stack)
    assert valid.all() and np.abs(corrected - truth).max() < 1e-5
    y = torch.linspace(0.02, 1.2, 101, dtype=F64)  # above T(0) (0.004 at S-Log3)
    with torch.no_grad():
        back = stack["tone_curve"](one_column(stack["tone_curve"].linearise(y))).image[:, 0].flatten()
    assert torch.allclose(back, y, atol=1e-10)
    a, c, _ = inverse_fields(range_m, stack)
    assert np.abs((image - c[0].permute(1, 2, 0).numpy()) / a[0].permute(1, 2, 0).numpy() - truth).max() > 1e-2


def test_the_correct_stages_exact_inverse_linearises_a_tone_curve_first():
    """The correct stage's exact inverse (pipeline.correct_physics.invert_exact) takes the curve off the image before
    the affine rest, as correct_physics does: the in-air colour back to 1e-5."""
    from pipeline.correct_physics import invert_exact

    state = make_state(batch=1, height=6, width=8)
    stack = Stack.ordered(["attenuation", "backscatter", "gain",
                           {"name": "tone_curve", "params": {"log_slope": S_CURVE}}]).double()
    with torch.no_grad():
        image = stack.render(state)[0].permute(1, 2, 0).numpy()
    range_m = state.range_m[0, 0].numpy()
    corrected = invert_exact(image, range_m, stack, None, 0, None, np.zeros(range_m.shape, bool))
    assert np.abs(corrected - state.direct[0].permute(1, 2, 0).numpy()).max() < 1e-5


def one_column(x: torch.Tensor) -> FormationState:
    """A state whose image is the values ``x`` (n,) in every channel (n 1x1 images)."""
    direct = x.view(-1, 1, 1, 1).expand(-1, 3, 1, 1)
    return FormationState(direct=direct, range_m=torch.ones_like(direct[:, :1]), pixel_uv=pixel_grid(1, 1, len(x), F64),
                          image_wh=(1, 1))


def curved_table() -> tuple[Observations, Stack]:
    """24 points of random albedo seen 4 times at 0.5-5 m, and a board of 12 patches at 0.6-4 m, rendered through an
    S-shaped tone curve; the stack that rendered them."""
    rng = np.random.default_rng(0)
    n_points, views, n_board = 24, 4, 12
    truth = Stack.ordered([{"name": "attenuation", "params": {"eta_per_m": [0.5, 0.2, 0.1]}},
                           {"name": "backscatter",
                            "params": {"b_inf": [0.05, 0.2, 0.3], "beta_per_m": [0.4, 0.3, 0.3]}},
                           {"name": "tone_curve", "params": {"log_slope": S_CURVE, "smoothness": 1e-9}}]).double()
    point, r, board_r = np.repeat(np.arange(n_points), views), rng.uniform(0.5, 5.0, n_points * views), \
        np.linspace(0.6, 4.0, n_board)
    ahead = lambda d: np.stack([0 * d, 0 * d, d], 1)  # noqa: E731
    obs = Observations(colour=np.zeros((len(r), 3)), range_m=r, depth_m=r, pixel_uv=np.full((len(r), 2), 0.5),
                       points_cam=ahead(r), point=point, frame=np.zeros(len(r), int), n_points=n_points,
                       image_wh=(8, 6), board_colour=np.zeros((n_board, 3)),
                       board_albedo=np.tile([0.8, 0.7, 0.6], (n_board, 1)), board_range_m=board_r,
                       board_depth_m=board_r, board_pixel_uv=np.full((n_board, 2), 0.5),
                       board_points_cam=ahead(board_r), board_frame=np.zeros(n_board, np.int64),
                       board_patch=np.arange(n_board))
    albedo = torch.from_numpy(rng.uniform(0.05, 0.9, (n_points, 3))[point])
    with torch.no_grad():
        obs.colour[:] = render_albedo(truth, observation_state(obs, np.arange(len(r))), albedo).numpy()
        obs.board_colour[:] = render_albedo(truth, board_state(obs), torch.from_numpy(obs.board_albedo)).numpy()
    return obs, truth


def test_the_fitter_fits_a_tone_curve_in_the_linear_domain():
    """A table rendered through a tone curve: the Problem is affine once linearised (closed-form albedos, exact at
    the truth), its board terms agree with a direct render, and a fit from the curve's starting values recovers
    eta and the curve over the table's signals (the backscatter held at its value: with it free, the curve's dark
    end and the veil trade on a table this small)."""
    obs, truth = curved_table()
    config = FitConfig(fixed_effects=("backscatter",), polish_iterations=0, max_iterations=200, bootstrap=0)
    at_truth = Problem(copy_stack(truth), obs, config, fitted_names(truth, config.fixed_effects, {}))
    with torch.no_grad():
        albedo, predicted = at_truth.albedo()
        assert at_truth.affine and torch.allclose(predicted, at_truth.y, atol=1e-12)
        assert float(at_truth._board_terms()[1].abs().max()) < 1e-12
    stack = Stack.ordered(["attenuation", truth["backscatter"].to_config(),
                           {"name": "tone_curve", "params": {"smoothness": 1e-9}}]).double()
    names = fitted_names(stack, config.fixed_effects, {})
    start_inside_bounds(stack, names)
    problem = Problem(stack, obs, config, names)
    with torch.no_grad():  # away from the truth, the board's residual is the slope-scaled linear one of a render
        rest, curve = stack.output_map()
        x, slope = curve.linearised(problem.board_y)
        direct = slope * (x - render_albedo(rest, problem.board_state, problem.board_j))
        assert torch.allclose(problem._board_terms()[1], direct, atol=1e-12) and float(direct.abs().max()) > 1e-3
    start = problem.minimise(0)
    problem.converge()
    assert problem.minimise(0) < 1e-4 * start
    np.testing.assert_allclose(stack["attenuation"].values()["eta_per_m"].numpy(), [0.5, 0.2, 0.1], rtol=0.02)
    signal = torch.linspace(0.02, 1.0, 50, dtype=F64)
    with torch.no_grad():
        fitted, true = (tone_curve(signal, s["tone_curve"].param("log_slope"), s["tone_curve"].param("log_profile"))
                        for s in (stack, truth))
    assert float((fitted - true).abs().max()) < 3e-3
