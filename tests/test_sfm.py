"""SfM on a small simulated stereo survey: registration, camera centres and sparse depth vs truth.

``survey_and_sfm`` is shared by the other 3D test modules (imported from here; cached, so the
survey is rendered and reconstructed once per session)."""

import functools
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import SCRATCH

from pipeline.scale import altitude_scale, similarity_align
from pipeline.sfm import SfmConfig, Tracks, run_sfm, run_sfm_folder
from pipeline.workspace import Workspace
from watergan.errors import UserInputError


@functools.lru_cache(maxsize=1)
def survey_and_sfm() -> tuple[Path, Workspace, dict]:
    """A 10-frame 320x240 stereo survey (2 lines x 5) in a temporary workspace, with SfM run on it.
    Returns (survey folder, workspace, sfm result record)."""
    from eval.synth import make_config, simulate_survey
    from eval.synth.camera import CameraConfig

    base = make_config("tiny")
    config = replace(base, camera=CameraConfig(width_px=320, height_px=240, hfov_deg=70.0),
                     trajectory=replace(base.trajectory, n_lines=2, frames_per_line=5, forward_overlap=0.75))
    ws = Workspace(Path(tempfile.mkdtemp(prefix="watergan-3d-", dir=SCRATCH)) / "ws")
    survey = ws.stage_dir("survey")
    simulate_survey(survey, config, force=True)
    record = ws.run("sfm", SfmConfig())
    return survey, ws, record


@pytest.fixture(scope="module")
def sfm():
    return survey_and_sfm()


def _truth_index(survey: Path) -> tuple[dict, np.ndarray]:
    from eval.synth import load_truth

    truth = load_truth(survey)
    return truth, {name: k for k, name in enumerate(truth.frames)}


def test_all_frames_register_with_stereo_scale(sfm):
    _, ws, record = sfm
    result = record
    assert result.n_registered == result.n_images == 10
    assert result.scale_method == "stereo" and result.scale_spread < 0.05
    assert result.n_points > 500 and result.mean_track_length > 3
    assert (ws.path(result.model_dir) / "points3D.bin").is_file()
    tracks = Tracks.load(ws.path(result.tracks))
    assert tracks.registered.all() and len(tracks.obs_xy) == len(tracks.obs_point) == len(tracks.obs_image)
    # the stage is skipped when run again with the same configuration
    assert ws.run("sfm", SfmConfig()).seconds == result.seconds
    assert abs(result.lens_k1) < 0.02 and not result.looks_distorted  # a pinhole camera looks undistorted


@pytest.mark.slow
@pytest.mark.parametrize("lens_model, coefficients", [("opencv", (-0.2, 0.05, 0.0, 0.0, 0.0)),
                                                      ("fisheye", (0.05, -0.02, 0.0, 0.0))])
