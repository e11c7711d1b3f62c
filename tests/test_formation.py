"""The effect library: every registered effect, the registry, stacks and physics sanity."""

import json
import math
import textwrap

import pytest
import torch
from conftest import make_state
from torch.func import functional_call

from watergan.formation import (
    Counts,
    Effect,
    MissingInputError,
    Param,
    ParameterError,
    PluginError,
    Stack,
    UnknownEffectError,
    available,
    builtin_effects,
    get,
    load_plugin,
)
from watergan.formation.water import EFFECTIVE_RGB_ATTENUATION_PER_M

BUILTINS = [
    "attenuation", "backscatter_conv", "backscatter", "vignetting", "gain",
    "vignetting_offcentre", "artificial_light", "sensor_response", "forward_scatter",
    "backscatter_coefficient", "wideband_attenuation", "caustics", "ambient_depth", "marine_snow",
]
#: The effect tests run over every built-in in the registry (one module each in
#: watergan/formation/effects/), so a new built-in is tested without touching this file; plugins that
#: other test modules register are left out.
EFFECTS = list(builtin_effects())


def run(effect: Effect, state):
    """Run an effect the way a stack does: `backscatter_coefficient` relates to `attenuation`'s beta_D."""
    if effect.name == "backscatter_coefficient":
        state = get("attenuation")()(state)
    return effect(state)


def test_all_fourteen_builtins_registered():
    names = available()
    assert set(BUILTINS) <= set(names)
    assert len(BUILTINS) == 14
    for name in EFFECTS:
        cls = names[name]
        assert cls.summary and cls.signature, name
        assert cls.axis in Effect.AXES, name
        # the equation lives in a module-level pure function with a docstring stating it
        module = __import__(cls.__module__, fromlist=["_"])
        funcs = [f for f in vars(module).values() if callable(f) and getattr(f, "__module__", "") == module.__name__
                 and not isinstance(f, type)]
        assert any(f.__doc__ and "=" in f.__doc__ for f in funcs), f"{name}: no pure function stating its equation"


def new(name: str):
    """A built-in made for a survey of 8 frames (``make_state``'s frame indices are 3 and 4), so that effects with a
    value per frame (``frame_gain``) have their rows."""
    return get(name)(counts=Counts(frames=8))


@pytest.mark.parametrize("name", EFFECTS)
def test_smoke_and_shapes(name):
    state = make_state(dtype=torch.float32)
    effect = new(name)
    out = run(effect, state)
    assert out.direct.shape == state.direct.shape
    assert out.backscatter.shape == state.direct.shape
    assert torch.isfinite(out.image).all()
    if name != "backscatter_conv":  # the paper's leaky ReLU lets the learned mask dip below zero
        assert (out.image >= 0).all(), "a physical image is non-negative"
    assert out.direct.dtype == torch.float32
    # geometry passes through untouched: stages change colour and intensity only
    assert out.range_m is state.range_m and out.pixel_uv is state.pixel_uv


@pytest.mark.parametrize("name", EFFECTS)
def test_identity_at_neutral(name):
    state = make_state()
    effect = new(name).double()
    effect.make_neutral()
    before = get("attenuation")()(state) if name == "backscatter_coefficient" else state
    out = effect(before)
    assert torch.allclose(out.image, before.image, atol=1e-6), name


AT_IDENTITY = ("gain", "image_field", "frame_gain", "image_grid")  # built-ins that start at the identity


@pytest.mark.parametrize("name", [n for n in EFFECTS if n not in AT_IDENTITY])
def test_not_identity_at_initial_values(name):
    """The converse of the identity test: at its initial values every effect changes the image."""
    state = make_state()
    effect = new(name).double()
    before = get("attenuation")()(state) if name == "backscatter_conv" or name == "backscatter_coefficient" \
        else state
    out = effect(before)
    assert (out.image - before.image).abs().max() > 1e-3, name


