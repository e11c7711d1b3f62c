"""Correcting an image folder with a restorer (an untrained tiny one: only files and formats matter), and the physics
correction's range for pixels without one on a small simulated survey."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pipeline.stages import STAGES
from watergan.data import DataError
from watergan.io import srgb_to_linear
from watergan.nets.restorer import Restorer, RestorerWidths
from watergan.restore_folder import correct_folder
from watergan.train_restorer import save_restorer

TINY = RestorerWidths(depth_core=(4, 6, 8, 8), colour_core=(4, 6, 8, 8), full_res=4)


def save_model(folder, **kwargs):
    """A tiny untrained restorer (``kwargs``: Restorer's modes) whose colour core does not start as the identity, so
    that what it is given changes what it writes."""
    model = Restorer(TINY, depth_hw=(16, 16), **kwargs).eval()
    with torch.no_grad():
        torch.nn.init.normal_(model.colour_net.core.head.weight, std=0.1)
    save_restorer(folder / "restorer.pt", model)
    return folder


def write_images(folder, names=("a.png", "b.png"), seed=0):
    """Random 40x32 8-bit frames."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for name in names:
        cv2.imwrite(str(folder / name), rng.integers(0, 256, (32, 40, 3), dtype=np.uint8))
    return folder


@pytest.fixture
def model_dir(tmp_path):
    save_restorer(tmp_path / "model" / "restorer.pt", Restorer(TINY, depth_hw=(16, 16)).eval())
    return tmp_path / "model"


@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(0)
    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "a8.png"), rng.integers(0, 256, (37, 45, 3), dtype=np.uint8))
    cv2.imwrite(str(folder / "b16.png"), rng.integers(0, 65536, (40, 48, 3), dtype=np.uint16))
    cv2.imwrite(str(folder / "c.jpg"), rng.integers(0, 256, (37, 45, 3), dtype=np.uint8))
    good = (folder / "a8.png").read_bytes()
    (folder / "d_truncated.png").write_bytes(good[: len(good) // 2])
    (folder / "e_garbage.png").write_bytes(b"not an image")
    return folder


def test_correct_keeps_bit_depth_and_names_and_reports_bad_files(tmp_path, model_dir, images):
    before = sorted(p.name for p in images.iterdir())
    out = tmp_path / "out"
    result = correct_folder(model_dir, images, out, batch_size=2, progress=False)
    assert result.corrected == 3 and result.already_done == 0 and len(result.failed) == 2
    assert any("d_truncated.png" in f and "truncated" in f for f in result.failed)
    assert any("e_garbage.png" in f for f in result.failed)
    assert sorted(p.name for p in images.iterdir()) == before  # nothing written into the input folder
    assert sorted(p.name for p in (out / "images").iterdir()) == ["a8.png", "b16.png", "c.png"]  # a JPEG's as PNG
    for stem, dtype, hw in (("a8", np.uint8, (37, 45)), ("b16", np.uint16, (40, 48)), ("c", np.uint8, (37, 45))):
        corrected = cv2.imread(str(next((out / "images").glob(f"{stem}.*"))), cv2.IMREAD_UNCHANGED)
        assert corrected.dtype == dtype and corrected.shape == (*hw, 3)
        depth = cv2.imread(str(out / "depth" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == hw
        rel = np.load(out / "depth" / f"{stem}.npy")
        assert rel.shape == hw and rel.dtype == np.float32 and 0 <= rel.min() and rel.max() <= 1
    assert '"failed": 2' in (out / "summary.json").read_text()


@pytest.mark.parametrize("image_format, names, dtypes", [
    ("png", ["a8.png", "b16.png", "c.png"], [np.uint8, np.uint16, np.uint8]),
    ("tiff", ["a8.tif", "b16.tif", "c.tif"], [np.uint8, np.uint16, np.uint8]),
    ("jpeg", ["a8.jpg", "b16.jpg", "c.jpg"], [np.uint8, np.uint8, np.uint8]),
])
def test_the_corrected_frames_format_is_an_option(tmp_path, model_dir, images, image_format, names, dtypes):
    """PNG and TIFF keep the input's bit depth (a 16-bit frame stays 16-bit), JPEG is 8 bits; a rerun in the same
    format finds its outputs done."""
    out = tmp_path / "out"
    correct_folder(model_dir, images, out, progress=False, image_format=image_format)
    assert sorted(p.name for p in (out / "images").iterdir()) == names
    assert [cv2.imread(str(out / "images" / n), cv2.IMREAD_UNCHANGED).dtype for n in names] == dtypes
    assert correct_folder(model_dir, images, out, progress=False, image_format=image_format).already_done == 3
    with pytest.raises(DataError, match="image_format must be one of"):
        correct_folder(model_dir, images, out, progress=False, image_format="bmp")


def test_default_skips_done_images_and_force_redoes(tmp_path, model_dir, images):
    out = tmp_path / "out"
    correct_folder(model_dir, images, out, progress=False)
    target = out / "images" / "a8.png"
    stamp = target.stat().st_mtime_ns
    again = correct_folder(model_dir, images, out, progress=False)
    assert again.corrected == 0 and again.already_done == 3
    assert target.stat().st_mtime_ns == stamp
    forced = correct_folder(model_dir, images, out, force=True, progress=False)
    assert forced.corrected == 3 and forced.already_done == 0


def test_refuses_to_write_into_the_input_folder(tmp_path, model_dir, images):
    with pytest.raises(DataError, match="input folder"):
        correct_folder(model_dir, images, images, progress=False)
    with pytest.raises(DataError, match="input folder"):
        correct_folder(model_dir, images, images.parent, progress=False)  # OUT/images is the input folder


def test_shared_stems_are_an_error(tmp_path, model_dir, images):
    cv2.imwrite(str(images / "a8.jpg"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(DataError, match="share the stem"):
        correct_folder(model_dir, images, tmp_path / "out", progress=False)


def test_a_restorer_that_takes_altitude_reads_the_navigation(tmp_path):
    """Without a navigation file, or with one that lacks an image, nothing is corrected and the error says
    what to give; with altitudes, the same image corrected at another altitude comes out differently."""
    save_model(tmp_path / "model", altitude=True)
    images = write_images(tmp_path / "survey" / "images")
    with pytest.raises(DataError, match="no navigation file .*--no-altitude"):
        correct_folder(tmp_path / "model", images, tmp_path / "out", progress=False)
    survey = tmp_path / "survey" / "survey.json"  # the default: beside the images folder
    survey.write_text(json.dumps({"frames": ["a.png"], "nav_altitude_m": [2.0]}))
    with pytest.raises(DataError, match="no altitude for 1 of the 2 images .e.g. b.png"):
        correct_folder(tmp_path / "model", images, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
    survey.write_text(json.dumps({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.0, 2.0]}))
    assert correct_folder(tmp_path / "model", images, tmp_path / "near", progress=False).corrected == 2
    far = tmp_path / "far.json"
    far.write_text(json.dumps({"frames": ["b.png", "a.png"], "nav_altitude_m": [3.5, 3.5]}))
    correct_folder(tmp_path / "model", images, tmp_path / "far", progress=False, navigation=far)
    a_near, a_far = (cv2.imread(str(tmp_path / d / "images" / "a.png")).astype(int) for d in ("near", "far"))
    assert np.abs(a_near - a_far).max() > 2


def test_an_rgbd_restorer_corrects_with_each_pixel_s_range(tmp_path):
    """An RGB-D restorer needs a range map per image (a clear error before any work otherwise); holes take the
    image's median range; a farther range map gives another correction of the same image."""
    from watergan.io import write_depth_png

    save_model(tmp_path / "model", range_input=True)
    images = write_images(tmp_path / "images")
    with pytest.raises(DataError, match="without range maps .monocular mode.*camera.json.*or give --range-dir"):
        correct_folder(tmp_path / "model", images, tmp_path / "out", progress=False)
    near, far = tmp_path / "near_range", tmp_path / "far_range"
    near_m = np.full((32, 40), 1.5)
    near_m[:4] = 0  # a hole
    write_depth_png(near / "a.png", near_m)
    with pytest.raises(DataError, match="1 of the 2 images have no range map .e.g. b.png.*--mode monocular"):
        correct_folder(tmp_path / "model", images, tmp_path / "out", progress=False, range_dir=near)
    assert not (tmp_path / "out").exists()
    write_depth_png(near / "b.png", near_m)
    for name in ("a.png", "b.png"):
        write_depth_png(far / name, np.full((32, 40), 4.0))
    assert correct_folder(tmp_path / "model", images, tmp_path / "near", progress=False, range_dir=near).corrected == 2
    correct_folder(tmp_path / "model", images, tmp_path / "far", progress=False, range_dir=far)
    a_near, a_far = (cv2.imread(str(tmp_path / d / "images" / "a.png")).astype(int) for d in ("near", "far"))
    assert np.abs(a_near - a_far).max() > 2


def test_lanes_side_by_side_write_the_same_files_and_leave_torch_s_threads(tmp_path, monkeypatch):
    """Batches corrected side by side on the CPU (watergan.parallel.cpu_lanes) give the bytes one lane gives, with
    batches of every size (a short last batch), and torch's thread count is left as it was."""
    import watergan.restore_folder as correct

    save_model(tmp_path / "model")
    images = write_images(tmp_path / "images", [f"f{k}.png" for k in range(7)], seed=3)
    threads = torch.get_num_threads()
    outputs = {}
    for lanes in (1, 3):
        monkeypatch.setattr(correct, "cpu_lanes", lambda lanes=lanes: lanes)
        result = correct_folder(tmp_path / "model", images, tmp_path / f"out{lanes}", batch_size=2, progress=False)
        assert result.corrected == 7 and torch.get_num_threads() == threads
        outputs[lanes] = {p.relative_to(tmp_path / f"out{lanes}"): p.read_bytes()
                          for p in sorted((tmp_path / f"out{lanes}").rglob("*")) if p.suffix in (".png", ".npy")}
    assert len(outputs[1]) == 21 and outputs[1] == outputs[3]


def test_an_rgbd_restorer_in_monocular_mode_takes_a_flat_seafloor_at_the_altitude(tmp_path):
    """Without range maps an RGB-D restorer corrects each frame at the range of a flat seafloor at its navigation
    altitude (with the camera's intrinsics; each missing input is a clear error): the same colours as range maps of
    that floor give, another colour at another altitude; a monocular restorer has no RGB-D mode."""
    from watergan.data import PinholeIntrinsics
    from watergan.formation.inverse import flat_floor_range
    from watergan.io import write_depth_png

    save_model(tmp_path / "model", range_input=True)
    images = write_images(tmp_path / "survey" / "images")
    camera = PinholeIntrinsics(30.0, 30.0, 19.5, 15.5, 40, 32)
    (tmp_path / "survey" / "camera.json").write_text(json.dumps(camera.to_json()))
    with pytest.raises(DataError, match="no navigation file .*--range-dir"):
        correct_folder(tmp_path / "model", images, tmp_path / "out", progress=False)
    (tmp_path / "survey" / "survey.json").write_text(json.dumps({"frames": ["a.png", "b.png"],
                                                                  "nav_altitude_m": [1.5, 3.0]}))
    mono = correct_folder(tmp_path / "model", images, tmp_path / "mono", progress=False)
    assert (mono.mode, mono.corrected) == ("monocular", 2)
    floor = tmp_path / "floor"
    for name, altitude_m in (("a.png", 1.5), ("b.png", 3.0)):
        write_depth_png(floor / name, flat_floor_range(altitude_m, camera.K, 32, 40))
    rgbd = correct_folder(tmp_path / "model", images, tmp_path / "rgbd", progress=False, range_dir=floor)
    assert rgbd.mode == "rgb-d"
    for name in ("a.png", "b.png"):
        m, r = (cv2.imread(str(tmp_path / d / "images" / name)).astype(int) for d in ("mono", "rgbd"))
        assert np.abs(m - r).max() <= 1  # the range maps hold millimetres
    far = correct_folder(tmp_path / "model", images, tmp_path / "far", progress=False, range_dir=floor,
                         mode="monocular")
    assert far.mode == "monocular"  # the mode wins over the range maps
    a_floor = flat_floor_range(1.5, camera.K, 32, 40)
    corner_m = 1.5 * np.sqrt(1 + (19.5 / 30) ** 2 + (15.5 / 30) ** 2)  # r = a |K^-1 (x, y, 1)| at pixel (0, 0)
    assert a_floor.min() == pytest.approx(1.5, abs=0.01) and a_floor[0, 0] == pytest.approx(corner_m, rel=1e-9)
    a_15 = cv2.imread(str(tmp_path / "mono" / "images" / "a.png")).astype(int)
    (tmp_path / "survey" / "survey.json").write_text(json.dumps({"frames": ["a.png", "b.png"],
                                                                  "nav_altitude_m": [3.0, 3.0]}))
    correct_folder(tmp_path / "model", images, tmp_path / "a3", progress=False)
    assert np.abs(a_15 - cv2.imread(str(tmp_path / "a3" / "images" / "a.png")).astype(int)).max() > 2
    save_restorer(tmp_path / "mono_model" / "restorer.pt", Restorer(TINY, depth_hw=(16, 16)).eval())
    with pytest.raises(DataError, match="trained monocular .* no RGB-D mode"):
        correct_folder(tmp_path / "mono_model", images, tmp_path / "x", progress=False, mode="rgb-d")


def test_a_flat_seafloor_s_range_follows_the_camera_s_attitude(tmp_path):
    """With the navigation's "down" in the camera frame (an attitude sensor's gravity), the flat seafloor's range is
    that of the tilted camera's rays: for a camera pitched by 30 degrees, the ray along "down" meets the floor at the
    altitude and the optical axis at a / cos 30; a malformed vector is a clear error."""
    from watergan.data import read_nav_down
    from watergan.formation.inverse import flat_floor_range

    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    tilt = np.radians(30.0)
    down = np.array([0.0, np.sin(tilt), np.cos(tilt)])  # the floor below appears towards the image's bottom
    r = flat_floor_range(2.0, K, 121, 101, down)
    assert r[40, 50] == pytest.approx(2.0 / np.cos(tilt))
    y_down = int(round(40 + 100 * np.tan(tilt)))  # the pixel whose ray is "down"
    assert r[y_down, 50] == pytest.approx(2.0, rel=2e-3) and r[:, 50].min() == pytest.approx(2.0, rel=2e-3)
    assert r[0, 50] > r[40, 50] > r[80, 50]  # farther towards the horizon, nearer towards "down"
    np.testing.assert_allclose(flat_floor_range(2.0, K, 81, 101, (0.0, 0.0, 1.0)), flat_floor_range(2.0, K, 81, 101))
    survey = tmp_path / "survey.json"
    survey.write_text(json.dumps({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.0, 2.0],
                                  "nav_down_cam": [list(down), [0.0, 0.0, 1.0]]}))
    np.testing.assert_allclose(read_nav_down(survey)["a.png"], down)
    survey.write_text(json.dumps({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.0, 2.0],
                                  "nav_down_cam": [list(down), [0.0, 0.0, -1.0]]}))
    with pytest.raises(DataError, match="nav_down_cam is not a unit vector .* for 1 frames .e.g. b.png"):
        read_nav_down(survey)
    survey.write_text(json.dumps({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.0, 2.0]}))
    assert read_nav_down(survey) is None


def test_the_allocator_keeps_freed_memory_on_glibc():
    """keep_freed_memory's two mallopt calls are accepted by this machine's C library (glibc on Linux); where there
    is none the correction runs with the allocator's defaults."""
    import platform

    from watergan.parallel import keep_freed_memory

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    assert keep_freed_memory()


# ---------------------------------------------------------------------------------------- range everywhere
ETA = np.array([0.45, 0.14, 0.2])
B_INF = np.array([0.05, 0.2, 0.3])
BETA = np.array([0.35, 0.3, 0.3])
STACK = [{"name": "attenuation", "params": {"eta_per_m": ETA.tolist()}},
         {"name": "backscatter", "params": {"b_inf": B_INF.tolist(), "beta_per_m": BETA.tolist()}}]
CAMERA_K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
H, W = 48, 64
OPEN_WATER = (slice(0, 16), slice(None))  # pure backscatter: no surface, no range
SMALL_HOLE = (slice(30, 33), slice(40, 43))  # a hole in the dense range on the floor
TIMESTAMP = (slice(42, 48), slice(0, 20))  # not the scene


def _underwater(j: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """I = J exp(-eta r) + B_inf (1 - exp(-beta r)) (the stack above); an infinite range gives B_inf."""
    r = range_m[..., None]
    return j * np.exp(-ETA * r) + B_INF * -np.expm1(-BETA * r)


def _simulated_workspace(tmp_path, altitudes_m=(1.5, 2.0, 2.5)):
    """A workspace with the records the physics correction reads, as the sfm, dense, range and water stages would
    save them, for a camera over a flat floor (truth: in-air colour J and range) whose frames see open water in their
    top rows (pure backscatter) and a burned-in timestamp (the scene mask); the range stage's maps have no range in
    the open water and a 3x3 hole on the floor. Returns (workspace, images folder, truth {name: (J, range)})."""
    from eval.tracks import Tracks
    from pipeline.dense import DenseConfig, DenseResult
    from pipeline.range import RangeConfig, RangeResult
    from pipeline.sfm import SfmConfig, SfmResult
    from pipeline.water import WaterResult, WaterStage
    from pipeline.workspace import Workspace
    from watergan.formation.inverse import flat_floor_range
    from watergan.io import linear_to_srgb, quantise, write_depth_png, write_png, write_scene_mask

    ws = Workspace(tmp_path / "ws")
    images = ws.stage_dir("survey") / "images"
    images.mkdir()
    ranges = ws.stage_dir("range") / "range"
    rng = np.random.default_rng(5)
    names, truth = [f"f{k}.png" for k in range(len(altitudes_m))], {}
    for name, altitude_m in zip(names, altitudes_m, strict=True):
        j = cv2.resize(rng.uniform(0.1, 0.7, (6, 8, 3)), (W, H), interpolation=cv2.INTER_CUBIC).clip(0.1, 0.7)
        range_m = flat_floor_range(altitude_m, CAMERA_K, H, W)
        seen = range_m.copy()
        seen[OPEN_WATER] = np.inf
        write_png(images / name, quantise(linear_to_srgb(_underwater(j, seen)), 16))
        measured = range_m.copy()
        measured[OPEN_WATER] = 0.0
        measured[SMALL_HOLE] = 0.0
        write_depth_png(ranges / f"{Path(name).stem}.png", measured)
        truth[name] = (j, range_m)
    scene = np.ones((H, W), bool)
    scene[TIMESTAMP] = False
    write_scene_mask(ws.stage_dir("sfm") / "scene_mask.png", scene)
    n = len(names)
    Tracks(image_names=np.array(names), registered=np.ones(n, bool), world_from_cam=np.tile(np.eye(4), (n, 1, 1)),
           K=CAMERA_K, width=W, height=H, point_id=np.zeros(0, np.int64), xyz=np.zeros((0, 3)),
           rgb=np.zeros((0, 3), np.uint8), obs_point=np.zeros(0, np.int64), obs_image=np.zeros(0, np.int64),
           obs_xy=np.zeros((0, 2), np.float32)).save(ws.stage_dir("sfm") / "tracks.npz")
    sfm, dense, water = (STAGES[s].folder for s in ("sfm", "dense", "water"))
    ws.save("sfm", SfmConfig(), SfmResult(
        model_dir=f"{sfm}/model", tracks=f"{sfm}/tracks.npz", n_images=n, n_registered=n, n_points=0,
        mean_track_length=0.0, mean_reprojection_error_px=0.0, matching="sequential", scale_method="altitude",
        scale_factor=1.0, scale_spread=0.0, seconds=0.0, scene_mask=f"{sfm}/scene_mask.png"))
    ws.save("dense", DenseConfig(), DenseResult(depth_dir=f"{dense}/depth", pairs={}, coverage={}, mean_coverage=0.0))
    ws.save("range", RangeConfig(), RangeResult(range_dir=ws.relative(ranges), mesh_fraction=0.0, range_missing=0.0,
                                                normal_smooth_px=24.0, n_frames=n, seconds=0.0))
    ws.save("water", WaterStage(), WaterResult(
        water_json=f"{water}/water.json", summary="", stack=STACK, board=False, at_bounds=[], converged=True,
        seconds=0.0, estimate_seconds=0.0, observations="", n_observations=0, n_points=0))
    return ws, images, truth


def test_fill_range_inpaints_small_holes_and_takes_the_far_range_in_large_ones():
    """A hole within fill_px of measured range takes the range around it (a tilted floor's, to a millimetre), a larger
    one the far range; pixels outside the scene are marked so and keep their range; without any measured range every
    scene pixel takes the far range."""
    from watergan.correction_range import RangeFrom, fill_range
    from watergan.formation.inverse import flat_floor_range

    down = np.array([0.0, np.sin(0.4), np.cos(0.4)])  # pitched: the range changes across the frame
    true = flat_floor_range(2.0, CAMERA_K, H, W, down)
    measured = true.copy()
    measured[OPEN_WATER] = np.nan
    measured[SMALL_HOLE] = 0.0
    measured[5, 5] = np.inf
    scene = np.ones((H, W), bool)
    scene[TIMESTAMP] = False
    r, source = fill_range(measured, 7.5, fill_px=6.0, scene=scene)
    assert r.dtype == np.float32 and source.dtype == np.uint8
    assert (source[SMALL_HOLE] == RangeFrom.neighbours).all()
    np.testing.assert_allclose(r[SMALL_HOLE], true[SMALL_HOLE], atol=2e-3)
    assert (source[OPEN_WATER] == RangeFrom.far).all() and (r[OPEN_WATER] == 7.5).all()
    assert (source[TIMESTAMP] == RangeFrom.not_scene).all()
    np.testing.assert_allclose(r[TIMESTAMP], true[TIMESTAMP], rtol=1e-6)
    rest = np.ones((H, W), bool)
    for region in (OPEN_WATER, SMALL_HOLE, TIMESTAMP):
        rest[region] = False
    assert (source[rest] == RangeFrom.measured).all() and np.array_equal(r[rest], true[rest].astype(np.float32))
    r, source = fill_range(np.zeros((H, W)), 3.0, scene=scene)
    assert (source[scene] == RangeFrom.far).all() and (r == 3.0).all()
    with pytest.raises(ValueError, match="far range"):
        fill_range(measured, float("nan"), fill_px=6.0)


def test_a_large_hole_on_the_near_floor_takes_the_plane_through_the_frames_measured_range():
    """With the intrinsics, a large hole on the camera's side of its edge takes the range of the plane through the
    frame's measured points (a forward camera's bottom rows, to a millimetre); a hole the plane puts beyond its edge
    (the top rows: open water, a far wall), or in a frame whose measured points are no plane, takes the far range."""
    from watergan.correction_range import RangeFrom, fill_range
    from watergan.formation.inverse import flat_floor_range

    true = flat_floor_range(2.0, CAMERA_K, H, W, np.array([0.0, np.sin(0.4), np.cos(0.4)]))  # pitched
    near_hole = (slice(36, 48), slice(None))  # the nearest rows
    measured = true.copy()
    measured[OPEN_WATER] = measured[near_hole] = np.nan
    r, source = fill_range(measured, 7.5, fill_px=6.0, K=CAMERA_K)
    assert (source[near_hole] == RangeFrom.plane).all()
    np.testing.assert_allclose(r[near_hole], true[near_hole], atol=1e-3)
    assert (source[OPEN_WATER] == RangeFrom.far).all() and (r[OPEN_WATER] == 7.5).all()
    _, source = fill_range(measured, 7.5, fill_px=6.0)  # without the intrinsics: no plane
    assert (source[near_hole] == RangeFrom.far).all()
    rough = np.where(np.isnan(measured), np.nan, np.random.default_rng(1).uniform(0.5, 5.0, measured.shape))
    _, source = fill_range(rough, 7.5, fill_px=6.0, K=CAMERA_K)  # no plane through these points
    assert (source[near_hole] == RangeFrom.far).all()


def test_the_gain_cap_holds_the_gain_and_removes_the_whole_veil():
    """cap_gain: J = min(exp(g), G) (I - C) where capped, the fields unchanged elsewhere."""
    from watergan.correction_range import cap_gain

    rng = np.random.default_rng(0)
    fields = torch.from_numpy(rng.normal(0, 2, (6, 5, 7)))
    capped = torch.from_numpy(rng.random((1, 5, 7)) < 0.5)
    image = torch.from_numpy(rng.random((3, 5, 7)))
    held = cap_gain(fields, capped, 4.0)
    gain, veil = fields[:3].exp(), -fields[3:] * (-fields[:3]).exp()  # J = exp(g) (I - C), C = -o exp(-g)
    expected = torch.where(capped, gain.clamp_max(4.0), gain) * (image - veil)
    torch.testing.assert_close(held[:3].exp() * image + held[3:], expected)
    assert torch.equal(held[:, ~capped[0]], fields[:, ~capped[0]])


def test_the_physics_correction_ranges_every_pixel_and_passes_the_non_scene_through(tmp_path):
    """With open water and a hole in the range maps and a timestamp masked out: no pixel of the scene is written
    black, the hole's pixels (ranged from their neighbours) are corrected to their in-air colour, the open water at
    the survey's far range (the 95th percentile of its ranges) to a finite colour no brighter than the capped gain
    allows (a gain held at 2 holds red, whose exp(eta r) is about 4 there), the timestamp's pixels are the raw input's
    levels exactly, and range_from/ and mask/ say which pixel got which range."""
    from pipeline.correct import CorrectStage

    ws, images, truth = _simulated_workspace(tmp_path)
    result = ws.run("correct", CorrectStage(fill_px=6.0, progress=False))
    _check_ranged_everywhere(ws, images, truth, result, 10.0)
    held = ws.run("correct", CorrectStage(fill_px=6.0, far_max_gain=2.0, progress=False))
    assert np.exp(ETA[0] * held.far_range_m) > 3.5
    _check_ranged_everywhere(ws, images, truth, held, 2.0)


def _check_ranged_everywhere(ws, images, truth, result, max_gain):
    from watergan.correction_range import RangeFrom

    assert result.physics == f"{STAGES['correct'].folder}/physics" and result.restorer == ""
    scene = np.ones((H, W), bool)
    scene[TIMESTAMP] = False
    ranged = scene.copy()
    ranged[OPEN_WATER] = ranged[SMALL_HOLE] = False
    measured = np.concatenate([r[ranged] for _, r in truth.values()])
    assert result.far_range_m == pytest.approx(np.percentile(measured, 95), abs=0.01)
    scene_px = scene.sum()
    assert result.far_fraction == pytest.approx(np.count_nonzero(scene[OPEN_WATER]) / scene_px)
    assert result.filled_fraction == pytest.approx(9 / scene_px)
    for name, (j, _) in truth.items():
        stem = Path(name).stem
        out = cv2.imread(str(ws.path(result.physics_images) / name), cv2.IMREAD_UNCHANGED)
        raw = cv2.imread(str(images / name), cv2.IMREAD_UNCHANGED)
        assert out.dtype == np.uint16 and out.shape == (H, W, 3)
        assert (out[scene].max(axis=1) > 0).all()  # no scene pixel black
        assert np.array_equal(out[~scene], raw[~scene])  # not the scene: as it came
        source = cv2.imread(str(ws.path(result.physics_range_from) / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert (source[SMALL_HOLE] == RangeFrom.neighbours).all() and (source[OPEN_WATER][scene[OPEN_WATER]]
                                                                         == RangeFrom.far).all()
        assert (source[~scene] == RangeFrom.not_scene).all()
        assert np.count_nonzero(source == RangeFrom.measured) == scene_px - 9 - np.count_nonzero(scene[OPEN_WATER])
        mask = cv2.imread(str(ws.path(result.physics_mask) / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(mask == 255, source == RangeFrom.measured)
        corrected = srgb_to_linear(out[..., ::-1] / 65535.0)
        np.testing.assert_allclose(corrected[SMALL_HOLE], j[SMALL_HOLE], atol=0.01)  # the hole: as the floor
        floor = (source == RangeFrom.measured)
        assert np.abs(corrected[floor] - j[floor]).max() < 0.01
        # open water is B_inf, what the veil at the far range leaves of it: B_inf exp(-beta r), times the gain
        r_far = result.far_range_m
        expected = np.minimum(np.exp(ETA * r_far), max_gain) * B_INF * np.exp(-BETA * r_far)
        water = corrected[OPEN_WATER][scene[OPEN_WATER]]
        np.testing.assert_allclose(water, np.broadcast_to(expected, water.shape), atol=0.005)


def test_an_rgbd_restorer_ranges_every_pixel_and_passes_the_non_scene_through(tmp_path):
    """A range map with a large hole, and one with no range at all, are corrected (the hole and the empty map at the
    survey's far range, the 95th percentile of the maps' ranges unless given: another far range gives another colour
    there); with a scene mask the pixels that are not the scene are the input's levels exactly."""
    from watergan.io import write_depth_png, write_scene_mask

    save_model(tmp_path / "model", range_input=True)
    images = write_images(tmp_path / "images")
    ranges = tmp_path / "range"
    holed = np.full((32, 40), 1.5)
    holed[:20] = 0.0  # more than fill_px from any range: the far range
    write_depth_png(ranges / "a.png", holed)
    write_depth_png(ranges / "b.png", np.zeros((32, 40)))
    scene = np.ones((32, 40), bool)
    scene[26:, :12] = False
    write_scene_mask(tmp_path / "scene.png", scene)
    runs = {}
    for far_range_m in (None, 6.0):
        out = tmp_path / f"out_{far_range_m}"
        done = correct_folder(tmp_path / "model", images, out, progress=False, range_dir=ranges, fill_px=4.0,
                              scene_mask=tmp_path / "scene.png", far_range_m=far_range_m)
        assert done.corrected == 2 and not done.failed
        runs[far_range_m] = {n: cv2.imread(str(out / "images" / n)).astype(int) for n in ("a.png", "b.png")}
        for name in ("a.png", "b.png"):
            raw = cv2.imread(str(images / name)).astype(int)
            assert np.array_equal(runs[far_range_m][name][~scene], raw[~scene])
            assert np.abs(runs[far_range_m][name][scene] - raw[scene]).max() > 2  # the scene is corrected
    assert np.abs(runs[None]["a.png"][:20] - runs[6.0]["a.png"][:20]).max() > 2
    assert np.abs(runs[None]["b.png"] - runs[6.0]["b.png"])[scene].max() > 2
