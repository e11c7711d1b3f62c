"""A navigation log as AUV and diver rigs write it (``navigation.csv`` beside the images), read into the survey
file's per-frame navigation.

Columns (a header row; names case-insensitive, other columns ignored):

- ``frame`` (an image file name) or ``time_s`` (seconds; then ``survey.json``'s ``frame_time_s`` gives each
  frame's time, and the log is interpolated linearly at it, attitude included);
- ``altitude_m`` (above the seafloor), ``depth_m`` (below the surface): optional, each;
- ``easting_m``, ``northing_m`` (the frame's position in the projected CRS that ``survey.json``'s ``crs`` names,
  e.g. a UTM zone; :mod:`pipeline.georeference`): optional, together, and only with that ``crs``;
- ``x_m``, ``y_m``, ``z_m`` (a local position track, metres: any two of them for a vehicle in a horizontal plane, or
  all three): ``nav_position_m``, which gives SfM its metric scale (:mod:`pipeline.scale`); easting_m and
  northing_m (with depth_m as the third axis, negated) give it too;
- ``roll_deg``, ``pitch_deg`` (the vehicle's attitude; ``heading_deg`` may be there and is not needed): optional,
  together. They give ``nav_down_cam``, "down" in the camera frame, for a camera looking straight down with the
  top of the image towards the bow (camera x to starboard, y aft, z down): with roll phi (starboard down positive)
  and pitch theta (bow up positive), down_body = (-sin theta, sin phi cos theta, cos phi cos theta) in the
  vehicle's (forward, starboard, down) axes, and down_cam = (down_body_y, -down_body_x, down_body_z).

:func:`navigation_from_log` returns the survey file's keys (``nav_altitude_m``, ``nav_depth_m``, ``nav_down_cam``,
``nav_easting_m``, ``nav_northing_m``, ``nav_position_m``) in the order of the frames; a frame the log does not reach
(no row of its name, a time outside the log) is an error naming it, as is a row that is not numbers.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError

#: The log's file name in a survey folder.
NAVIGATION_CSV = "navigation.csv"
#: Survey-file keys and the log's columns that give them.
COLUMNS = {"nav_altitude_m": "altitude_m", "nav_depth_m": "depth_m", "nav_easting_m": "easting_m",
           "nav_northing_m": "northing_m"}


#: A local position track's columns (metres).
POSITION_COLUMNS = ("x_m", "y_m", "z_m")


def down_in_camera(roll_deg: np.ndarray, pitch_deg: np.ndarray) -> np.ndarray:
    """(N,3) "down" in the camera frame from the vehicle's roll and pitch (degrees; see the module docstring)."""
    phi, theta = np.radians(roll_deg), np.radians(pitch_deg)
    body = np.stack([-np.sin(theta), np.sin(phi) * np.cos(theta), np.cos(phi) * np.cos(theta)], -1)
    return np.stack([body[:, 1], -body[:, 0], body[:, 2]], -1)


def read_log(path: Path) -> dict[str, list[str]]:
    """{column (lower case): its values as text} of a CSV file with a header row."""
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise UserInputError(f"navigation log {path} cannot be read: {exc}") from exc
    if len(rows) < 2:
        raise UserInputError(f"navigation log {path} has no rows under its header")
    header = [h.strip().lower() for h in rows[0]]
    short = [i + 2 for i, r in enumerate(rows[1:]) if len(r) != len(header) and any(c.strip() for c in r)]
    if short:
        raise UserInputError(f"navigation log {path}: line {short[0]} has another number of values than the header")
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    return {h: [r[i].strip() for r in body] for i, h in enumerate(header)}


def _numbers(path: Path, log: dict[str, list[str]], column: str) -> np.ndarray:
    try:
        return np.array([float(v) for v in log[column]])
    except ValueError:
        bad = next(v for v in log[column] if not _is_float(v))
        raise UserInputError(f"navigation log {path}: {column} holds {bad!r}, not a number") from None


def _is_float(text: str) -> bool:
    try:
        float(text)
        return math.isfinite(float(text))
    except ValueError:
        return False