@pytest.mark.parametrize("name", EFFECTS)
def test_gradcheck_float64(name):
    torch.manual_seed(0)
    state = make_state(batch=2, height=5, width=6)
    effect = new(name).double()
    if name == "backscatter_conv":
        # the learned layers: check through the noise vector and the convolutions (the 100 -> 3072
        # projection is an ordinary Linear layer)
        targets = {k: v for k, v in effect.named_parameters() if k.startswith("convs.0")}
        extra = {"z": state.z.clone().requires_grad_()}
    else:
        targets = {k: v for k, v in effect.named_parameters() if v.requires_grad}
        extra = {}
    names = list(targets)
    # marine snow samples its particles' distances: they are drawn, not differentiable in range
    differentiable_range = name != "marine_snow"

    def f(direct, range_m, *values):
        params = dict(zip(names, values, strict=True))
        z = params.pop("z", state.z) if "z" in params else state.z
        s = state.replace(direct=direct, range_m=range_m if differentiable_range else state.range_m, z=z)
        return run_functional(effect, params, s).image

    def run_functional(module, params, s):
        if module.name == "backscatter_coefficient":
            s = get("attenuation")().double()(s)
        return functional_call(module, params, (s,), strict=False)

    inputs = [state.direct.clone().requires_grad_(), state.range_m.clone().requires_grad_()]
    inputs += [targets[k].detach().clone().requires_grad_() for k in names]
    if extra:
        names.append("z")
        inputs.append(extra["z"])
    assert torch.autograd.gradcheck(f, tuple(inputs), eps=1e-6, atol=1e-5, rtol=1e-3)


@pytest.mark.parametrize("name", EFFECTS)
def test_bounds_hold_for_random_raw_parameters(name):
    g = torch.Generator().manual_seed(1)
    effect = new(name)
    for _ in range(20):
        with torch.no_grad():
            for raw in effect.raw.values():
                if raw.requires_grad:
                    raw.copy_(torch.randn(raw.shape, generator=g, dtype=raw.dtype) * 30)
        for p in effect.params:
            value = effect.param(p.name)
            assert (value >= p.lower).all() and (value <= p.upper).all(), (name, p.name, value)


@pytest.mark.parametrize("name", ["vignetting", "vignetting_offcentre"])
def test_vignetting_constraint_holds_for_random_raw_parameters(name):
    """c >= 0 and 4b^2 - 12ac < 0 for raw values spanning the sigmoids' useful range (|raw| <~ 9;
    beyond it c underflows towards 0 and the discriminant cancels to rounding noise in float64)."""
    g = torch.Generator().manual_seed(2)
    effect = get(name)()
    for _ in range(200):
        with torch.no_grad():
            for raw in effect.raw.values():
                raw.copy_(torch.randn(raw.shape, generator=g, dtype=raw.dtype) * 3)
        a_margin, b, c = (effect.param(n) for n in ("a_margin", "b", "c"))
        a = b * b / (3 * c) + a_margin
        assert c >= 0 and 4 * b * b - 12 * a * c < 0


def test_vignetting_is_monotonic_and_constrained():
    from watergan.formation.effects.vignetting import vignetting_coefficients, vignetting_falloff

    r = torch.linspace(0, 1, 201, dtype=torch.float64)
    for b in (-3.0, -0.5, 0.0, 2.0):
        a, b_, c = vignetting_coefficients(torch.tensor(0.05), torch.tensor(b), torch.tensor(0.4))
        assert 4 * b_ ** 2 - 12 * a * c < 0
        v = 1 + vignetting_falloff(r, a, b_, c)
        assert (v[1:] > v[:-1]).all(), "V must rise monotonically from the centre"


def test_stack_json_round_trip_every_effect():
    stack = Stack.from_names(EFFECTS, counts=Counts(frames=8))
    config = stack.to_config()
    text = json.dumps(config)
    again = Stack.from_config(json.loads(text)).to_config()
    assert again == config
    assert [c["name"] for c in again] == EFFECTS


