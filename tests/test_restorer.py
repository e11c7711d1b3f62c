"""Restorer nets and their training (tiny sizes; fast on 2 CPU cores)."""

import json

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from watergan.data import DataError, read_depth
from watergan.errors import UserInputError
from watergan.formation.inverse import SIGNAL_FLOOR
from watergan.nets.restorer import (
    Restorer,
    RestorerWidths,
    SegNetCore,
    apply_affine,
    bilinear_upsampler,
    fill_range_holes,
    image_context,
    position_maps,
    restore,
    srgb_decode,
    srgb_encode,
    water_fields,
)
from watergan.train_restorer import RestorerConfig, load_paired, load_restorer, masked_mse, train_restorer

TINY = RestorerWidths(depth_core=(4, 6, 8, 8), colour_core=(4, 6, 8, 8), full_res=4)


def write_generate_folder(root, count=5, hw=(64, 72), seed=0):
    """A random paired set in the `watergan generate` layout."""
    rng = np.random.default_rng(seed)
    for sub in ("inair", "depth", "underwater"):
        (root / sub).mkdir(parents=True)
    for i in range(count):
        air = rng.integers(0, 256, (*hw, 3), dtype=np.uint8)
        water = (air * np.array([0.3, 0.7, 0.8]) + 20).astype(np.uint8)
        depth = rng.integers(500, 4000, hw).astype(np.uint16)
        cv2.imwrite(str(root / "inair" / f"f{i:02d}.png"), air)
        cv2.imwrite(str(root / "underwater" / f"f{i:02d}.png"), water)
        cv2.imwrite(str(root / "depth" / f"f{i:02d}.png"), depth)
    return root


def test_shapes_at_odd_sizes():
    model = Restorer(TINY).eval()
    with torch.no_grad():
        rgb, depth = restore(model, torch.rand(2, 3, 37, 51))
    assert rgb.shape == (2, 3, 37, 51) and depth.shape == (2, 1, 37, 51)
    assert rgb.min() >= 0 and rgb.max() <= 1 and depth.min() >= 0 and depth.max() <= 1


def test_unpooling_puts_values_at_the_argmax_positions():
    core = SegNetCore(1, 1, (2, 2, 2, 2))
    x = torch.randn(1, 3, 8, 10)
    pooled, idx = core.pool(x)
    unpooled = core.unpool(pooled, idx)
    block_max = F.max_pool2d(x, 2).repeat_interleave(2, -1).repeat_interleave(2, -2)
    at_argmax = x == block_max
    assert torch.equal(unpooled != 0, at_argmax)
    assert torch.equal(unpooled[at_argmax], x[at_argmax])


def test_core_rejects_sides_not_divisible_by_8():
    with pytest.raises(ValueError, match="divisible by 8"):
        SegNetCore(3, 1, (2, 2, 2, 2))(torch.rand(1, 3, 12, 16))


def test_bilinear_init_matches_interpolate_away_from_borders():
    factor = 4
    up = bilinear_upsampler(3, factor)
    x = torch.rand(2, 3, 9, 11)
    with torch.no_grad():
        ours = up(x)
    ref = F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False)
    assert ours.shape == ref.shape
    inner = (ours - ref)[..., factor:-factor, factor:-factor]
    assert inner.abs().max() < 1e-5


@pytest.mark.parametrize("head", ["affine", "direct"])
def test_skip_output_starts_as_the_upsampled_core(head):
    model = Restorer(TINY, head=head).eval()
    x = torch.rand(1, 7, 64, 64)
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)  # a core that is not the identity
        coarse = model.colour_net.colours(model.colour_net.up(model.colour_net.run_core(F.avg_pool2d(x, 4))), x)
        assert torch.allclose(model.colour_net(x), coarse)
        assert not torch.allclose(coarse, x[:, :3], atol=1e-3)


def test_affine_head_starts_as_the_identity():
    model = Restorer(TINY).eval()
    x = torch.rand(2, 7, 64, 64)
    with torch.no_grad():
        assert torch.allclose(model.colour_net(x), x[:, :3], atol=1e-5)


