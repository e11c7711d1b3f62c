"""Named simulation presets and the parameters of the hidden effects.

- ``demo``: 44 frames (4 lines x 11) of 640x480 from a stereo rig at 2.5 m over a 14 m x 10 m
  site with the colour board, plus a 240-view RGB-D set at 128x96.
- ``tiny``: 6 frames (2 lines x 3) of 160x120 over a small site, a 12-view RGB-D set; for tests.
"""

from __future__ import annotations

from dataclasses import replace

from watergan.formation import get

from .camera import CameraConfig
from .config import SimulationConfig
from .rgbd import RGBDConfig
from .scene import SceneConfig
from .trajectory import TrajectoryConfig

#: Parameters the simulator gives each hidden effect ({} = the effect's own initial values).
HIDDEN_DEFAULTS: dict[str, dict] = {
    "vignetting_offcentre": {"centre_uv": [0.61, 0.44]},
}

PRESETS: dict[str, SimulationConfig] = {
    "demo": SimulationConfig(
        preset="demo",
        camera=CameraConfig(width_px=640, height_px=480, hfov_deg=70.0),
        trajectory=TrajectoryConfig(n_lines=4, frames_per_line=11, stereo=True),
        rgbd=RGBDConfig(n_scenes=4, views_per_scene=60, width_px=128, height_px=96),
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


def make_config(preset: str = "demo", hidden: list[str] | tuple[str, ...] = (), seed: int = 0) -> SimulationConfig:
    """The named preset with the given hidden effects (parameters from HIDDEN_DEFAULTS) and seed."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset '{preset}'; choose one of {', '.join(PRESETS)}")
    base = PRESETS[preset]
    entries = []
    for name in hidden:
        get(name)  # a clear error listing the registered effects for an unknown name
        entries.append({"name": name, "params": dict(HIDDEN_DEFAULTS.get(name, {}))})
    return replace(base, seed=seed, formation=replace(base.formation, hidden=tuple(entries)))

