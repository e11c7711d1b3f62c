"""Colour consistency (Table II) and colour-board accuracy (Table I)."""

import numpy as np
import pytest
from test_sfm import survey_and_sfm

from eval.colour import (
    Board,
    ColourEvalConfig,
    board_accuracy,
    board_for_images,
    consistency,
    normalise,
    patch_means,
    project_board,
    truth_board,
)
from eval.tracks import Tracks
from pipeline.evaluate import run_colour_eval
from watergan.errors import UserInputError


@pytest.fixture(scope="module")
def sfm():
    return survey_and_sfm()


def test_inair_truth_is_more_consistent_than_raw(sfm):
    survey, ws, record = sfm
    tracks = Tracks.load(ws.path(record.tracks))
    result = consistency(tracks, {"raw": survey / "images", "inair": survey / "truth" / "inair"})
    assert result.n_points > 300 and result.patch_px == 5
    raw, inair = result.scores["raw"], result.scores["inair"]
    assert inair.mean_variance < 0.5 * raw.mean_variance
    assert all(v >= 0 for v in raw.variance + inair.variance)


def test_board_metric_is_near_zero_for_inair_truth(sfm):
    survey, _, _ = sfm
    board = truth_board(survey)
    inair = board_accuracy(survey / "truth" / "inair", board)
    raw = board_accuracy(survey / "images", board)
    assert inair.n_images >= 3
    assert inair.mean_distance < 0.01 and inair.mean_ciede2000 < 1.0
    assert raw.mean_distance > 10 * inair.mean_distance and raw.mean_ciede2000 > 5


def test_workspace_colour_eval_writes_json(sfm, tmp_path):
    survey, ws, _ = sfm
    cfg = ColourEvalConfig(folders=(f"raw={survey / 'images'}", f"inair={survey / 'truth' / 'inair'}"),
                           truth_dir=str(survey))
    result = run_colour_eval(ws, cfg, tmp_path)
    assert result.table == str(tmp_path / "colour.json") and (tmp_path / "colour.json").is_file()
    assert set(result.board) == {"raw", "inair"}


def test_patch_means_and_normalisation():
    image = np.zeros((10, 10, 3), np.float32)
    image[..., 0] = np.arange(10)[None, :]
    values, inside = patch_means(image, np.array([[4.2, 4.0], [0.0, 5.0]]), 3)
    assert inside.tolist() == [True, False]
    assert values[0, 0] == pytest.approx(4.0) and np.isnan(values[1]).all()
    assert np.allclose(normalise(np.array([1.0, 2.0, 1.0])), [0.25, 0.5, 0.25])
    with pytest.raises(UserInputError, match="odd"):
        patch_means(image, np.zeros((1, 2)), 4)


def test_project_board_hides_patches_outside_the_image():
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]])
    pose = np.eye(4)  # camera at the origin looking along +z
    square = np.array([[-0.1, -0.1, 2], [0.1, -0.1, 2], [0.1, 0.1, 2], [-0.1, 0.1, 2]])
    board = project_board(["in", "out"], [square, square + [5, 0, 0]], np.ones((2, 3)), ["a.png"], pose[None],
                          K, 100, 100)
    assert np.allclose(board.quads["a.png"][0, 0], [44.5, 44.5]) and np.isnan(board.quads["a.png"][1]).all()


def test_a_board_whose_frames_match_no_image_is_refused(capsys):
    """A board file keyed by names that are no image of the survey would take part with no rows: refused, naming
    both. Names that differ only in the suffix (the board marked on a survey's JPEG originals, the simulator's truth
    of a survey converted to TIFF) are the images'; other unmatched frames are left out, saying how many."""
    quad = np.array([[[1.0, 1.0], [5.0, 1.0], [5.0, 5.0], [1.0, 5.0]]])
    board = Board(names=["white"], true_linear_rgb=np.ones((1, 3)), quads={"IMG_0001.JPG": quad, "000001.png": quad})
    with pytest.raises(UserInputError, match=r"board file b.json: none of its 2 frames is an image of the survey "
                                             r"\(e.g. 'IMG_0001.JPG'; the survey's are like '000000.png'\)"):
        board_for_images(board, ["000000.png"], "b.json")
    used = board_for_images(board, ["000000.png", "000001.png"], "b.json")
    assert list(used.quads) == ["000001.png"]
    assert "1 of its frames are not images of the survey" in capsys.readouterr().err
    assert sorted(board_for_images(board, ["IMG_0001.png", "000001.tif"], "b.json").quads) == ["000001.tif",
                                                                                              "IMG_0001.png"]
