"""Named simulation presets and the parameters of the hidden effects.

- ``demo``: 44 frames (4 lines x 11) of 640x480 from a stereo rig at 2.0-3.0 m (2.5 m with a slow
  0.5 m altitude wave, as a vehicle following terrain does) over a 14 m x 10 m site with the colour
  board, plus a 240-view RGB-D set at 320x240 over the same altitudes.
  The altitude wave matters to WaterGAN: at one range a common change of every eta_c is undone by the
  gain, so only frames at several ranges fix eta's level. The RGB-D set is rendered at 320x240, not
  smaller: a point-sampled texture at a coarse resolution aliases into far more contrast than the
  site's frames show once both are reduced to WaterGAN's 64x48.
- ``reef``: a diver's hand-held stereo rig over a coral reef after the WaterGAN paper's Port Royal and
  Lizard Island sites (see :func:`reef_config`): 60 frames of 640x480, passes 1.1-2.5 m above the datum
  over mounds (about 0.8-2.5 m from the reef below the image centre), looking down, ahead, back and
  sideways (up to 35 degrees off nadir), colonies of saturated reds, purples, oranges, greens and blues
  over sand and rock, shallow water (5 m) lit from above.
- ``auv``: an AUV after Bryson et al.'s surveys (see :func:`auv_config`): 60 stereo frames of 640x480 at
  2-4 m altitude (changing along each line) over sand and boulders at 34 m depth in darkness, lit by two
  strobes beside the camera that ``survey.json`` declares.
  Both give WaterGAN the generic in-air set (``RGBDConfig.like_site`` False: grey sediment photographs and
  sediment tints, not the site's), as a user without a site-matched RGB-D set has.
- ``tiny``: 6 frames (2 lines x 3) of 160x120 over a small site, a 12-view RGB-D set; for tests.
- ``small``: 10 frames (2 lines x 5) of 320x240 over the tiny site, with the overlap SfM needs; for
  end-to-end tests of every stage.
"""

from __future__ import annotations

import math
from dataclasses import replace

from watergan.formation import builtin_effects, get
from watergan.formation.effects.artificial_light import FWHM_PER_SIGMA

from .camera import CameraConfig
from .config import FormationConfig, SimulationConfig, default_visible_stack
from .render import RenderConfig
from .rgbd import RGBDConfig
from .scene import SceneConfig
from .survey import SimulationError
from .trajectory import TrajectoryConfig

#: Effects that cannot be hidden, and why.
NOT_SIMULATED = {"backscatter_conv": "it is a learned network (WaterGAN's G-II), not a physical model to render",
                 **{name: "a nuisance that stands in for what a fitted stack lacks, not one physical effect"
                    for name, cls in builtin_effects().items() if cls.nuisance}}

#: The parameters the simulator gives each built-in effect it can hide (those not in the visible stack
#: nor in NOT_SIMULATED): each class's ``simulation_params`` ({} = the effect's own initial values).
HIDDEN_DEFAULTS: dict[str, dict] = {
    name: dict(cls.simulation_params) for name, cls in builtin_effects().items()
    if name not in NOT_SIMULATED and name not in {e["name"] for e in default_visible_stack()}
}