def test_affine_fields_invert_the_formation_model_for_any_colour():
    """I = srgb(k (J t + B)) per channel; the fields g = -log(k t), o = -B / t give back srgb(J) for every
    colour J, saturated or not, with one pair of fields per pixel."""
    g = torch.Generator().manual_seed(0)
    j = 0.05 + 0.95 * torch.rand(1, 3, 8, 8, generator=g)  # linear in-air colours, none darker than the floor
    t = torch.tensor([0.3, 0.75, 0.6]).view(1, 3, 1, 1)
    b = torch.tensor([0.02, 0.1, 0.12]).view(1, 3, 1, 1)
    k = 1.5
    recorded = srgb_encode((k * (j * t + b)).clamp(max=1.0))
    fields = torch.cat([(-torch.log(k * t)).expand(1, 3, 8, 8), (-b / t).expand(1, 3, 8, 8)], dim=1)
    keep = (k * (j * t + b) < 1.0)  # unclipped pixels
    assert torch.allclose(apply_affine(fields, recorded)[keep], srgb_encode(j)[keep], atol=1e-5)
    assert torch.allclose(srgb_decode(srgb_encode(j)), j, atol=1e-6)
    with torch.no_grad():  # inference's in-place passes give training's values to float rounding
        fast = apply_affine(fields, recorded)
        given = apply_affine(fields, recorded, srgb_decode(recorded))  # the colours decoded by the caller
    assert torch.allclose(fast, apply_affine(fields.clone().requires_grad_(), recorded), atol=1e-6)
    assert torch.allclose(given, fast, atol=1e-6)
    # a pixel darker than the veil the fields remove keeps SIGNAL_FLOOR of its own signal, not black
    dark = srgb_encode(0.5 * k * b.expand(1, 3, 8, 8))
    floored = srgb_decode(apply_affine(fields, dark))
    expected = SIGNAL_FLOOR * srgb_decode(dark) / (k * t)
    assert torch.allclose(floored, expected, rtol=1e-4) and (floored > 0).all()
    with torch.no_grad():
        assert torch.allclose(srgb_decode(apply_affine(fields, dark)), expected, rtol=1e-4)


def test_a_restorer_without_skip_layers_pools_its_input_by_parts():
    """Restorer.forward pools the image, depth, position and range apart (and takes decoded colours): the same
    colours as the colour net on the whole full-resolution input."""
    model = Restorer(TINY, skip=False, range_input=True).eval()
    g = torch.Generator().manual_seed(1)
    image, range_m = torch.rand(2, 3, 64, 96, generator=g), 1.0 + torch.rand(2, 1, 64, 96, generator=g)
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
        rgb, depth = model(image, None, None, range_m)
        whole = model.colour_net(torch.cat([image, depth, position_maps(64, 96).expand(2, -1, -1, -1), range_m], 1))
        decoded, _ = model(image, None, None, range_m, None, srgb_decode(image))
    assert torch.allclose(rgb, whole, atol=1e-5)  # float rounding of the pooled means (OpenCV's on the CPU)
    assert torch.allclose(decoded, rgb, atol=1e-5)
    assert not torch.allclose(rgb, image, atol=1e-3)


def test_the_colour_net_sees_the_whole_image_context():
    """A crop is corrected with the context (per-channel mean and std) of its whole image: the same crop
    in a darker frame comes out differently."""
    x = torch.rand(1, 7, 64, 64)
    context = image_context(x)
    np.testing.assert_allclose(context[0, :3].numpy(), x[0, :3].mean(dim=(1, 2)).numpy(), rtol=1e-6)
    np.testing.assert_allclose(context[0, 3:].numpy(), x[0, :3].flatten(1).std(dim=1).numpy(), rtol=1e-5)
    model = Restorer(TINY).eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
        own = model.colour_net(x)
        darker_frame = model.colour_net(x, context * torch.tensor([0.5, 0.5, 0.5, 1.0, 1.0, 1.0]))
    assert (own - darker_frame).abs().max() > 1e-3


