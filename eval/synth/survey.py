"""``simulate_survey``: render a survey with known truth and write it to a folder.

Layout (what a user would have at the top, the truth under ``truth/``):

    images/NNNNNN.png        underwater images (sRGB, 8 or 16 bit); right/ too for a stereo rig
    camera.json              intrinsics (fx, fy, cx, cy, width, height, hfov_deg; baseline_m if stereo)
    survey.json              frame names, navigation altitude and depth per frame, site depth, lights
    rgbd/                    in-air RGB-D training set of other scenes (rgb/, depth/, camera.json)
    truth/inair/             in-air sRGB 8-bit images
    truth/inair_linear/      in-air linear 16-bit images
    truth/depth/, range/     camera z and ray length, 16-bit millimetres
    truth/poses.json         world_from_cam per frame (and the right camera's)
    truth/effects.json       {"visible", "hidden", "full"} stack configurations
    truth/board.json         colour-board patch corners (world) and true colours
    truth/scene.ply          the site mesh
    truth/config.json        the simulation configuration

Everything is written into a temporary sibling folder that is renamed into place at the end.
"""

from __future__ import annotations

import os
import shutil
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from tqdm import tqdm

from watergan.device import single_torch_thread
from watergan.errors import UserInputError
from watergan.formation import Counts, Stack
from watergan.formation.effects.artificial_light import beam_angle_deg
from watergan.io import quantise, write_depth_png, write_png, write_srgb_png

from .camera import intrinsics_for, lens_rays_cam
from .config import SimulationConfig, config_to_dict
from .imaging import add_sensor_noise, build_stacks, encode, linear_image, rig_camera_config
from .io import write_json
from .render import View, frame_state, make_raycaster, render_view
from .rgbd import write_rgbd_set
from .scene import BOARD, build_scene
from .trajectory import Trajectory, lawnmower


class SimulationError(UserInputError):
    """The simulation cannot run as asked (output folder, configuration); the message says what to do."""


