"""Survey trajectories: a lawnmower pattern of a downward-looking camera, with pose jitter; lines
may fly at different heights and look ahead, back or sideways (a diver's passes over a reef).

The vehicle body frame is x forward, y left, z up. The camera looks down (nadir) with the image's
top edge towards the direction of travel: camera x = body -y, camera y = body -x, camera z =
body -z. Body attitude is R_wb = Rz(heading + yaw) Ry(pitch) Rx(roll); the camera pose is
world_from_cam = [R_wb R_bc, centre]. A stereo rig's right camera sits ``baseline_m`` along the
left camera's +x axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .camera import Intrinsics, make_pose

#: Columns: the camera's x, y, z axes in the body frame (nadir camera, image top = forward).
CAM_IN_BODY = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).T


@dataclass(frozen=True)
class TrajectoryConfig:
    """A lawnmower survey: parallel lines along world x, alternating direction."""

    altitude_m: float = 2.5
    """Planned camera height above the flat seafloor datum z = 0 (the board area), metres."""
    forward_overlap: float = 0.8
    """Fraction of the along-track footprint shared by consecutive frames (0..1)."""
    side_overlap: float = 0.6
    """Fraction of the across-track footprint shared by neighbouring lines (0..1)."""
    n_lines: int = 4
    """Number of survey lines."""
    frames_per_line: int = 11
    """Frames taken along each line."""
    centre_xy_m: tuple[float, float] = (0.0, 0.0)
    """Centre of the surveyed rectangle in world x, y, metres."""
    roll_pitch_std_deg: float = 2.0
    """Standard deviation of roll and pitch (smooth AR(1) series), degrees."""
    yaw_std_deg: float = 1.5
    """Standard deviation of yaw about the line heading, degrees."""
    altitude_wave_m: float = 0.12
    """Amplitude of the slow altitude oscillation, metres."""
    altitude_wave_frames: float = 17.0
    """Period of the altitude oscillation, frames."""
    position_std_m: float = 0.03
    """Standard deviation of the cross-track and along-track position noise, metres."""
    stereo: bool = False
    """Also render a right camera of a stereo rig."""
    baseline_m: float = 0.12
    """Stereo baseline along the left camera's x axis, metres."""
    nav_altitude_noise_m: float = 0.01
    """Standard deviation of the navigation's (DVL-like) altitude reading, metres."""
    line_altitudes_m: tuple[float, ...] = ()
    """Camera height of each line in turn (cycled), metres; empty: ``altitude_m`` for every line. Line
    and frame spacing follow ``altitude_m`` whatever the line's height."""
    line_tilts_deg: tuple[tuple[float, float], ...] = ()
    """Tilt of the optical axis of each line in turn (cycled) from nadir, (towards the direction of
    travel, towards the left of it), degrees; the camera is moved so that its axis still meets the
    datum on the planned line (it looks at the same strip from the side). Empty: nadir lines."""


@dataclass(frozen=True)
class Trajectory:
    world_from_cam: np.ndarray               # (N,4,4) left (or only) camera
    world_from_cam_right: np.ndarray | None  # (N,4,4) right camera of a stereo rig
    line: np.ndarray                         # (N,) survey line index of each frame

    def __len__(self) -> int:
        return len(self.world_from_cam)


