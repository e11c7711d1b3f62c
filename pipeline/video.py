"""Video in: a dive's video clips turned into a survey folder of frames, as many as the survey needs.

:func:`frames_from_video` reads the clips with OpenCV, in the order given, and keeps frames at a step set by the
image's motion and bounded in time:

- motion: Shi-Tomasi corners of the last kept frame (grey, shrunk to ``motion_width_px``; outside ``mask.png``'s
  non-scene pixels when there is one) are tracked into each later frame by pyramidal Lucas-Kanade, checked forwards
  and backwards; with dx, dy the median absolute displacement along each axis over the image's width and height,
  the frames' overlap is (1 - dx) (1 - dy). A step is done once the overlap falls to ``overlap``, or
  ``max_step_s`` has passed (a still camera, open water without corners), but never before ``min_step_s``; a frame
  whose corners are lost (a fast turn) ends the step at once.
- sharpness: the frames of the step's last ``window`` (of its motion or of ``max_step_s``, whichever is further)
  are its candidates; the kept one is at least 90 % as sharp as the sharpest of them (the variance of the
  Laplacian of the grey frame at full resolution), later ones preferred, so a blurred frame is passed over for a
  sharp neighbour and the steps stay near the target.
- each clip starts with the choice among the frames of its first ``window`` of a step, and ends with the pending
  step's choice when that step reached its window.

Time: a frame's time in its clip is its presentation time as OpenCV reports it, less the clip's first frame's (a
frame without a later time than the one before gets that one's plus one frame period, 1/fps). Clips follow each
other: each clip starts one frame period after the previous clip's last frame (a recording the camera split into
files continues without a gap; a real gap between clips is not seen), so ``frame_time_s`` is the running time from
the first clip's first frame, the clock a navigation log's ``time_s`` must be on.

The survey folder written (``out_dir``):

    images/          the kept frames, PNG: ``<clip position>_<clip name>_<time in the clip, s>.png``
                     (``01_dive_000012.300.png``): names sort in time order
    survey.json      "frames" and "frame_time_s"; a survey.json beside the video gives its survey-wide keys
                     (site_depth_m, lights, crs)
    camera.json      the one given or beside the video, else {"width", "height"} alone
    navigation.csv   the one given or beside the video, copied (interpolated at frame_time_s by the survey stage)
    mask.png         the one beside the video, copied
    video.json       the record: the clips (name, size, modification time) and the options the frames came from

"Beside the video": in the folder of the first clip. A second call with the same clips and options keeps the
frames (the record says so) and refreshes the other files. :func:`video_survey` resolves ``watergan run``'s
survey argument: a video file or a folder of clips becomes ``WORKSPACE/video_frames/<key>``, the key a hash of the
clips and options (:func:`source_key`), so that other frames are another survey folder for the stages.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from watergan.errors import UserInputError
from watergan.io import (
    SCENE_MASK_PNG,
    atomic_write_bytes,
    atomic_write_json,
    read_json,
    scene_mask_from,
    to_jsonable,
    write_failed,
    write_png,
)
from watergan.survey_files import read_survey_json

from .navigation import NAVIGATION_CSV

#: The clips a folder may hold (case-insensitive), taken in name order.
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv")
#: The folder of the workspace that ``watergan run`` extracts a video into (a survey folder per clips and options).
FRAMES_FOLDER = "video_frames"
#: The record of the extraction in the survey folder.
RECORD_JSON = "video.json"
#: survey.json keys that hold for the whole survey (carried over from a survey.json beside the video).
SURVEY_WIDE_KEYS = ("site_depth_m", "lights", "crs")
#: A later candidate is kept over a sharper earlier one when it is at least this share as sharp.
SHARP_ENOUGH = 0.9
#: Fewer tracked corners than this: the motion is lost (or, in the kept frame, not measurable).
MIN_TRACKS = 12
#: Corners detected in a kept frame.
MAX_CORNERS = 400
#: A track whose backward track misses its start by more than this (pixels of the shrunk frame) is dropped.
FORWARD_BACKWARD_PX = 1.0
#: Timestamps closer than this count as equal (seconds): a step of max_step_s is not missed by a rounding error.
TIME_SLACK_S = 1e-6
#: The frame period assumed for a clip that gives no frame rate (seconds).
DEFAULT_PERIOD_S = 1 / 30
_LK = {"winSize": (21, 21), "maxLevel": 3, "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
       "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}


@dataclass(frozen=True)
class VideoConfig:
    """How frames are taken from a video (module docstring)."""

    overlap: float = 0.8
    """Share of the image that consecutive kept frames have in common (0-1): a step ends when (1 - dx)(1 - dy)
    falls to it, dx and dy the median motion of the tracked corners over the image's width and height."""
    max_step_s: float = 2.0
    """The longest time between kept frames (seconds): a still or slow camera still gives a frame this often."""
    min_step_s: float = 0.0
    """The shortest time between kept frames (seconds; 0: as often as the overlap asks)."""
    window: float = 0.3
    """The share of each step, at its end, whose frames are candidates (0-0.5): one at least 90 % as sharp as the
    sharpest (variance of the Laplacian), later ones preferred, is kept, so a blurred frame is passed over."""
    max_frames: int = 0
    """At most this many frames, evenly spaced among those chosen (0: no limit)."""
    motion_width_px: int = 480
    """Frames are shrunk to this width (pixels) to track their motion (a narrower frame is tracked as it is)."""
    camera_json: str = field(default="", metadata={"hash": False})
    """camera.json to copy next to the frames; empty: the one beside the video, else the frames' width and height
    alone (SfM then estimates the intrinsics)."""
    navigation_csv: str = field(default="", metadata={"hash": False})
    """Navigation log to copy next to the frames (time_s on the frames' clock: seconds from the first clip's first
    frame); empty: navigation.csv beside the video, if any."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bar."""

    def __post_init__(self) -> None:
        bad = [f"{name} = {value!r} ({rule})" for name, value, ok, rule in (
            ("overlap", self.overlap, 0 < self.overlap < 1, "between 0 and 1"),
            ("max_step_s", self.max_step_s, self.max_step_s > 0, "positive"),
            ("min_step_s", self.min_step_s, 0 <= self.min_step_s <= self.max_step_s, "0 to max_step_s"),
            ("window", self.window, 0 < self.window <= 0.5, "above 0, at most 0.5"),
            ("max_frames", self.max_frames, self.max_frames == 0 or self.max_frames >= 3, "0 or at least 3"),
            ("motion_width_px", self.motion_width_px, self.motion_width_px >= 32, "at least 32")) if not ok]
        if bad:
            raise UserInputError(f"video options: {'; '.join(bad)}")