def test_user_config_round_trips_unchanged():
    config = [
        {"name": "attenuation", "params": {"eta_per_m": [0.21, 0.06, 0.025]}},
        {"name": "backscatter", "params": {"b_inf": [0.02, 0.15, 0.21], "beta_per_m": [0.5, 0.35, 0.3]}},
        {"name": "vignetting_offcentre", "params": {"centre_uv": [0.61, 0.44], "a_margin": 0.7, "b": -0.25,
                                                    "c": 0.125, "strength": [1.0, 0.9, 0.8]}},
        {"name": "artificial_light", "params": {"offset_m": [[0.4, 0.0, 0.1], [-0.4, 0.0, 0.1]],
                                                "tilt_deg": [[-10.0, 0.0], [10.0, 0.0]], "beam_deg": [30.0, 45.0],
                                                "power": [2.5, 3.0], "eta_per_m": [0.3, 0.2, 0.3],
                                                "ambient": 0.1}},
        {"name": "gain", "params": {"k": [1.7]}},
    ]
    assert Stack.from_config(json.dumps(config)).to_config() == config


def test_gain_accepts_one_value_or_per_channel():
    state = make_state()
    one = get("gain")(k=[2.0]).double()(state)
    three = get("gain")(k=[2.0, 2.0, 2.0]).double()(state)
    assert torch.allclose(one.image, three.image)
    with pytest.raises(ParameterError, match="shape"):
        get("gain")(k=[1.0, 2.0])


def test_long_range_tends_to_b_inf_and_zero_range_to_j():
    b_inf = [0.03, 0.16, 0.24]
    eta = [0.34, 0.24, 0.33]
    stack = Stack.from_config([{"name": "attenuation", "params": {"eta_per_m": eta}},
                               {"name": "backscatter", "params": {"b_inf": b_inf, "beta_per_m": eta}}]).double()
    far = make_state(range_m=300.0)
    assert torch.allclose(stack.render(far), torch.tensor(b_inf, dtype=torch.float64).view(1, 3, 1, 1)
                          .expand_as(far.direct), atol=1e-9)
    near = make_state(range_m=0.0)
    assert torch.allclose(stack.render(near), near.direct, atol=1e-12)
    # with beta_B = beta_D the image in between is the blend t J + (1 - t) B_inf, t = exp(-eta r)
    t = torch.exp(-torch.tensor(eta, dtype=torch.float64) * 3.0).view(1, 3, 1, 1)
    mid = stack.render(make_state(range_m=3.0))
    b = torch.tensor(b_inf, dtype=torch.float64).view(1, 3, 1, 1)
    assert torch.allclose(mid, t * near.direct + (1 - t) * b, atol=1e-12)


def test_red_decays_fastest_in_ocean_water():
    eta = EFFECTIVE_RGB_ATTENUATION_PER_M["I"]
    effect = get("attenuation")(eta_per_m=eta).double()
    white = make_state(range_m=5.0).replace(direct=torch.ones(2, 3, 6, 8, dtype=torch.float64))
    out = effect(white).image.mean(dim=(0, 2, 3))
    assert out[0] < out[1] < out[2]
    assert math.isclose(out[0].item(), math.exp(-eta[0] * 5.0), rel_tol=1e-9)


def test_artificial_light_falls_with_distance_and_off_axis():
    light = get("artificial_light")(offset_m=[[0.0, 0.0, 0.0]], power=[1.0], eta_per_m=[0.0, 0.0, 0.0]).double()
    s = make_state(range_m=2.0)
    flat = s.replace(direct=torch.ones_like(s.direct), normals_cam=-s.points_cam / s.range_m)
    near = light(flat.replace(points_cam=flat.points_cam / 2)).image
    far = light(flat).image
    # inverse square: half the distance, four times the irradiance (same angles, normal incidence)
    assert torch.allclose(near, 4 * far, rtol=1e-6)
    centre = far[0, 0, 2:4, 3:5].mean()
    corner = far[0, 0, 0, 0]
    assert corner < centre


