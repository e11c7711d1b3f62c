"""The survey simulator: determinism, geometry, board colours, layout, output-folder safety and
hidden effects (tiny surveys, a few seconds in all)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from eval.synth import HIDDEN_DEFAULTS, SimulationError, load_truth, make_config, simulate_survey, with_frames
from eval.synth.camera import intrinsics_from_fov, make_pose, pixel_rays_cam, project
from eval.synth.imaging import full_stack_config, linear_image
from eval.synth.render import RenderConfig, frame_state, make_raycaster, render_view
from eval.synth.rgbd import RGBDConfig
from eval.synth.scene import SceneConfig, build_scene, make_board
from eval.synth.trajectory import CAM_IN_BODY, TrajectoryConfig, body_rotation, lawnmower
from watergan.formation import Stack
from watergan.io import linear_to_srgb, read_png

SMALL_RGBD = RGBDConfig(n_scenes=1, views_per_scene=2, width_px=32, height_px=24, scene_size_m=8.0,
                        grid_spacing_m=0.25)


def tree_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tiny") / "survey"
    simulate_survey(out, make_config("tiny", hidden=["vignetting_offcentre"], seed=3), progress=False)
    return out


def test_same_seed_gives_identical_files(tiny, tmp_path):
    again = tmp_path / "again"
    simulate_survey(again, make_config("tiny", hidden=["vignetting_offcentre"], seed=3), progress=False)
    first, second = tree_hashes(tiny), tree_hashes(again)
    assert len(first) > 50
    assert first == second
    other = tmp_path / "other_seed"
    simulate_survey(other, make_config("tiny", hidden=["vignetting_offcentre"], seed=4), progress=False)
    assert tree_hashes(other)["images/000000.png"] != first["images/000000.png"]


def test_layout_has_every_file(tiny):
    truth = load_truth(tiny)
    n = len(truth.frames)
    assert n == 6
    for folder in ("images", "right", "truth/inair", "truth/inair_linear", "truth/depth", "truth/range"):
        assert sorted(p.name for p in (tiny / folder).iterdir()) == truth.frames, folder
    for name in ("camera.json", "survey.json", "truth/poses.json", "truth/effects.json", "truth/board.json",
                 "truth/scene.ply", "truth/config.json", "rgbd/camera.json"):
        assert (tiny / name).is_file(), name
    rgb = sorted(p.name for p in (tiny / "rgbd/rgb").iterdir())
    assert rgb == sorted(p.name for p in (tiny / "rgbd/depth").iterdir()) and len(rgb) == 12
    depth = read_png(tiny / "rgbd/depth" / rgb[0])
    assert depth.dtype == np.uint16 and depth.max() > 500
    image = read_png(tiny / "images/000000.png")
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8
    assert read_png(tiny / "truth/inair_linear/000000.png").dtype == np.uint16
    assert truth.world_from_cam_right is not None and truth.baseline_m == pytest.approx(0.12)
    # the right camera sits one baseline along the left camera's x axis
    offset = np.linalg.inv(truth.world_from_cam[0]) @ truth.world_from_cam_right[0]
    np.testing.assert_allclose(offset[:3, 3], [0.12, 0, 0], atol=1e-12)
    assert truth.config == make_config("tiny", hidden=["vignetting_offcentre"], seed=3)
    survey = __import__("json").loads((tiny / "survey.json").read_text())
    assert survey["frames"] == truth.frames and len(survey["nav_altitude_m"]) == n
    # navigation altitude is the camera's height above the flat board area (~2.5 m) give or take
    assert 2.0 < min(survey["nav_altitude_m"]) and max(survey["nav_altitude_m"]) == survey["max_altitude_m"] < 3.2
    # the attitude sensor's "down" in each camera's frame is the world's -z seen from the camera's true pose
    down = np.asarray(survey["nav_down_cam"])
    np.testing.assert_allclose(down, np.einsum("nij,i->nj", truth.world_from_cam[:, :3, :3], [0.0, 0.0, -1.0]),
                               atol=1e-6)
    assert (down[:, 2] > 0.99).all()  # the tiny survey looks down


def test_hidden_effects_in_truth_not_in_visible(tiny):
    effects = load_truth(tiny).effects
    visible = [e["name"] for e in effects["visible"]]
    assert "vignetting_offcentre" not in visible
    assert [e["name"] for e in effects["hidden"]] == ["vignetting_offcentre"]
    assert effects["hidden"][0]["params"]["centre_uv"] == pytest.approx(
        HIDDEN_DEFAULTS["vignetting_offcentre"]["centre_uv"])
    full = [e["name"] for e in effects["full"]]
    assert full == ["attenuation", "backscatter", "vignetting", "vignetting_offcentre", "gain"]
    assert "vignetting_offcentre" not in (tiny / "survey.json").read_text()


def test_full_stack_order_and_duplicates():
    cfg = full_stack_config([{"name": "attenuation"}, {"name": "gain"}],
                            [{"name": "sensor_response"}, {"name": "artificial_light"}])
    assert [e["name"] for e in cfg] == ["artificial_light", "attenuation", "gain", "sensor_response"]
    with pytest.raises(ValueError, match="already in the visible stack"):
        full_stack_config([{"name": "gain"}], [{"name": "gain"}])


def test_images_are_full_stack_of_inair_render_plus_noise(tiny):
    truth = load_truth(tiny)
    scene = build_scene(truth.config.scene, truth.config.seed)
    view = render_view(make_raycaster(scene), scene, truth.intrinsics, truth.world_from_cam[2], RenderConfig())
    linear = linear_image(Stack.from_config(truth.effects["full"]), frame_state(view, 2, 20.0))
    expected = np.rint(linear_to_srgb(np.clip(linear, 0, 1)) * 255)
    diff = read_png(tiny / "images" / truth.frames[2]).astype(float) - expected
    assert abs(diff.mean()) < 0.3          # noise is zero-mean
    assert 0.3 < diff.std() < 4.0          # ... and present
    # without the hidden off-centre vignetting the prediction is clearly worse at the far corner
    visible = linear_image(Stack.from_config(truth.effects["visible"]), frame_state(view, 2, 20.0))
    assert (visible[:15, :15] > linear[:15, :15] * 1.05).all()


def test_plane_depth_matches_analytic(tmp_path):
    """A flat seafloor z = 0 seen by a tilted camera: depth = z_cam of o + t d with t = -o_z / d_z."""
    flat = SceneConfig(size_x_m=12.0, size_y_m=12.0, grid_spacing_m=0.5, relief_m=0.0, n_rocks=0, board=None)
    scene = build_scene(flat, seed=1)
    intr = intrinsics_from_fov(96, 64, 60.0)
    pose = make_pose(body_rotation(0.4, np.radians(20), np.radians(-12)) @ CAM_IN_BODY, np.array([0.3, -0.2, 2.2]))
    view = render_view(make_raycaster(scene), scene, intr, pose, RenderConfig())
    d_cam = pixel_rays_cam(intr)
    d_world = d_cam @ pose[:3, :3].T
    t = -pose[2, 3] / d_world[..., 2]
    assert view.valid.all()
    np.testing.assert_allclose(view.range_m, t, atol=1e-4)
    np.testing.assert_allclose(view.depth_m, t * d_cam[..., 2], atol=1e-4)
    assert np.ptp(view.depth_m) > 0.5  # the tilt makes depth vary across the image
    np.testing.assert_allclose(view.normals_world, np.broadcast_to([0, 0, 1], view.normals_world.shape), atol=1e-6)

    # the same through the written survey: depth PNGs (mm) against saved poses and intrinsics
    cfg = make_config("tiny", seed=5)
    cfg = replace(cfg, scene=replace(flat, size_x_m=8.0, size_y_m=7.0), rgbd=SMALL_RGBD)
    simulate_survey(tmp_path / "flat", cfg, progress=False)
    truth = load_truth(tmp_path / "flat")
    d_cam = pixel_rays_cam(truth.intrinsics)
    for k in range(len(truth.frames)):
        pose = truth.world_from_cam[k]
        d_world = d_cam @ pose[:3, :3].T
        analytic = -pose[2, 3] / d_world[..., 2] * d_cam[..., 2]
        assert np.abs(truth.depth_m(k) - analytic).max() < 1e-3


def test_world_points_project_to_their_pixels(tiny):
    truth = load_truth(tiny)
    scene = build_scene(truth.config.scene, truth.config.seed)
    k = 4
    view = render_view(make_raycaster(scene), scene, truth.intrinsics, truth.world_from_cam[k], RenderConfig())
    uv, z = project(view.points_world.astype(np.float64), truth.world_from_cam[k], truth.intrinsics)
    cols, rows = np.meshgrid(np.arange(truth.intrinsics.width), np.arange(truth.intrinsics.height))
    assert np.abs(uv[..., 0] - cols).max() < 0.01 and np.abs(uv[..., 1] - rows).max() < 0.01
    assert np.abs(z - truth.depth_m(k)).max() < 1e-3


def test_board_patches_render_to_true_colours(tmp_path):
    """Board patches in the in-air truth image (sampled at projected patch centres) equal the
    chart's sRGB colours within 1/255."""
    base = make_config("tiny", seed=2)
    board = base.scene.board
    cfg = replace(base, rgbd=SMALL_RGBD, trajectory=TrajectoryConfig(
        altitude_m=1.0, n_lines=1, frames_per_line=2, centre_xy_m=board.centre_xy_m, stereo=False))
    simulate_survey(tmp_path / "board", cfg, progress=False)
    truth = load_truth(tmp_path / "board")
    chart = make_board(board)
    np.testing.assert_allclose(truth.board.corners_world, chart.corners_world)
    assert truth.board.names[0] == "dark skin" and truth.board.srgb.shape == (24, 3)
    seen = set()
    for k, name in enumerate(truth.frames):
        image = read_png(tmp_path / "board/truth/inair" / name).astype(int)
        pose = truth.world_from_cam[k]
        centres, _ = project(truth.board.corners_world.mean(1), pose, truth.intrinsics)
        corners, _ = project(truth.board.corners_world, pose, truth.intrinsics)
        for i in range(24):
            c = np.rint(centres[i]).astype(int)
            half_side = np.linalg.norm(corners[i, 1] - corners[i, 0]) / 2
            inside = (2 <= c[0] < truth.intrinsics.width - 2) and (2 <= c[1] < truth.intrinsics.height - 2)
            if not inside or half_side < 3.5:
                continue
            patch = image[c[1] - 1:c[1] + 2, c[0] - 1:c[0] + 2].reshape(-1, 3)
            assert np.abs(patch - np.rint(truth.board.srgb[i] * 255)).max() <= 1, (name, truth.board.names[i])
            seen.add(i)
    assert seen == set(range(24))