def _check_positions(path: Path, log: dict[str, list[str]]) -> None:
    """easting_m and northing_m come together, and with the ``crs`` of the survey file beside the log."""
    from watergan.survey_files import read_survey_json

    positions = [c for c in ("easting_m", "northing_m") if c in log]
    if len(positions) == 1:
        raise UserInputError(f"navigation log {path} has {positions[0]} alone: give easting_m and northing_m")
    survey = path.with_name("survey.json")
    declared = read_survey_json(survey) if survey.is_file() else {}
    if positions and "crs" not in declared:
        raise UserInputError(f"navigation log {path} gives easting_m and northing_m but {survey} names no crs: add "
                             f"\"crs\": \"EPSG:<code>\" to it (the projected CRS in metres of the positions)")
    if "crs" in declared and not positions and "nav_easting_m" not in declared:
        raise UserInputError(f"{survey} gives crs {declared['crs']} but neither it (nav_easting_m, nav_northing_m) "
                             f"nor the navigation log {path} (easting_m, northing_m) gives the frames' positions")


def navigation_from_log(path: Path, frames: list[str], frame_time_s: list[float] | None = None) -> dict:
    """The survey file's navigation keys for ``frames`` (image file names) from the log at ``path`` (see the module
    docstring): rows matched by ``frame``, or interpolated at ``frame_time_s`` by ``time_s``."""
    log = read_log(path)
    given = [key for key, column in COLUMNS.items() if column in log]
    attitude = "roll_deg" in log and "pitch_deg" in log
    local = [c for c in POSITION_COLUMNS if c in log]
    if len(local) == 1:
        raise UserInputError(f"navigation log {path} has {local[0]} alone: a position needs two of x_m, y_m, z_m")
    if not given and not attitude and not local:
        raise UserInputError(f"navigation log {path} has none of the columns altitude_m, depth_m, roll_deg + "
                             f"pitch_deg, easting_m + northing_m, x_m + y_m (its columns: {', '.join(log)})")
    _check_positions(path, log)
    columns = [COLUMNS[k] for k in given] + (["roll_deg", "pitch_deg"] if attitude else []) + local
    values = {c: _numbers(path, log, c) for c in columns}
    if "frame" in log:
        index = {name: i for i, name in enumerate(log["frame"])}
        lacking = [f for f in frames if f not in index]
        if lacking:
            raise UserInputError(f"navigation log {path} has no row for {len(lacking)} of the {len(frames)} frames "
                                 f"(e.g. {lacking[0]}): add them, or give time_s and survey.json's frame_time_s")
        at = {c: v[[index[f] for f in frames]] for c, v in values.items()}
    elif "time_s" in log:
        if frame_time_s is None or len(frame_time_s) != len(frames):
            raise UserInputError(f"navigation log {path} is by time (time_s): survey.json must give frame_time_s, "
                                 f"one time per frame of its frames")
        t = _numbers(path, log, "time_s")
        order = np.argsort(t)
        times = np.asarray(frame_time_s, float)
        outside = [f for f, s in zip(frames, times, strict=True) if not t.min() <= s <= t.max()]
        if outside:
            raise UserInputError(f"navigation log {path} spans {t.min():g}-{t.max():g} s; {len(outside)} frames lie "
                                 f"outside it (e.g. {outside[0]})")
        at = {c: np.interp(times, t[order], v[order]) for c, v in values.items()}
    else:
        raise UserInputError(f"navigation log {path} needs a frame column (image file names) or a time_s column")
    if "altitude_m" in at and not (at["altitude_m"] > 0).all():
        bad = frames[int(np.argmin(at["altitude_m"]))]
        raise UserInputError(f"navigation log {path}: altitude_m is not positive for {bad}")
    out = {key: np.round(at[COLUMNS[key]], 4).tolist() for key in given}
    if attitude:
        out["nav_down_cam"] = np.round(down_in_camera(at["roll_deg"], at["pitch_deg"]), 6).tolist()
    if local:
        out["nav_position_m"] = np.round(np.stack([at[c] for c in local], 1), 5).tolist()
    elif "easting_m" in at:
        axes = [at["easting_m"], at["northing_m"]] + ([-at["depth_m"]] if "depth_m" in at else [])
        out["nav_position_m"] = np.round(np.stack(axes, 1), 5).tolist()
    return out
