"""The lens models (watergan.lens) against COLMAP's own projection, and camera.json's two forms."""

import json

import numpy as np
import pytest

from watergan.data import DataError
from watergan.lens import (
    COLMAP_MODELS,
    FISHEYE,
    Lens,
    camera_from_colmap,
    camera_matrix,
    distorted_pixels,
    distortion_of,
    undistort_image,
    undistorted_points,
)
from watergan.survey_files import read_camera_json

#: A moderate wide lens in each of COLMAP's models (its parameter order, pixel centres at +0.5).
COLMAP_CAMERAS = {
    "SIMPLE_PINHOLE": [450.0, 320.0, 240.0],
    "PINHOLE": [450.0, 455.0, 320.0, 240.0],
    "SIMPLE_RADIAL": [450.0, 320.0, 240.0, -0.15],
    "RADIAL": [450.0, 320.0, 240.0, -0.2, 0.05],
    "OPENCV": [450.0, 455.0, 321.0, 238.0, -0.2, 0.05, 0.001, -0.002],
    "FULL_OPENCV": [450.0, 455.0, 321.0, 238.0, -0.2, 0.05, 0.001, -0.002, 0.01, 0.02, -0.01, 0.005],
    "SIMPLE_RADIAL_FISHEYE": [300.0, 320.0, 240.0, 0.05],
    "RADIAL_FISHEYE": [300.0, 320.0, 240.0, 0.05, -0.01],
    "OPENCV_FISHEYE": [300.0, 305.0, 321.0, 238.0, 0.05, -0.01, 0.004, -0.001],
}


@pytest.mark.parametrize("model", sorted(COLMAP_MODELS))
def test_each_colmap_model_projects_as_colmap_does(model):
    """camera.json's named form of COLMAP's model and params projects points where pycolmap's camera does, within
    1e-6 px, over rays out to 45 degrees (OpenCV's pixel convention here, COLMAP's +0.5 there)."""
    import pycolmap

    params = COLMAP_CAMERAS[model]
    camera = camera_from_colmap(model, params, "test")
    lens = distortion_of(camera)
    xy = np.random.default_rng(0).uniform(-0.7, 0.7, (200, 2))
    ours = distorted_pixels(xy, camera_matrix(camera), lens) if lens is not None else \
        xy * [camera["fx"], camera["fy"]] + [camera["cx"], camera["cy"]]
    colmap = pycolmap.Camera(model=model, width=640, height=480, params=params)
    theirs = colmap.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], 1)) - 0.5
    assert np.abs(ours - theirs).max() < 1e-6
    if lens is not None:  # and back: COLMAP's model and parameters of the lens give the same camera
        name, back = lens.to_colmap(camera)
        again = pycolmap.Camera(model=name, width=640, height=480, params=back)
        assert np.abs(again.img_from_cam(np.concatenate([xy, np.ones((len(xy), 1))], 1)) - 0.5 - ours).max() < 1e-6


@pytest.mark.parametrize("lens", [Lens("opencv", (-0.25, 0.07, 0.001, -0.001, 0.0)),
                                  Lens("fisheye", (0.05, -0.01, 0.004, -0.001))])
def test_undistorting_inverts_the_lens_points_and_images(lens):
    """A pixel's undistorted coordinates map back to it (1e-6 px), and a frame rendered through the lens and
    undistorted matches the pinhole frame within 1 % of the pattern's range inside the frame."""
    K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
    j, i = np.mgrid[0:240, 0:320].astype(np.float64)
    pixels = np.stack([i.ravel(), j.ravel()], 1)
    xy = undistorted_points(pixels, K, lens)
    assert np.abs(distorted_pixels(xy, K, lens) - pixels).max() < 1e-6

    def pattern(x, y):  # smooth, so that bilinear resampling is exact to well under 1 %
        return 0.5 + 0.25 * np.sin(20 * x) * np.cos(17 * y)

    seen = pattern(xy[:, 0], xy[:, 1]).reshape(240, 320).astype(np.float32)
    pinhole = pattern((i - K[0, 2]) / K[0, 0], (j - K[1, 2]) / K[1, 1])
    undistorted = undistort_image(seen, K, lens)
    inside = (slice(30, -30), slice(40, -40))
    assert np.abs(undistorted[inside] - pinhole[inside]).max() < 0.01 * 0.5
    assert np.abs(seen[inside] - pinhole[inside]).max() > 0.05  # the lens does move the pattern


