"""Georeferencing: the survey frame placed in a projected CRS by the navigation's positions.

The survey frame (:func:`pipeline.scale.survey_frame`) is metric with z up, but its rotation about the vertical and
its origin are arbitrary. When ``survey.json`` names a CRS (``"crs": "EPSG:<code>"``, projected, in metres, e.g.
a UTM zone) and gives each frame's position in it (``nav_easting_m``, ``nav_northing_m``, or a navigation log's
``easting_m``, ``northing_m``: :mod:`pipeline.navigation`), a 2-D similarity

    (E, N) = s R(theta) (x, y) + (t_E, t_N),   R(theta) = [[cos theta, -sin theta], [sin theta, cos theta]],

is fitted by least squares (Umeyama 1991, in 2-D; no reflection) from the registered cameras' centres (x, y in
the survey frame) to their positions. theta (degrees, counter-clockwise) turns the survey frame's x axis onto
east. The scale s is fitted and applied (an unscaled SfM then still lands in metres), but SfM is already metric:
s beyond 1 +- ``MAX_SCALE_ERROR`` is a warning, as is an RMS residual over ``MAX_RMS_M`` or over
``MAX_RMS_FRACTION`` of the positions' spread (the rotation is then poorly pinned), and positions that fit
better mirrored (easting and northing swapped?). Fewer than 3 registered frames with a position, or positions
that do not spread (all within ``MIN_SPREAD_M`` of their centroid), are an error: nothing fixes the rotation.
A single straight line is enough: without a reflection the line's direction fixes theta.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.survey_files import EPSG_PATTERN

#: |s - 1| above this is a warning (SfM is metric: the navigation and SfM disagree on the scale).
MAX_SCALE_ERROR = 0.05
#: An RMS residual above this (metres) is a warning.
MAX_RMS_M = 0.5
#: An RMS residual above this fraction of the positions' RMS spread about their centroid is a warning.
MAX_RMS_FRACTION = 0.1
#: Positions within this distance (RMS, metres) of their centroid cannot fix the rotation.
MIN_SPREAD_M = 0.05


class GeoreferenceError(UserInputError):
    """The positions cannot place the survey frame (too few, or not spread)."""


@dataclass(frozen=True)
class Georeference:
    """The fitted similarity from the survey frame's (x, y) to (easting, northing) in ``crs``."""

    crs: str
    """"EPSG:<code>"."""
    rotation_deg: float
    """theta: counter-clockwise angle from the survey frame's x axis to east."""
    scale: float
    """s: CRS metres per survey-frame unit."""
    translation_m: tuple[float, float]
    """(t_E, t_N): where the survey frame's origin lands."""
    rms_m: float
    """RMS distance between the fitted and the given positions."""
    max_residual_m: float
    n_frames: int
    """Registered frames with a position (the fit's samples)."""
    warning: str = ""
    """Why the fit is doubtful (scale, residual, mirror); empty: none."""

    @property
    def epsg(self) -> int:
        return int(self.crs.split(":")[1])

    def linear(self) -> np.ndarray:
        """The 2x2 matrix s R(theta)."""
        c, s = math.cos(math.radians(self.rotation_deg)), math.sin(math.radians(self.rotation_deg))
        return self.scale * np.array([[c, -s], [s, c]])

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) survey-frame x, y -> easting, northing."""
        return np.asarray(xy, float) @ self.linear().T + np.asarray(self.translation_m)

    def summary(self) -> str:
        """One line: CRS, rotation, scale, residual."""
        return (f"{self.crs}: rotation {self.rotation_deg:+.2f} deg, scale {self.scale:.4f}, RMS residual "
                f"{self.rms_m:.3f} m over {self.n_frames} frames")


def epsg_code(crs: str) -> str:
    """"EPSG:<code>" (upper case, stripped) of a CRS text as :func:`watergan.survey_files.read_survey_json` accepts
    it."""
    match = EPSG_PATTERN.fullmatch(str(crs))
    if match is None:
        raise UserInputError(f"crs {crs!r} is not \"EPSG:<code>\"")
    return f"EPSG:{int(match[1])}"


def _umeyama_2d(src: np.ndarray, dst: np.ndarray, reflect: bool = False) -> tuple[np.ndarray, float, np.ndarray]:
    """(R, s, t) minimising sum |dst - (s R src + t)|^2; R a rotation (``reflect``: a reflection)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sv, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.ones(2)
    if (np.linalg.det(u) * np.linalg.det(vt) < 0) != reflect:
        d[1] = -1.0
    rot = u @ np.diag(d) @ vt
    scale = float((sv * d).sum() / (a**2).sum(1).mean())
    return rot, scale, mu_d - scale * rot @ mu_s