def reef_config() -> SimulationConfig:
    """The ``reef`` preset. Five passes of 12 frames over the same 3 m x 3 m of reef, each at its own height
    above the datum and tilt (1.2 m looking 28 degrees ahead, 2.4 m nadir, 1.1 m looking back, 2.5 m nadir,
    1.2 m looking left), a diver's 0.4 m bobbing with a 5-frame period (camera 0.75-2.9 m above the datum)
    and 3 degrees of hand-held jitter, so a point is seen from several ranges and angles, also within a
    pass. Mounds 0.2-0.4 m high (relief up to 0.62 m). Colonies of seven colours (saturated reds, purples,
    oranges, pinks, yellow-browns, greens, blues) cover 85 % of the floor, mounds first; sand shows around
    the board and between colonies. Water: coastal reef water, red beam
    attenuation 0.6 /m (a little above Jerlov 3C's Kd at 650 nm) (eta 0.6, 0.12, 0.1 /m) under a blue veil
    (B_inf 0.01, 0.05, 0.5); downwelling light fading with the point's depth by Jerlov 1C's Kd
    (0.45, 0.13, 0.25) /m about the 5 m datum.

    Why these numbers (issue 19's target: raw consistency >= 2e-3 in R and B on the SfM tracks): SfM tracks
    link views with similar viewpoints, so a track spans less range than the views that see its point, and a
    track's variance grows with that spread. The fast, large bobbing changes the range within a pass, where SfM
    links consecutive frames. Saturated albedos vary more across views than grey ones, hence the large cover and
    a pink in place of a pale coral. The strong red attenuation and the blue veil steepen the normalised colour's
    change with range. Measurements: benchmarks/RESULTS/corrections.md."""
    visible = (
        {"name": "attenuation", "params": {"eta_per_m": [0.6, 0.12, 0.1]}},
        {"name": "backscatter", "params": {"b_inf": [0.01, 0.05, 0.5], "beta_per_m": [0.35, 0.3, 0.3]}},
        {"name": "vignetting", "params": {"a_margin": 0.35, "b": 0.0, "c": 0.05}},
        {"name": "gain", "params": {"k": [1.5, 1.5, 1.5]}},
        {"name": "ambient_depth", "params": {"kappa_per_m": [0.45, 0.13, 0.25], "reference_depth_m": 5.0}})
    return SimulationConfig(
        preset="reef",
        camera=CameraConfig(width_px=640, height_px=480, hfov_deg=70.0),
        scene=SceneConfig(
            size_x_m=12.0, size_y_m=12.0, relief_m=0.05, n_rocks=40, rock_radius_m=(0.25, 0.6),
            rock_height_m=(0.2, 0.4), detail_texture="moon", overlay_texture="moon", tint_linear=(0.45, 0.4, 0.3),
            rock_tint_linear=(0.2, 0.17, 0.13), colour_variation=0.2, detail_contrast=1.6,
            cover_palette_linear=(
                (0.5, 0.03, 0.04),    # red encrusting sponge
                (0.3, 0.04, 0.38),    # purple soft coral
                (0.6, 0.15, 0.02),    # orange sponge
                (0.42, 0.28, 0.04),   # yellow-brown hard coral
                (0.05, 0.28, 0.05),   # green algae
                (0.03, 0.12, 0.4),    # blue coral tips
                (0.5, 0.1, 0.25),     # pink coralline algae
            ),
            cover_fraction=0.85, cover_patch_m=0.4),
        trajectory=TrajectoryConfig(
            altitude_m=2.0, n_lines=5, frames_per_line=12, forward_overlap=0.85, side_overlap=0.75, stereo=True,
            line_altitudes_m=(1.2, 2.4, 1.1, 2.5, 1.2),
            line_tilts_deg=((28.0, 0.0), (0.0, 0.0), (-28.0, 0.0), (0.0, 0.0), (0.0, 28.0)),
            roll_pitch_std_deg=3.0, yaw_std_deg=3.0, altitude_wave_m=0.4, altitude_wave_frames=5.0,
            position_std_m=0.04),
        render=RenderConfig(ambient=0.3, site_depth_m=5.0),
        formation=FormationConfig(visible=visible),
        rgbd=RGBDConfig(n_scenes=4, views_per_scene=50, width_px=320, height_px=240, altitude_m=(1.0, 2.8),
                        max_tilt_deg=30.0, like_site=False),
    )


#: The auv preset's strobes: (position in the camera frame of images/, metres; aim, degrees towards +x and
#: +y; beam angle, the full angle at half intensity, degrees).
AUV_STROBES = (((-0.44, 0.0, 0.0), (10.0, 0.0), 90.0), ((0.56, 0.0, 0.0), (-10.0, 0.0), 90.0))