@dataclass(frozen=True)
class SimulationResult:
    """What ``simulate_survey`` wrote."""

    out_dir: Path
    """The survey folder (absolute)."""
    frames: int
    """Frames of the survey (per camera)."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""
    stereo: bool
    """Whether right-camera images were written to ``right/``."""
    board_frames: list[int]
    """Frames in which the colour board covers at least one pixel."""
    n_rgbd: int
    """Views in the RGB-D training set."""
    seconds: float
    """Wall time of the simulation."""


class _Writer:
    """Runs file writes on background threads (cv2's PNG encoder releases the GIL), so they overlap
    with rendering; leaving the ``with`` block waits for them and re-raises the first error."""

    def __init__(self, workers: int = 2, max_pending: int = 32) -> None:
        self._pool = ThreadPoolExecutor(workers)
        self._pending: list[Future] = []
        self._max_pending = max_pending

    def submit(self, fn, *args) -> None:
        self._pending.append(self._pool.submit(fn, *args))
        if len(self._pending) > self._max_pending:
            self._pending.pop(0).result()

    def __enter__(self) -> _Writer:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                for future in self._pending:
                    future.result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


def simulate_survey(out_dir: str | Path, config: SimulationConfig, force: bool = False,
                    progress: bool | None = None) -> SimulationResult:
    """Render the survey described by ``config`` into ``out_dir``.

    ``out_dir`` must not exist or be empty unless ``force`` (then it is replaced once the new
    survey is complete). ``progress``: show progress bars (None: only on a terminal).
    Raises :class:`SimulationError` for an unusable output folder or configuration.
    """
    start = time.perf_counter()
    out_dir = Path(out_dir).absolute()
    _check_config(config)
    try:
        stacks = build_stacks(config.formation.visible, config.formation.hidden,
                              config.trajectory.n_lines * config.trajectory.frames_per_line)
    except (ValueError, KeyError) as exc:
        raise SimulationError(f"invalid formation stack: {exc}") from exc
    tmp = _prepare_output(out_dir, force)
    try:
        frames, board_frames, n_rgbd = _write_survey(tmp, config, stacks, progress)
        _commit(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SimulationResult(out_dir=out_dir, frames=frames, width=config.camera.width_px,
                            height=config.camera.height_px, stereo=config.trajectory.stereo,
                            board_frames=board_frames, n_rgbd=n_rgbd, seconds=time.perf_counter() - start)


def _check_config(config: SimulationConfig) -> None:
    f = config.formation
    if f.bit_depth not in (8, 16):
        raise SimulationError(f"formation.bit_depth must be 8 or 16, got {f.bit_depth}")
    if f.shot_noise_e <= 0 or f.read_noise < 0:
        raise SimulationError("formation.shot_noise_e must be > 0 and formation.read_noise >= 0")
    t = config.trajectory
    if t.n_lines < 1 or t.frames_per_line < 1:
        raise SimulationError("trajectory.n_lines and trajectory.frames_per_line must be at least 1")


def _prepare_output(out_dir: Path, force: bool) -> Path:
    """Check ``out_dir`` and create the temporary sibling folder the survey is written into."""
    if out_dir.exists() and not out_dir.is_dir():
        raise SimulationError(f"output path {out_dir} exists and is not a folder: choose another path")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise SimulationError(f"output folder {out_dir} already exists and is not empty: choose another "
                              f"folder, or pass force=True (--force) to replace it")
    parent = out_dir.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        if not os.access(parent, os.W_OK):
            raise PermissionError(f"no write permission on {parent}")
        tmp = parent / f".{out_dir.name}.partial-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
    except OSError as exc:
        raise SimulationError(f"cannot write the survey next to {out_dir} ({exc.__class__.__name__}: {exc}); "
                              f"choose an output folder in a writable location") from exc
    return tmp


def _commit(tmp: Path, out_dir: Path) -> None:
    """Rename the finished folder into place, replacing an old one only after the new one is complete."""
    if out_dir.exists():
        old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
        out_dir.rename(old)
        tmp.rename(out_dir)
        shutil.rmtree(old)
    else:
        tmp.rename(out_dir)


def nav_altitudes(caster: o3d.t.geometry.RaycastingScene, trajectory: Trajectory, noise_m: float,
                  seed: int) -> np.ndarray:
    """What a DVL-like altimeter reports: the vertical distance from each camera centre down to
    the seafloor (or board), plus Gaussian noise of ``noise_m``, metres."""
    centres = trajectory.world_from_cam[:, :3, 3]
    rays = np.concatenate([centres, np.tile([0.0, 0.0, -1.0], (len(centres), 1))], 1).astype(np.float32)
    t = caster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    if not np.isfinite(t).all():
        raise SimulationError("a camera is not above the site: enlarge the scene or move the survey")
    return t + np.random.default_rng([seed, 43]).normal(0.0, noise_m, len(t))


def _write_survey(root: Path, config: SimulationConfig, stacks, progress: bool | None
                  ) -> tuple[int, list[int], int]:
    visible, hidden, full = stacks
    intr = intrinsics_for(config.camera)
    scene = build_scene(config.scene, config.seed)
    caster = make_raycaster(scene)
    trajectory = lawnmower(config.trajectory, intr, config.seed)
    stereo = trajectory.world_from_cam_right is not None
    cameras = [("images", trajectory.world_from_cam, full)]
    if stereo:  # lights are fixed to the rig: the right camera sees them shifted by the baseline
        right = full if "artificial_light" not in full.names else Stack.from_config(
            rig_camera_config(full.to_config(), (config.trajectory.baseline_m, 0.0, 0.0)),
            Counts(frames=len(trajectory)))
        cameras.append(("right", trajectory.world_from_cam_right, right))
    truth = root / "truth"
    for folder in [name for name, _, _ in cameras] + ["inair", "inair_linear", "depth", "range"]:
        (root / folder if folder in ("images", "right") else truth / folder).mkdir(parents=True, exist_ok=True)

    board_part = next((i for i, p in enumerate(scene.parts) if p.kind == BOARD), None)
    board_pixels = []
    names = [frame_name(k) for k in range(len(trajectory))]
    f = config.formation
    lens = lens_rays_cam(intr, config.camera.lens) if config.camera.lens else None
    with _Writer() as writer, single_torch_thread():
        for k in tqdm(range(len(trajectory)), desc="survey", unit="frame",
                      disable=None if progress is None else not progress):
            for cam, (folder, poses, stack) in enumerate(cameras):
                view = render_view(caster, scene, intr, poses[k], config.render, lens)
                if not view.valid.all():
                    raise SimulationError(f"frame {k} ({folder}) sees past the edge of the site: enlarge "
                                          f"the scene or shrink the survey")
                state = frame_state(view, k, config.render.site_depth_m)
                noisy = add_sensor_noise(linear_image(stack, state), f.shot_noise_e, f.read_noise,
                                         np.random.default_rng([config.seed, 41, k, cam]))
                writer.submit(_write_image, root / folder / names[k], noisy, f.bit_depth)
                if cam == 0:
                    if lens is not None:  # the truth in the pinhole geometry the survey stage undistorts to
                        view = render_view(caster, scene, intr, poses[k], config.render)
                    writer.submit(_write_frame_truth, truth, names[k], view)
                    board_pixels.append(int((view.part == board_part).sum()) if board_part is not None else 0)

    altitudes = nav_altitudes(caster, trajectory, config.trajectory.nav_altitude_noise_m, config.seed)
    camera_json = intr.to_json()
    camera_json.update(config.camera.lens.to_json() if config.camera.lens else {})
    if stereo:
        camera_json["baseline_m"] = config.trajectory.baseline_m
    write_json(root / "camera.json", camera_json)
    write_json(root / "survey.json", {
        "frames": names,
        "images": "images",
        "right_images": "right" if stereo else None,
        "stereo": stereo,
        "bit_depth": f.bit_depth,
        "nav_altitude_m": altitudes.round(4).tolist(),
        "nav_down_cam": (-trajectory.world_from_cam[:, 2, :3]).round(6).tolist(),  # R^T (0, 0, -1): the IMU's gravity
        "nav_depth_m": (config.render.site_depth_m - trajectory.world_from_cam[:, 2, 3]).round(4).tolist(),
        "max_altitude_m": round(float(altitudes.max()), 4),
        "site_depth_m": config.render.site_depth_m,
        "lights": _lights(full),
    })
    frames_json = []
    for k, name in enumerate(names):
        entry = {"name": name, "world_from_cam": trajectory.world_from_cam[k].tolist()}
        if stereo:
            entry["world_from_cam_right"] = trajectory.world_from_cam_right[k].tolist()
        frames_json.append(entry)
    write_json(truth / "poses.json", {
        "convention": "world_from_cam 4x4: p_world = R p_cam + t; camera x right, y down, z forward; "
                      "world z up; metres",
        "frames": frames_json,
    })
    write_json(truth / "effects.json", {"visible": visible.to_config(), "hidden": hidden.to_config(),
                                        "full": full.to_config()})
    board_frames = [k for k, n in enumerate(board_pixels) if n > 0]
    board_json = scene.board.to_json() if scene.board is not None else {"patches": []}
    board_json["frames"] = [{"name": names[k], "pixels": board_pixels[k]} for k in board_frames]
    write_json(truth / "board.json", board_json)
    if not o3d.io.write_triangle_mesh(str(truth / "scene.ply"), scene.legacy_mesh()):
        raise OSError(f"could not write {truth / 'scene.ply'}")
    write_json(truth / "config.json", config_to_dict(config))
    n_rgbd = write_rgbd_set(root / "rgbd", config.rgbd, config.seed, progress,
                            site=config.scene if config.rgbd.like_site else None)
    return len(names), board_frames, n_rgbd


def _write_image(path: Path, linear: np.ndarray, bit_depth: int) -> None:
    write_png(path, encode(linear, bit_depth))


def _write_frame_truth(truth: Path, name: str, view: View) -> None:
    write_srgb_png(truth / "inair" / name, view.inair)
    write_png(truth / "inair_linear" / name, quantise(view.inair, 16))
    write_depth_png(truth / "depth" / name, view.depth_m)
    write_depth_png(truth / "range" / name, view.range_m)


def _lights(full) -> list[dict]:
    """The light rig a user knows, if the scene is lit artificially: per light ``artificial_light``'s
    ``rig_params`` exactly as rendered (``offset_m`` in the frame of the camera of ``images/``, metres;
    ``tilt_deg``, the aim; ``beam_deg``, the Gaussian beam's sigma) and ``beam_angle_deg``, the full angle
    at half intensity that a strobe's data sheet gives (2 sqrt(2 ln 2) sigma)."""
    for effect in full.effects:
        if effect.name == "artificial_light":
            p = effect.to_config()["params"]
            return [{key: p[key][i] for key in effect.rig_params if key in p}
                    | {"beam_angle_deg": beam_angle_deg(p["beam_deg"][i])} for i in range(len(p["offset_m"]))]
    return []
