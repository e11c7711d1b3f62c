"""Inputs as users bring them (issue 63): navigation logs as spreadsheets write them, masks given wrong, an overlay on
real footage, read-only places, Ctrl-C, checks before anything is written, and advice that does not repeat itself."""

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.cli import main
from pipeline.navigation import navigation_from_log
from watergan.errors import UserInputError
from watergan.io import DataError, atomic_write_json, from_jsonable, scene_mask_from

FRAMES = ["f0.png", "f1.png", "f2.png"]
POOL = Path(__file__).resolve().parents[2] / "shared" / "data" / "subvo-pool" / "images"


def _survey(root: Path, n: int = 4, camera: dict | None = None) -> Path:
    images = root / "images"
    images.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(n):
        cv2.imwrite(str(images / f"f{k}.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    (root / "camera.json").write_text(json.dumps(camera or {"fx": 50, "fy": 50, "cx": 32, "cy": 24, "width": 64,
                                                            "height": 48}))
    return images


def _files(root: Path) -> dict:
    return {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------------- navigation logs
def test_a_spreadsheet_s_csv_with_a_byte_order_mark_or_semicolons_reads(tmp_path):
    log = tmp_path / "navigation.csv"
    log.write_text("\ufeffframe,altitude_m\nf0.png,2\nf1.png,2.1\nf2.png,2.2\n", encoding="utf-8")
    assert navigation_from_log(log, FRAMES)["nav_altitude_m"] == [2.0, 2.1, 2.2]
    log.write_text("frame;altitude_m\nf0.png;2\nf1.png;2.1\nf2.png;2.2\n")
    assert navigation_from_log(log, FRAMES)["nav_altitude_m"] == [2.0, 2.1, 2.2]


@pytest.mark.parametrize("rows, message", [
    ("f0.png,2,10\nf1.png,2.1,nan\nf2.png,2.2,10", r"depth_m holds 'nan', not a finite number, on line 3 \(frame f1"),
    ("f0.png,2,10\nf1.png,inf,10\nf2.png,2.2,10", r"altitude_m holds 'inf', not a finite number, on line 3 \(frame f1"),
    ("f0.png,2,10\n\nf1.png,,10\nf2.png,2.2,10", r"altitude_m is empty, on line 4 \(frame f1.png\)"),
    ("f0.png,2,10\nf1.png,2.37,10\nf2.png,2.2,10\nf1.png,9.9,10", r"frame f1.png is on line 3 and again on line 5"),
])
def test_a_bad_cell_or_a_frame_listed_twice_names_the_log_the_line_and_the_frame(tmp_path, rows, message):
    log = tmp_path / "navigation.csv"
    log.write_text("frame,altitude_m,depth_m\n" + rows + "\n")
    with pytest.raises(UserInputError, match=f"navigation log {log}: " + message):
        navigation_from_log(log, FRAMES)


def test_nan_in_a_log_never_reaches_the_workspace(tmp_path):
    """The survey stage refuses the log, naming it, before anything is written; no workspace file holds NaN."""
    from pipeline.survey import SurveyConfig
    from pipeline.workspace import Workspace

    survey = tmp_path / "survey"
    _survey(survey)
    (survey / "navigation.csv").write_text("frame,altitude_m,depth_m\nf0.png,2,10\nf1.png,2,nan\nf2.png,2,10\n"
                                           "f3.png,2,10\n")
    with pytest.raises(UserInputError, match=r"navigation.csv: depth_m holds 'nan'.* line 3 \(frame f1.png\)"):
        Workspace(tmp_path / "ws").run("survey", SurveyConfig(str(survey), progress=False))
    assert not (tmp_path / "ws" / "00_survey" / "survey.json").exists()


def test_workspace_json_never_holds_nan(tmp_path):
    """A number with no value is written as null (valid JSON) and read back as NaN into a float field; a survey file
    refuses it, naming the key."""

    @dataclasses.dataclass
    class Result:
        spread: float
        values: list[float]

    path = tmp_path / "result.json"
    atomic_write_json(path, Result(float("nan"), [1.0, float("inf")]))
    assert "NaN" not in path.read_text() and "Infinity" not in path.read_text()
    back = from_jsonable(Result, json.loads(path.read_text()))
    assert np.isnan(back.spread) and back.values[0] == 1.0 and np.isnan(back.values[1])
    with pytest.raises(DataError, match=r"cannot write .*survey.json: nav_depth_m\[1\] is nan, not a finite number"):
        atomic_write_json(tmp_path / "survey.json", {"nav_depth_m": [1.0, float("nan")]}, finite=True)


# ------------------------------------------------------------------------------------------------------ masks
@pytest.mark.parametrize("rects, message", [
    (5, r"mask_rects_px = 5 is not a list of rectangles"),
    ([[40, 0, 10, 20]], r"x1 <= x0 or y1 <= y0: .*\[x, y, width, height\] is \[40, 0, 50, 20\]"),
    ([[0, 0, 100, 20]], r"reaches outside the 64x48 frame"),
    ([[-5, 0, 10, 10]], r"reaches outside the 64x48 frame"),
    ([["a", 0, 1, 1]], r"is not \[x0, y0, x1, y1\]"),
])
def test_a_mask_rectangle_given_wrong_is_a_clear_error(rects, message):
    with pytest.raises(DataError, match=message):
        scene_mask_from(64, 48, None, rects)


def test_a_wrong_mask_rectangle_in_camera_json_stops_the_survey_check(tmp_path):
    from pipeline.survey import check_survey

    _survey(tmp_path, camera={"width": 64, "height": 48, "mask_rects_px": 5})
    with pytest.raises(UserInputError, match=r"camera file .*camera.json: mask_rects_px = 5 is not a list"):
        check_survey(tmp_path)
    assert scene_mask_from(64, 48, None, [[0, 0, 64, 10]])[:10].sum() == 0  # a right one still masks


def _pool(n: int, top_cut: int = 0) -> list[np.ndarray]:
    names = sorted(POOL.glob("*.jpg"))
    return [cv2.imread(str(names[i]), cv2.IMREAD_GRAYSCALE)[top_cut:]
            for i in np.linspace(0, len(names) - 1, n).round().astype(int)]


@pytest.mark.skipif(not POOL.is_dir(), reason="the pool footage (../shared/data/subvo-pool) is not here")
def test_the_overlay_finder_finds_the_pool_s_timestamp_and_nothing_else():
    """On real footage (the pool's 1280x720 frames, a timestamp burned in at x 15-168, y 1-13) the finder proposes one
    tight box around it, not the far wall or the chain; with the timestamp cut away it proposes nothing."""
    from pipeline.overlay import overlay_boxes

    frames = _pool(6)
    (x0, y0, x1, y1), = overlay_boxes(frames)
    assert x0 <= 15 and y0 <= 1 and 168 <= x1 <= 200 and 13 <= y1 <= 30
    half = [cv2.resize(f, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for f in frames]
    assert overlay_boxes(half)[0][2] < 100
    assert overlay_boxes([f[30:] for f in frames]) == []


@pytest.mark.skipif(not POOL.is_dir(), reason="the pool footage (../shared/data/subvo-pool) is not here")
def test_the_report_draws_the_mask_over_a_frame(tmp_path):
    from pipeline.report import section_mask
    from pipeline.survey import SurveyResult
    from pipeline.workspace import Workspace
    from watergan.io import write_scene_mask

    ws = Workspace(tmp_path / "ws")
    images = ws.stage_dir("survey") / "images"
    images.mkdir()
    for k, frame in enumerate(_pool(3)):
        cv2.imwrite(str(images / f"f{k}.png"), frame)
    mask = np.ones((720, 1280), bool)
    mask[:20, :180] = False
    write_scene_mask(ws.stage_dir("survey") / "scene_mask.png", mask)
    ws.save("survey", {"survey_dir": "S"}, SurveyResult(n_images=3, width=1280, height=720, stereo=False,
                                                         simulated=False, rgbd_dir="", survey_dir="S",
                                                         scene_mask="00_survey/scene_mask.png"))
    body, info = section_mask(ws, tmp_path)
    assert body.startswith("<img src='data:image/jpeg;base64,") and info["frame"] == "f1.png"
    assert info["masked_pct"] == pytest.approx(100 * 20 * 180 / (720 * 1280), abs=0.01)


# ------------------------------------------------------------------------------- read-only places, Ctrl-C
def test_frames_into_a_place_that_cannot_be_written_is_one_line_and_exit_3(tmp_path, capsys):
    from test_video import pan, write_video

    clip = write_video(tmp_path / "dive.mp4", pan(4.0, n=20))
    (tmp_path / "afile").write_text("not a folder")
    assert main(["frames", str(clip), "--out", str(tmp_path / "afile" / "frames"), "--no-progress"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write" in err and "afile" in err


def test_a_workspace_that_cannot_be_written_is_one_line(tmp_path):
    from pipeline.workspace import lock_workspace

    with pytest.raises(UserInputError, match=r"cannot write workspace /proc .*lock file"):
        lock_workspace(Path("/proc"))


def test_ctrl_c_is_one_line_and_exit_130(monkeypatch, capsys):
    import pipeline.cli as cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "cmd_effects", interrupted)
    assert cli.main(["effects"]) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith("watergan: interrupted") and err.count("\n") == 0 and "Traceback" not in err


# ------------------------------------------------------------------------- checks before anything is written
def test_a_camera_json_for_another_frame_size_is_refused_before_the_frames_are_written(tmp_path):
    from test_video import pan, write_video

    from pipeline.video import VideoConfig, frames_from_video

    clip = write_video(tmp_path / "dive.mp4", pan(4.0, n=20))
    (tmp_path / "camera.json").write_text(json.dumps({"width": 320, "height": 240}))
    with pytest.raises(UserInputError, match=r"camera file .*camera.json is for 320x240 images; the video's frames"):
        frames_from_video([clip], tmp_path / "out", VideoConfig(progress=False))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("inside", [".", "ws"])
def test_a_workspace_inside_the_survey_folder_is_refused_and_nothing_is_written_there(tmp_path, inside):
    from pipeline.survey import SurveyConfig
    from pipeline.workspace import Workspace

    survey = tmp_path / "survey"
    _survey(survey)
    before = _files(survey)
    with pytest.raises(UserInputError, match=r"inside the survey folder .*never written to: give a workspace "
                                             r"outside it"):
        Workspace(survey / inside).run("survey", SurveyConfig(str(survey), progress=False))
    assert _files(survey) == before and sorted(p.name for p in survey.iterdir()) == ["camera.json", "images"]


# ------------------------------------------------------------------------------------------------------ advice
def test_after_the_diagnosis_the_next_step_is_never_the_diagnosis_again(tmp_path):
    from types import SimpleNamespace

    from pipeline.report_found import after_diagnosis

    found = SimpleNamespace(best="vignetting_x", unexplained_axes=[])
    assert after_diagnosis("watergan diagnose WS", found, tmp_path) == f"watergan run --workspace {tmp_path} " \
                                                                         f"--add vignetting_x"
    nothing = SimpleNamespace(best=None, unexplained_axes=[])
    advice = after_diagnosis(f"watergan diagnose {tmp_path}", nothing, tmp_path)
    assert "diagnose" not in advice and "--plugin FILE.py" in advice and "--add NAME" in advice
    assert after_diagnosis("", nothing, tmp_path) == ""


def test_an_unscaled_run_gives_eta_per_sfm_unit():
    from pipeline.report_found import in_sfm_units

    line = in_sfm_units("Water: eta_per_m 0.100[0.050,0.200]; veil at 1.2 m 0.1; accepted 0.1-0.2 1/m (R / G / B).")
    assert line == ("Water: eta per SfM unit 0.100[0.050,0.200]; veil at 1.2 SfM units 0.1; accepted 0.1-0.2 per "
                    "SfM unit (R / G / B).")


def test_a_difference_within_the_measurement_s_spread_is_a_tie():
    """The demo's R consistency, 4.40e-05 against 4.37e-05 over points that scatter far more, is a tie, not a loss; a
    difference the paired items all share is a loss; without items, within 1 % ties."""
    from eval.tables import verdict_lines

    rng = np.random.default_rng(0)
    raw = rng.gamma(1.0, 4.37e-5, 3000)
    noise = rng.normal(0.0, 4e-5, 3000)
    ours = raw + noise - noise.mean() + 0.03e-5  # 0.7 % worse on average, each point's difference far wider
    lines = verdict_lines([("R consistency", {"raw": raw.mean(), "ours": ours.mean()}, "lower",
                            {"raw": raw, "ours": ours})], ["raw", "ours"])
    assert len(lines) == 1 and lines[0].startswith("ours ties with raw") and "loses" not in lines[0]
    shifted = raw + 0.3e-5
    lines = verdict_lines([("R consistency", {"raw": raw.mean(), "ours": shifted.mean()}, "lower",
                            {"raw": raw, "ours": shifted})], ["raw", "ours"])
    assert lines[0].startswith("ours loses to raw on R consistency")
    lines = verdict_lines([("PSNR", {"raw": 33.54, "ours": 33.28, "clahe": 20.0}, "higher")],
                          ["raw", "clahe", "ours"])
    assert lines == ["ours ties with raw (33.5) on PSNR (33.3: a difference within 1 %)",
                     "ours beats CLAHE on PSNR (33.3)"]