def test_a_lens_is_undistorted_once_and_a_withheld_one_is_named_or_estimated(tmp_path, lens_model, coefficients):
    """The survey seen through a wide lens (OpenCV k1 -0.2, k2 0.05, or a fisheye): given in camera.json, the survey
    stage undistorts the frames into the workspace (the user's stay as they are), where they match the pinhole truth;
    withheld, SfM's refined k1 names the distortion and its one-line summary says what to do (undistorted frames:
    near 0, as the pinhole survey's in ``test_all_frames_register_with_stereo_scale``); withheld and estimated
    (``estimate_lens``; the fisheye's camera.json keeps its ``lens_model``), the survey stage finds the lens and SfM
    then sees undistorted frames."""
    import json

    import cv2

    from eval.synth import make_config, simulate_survey
    from eval.synth.camera import CameraConfig
    from pipeline.report_found import found_lines
    from pipeline.survey import SurveyConfig
    from watergan.lens import LENS_KEYS, Lens

    base = make_config("tiny")
    config = replace(base, camera=CameraConfig(width_px=320, height_px=240, hfov_deg=70.0,
                                               distortion=coefficients, lens_model=lens_model),
                     trajectory=replace(base.trajectory, n_lines=2, frames_per_line=5, forward_overlap=0.75))
    raw = tmp_path / "lens"
    simulate_survey(raw, config, force=True, progress=False)
    before = (raw / "images" / "000000.png").read_bytes()
    ws = Workspace(tmp_path / "ws")
    survey = ws.run("survey", SurveyConfig(survey_dir=str(raw), progress=False))
    assert survey.undistorted == Lens(lens_model, coefficients).to_json()
    assert (raw / "images" / "000000.png").read_bytes() == before
    assert "k1" not in json.loads((ws.folder("survey") / "camera.json").read_text())
    undistorted = cv2.imread(str(ws.folder("survey") / "images" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    truth = cv2.imread(str(raw / "truth" / "inair" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    distorted = cv2.imread(str(raw / "images" / "000000.png"), cv2.IMREAD_GRAYSCALE)

    def edges(image):
        return cv2.Laplacian(cv2.GaussianBlur(image.astype(float), (5, 5), 1.0), cv2.CV_64F)[30:-30, 40:-40].ravel()

    assert np.corrcoef(edges(undistorted), edges(truth))[0, 1] > np.corrcoef(edges(distorted), edges(truth))[0, 1] + 0.2

    camera = json.loads((raw / "camera.json").read_text())
    (raw / "camera.json").write_text(json.dumps({k: v for k, v in camera.items() if k not in LENS_KEYS}))
    withheld = Workspace(tmp_path / "withheld")
    assert not withheld.run("survey", SurveyConfig(survey_dir=str(raw), progress=False)).undistorted
    result = withheld.run("sfm", SfmConfig(progress=False))
    assert result.lens_k1 < -0.05 and result.looks_distorted  # -0.08 measured: one coefficient for k1 and k2
    assert "the frames look distorted (SfM's refined k1 = -0." in result.summary()
    lines, command = found_lines(withheld)  # the report's first screen: the lens, and the run that estimates it
    assert lines[0].startswith("Lens: the frames look distorted")
    assert command.startswith(f"watergan run {raw.resolve()} --workspace {withheld.root}")
    assert '"calibrated": false' in command and "--survey-estimate-lens" not in command

    estimated = Workspace(tmp_path / "estimated")
    if lens_model == "fisheye":  # the model declared, its coefficients left to SfM
        (raw / "camera.json").write_text(json.dumps({**json.loads((raw / "camera.json").read_text()),
                                                     "lens_model": "fisheye"}))
    survey = estimated.run("survey", SurveyConfig(survey_dir=str(raw), estimate_lens=True, progress=False))
    assert survey.lens_estimate["registered"] == 10 and survey.undistorted["lens_model"] == lens_model
    assert survey.undistorted["k1"] == pytest.approx(coefficients[0], abs=0.02)
    assert json.loads((estimated.folder("survey") / "camera.json").read_text())["undistorted"] == survey.undistorted
    assert abs(estimated.run("sfm", SfmConfig(progress=False)).lens_k1) < 0.02
    if lens_model == "fisheye":
        return
    # only the image size known: SfM calibrates focal length, principal point and lens on the survey
    (raw / "camera.json").write_text(json.dumps({"width": 320, "height": 240}))
    calibrated = Workspace(tmp_path / "calibrated")
    survey = calibrated.run("survey", SurveyConfig(survey_dir=str(raw), progress=False))
    found = json.loads((calibrated.folder("survey") / "camera.json").read_text())
    assert survey.self_calibration["registered"] == 10 and found["self_calibration"] == survey.self_calibration
    assert found["fx"] == pytest.approx(camera["fx"], rel=0.05) and found["fy"] == pytest.approx(camera["fy"], rel=0.05)
    assert survey.undistorted["k1"] == pytest.approx(coefficients[0], abs=0.05)
    assert set(survey.self_calibration["models"]) == {"SIMPLE_RADIAL", "RADIAL", "OPENCV"}
    sfm = calibrated.run("sfm", SfmConfig(progress=False))
    assert sfm.n_registered == 10 and abs(sfm.lens_k1) < 0.02 and sfm.lens_source == "self-calibrated"


def test_camera_centres_match_truth_after_similarity(sfm):
    survey, ws, record = sfm
    truth, index = _truth_index(survey)
    tracks = Tracks.load(ws.path(record.tracks))
    est = tracks.world_from_cam[:, :3, 3]
    true = truth.world_from_cam[[index[str(n)] for n in tracks.image_names], :3, 3]
    s, R, t = similarity_align(est, true)
    error = np.linalg.norm(s * est @ R.T + t - true, axis=1)
    extent = np.linalg.norm(true.max(0) - true.min(0))
    assert error.max() < 0.01 * extent
    assert s == pytest.approx(1.0, abs=0.02)  # metric scale from the stereo baseline


@pytest.mark.parametrize("mapper", ["global", "hierarchical"])
def test_the_other_mappers_recover_the_same_cameras(sfm, tmp_path, mapper):
    """Global mapping (GLOMAP's) and hierarchical mapping (clusters merged; one cluster here) register every frame
    and put the cameras where the truth has them, at the stereo scale, as incremental mapping does."""
    survey, _, _ = sfm
    truth, index = _truth_index(survey)
    result = Workspace(tmp_path / "ws").run("sfm", SfmConfig(images_dir=str(survey / "images"), mapper=mapper,
                                                              progress=False))
    assert result.n_registered == result.n_images == 10 and result.scale_method == "stereo"
    tracks = Tracks.load(tmp_path / "ws" / result.tracks)
    est = tracks.world_from_cam[:, :3, 3]
    true = truth.world_from_cam[[index[str(n)] for n in tracks.image_names], :3, 3]
    s, R, t = similarity_align(est, true)
    assert np.linalg.norm(s * est @ R.T + t - true, axis=1).max() < 0.01 * np.linalg.norm(true.max(0) - true.min(0))
    assert s == pytest.approx(1.0, abs=0.02)


def test_sparse_depth_matches_rendered_depth(sfm):
    survey, ws, record = sfm
    truth, index = _truth_index(survey)
    tracks = Tracks.load(ws.path(record.tracks))
    depth = tracks.depths()
    ratios = []
    for k, name in enumerate(tracks.image_names):
        true_depth = truth.depth_m(index[str(name)])
        rows = np.flatnonzero(tracks.obs_image == k)
        ij = np.rint(tracks.obs_xy[rows]).astype(int)
        ratios.append(depth[rows] / true_depth[ij[:, 1], ij[:, 0]])
    ratios = np.concatenate(ratios)
    assert np.median(np.abs(ratios - 1)) < 0.01


def test_altitude_scale_agrees_with_stereo_scale(sfm):
    survey, ws, record = sfm
    import json

    tracks = Tracks.load(ws.path(record.tracks))
    nav = json.loads((survey / "survey.json").read_text())
    by_name = dict(zip(nav["frames"], nav["nav_altitude_m"], strict=True))
    altitudes = np.array([by_name[str(n)] for n in tracks.image_names])
    s, spread = altitude_scale(tracks.xyz, tracks.world_from_cam[:, :3, 3], altitudes)
    assert s == pytest.approx(1.0, abs=0.1) and spread < 0.1


def test_track_scale_recovers_the_positions_scale_despite_a_glitch(sfm, tmp_path):
    """A vehicle's position track (2-D positions in metres, one of them a glitch 5 m off) gives SfM its scale: the
    reconstruction run with ``scale="track"`` and only the track has the stereo model's scale within 2 %, reports
    the residual, drops the glitch, and its two halves agree within 5 %; a camera height over the floor gives it
    within 10 %."""
    import json

    from pipeline.scale import height_scale

    survey, ws, record = sfm
    truth, index = _truth_index(survey)
    names = sorted(index)
    positions = truth.world_from_cam[[index[n] for n in names], :2, 3].copy()
    positions[3] += [5.0, 0.0]
    (tmp_path / "survey.json").write_text(json.dumps({"frames": names, "nav_position_m": positions.tolist()}))
    result = run_sfm_folder(survey / "images", tmp_path / "track",
                            SfmConfig(scale="track", survey_json=str(tmp_path / "survey.json"), progress=False))
    assert result.scale_method == "track"
    assert result.scale_factor == pytest.approx(record.scale_factor, rel=0.02)
    assert result.scale_detail["kept"] == 9 and result.scale_detail["used"] == 10
    assert not result.scale_detail["mirrored"]  # the simulator's x, y are right-handed seen from above
    assert result.scale_detail["residual_m"] < 0.05 and result.scale_detail["halves"]["heldout_pct"] < 5
    assert "residual" in result.summary()
    tracks = Tracks.load(ws.path(record.tracks))
    altitude = float(np.median(json.loads((survey / "survey.json").read_text())["nav_altitude_m"]))
    s, spread, detail = height_scale(tracks.xyz / 3.7, tracks.world_from_cam[:, :3, 3] / 3.7, altitude)
    assert s == pytest.approx(3.7, rel=0.1) and spread < 0.1
    assert detail["halves"]["first"] == pytest.approx(3.7, rel=0.1) and detail["halves"]["heldout_pct"] < 10


def test_the_height_halves_read_a_models_scale_drift():
    """A model whose second half is 5 % smaller (its camera 5 % lower over the floor) gives halves 5.3 % apart."""
    from pipeline.scale import height_halves

    heights = np.r_[np.full(20, 0.30), np.full(20, 0.285)] * (1 + 0.01 * np.sin(np.arange(40)))
    halves = height_halves(heights, camera_height_m=0.3)
    assert halves["first"] == pytest.approx(1.0, rel=0.01)
    assert halves["heldout_pct"] == pytest.approx(100 * (1 / 0.95 - 1), abs=1.0)


def test_an_unscaled_model_has_the_median_depth_as_its_unit(sfm, tmp_path):
    survey, _, _ = sfm
    result = run_sfm_folder(survey / "images", tmp_path / "none", SfmConfig(scale="none", progress=False))
    tracks = Tracks.load(tmp_path / "none" / "tracks.npz")
    assert np.median(tracks.depths()) == pytest.approx(1.0, rel=1e-3)
    assert "unscaled" in result.summary()


def test_an_overlay_that_never_moves_is_named_with_the_rectangle_to_mask(sfm, tmp_path):
    """A patch burned into every frame at the same place (a timestamp's stand-in) keeps its features still while the
    scene moves: SfM names the box to mask, which holds the patch; the survey as rendered has none."""
    import shutil

    import cv2

    survey, _, record = sfm
    assert not record.still_features
    images = tmp_path / "stamped" / "images"
    images.mkdir(parents=True)
    shutil.copy(survey / "camera.json", images.parent / "camera.json")
    rng = np.random.default_rng(3)
    stamp = np.kron(rng.integers(0, 2, (6, 12)) * 255, np.ones((4, 4))).astype(np.uint8)  # 48 x 24 px blocks
    for path in sorted((survey / "images").iterdir()):
        frame = cv2.imread(str(path), cv2.IMREAD_COLOR)
        frame[8:32, 8:56] = stamp[..., None]
        cv2.imwrite(str(images / path.name), frame)
    result = run_sfm_folder(images, tmp_path / "sfm", SfmConfig(scale="none", progress=False))
    x0, y0, x1, y1 = result.still_features["box_px"]
    assert x0 <= 8 and y0 <= 8 and 56 <= x1 <= 128 and 32 <= y1 <= 96
    assert any('"mask_rects_px"' in warning for warning in result.warnings())


def test_similarity_align_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    angle = 0.7
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    s, R_est, t = similarity_align(src, 2.5 * src @ R.T + [1, 2, 3])
    assert s == pytest.approx(2.5) and np.allclose(R_est, R) and np.allclose(t, [1, 2, 3])


def _lawnmower_centres(rng: np.random.Generator) -> np.ndarray:
    """60 camera centres (model units) along three 2-unit legs joined by turns, at a constant height, with the
    model's noise."""
    legs = [np.c_[np.linspace(0, 2, 20), np.full(20, y)] for y in (0.0, 0.6, 1.2)]
    legs[1] = legs[1][::-1]
    plane = np.concatenate(legs)
    return np.c_[plane, np.full(len(plane), 1.5)] + rng.normal(0, 0.003, (len(plane), 3))


def test_a_dead_reckoned_track_takes_its_scale_from_its_straight_steps():
    """A log whose errors accumulate (an odometer's walk, and two gaps in the recording across which it advances one
    ordinary step while the camera moves three: three gaps
    on the first leg) bends the positions' similarity; its residuals follow each other, so
    the scale is read from the straight steps, within 3 % of the truth, as are both halves'."""
    from pipeline.scale import fit_track, track_halves

    rng = np.random.default_rng(3)
    centres = _lawnmower_centres(rng)
    truth = centres[:, :2] * 0.4
    steps = np.diff(truth, axis=0) * (1 + rng.normal(0, 0.02, (len(truth) - 1, 1)))
    steps[[4, 8, 12]] /= 3.0
    logged = np.concatenate([truth[:1], truth[0] + np.cumsum(steps, axis=0)])
    fit = fit_track(centres, logged)
    assert fit.estimator == "steps" and fit.durbin_watson < 1.0
    assert fit.scale == pytest.approx(0.4, rel=0.03)
    halves = track_halves(centres, logged, fit.estimator)
    assert halves["first"] == pytest.approx(0.4, rel=0.03) and halves["second"] == pytest.approx(0.4, rel=0.03)
    assert track_halves(centres, logged, "positions")["heldout_pct"] > 5  # what the similarity alone would say


def test_a_track_with_white_errors_keeps_the_positions_scale():
    """Positions with independent errors (a USBL fix per frame, 2 cm) keep the similarity's scale, which averages
    them, not the steps', which they would bias."""
    from pipeline.scale import fit_track

    rng = np.random.default_rng(4)
    centres = _lawnmower_centres(rng)
    logged = centres[:, :2] * 0.4 + rng.normal(0, 0.02, (len(centres), 2))
    fit = fit_track(centres, logged)
    assert fit.estimator == "positions" and fit.durbin_watson > 1.0
    assert fit.scale == pytest.approx(0.4, rel=0.01)


def test_too_few_registered_images_is_a_clear_error(tmp_path):
    import cv2

    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(1)
    for k in range(4):  # unrelated noise images: nothing to match
        cv2.imwrite(str(images / f"{k:06d}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    ws = Workspace(tmp_path / "ws")
    with pytest.raises(UserInputError, match=r"registered only \d+ of 4 images.*exhaustive"):
        run_sfm(ws, SfmConfig(images_dir=str(images)))


def test_colmap_log_is_silenced_and_sfm_ends_in_one_line(sfm, tmp_path, capfd):
    """pycolmap's INFO log (hundreds of lines on this survey) never reaches the terminal; with progress
    the stage prints one summary line, without it nothing."""
    survey, _, _ = sfm
    result = run_sfm_folder(survey / "images", tmp_path / "loud", SfmConfig(progress=True))
    captured = capfd.readouterr()
    assert captured.err.strip().splitlines() == [result.summary()] and captured.out == ""
    run_sfm_folder(survey / "images", tmp_path / "quiet", SfmConfig(progress=False))
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""


def test_missing_images_folder_is_a_clear_error(tmp_path):
    with pytest.raises(UserInputError, match="does not exist"):
        run_sfm(Workspace(tmp_path / "ws"), SfmConfig(images_dir=str(tmp_path / "nope")))


def _board_clicks(survey: Path, tmp_path: Path, outline: bool) -> Path:
    """A user's board file: the truth board's corners projected with the true poses (as if clicked)."""
    import json

    from eval.colour import project_board, truth_board

    board = json.loads((survey / "truth" / "board.json").read_text())
    if not outline:
        quads = truth_board(survey).quads
        data = {"patch_side_m": board["patch_side_m"], "patches": board["patches"],
                "images": {n: [None if np.isnan(q).any() else q.tolist() for q in qs] for n, qs in quads.items()}}
    else:
        poses = json.loads((survey / "truth" / "poses.json").read_text())["frames"]
        cam = json.loads((survey / "camera.json").read_text())
        K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
        outline_world = np.array(board["outline_world"])
        projected = project_board(["board"], outline_world[None], np.zeros((1, 3)), [f["name"] for f in poses],
                                  np.array([f["world_from_cam"] for f in poses]), K, cam["width"], cam["height"])
        edges = np.linalg.norm(outline_world - np.roll(outline_world, -1, axis=0), axis=1)
        data = {"width_m": float(edges[0]), "height_m": float(edges[1]),
                "images": {n: q[0].tolist() for n, q in projected.quads.items() if np.isfinite(q).all()}}
    path = tmp_path / ("outline.json" if outline else "board.json")
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("outline", [False, True])
def test_board_scale_agrees_with_stereo_scale(sfm, tmp_path, outline):
    import json

    from pipeline.sfm import _choose_scale

    survey, ws, record = sfm
    tracks = Tracks.load(ws.path(record.tracks))  # already metric (stereo): expect s = 1
    cfg = SfmConfig(scale="board", board_json=str(_board_clicks(survey, tmp_path, outline)))
    cam = json.loads((survey / "camera.json").read_text())
    method, s, spread, _ = _choose_scale(cfg, tracks, survey / "images", cam, tracks.track_lengths() >= 3)
    assert method == "board" and s == pytest.approx(1.0, abs=0.01) and spread < 0.02


def test_board_scale_without_a_board_file_is_a_clear_error(sfm):
    from pipeline.sfm import _choose_scale

    survey, ws, record = sfm
    tracks = Tracks.load(ws.path(record.tracks))
    with pytest.raises(UserInputError, match="board scale needs"):
        _choose_scale(SfmConfig(scale="board"), tracks, survey / "images", None, tracks.track_lengths() >= 3)