def test_position_maps_tell_the_centre_from_the_corners():
    maps = position_maps(4, 6)[0]
    assert maps.shape == (3, 4, 6)
    np.testing.assert_allclose(maps[0, 0].numpy(), (np.arange(6) + 0.5) / 6 * 2 - 1, rtol=1e-6)
    np.testing.assert_allclose(maps[1, :, 0].numpy(), (np.arange(4) + 0.5) / 4 * 2 - 1, rtol=1e-6)
    assert maps[2].argmax() in (0, 5, 18, 23) and maps[2].max() < 1 and maps[2, 1:3, 2:4].max() < 0.1


def test_the_same_pixels_are_corrected_by_where_they_are():
    """A crop taken from the top-left corner and the same pixels placed at the centre of the frame: the
    colour net gets different position maps and may correct them differently (vignetting)."""
    torch.manual_seed(0)
    model = Restorer(TINY).eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
        image = torch.rand(1, 3, 64, 64)
        full = position_maps(128, 128)
        corner, centre = full[..., :64, :64], full[..., 32:96, 32:96]
        a, _ = model(image, corner)
        b, _ = model(image, centre)
        c, _ = model(image)  # its own maps: the crop is a whole image
        d, _ = model(image, position_maps(64, 64))
    assert (a - b).abs().max() > 1e-3
    assert torch.equal(c, d)


def test_the_altitude_enters_the_colour_net():
    """A restorer that takes altitude refuses to run without it, corrects the same image differently at
    another altitude, and its configuration keeps the choice."""
    torch.manual_seed(0)
    model = Restorer(TINY, altitude=True).eval()
    image = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
        with pytest.raises(ValueError, match="altitude"):
            restore(model, image)
        near, _ = restore(model, image, torch.tensor([1.5]))
        far, _ = restore(model, image, torch.tensor([3.0]))
    assert (near - far).abs().max() > 1e-3
    assert Restorer.from_config(model.to_config()).altitude and not Restorer(TINY).altitude


def test_the_range_enters_the_colour_net():
    """An RGB-D restorer refuses to run without each pixel's range and corrects the same image differently at
    another range; holes take the image's median range."""
    torch.manual_seed(0)
    model = Restorer(TINY, range_input=True).eval()
    image = torch.rand(1, 3, 40, 48)
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
        with pytest.raises(ValueError, match="range"):
            restore(model, image)
        near, _ = restore(model, image, range_m=torch.full((1, 1, 40, 48), 1.5))
        far, _ = restore(model, image, range_m=torch.full((1, 1, 40, 48), 3.0))
    assert (near - far).abs().max() > 1e-3
    assert Restorer.from_config(model.to_config()).range_input and not Restorer(TINY).range_input
    holes = torch.tensor([[[[1.0, 0.0], [float("nan"), 3.0]]]])
    filled, share = fill_range_holes(holes)
    assert filled.flatten().tolist() == [1.0, 1.0, 1.0, 3.0] and share == 0.5  # torch's median: the lower middle
    with pytest.raises(ValueError, match="no range"):
        fill_range_holes(torch.zeros(1, 1, 2, 2))
    maps = torch.rand(3, 1, 30, 41, generator=torch.Generator().manual_seed(2)) * 4.0
    maps[maps < 1.0] = 0.0  # about a quarter holes, a different count in each map
    filled, share = fill_range_holes(maps)
    for b in range(3):
        valid = maps[b] > 0
        assert torch.equal(filled[b][~valid], torch.full_like(filled[b][~valid], float(maps[b][valid].median())))
        assert torch.equal(filled[b][valid], maps[b][valid])
    assert share == pytest.approx(float((maps == 0).float().mean()))


def test_an_rgbd_restorer_trains_on_the_paired_range(tmp_path):
    from watergan.io import write_depth_png

    folder = write_generate_folder(tmp_path / "gen", count=3, hw=(40, 40))
    with pytest.raises(DataError, match="missing .*range"):
        train_restorer(_config(tmp_path, range_input=True))
    for i in range(3):
        write_depth_png(folder / "range" / f"f{i:02d}.png", read_depth(folder / "depth" / f"f{i:02d}.png") * 1.1)
    with pytest.raises(DataError, match="manifest.json.*--no-water"):
        train_restorer(_config(tmp_path, range_input=True))
    result = train_restorer(_config(tmp_path, range_input=True, water=False))
    assert result.steps == (2, 2) and load_restorer(result.out_dir).range_input
    assert load_restorer(result.out_dir).water is None
    assert np.isfinite(json.loads((result.out_dir / "validation.json").read_text())["rmse"]["restorer"]["R"])


