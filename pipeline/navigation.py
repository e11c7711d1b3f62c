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
(no row of its name, a time outside the log) is an error naming it, as is a cell that is empty, not a number, NaN or
infinite, and a frame (or time) on two rows: each error names the log, the line and the frame. A spreadsheet's CSV
reads as it is: a UTF-8 byte order mark is skipped, and ';' may separate the values.
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


class Log:
    """A navigation log's rows: ``columns`` {column (lower case): its values as text}, ``lines`` (each row's line in
    the file, 1 the header), ``path``."""

    def __init__(self, path: Path, columns: dict[str, list[str]], lines: list[int]) -> None:
        self.path, self.columns, self.lines = path, columns, lines

    def __contains__(self, column: str) -> bool:
        return column in self.columns

    def __getitem__(self, column: str) -> list[str]:
        return self.columns[column]

    def __iter__(self):
        return iter(self.columns)

    def row(self, i: int) -> str:
        """Where row ``i`` is, for an error: its line and its frame (or time)."""
        key = next((c for c in ("frame", "time_s") if c in self.columns), None)
        return f"line {self.lines[i]}" + (f" ({key} {self.columns[key][i]})" if key else "")


def read_log(path: Path) -> Log:
    """The rows of a CSV file with a header row, as spreadsheets write it: a UTF-8 byte order mark (Excel's "CSV
    UTF-8") is skipped, ';' separates the values when the header has no ',', blank rows are left out."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserInputError(f"navigation log {path} cannot be read: {exc}; save it as CSV (UTF-8)") from exc
    first = text.split("\n", 1)[0]
    rows = list(csv.reader(text.splitlines(), delimiter=";" if ";" in first and "," not in first else ","))
    numbered = [(k + 2, r) for k, r in enumerate(rows[1:]) if any(c.strip() for c in r)]
    if not rows or not numbered:
        raise UserInputError(f"navigation log {path} has no rows under its header")
    header = [h.strip().lower() for h in rows[0]]
    short = [line for line, r in numbered if len(r) != len(header)]
    if short:
        raise UserInputError(f"navigation log {path}: line {short[0]} has {len(dict(numbered)[short[0]])} values, the "
                             f"header {len(header)} ({', '.join(header)})")
    return Log(path, {h: [r[i].strip() for _, r in numbered] for i, h in enumerate(header)},
               [line for line, _ in numbered])


def _numbers(log: Log, column: str) -> np.ndarray:
    """The column's values, each a finite number: an empty cell, text, NaN or an infinity is an error naming the
    log, the line and the frame."""
    for i, text in enumerate(log[column]):
        if not _is_float(text):
            what = ("is empty" if not text else f"holds {text!r}, not a number" if not _parses(text) else
                    f"holds {text!r}, not a finite number")
            raise UserInputError(f"navigation log {log.path}: {column} {what}, on {log.row(i)}: give every row a "
                                 f"number there, or remove the row")
    return np.array([float(v) for v in log[column]])


def _parses(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _is_float(text: str) -> bool:
    return _parses(text) and math.isfinite(float(text))


def _unique(log: Log, column: str, values: list) -> None:
    """Each frame (or time) on one row only: a second row for it is an error naming both lines."""
    seen: dict = {}
    for i, value in enumerate(values):
        if value in seen:
            raise UserInputError(f"navigation log {log.path}: {column} {log[column][i]} is on line "
                                 f"{log.lines[seen[value]]} and again on line {log.lines[i]}: keep one row per "
                                 f"{'frame' if column == 'frame' else 'time'}")
        seen[value] = i


def _check_positions(path: Path, log: Log) -> None:
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
    values = {c: _numbers(log, c) for c in columns}
    if "frame" in log:
        _unique(log, "frame", log["frame"])
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
        t = _numbers(log, "time_s")
        _unique(log, "time_s", t.tolist())
        order = np.argsort(t)
        times = np.asarray(frame_time_s, float)
        outside = [f for f, s in zip(frames, times, strict=True) if not t.min() <= s <= t.max()]
        if outside:
            raise UserInputError(f"navigation log {path} spans {t.min():g}-{t.max():g} s; {len(outside)} frames lie "
                                 f"outside it (e.g. {outside[0]})")
        at = {c: np.interp(times, t[order], v[order]) for c, v in values.items()}
    else:
        raise UserInputError(f"navigation log {path} needs a frame column (image file names) or a time_s column "
                             f"(its columns: {', '.join(log)})")
    if "altitude_m" in at and not (at["altitude_m"] > 0).all():
        bad = frames[int(np.argmin(at["altitude_m"]))]
        where = f" on line {log.lines[index[bad]]}" if "frame" in log else ""
        raise UserInputError(f"navigation log {path}: altitude_m is not positive for {bad}{where}")
    out = {key: np.round(at[COLUMNS[key]], 4).tolist() for key in given}
    if attitude:
        out["nav_down_cam"] = np.round(down_in_camera(at["roll_deg"], at["pitch_deg"]), 6).tolist()
    if local:
        out["nav_position_m"] = np.round(np.stack([at[c] for c in local], 1), 5).tolist()
    elif "easting_m" in at:
        axes = [at["easting_m"], at["northing_m"]] + ([-at["depth_m"]] if "depth_m" in at else [])
        out["nav_position_m"] = np.round(np.stack(axes, 1), 5).tolist()
    return out
