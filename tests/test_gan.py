"""WaterGAN: generator structure and alignment, discriminator, training steps, checkpoints, resume,
full-resolution generation and the CLI commands."""

import argparse
import json

import cv2
import numpy as np
import pytest
import torch

from watergan.data import PinholeIntrinsics, read_depth, write_depth_png, write_srgb8
from watergan.errors import UserInputError
from watergan.formation import Effect, Param, Stack, register
from watergan.formation.effects.vignetting import vignetting_coefficients
from watergan.generate import GenerateConfig, generate, load_generator
from watergan.nets.discriminator import Discriminator
from watergan.nets.generator import DEFAULT_EFFECTS, WaterGenerator, generator_stack_config, select_state
from watergan.train import GanConfig, build_gan, generator_param_groups, load_checkpoint, train_gan
from watergan.water_record import WaterRecord, write_water

HW = (24, 32)
TRUTH = [{"name": "attenuation", "params": {"eta_per_m": [0.5, 0.15, 0.2]}},
         {"name": "backscatter", "params": {"b_inf": [0.03, 0.15, 0.2]}},
         {"name": "vignetting", "params": {"a_margin": 0.35}},
         {"name": "gain", "params": {"k": [1.4, 1.4, 1.4]}}]


@register
class UserTint(Effect):
    """A user's own effect (as a plugin file would register it): a per-channel offset."""

    name = "test_gan_tint"
    summary = "adds a constant colour"
    signature = "intensity: a constant offset"
    axis = "intensity"
    params = (Param("offset", (0.0, 0.0, 0.0), -0.5, 0.5, "linear radiance", "added colour"),)
    neutral = {"offset": (0.0, 0.0, 0.0)}
    rank = 55

    def forward(self, state):
        return state.replace(direct=state.direct + self.param("offset", state.direct).view(1, 3, 1, 1))