WATER = [{"name": "attenuation", "params": {"eta_per_m": [0.45, 0.14, 0.2]}},
         {"name": "backscatter", "params": {"b_inf": [0.03, 0.16, 0.19], "beta_per_m": [0.44, 0.33, 0.32]}},
         {"name": "vignetting", "params": {"a_margin": 0.3, "b": -0.05, "c": 0.09}},
         {"name": "gain", "params": {"k": [1.5, 1.5, 1.5]}}]


def write_rendered_folder(root, stack, count=4, hw=(40, 48), seed=0):
    """A `watergan generate` folder whose underwater images are ``stack`` rendered from random in-air images at
    random ranges (8-bit sRGB, as generate writes them), with its manifest."""
    from watergan.formation import FormationState, Stack, pixel_grid
    from watergan.io import write_depth_png, write_srgb8

    rng = np.random.default_rng(seed)
    for sub in ("inair", "depth", "range", "underwater"):
        (root / sub).mkdir(parents=True)
    items = []
    for i in range(count):
        air = rng.uniform(0.05, 0.9, (*hw, 3))
        range_m = rng.uniform(1.5, 3.5) + 0.5 * rng.random(hw)
        state = FormationState(direct=torch.from_numpy(air.transpose(2, 0, 1)[None].copy()),
                               range_m=torch.from_numpy(range_m[None, None].copy()),
                               depth_m=torch.from_numpy(range_m[None, None].copy()),
                               pixel_uv=pixel_grid(*hw, 1, torch.float64), image_wh=(hw[1], hw[0]))
        with torch.no_grad():
            under = Stack.from_config(stack).to(torch.float64).render(state)[0].numpy().transpose(1, 2, 0)
        name = f"f{i:02d}.png"
        write_srgb8(root / "inair" / name, air)
        write_srgb8(root / "underwater" / name, under.clip(0, 1))
        write_depth_png(root / "depth" / name, range_m)
        write_depth_png(root / "range" / name, range_m)
        items.append({"stem": f"f{i:02d}", "intrinsics": None})
    (root / "manifest.json").write_text(json.dumps({"stack": stack, "items": items}))
    return root


def test_an_rgbd_restorer_starts_as_the_exact_inverse_of_the_pairs_water(tmp_path):
    """Before any training, a restorer given the pairs' water corrects them to within the 8-bit rounding of the
    pairs (its fields are the physics correction's: watergan.formation.inverse.correct_physics), where the same
    restorer without the water leaves them as raw; the water travels with the saved model."""
    from watergan.formation.inverse import correct_physics
    from watergan.io import linear_to_srgb, read_image, srgb_to_linear

    folder = write_rendered_folder(tmp_path / "gen", WATER)
    untrained = dict(range_input=True, stage1_iterations=0, stage2_iterations=0, val_fraction=0.5)
    result = train_restorer(_config(tmp_path, **untrained))
    model = load_restorer(result.out_dir)
    assert [e["name"] for e in model.water] == [e["name"] for e in WATER]
    rmse = result.validation["restorer"]
    assert max(rmse[c] for c in "RGB") < 0.006, rmse  # 8-bit rounding of the pairs, amplified by the inverse
    assert min(result.validation["raw"][c] for c in "RGB") > 0.05
    blind = train_restorer(_config(tmp_path, out_dir=tmp_path / "blind", water=False, **untrained))
    assert min(blind.validation["restorer"][c] for c in "RGB") > 0.05
    stored = read_image(folder / "underwater" / "f00.png", "linear")
    range_m = read_depth(folder / "range" / "f00.png")
    with torch.no_grad():
        rgb, _ = restore(model, torch.from_numpy(stored.transpose(2, 0, 1)[None].copy()).float(),
                         torch.tensor([2.5]), torch.from_numpy(range_m[None, None]).float())
    physics, _ = correct_physics(srgb_to_linear(stored), range_m, WATER)
    expected = linear_to_srgb(physics)
    assert np.abs(rgb[0].numpy().transpose(1, 2, 0) - expected).max() < 2e-3


