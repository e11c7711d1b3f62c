"""A survey folder's own files, read and checked: its images' names, ``camera.json`` (intrinsics, lens, stereo
baseline) and ``survey.json`` (per-frame navigation, lights, a CRS). A malformed file is a :class:`DataError` naming
the file and the key. The scene mask (``mask.png``) is an image file: :mod:`watergan.io`.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .io import IMAGE_SUFFIXES, DataError, is_number, read_json


def image_files(folder: Path) -> list[str]:
    """Sorted image file names in a folder (clear error when there are none)."""
    if not folder.is_dir():
        raise DataError(f"image folder {folder} does not exist")
    names = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise DataError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    return names


def read_camera_json(path: Path, partial: bool = False) -> dict | None:
    """camera.json's intrinsics, None when there is no such file: fx, fy, cx, cy (OpenCV's pixel convention: pixel
    (i, j)'s centre at (i, j)), width, height, optional ``baseline_m`` and the lens (:mod:`watergan.lens`: OpenCV's
    ``k1, k2, p1, p2, k3[, k4, k5, k6]``, or ``"lens_model": "fisheye"`` with ``k1..k4``). COLMAP's form, ``model``
    and ``params`` in its order and pixel convention (cx + 0.5), is read into those names. Malformed JSON, a
    missing key, a value that is not a number, an unknown model or lens keys that are not the model's are an
    error naming the file. ``partial``: the intrinsics may be missing (a camera SfM self-calibrates): width and
    height are required, fx, fy, cx, cy optional (``hfov_deg``, the horizontal field of view, may stand for fx)."""
    from watergan.lens import MODEL_KEYS, camera_from_colmap

    path = Path(path)
    if not path.is_file():
        return None
    cam = read_json(path, "camera file")
    if not isinstance(cam, dict):
        raise DataError(f"{path} holds {type(cam).__name__}; expected an object with fx, fy, cx, cy, width, height")
    if "params" in cam:
        named = sorted({"fx", "fy", "cx", "cy", "lens_model", *MODEL_KEYS["opencv"]} & set(cam))
        if named:
            raise DataError(f"camera file {path} gives COLMAP's params and {', '.join(named)}: give one of them")
        params = cam["params"]
        if not (isinstance(params, list) and all(is_number(v) for v in params)):
            raise DataError(f"camera file {path}: params = {params!r} is not a list of numbers (COLMAP's order)")
        try:
            cam = {**cam, **camera_from_colmap(str(cam.get("model")), params, f"camera file {path}")}
        except ValueError as exc:
            raise DataError(str(exc)) from None
        del cam["params"]
    missing = ({"width", "height"} if partial else {"fx", "fy", "cx", "cy", "width", "height"}) - set(cam)
    if missing:
        raise DataError(f"{path} lacks {', '.join(sorted(missing))}: give fx, fy, cx, cy, width, height (or "
                        f"COLMAP's model and params)" + ("; width and height alone let SfM calibrate the camera"
                                                         if partial else ""))
    optional = {"baseline_m", "hfov_deg"} | ({"fx", "fy", "cx", "cy"} if partial else set())
    for key in ("fx", "fy", "cx", "cy", "width", "height", "baseline_m", "hfov_deg"):
        value = cam.get(key)
        if key in optional and value is None:
            continue
        positive = key not in ("cx", "cy")
        if not is_number(value) or (positive and not value > 0):
            raise DataError(f"camera file {path}: {key} = {value!r} is not a {'positive ' if positive else ''}number")
        if key in ("width", "height") and value != int(value):
            raise DataError(f"camera file {path}: {key} = {value!r} is not a whole number of pixels")
    if "hfov_deg" in cam and not 0 < cam["hfov_deg"] < 180:
        raise DataError(f"camera file {path}: hfov_deg = {cam['hfov_deg']!r} is not a field of view in degrees")
    if not isinstance(cam.get("calibrated", True), bool):
        raise DataError(f"camera file {path}: calibrated = {cam['calibrated']!r}: give true or false")
    model = cam.get("lens_model", "opencv")
    if model not in MODEL_KEYS:
        raise DataError(f"camera file {path}: lens_model = {model!r}: give \"opencv\" (k1, k2, p1, p2, k3[, k4, k5, "
                        f"k6]) or \"fisheye\" (k1, k2, k3, k4)")
    for key in MODEL_KEYS["opencv"]:
        value = cam.get(key)
        if value is None:
            continue
        if key not in MODEL_KEYS[model]:
            raise DataError(f"camera file {path}: {key} is not a coefficient of the fisheye lens (k1, k2, k3, k4)")
        if not is_number(value):
            raise DataError(f"camera file {path}: {key} = {value!r} is not a number (the {model} lens's distortion)")
    return cam


#: A CRS as survey.json names it: "EPSG:<code>" (case and surrounding spaces aside).
EPSG_PATTERN = re.compile(r"\s*EPSG:(\d{4,5})\s*", re.IGNORECASE)


#: survey.json's per-frame lists and what each value must be.
_PER_FRAME = {"nav_altitude_m": "a positive number", "nav_depth_m": "a number", "frame_time_s": "a number",
              "nav_easting_m": "a number", "nav_northing_m": "a number"}


def _check_crs(survey: dict, path: Path, where: str) -> None:
    """``crs`` ("EPSG:<code>" of a projected CRS in metres) and the positions (``nav_easting_m``, ``nav_northing_m``)
    come together; a navigation log beside the file may give the positions."""
    crs, given = survey.get("crs"), [k for k in ("nav_easting_m", "nav_northing_m") if k in survey]
    if len(given) == 1:
        raise DataError(f"{where} gives {given[0]} alone: give nav_easting_m and nav_northing_m (metres in its crs)")
    if crs is None:
        if given:
            raise DataError(f"{where} gives nav_easting_m and nav_northing_m but no crs: add \"crs\": \"EPSG:<code>\" "
                            f"(the projected CRS in metres they are in, e.g. EPSG:32633 for UTM zone 33N)")
        return
    match = EPSG_PATTERN.fullmatch(crs) if isinstance(crs, str) else None
    if match is None or not 1024 <= int(match[1]) <= 32766 or 4000 <= int(match[1]) < 5000:
        why = " (geographic, in degrees)" if match and 4000 <= int(match[1]) < 5000 else ""
        raise DataError(f"{where}: crs = {crs!r}{why} is not \"EPSG:<code>\" of a projected CRS in metres (e.g. "
                        f"\"EPSG:32633\", WGS 84 / UTM zone 33N)")
    if not given and not (path.parent / "navigation.csv").is_file():
        raise DataError(f"{where} gives crs {crs} but no positions: add nav_easting_m and nav_northing_m (one per "
                        f"frame), or a navigation.csv beside it with easting_m and northing_m columns")


def read_survey_json(path: Path) -> dict:
    """A survey file (``survey.json``: ``frames``, ``nav_altitude_m``, ``nav_depth_m``, ``frame_time_s``,
    ``nav_position_m`` ([x, y] or [x, y, z] metres per frame), ``camera_height_m``, ``site_depth_m``, ``lights``,
    ``crs`` with ``nav_easting_m`` + ``nav_northing_m``; every key optional), checked:
    malformed JSON, a value of the wrong type, or per-frame lists whose length differs from ``frames`` are an error
    naming the file and the key."""
    path = Path(path)
    survey = read_json(path, "survey file")
    where = f"survey file {path}"
    if not isinstance(survey, dict):
        raise DataError(f"{where} holds {type(survey).__name__}; expected an object (frames, nav_altitude_m, ...)")
    frames = survey.get("frames")
    if frames is not None and not (isinstance(frames, list) and all(isinstance(f, str) for f in frames)):
        raise DataError(f"{where}: frames must be a list of image file names")
    for key, what in _PER_FRAME.items():
        if key not in survey:
            continue
        values = survey[key]
        if not isinstance(values, list):
            raise DataError(f"{where}: {key} must be a list, one value per frame")
        bad = [i for i, v in enumerate(values) if not is_number(v) or (key == "nav_altitude_m" and not v > 0)]
        if bad:
            first = frames[bad[0]] if frames is not None and bad[0] < len(frames) else f"value {bad[0]}"
            raise DataError(f"{where}: {key} is not {what} for {len(bad)} frames (e.g. {first}: {values[bad[0]]!r})")
        if frames is not None and len(values) != len(frames):
            raise DataError(f"{where}: {len(values)} {key} values for {len(frames)} frames")
    _check_crs(survey, path, where)
    positions = survey.get("nav_position_m")
    if positions is not None:
        if not (isinstance(positions, list) and all(isinstance(p, list) and len(p) in (2, 3)
                                                    and all(is_number(v) for v in p) for p in positions)):
            raise DataError(f"{where}: nav_position_m must be a list of [x, y] or [x, y, z] positions in metres, "
                            f"one per frame")
        if frames is not None and len(positions) != len(frames):
            raise DataError(f"{where}: {len(positions)} nav_position_m values for {len(frames)} frames")
    if "camera_height_m" in survey and not (is_number(survey["camera_height_m"]) and survey["camera_height_m"] > 0):
        raise DataError(f"{where}: camera_height_m = {survey['camera_height_m']!r} is not a positive number (the "
                        f"camera's height over the floor, metres)")
    if "site_depth_m" in survey and not is_number(survey["site_depth_m"]):
        raise DataError(f"{where}: site_depth_m = {survey['site_depth_m']!r} is not a number")
    lights = survey.get("lights")
    if lights is not None:
        if not isinstance(lights, list) or not all(isinstance(light, dict) for light in lights):
            raise DataError(f"{where}: lights must be a list of objects (offset_m, tilt_deg, beam_deg per light)")
        for i, light in enumerate(lights):
            for key, value in light.items():
                flat = np.ravel(np.asarray(value, dtype=object))
                if not flat.size or not all(is_number(v) for v in flat):
                    raise DataError(f"{where}: lights[{i}].{key} = {value!r} is not a number or a list of numbers")
    return survey
