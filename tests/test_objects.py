"""Labelled objects of one colour seen at several ranges (eval/objects.py): the labels file's checks, the constancy
measures on synthetic frames whose answer is known, the pool footage's labels and their drawing tool."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from eval.objects import (
    apparent_size_ratio,
    chromaticity_figure,
    load_object_labels,
    measure_objects,
    object_pixels,
    parse_object_labels,
)
from watergan.errors import UserInputError

ROOT = Path(__file__).resolve().parents[1]
POOL_LABELS = ROOT / "benchmarks" / "data" / "subvo_objects.json"


def labels_dict(frames: dict, size=(60, 40), kind="white") -> dict:
    return {"source": "test", "notice": "", "image_size_px": list(size),
            "objects": [{"name": "board", "kind": kind, "description": "", "frames": frames}]}


def test_a_constant_object_under_exponential_falloff_spreads_as_the_formula_says():
    albedo, eta = np.array([0.6, 0.5, 0.4]), np.array([0.5, 0.1, 0.05])
    ranges_m = [1.0, 2.0, 4.0]
    names = [f"f{k}.png" for k in range(3)]
    # labelled at twice the measured size: the box [20, 10, 40, 30] is pixels 10..19 x 5..14 of the 30x20 frames
    labels = parse_object_labels(labels_dict({n: {"box_px": [20, 10, 40, 30]} for n in names}), "test", names)
    images, ranges = {}, {}
    for name, r in zip(names, ranges_m, strict=True):
        image = np.full((20, 30, 3), 0.05)
        image[5:15, 10:20] = albedo * np.exp(-eta * r)
        images[name], ranges[name] = image, np.where(np.arange(30) < 25, r, np.nan) * np.ones((20, 1))
    images[names[1]][5:8, 10:20] = 0.0  # pixels a correction left black are not the object's colour
    measured = measure_objects(images, labels, ranges=ranges)
    board = measured["objects"]["board"]

    c = np.array([albedo * np.exp(-eta * r) / (albedo * np.exp(-eta * r)).sum() for r in ranges_m])
    assert board["object_chromaticity_spread"] == pytest.approx((c.max(0) - c.min(0)).sum(), abs=1e-5)
    x = np.log(ranges_m) - np.log(ranges_m).mean()
    slope = (x @ (c - c.mean(0))) / (x @ x)
    assert board["chromaticity_slope_per_log_range"] == pytest.approx(slope.tolist(), abs=1e-5)
    assert board["median_range_m"] == 2.0 and board["range_ratio"] == 4.0
    assert board["pixels"] == [100, 70, 100]
    assert measured["objects_median_spread"] == board["object_chromaticity_spread"]

    kept = {n: np.where(images[n] > 0, 0.3, 0.0) for n in names}  # a method that keeps the colour at every range
    assert measure_objects(kept, labels, ranges=ranges)["objects_median_spread"] == 0.0


def test_the_regions_follow_a_warp_into_the_measured_geometry():
    labels = parse_object_labels(labels_dict({"a.jpg": {"polygon_px": [[0, 0], [20, 0], [20, 40], [0, 40]]}}), "t")
    flipped = object_pixels(labels, (20, 30), ["a.png"], warp=np.fliplr)["board"]["a.png"]
    columns = np.unique(flipped % 30)
    assert columns.min() >= 20 and columns.max() == 29  # the left third, mirrored; found by stem (jpg -> png)


@pytest.mark.parametrize("entry, message", [
    ({"box_px": [40, 10, 20, 30]}, "x0 < x1"),
    ({"box_px": [20, 10, 70, 30]}, "leaves the 60x40 frame"),
    ({"box_px": [20, -1, 30, 30]}, "leaves the 60x40 frame"),
    ({"box_px": [20, 10, 30]}, "4 numbers"),
    ({"polygon_px": [[1, 1], [5, 5]]}, "3 or more"),
    ({"box_px": [1, 1, 5, 5], "polygon_px": [[1, 1], [5, 1], [5, 5]]}, "exactly one"),
])
def test_a_labels_file_with_a_bad_region_is_refused(tmp_path, entry, message):
    path = tmp_path / "labels.json"
    path.write_text(json.dumps(labels_dict({"f0.png": entry})))
    with pytest.raises(UserInputError, match=message) as caught:
        load_object_labels(path, ["f0.png"])
    assert "board" in str(caught.value) and "f0.png" in str(caught.value) and str(path) in str(caught.value)


def test_a_labels_file_naming_an_unknown_frame_or_kind_is_refused():
    with pytest.raises(UserInputError, match="not a frame of the survey"):
        parse_object_labels(labels_dict({"other.png": {"box_px": [1, 1, 5, 5]}}), "t", ["f0.png"])
    with pytest.raises(UserInputError, match="'kind' must be one of"):
        parse_object_labels(labels_dict({"f0.png": {"box_px": [1, 1, 5, 5]}}, kind="green"), "t")


def test_the_pool_labels_follow_six_objects_across_range():
    labels = load_object_labels(POOL_LABELS)
    kinds = {o.kind for o in labels.objects}
    assert {"white", "red", "yellow", "cyan", "dark", "tiles_wall", "tiles_floor"} <= kinds
    assert len(labels.objects) >= 6 and labels.n_object_frames() >= 40
    assert sum(o.kind == "dark" for o in labels.objects) >= 2
    assert all(apparent_size_ratio(o) >= 1.5 for o in labels.objects)
    assert "CC BY 4.0" in labels.notice


def test_draw_objects_writes_a_picture_per_labelled_frame_and_a_sheet(tmp_path):
    import cv2

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from draw_objects import draw_objects

    survey = tmp_path / "survey"
    (survey / "images").mkdir(parents=True)
    for k in range(3):
        cv2.imwrite(str(survey / "images" / f"f{k}.jpg"), np.full((20, 30, 3), 90, np.uint8))
    (survey / "README.md").write_text("notice")
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps({**labels_dict({"f0.jpg": {"box_px": [2, 2, 40, 30]},
                                                 "f2.jpg": {"box_px": [2, 2, 20, 20]}})}))
    written = draw_objects(survey, labels, tmp_path / "out", sheet_width_px=60)
    assert sorted(p.name for p in written) == ["contact_sheet.png", "f0.png", "f2.png"]
    drawn = cv2.imread(str(tmp_path / "out" / "f0.png"))
    assert drawn.shape == (20, 30, 3) and (drawn != 90).any()  # the box at half the labels' size, outlined
    assert (tmp_path / "out" / "NOTICE.md").read_text() == "notice"


def test_the_chromaticity_figure_is_written(tmp_path):
    entry = {"range_m": [1.0, None, 2.0], "chromaticity": [[0.4, 0.3, 0.3], [0.4, 0.3, 0.3], [0.3, 0.3, 0.4]]}
    chromaticity_figure({"raw": {"board": entry}, "physics": {"board": entry}}, tmp_path / "f.png", note="notice")
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_dark_objects_radiance_is_read_against_the_veil_and_the_corners_of_its_interval():
    from eval.objects import dark_object_veil

    b_inf = {"value": [0.1, 0.2, 0.3], "low": [0.08, 0.18, 0.25], "high": [0.12, 0.22, 0.35]}
    beta = {"value": 0.5, "low": 0.4, "high": 0.6}
    gain = {"value": 2.0, "low": 1.9, "high": 2.1}
    veil = 2.0 * np.array([0.1, 0.2, 0.3]) * (1 - np.exp(-0.5 * 2.0))
    high = 2.1 * np.array([0.12, 0.22, 0.35]) * (1 - np.exp(-0.6 * 2.0))
    objects = {"block": {"kind": "dark", "frames": ["a.png", "b.png", "c.png"], "median_range_m": 2.0,
                         "range_m": [2.0, 2.0, None],
                         "mean_linear_rgb": [veil.tolist(), (high * [1.01, 0.9, 0.9]).tolist(), [0.1, 0.1, 0.1]]},
               "board": {"kind": "white", "frames": ["a.png"], "range_m": [1.0], "mean_linear_rgb": [[1, 1, 1]]}}
    out = dark_object_veil(objects, b_inf, beta, gain)
    assert list(out["objects"]) == ["block"]
    a, b, c = out["objects"]["block"]["frames"]
    np.testing.assert_allclose(a["veil"], veil, atol=1e-6)
    np.testing.assert_allclose(a["veil_high"], high, atol=1e-6)
    np.testing.assert_allclose(a["veil_low"], 1.9 * np.array([0.08, 0.18, 0.25]) * (1 - np.exp(-0.4 * 2)), atol=1e-6)
    assert a["inside"] == [True, True, True] and b["inside"] == [False, True, True]
    assert c["veil"] is None and c["inside"] is None  # no range there
    assert out["inside_fraction"] == pytest.approx(5 / 6, abs=1e-4)
    no_interval = dark_object_veil(objects, {**b_inf, "low": None}, beta)
    assert no_interval["objects"]["block"]["frames"][0]["inside"] is None and no_interval["inside_fraction"] is None


def _bench_real():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_real

    return bench_real


def test_the_model_s_floor_gives_each_camera_the_flat_seafloor_it_sees():
    from watergan.formation.inverse import flat_floor_depth, rays_cam

    bench_real = _bench_real()
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-3, 3, (400, 2)), np.zeros(400)]  # the floor z = 0, cameras above it
    poses = []
    for height, tilt in ((0.5, 0.3), (0.8, 1.0)):  # a camera tilted up from nadir by `tilt` radians about x
        c, s = np.cos(tilt), np.sin(tilt)
        pose = np.eye(4)
        pose[:3, :3] = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        pose[:3, 3] = [0.2, -0.1, height]
        poses.append(pose)
    altitude, down = bench_real.floor_navigation(floor, np.array(poses), ["f0.jpg", "f1.jpg"])
    assert altitude == pytest.approx({"f0": 0.5, "f1": 0.8})
    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    for stem, pose in zip(("f0", "f1"), poses, strict=True):
        depth = flat_floor_depth(altitude[stem], K, 48, 64, down[stem])
        rays_world = rays_cam(K, 48, 64) @ pose[:3, :3].T
        truth = -pose[2, 3] / rays_world[..., 2]  # camera z of the ray's meeting with z = 0
        seen = rays_world[..., 2] < -0.05
        np.testing.assert_allclose(depth[seen], truth[seen], rtol=1e-6)


def test_the_relief_ratio_divides_the_net_s_relief_error_by_the_plane_s(tmp_path):
    from eval.depth import RELIEF_M, DepthCompareConfig, Navigation, best_plane, compare_depth_folders
    from watergan.data import PinholeIntrinsics
    from watergan.formation.inverse import flat_floor_depth

    bench_real = _bench_real()
    camera = PinholeIntrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
    floor = flat_floor_depth(1.0, camera.K, 48, 64)
    ref = floor.copy()
    ref[10:30, 20:40] -= 0.3  # a block 30 cm high: relief pixels
    pred = ref + 0.02 * np.where(np.indices(ref.shape).sum(0) % 2, 1, -1)  # the net: 2 cm off everywhere
    for folder, depth in (("pred", pred), ("ref", ref)):
        (tmp_path / folder).mkdir()
        np.save(tmp_path / folder / "f0.npy", depth.astype(np.float32))
    compare_depth_folders(tmp_path / "pred", tmp_path / "ref", tmp_path / "out",
                          DepthCompareConfig(pred_dir=str(tmp_path / "pred"), metric=True),
                          Navigation(camera, {"f0": 1.0}))
    summary = bench_real.relief_summary(json.loads((tmp_path / "out" / "metrics.json").read_text()))
    assert summary["plane"] == "flat seafloor" and summary["held_out_frames"] == 1
    assert summary["net_relief_rmse_m"] == pytest.approx(0.02, rel=1e-3)
    relief = best_plane(ref, camera.K)[1] > RELIEF_M  # the block and the floor the best plane tilts away from
    plane = float(np.sqrt(np.mean((floor - ref)[relief] ** 2)))
    assert relief[10:30, 20:40].all() and summary["plane_relief_rmse_m"] == pytest.approx(plane, rel=1e-4)
    assert summary["depth_relief_ratio"] == pytest.approx(0.02 / plane, abs=1e-3)
    assert summary["depth_relief_ratio"] < 0.2


def test_the_report_shows_the_survey_s_objects_of_one_colour_and_says_not_run_without_labels(tmp_path):
    import cv2

    from pipeline.report import section_objects
    from pipeline.report_found import NotRun
    from pipeline.survey import SurveyResult
    from pipeline.workspace import Workspace

    survey = tmp_path / "survey"
    survey.mkdir()
    ws = Workspace(tmp_path / "ws")
    images = ws.stage_dir("survey") / "images"
    images.mkdir()
    for k, colour in enumerate(([200, 100, 50], [200, 100, 100])):  # the board's colour drifts: RGB, as written
        frame = np.full((40, 60, 3), 30, np.uint8)
        frame[10:30, 20:40] = colour
        cv2.imwrite(str(images / f"f{k}.png"), frame[..., ::-1])
    ws.save("survey", {"survey_dir": str(survey)}, SurveyResult(n_images=2, width=60, height=40, stereo=False,
                                                                simulated=False, rgbd_dir="", survey_dir=str(survey)))
    with pytest.raises(NotRun, match="objects.json"):
        section_objects(ws, tmp_path)
    (survey / "objects.json").write_text(json.dumps(labels_dict({f"f{k}.png": {"box_px": [20, 10, 40, 30]}
                                                                for k in range(2)})))
    body, info = section_objects(ws, tmp_path)
    from watergan.io import srgb_to_linear

    linear = srgb_to_linear(np.array([[200, 100, 50], [200, 100, 100]]) / 255.0)
    c = linear / linear.sum(1, keepdims=True)
    assert info["objects"] == 1 and info["median_spread"]["raw"] == pytest.approx((c.max(0) - c.min(0)).sum(),
                                                                                   abs=1e-4)
    assert "<th>board</th>" in body and "data:image/png;base64," in body and (tmp_path / "objects.png").is_file()