@pytest.mark.parametrize("frames", [176, 500, 10])
def test_a_longer_survey_flies_more_lines_over_a_site_grown_with_them(frames):
    """--frames N: at least N frames (whole lines), lines and frames per line grown alike, and the frames' centres
    as far from the site's edge as the preset's are (a shorter survey keeps the site, never shrinks it)."""
    base = make_config("demo")
    config = with_frames(base, frames)
    t = config.trajectory
    assert frames <= t.n_lines * t.frames_per_line < frames + t.n_lines
    if frames > 44:
        assert t.n_lines > base.trajectory.n_lines and t.frames_per_line > base.trajectory.frames_per_line

    def margin_m(c) -> float:
        intr = intrinsics_from_fov(c.camera.width_px, c.camera.height_px, c.camera.hfov_deg)
        centres = lawnmower(c.trajectory, intr, 0).world_from_cam[:, :2, 3]
        return min(c.scene.size_x_m / 2 - np.abs(centres[:, 0]).max(),
                   c.scene.size_y_m / 2 - np.abs(centres[:, 1]).max())

    assert margin_m(config) >= margin_m(base) - 0.05
    with pytest.raises(SimulationError, match="at least one frame"):
        with_frames(base, 0)


def test_existing_output_is_refused_unless_forced(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    cfg = replace(make_config("tiny", seed=0), rgbd=SMALL_RGBD)
    with pytest.raises(SimulationError, match="not empty.*force"):
        simulate_survey(out, cfg, progress=False)
    assert (out / "keep.txt").read_text() == "user data"
    simulate_survey(out, cfg, force=True, progress=False)
    assert not (out / "keep.txt").exists() and (out / "images/000000.png").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]  # no temporary folders left behind