@dataclass(frozen=True)
class VideoFrames:
    """A survey folder extracted from video."""

    survey_dir: Path
    """The survey folder written."""
    frames: list[str]
    """The kept frames' file names in images/, in time order."""
    frame_time_s: list[float]
    """Each frame's time, seconds from the first clip's first frame."""
    video_s: float
    """The clips' total length (seconds)."""
    width: int
    height: int
    reused: bool
    """Whether the frames were extracted by an earlier call (same clips and options)."""


def video_inputs(path: Path) -> list[Path] | None:
    """The clips a survey argument names: a file is a video; a folder without ``images/`` gives its clips
    (:data:`VIDEO_SUFFIXES`) in name order. None for anything else (a survey folder, a folder without clips, a
    missing path): the survey's own check says what it lacks."""
    path = Path(path)
    if path.is_file():
        return [path]
    if path.is_dir() and not (path / "images").is_dir():
        return _clips(path) or None
    return None


def _clips(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)


def clips_of(paths: list[Path]) -> list[Path]:
    """Video files from files and folders (a folder: its clips in name order); a folder without clips, or a path that
    is not there, is an error."""
    out = []
    for path in map(Path, paths):
        if path.is_dir():
            clips = _clips(path)
            if not clips:
                raise UserInputError(f"{path} holds no video clips ({', '.join(VIDEO_SUFFIXES)})")
            out += clips
        elif path.is_file():
            out.append(path)
        else:
            raise UserInputError(f"video {path} does not exist")
    if not out:
        raise UserInputError("no video given")
    return out