def test_backscatter_coefficient_needs_attenuation_first():
    with pytest.raises(MissingInputError, match="beta_d_per_m"):
        get("backscatter_coefficient")().double()(make_state())


def test_effect_needing_missing_field_says_which():
    s = make_state().replace(water_depth_m=None)
    with pytest.raises(MissingInputError, match="ambient_depth.*water_depth_m"):
        get("ambient_depth")().double()(s)


def test_unknown_effect_is_a_clear_error():
    with pytest.raises(UnknownEffectError, match="unknown effect 'vignetting_offcenter'.*vignetting_offcentre"):
        Stack.from_names(["attenuation", "vignetting_offcenter"])


@pytest.mark.parametrize("params, match", [
    ({"eta_per_m": [0.3, -0.1, 0.2]}, r"attenuation.eta_per_m .* out of its bounds \[0.0, 5.0\] 1/m"),
    ({"eta_per_m": [0.3, float("nan"), 0.2]}, "not finite"),
    ({"eta_per_m": [0.3, 0.2]}, "shape"),
    ({"eta": [0.3, 0.2, 0.1]}, "has no parameter"),
])
def test_bad_parameter_is_a_clear_error(params, match):
    with pytest.raises(ParameterError, match=match):
        Stack.from_config([{"name": "attenuation", "params": params}])


def test_repeated_effect_is_refused():
    with pytest.raises(ParameterError, match="repeated"):
        Stack.from_names(["gain", "gain"])


def test_every_module_of_the_effects_folder_is_a_registered_builtin():
    from pathlib import Path

    import watergan.formation.effects as effects

    files = {p.stem for p in Path(effects.__file__).parent.glob("*.py") if p.stem != "__init__"}
    assert {cls.__module__.rsplit(".", 1)[1] for cls in builtin_effects().values()} == files


def test_stack_orders_by_rank_and_inserts_by_rank():
    entries = ["gain", {"name": "vignetting"}, "attenuation", "vignetting_offcentre", "artificial_light"]
    assert Stack.rank_order(entries) == ["artificial_light", "attenuation", {"name": "vignetting"},
                                         "vignetting_offcentre", "gain"]  # stable among equal ranks
    assert Stack.ordered(entries).names == ["artificial_light", "attenuation", "vignetting",
                                            "vignetting_offcentre", "gain"]
    base = Stack.from_names(["attenuation", "vignetting", "gain"])
    grown = base.with_effect(get("vignetting_offcentre")()).with_effect(get("caustics")())
    assert grown.names == ["caustics", "attenuation", "vignetting", "vignetting_offcentre", "gain"]
    assert grown["gain"] is base["gain"] and base.names == ["attenuation", "vignetting", "gain"]


def test_effect_declarations_default_to_nothing_declared():
    assert Effect.start_grid == {} and Effect.simulation_params == {} and Effect.rig_params == ()
    light = get("artificial_light")
    assert set(light.rig_params) <= {p.name for p in light.params}
    for name, cls in builtin_effects().items():
        spec = {p.name for p in cls.params}
        assert set(cls.start_grid) <= spec and set(cls.simulation_params) <= spec, name
        cls(counts=Counts(frames=8), **cls.simulation_params)  # the simulated values are valid


