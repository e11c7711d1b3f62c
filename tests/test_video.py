"""Video in (pipeline/video.py): frames kept by overlap and sharpness from short synthetic clips (a crop panning over a
smoothed random texture, written with OpenCV's mp4v), their true times, the record that makes a second extraction a
no-op, `watergan run`'s video argument, and the errors."""

import json

import cv2
import numpy as np
import pytest

from pipeline.cli import main
from pipeline.navigation import navigation_from_log
from pipeline.run import run_options
from pipeline.video import (
    FRAMES_FOLDER,
    VideoConfig,
    clips_of,
    frames_from_video,
    source_key,
    video_inputs,
    video_survey,
)
from watergan.errors import UserInputError
from watergan.survey_files import read_survey_json

W, H, FPS = 160, 120, 10
CFG = VideoConfig(progress=False, max_step_s=10.0)
#: The image's motion between kept frames at the default overlap (pixels).
TARGET_PX = round((1 - CFG.overlap) * W, 6)


def texture(width: int = 900, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((H, width, 3)).astype(np.float32), (0, 0), 1.5)
    return np.round(255 * (tex - tex.min()) / (tex.max() - tex.min())).astype(np.uint8)


def pan(speed_px: float, n: int = 60, blurred: tuple[int, ...] = (), size: tuple[int, int] = (W, H)) -> list:
    """n frames of a crop moving ``speed_px`` to the right per frame; the ``blurred`` ones out of focus."""
    tex = texture()
    frames = []
    for i in range(n):
        x = int(round(speed_px * i))
        frame = np.ascontiguousarray(tex[:size[1], x:x + size[0]])
        frames.append(cv2.GaussianBlur(frame, (0, 0), 3) if i in blurred else frame)
    return frames


def write_video(path, frames, fps: int = FPS):
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def true_index(image_path, frames) -> int:
    """The synthetic frame a kept PNG shows (the closest in mean absolute difference)."""
    image = cv2.imread(str(image_path)).astype(np.float32)
    return int(np.argmin([np.abs(image - f).mean() for f in frames]))


def kept_indices(result, frames) -> list[int]:
    return [true_index(result.survey_dir / "images" / name, frames) for name in result.frames]


def test_step_follows_the_motion_and_times_are_the_frames_own(tmp_path):
    rates = {}
    for speed in (3, 6):
        frames = pan(speed)
        result = frames_from_video([write_video(tmp_path / f"pan{speed}.mp4", frames)], tmp_path / f"s{speed}", CFG)
        index = kept_indices(result, frames)
        assert result.frame_time_s == pytest.approx([i / FPS for i in index], abs=1e-3)
        assert result.frames == sorted(result.frames) and index == sorted(index)
        assert result.video_s == pytest.approx(len(frames) / FPS)
        steps_px = np.diff(index) * speed
        # never less overlap than asked (one frame's motion of slack), never much more than the window allows
        assert steps_px.max() <= TARGET_PX + speed
        assert steps_px.min() >= (1 - CFG.window) * TARGET_PX - speed
        rates[speed] = len(index) / result.video_s
        survey = read_survey_json(result.survey_dir / "survey.json")
        assert survey["frames"] == result.frames and survey["frame_time_s"] == result.frame_time_s
    assert rates[6] > 1.6 * rates[3]


def test_clips_follow_each_other_in_name_order(tmp_path):
    frames = pan(4)
    write_video(tmp_path / "dive_b.mp4", frames[30:])
    write_video(tmp_path / "dive_a.mp4", frames[:30])
    (tmp_path / "notes.txt").write_text("not a clip")
    videos = video_inputs(tmp_path)
    assert [v.name for v in videos] == ["dive_a.mp4", "dive_b.mp4"]
    result = frames_from_video(videos, tmp_path / "out", CFG)
    index = kept_indices(result, frames)
    assert any(i >= 30 for i in index) and any(i < 30 for i in index)
    # the second clip starts one frame period after the first one's last frame: its times are the dive's
    assert result.frame_time_s == pytest.approx([i / FPS for i in index], abs=1e-3)
    assert result.frames == sorted(result.frames)
    clips = ["01_dive_a_" if i < 30 else "02_dive_b_" for i in index]
    assert all(name.startswith(clip) for name, clip in zip(result.frames, clips, strict=True))