def test_a_training_frame_s_altitude_is_its_median_depth(tmp_path):
    folder = write_generate_folder(tmp_path / "d", count=2)
    depth = read_depth(folder / "depth" / "f01.png")
    depth[:5] = 0  # holes are not part of the median
    cv2.imwrite(str(folder / "depth" / "f01.png"), np.rint(depth * 1000).astype(np.uint16))
    data = load_paired(folder)
    assert data.altitude_m[1].item() == pytest.approx(np.median(depth[5:]), rel=1e-6)


def test_unknown_head_is_refused(tmp_path):
    with pytest.raises(ValueError, match="head"):
        Restorer(TINY, head="rgb")
    with pytest.raises(UserInputError, match="head"):
        train_restorer(RestorerConfig(data_dir=write_generate_folder(tmp_path / "d"), out_dir=tmp_path / "m",
                                      head="rgb"))
    with pytest.raises(UserInputError, match="affine head.*--no-water"):
        train_restorer(RestorerConfig(data_dir=tmp_path / "d", out_dir=tmp_path / "m", head="direct", range_input=True))


def test_two_training_steps_reduce_the_loss():
    torch.manual_seed(0)
    model = Restorer(TINY).train()
    x, target, depth_t = torch.rand(4, 3, 32, 32), torch.rand(4, 3, 32, 32), torch.rand(4, 1, 56, 56)
    opt = torch.optim.Adam(model.parameters(), 1e-2)

    def loss():
        rgb, _ = model(x)
        return F.mse_loss(rgb, target) + masked_mse(model.depth_net(x), depth_t)

    first = loss()
    for _ in range(2):
        opt.zero_grad()
        value = loss()
        value.backward()
        opt.step()
    assert loss().item() < first.item()


def _config(tmp_path, **kw):
    base = dict(data_dir=tmp_path / "gen", out_dir=tmp_path / "model", depth_hw=(16, 16), core_hw=(32, 32),
                crop_px=32, batch_size=2, stage1_iterations=2, stage2_iterations=2, progress=False)
    base["widths"] = "cpu"
    base.update(kw)
    return RestorerConfig(**base)


def test_train_restorer_end_to_end_and_resume(tmp_path):
    write_generate_folder(tmp_path / "gen")
    result = train_restorer(_config(tmp_path))
    out = tmp_path / "model"
    assert result.steps == (2, 2) and (result.train_count, result.val_count) == (4, 1)
    for name in ("restorer.pt", "checkpoint.pt", "train_log.jsonl", "validation.json", "validation.md", "result.json"):
        assert (out / name).is_file()
    table = json.loads((out / "validation.json").read_text())["rmse"]
    assert set(table["restorer"]) == {"R", "G", "B", "depth"} and table["restorer"]["depth"] is not None
    assert "| raw (uncorrected) |" in (out / "validation.md").read_text()
    model = load_restorer(out)
    assert not model.skip and model.depth_hw == (16, 16)  # no full-resolution skip layers by default

    resumed = train_restorer(_config(tmp_path, stage2_iterations=3, resume=True))
    assert resumed.steps == (2, 3)
    lines = [json.loads(s) for s in (out / "train_log.jsonl").read_text().splitlines()]
    assert [(r["stage"], r["step"]) for r in lines] == [(1, 1), (1, 2), (2, 1), (2, 2), (2, 3)]


def test_skip_layers_on_request_and_bad_config(tmp_path):
    write_generate_folder(tmp_path / "gen", count=3, hw=(40, 40))
    result = train_restorer(_config(tmp_path, skip=True, stage1_iterations=1, stage2_iterations=1))
    assert "restorer (skip layers)" in (result.out_dir / "validation.md").read_text()
    assert load_restorer(result.out_dir).skip
    with pytest.raises(UserInputError, match="widths"):
        train_restorer(_config(tmp_path, widths="huge"))
    with pytest.raises(UserInputError, match="generate"):
        train_restorer(_config(tmp_path, data_dir=tmp_path / "nothing"))