def test_unwritable_parent_is_a_clear_error(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    cfg = replace(make_config("tiny", seed=0), rgbd=SMALL_RGBD)
    with pytest.raises(SimulationError, match="writable location"):
        simulate_survey(blocker / "survey", cfg, progress=False)
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(SimulationError, match="writable location"):
            simulate_survey(locked / "survey", cfg, progress=False)


def test_unknown_hidden_effect_is_rejected():
    with pytest.raises(KeyError, match="unknown effect 'vignetting_ofcentre'"):
        make_config("tiny", hidden=["vignetting_ofcentre"])
    with pytest.raises(ValueError, match="unknown preset"):
        make_config("huge")


def test_demo_preset_has_enough_frames_and_sees_the_board():
    from eval.synth.camera import intrinsics_for
    from eval.synth.trajectory import lawnmower

    cfg = make_config("demo", seed=0)
    intr = intrinsics_for(cfg.camera)
    trajectory = lawnmower(cfg.trajectory, intr, cfg.seed)
    assert len(trajectory) >= 40 and (intr.width, intr.height) == (640, 480)
    board_centre = np.array([*cfg.scene.board.centre_xy_m, cfg.scene.board.lift_m])
    uv = np.array([project(board_centre, p, intr)[0] for p in trajectory.world_from_cam])
    in_view = (uv[:, 0] > 0) & (uv[:, 0] < intr.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < intr.height - 1)
    assert in_view.sum() >= 5


@pytest.fixture(scope="module")
def no_hidden(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("none") / "survey"
    simulate_survey(out, replace(make_config("tiny", seed=1), rgbd=SMALL_RGBD), progress=False)
    return out


@pytest.mark.parametrize("name", sorted(HIDDEN_DEFAULTS))
def test_every_candidate_effect_can_be_hidden(name, no_hidden, tmp_path):
    """Each candidate renders as a hidden effect and changes the images it is hidden in."""
    simulate_survey(tmp_path / name, replace(make_config("tiny", hidden=[name], seed=1), rgbd=SMALL_RGBD),
                    progress=False)
    frames = sorted(p.name for p in (no_hidden / "images").iterdir())
    diff = np.mean([np.abs(read_png(tmp_path / name / "images" / f).astype(float)
                           - read_png(no_hidden / "images" / f)).mean() for f in frames])
    assert diff > 0.1, f"hidden {name} left the images unchanged (mean |diff| {diff:.3f} of 255)"


def test_learned_effect_cannot_be_hidden():
    with pytest.raises(SimulationError, match="backscatter_conv.*learned"):
        make_config("tiny", hidden=["backscatter_conv"])


def test_rgbd_scenes_resemble_the_site():
    from eval.synth.rgbd import (
        GREY_TEXTURES,
        SITE_BRIGHTNESS_SPREAD,
        SITE_TINT_SPREAD,
        TINTS,
        random_scene_config,
    )
    from eval.synth.scene import SceneConfig

    site = SceneConfig(tint_linear=(0.4, 0.3, 0.2), detail_texture="brick", overlay_texture="gravel")
    rng = np.random.default_rng(0)
    for _ in range(20):
        scene = random_scene_config(rng, 10.0, 0.1, site)
        assert (scene.detail_texture, scene.overlay_texture, scene.board) == ("brick", "gravel", None)
        ratio = np.array(scene.tint_linear) / np.array(site.tint_linear)
        assert np.all(np.abs(np.log(ratio)) < np.log(1 + SITE_BRIGHTNESS_SPREAD) + 4 * SITE_TINT_SPREAD)
    for seed in range(5):  # without a site: the generic sediment tints and grey photographs
        generic = random_scene_config(np.random.default_rng(seed), 10.0, 0.1)
        assert generic.tint_linear in TINTS
        assert {generic.detail_texture, generic.overlay_texture} <= set(GREY_TEXTURES)


def test_downsample_view_averages_blocks_and_drops_partial_depth():
    from eval.synth.rgbd import downsample_view

    rgb = np.arange(4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3)
    depth = np.full((4, 6), 2.0)
    depth[0, 1] = 4.0
    valid = np.ones((4, 6), bool)
    valid[3, 5] = False
    small_rgb, small_depth = downsample_view(rgb, depth, valid, 2)
    assert small_rgb.shape == (2, 3, 3) and small_depth.shape == (2, 3)
    np.testing.assert_allclose(small_rgb[0, 0], rgb[:2, :2].reshape(-1, 3).mean(0))
    assert small_depth[0, 0] == pytest.approx(2.5) and small_depth[1, 2] == 0.0 and small_depth[1, 1] == 2.0