def test_plugin_registers_a_user_effect(tmp_path):
    plugin = tmp_path / "my_haze.py"
    plugin.write_text(textwrap.dedent('''
        import torch
        from watergan.formation import Effect, Param, register

        def haze(direct, strength):
            """D = J + s: a flat haze (units of J)."""
            return direct + strength

        @register
        class TestHaze(Effect):
            name = "test_haze_plugin"
            summary = "flat haze"
            signature = "intensity: constant offset"
            axis = "intensity"
            params = (Param("strength", 0.1, 0.0, 1.0, ""),)
            neutral = {"strength": 0.0}

            def forward(self, state):
                return state.replace(direct=haze(state.direct, self.param("strength", state.direct)))
    '''))
    assert load_plugin(plugin) == ["test_haze_plugin"]
    stack = Stack.from_names(["attenuation", "test_haze_plugin"]).double()
    s = make_state(range_m=0.0)
    assert torch.allclose(stack.render(s), s.direct + 0.1)
    assert Stack.from_config(stack.to_config()).to_config() == stack.to_config()


def test_plugin_with_errors_is_reported(tmp_path):
    broken = tmp_path / "broken.py"
    broken.write_text("import torch\ndef oops(:\n    pass\n")
    with pytest.raises(PluginError, match="broken.py failed to import: SyntaxError"):
        load_plugin(broken)
    empty = tmp_path / "empty.py"
    empty.write_text("x = 1\n")
    with pytest.raises(PluginError, match="registered no effect"):
        load_plugin(empty)
    with pytest.raises(PluginError, match="does not exist"):
        load_plugin(tmp_path / "missing.py")


def test_state_from_rgbd_geometry_of_a_tilted_plane():
    """Points, range and normals from depth: a plane z = 2 + 0.5 x (camera frame) has the normal
    (0.5, 0, -1)/|.| facing the camera everywhere, and range = |points|."""
    from watergan.formation import state_from_rgbd

    h, w, f = 12, 16, 20.0
    xs = (torch.arange(w, dtype=torch.float64) - 7.5) / f
    # on the plane z = 2 + 0.5 x with x = z * xs: z = 2 / (1 - 0.5 xs)
    depth = (2.0 / (1 - 0.5 * xs)).expand(h, w)[None, None].clone()
    s = state_from_rgbd(torch.ones(1, 3, h, w, dtype=torch.float64), depth, f, f, 7.5, 5.5)
    expected = torch.tensor([0.5, 0.0, -1.0], dtype=torch.float64) / math.sqrt(1.25)
    assert torch.allclose(s.normals_cam[0, :, 1:-1, 1:-1], expected.view(3, 1, 1).expand(3, h - 2, w - 2), atol=1e-9)
    assert torch.allclose(s.range_m, s.points_cam.norm(dim=1, keepdim=True))
    assert torch.allclose(s.points_cam[:, 2:3], depth)
    with pytest.raises(ValueError, match="NaN"):
        state_from_rgbd(torch.ones(1, 3, h, w), depth.float() * float("nan"), f, f, 7.5, 5.5)


def test_entry_point_group_registers_a_packaged_effect(tmp_path, monkeypatch):
    """A package that declares an effect in the `watergan.effects` entry-point group is found."""
    from watergan.formation import registry

    (tmp_path / "ep_effect_pkg.py").write_text(textwrap.dedent('''
        from watergan.formation import Effect, Param

        def dim(direct, f):
            """D = f J (unitless f)."""
            return direct * f

        class Dim(Effect):
            name = "test_dim_entry_point"
            summary = "dims"
            signature = "intensity: uniform"
            axis = "intensity"
            params = (Param("f", 0.5, 0.0, 1.0, ""),)
            neutral = {"f": 1.0}

            def forward(self, state):
                return state.replace(direct=dim(state.direct, self.param("f", state.direct)))
    '''))
    dist = tmp_path / "ep_effect_pkg-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: ep-effect-pkg\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\ndim = ep_effect_pkg:Dim\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(registry, "_entry_points_loaded", False)
    assert "test_dim_entry_point" in available()
    s = make_state()
    assert torch.allclose(Stack.from_names(["test_dim_entry_point"]).double().render(s), 0.5 * s.direct)