def test_a_restorer_from_older_nets_asks_to_be_trained_again(tmp_path):
    """restorer.pt written before the position maps and the head existed: a clear error, not a traceback."""
    from watergan.train_restorer import MODEL, save_restorer

    save_restorer(tmp_path / MODEL, Restorer(TINY))
    saved = torch.load(tmp_path / MODEL, weights_only=True)
    del saved["model_config"]["head"]
    saved["model"]["colour_net.skip1.0.weight"] = saved["model"]["colour_net.skip1.0.weight"][:, :4]
    torch.save(saved, tmp_path / MODEL)
    with pytest.raises(UserInputError, match="train it again"):
        load_restorer(tmp_path)


def test_the_learning_rate_warms_up_then_decays_over_each_stage(tmp_path):
    from watergan.train_restorer import stage_lr

    config = _config(tmp_path, lr=1e-3, warmup_iterations=10)
    assert stage_lr(config, 0, 100, 0.0, None) == pytest.approx(1e-4 * 0.5 * (1 + np.cos(0.0)))
    assert stage_lr(config, 9, 100, 0.0, None) == pytest.approx(1e-3 * 0.5 * (1 + np.cos(np.pi * 0.09)))
    assert stage_lr(config, 50, 100, 0.0, None) == pytest.approx(5e-4)  # half-way: half the rate
    assert stage_lr(config, 10, 1000, 30.0, 60.0) == pytest.approx(5e-4)  # the budget's share decides
    assert stage_lr(config, 100, 100, 0.0, None) == pytest.approx(0.0, abs=1e-12)
    flat = _config(tmp_path, lr=1e-3, warmup_iterations=0, lr_decay=False)
    assert stage_lr(flat, 0, 100, 0.0, None) == stage_lr(flat, 99, 100, 50.0, 60.0) == 1e-3
    # past the budget with fewer iterations than the stage's least, the rate decays over those iterations
    assert stage_lr(config, 10, 1000, 90.0, 60.0) == pytest.approx(0.0, abs=1e-12)
    assert stage_lr(config, 10, 1000, 90.0, 60.0, 20) == pytest.approx(5e-4)
    assert stage_lr(config, 10, 1000, 30.0, 60.0, 5) == pytest.approx(5e-4)  # ahead of the least: the budget


def test_a_budget_too_short_still_runs_each_stage_s_least_iterations(tmp_path):
    """A budget that ends before a single step (a busy machine) still trains each stage its least iterations."""
    write_generate_folder(tmp_path / "gen")
    result = train_restorer(_config(tmp_path, stage1_iterations=50, stage2_iterations=50, budget_min=1e-6,
                                    stage1_min_iterations=3, stage2_min_iterations=2))
    assert result.steps == (3, 2)
    with pytest.raises(UserInputError, match=">= 0"):
        train_restorer(_config(tmp_path, stage1_min_iterations=-1))


@pytest.mark.parametrize("with_intrinsics", [False, True])
def test_interpolated_water_fields_match_the_exact_ones(with_intrinsics):
    """The fields correct uses (a grid of positions and ranges, interpolated) are within 1e-3 of the exact log gain
    and 1e-4 of the exact offset over a range map with relief and holes filled, off-centre vignetting included."""
    water = [*WATER[:3], {"name": "vignetting_offcentre", "params": {"centre_uv": [0.6, 0.44]}}, WATER[3]]
    rng = np.random.default_rng(1)
    relief = cv2.GaussianBlur(rng.uniform(-0.6, 0.6, (120, 160)), (0, 0), 3)
    range_m = torch.from_numpy(2.5 + relief + np.linspace(0, 1, 160)[None]).float()[None, None]
    intrinsics = (140.0, 140.0, 79.5, 59.5) if with_intrinsics else None
    exact = water_fields(water, range_m, intrinsics, exact=True)
    interpolated = water_fields(water, range_m, intrinsics)
    error = (exact - interpolated).abs()
    assert error[:, :3].max() < 1e-3 and error[:, 3:].max() < 1e-4
    assert exact[:, :3].std() > 0.05  # the fields vary: the test is not comparing constants


