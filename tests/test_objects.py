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