def test_camera_json_takes_colmap_s_form_and_names_what_is_wrong(tmp_path):
    path = tmp_path / "camera.json"

    def read(camera):
        path.write_text(json.dumps(camera))
        return read_camera_json(path)

    camera = read({"model": "OPENCV_FISHEYE", "params": COLMAP_CAMERAS["OPENCV_FISHEYE"], "width": 640,
                   "height": 480})
    assert (camera["fx"], camera["cx"], camera["cy"]) == (300.0, 320.5, 237.5)
    assert distortion_of(camera) == Lens(FISHEYE, (0.05, -0.01, 0.004, -0.001))
    named = read({"fx": 400, "fy": 400, "cx": 319.5, "cy": 239.5, "width": 640, "height": 480, "k1": -0.2})
    assert distortion_of(named).coefficients == (-0.2, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(DataError, match="THIN_PRISM_FISHEYE.*not supported; use one of"):
        read({"model": "THIN_PRISM_FISHEYE", "params": [1.0] * 12, "width": 640, "height": 480})
    with pytest.raises(DataError, match=r"RADIAL takes 5 parameters \(f, cx, cy, k1, k2\), got 4"):
        read({"model": "RADIAL", "params": [400, 320, 240, 0.1], "width": 640, "height": 480})
    with pytest.raises(DataError, match="gives COLMAP's params and fx: give one of them"):
        read({"model": "PINHOLE", "params": [400, 400, 320, 240], "fx": 400, "width": 640, "height": 480})
    with pytest.raises(DataError, match="p1 is not a coefficient of the fisheye lens"):
        read({**named, "lens_model": "fisheye", "p1": 0.01})
    with pytest.raises(DataError, match="lens_model = 'kannala'"):
        read({**named, "lens_model": "kannala"})


def test_the_survey_stage_reads_colmap_s_form_into_the_workspace(tmp_path):
    """A survey whose camera.json is COLMAP's OPENCV camera: the workspace gets the frames undistorted and its own
    camera.json in the named form (OpenCV's pixel convention, no lens left), the user's files unchanged."""
    import cv2

    from pipeline.survey import SurveyConfig
    from pipeline.workspace import Workspace

    survey = tmp_path / "survey"
    (survey / "images").mkdir(parents=True)
    (tmp_path / "rgbd" / "rgb").mkdir(parents=True)  # an in-air set given, so that none is rendered
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png", "c.png"):
        cv2.imwrite(str(survey / "images" / name), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    user_camera = {"model": "OPENCV", "params": [60.0, 61.0, 32.0, 24.0, -0.1, 0.01, 0.0, 0.0], "width": 64,
                   "height": 48}
    (survey / "camera.json").write_text(json.dumps(user_camera))
    before = (survey / "images" / "a.png").read_bytes()
    ws = Workspace(tmp_path / "ws")
    result = ws.run("survey", SurveyConfig(survey_dir=str(survey), rgbd_dir=str(tmp_path / "rgbd"), progress=False))
    assert result.undistorted == {"lens_model": "opencv", "k1": -0.1, "k2": 0.01, "p1": 0.0, "p2": 0.0, "k3": 0.0}
    camera = json.loads((ws.folder("survey") / "camera.json").read_text())
    assert {k: camera[k] for k in ("fx", "fy", "cx", "cy")} == {"fx": 60.0, "fy": 61.0, "cx": 31.5, "cy": 23.5}
    assert not {"model", "params", "k1", "lens_model"} & set(camera)
    assert not (ws.folder("survey") / "images").is_symlink()
    assert (survey / "images" / "a.png").read_bytes() == before
    assert json.loads((survey / "camera.json").read_text()) == user_camera
