"""The in-air RGB-D training set: many views of other random seafloor scenes (other seeds, other
photographs and tints, no board), from nadir and oblique poses.

The scenes are drawn to resemble the survey site, as an in-air set chosen for a survey would be
(``RGBDConfig.like_site``, the demo's choice): with the site's own scene configuration, each scene takes
the site's sediment photographs and a tint and texture contrast within about 15 % of the site's; without
one (a real survey, or the reef and auv presets), generic sediment photographs and tints.
WaterGAN can change colour and brightness, not content, so whatever differs between the set and the
site is learned as water: a set with twice the site's texture contrast pushes the learned water towards
a murkier one (a larger eta dims the texture, a stronger veil restores the mean), and a set greener than
the site raises the learned green and blue eta (measurements: benchmarks/RESULTS/gan.md).

Written as ``rgb/NNNNNN.png`` (sRGB 8-bit in-air colour), ``depth/NNNNNN.png`` (camera z, 16-bit
millimetres, 0 where a ray leaves the scene) and ``camera.json`` (intrinsics of these images).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from tqdm import tqdm

from watergan.io import write_depth_png, write_srgb_png

from .camera import intrinsics_from_fov, make_pose
from .io import write_json
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
    supersample: int = 2
    """Render at this many times the width and height, then area-average down.
    A point-sampled texture aliases into more contrast than the site's frames show once both are reduced to
    WaterGAN's size, and the discriminator then tells generated images by their texture, which no physical stage
    can change."""
    like_site: bool = True
    """Draw the scenes to resemble the survey site (its photographs, tint and texture contrast).
    As an in-air set chosen for the survey would be; False: the generic seafloor set (grey sediment photographs,
    sediment tints) that a user without a site-matched RGB-D set has."""


#: Relative spread of a scene's brightness and of each tint channel around the site's (site-matched sets).
SITE_BRIGHTNESS_SPREAD = 0.15
SITE_TINT_SPREAD = 0.05


def random_scene_config(rng: np.random.Generator, size_m: float, spacing_m: float,
                        site: SceneConfig | None = None) -> SceneConfig:
    """A board-less seafloor with random relief and rocks. Like ``site`` when given: its detail and
    overlay photographs, its tint times a brightness factor U(1 -/+ SITE_BRIGHTNESS_SPREAD) and a
    per-channel factor exp(N(0, SITE_TINT_SPREAD)), its texture contrast times U(0.85, 1.15).
    Otherwise generic: two different grey sediment photographs and one of TINTS."""
    if site is not None:
        detail, overlay = site.detail_texture, site.overlay_texture
        brightness = rng.uniform(1 - SITE_BRIGHTNESS_SPREAD, 1 + SITE_BRIGHTNESS_SPREAD)
        tint = np.asarray(site.tint_linear) * brightness * np.exp(rng.normal(0.0, SITE_TINT_SPREAD, 3))
        tint_linear = tuple(float(t) for t in tint.clip(0.02, 0.9))
        contrast = site.detail_contrast * float(rng.uniform(0.85, 1.15))
    else:
        detail = GREY_TEXTURES[rng.integers(len(GREY_TEXTURES))]
        overlay = [t for t in GREY_TEXTURES if t != detail][rng.integers(len(GREY_TEXTURES) - 1)]
        tint_linear = TINTS[rng.integers(len(TINTS))]
        contrast = float(rng.uniform(0.9, 1.3))
    return SceneConfig(size_x_m=size_m, size_y_m=size_m, grid_spacing_m=spacing_m,
                       relief_m=float(rng.uniform(0.05, 0.3)), n_rocks=int(rng.integers(3, 10)),
                       rock_height_m=(0.1, float(rng.uniform(0.3, 0.8))),
                       texel_m=float(rng.uniform(0.004, 0.007)),
                       detail_texture=detail, overlay_texture=overlay, tint_linear=tint_linear,
                       colour_variation=float(rng.uniform(0.1, 0.25)), detail_contrast=contrast, board=None)


def random_view_pose(rng: np.random.Generator, config: RGBDConfig) -> np.ndarray:
    """A camera above the central third of the scene, looking down with a random tilt and
    heading: world_from_cam = [Rz(heading) Ry(tilt cos phi) Rx(tilt sin phi) R_bc, centre]."""
    half = config.scene_size_m / 6
    centre = np.array([rng.uniform(-half, half), rng.uniform(-half, half), rng.uniform(*config.altitude_m)])
    tilt = math.radians(rng.uniform(0, config.max_tilt_deg))
    phi = rng.uniform(0, 2 * math.pi)
    rotation = body_rotation(rng.uniform(0, 2 * math.pi), tilt * math.cos(phi), tilt * math.sin(phi))
    return make_pose(rotation @ CAM_IN_BODY, centre)


def write_rgbd_set(out_dir: Path, config: RGBDConfig, seed: int, progress: bool | None = None,
                   site: SceneConfig | None = None) -> int:
    """Render the set into ``out_dir`` (created), its scenes like ``site`` when given (see
    :func:`random_scene_config`); returns the number of views."""
    intr = intrinsics_from_fov(config.width_px, config.height_px, config.hfov_deg)
    factor = max(1, config.supersample)
    fine = intrinsics_from_fov(config.width_px * factor, config.height_px * factor, config.hfov_deg)
    (out_dir / "rgb").mkdir(parents=True)
    (out_dir / "depth").mkdir()
    write_json(out_dir / "camera.json", intr.to_json())
    rng = np.random.default_rng([seed, 31])
    render = RenderConfig()
    total = config.n_scenes * config.views_per_scene
    with tqdm(total=total, desc="rgb-d set", unit="view", disable=None if progress is None else not progress) as bar, \
            ThreadPoolExecutor(RENDER_THREADS) as pool:
        for s in range(config.n_scenes):
            scene = build_scene(random_scene_config(rng, config.scene_size_m, config.grid_spacing_m, site),
                                seed=int(rng.integers(2**31)))
            caster = make_raycaster(scene)
            poses = [random_view_pose(rng, config) for _ in range(config.views_per_scene)]
            names = [f"{s * config.views_per_scene + v:06d}.png" for v in range(config.views_per_scene)]
            for _ in pool.map(partial(_write_view, out_dir, caster, scene, fine, render, factor), names, poses):
                bar.update()
    return total


def _write_view(out_dir: Path, caster, scene, intr, render: RenderConfig, factor: int, name: str,
                world_from_cam: np.ndarray) -> None:
    """One view of the set, rendered at ``factor`` times its size and area-averaged, into ``out_dir``."""
    view = render_view(caster, scene, intr, world_from_cam, render)
    rgb, depth_m = downsample_view(view.inair, view.depth_m, view.valid, factor)
    write_srgb_png(out_dir / "rgb" / name, rgb)
    write_depth_png(out_dir / "depth" / name, depth_m)


RENDER_THREADS = 2
"""Views of the RGB-D set rendered at once (NumPy's array work and OpenCV's encoding release the GIL); each view
is the same whatever the number."""


def downsample_view(rgb: np.ndarray, depth_m: np.ndarray, valid: np.ndarray, factor: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Area-average (H f, W f) renders to (H, W): the mean colour of each f x f block, and its mean
    depth where every pixel of the block has one (0 elsewhere: no value). Pixel centres map as the
    intrinsics of :func:`intrinsics_from_fov` at both sizes do."""
    if factor == 1:
        return rgb, np.where(valid, depth_m, 0.0)
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor

    def blocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(h, factor, w, factor, *a.shape[2:]).astype(np.float64)

    full = blocks(valid).min(axis=(1, 3)) > 0
    return blocks(rgb).mean(axis=(1, 3)), np.where(full, blocks(np.where(valid, depth_m, 0.0)).mean(axis=(1, 3)), 0.0)