def test_a_low_rank_field_table_samples_as_its_trilinear_interpolation():
    """A water of attenuation, backscatter and (off-centre) falloffs has fields that are sums of range-by-position
    products: the table is sampled as that sum, within a few 1e-4 of the trilinear interpolation of the same table
    (the range functions' 1 mm step); a table that is not of low rank is sampled trilinearly."""
    import dataclasses

    from watergan.formation import Stack
    from watergan.formation.inverse import FieldTable, factorised

    water = [*WATER[:3], {"name": "vignetting_offcentre", "params": {"centre_uv": [0.6, 0.44]}}, WATER[3]]
    K = np.array([[140.0, 0.0, 79.5], [0.0, 140.0, 59.5], [0.0, 0.0, 1.0]])
    table = FieldTable.build(Stack.from_config(water), 160, 120, K, 1.0, 5.0)
    assert table.curves is not None
    rng = np.random.default_rng(3)
    range_m = torch.from_numpy(cv2.GaussianBlur(rng.uniform(1.2, 4.8, (120, 160)), (0, 0), 2)).float()[None, None]
    fast = table.sample(range_m)
    trilinear = dataclasses.replace(table, curves=None, maps=None).sample(range_m)
    error = (fast - trilinear).abs()
    assert error[:, :3].max() < 3e-4 and error[:, 3:].max() < 1e-4
    assert fast[:, :3].std() > 0.05
    r = torch.linspace(1.0, 5.0, 41, dtype=torch.float64)
    x = torch.linspace(-1.0, 1.0, 9, dtype=torch.float64)
    tangled = torch.exp(3.0 * r[:, None, None] * x[None, :, None] * x[None, None, :])  # no few-term product
    assert factorised(tangled[None].expand(6, -1, -1, -1), r) == (None, None)


def test_the_inference_copy_gives_the_same_colours_and_depth():
    """for_inference folds each batch norm into its convolution (with trained, not default, statistics) and lays out
    the output convolution channels-last; the outputs are those of the model itself."""
    torch.manual_seed(0)
    model = Restorer(range_input=True).eval()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.2, 0.2)
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
        torch.nn.init.normal_(model.colour_net.out.weight, std=0.1)
        image, range_m = torch.rand(2, 3, 64, 96), 1.0 + 2.0 * torch.rand(2, 1, 64, 96)
        rgb, depth = restore(model, image, range_m=range_m)
        fast = model.for_inference()
        rgb_fast, depth_fast = restore(fast, image, range_m=range_m)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())  # the model itself is left as it was
    assert (rgb - rgb_fast).abs().max() < 1e-5 and (depth - depth_fast).abs().max() < 1e-5
    assert rgb.std() > 0.05 and (rgb - image).abs().mean() > 0.01  # the comparison is not of an identity


def test_water_fields_keep_their_grid_while_it_covers_the_frames():
    """WaterFields builds its grid once for frames within its (rounded) range span, rebuilds it over both spans for
    farther frames or another camera, and matches the exact fields throughout."""
    from watergan.nets.restorer import WaterFields

    fields = WaterFields(WATER)
    rng = np.random.default_rng(2)
    intrinsics = (140.0, 140.0, 79.5, 59.5)

    def frame(lo, hi):
        return torch.from_numpy(rng.uniform(lo, hi, (1, 1, 120, 160))).float()

    tables = []
    for range_m, k in ((frame(2.1, 2.9), intrinsics), (frame(2.2, 2.8), intrinsics), (frame(3.5, 4.4), intrinsics),
                       (frame(2.2, 2.8), intrinsics), (frame(2.2, 2.8), None)):
        got = fields(range_m, k)
        exact = water_fields(WATER, range_m, k, exact=True)
        assert (got - exact)[:, :3].abs().max() < 1e-3 and (got - exact)[:, 3:].abs().max() < 1e-4
        tables.append(fields._table)
    assert tables[0] is tables[1]  # covered: kept
    # the first span, 2.1-2.9 m widened by 1 m and rounded, is 1.0-4.0 m; farther: both spans
    assert tables[2] is not tables[1] and (tables[2].r_lo_m, tables[2].r_hi_m) == (1.0, 5.5)
    assert tables[3] is tables[2]
    assert tables[4] is not tables[3] and tables[4].K is None  # another camera