def video_survey(argument: Path, workspace: Path, cfg: VideoConfig) -> VideoFrames | None:
    """``watergan run``'s survey argument resolved: a video file or a folder of clips (:func:`video_inputs`) is
    extracted into ``workspace/video_frames/<key>`` (:func:`frames_from_video`, :func:`source_key`; the workspace is
    created and locked first, the frames of other clips or options removed), saying in one line what was kept;
    None for a survey folder."""
    from .workspace import Workspace, lock_workspace

    videos = video_inputs(Path(argument))
    if videos is None:
        return None
    ws = Workspace(workspace)
    lock_workspace(ws.root)
    folder = ws.root / FRAMES_FOLDER
    frames = frames_from_video(videos, folder / source_key(videos, cfg), cfg)
    for other in folder.iterdir():
        if other.is_dir() and other != frames.survey_dir:
            shutil.rmtree(other)
    what = f"{len(videos)} clips" if len(videos) > 1 else videos[0].name
    if frames.reused:
        print(f"video: {len(frames.frames)} frames of {what} ({frames.video_s:.1f} s) extracted earlier, kept in "
              f"{frames.survey_dir}", flush=True)
    else:
        print(f"video: kept {len(frames.frames)} frames from {frames.video_s:.1f} s of video ({what}) in "
              f"{frames.survey_dir}", flush=True)
    return frames


def sharpness(grey: np.ndarray) -> float:
    """The variance of the Laplacian of a grey frame (higher: sharper)."""
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _open(path: Path) -> cv2.VideoCapture:
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise UserInputError(f"video {path} cannot be opened by OpenCV: give a video its FFmpeg decodes (.mp4, .mov, "
                             f".avi, .mkv), or re-encode it (ffmpeg -i IN -c:v libx264 OUT.mp4)")
    return capture


def _too_short(path: Path, n: int) -> UserInputError:
    return UserInputError(f"video {path} has {n} frame(s) OpenCV can decode; at least 3 are needed (is it cut short?)")


class _Clip:
    """One clip's frames in order: (time in the clip in seconds, BGR image), each counted on the progress ``bar``;
    afterwards ``n_frames`` and ``duration_s`` (its last frame's time plus one frame period)."""

    def __init__(self, path: Path, bar: tqdm) -> None:
        self.bar = bar
        self.capture = _open(path)
        fps = self.capture.get(cv2.CAP_PROP_FPS)
        self.period_s = 1 / fps if math.isfinite(fps) and fps > 0 else DEFAULT_PERIOD_S
        self.n_frames, self.last_s = 0, 0.0

    def frames(self) -> Iterator[tuple[float, np.ndarray]]:
        first_s = 0.0
        try:
            while True:
                ok, image = self.capture.read()
                if not ok:
                    break
                stamp_s = self.capture.get(cv2.CAP_PROP_POS_MSEC) / 1000
                if self.n_frames == 0:
                    first_s, time_s = (stamp_s if math.isfinite(stamp_s) else 0.0), 0.0
                else:
                    time_s = stamp_s - first_s
                    time_s = time_s if time_s > self.last_s else self.last_s + self.period_s  # nan: not later
                self.n_frames, self.last_s = self.n_frames + 1, time_s
                self.bar.update(1)
                yield time_s, image
        finally:
            self.capture.release()

    @property
    def duration_s(self) -> float:
        return self.last_s + self.period_s


def _shrink(grey: np.ndarray, width_px: int) -> np.ndarray:
    h, w = grey.shape
    if w <= width_px:
        return grey
    return cv2.resize(grey, (width_px, max(1, round(h * width_px / w))), interpolation=cv2.INTER_AREA)


