"""Frames and lenses as users bring them (issue 63): a frame with an EXIF orientation tag, a file whose name is not its
format, a given lens no camera has, and a self-calibration that gives the same camera twice."""

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.calibrate import check_plausible, halves_warning
from pipeline.survey import SurveyConfig, check_survey
from pipeline.workspace import Workspace
from watergan.errors import UserInputError
from watergan.io import read_bgr8, read_grey8, read_image, read_stored

W, H = 64, 48
#: A pinhole camera for the 64x48 frames (a 56-degree field of view).
CAMERA = {"fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "width": W, "height": H}


def jpeg_survey(folder: Path, camera: dict, turned: int | None = None) -> Path:
    """Four 64x48 JPEG frames (f0..f3.jpg; f1 tagged with EXIF orientation ``turned`` when given) and camera.json."""
    from PIL import Image

    rng = np.random.default_rng(0)
    (folder / "images").mkdir(parents=True)
    for k in range(4):
        exif = Image.Exif()
        if k == 1 and turned is not None:
            exif[0x0112] = turned
        pixels = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(folder / "images" / f"f{k}.jpg", exif=exif.tobytes(), quality=95)
    (folder / "camera.json").write_text(json.dumps(camera))
    return folder


def test_a_frame_with_an_exif_orientation_is_read_as_stored_by_every_stage_and_by_sfm(tmp_path, capsys):
    """The tag (6: a viewer turns the frame a quarter) changes no reading: every reader the stages use gives the
    stored 64x48 grid, the one COLMAP reads (one camera model for every frame); the survey stage says so, naming
    the frame; a camera.json written for the turned frames is refused with the reason."""
    import pycolmap

    survey = jpeg_survey(tmp_path / "survey", CAMERA, turned=6)
    frame = survey / "images" / "f1.jpg"
    stored = read_stored(frame)
    assert stored.shape == (H, W, 3) and read_image(frame).shape == (H, W, 3)
    assert np.array_equal(read_bgr8(frame), stored) and read_grey8(frame).shape == (H, W)
    seen_by_sfm = np.asarray(pycolmap.Bitmap.read(str(frame), True).to_array())
    assert seen_by_sfm.shape == (H, W, 3) and np.abs(seen_by_sfm[..., ::-1].astype(int) - stored).mean() < 2

    (tmp_path / "rgbd" / "rgb").mkdir(parents=True)
    Workspace(tmp_path / "ws").run("survey", SurveyConfig(survey_dir=str(survey), rgbd_dir=str(tmp_path / "rgbd"),
                                                          progress=False))
    note = capsys.readouterr().err
    assert "1 frame(s) carry an EXIF orientation" in note and "f1.jpg: 6, turn 90 deg clockwise" in note

    turned = jpeg_survey(tmp_path / "turned", {**CAMERA, "width": H, "height": W}, turned=6)
    with pytest.raises(UserInputError, match=r"images in .* are 64x48 as stored \(1 carry an EXIF orientation"):
        check_survey(turned)


def test_a_jpeg_named_png_is_named_as_a_jpeg(tmp_path):
    survey = jpeg_survey(tmp_path / "survey", CAMERA)
    (survey / "images" / "f2.jpg").rename(survey / "images" / "f2.png")
    with pytest.raises(UserInputError, match=r"f2.png is a JPEG file named .png: rename it to f2.jpg"):
        check_survey(survey)


@pytest.mark.parametrize("lens, found", [
    ({"fx": 0.5, "fy": 0.5}, "fx 0 px, a horizontal field of view of 178 deg on 64 px"),
    ({"p1": 0.5, "calibrated": True}, "a tangential coefficient of 0.500"),
    ({"cx": 60.0}, r"the principal point \(60, 24\) far from the image's centre \(32, 24\)"),
    ({"k1": -2.0}, "k1 -2.000 fold the image before its corner"),
])
def test_a_given_lens_gets_the_check_sfm_s_lenses_get(tmp_path, lens, found):
    """camera.json's calibration, held fixed, is refused at the survey check when no camera has it (the check SfM's
    lenses pass), with the value and what to do; a plausible one passes."""
    assert check_survey(jpeg_survey(tmp_path / "good", CAMERA))["n_images"] == 4
    with pytest.raises(UserInputError, match=f"camera file .*camera.json is not a plausible camera: {found}.*SfM "
                                             f"calibrates the camera on the survey"):
        check_survey(jpeg_survey(tmp_path / "bad", {**CAMERA, **lens}))
    with pytest.raises(UserInputError, match=f"the lens SfM found on the survey is not plausible: {found}"):
        check_plausible({**CAMERA, **lens})


def test_a_starting_focal_length_no_camera_has_is_refused(tmp_path):
    guess = {"width": W, "height": H, "fx": 0.5, "calibrated": False}
    with pytest.raises(UserInputError, match="the starting focal length is not a camera's: fx 0 px, a horizontal "
                                             "field of view of 178 deg"):
        check_survey(jpeg_survey(tmp_path / "survey", guess))


def test_halves_that_disagree_are_a_warning():
    apart = {"first": {"focal_px": 1010.0}, "second": {"focal_px": 1232.0}, "focal_diff_pct": 19.9}
    assert "1010.0 and 1232.0 px, 19.9 % apart (more than 5 %)" in halves_warning(apart)
    assert halves_warning({**apart, "focal_diff_pct": 0.8}) == ""


def test_the_frames_enter_colmap_s_database_in_name_order(tmp_path):
    """Their ids follow their sorted names whatever order extraction's threads finish in (the mapper breaks ties by
    id)."""
    import pycolmap

    from pipeline.colmap import extract_in_order

    survey = jpeg_survey(tmp_path / "survey", CAMERA)
    names = sorted(p.name for p in (survey / "images").iterdir())
    extract_in_order(tmp_path / "db.db", survey / "images", names[::-1], pycolmap.ImageReaderOptions(),
                     pycolmap.FeatureExtractionOptions())
    database = pycolmap.Database.open(str(tmp_path / "db.db"))
    try:
        assert [image.name for image in sorted(database.read_all_images(), key=lambda i: i.image_id)] == names
    finally:
        database.close()


@pytest.mark.slow
def test_self_calibration_gives_the_same_camera_twice(tmp_path):
    """Two self-calibrations of the same frames, COLMAP's threads as it chooses them: the same camera model, its
    intrinsics within 1 % and each half's focal length within 2 %, finer than this survey pins (its halves are 6 %
    apart); not to the bit (docs/cameras.md)."""
    from test_sfm import survey_and_sfm

    from pipeline.calibrate import self_calibrate
    from watergan.survey_files import image_files

    survey, _, _ = survey_and_sfm()
    names = image_files(survey / "images")
    runs = [self_calibrate(survey / "images", names, {"width": 320, "height": 240}, tmp_path / f"run{k}")
            for k in range(2)]
    (first, record), (second, again) = runs
    assert first.keys() == second.keys() and first["lens_model"] == second["lens_model"]
    assert all(first[k] == pytest.approx(second[k], rel=0.01) for k in ("fx", "fy", "cx", "cy"))
    assert all(record["halves"][h]["focal_px"] == pytest.approx(again["halves"][h]["focal_px"], rel=0.02)
               for h in ("first", "second"))
