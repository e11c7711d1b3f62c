"""The in-air RGB-D training set: many views of other random seafloor scenes (other seeds, other
photographs and tints, no board), from nadir and oblique poses.

The scenes are drawn to resemble the survey site (sediment photographs, tints and texture contrast
near the site's), as an in-air set chosen for a survey would be: WaterGAN can change colour and
brightness, not content, so a set with twice the site's texture contrast pushes the learned water
towards a murkier one (a larger eta dims the texture, a stronger veil restores the mean).

Written as ``rgb/NNNNNN.png`` (sRGB 8-bit in-air colour), ``depth/NNNNNN.png`` (camera z, 16-bit
millimetres, 0 where a ray leaves the scene) and ``camera.json`` (intrinsics of these images).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .camera import intrinsics_from_fov, make_pose
from .io import write_depth_png, write_json, write_srgb_png
from .render import RenderConfig, make_raycaster, render_view
from .scene import SceneConfig, build_scene
from .trajectory import CAM_IN_BODY, body_rotation

#: Photographs whose texture reads as sediment (the colour ones are left out: their hues are not
#: sediment's).
GREY_TEXTURES = ("gravel", "grass", "brick")

#: Sediment tints (linear albedo) the random scenes choose from: sand, darker sand, shell grit, algal
#: film. Close to the survey site's brightness, as an in-air set chosen for a survey would be.
TINTS = ((0.42, 0.35, 0.24), (0.34, 0.29, 0.21), (0.5, 0.47, 0.4), (0.3, 0.34, 0.22))


@dataclass(frozen=True)
class RGBDConfig:
    """Size and variety of the RGB-D training set."""

    n_scenes: int = 4
    """Number of random seafloor scenes."""
    views_per_scene: int = 60
    """Views rendered of each scene."""
    width_px: int = 128
    """Image width, pixels."""
    height_px: int = 96
    """Image height, pixels."""
    hfov_deg: float = 70.0
    """Horizontal field of view, degrees."""
    altitude_m: tuple[float, float] = (1.5, 3.5)
    """Range of camera heights above the scene datum, metres."""
    max_tilt_deg: float = 25.0
    """Largest tilt of the optical axis from nadir, degrees (uniform in 0..this)."""
    scene_size_m: float = 16.0
    """Side of each square scene, metres."""
    grid_spacing_m: float = 0.08
    """Heightfield vertex spacing of the scenes, metres."""


def random_scene_config(rng: np.random.Generator, size_m: float, spacing_m: float) -> SceneConfig:
    """A board-less seafloor with random sediment photographs (two different grey ones, for the detail
    and the overlay), tint, texture contrast, relief and rocks."""
    detail = GREY_TEXTURES[rng.integers(len(GREY_TEXTURES))]
    overlay = [t for t in GREY_TEXTURES if t != detail][rng.integers(len(GREY_TEXTURES) - 1)]
    return SceneConfig(size_x_m=size_m, size_y_m=size_m, grid_spacing_m=spacing_m,
                       relief_m=float(rng.uniform(0.05, 0.3)), n_rocks=int(rng.integers(3, 10)),
                       rock_height_m=(0.1, float(rng.uniform(0.3, 0.8))),
                       texel_m=float(rng.uniform(0.004, 0.007)),
                       detail_texture=detail, overlay_texture=overlay,
                       tint_linear=TINTS[rng.integers(len(TINTS))],
                       colour_variation=float(rng.uniform(0.1, 0.25)),
                       detail_contrast=float(rng.uniform(0.9, 1.3)), board=None)


def random_view_pose(rng: np.random.Generator, config: RGBDConfig) -> np.ndarray:
    """A camera above the central third of the scene, looking down with a random tilt and
    heading: world_from_cam = [Rz(heading) Ry(tilt cos phi) Rx(tilt sin phi) R_bc, centre]."""
    half = config.scene_size_m / 6
    centre = np.array([rng.uniform(-half, half), rng.uniform(-half, half), rng.uniform(*config.altitude_m)])
    tilt = math.radians(rng.uniform(0, config.max_tilt_deg))
    phi = rng.uniform(0, 2 * math.pi)
    rotation = body_rotation(rng.uniform(0, 2 * math.pi), tilt * math.cos(phi), tilt * math.sin(phi))
    return make_pose(rotation @ CAM_IN_BODY, centre)


def write_rgbd_set(out_dir: Path, config: RGBDConfig, seed: int, progress: bool | None = None) -> int:
    """Render the set into ``out_dir`` (created); returns the number of views."""
    intr = intrinsics_from_fov(config.width_px, config.height_px, config.hfov_deg)
    (out_dir / "rgb").mkdir(parents=True)
    (out_dir / "depth").mkdir()
    write_json(out_dir / "camera.json", intr.to_json())
    rng = np.random.default_rng([seed, 31])
    render = RenderConfig()
    total = config.n_scenes * config.views_per_scene
    with tqdm(total=total, desc="rgb-d set", unit="view", disable=None if progress is None else not progress) as bar:
        for s in range(config.n_scenes):
            scene = build_scene(random_scene_config(rng, config.scene_size_m, config.grid_spacing_m),
                                seed=int(rng.integers(2**31)))
            caster = make_raycaster(scene)
            for v in range(config.views_per_scene):
                view = render_view(caster, scene, intr, random_view_pose(rng, config), render)
                name = f"{s * config.views_per_scene + v:06d}.png"
                write_srgb_png(out_dir / "rgb" / name, view.inair)
                write_depth_png(out_dir / "depth" / name, np.where(view.valid, view.depth_m, 0.0))
                bar.update()
    return total