def fit_georeference(local_xy: np.ndarray, en: np.ndarray, crs: str) -> Georeference:
    """The similarity from ``local_xy`` (N,2: survey-frame x, y of the camera centres) to ``en`` (N,2: easting,
    northing in ``crs``); see the module docstring for the errors and warnings."""
    local_xy, en = np.asarray(local_xy, float).reshape(-1, 2), np.asarray(en, float).reshape(-1, 2)
    crs = epsg_code(crs)
    if len(local_xy) < 3:
        raise GeoreferenceError(f"georeferencing needs at least 3 registered frames with a position; "
                                f"{len(local_xy)} have one")
    spread_local = float(np.sqrt(((local_xy - local_xy.mean(0)) ** 2).sum(1).mean()))
    spread = float(np.sqrt(((en - en.mean(0)) ** 2).sum(1).mean()))
    if min(spread, spread_local) < MIN_SPREAD_M:
        raise GeoreferenceError(f"the {len(en)} registered frames' positions lie within {min(spread, spread_local):.3f}"
                                f" m of their centroid: they cannot fix the survey's rotation")
    rot, scale, t = _umeyama_2d(local_xy, en)
    residual = np.linalg.norm(en - (local_xy @ (scale * rot).T + t), axis=1)
    rms = float(np.sqrt((residual**2).mean()))
    notes = []
    if abs(scale - 1) > MAX_SCALE_ERROR:
        notes.append(f"scale {scale:.3f} is {100 * abs(scale - 1):.0f} % from 1 (SfM's scale and the navigation "
                     f"disagree)")
    if rms > MAX_RMS_M or rms > MAX_RMS_FRACTION * spread:
        notes.append(f"RMS residual {rms:.3f} m is large for positions spread over {spread:.2f} m (the rotation is "
                     f"poorly fixed)")
    m_rot, m_scale, m_t = _umeyama_2d(local_xy, en, reflect=True)
    mirrored = float(np.sqrt((np.linalg.norm(en - (local_xy @ (m_scale * m_rot).T + m_t), axis=1) ** 2).mean()))
    if mirrored < 0.5 * rms:
        notes.append(f"the positions fit mirrored (RMS {mirrored:.3f} m): are easting and northing swapped?")
    return Georeference(crs=crs, rotation_deg=math.degrees(math.atan2(rot[1, 0], rot[0, 0])), scale=scale,
                        translation_m=(float(t[0]), float(t[1])), rms_m=rms, max_residual_m=float(residual.max()),
                        n_frames=len(en), warning="; ".join(notes))


def survey_positions(survey: dict, names: list[str]) -> tuple[str, dict[str, tuple[float, float]]] | None:
    """(crs, {frame name: (easting, northing)}) of a checked survey file's content
    (:func:`watergan.survey_files.read_survey_json`; ``frames`` absent: ``names`` in order); None without a crs."""
    if "crs" not in survey:
        return None
    if "nav_easting_m" not in survey:
        raise GeoreferenceError(f"the survey names crs {survey['crs']} but gives no positions (nav_easting_m, "
                                f"nav_northing_m)")
    frames = survey.get("frames", names)
    if len(frames) != len(survey["nav_easting_m"]):
        raise GeoreferenceError(f"{len(survey['nav_easting_m'])} positions for {len(frames)} frames: give frames "
                                f"(the file name of each position) in survey.json")
    return epsg_code(survey["crs"]), {str(f): (float(e), float(n)) for f, e, n in
                                      zip(frames, survey["nav_easting_m"], survey["nav_northing_m"], strict=True)}


def georeference_tracks(tracks, survey_json: Path) -> Georeference | None:
    """The fit (:func:`fit_georeference`) of the registered cameras of ``tracks`` (:class:`eval.tracks.Tracks`,
    survey frame) to the positions of the survey file ``survey_json``; None when it names no crs (or is absent)."""
    from watergan.survey_files import read_survey_json

    if not Path(survey_json).is_file():
        return None
    names = [str(n) for n in tracks.image_names]
    given = survey_positions(read_survey_json(Path(survey_json)), names)
    if given is None:
        return None
    crs, positions = given
    rows = [k for k in np.flatnonzero(tracks.registered) if names[k] in positions]
    local = tracks.world_from_cam[rows, :2, 3] if rows else np.zeros((0, 2))
    return fit_georeference(local, np.array([positions[names[k]] for k in rows]).reshape(-1, 2), crs)