def auv_config() -> SimulationConfig:
    """The ``auv`` preset. Four lines of 15 frames at 3 m +/- 0.9 m altitude (a full altitude cycle per
    line), side overlap 50 %, over sand and boulders at 34 m depth. Darkness: the in-air image is the albedo
    (render ambient 1: no downwelling shading) and ``artificial_light`` lights it with two strobes 0.5 m
    either side of the rig's centre, aimed 10 degrees inwards, beam angle 90 degrees, no ambient light,
    the light path attenuated as the view path. Water: Jerlov III's effective attenuation (0.281, 0.136,
    0.129) /m (REFERENCE-water), a weak veil (the strobes light little of the water column in view)."""
    eta = [0.281, 0.136, 0.129]
    light = {"name": "artificial_light", "params": {
        "offset_m": [list(s[0]) for s in AUV_STROBES], "tilt_deg": [list(s[1]) for s in AUV_STROBES],
        "beam_deg": [s[2] / FWHM_PER_SIGMA for s in AUV_STROBES], "power": [4.0] * len(AUV_STROBES),
        "eta_per_m": eta, "ambient": 0.0}}
    visible = (
        light,
        {"name": "attenuation", "params": {"eta_per_m": eta}},
        {"name": "backscatter", "params": {"b_inf": [0.005, 0.02, 0.025], "beta_per_m": [0.3, 0.3, 0.3]}},
        {"name": "vignetting", "params": {"a_margin": 0.35, "b": 0.0, "c": 0.05}},
        {"name": "gain", "params": {"k": [1.5, 1.5, 1.5]}},
    )
    return SimulationConfig(
        preset="auv",
        camera=CameraConfig(width_px=640, height_px=480, hfov_deg=70.0),
        scene=SceneConfig(
            size_x_m=20.0, size_y_m=16.0, relief_m=0.1, n_rocks=30, rock_radius_m=(0.2, 0.5),
            rock_height_m=(0.15, 0.5), detail_texture="moon", overlay_texture="gravel",
            tint_linear=(0.42, 0.36, 0.26), rock_tint_linear=(0.15, 0.14, 0.12), colour_variation=0.15),
        trajectory=TrajectoryConfig(
            altitude_m=3.0, n_lines=4, frames_per_line=15, forward_overlap=0.75, side_overlap=0.5, stereo=True,
            altitude_wave_m=0.85, altitude_wave_frames=15.0, roll_pitch_std_deg=1.5, yaw_std_deg=1.5),
        render=RenderConfig(ambient=1.0, site_depth_m=34.0),
        formation=FormationConfig(visible=visible),
        rgbd=RGBDConfig(n_scenes=4, views_per_scene=50, width_px=320, height_px=240, altitude_m=(2.0, 4.0),
                        max_tilt_deg=10.0, like_site=False),
    )


PRESETS: dict[str, SimulationConfig] = {
    "demo": SimulationConfig(
        preset="demo",
        camera=CameraConfig(width_px=640, height_px=480, hfov_deg=70.0),
        trajectory=TrajectoryConfig(n_lines=4, frames_per_line=11, stereo=True, altitude_wave_m=0.5),
        rgbd=RGBDConfig(n_scenes=4, views_per_scene=60, width_px=320, height_px=240, altitude_m=(2.0, 3.0),
                        max_tilt_deg=10.0),
    ),
    "reef": reef_config(),
    "auv": auv_config(),
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


def with_frames(config: SimulationConfig, frames: int) -> SimulationConfig:
    """The survey flown longer or shorter over a site grown or shrunk alike: at least ``frames`` frames, its lines
    scaled by sqrt(frames / the survey's frames) and as many frames per line as it then takes, the site's sides grown
    (never shrunk: the frames would see past its edge) by the same factors as the lines and the frames per line (its
    rocks by their product); camera, altitudes, overlaps
    and the RGB-D set as they are. The demo's 44 frames (4 x 11) become 176 as 8 x 22 over a site twice as long and
    wide, 500 as 13 x 39 (507 frames)."""
    t, scene = config.trajectory, config.scene
    if frames < 1:
        raise SimulationError(f"a survey needs at least one frame, not {frames}")
    factor = math.sqrt(frames / (t.n_lines * t.frames_per_line))
    lines = max(1, round(t.n_lines * factor))
    per_line = math.ceil(frames / lines)
    grow_x, grow_y = max(1.0, per_line / t.frames_per_line), max(1.0, lines / t.n_lines)  # lines run along x
    return replace(config, trajectory=replace(t, n_lines=lines, frames_per_line=per_line),
                   scene=replace(scene, size_x_m=scene.size_x_m * grow_x, size_y_m=scene.size_y_m * grow_y,
                                 n_rocks=max(1, round(scene.n_rocks * grow_x * grow_y))))


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

