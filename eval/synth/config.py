"""The simulation's configuration: one frozen dataclass tree, saved as ``truth/config.json``."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from watergan.io import from_jsonable

from .camera import CameraConfig
from .render import RenderConfig
from .rgbd import RGBDConfig
from .scene import SceneConfig
from .trajectory import TrajectoryConfig


def default_visible_stack() -> tuple[dict, ...]:
    """The physics a WaterGAN-style model knows: coastal water seen at ~2.5 m, where red fades
    fastest, green-blue veiling light, centred vignetting and a camera gain that exposes the scene
    reasonably."""
    return (
        {"name": "attenuation", "params": {"eta_per_m": [0.45, 0.14, 0.2]}},
        {"name": "backscatter", "params": {"b_inf": [0.03, 0.16, 0.19], "beta_per_m": [0.45, 0.32, 0.32]}},
        {"name": "vignetting", "params": {"a_margin": 0.35, "b": 0.0, "c": 0.05}},
        {"name": "gain", "params": {"k": [1.5, 1.5, 1.5]}},
    )


@dataclass(frozen=True)
class FormationConfig:
    """How the underwater images are formed from the in-air render."""

    visible: tuple[dict, ...] = field(default_factory=default_visible_stack)
    """Stack configuration ({name, params} in scene-to-sensor order) of the physics the product
    knows about."""
    hidden: tuple[dict, ...] = ()
    """Stack configurations of the hidden effects, inserted into the visible stack by their rank."""
    shot_noise_e: float = 3000.0
    """Photo-electrons collected at a linear signal of 1: shot-noise variance = signal / this."""
    read_noise: float = 0.002
    """Standard deviation of the Gaussian read noise, linear signal units."""
    bit_depth: int = 8
    """Bits per channel of the written underwater images (8 or 16), sRGB-encoded."""


@dataclass(frozen=True)
class SimulationConfig:
    """A whole simulated survey: site, camera, trajectory, rendering, water and the RGB-D set."""

    preset: str = "custom"
    """Name of the preset this configuration came from."""
    seed: int = 0
    """Seed of every random choice; the same seed gives byte-identical output."""
    camera: CameraConfig = field(default_factory=CameraConfig)
    """The survey camera (the right camera of a stereo rig is identical)."""
    scene: SceneConfig = field(default_factory=SceneConfig)
    """The surveyed site."""
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    """The lawnmower survey and stereo rig."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """In-air shading and site depth."""
    formation: FormationConfig = field(default_factory=FormationConfig)
    """Underwater image formation (visible and hidden effects, noise, bit depth)."""
    rgbd: RGBDConfig = field(default_factory=RGBDConfig)
    """The in-air RGB-D training set of other seafloor scenes."""


def config_to_dict(config) -> dict:
    """A JSON-ready dict of a configuration dataclass (tuples become lists)."""
    return dataclasses.asdict(config)


def config_from_dict(cls, data: dict):
    """Rebuild a configuration dataclass (e.g. :class:`SimulationConfig`) from
    :func:`config_to_dict`'s output; unknown keys are an error (:func:`watergan.io.from_jsonable`)."""
    return from_jsonable(cls, data)