class _Anchor:
    """The last kept frame (shrunk, grey), its corners, and their tracks into the frames after it."""

    def __init__(self, small: np.ndarray, time_s: float, mask: np.ndarray | None) -> None:
        self.small, self.time_s = small, time_s
        corners = cv2.goodFeaturesToTrack(small, MAX_CORNERS, 0.01, max(4, small.shape[1] // 60), mask=mask)
        self.points = np.empty((0, 1, 2), np.float32) if corners is None else corners.astype(np.float32)
        self.guess = self.points.copy()

    def motion(self, small: np.ndarray) -> float:
        """1 - the overlap of ``small`` with this frame (module docstring): 0 when this frame has too few corners to
        tell (time alone then ends the step), inf when they are lost in ``small``."""
        if len(self.points) < MIN_TRACKS:
            return 0.0
        moved, status, _ = cv2.calcOpticalFlowPyrLK(self.small, small, self.points, self.guess.copy(), **_LK)
        back, status_back, _ = cv2.calcOpticalFlowPyrLK(small, self.small, moved, self.points.copy(), **_LK)
        good = (status.ravel() == 1) & (status_back.ravel() == 1) & \
            (np.linalg.norm((back - self.points).reshape(-1, 2), axis=1) < FORWARD_BACKWARD_PX)
        if good.sum() < MIN_TRACKS:
            return math.inf
        self.guess[good] = moved[good]
        shift = np.abs(moved[good] - self.points[good]).reshape(-1, 2)
        h, w = small.shape
        dx, dy = min(float(np.median(shift[:, 0])) / w, 1.0), min(float(np.median(shift[:, 1])) / h, 1.0)
        return 1 - (1 - dx) * (1 - dy)


@dataclass
class _Candidate:
    time_s: float
    image: np.ndarray
    small: np.ndarray


def keyframes(frames: Iterator[tuple[float, np.ndarray]], cfg: VideoConfig,
              mask: np.ndarray | None = None) -> Iterator[tuple[float, np.ndarray]]:
    """The kept frames (time, image) of one clip's ``frames`` (time in seconds, increasing; BGR images), in order
    (module docstring). ``mask``: (H,W) bool of the frames, True where a pixel is the scene (corners only there)."""
    anchor: _Anchor | None = None
    small_mask = None
    first = True
    best: _Candidate | None = None
    sharpest = 0.0
    for time_s, image in frames:
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        small = _shrink(grey, cfg.motion_width_px)
        if anchor is None:
            if mask is not None:
                small_mask = cv2.resize(mask.astype(np.uint8) * 255, small.shape[::-1],
                                        interpolation=cv2.INTER_NEAREST)
            anchor = _Anchor(small, time_s, small_mask)
        elapsed_s = time_s - anchor.time_s + TIME_SLACK_S
        done = max(anchor.motion(small) / (1 - cfg.overlap), elapsed_s / cfg.max_step_s)
        start, end = (0.0, cfg.window) if first else (1 - cfg.window, 1.0)
        if done < start or (not first and elapsed_s < cfg.min_step_s):
            continue
        score = sharpness(grey)
        sharpest = max(sharpest, score)
        if best is None or score >= SHARP_ENOUGH * sharpest:
            best = _Candidate(time_s, image, small)
        if done >= end:
            yield best.time_s, best.image
            anchor = _Anchor(best.small, best.time_s, small_mask)
            first, best, sharpest = False, None, 0.0
    if best is not None:
        yield best.time_s, best.image


def _source(videos: list[Path], cfg: VideoConfig) -> dict:
    """What the frames come from: each clip's name, size and modification time, and the options that choose them."""
    clips = []
    for path in videos:
        if not path.is_file():
            raise UserInputError(f"video {path} does not exist")
        stat = path.stat()
        clips.append({"name": path.name, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns})
    return {"clips": clips, "options": to_jsonable(cfg, for_hash=True)}


def source_key(videos: list[Path], cfg: VideoConfig) -> str:
    """A short hash of what the frames come from: the clips (name, size, modification time) and the options that
    choose the frames."""
    text = json.dumps(_source([Path(v) for v in videos], cfg), sort_keys=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:12]


def _probe(path: Path) -> tuple[int, int, int]:
    """(width, height) of the clip's first frame and its frame count as the container gives it (0 or less: unknown);
    a clip OpenCV cannot open or decode is an error."""
    capture = _open(path)
    try:
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        ok, image = capture.read()
    finally:
        capture.release()
    if not ok:
        raise _too_short(path, 0)
    return image.shape[1], image.shape[0], count


def _stem(path: Path) -> str:
    return "".join(c if c.isalnum() or c in "-." else "_" for c in path.stem)


def frames_from_video(videos: list[Path], out_dir: Path, cfg: VideoConfig = VideoConfig()) -> VideoFrames:
    """Write the survey folder ``out_dir`` from the clips ``videos`` (in that order; module docstring). Kept as it is
    when its record names the same clips (name, size, modification time) and options; else its frames are replaced
    (an ``out_dir`` whose images/ holds frames without a record is not written: they are not ours). Errors: a clip
    that is missing or that OpenCV cannot open, one with fewer than 3 frames, clips of different frame sizes, fewer
    than 3 frames kept, a camera.json given or beside the video for another frame size."""
    videos, out_dir = [Path(v) for v in videos], Path(out_dir)
    if not videos:
        raise UserInputError("no video given")
    source = _source(videos, cfg)
    camera, _ = _side_files(videos[0].parent, cfg)
    if camera.is_file():  # before anything is written
        width, height, _ = _probe(videos[0])
        _check_camera(camera, width, height)
    _writable(out_dir)
    record_path, images = out_dir / RECORD_JSON, out_dir / "images"
    record = read_json(record_path, "video record") if record_path.is_file() else None
    if record is None and images.is_dir() and any(images.iterdir()):
        raise UserInputError(f"{images} holds files that were not extracted from video: give another folder")
    if (isinstance(record, dict) and record.get("source") == source
            and all((images / name).is_file() for name in record.get("frames", []))):
        frames = VideoFrames(out_dir, record["frames"], record["frame_time_s"], record["video_s"], record["width"],
                             record["height"], reused=True)
    else:
        frames = _extract(videos, out_dir, cfg)
        atomic_write_json(record_path, {"source": source, "frames": frames.frames,
                                        "frame_time_s": frames.frame_time_s, "video_s": frames.video_s,
                                        "width": frames.width, "height": frames.height})
    _write_survey_files(videos[0].parent, out_dir, cfg, frames)
    return frames


def _extract(videos: list[Path], out_dir: Path, cfg: VideoConfig) -> VideoFrames:
    """Extract the frames into ``out_dir/images`` (through a partial folder swapped in at the end)."""
    probes = {path: _probe(path) for path in videos}
    sizes = {path: (w, h) for path, (w, h, _) in probes.items()}
    if len(set(sizes.values())) > 1:
        listing = "; ".join(f"{path.name}: {w}x{h}" for path, (w, h) in sizes.items())
        raise UserInputError(f"the clips have different frame sizes ({listing}): one camera per survey")
    (width, height), = set(sizes.values())
    mask_png = videos[0].parent / SCENE_MASK_PNG
    mask = scene_mask_from(width, height, mask_png) if mask_png.is_file() else None
    partial = out_dir / ".images.partial"
    shutil.rmtree(partial, ignore_errors=True)
    try:
        partial.mkdir(parents=True)
    except OSError as exc:
        raise write_failed(partial, exc) from exc
    names: list[str] = []
    times_s: list[float] = []
    offset_s = 0.0
    digits = max(2, len(str(len(videos))))
    counts = [count for _, _, count in probes.values()]
    try:
        with tqdm(total=sum(counts) if min(counts) > 0 else None, desc="video", unit="frame",
                  disable=not cfg.progress) as bar:
            for k, path in enumerate(videos):
                clip = _Clip(path, bar)
                for time_s, image in keyframes(clip.frames(), cfg, mask):
                    name = f"{k + 1:0{digits}d}_{_stem(path)}_{time_s:010.3f}.png"
                    write_png(partial / name, np.ascontiguousarray(image[..., ::-1]))
                    names.append(name)
                    times_s.append(round(offset_s + time_s, 6))
                if clip.n_frames < 3:
                    raise _too_short(path, clip.n_frames)
                offset_s += clip.duration_s
        if len(names) < 3:
            raise UserInputError(f"{len(names)} frames kept from {offset_s:.1f} s of video; a survey needs at least "
                                 f"3: lower the video options max_step_s or overlap")
        if cfg.max_frames and len(names) > cfg.max_frames:
            chosen = set(np.round(np.linspace(0, len(names) - 1, cfg.max_frames)).astype(int).tolist())
            for k in set(range(len(names))) - chosen:
                (partial / names[k]).unlink()
            names, times_s = [names[k] for k in sorted(chosen)], [times_s[k] for k in sorted(chosen)]
        shutil.rmtree(out_dir / "images", ignore_errors=True)
        partial.rename(out_dir / "images")
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return VideoFrames(out_dir, names, times_s, round(offset_s, 6), width, height, reused=False)


def _side_files(beside: Path, cfg: VideoConfig) -> tuple[Path, Path]:
    """The camera.json and navigation.csv to copy: those given (an error when missing), else those ``beside`` the
    video (which may not be there)."""
    camera = Path(cfg.camera_json) if cfg.camera_json else beside / "camera.json"
    navigation = Path(cfg.navigation_csv) if cfg.navigation_csv else beside / NAVIGATION_CSV
    for path, given, what in ((camera, cfg.camera_json, "camera file"),
                              (navigation, cfg.navigation_csv, "navigation log")):
        if given and not path.is_file():
            raise UserInputError(f"{what} {path} does not exist")
    return camera, navigation


def _check_camera(camera: Path, width: int, height: int) -> None:
    """A camera.json for another frame size than the video's (``width`` x ``height``) is an error."""
    declared = read_json(camera, "camera file")
    size = (declared.get("width"), declared.get("height")) if isinstance(declared, dict) else None
    if size is not None and None not in size and size != (width, height):
        raise UserInputError(f"camera file {camera} is for {size[0]}x{size[1]} images; the video's frames are "
                             f"{width}x{height}: give the camera.json of this video's camera and frame size")


def _writable(out_dir: Path) -> None:
    """``out_dir`` made (when missing) and checked writable, before the frames are extracted: a WriteError naming it
    otherwise (a read-only place, a file where the folder should be)."""
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=out_dir, prefix=".write-test.")  # noqa: SIM115
    except OSError as exc:
        raise write_failed(out_dir, exc) from exc
    probe.close()


def _write_survey_files(beside: Path, out_dir: Path, cfg: VideoConfig, frames: VideoFrames) -> None:
    """survey.json, camera.json, navigation.csv and mask.png of the survey folder, from the files given or ``beside``
    the video (module docstring); one no longer there is removed. A camera.json for another frame size is an error
    (:func:`frames_from_video` checks it before anything is written)."""
    camera, navigation = _side_files(beside, cfg)
    if camera.is_file():
        _check_camera(camera, frames.width, frames.height)
    survey: dict = {"frames": frames.frames, "frame_time_s": frames.frame_time_s}
    if (beside / "survey.json").is_file():
        declared = read_survey_json(beside / "survey.json")
        survey.update({k: declared[k] for k in SURVEY_WIDE_KEYS if k in declared})
    atomic_write_json(out_dir / "survey.json", survey, finite=True)
    if camera.is_file():
        atomic_write_bytes(out_dir / "camera.json", camera.read_bytes())
    else:
        atomic_write_json(out_dir / "camera.json", {"width": frames.width, "height": frames.height})
    for source, name in ((navigation, NAVIGATION_CSV), (beside / SCENE_MASK_PNG, SCENE_MASK_PNG)):
        if source.is_file():
            atomic_write_bytes(out_dir / name, source.read_bytes())
        else:
            (out_dir / name).unlink(missing_ok=True)
