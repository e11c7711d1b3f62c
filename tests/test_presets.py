"""The field-like presets ``reef`` and ``auv`` (issue 19): each at a small size renders with the expected
layout and truth; the full presets' geometry is checked without rendering; the strobes declared in
survey.json are exactly those the renderer used (left and right camera)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from eval.synth import PRESETS, load_truth, make_config, simulate_survey
from eval.synth.camera import CameraConfig, intrinsics_for, project
from eval.synth.imaging import linear_image, rig_camera_config
from eval.synth.render import frame_state, make_raycaster, render_view
from eval.synth.rgbd import RGBDConfig
from eval.synth.scene import build_scene
from eval.synth.trajectory import TrajectoryConfig, lawnmower
from pipeline.survey import check_survey
from watergan.errors import UserInputError
from watergan.formation import Stack
from watergan.formation.effects.artificial_light import FWHM_PER_SIGMA
from watergan.io import linear_to_srgb, read_png, srgb_to_linear

TINY_RGBD = dict(n_scenes=1, views_per_scene=3, width_px=32, height_px=24, scene_size_m=8.0, grid_spacing_m=0.25)


def small(preset: str, n_lines: int, frames_per_line: int):
    """The preset at 160x120 (same field of view, so the same footprints) with fewer frames per line and a
    tiny RGB-D set of the same kind."""
    cfg = make_config(preset, seed=0)
    return replace(cfg, camera=CameraConfig(width_px=160, height_px=120, hfov_deg=cfg.camera.hfov_deg),
                   trajectory=replace(cfg.trajectory, n_lines=n_lines, frames_per_line=frames_per_line),
                   rgbd=RGBDConfig(**TINY_RGBD, like_site=cfg.rgbd.like_site))


@pytest.fixture(scope="module")
def reef(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reef") / "survey"
    simulate_survey(out, small("reef", n_lines=5, frames_per_line=2), progress=False)
    return out


@pytest.fixture(scope="module")
def auv(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("auv") / "survey"
    simulate_survey(out, small("auv", n_lines=2, frames_per_line=4), progress=False)
    return out


def off_nadir_deg(world_from_cam: np.ndarray) -> np.ndarray:
    """Angle between each camera's optical axis (camera +z in the world) and straight down, degrees."""
    return np.degrees(np.arccos(np.clip(-world_from_cam[:, 2, 2], -1.0, 1.0)))


@pytest.mark.parametrize("name", ["reef", "auv"])
def test_full_presets_are_60_frames_of_640x480_that_see_the_board(name):
    cfg = make_config(name)
    intr = intrinsics_for(cfg.camera)
    trajectory = lawnmower(cfg.trajectory, intr, cfg.seed)
    assert len(trajectory) == 60 and (intr.width, intr.height) == (640, 480)
    assert cfg.rgbd.like_site is False  # the generic in-air set, not one drawn like the site
    board = np.array([*cfg.scene.board.centre_xy_m, cfg.scene.board.lift_m])
    uv = np.array([project(board, pose, intr)[0] for pose in trajectory.world_from_cam])
    seen = (uv[:, 0] > 0) & (uv[:, 0] < intr.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < intr.height - 1)
    assert seen.sum() >= 5


def test_reef_geometry_relief_heights_and_views():
    cfg = make_config("reef")
    scene = build_scene(cfg.scene, cfg.seed)
    x, y = np.meshgrid(np.linspace(-6, 6, 300), np.linspace(-6, 6, 300))
    height = scene.height(x, y)
    assert 0.4 < height.max() <= 0.8  # mounds of real relief, no higher than 0.8 m
    trajectory = lawnmower(cfg.trajectory, intrinsics_for(cfg.camera), cfg.seed)
    tilt = off_nadir_deg(trajectory.world_from_cam)
    assert 20.0 < tilt.max() <= 35.0 and tilt.min() < 8.0  # nadir passes and passes up to 35 degrees off
    z = trajectory.world_from_cam[:, 2, 3]
    line_mean = [z[trajectory.line == k].mean() for k in range(cfg.trajectory.n_lines)]
    assert max(line_mean) - min(line_mean) > 1.0  # passes at different heights