def blocks(seed: int, h: int, w: int) -> np.ndarray:
    """A structured in-air image: random colour blocks (strong edges), linear 0.05..0.95."""
    rng = np.random.default_rng(seed)
    return (0.05 + 0.9 * rng.random((6, 8, 3))).repeat(h // 6, 0).repeat(w // 8, 1)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """8 in-air RGB-D frames (48x64) and 8 underwater frames rendered with the known TRUTH stack."""
    root = tmp_path_factory.mktemp("gan_data")
    for sub in ("rgbd/rgb", "rgbd/depth", "water"):
        (root / sub).mkdir(parents=True)
    truth = Stack.from_config(TRUTH)
    for i in range(8):
        rgb = blocks(i, 48, 64)
        depth = 1.0 + 3.0 * np.linspace(0, 1, 64)[None, :].repeat(48, 0) + 0.5 * (i % 3)
        write_srgb8(root / "rgbd" / "rgb" / f"{i:03d}.png", rgb)
        write_depth_png(root / "rgbd" / "depth" / f"{i:03d}.png", depth)
        generator = WaterGenerator(truth)
        with torch.no_grad():
            water = generator(torch.from_numpy(blocks(i + 100, 48, 64).transpose(2, 0, 1)).float()[None],
                              torch.from_numpy(depth).float()[None, None], torch.zeros(1, 100))
        write_srgb8(root / "water" / f"{i:03d}.png", water[0].numpy().transpose(1, 2, 0))
    return root


def small_config(data_dir, out, **changes) -> GanConfig:
    base = dict(rgbd_dir=data_dir / "rgbd", underwater_dir=data_dir / "water", out_dir=out, image_hw=HW,
                batch_size=8, disc_width=8, iterations=2, budget_min=None, progress=False, checkpoint_every=1)
    base.update(changes)
    return GanConfig(**base)


def sobel_magnitude(image: torch.Tensor) -> np.ndarray:
    grey = image.mean(dim=1)[0].detach().numpy().astype(np.float64)
    return np.hypot(cv2.Sobel(grey, cv2.CV_64F, 1, 0), cv2.Sobel(grey, cv2.CV_64F, 0, 1))


# --------------------------------------------------------------------------------------------- generator
def test_generator_stack_default_and_ranked_additions():
    assert WaterGenerator.build().stack.names == list(DEFAULT_EFFECTS)
    names = [c["name"] for c in generator_stack_config(["gain", "vignetting", "attenuation", "backscatter_conv",
                                                        "test_gan_tint", "backscatter"])]
    assert names == ["attenuation", "backscatter_conv", "backscatter", "vignetting", "test_gan_tint", "gain"]
    conv = WaterGenerator.build(depth_scale_m=7.5, mask_hw=HW).stack["backscatter_conv"]
    assert conv.param("depth_scale_m").item() == pytest.approx(7.5) and conv.mask_hw == HW


def test_generator_bounded_and_aligned_with_input():
    torch.manual_seed(0)
    generator = WaterGenerator.build(depth_scale_m=5.0)
    rgb = torch.from_numpy(blocks(1, 48, 64).transpose(2, 0, 1)).float()[None].repeat(4, 1, 1, 1)
    depth = torch.linspace(1.0, 4.5, 64).view(1, 1, 1, 64).expand(4, 1, 48, 64).contiguous()
    out = generator(rgb, depth, torch.rand(4, 100) * 2 - 1)
    assert out.shape == rgb.shape and out.min() >= 0 and out.max() <= 1
    for k in range(4):
        corr = np.corrcoef(sobel_magnitude(rgb[k:k + 1]).ravel(), sobel_magnitude(out[k:k + 1]).ravel())[0, 1]
        assert corr > 0.9, corr
    # the water changes colour: red falls most with range
    assert (out[:, 0] / rgb[:, 0]).mean() < (out[:, 1] / rgb[:, 1]).mean()


def test_generator_with_intrinsics_uses_ray_range():
    generator = WaterGenerator.build(["attenuation"])
    rgb, depth = torch.full((1, 3, 48, 64), 0.5), torch.full((1, 1, 48, 64), 2.0)
    k = PinholeIntrinsics(40.0, 40.0, 31.5, 23.5, 64, 48).as_tuple()
    plain, rays = generator(rgb, depth, torch.zeros(1, 100)), generator(rgb, depth, torch.zeros(1, 100), k)
    assert torch.allclose(plain[..., 24, 32], rays[..., 24, 32], atol=2e-3)
    assert (rays[..., 0, 0] < plain[..., 0, 0]).all()  # corners: longer ray, more attenuation


def test_selected_state_renders_like_a_fresh_one():
    """Training builds the dataset's state once and selects batches from it: same images as the
    state built from the batch itself."""
    torch.manual_seed(0)
    generator = WaterGenerator.build(depth_scale_m=5.0).eval()
    rgb, depth = torch.rand(6, 3, 48, 64), 1 + 3 * torch.rand(6, 1, 48, 64)
    k = PinholeIntrinsics(40.0, 40.0, 31.5, 23.5, 64, 48).as_tuple()
    index, z = torch.tensor([4, 1, 1]), torch.rand(3, 100) * 2 - 1
    whole = generator.state(rgb, depth, None, k)
    with torch.no_grad():
        assert torch.allclose(generator.render(select_state(whole, index, z=z)),
                              generator(rgb[index], depth[index], z, k), atol=1e-6)


def test_discriminator_shape_and_layers():
    d = Discriminator(width=8)
    convs = [m for m in d.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs] == [8, 16, 32, 64] and all(c.kernel_size == (5, 5) for c in convs)
    assert all(c.stride == (2, 2) for c in convs)
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in d.modules()) == 3
    assert d(torch.rand(5, 3, 48, 64)).shape == (5,)
    assert Discriminator().logit.in_features == 512 * 3 * 4