def body_rotation(heading: float, pitch: float, roll: float) -> np.ndarray:
    """R_wb = Rz(heading) Ry(pitch) Rx(roll), angles in radians."""
    ch, sh, cp, sp, cr, sr = (math.cos(heading), math.sin(heading), math.cos(pitch), math.sin(pitch),
                              math.cos(roll), math.sin(roll))
    rz = np.array([[ch, -sh, 0], [sh, ch, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def footprint_m(intr: Intrinsics, altitude_m: float) -> tuple[float, float]:
    """Across-track (image width) and along-track (image height) ground footprint of a nadir
    camera over flat ground, metres: W z / fx, H z / fy."""
    return intr.width * altitude_m / intr.fx, intr.height * altitude_m / intr.fy


def _ar1(rng: np.random.Generator, n: int, std: float, rho: float = 0.8) -> np.ndarray:
    """A stationary AR(1) series x_k = rho x_{k-1} + sqrt(1 - rho^2) std e_k."""
    x = np.empty(n)
    x[0] = rng.normal(0, std)
    for k in range(1, n):
        x[k] = rho * x[k - 1] + math.sqrt(1 - rho * rho) * rng.normal(0, std)
    return x


def rig_right(world_from_cam: np.ndarray, baseline_m: float) -> np.ndarray:
    """Pose of the right camera: world_from_cam @ T(baseline, 0, 0)."""
    offset = np.eye(4)
    offset[0, 3] = baseline_m
    return world_from_cam @ offset


def lawnmower(config: TrajectoryConfig, intr: Intrinsics, seed: int) -> Trajectory:
    """Frame poses of a lawnmower survey. Line spacing = (1 - side_overlap) x across-track
    footprint, frame spacing = (1 - forward_overlap) x along-track footprint (at ``altitude_m``);
    lines run along +x and -x in turn, ordered from +y to -y. A line of height h (``line_altitudes_m``)
    tilted by (a forward, b left) (``line_tilts_deg``) has pitch -a and roll +b added to the body
    attitude and its camera centre moved by -h (tan a f + tan b l), f and l the unit forward and left
    directions, so the tilted axis meets the datum where a nadir one would."""
    c = config
    if c.n_lines < 1 or c.frames_per_line < 1:
        raise ValueError("n_lines and frames_per_line must be at least 1")
    if not (0 <= c.forward_overlap < 1 and 0 <= c.side_overlap < 1):
        raise ValueError("forward_overlap and side_overlap must be in [0, 1)")
    rng = np.random.default_rng([seed, 23])
    across, along = footprint_m(intr, c.altitude_m)
    line_step, frame_step = (1 - c.side_overlap) * across, (1 - c.forward_overlap) * along
    n = c.n_lines * c.frames_per_line
    roll = np.radians(_ar1(rng, n, c.roll_pitch_std_deg))
    pitch = np.radians(_ar1(rng, n, c.roll_pitch_std_deg))
    yaw = np.radians(_ar1(rng, n, c.yaw_std_deg))
    jitter = rng.normal(0, c.position_std_m, (n, 2))
    wave_phase = rng.uniform(0, 2 * math.pi)
    poses, lines = [], []
    for k in range(n):
        line, j = divmod(k, c.frames_per_line)
        direction = 1.0 if line % 2 == 0 else -1.0
        along_pos = (j - (c.frames_per_line - 1) / 2) * frame_step * direction
        height = c.line_altitudes_m[line % len(c.line_altitudes_m)] if c.line_altitudes_m else c.altitude_m
        forward, left = (math.radians(a) for a in c.line_tilts_deg[line % len(c.line_tilts_deg)]) \
            if c.line_tilts_deg else (0.0, 0.0)
        heading = 0.0 if direction > 0 else math.pi
        axis = (body_rotation(heading, -forward, left) @ CAM_IN_BODY)[:, 2]  # the line's optical axis, no jitter
        y = c.centre_xy_m[1] + ((c.n_lines - 1) / 2 - line) * line_step + jitter[k, 1] + height * axis[1] / axis[2]
        x = c.centre_xy_m[0] + along_pos + jitter[k, 0] + height * axis[0] / axis[2]
        z = height + c.altitude_wave_m * math.sin(2 * math.pi * k / c.altitude_wave_frames + wave_phase)
        rotation = body_rotation(heading + yaw[k], pitch[k] - forward, roll[k] + left) @ CAM_IN_BODY
        poses.append(make_pose(rotation, np.array([x, y, z])))
        lines.append(line)
    poses = np.array(poses)
    right = np.array([rig_right(p, c.baseline_m) for p in poses]) if c.stereo else None
    return Trajectory(world_from_cam=poses, world_from_cam_right=right, line=np.array(lines))