def test_tilted_line_still_looks_at_its_planned_strip():
    """A tilted line's camera is moved so its axis meets the datum where the nadir line's does."""
    base = TrajectoryConfig(n_lines=1, frames_per_line=3, roll_pitch_std_deg=0.0, yaw_std_deg=0.0,
                            altitude_wave_m=0.0, position_std_m=0.0)
    intr = intrinsics_for(CameraConfig())
    nadir = lawnmower(base, intr, 0).world_from_cam
    for tilt in ((25.0, 0.0), (0.0, -30.0), (15.0, 20.0)):
        tilted = lawnmower(replace(base, line_altitudes_m=(1.7,), line_tilts_deg=(tilt,)), intr, 0).world_from_cam
        for a, b in zip(nadir, tilted, strict=True):
            hit_a = a[:3, 3] - a[:3, 3][2] / a[2, 2] * a[:3, 2]  # optical axis meets z = 0
            hit_b = b[:3, 3] - b[:3, 3][2] / b[2, 2] * b[:3, 2]
            np.testing.assert_allclose(hit_b[:2], hit_a[:2], atol=0.02)
        assert off_nadir_deg(tilted) == pytest.approx([np.degrees(np.arccos(
            np.cos(np.radians(tilt[0])) * np.cos(np.radians(tilt[1]))))] * 3, abs=0.01)


def test_reef_small_layout_truth_and_colonies(reef):
    truth = load_truth(reef)
    assert len(truth.frames) == 10 and truth.world_from_cam_right is not None
    for folder in ("images", "right", "truth/inair", "truth/depth", "truth/range"):
        assert sorted(p.name for p in (reef / folder).iterdir()) == truth.frames, folder
    survey = json.loads((reef / "survey.json").read_text())
    assert survey["lights"] == [] and survey["site_depth_m"] == 5.0
    assert check_survey(reef)["n_images"] == 10
    assert [e["name"] for e in truth.effects["full"]].count("ambient_depth") == 1
    ranges = np.concatenate([truth.range_m(k).ravel() for k in range(len(truth.frames))])
    assert 0.5 < np.percentile(ranges, 5) and np.median(ranges) < 2.5
    # the colonies' saturated colours are in the site's albedos: reds and purples among them
    inair = np.concatenate([srgb_to_linear(read_png(reef / "truth/inair" / f) / 255.0).reshape(-1, 3)
                            for f in truth.frames])
    chroma = inair / inair.sum(1, keepdims=True).clip(1e-6)
    red = (chroma[:, 0] > 0.75).mean()
    purple = ((chroma[:, 0] > 0.35) & (chroma[:, 2] > 0.4) & (chroma[:, 1] < 0.15)).mean()
    assert red > 0.01 and purple > 0.01, (red, purple)
    # ... and not in the generic in-air set WaterGAN gets
    rgbd = np.concatenate([srgb_to_linear(read_png(p) / 255.0).reshape(-1, 3) for p in (reef / "rgbd/rgb").iterdir()])
    rgbd_chroma = rgbd / rgbd.sum(1, keepdims=True).clip(1e-6)
    assert (rgbd_chroma[:, 0] > 0.75).mean() < 0.001


def test_scene_colonies_cover_the_asked_share_with_the_palette():
    """Colonies change the colour raster on the asked share of the floor, each to a palette colour times the
    raster's own variation (base / tint); the rest of the site is as it is without colonies."""
    cfg = replace(make_config("reef").scene, board=None, n_rocks=0, size_x_m=6.0, size_y_m=6.0)
    with_cover = build_scene(cfg, 0)._base
    plain = build_scene(replace(cfg, cover_fraction=0.0), 0)._base
    covered = (with_cover != plain).any(-1)
    assert covered.mean() == pytest.approx(cfg.cover_fraction, abs=0.01)
    variation = plain[covered] / np.asarray(cfg.tint_linear, np.float32)
    palette = np.asarray(cfg.cover_palette_linear, np.float32)
    error = np.abs(with_cover[covered][:, None] - palette[None] * variation[:, None]).max(-1).min(-1)
    assert error.max() < 1e-5
    colours = np.abs(with_cover[covered][:, None] - palette[None] * variation[:, None]).max(-1).argmin(-1)
    assert np.bincount(colours, minlength=len(palette)).min() > 0.02 * covered.sum()  # every colour is used