def test_a_blurred_frame_is_passed_over_for_a_sharp_neighbour(tmp_path):
    frames = pan(4)
    sharp = kept_indices(frames_from_video([write_video(tmp_path / "sharp.mp4", frames)], tmp_path / "a", CFG), frames)
    chosen = sharp[2]
    blurred = pan(4, blurred=(chosen,))
    again = kept_indices(frames_from_video([write_video(tmp_path / "blur.mp4", blurred)], tmp_path / "b", CFG),
                         frames)
    assert chosen not in again
    assert min(abs(i - chosen) for i in again) <= 2  # a neighbour instead


def test_mask_keeps_a_burned_in_overlay_out_of_the_motion(tmp_path):
    frames = pan(4)
    overlay = np.random.default_rng(1).integers(0, 2, (84, W, 1), dtype=np.uint8) * 255  # static, high contrast
    for frame in frames:
        frame[:84] = overlay
    cfg = VideoConfig(progress=False, max_step_s=2.0)
    (tmp_path / "dive").mkdir()
    video = write_video(tmp_path / "dive" / "pan.mp4", frames)
    unmasked = kept_indices(frames_from_video([video], tmp_path / "a", cfg), frames)
    mask = np.full((H, W), 255, np.uint8)
    mask[:84] = 0
    cv2.imwrite(str(tmp_path / "dive" / "mask.png"), mask)
    masked = kept_indices(frames_from_video([video], tmp_path / "b", cfg), frames)
    assert np.diff(unmasked).min() * 4 > TARGET_PX + 4  # the overlay holds the motion at 0: time alone sets the step
    steps_px = np.diff(masked) * 4
    assert steps_px.max() <= TARGET_PX + 4 and steps_px.min() >= (1 - cfg.window) * TARGET_PX - 4


def test_a_still_camera_gives_a_frame_every_max_step(tmp_path):
    result = frames_from_video([write_video(tmp_path / "still.mp4", pan(0, n=45))], tmp_path / "out",
                               VideoConfig(progress=False, max_step_s=1.0))
    steps_s = np.diff(result.frame_time_s)
    assert len(result.frames) >= 4
    assert steps_s.max() <= 1.0 + 1e-6 and steps_s.min() >= 0.7 - 1e-6


def test_max_frames_spaces_the_frames_evenly(tmp_path):
    video = write_video(tmp_path / "pan.mp4", pan(6))
    every = frames_from_video([video], tmp_path / "all", CFG)
    few = frames_from_video([video], tmp_path / "few", VideoConfig(progress=False, max_step_s=10.0, max_frames=4))
    assert len(every.frames) > 4 and len(few.frames) == 4
    assert few.frames[0] == every.frames[0] and few.frames[-1] == every.frames[-1]
    assert sorted(p.name for p in (tmp_path / "few" / "images").iterdir()) == few.frames


def test_the_record_makes_a_second_extraction_a_no_op(tmp_path):
    video = write_video(tmp_path / "pan.mp4", pan(4))
    first = frames_from_video([video], tmp_path / "out", CFG)
    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out" / "images").iterdir()}
    second = frames_from_video([video], tmp_path / "out", CFG)
    assert second.reused and not first.reused and second.frames == first.frames
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "out" / "images").iterdir()} == stamps
    other = frames_from_video([video], tmp_path / "out", VideoConfig(progress=False, max_step_s=10.0, overlap=0.6))
    assert not other.reused and len(other.frames) < len(first.frames)
    assert sorted(p.name for p in (tmp_path / "out" / "images").iterdir()) == other.frames


def test_run_resolves_a_video_into_the_workspace(tmp_path, capsys):
    dive = tmp_path / "dive"
    dive.mkdir()
    video = write_video(dive / "DIVE.mp4", pan(4))
    (dive / "navigation.csv").write_text("time_s,altitude_m,depth_m\n0,2.0,10\n6.0,3.0,12\n")
    mask = np.full((H, W), 255, np.uint8)
    mask[:12, :40] = 0  # a burned-in timestamp
    cv2.imwrite(str(dive / "mask.png"), mask)
    ws = tmp_path / "ws"
    frames = video_survey(video, ws, CFG)
    assert frames.survey_dir == ws / FRAMES_FOLDER / source_key([video], CFG) and len(frames.frames) >= 3
    assert f"kept {len(frames.frames)} frames from 6.0 s of video" in capsys.readouterr().out
    survey = frames.survey_dir
    assert json.loads((survey / "camera.json").read_text()) == {"width": W, "height": H}
    assert (survey / "mask.png").read_bytes() == (dive / "mask.png").read_bytes()
    declared = read_survey_json(survey / "survey.json")
    nav = navigation_from_log(survey / "navigation.csv", declared["frames"], declared["frame_time_s"])
    assert nav["nav_altitude_m"] == pytest.approx([2.0 + t / 6.0 for t in frames.frame_time_s], abs=1e-4)
    # a camera.json beside the video is copied; the frames are not extracted again
    (dive / "camera.json").write_text(json.dumps({"fx": 150, "fy": 150, "cx": 80, "cy": 60, "width": W, "height": H}))
    again = video_survey(dive, ws, CFG)
    assert again.reused and again.frames == frames.frames
    assert json.loads((survey / "camera.json").read_text())["fx"] == 150
    assert "extracted earlier" in capsys.readouterr().out
    # other options: another survey folder (the stages rerun on it), the earlier one removed
    other = video_survey(video, ws, VideoConfig(progress=False, overlap=0.6))
    assert not other.reused and other.survey_dir != survey and not survey.exists()
    assert sorted((ws / FRAMES_FOLDER).iterdir()) == [other.survey_dir]
    # a survey folder is no video
    (tmp_path / "survey" / "images").mkdir(parents=True)
    assert video_survey(tmp_path / "survey", ws, CFG) is None
    assert video_inputs(tmp_path / "missing") is None