# ---------------------------------------------------------------------------------------------- training
def test_two_steps_change_params_files_and_constraint(data_dir, tmp_path):
    result = train_gan(small_config(data_dir, tmp_path, effects=DEFAULT_EFFECTS + ("test_gan_tint",)))
    assert result.steps == 2 and result.stopped_by == "iterations"
    initial = WaterGenerator.build(DEFAULT_EFFECTS + ("test_gan_tint",)).physical_values()
    for name, value in result.params.items():
        assert not np.allclose(value, initial[name].numpy()), name  # every learned parameter moved
    assert "test_gan_tint.offset" in result.params  # a user's effect is trained
    for name in ("checkpoint.pt", "stack.json", "train_log.jsonl", "training.png", "result.json",
                 "samples/step_000002.png"):
        assert (tmp_path / name).is_file(), name
    rows = [json.loads(line) for line in (tmp_path / "train_log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    assert set(rows[0]["params"]) == set(result.params) and all(np.isfinite(r["d_loss"]) for r in rows)
    stack = Stack.load(tmp_path / "stack.json")
    a, b, c = vignetting_coefficients(*(stack["vignetting"].param(n) for n in ("a_margin", "b", "c")))
    assert c >= 0 and 4 * b * b - 12 * a * c < 0
    assert list(tmp_path.glob(".*tmp*")) == []


def test_param_groups_fast_physics():
    generator = WaterGenerator.build()
    slow, fast = generator_param_groups(generator, 2e-4, 1e-2)
    assert fast["lr"] == 1e-2 and slow["lr"] == 2e-4
    assert len(fast["params"]) == 5  # eta, a_margin, b, c, k
    assert sum(p.numel() for p in slow["params"]) > 100 * 48 * 64  # z projection and convolutions
    norm = generator.stack["backscatter_conv"].norm
    slow, fast, level, spread = generator_param_groups(generator, 2e-4, 1e-2, 2e-3, 5e-4)
    assert level["lr"] == 2e-3 and level["params"] == [norm.bias]  # the veil's level, 3 channels
    assert spread["lr"] == 5e-4 and spread["params"] == [norm.weight]  # its spread
    ids = [id(p) for group in (slow, fast, level, spread) for p in group["params"]]
    assert len(ids) == len(set(ids)) == sum(1 for p in generator.parameters() if p.requires_grad)


def test_checkpoint_round_trip(data_dir, tmp_path):
    train_gan(small_config(data_dir, tmp_path, iterations=1))
    checkpoint = load_checkpoint(tmp_path / "checkpoint.pt")
    assert checkpoint["step"] == 1 and checkpoint["stack"] == json.loads((tmp_path / "stack.json").read_text())
    loaded = load_generator(tmp_path)
    again = WaterGenerator.from_config(checkpoint["stack"])
    again.load_state_dict(checkpoint["generator"])
    rgb, depth, z = torch.rand(2, 3, *HW), 1 + torch.rand(2, 1, *HW), torch.rand(2, 100) * 2 - 1
    with torch.no_grad():
        assert torch.equal(loaded(rgb, depth, z), again.eval()(rgb, depth, z))
    disc = Discriminator(8, HW)
    disc.load_state_dict(checkpoint["discriminator"])
    assert {"opt_g", "opt_d", "rng", "depth_scale_m", "config"} <= set(checkpoint)


def test_resume_continues_the_same_run(data_dir, tmp_path):
    whole = train_gan(small_config(data_dir, tmp_path / "whole", iterations=4, checkpoint_every=2))
    train_gan(small_config(data_dir, tmp_path / "parts", iterations=2, checkpoint_every=2))
    resumed = train_gan(small_config(data_dir, tmp_path / "parts", iterations=4, checkpoint_every=2, resume=True))
    assert resumed.steps == 4

    def rows(folder):
        return [{k: v for k, v in json.loads(line).items() if k != "seconds"}
                for line in (folder / "train_log.jsonl").read_text().splitlines()]

    assert rows(tmp_path / "whole") == rows(tmp_path / "parts")
    assert whole.params == resumed.params
    a, b = load_checkpoint(tmp_path / "whole" / "checkpoint.pt"), load_checkpoint(tmp_path / "parts" / "checkpoint.pt")
    for key in ("generator", "discriminator"):
        assert all(torch.equal(a[key][n], b[key][n]) for n in a[key])
    assert torch.equal(a["rng"], b["rng"])


def test_training_config_errors(data_dir, tmp_path):
    with pytest.raises(UserInputError, match="limit"):
        train_gan(small_config(data_dir, tmp_path, iterations=None))
    with pytest.raises(UserInputError, match="at least 1"):
        train_gan(small_config(data_dir, tmp_path, batch_size=0))
    train_gan(small_config(data_dir, tmp_path, iterations=1))
    with pytest.raises(UserInputError, match="same effects"):
        train_gan(small_config(data_dir, tmp_path, iterations=2, resume=True, effects=("attenuation", "gain")))


# -------------------------------------------------------------------------------------- generation and CLI
def test_generate_full_resolution_paired_dataset(data_dir, tmp_path):
    train_gan(small_config(data_dir, tmp_path / "model", iterations=1))
    result = generate(GenerateConfig(model_dir=tmp_path / "model", rgbd_dir=data_dir / "rgbd",
                                     out_dir=tmp_path / "gen", size_hw=(96, 128), progress=False))
    assert result.count == 8 and result.skipped == []
    manifest = json.loads((tmp_path / "gen" / "manifest.json").read_text())
    assert manifest["count"] == 8 and [s["name"] for s in manifest["stack"]] == list(DEFAULT_EFFECTS)
    item = manifest["items"][0]
    underwater = cv2.imread(str(tmp_path / "gen" / item["underwater"]), cv2.IMREAD_UNCHANGED)
    inair = cv2.imread(str(tmp_path / "gen" / item["inair"]), cv2.IMREAD_UNCHANGED)
    assert underwater.shape == inair.shape == (96, 128, 3) and underwater.dtype == np.uint8
    depth = read_depth(tmp_path / "gen" / item["depth"])
    assert depth.shape == (96, 128) and 1.0 <= depth.min() and depth.max() <= 5.0
    grey = [cv2.cvtColor(x, cv2.COLOR_BGR2GRAY).astype(np.float64) for x in (inair, underwater)]
    edges = [np.hypot(cv2.Sobel(g, cv2.CV_64F, 1, 0), cv2.Sobel(g, cv2.CV_64F, 0, 1)).ravel() for g in grey]
    assert np.corrcoef(*edges)[0, 1] > 0.9
    assert list((tmp_path / "gen").rglob(".*tmp*")) == []


def test_cli_train_and_generate(data_dir, tmp_path):
    from pipeline.cli_gan import add_commands

    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(dest="command", required=True), [])
    args = parser.parse_args(["train-gan", "--rgbd-dir", str(data_dir / "rgbd"),
                              "--underwater-dir", str(data_dir / "water"), "--out-dir", str(tmp_path / "m"),
                              "--iterations", "1", "--batch-size", "4", "--disc-width", "4", "--add", "test_gan_tint"])
    assert args.func(args) == 0
    assert "test_gan_tint" in (tmp_path / "m" / "stack.json").read_text()
    args = parser.parse_args(["generate", "--model-dir", str(tmp_path / "m"), "--rgbd-dir", str(data_dir / "rgbd"),
                              "--out-dir", str(tmp_path / "g"), "--size-hw", "30x40"])
    assert args.func(args) == 0
    assert cv2.imread(str(tmp_path / "g" / "underwater" / "000.png")).shape == (30, 40, 3)
    with pytest.raises(SystemExit):
        parser.parse_args(["generate", "--model-dir", "m", "--rgbd-dir", "r", "--out-dir", "o", "--size-hw", "big"])


def test_augment_is_a_flip_and_shift_of_each_image():
    from torch.nn.functional import pad

    from watergan.train import augment

    images = torch.rand(6, 3, 16, 24)
    out = augment(images, torch.Generator().manual_seed(0))
    assert out.shape == images.shape
    dy, dx = 2, 3  # 1/8 of each side
    for image, result in zip(images, out, strict=True):
        candidates = [pad(f[None], (dx, dx, dy, dy), mode="reflect")[0][:, oy:oy + 16, ox:ox + 24]
                      for f in (image, image.flip(-1), image.flip(-2), image.flip(-1).flip(-2))
                      for oy in range(2 * dy + 1) for ox in range(2 * dx + 1)]
        assert any(torch.equal(result, c) for c in candidates)
    flat = torch.full((4, 3, 16, 24), 0.3)
    assert torch.equal(augment(flat, torch.Generator().manual_seed(1)), flat)  # colour untouched


def test_init_from_data_recovers_the_linear_water_map():
    """Real frames rendered with a known eta, veil and gain from textured in-air views at one range: the
    initial eta differs between channels as the truth does, the veil level and k T match."""
    from watergan.train import init_from_data

    g = torch.Generator().manual_seed(0)
    air = (0.2 + 0.5 * torch.rand(48, 3, 24, 32, generator=g)) * torch.tensor([1.0, 0.8, 0.5]).view(1, 3, 1, 1)
    depth = torch.full((48, 1, 24, 32), 2.5)
    truth = WaterGenerator.build(("attenuation", "backscatter_conv", "gain"), depth_scale_m=3.0)
    truth.stack["attenuation"].set_values(eta_per_m=[0.45, 0.14, 0.2])
    truth.stack["gain"].set_values(k=[1.5])
    with torch.no_grad():
        truth.stack["backscatter_conv"].norm.weight.zero_()
        truth.stack["backscatter_conv"].norm.bias.copy_(torch.tensor([0.02, 0.09, 0.11]))
    real = truth.eval()(air, depth, torch.zeros(48, truth.z_dim))
    fresh = WaterGenerator.build(("attenuation", "backscatter_conv", "gain"), depth_scale_m=3.0)
    values = init_from_data(fresh, air, depth, real, None)
    eta = np.array(values["attenuation.eta_per_m"])
    np.testing.assert_allclose(eta - eta.mean(), np.array([0.45, 0.14, 0.2]) - 0.79 / 3, atol=0.01)
    k = values["gain.k"][0]
    np.testing.assert_allclose(k * np.exp(-eta * 2.5), 1.5 * np.exp(-np.array([0.45, 0.14, 0.2]) * 2.5), rtol=0.03)
    np.testing.assert_allclose(k * np.array(values["veil_level"]), 1.5 * np.array([0.02, 0.09, 0.11]), atol=0.01)


@pytest.mark.parametrize("adversarial", [False, True])
def test_adversarial_physics_decides_whether_the_discriminator_moves_the_water(data_dir, tmp_path, adversarial):
    """One generator step against two different discriminators (widths 8 and 16): the learned physical
    values are identical when only the colour statistics move them, and differ when the discriminator
    does too (settling after training is left out: it starts from the two runs' different veil layers)."""
    params = []
    for width in (8, 16):
        result = train_gan(small_config(data_dir, tmp_path / f"w{width}", iterations=1, gen_steps_per_disc_step=1,
                                        disc_width=width, adversarial_physics=adversarial, settle_steps=0))
        params.append(np.concatenate([np.ravel(v) for v in result.params.values()]))
    start = WaterGenerator.build().physical_values()
    assert not np.allclose(params[0][:3], np.ravel(start["attenuation.eta_per_m"].numpy()))  # it moved
    assert np.array_equal(params[0], params[1]) != adversarial


def test_statistics_only_needs_a_moment_term(data_dir, tmp_path):
    with pytest.raises(UserInputError, match="nothing moves the physical parameters"):
        train_gan(small_config(data_dir, tmp_path, moment_weight=0.0, adversarial_physics=False))


def test_recolour_keeps_grey_and_brightness_and_changes_hue():
    from watergan.generate import recolour

    rng = np.random.default_rng(0)
    grey = np.full((20, 30, 3), 0.4)
    np.testing.assert_allclose(recolour(grey, rng), grey, atol=1e-12)
    image = 0.3 + 0.1 * np.random.default_rng(1).random((20, 30, 3))  # low chroma: nothing clips
    out = recolour(image, rng)
    np.testing.assert_allclose(out.mean(axis=2), image.mean(axis=2), atol=1e-9)  # the grey component is kept
    chroma_in, chroma_out = image - image.mean(2, keepdims=True), out - out.mean(2, keepdims=True)
    cosine = (chroma_in * chroma_out).sum(2) / np.linalg.norm(chroma_in, axis=2) / np.linalg.norm(chroma_out, axis=2)
    assert cosine.min() < 0.5  # hues turned by more than 60 degrees somewhere


def test_generate_recolours_the_asked_fraction(data_dir, tmp_path):
    train_gan(small_config(data_dir, tmp_path / "model", iterations=1))
    for fraction, expected in ((0.0, 0), (1.0, 8)):
        generate(GenerateConfig(model_dir=tmp_path / "model", rgbd_dir=data_dir / "rgbd",
                                out_dir=tmp_path / f"g{fraction}", recolour_fraction=fraction, progress=False))
        manifest = json.loads((tmp_path / f"g{fraction}" / "manifest.json").read_text())
        assert sum(item["recoloured"] for item in manifest["items"]) == expected
    with pytest.raises(UserInputError, match="recolour_fraction"):
        generate(GenerateConfig(model_dir=tmp_path / "model", rgbd_dir=data_dir / "rgbd", out_dir=tmp_path / "bad",
                                recolour_fraction=1.5, progress=False))
    assert not (tmp_path / "bad").exists()  # refused before anything is written
    plain = cv2.imread(str(tmp_path / "g0.0" / "inair" / "000.png"))
    coloured = cv2.imread(str(tmp_path / "g1.0" / "inair" / "000.png"))
    assert plain.shape == coloured.shape and np.abs(plain.astype(int) - coloured.astype(int)).mean() > 3


def test_the_papers_loss_alone_trains(data_dir, tmp_path):
    """moment_weight 0 with the discriminator moving the physics: the paper's generator loss."""
    result = train_gan(small_config(data_dir, tmp_path, moment_weight=0.0, adversarial_physics=True))
    assert result.steps == 2 and np.isfinite(result.g_loss)


def test_settle_matches_the_statistics_and_moves_only_the_physics():
    """Full-batch settling against frames of a nearby water brings the colour-statistics term down by far; the
    learned veil layers and batch norm's running statistics stay as they were."""
    from watergan.train import settle_statistics

    g = torch.Generator().manual_seed(1)
    air = 0.2 + 0.6 * torch.rand(16, 3, 24, 32, generator=g)
    depth = 2.0 + torch.rand(16, 1, 1, 1, generator=g).expand(16, 1, 24, 32)
    truth = WaterGenerator.build(DEFAULT_EFFECTS, depth_scale_m=3.0).eval()
    truth.stack["attenuation"].set_values(eta_per_m=[0.45, 0.14, 0.2])
    with torch.no_grad():
        real = truth(air, depth, torch.zeros(16, truth.z_dim))
    fresh = WaterGenerator.build(DEFAULT_EFFECTS, depth_scale_m=3.0)  # water near the truth, as after training
    fresh.stack["attenuation"].set_values(eta_per_m=[0.5, 0.2, 0.25])
    fresh.stack["gain"].set_values(k=[1.2])
    state = fresh.state(air, depth, None)
    fixed = {n: v.clone() for n, v in fresh.state_dict().items() if "convs" in n or "project" in n or "running" in n}
    trains = {n: p.requires_grad for n, p in fresh.named_parameters()}
    before = settle_statistics(fresh, state, real, 0, 1000.0, seed=0)
    after = settle_statistics(fresh, state, real, 150, 1000.0, seed=0)
    assert after < 0.05 * before, (before, after)
    assert all(torch.equal(fresh.state_dict()[n], v) for n, v in fixed.items())
    assert fresh.training  # its mode and which parameters train are given back
    assert {n: p.requires_grad for n, p in fresh.named_parameters()} == trains
    assert not all(trains.values())  # fixed settings stay fixed


# ------------------------------------------------------------------------------------------- site water
def write_water_json(path, stack=TRUTH, half_width=0.1):
    """A water stage's water.json holding ``stack`` with a 95 % interval of +-``half_width`` (relative) around
    each value (the gain marked not fitted, as without a board)."""
    params = {}
    for entry in stack:
        for name, value in entry["params"].items():
            v = np.atleast_1d(np.asarray(value, float))
            params[f"{entry['name']}.{name}"] = {"value": v.tolist(), "low": (v - half_width * np.abs(v)).tolist(),
                                                 "high": (v + half_width * np.abs(v)).tolist(),
                                                 "fitted": entry["name"] != "gain"}
    write_water(path, WaterRecord(stack=stack, params=params))
    return path


def test_site_water_held_keeps_the_estimate_and_trains_the_scattering(data_dir, tmp_path):
    from watergan.site_water import read_site_water

    water = write_water_json(tmp_path / "water.json")
    result = train_gan(small_config(data_dir, tmp_path / "model", site_water=water, iterations=3,
                                    site_water_scattering=True))
    assert result.site_water["mode"] == "held" and result.settle_loss is None  # no statistics term
    stack = Stack.load(tmp_path / "model" / "stack.json")
    assert stack.names == ["attenuation", "backscatter", "backscatter_conv", "vignetting", "gain"]
    truth = Stack.from_config(TRUTH)
    for entry in TRUTH:  # every parameter of the site water is where the water stage put it
        for name in entry["params"]:
            assert torch.allclose(stack[entry["name"]].param(name), truth[entry["name"]].param(name), atol=1e-6)
    checkpoint = load_checkpoint(tmp_path / "model" / "checkpoint.pt")
    assert torch.count_nonzero(checkpoint["generator"]["stack.effects.2.norm.bias"]) == 0  # no veil level
    run = build_gan(small_config(data_dir, tmp_path / "again", site_water=water, site_water_scattering=True))
    trained = [n for n, p in run.generator.named_parameters() if p.requires_grad]
    assert trained and all(n.startswith("stack.effects.2.") for n in trained)  # backscatter_conv alone
    assert "stack.effects.2.norm.bias" not in trained and run.physics == []
    assert len(read_site_water(water).prior) == 3  # eta, b_inf, a_margin; the gain is not fitted


def test_site_water_prior_pulls_towards_the_estimate(data_dir, tmp_path):
    from watergan.site_water import prior_loss, read_site_water

    far = [dict(e, params=dict(e["params"])) for e in TRUTH]
    far[0]["params"]["eta_per_m"] = [0.9, 0.4, 0.5]  # an estimate far from the water the frames show
    water = write_water_json(tmp_path / "water.json", far, half_width=0.01)
    site = read_site_water(water)
    result = train_gan(small_config(data_dir, tmp_path / "prior", site_water=water, site_water_mode="prior",
                                    iterations=4, settle_steps=5))
    free = train_gan(small_config(data_dir, tmp_path / "free", site_water=write_water_json(
        tmp_path / "wide.json", far, half_width=50.0), site_water_mode="prior", iterations=4, settle_steps=5))
    eta_prior = np.asarray(result.params["attenuation.eta_per_m"])
    eta_free = np.asarray(free.params["attenuation.eta_per_m"])
    # a tight prior keeps eta near the estimate; a wide one lets the statistics move it further
    assert np.abs(eta_prior - [0.9, 0.4, 0.5]).max() < np.abs(eta_free - [0.9, 0.4, 0.5]).max()
    assert float(prior_loss(Stack.from_config(far), site.prior).detach()) == pytest.approx(0.0, abs=1e-9)
    assert float(prior_loss(Stack.from_config(TRUTH), site.prior).detach()) > 100  # eta 0.5 vs 0.9 +- 0.005


def test_site_water_errors(data_dir, tmp_path):
    with pytest.raises(UserInputError, match="does not exist"):
        train_gan(small_config(data_dir, tmp_path, site_water=tmp_path / "none.json"))
    with pytest.raises(UserInputError, match="learned"):
        train_gan(small_config(data_dir, tmp_path, site_water=write_water_json(tmp_path / "w.json"),
                               site_water_mode="learned"))
    (tmp_path / "bad.json").write_text(json.dumps({"params": {}}))
    with pytest.raises(UserInputError, match="no stack"):
        train_gan(small_config(data_dir, tmp_path, site_water=tmp_path / "bad.json"))


def test_generate_writes_the_range_the_generator_used(data_dir, tmp_path):
    train_gan(small_config(data_dir, tmp_path / "model", site_water=write_water_json(tmp_path / "w.json"),
                           iterations=1))
    generate(GenerateConfig(model_dir=tmp_path / "model", rgbd_dir=data_dir / "rgbd", out_dir=tmp_path / "gen",
                            progress=False))
    item = json.loads((tmp_path / "gen" / "manifest.json").read_text())["items"][0]
    depth, range_m = read_depth(tmp_path / "gen" / item["depth"]), read_depth(tmp_path / "gen" / item["range"])
    assert np.allclose(range_m, depth, atol=1.5e-3)  # no camera.json: range = depth, to the millimetre


def test_a_held_site_water_without_learned_effects_is_rendered_not_trained(data_dir, tmp_path):
    water = write_water_json(tmp_path / "water.json")
    result = train_gan(small_config(data_dir, tmp_path / "model", site_water=water))  # the default effects
    assert result.stopped_by == "nothing to train" and result.steps == 0
    assert Stack.load(tmp_path / "model" / "stack.json").to_config() == Stack.from_config(TRUTH).to_config()
    generate(GenerateConfig(model_dir=tmp_path / "model", rgbd_dir=data_dir / "rgbd", out_dir=tmp_path / "gen",
                            progress=False, recolour_fraction=0.0))
    # the generated pairs are the site water's rendering of the in-air views, to 8-bit rounding
    truth = WaterGenerator(Stack.from_config(TRUTH)).eval()
    item = json.loads((tmp_path / "gen" / "manifest.json").read_text())["items"][0]
    rgb = cv2.imread(str(tmp_path / "gen" / item["inair"]))[..., ::-1] / 255.0
    from watergan.io import srgb_to_linear

    depth = read_depth(tmp_path / "gen" / item["depth"])
    with torch.no_grad():
        expected = truth(torch.from_numpy(srgb_to_linear(rgb).transpose(2, 0, 1).copy()).float()[None],
                         torch.from_numpy(depth).float()[None, None], torch.zeros(1, 100))[0]
    made = srgb_to_linear(cv2.imread(str(tmp_path / "gen" / item["underwater"]))[..., ::-1] / 255.0)
    assert np.abs(made - expected.numpy().transpose(1, 2, 0)).max() < 0.01