def test_auv_strobes_in_survey_json_are_what_the_renderer_used(auv):
    truth = load_truth(auv)
    survey = json.loads((auv / "survey.json").read_text())
    lights = survey["lights"]
    assert check_survey(auv)["stereo"]
    full = truth.effects["full"]
    rendered = next(e["params"] for e in full if e["name"] == "artificial_light")
    assert len(lights) == 2
    for i, light in enumerate(lights):
        assert light["offset_m"] == rendered["offset_m"][i] and light["tilt_deg"] == rendered["tilt_deg"][i]
        assert light["beam_deg"] == rendered["beam_deg"][i]
        assert light["beam_angle_deg"] == pytest.approx(90.0, abs=1e-4)
        assert light["beam_angle_deg"] == pytest.approx(FWHM_PER_SIGMA * light["beam_deg"])
    assert abs(lights[0]["offset_m"][0] - lights[1]["offset_m"][0]) == pytest.approx(1.0)
    # re-render frame 1 with the lights exactly as declared (each camera of the rig): the written images agree
    rig = {key: [light[key] for light in lights] for key in ("offset_m", "tilt_deg", "beam_deg")}
    declared = [dict(e, params=dict(e["params"], **rig)) if e["name"] == "artificial_light" else e for e in full]
    cfg = truth.config
    scene = build_scene(cfg.scene, cfg.seed)
    caster = make_raycaster(scene)
    for folder, pose, stack in (
            ("images", truth.world_from_cam[1], declared),
            ("right", truth.world_from_cam_right[1], rig_camera_config(declared, (truth.baseline_m, 0.0, 0.0)))):
        view = render_view(caster, scene, truth.intrinsics, pose, cfg.render)
        linear = linear_image(Stack.from_config(stack), frame_state(view, 1, cfg.render.site_depth_m))
        diff = read_png(auv / folder / truth.frames[1]).astype(float) - np.rint(linear_to_srgb(linear) * 255)
        assert abs(diff.mean()) < 0.3 and diff.std() < 3.0, (folder, diff.mean(), diff.std())
    # the right camera rendered with the left camera's light positions would not match
    view = render_view(caster, scene, truth.intrinsics, truth.world_from_cam_right[1], cfg.render)
    wrong = linear_image(Stack.from_config(declared), frame_state(view, 1, cfg.render.site_depth_m))
    diff = read_png(auv / "right" / truth.frames[1]).astype(float) - np.rint(linear_to_srgb(wrong) * 255)
    assert np.abs(diff).mean() > 1.0


def test_auv_frames_show_the_strobe_pattern(auv):
    """Darkness: the image over the in-air albedo is brightest near the strobes and falls with range."""
    truth = load_truth(auv)
    lights = np.array([lt["offset_m"] for lt in json.loads((auv / "survey.json").read_text())["lights"]])
    ratios, distances = [], []
    for k, name in enumerate(truth.frames):
        raw = srgb_to_linear(read_png(auv / "images" / name) / 255.0).mean(-1)
        inair = srgb_to_linear(read_png(auv / "truth/inair" / name) / 255.0).mean(-1)
        depth = truth.depth_m(k)
        intr = truth.intrinsics
        v, u = np.mgrid[0:intr.height, 0:intr.width]
        points = np.stack([(u - intr.cx) / intr.fx * depth, (v - intr.cy) / intr.fy * depth, depth], -1)
        nearest = np.linalg.norm(points[..., None, :] - lights, axis=-1).min(-1)
        ok = inair > 0.05
        ratios.append(raw[ok] / inair[ok])
        distances.append(nearest[ok])
    ratio, distance = np.concatenate(ratios), np.concatenate(distances)
    near, far = distance < np.percentile(distance, 20), distance > np.percentile(distance, 80)
    assert ratio[near].mean() > 2.0 * ratio[far].mean()
    assert np.corrcoef(np.log(ratio), distance)[0, 1] < -0.7
    survey = json.loads((auv / "survey.json").read_text())
    altitudes = np.array(survey["nav_altitude_m"])
    assert altitudes.max() - altitudes.min() > 0.5  # the altitude changes along the line


def test_survey_check_refuses_malformed_lights(auv, tmp_path):
    survey = json.loads((auv / "survey.json").read_text())
    for bad in ([{"tilt_deg": [0, 0]}], [{"offset_m": [0, 0]}], [dict(survey["lights"][0], beam_angle_deg=60.0)],
                [dict(survey["lights"][0], beam_deg=-1.0)], {"offset_m": [0, 0, 0]}):
        folder = tmp_path / "s"
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir()
        for name in ("images", "camera.json"):
            (folder / name).symlink_to(auv / name)
        (folder / "survey.json").write_text(json.dumps(dict(survey, lights=bad)))
        with pytest.raises(UserInputError, match="lights"):
            check_survey(folder)


def test_preset_choices_come_from_one_list():
    from pipeline.cli import Preset, build_parser

    assert [p.value for p in Preset] == list(PRESETS)
    demo = build_parser()._subparsers._group_actions[0].choices["demo"]
    preset = next(a for a in demo._actions if a.dest == "preset")
    assert list(preset.choices) == list(PRESETS)
