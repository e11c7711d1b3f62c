"""Correcting an image folder with a restorer (an untrained tiny one: only files and formats matter)."""

import json

import cv2
import numpy as np
import pytest
import torch

from pipeline.correct import correct_folder
from watergan.data import DataError
from watergan.nets.restorer import Restorer, RestorerWidths
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
    """Batches corrected side by side on the CPU (pipeline.correct.cpu_lanes) give the bytes one lane gives, with
    batches of every size (a short last batch), and torch's thread count is left as it was."""
    import pipeline.correct as correct

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

    from pipeline.correct import keep_freed_memory

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    assert keep_freed_memory()
