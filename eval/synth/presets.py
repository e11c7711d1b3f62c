"""Named simulation presets and the parameters of the hidden effects.

- ``demo``: 44 frames (4 lines x 11) of 640x480 from a stereo rig at 2.0-3.0 m (2.5 m with a slow
  0.5 m altitude wave, as a vehicle following terrain does) over a 14 m x 10 m site with the colour
  board, plus a 240-view RGB-D set at 320x240 over the same altitudes.
  The altitude wave matters to WaterGAN: at one range a common change of every eta_c is undone by the
  gain, so only frames at several ranges fix eta's level. The RGB-D set is rendered at 320x240, not
  smaller: a point-sampled texture at a coarse resolution aliases into far more contrast than the
  site's frames show once both are reduced to WaterGAN's 64x48.
- ``tiny``: 6 frames (2 lines x 3) of 160x120 over a small site, a 12-view RGB-D set; for tests.
- ``small``: 10 frames (2 lines x 5) of 320x240 over the tiny site, with the overlap SfM needs; for
  end-to-end tests of every stage.
"""

from __future__ import annotations

from dataclasses import replace

from watergan.formation import builtin_effects, get

from .camera import CameraConfig
from .config import SimulationConfig, default_visible_stack
from .rgbd import RGBDConfig
from .scene import SceneConfig
from .survey import SimulationError
from .trajectory import TrajectoryConfig

#: Effects that cannot be hidden: learned ones have no physical parameters to simulate from.
NOT_SIMULATED = {"backscatter_conv": "it is a learned network (WaterGAN's G-II), not a physical model to render"}

#: The parameters the simulator gives each built-in effect it can hide (those not in the visible stack
#: nor in NOT_SIMULATED): each class's ``simulation_params`` ({} = the effect's own initial values).
HIDDEN_DEFAULTS: dict[str, dict] = {
    name: dict(cls.simulation_params) for name, cls in builtin_effects().items()
    if name not in NOT_SIMULATED and name not in {e["name"] for e in default_visible_stack()}
}

PRESETS: dict[str, SimulationConfig] = {
    "demo": SimulationConfig(
        preset="demo",
        camera=CameraConfig(width_px=640, height_px=480, hfov_deg=70.0),
        trajectory=TrajectoryConfig(n_lines=4, frames_per_line=11, stereo=True, altitude_wave_m=0.5),
        rgbd=RGBDConfig(n_scenes=4, views_per_scene=60, width_px=320, height_px=240, altitude_m=(2.0, 3.0),
                        max_tilt_deg=10.0),
    ),
    "tiny": SimulationConfig(
        preset="tiny",
        camera=CameraConfig(width_px=160, height_px=120, hfov_deg=70.0),
        scene=SceneConfig(size_x_m=8.0, size_y_m=7.0, grid_spacing_m=0.1, n_rocks=3),
        trajectory=TrajectoryConfig(n_lines=2, frames_per_line=3, forward_overlap=0.6, stereo=True),
        rgbd=RGBDConfig(n_scenes=2, views_per_scene=6, width_px=64, height_px=48, scene_size_m=10.0,
                        grid_spacing_m=0.2),
    ),
}
PRESETS["small"] = replace(
    PRESETS["tiny"], preset="small", camera=CameraConfig(width_px=320, height_px=240, hfov_deg=70.0),
    trajectory=replace(PRESETS["tiny"].trajectory, n_lines=2, frames_per_line=5, forward_overlap=0.75),
    rgbd=replace(PRESETS["tiny"].rgbd, views_per_scene=12))


def make_config(preset: str = "demo", hidden: list[str] | tuple[str, ...] = (), seed: int = 0) -> SimulationConfig:
    """The named preset with the given hidden effects (parameters: each class's ``simulation_params``)
    and seed."""
    if preset not in PRESETS:
        raise SimulationError(f"unknown preset '{preset}'; choose one of {', '.join(PRESETS)}")
    base = PRESETS[preset]
    entries = []
    for name in hidden:
        cls = get(name)  # a clear error listing the registered effects for an unknown name
        if name in NOT_SIMULATED:
            raise SimulationError(f"effect '{name}' cannot be hidden in a simulation: {NOT_SIMULATED[name]}")
        entries.append({"name": name, "params": dict(cls.simulation_params)})
    return replace(base, seed=seed, formation=replace(base.formation, hidden=tuple(entries)))