class _FrameOffset(Effect):
    """A per-frame effect made in the test (not registered): each frame's signal scaled by exp(g_k)."""

    name = "test_frame_offset"
    axis = "frame"
    params = (Param("log_gain", (0.0, 0.0, 0.0), -1.0, 1.0, "", "per channel, per frame", per="frame"),)

    def forward(self, state):
        return state.replace(direct=state.direct * torch.exp(self.per_frame("log_gain", state))[..., None, None])


def test_per_frame_parameter_is_sized_by_the_survey_and_read_by_frame_index(state):
    effect = _FrameOffset(Counts(frames=5))
    assert effect.param("log_gain").shape == (5, 3) and not effect.param("log_gain").any()
    effect.set_values(log_gain=[[0.1 * k] * 3 for k in range(5)])
    out = effect(state)  # the conftest state's frames are 3 and 4
    for b, k in enumerate(state.frame_index.tolist()):
        assert torch.allclose(out.direct[b], state.direct[b] * math.exp(0.1 * k))
    assert _FrameOffset(log_gain=[[0.0] * 3] * 9).param("log_gain").shape == (9, 3)  # given: any number of frames
    with pytest.raises(ParameterError, match="one value per survey frame"):
        _FrameOffset()
    with pytest.raises(ParameterError, match=r"holds 2 frames' values; the data has frame 4"):
        _FrameOffset(Counts(frames=2))(state)
    with pytest.raises(ParameterError, match=r"expected \(N frames, 3\)"):
        _FrameOffset(log_gain=[0.0, 0.0, 0.0])
    assert "log_gain = (0.0, 0.0, 0.0) per frame" in _FrameOffset.describe()


def test_per_light_parameters_take_one_row_per_declared_light():
    light = get("artificial_light")(Counts(lights=2))
    assert light.param("offset_m").shape == (2, 3)
    assert torch.allclose(light.param("power"), torch.tensor([4.0, 4.0], dtype=torch.float64))
    assert get("artificial_light")().param("offset_m").shape == (1, 3)  # no count: one light
    stack = Stack.from_names(["artificial_light"], Counts(frames=7, lights=3))
    assert stack["artificial_light"].param("beam_deg").shape == (3,)


def test_vector_length_is_torch_s_norm():
    """The lengths of 3-vectors along a leading dimension equal torch's norm to rounding."""
    from watergan.formation.state import vector_length

    t = torch.randn(2, 3, 5, 7, dtype=torch.float64)
    torch.testing.assert_close(vector_length(t, 1), t.norm(dim=1, keepdim=True), rtol=1e-15, atol=1e-15)
    torch.testing.assert_close(vector_length(t[0], 0), t[0].norm(dim=0, keepdim=True), rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("smooth_px", [4.0, 24.0])
def test_normals_from_range_give_a_tilted_planes_normal_and_no_range_stays_none(smooth_px):
    """A plane z = z0 + a x (camera frame) seen through a pinhole: its normal (a, 0, -1) / |.| within 0.3 degrees
    away from the image's border, whether smoothed at full resolution (4 px) or on the coarser grid (24 px); a hole
    in the range stays NaN."""
    import numpy as np

    from watergan.formation.inverse import normals_from_range, rays_cam

    h, w, f, z0, a = 240, 320, 300.0, 2.0, 0.4
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    rays = rays_cam(K, h, w)
    range_m = z0 / (1 - a * rays[..., 0] / rays[..., 2]) * np.linalg.norm(rays / rays[..., 2:], axis=-1)
    truth = np.array([a, 0.0, -1.0]) / math.hypot(a, 1.0)
    inner = normals_from_range(range_m, K, smooth_px)[60:-60, 60:-60]
    assert np.degrees(np.arccos(np.clip(inner @ truth, -1.0, 1.0))).max() < 0.3
    range_m[100:120, 150:170] = np.nan
    normals = normals_from_range(range_m, K, smooth_px)
    assert np.isnan(normals[100:120, 150:170]).all() and np.isfinite(normals[:100]).all()