def test_the_video_options_reach_the_run_and_the_frames_command(tmp_path, capsys):
    opts = run_options({"survey_dir": "dive.mp4", "workspace": "ws", "video_overlap": 0.7, "video_max_step_s": 3})
    assert opts.video.overlap == 0.7 and opts.video.max_step_s == 3.0
    video = write_video(tmp_path / "pan.mp4", pan(4))
    assert main(["frames", str(video), "--out", str(tmp_path / "out"), "--overlap", "0.6", "--no-progress"]) == 0
    assert "frames of 160x120 kept from 6.0 s of video (1 clip)" in capsys.readouterr().out
    record = json.loads((tmp_path / "out" / "video.json").read_text())
    assert record["source"]["options"]["overlap"] == 0.6


@pytest.mark.parametrize("problem, message", [
    ("unreadable", "cannot be opened by OpenCV"),
    ("too_short", r"has 2 frame\(s\) OpenCV can decode; at least 3"),
    ("empty_folder", "holds no video clips"),
    ("mixed_sizes", r"different frame sizes \(a.mp4: 160x120; b.mp4: 144x112\)"),
    ("not_ours", "not extracted from video"),
    ("bad_option", r"overlap = 1.5 \(between 0 and 1\)"),
    ("camera_other_size", r"camera file .*cam.json is for 320x240 images; the video's frames are 160x120"),
    ("camera_missing", r"camera file .*nowhere.json does not exist"),
])
def test_bad_input_is_a_clear_error(tmp_path, problem, message):
    out = tmp_path / "out"
    with pytest.raises(UserInputError, match=message):
        if problem == "unreadable":
            (tmp_path / "x.mp4").write_bytes(b"not a video" * 100)
            frames_from_video([tmp_path / "x.mp4"], out, CFG)
        elif problem == "too_short":
            frames_from_video([write_video(tmp_path / "x.mp4", pan(4, n=2))], out, CFG)
        elif problem == "empty_folder":
            (tmp_path / "clips").mkdir()
            clips_of([tmp_path / "clips"])
        elif problem == "mixed_sizes":
            write_video(tmp_path / "a.mp4", pan(4, n=5))
            write_video(tmp_path / "b.mp4", pan(4, n=5, size=(144, 112)))
            frames_from_video(clips_of([tmp_path]), out, CFG)
        elif problem == "not_ours":
            (out / "images").mkdir(parents=True)
            (out / "images" / "mine.png").write_bytes(b"x")
            frames_from_video([write_video(tmp_path / "x.mp4", pan(4))], out, CFG)
        elif problem == "camera_other_size":
            (tmp_path / "cam.json").write_text(json.dumps({"fx": 1, "fy": 1, "cx": 1, "cy": 1, "width": 320,
                                                          "height": 240}))
            frames_from_video([write_video(tmp_path / "x.mp4", pan(4))], out,
                              VideoConfig(progress=False, camera_json=str(tmp_path / "cam.json")))
        elif problem == "camera_missing":
            frames_from_video([write_video(tmp_path / "x.mp4", pan(4))], out,
                              VideoConfig(progress=False, camera_json=str(tmp_path / "nowhere.json")))
        else:
            VideoConfig(overlap=1.5)
    assert not (out / "survey.json").exists()
    assert not (out / "camera.json").exists()
    assert not (out / ".images.partial").exists()
