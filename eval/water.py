"""The site's water from the survey's own geometry, and the physics correction with each pixel's range.

``estimate_water(frames, K, ...)`` fits a formation stack (default ``attenuation``, ``backscatter``,
``vignetting``, ``gain``; any registered effect may be added) to the raw frames of one survey, their poses and
their dense range maps; ``correct_physics(image, range_m, stack)`` inverts that stack pixel by pixel with the
pixel's range. Both are functions of arrays: the pipeline's ``water`` stage reads the workspace and calls them.

Model. Every built-in effect of the default stack is affine in the in-air colour J, so an observation o (a
surface point p seen in frame f at pixel x_o with range r_o) records per channel c

    y_oc = A_c(x_o, r_o; theta) J_pc + C_c(x_o, r_o; theta)
    (default stack: A = k_c exp(-eta_c r) / V(x),  C = k_c B_inf,c (1 - exp(-beta_c r)) / V(x)),

with A = render(J = 1) - render(J = 0) and C = render(J = 0) of the stack (so added effects need no special
code). Per point the albedo J_p is projected out in closed form (weighted least squares over its views,
clamped at 0); the stack's bounded parameters theta are fitted by L-BFGS on a soft-L1 loss of the residuals.

Measurements, from the inputs alone:

- dense correspondences: ``samples_per_frame`` pixels of every frame with range (a quarter of them among the
  frame's darkest 5 %) are lifted to 3D with the range and the pose and projected into every other frame; a
  projection counts as a view of the same surface point when it lands inside the image and that frame's own
  range agrees with the point's distance within ``range_tolerance`` (occlusion test). Colours are read
  (bilinear) from the image blurred by a fixed footprint on the surface (``footprint_m``, see below), so a
  pixel of misregistration costs little; views with a channel at or above 0.98 (clipped) are dropped;
- SfM tracks (optional, off in the benchmark): each sparse point's observations, colour read at the feature
  positions (keypoints sit on blobs of the texture at one scale, which the other views see differently);
- the board (optional, :class:`eval.colour.Board`: true linear colours and per frame pixel quads): the patch
  means of each visible patch with its known J, range from the frame's range map.

What pins what (and what does not):

- attenuation eta_c: the same point seen at several ranges; the ratio of its views falls as exp(-eta_c dr).
  Frames flown at different altitudes see a point at one image position at different ranges, which separates
  eta from the vignetting (at one altitude, range and image position are tied for a flat seafloor and a
  common change of eta is nearly undone by the vignetting polynomial); channel differences of eta are pinned
  even without that, since the centred vignetting and the range are the same for the three channels.
- backscatter B_inf,c: the offset of each view (C above) that no albedo explains: points seen at several ranges
  give C(r2) - (A2/A1) C(r1), which for beta near eta is B_inf (1 - exp(-eta dr)): the asymptote is pinned by
  the multi-range views of many points of different albedo. Dark pixels (J clamped at 0; a quarter of the
  samples are the darkest pixels of each frame, Sea-thru's prior) record C alone. The board pins C at its
  ranges outright (known J, the black patch).
- backscatter beta_c: only through the curvature of C over the survey's range span (2-4 m on the demo); the
  family J_p + d, B(r) - d exp(-eta r) is close to the model's, so beta is weakly pinned, and more weakly
  the closer beta is to eta. Its interval says so.
- vignetting (a, b, c): the same point at different image positions; ``vignetting_offcentre`` (added) also
  its centre and per-channel strength.
- gain k_c: exactly degenerate with the albedos' overall scale per channel (k J = (k s)(J / s)), and B_inf
  carries the same factor (C = k B_inf ...). With a board, the board's known J pins k (and with it B_inf's
  absolute level). Without one, ``gain`` keeps its configured value (1) and is reported as fixed: B_inf and
  the corrected colours are then in units of that gain (their ratios between channels are still free of it
  only if the gain is grey, which a white balance need not be).

Uncertainty: a bootstrap (``bootstrap`` replicates): frames drawn with replacement (the frames that see the board
and the others drawn separately, so every replicate keeps the board), each surface point's views weighted Poisson(1)
times (the views of one point share its texture and registration errors, so frames alone are not independent units)
and so is each board patch's (a patch's error, e.g. its known colour against what its rendered or printed surface
gives, is shared by every frame that sees it: with frames alone resampled the board-pinned eta and B_inf had
intervals of +-1 % that missed 1-2 % errors). Each replicate is refitted from the full fit: one Newton step with the
full fit's Hessian (central differences of the gradient; eigenvalues floored at 1e-6 of the largest, the step halved
until it lowers the replicate's loss), then ``bootstrap_iterations`` L-BFGS steps. Resampling cannot see a bias that
every subset shares, so the fit is repeated under ``spec_alternatives`` (by default the board weighted 10x less: how
far the correspondences alone pull the estimate from the board's) and each parameter's largest change is added in
quadrature: interval = estimate +- sqrt((1.96 sd_boot)^2 + change^2), clipped to the bounds; coefficients in 1/m
also take the range's scale uncertainty (``range_scale_sd``: the monocular demo's altitude scale is 1.3 % short,
which moves every eta by +1.3 %). The bootstrap percentiles are kept too. Pairs of parameter components whose
bootstrap correlation exceeds 0.95 are reported as trade-offs (eta_c with k_c through the board's range, B_inf with
beta).

Why colours are read at a fixed footprint on the surface: with a fixed blur in pixels a near view averages a
smaller patch of the seafloor's texture than a far view, so the views of one point differ by a texture term
whose size depends on range; the profiled least squares then biases the ratio of near to far views, i.e. eta
(on the demo +3-7 %, gain +3 %, B_inf green +16 %, with the true geometry as much as with SfM's). Reading
every view at the same footprint (``footprint_m``) removes most of it (eta within 2 % without the board's
extra weight). This is the likely cause of the high eta of the diagnosis fit when it measures a survey itself (5 px
patches at SfM features), along with its few points; in a workspace it takes this table instead
(``Observations.save``, :func:`eval.diagnose_measure.measure_observations`).

Measured (benchmarks/bench_water.py, results/water.json; 2-core machine shared with other jobs): on the demo
with the board (seeds 0 and 1, stereo) eta within 1.2 % and B_inf within 2 % of the truth, beta within 5 %,
gain within 0.6 %; the monocular demo +1.9 % on eta (its altitude scale is 1.3 % short, which
``range_scale_sd`` carries into the interval); with ``vignetting_offcentre`` hidden and added, eta within 1.2 %
and B_inf within 1.5 %. All 24 eta and B_inf intervals of these four surveys cover the truth (with frames and
points alone resampled, before the board's patches were, 19 did; with one round of 150 iterations the
off-centre fit had stopped at red B_inf +12 %). Without a board (gain held at its true value) the
correspondences alone: eta +2/-3/+6 %, B_inf +13/-6/-2 %, beta poorly pinned (green 0.50 against 0.32).

A declared light rig (``lights``: survey.json's strobes, per light offset_m, tilt_deg, beam_deg; an AUV in
darkness): the stack gets ``artificial_light`` (:func:`build_stack`), so each view's in-air colour is lit by

    E_c(X) = ambient + sum_l P_l exp(-theta_l^2 / (2 sigma_l^2)) max(0, n . s_l / d_l) exp(-eta_c d_l) / d_l^2

(X the point and n its surface normal in the view's camera frame, s_l = L_l - X, d_l = |s_l| the light-to-point
distance; see :func:`watergan.formation.effects.artificial_light.light_irradiance`), and A = k_c E_c(X)
exp(-eta_c r) / V(x). Without it the lights' fall-off with distance (1/d^2 and the light path's exp(-eta d),
d ~ r for lights beside the camera) is read as attenuation: on the auv preset eta 1.17/0.81/0.76 per m against
0.28/0.14/0.13. What pins what there:

- offset_m, tilt_deg, beam_deg (the rig): declared, held (:func:`watergan.formation.rig.held_rig`, as the
  diagnosis holds them); a fit that moved them would trade them against eta.
- the light path's eta: tied to ``attenuation.eta_per_m`` (``WaterConfig.tied_params``: one water, one eta), so
  the same multi-range views pin both paths; with the rig known the lights' 1/d^2 and beam pattern are
  geometry, not parameters, and the remaining fall-off with range is the water's.
- power P_l: its level is exactly degenerate with the gain (only k_c P_l is seen, the board included), so it is
  held (``WaterConfig.held_params``, at the effect's initial value 4 unless ``initial`` gives one); the gain, and
  B_inf's level (C = k_c B_inf ...), are then in units of that power: only k_c P_l and k_c B_inf,c are measured.
  With the powers held the ratio between lights is the held one (equal by default).
- ambient: brightness that does not fall with the distance from the lights (other light), against the lights'
  pattern across the image and over range.
- normals: each dense sample's normal is taken from its source frame's range map smoothed by
  ``normal_smooth_px`` (:func:`normals_from_range`) and rotated into every view; SGBM range is noisy at the pixel
  scale: on auv the normals' median error against the truth was 15 deg at sigma 3 px, 2.8 at 16, 2.3 at 24 (the
  default), 3.2 at 48; the fused mesh's triangle normals 16 deg. Board patches take the mean normal inside the
  patch; SfM tracks the normals of the sparse cloud (:func:`eval.diagnose_measure.pca_normals`).

Measured on auv (seed 0, benchmarks/bench_water.py ``auv0``; off-centre vignetting hidden): eta +4.3/-11.9/-19.5 %
(without the rig +315/+493/+492 %), B_inf +32/+93/+123 %, 2 of 6 intervals covering the truth; with the hidden
effect added (``auv0_add``) eta +21/+12/+12 %. The hidden effect and the geometry limit it: with the true range,
poses and normals the fit gives eta +2/-7/-13 % without the hidden effect in the stack and within 2.5 % with it;
with the dense range and SfM poses but true normals +2/-11/-18 % and +10/+4/+5 % (README has the table). The veil
over the survey's 2-4 m, k B_inf (1 - exp(-beta r)), is within 4-12 %; its asymptote B_inf is not (beta 0.12-0.17
against 0.3: the strobes light little water and the span is short).

Known limits: in a flat direction (red B_inf against beta, the two vignettings) a fit stops where a round of
L-BFGS stops gaining, so what lies further along it is only as pinned as ``convergence_rtol`` says; the
off-centre fit needed 600 iterations (the ``max_iterations`` default). The vignetting polynomial's b and c
trade with each other (r^4 against r^6; bootstrap correlation -0.96): the falloff as a function is recovered
within 1 %, but their intervals do not cover the truth (b -0.04 to -0.05 and c 0.09-0.10 against 0 and 0.05
on every survey). The added effect's overall strength is exactly degenerate with its polynomial (s (a r^2 + b r^4 +
c r^6)), and the two vignetting effects trade with each other: only their product, and the strength ratios
between channels, are pinned (the off-centre strengths +12/+11/+12 % each, ratios 1 : 0.892 : 0.797 against
1 : 0.9 : 0.8).

Bad input: fewer than ``min_frames`` frames with a pose and range, range on too small a part of the frames,
or too few points seen at different ranges raise :class:`WaterInputError`, saying what to give.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from watergan.errors import UserInputError
from watergan.formation import Counts, FormationState, Stack, get
from watergan.formation.inverse import (
    affine_images,
    clean_range,
    inverse_fields,
    needs_normals,
    normals_from_range,
    rays_cam,
)
from watergan.formation.rig import held_rig, rig_settings

#: The water stack fitted by default: the simulator's visible physics (WaterGAN's learned backscatter
#: network is replaced by its analytic counterpart, which has physical parameters to estimate).
DEFAULT_WATER_EFFECTS = ("attenuation", "backscatter", "vignetting", "gain")


class WaterInputError(UserInputError):
    """The survey does not hold what the water estimate needs; the message says what to give."""


@dataclass(frozen=True)
class WaterFrame:
    """One survey frame as the estimator sees it.

    name:           the image's file name (the board's quads are keyed by it).
    image:          (H,W,3) raw linear RGB, 0..1 (sRGB-decoded).
    range_m:        (H,W) ray length from the camera centre to the scene, metres; NaN or <= 0 = no value.
                    (The dense stage writes camera z in millimetres; r = z |K^-1 (x, y, 1)|.)
    world_from_cam: (4,4) camera-to-world pose (OpenCV camera axes), same metric frame for every frame;
                    None: the frame has no pose (it takes no part).
    normals_cam:    optional (H,W,3) unit surface normals in the camera frame (e.g. of a fused mesh), read by
                    effects that need them (``artificial_light``); None: :func:`normals_from_range` of
                    ``range_m``.
    """

    name: str
    image: np.ndarray
    range_m: np.ndarray
    world_from_cam: np.ndarray | None
    normals_cam: np.ndarray | None = None


@dataclass(frozen=True)
class SparseTracks:
    """SfM points and their observations. ``obs_frame`` indexes the ``frames`` list given to estimate_water
    (map SfM image indices to it first); xy in pixels, OpenCV centres."""

    xyz: np.ndarray        # (P,3) world, same frame as the poses
    obs_point: np.ndarray  # (M,)
    obs_frame: np.ndarray  # (M,)
    obs_xy: np.ndarray     # (M,2)


@dataclass(frozen=True)
class WaterConfig:
    """How the water is estimated."""

    effects: tuple[str, ...] = DEFAULT_WATER_EFFECTS
    """Effects of the stack (any registered name), placed in scene-to-sensor order by their rank."""
    add: tuple[str, ...] = ()
    """Effects added to ``effects`` (``watergan run --add``: e.g. what the diagnosis found)."""
    light_rig: bool = True
    """When the survey declares lights (survey.json's ``lights``), model them: the stack gets ``artificial_light``
    (unless an effect with ``rig_params`` is already listed) with the declared rig (offset, tilt, beam) held."""
    held_params: tuple[str, ...] = ("artificial_light.power",)
    """Parameters ("effect.param") held at their starting values inside fitted effects. The lights' power is
    exactly degenerate with the gain (only k_c P_l is seen, even with a board): it is held (at the effect's
    initial value, or ``initial``'s), so the gain, and B_inf's level with it, are in units of that power."""
    tied_params: tuple[tuple[str, str], ...] = (("artificial_light.eta_per_m", "attenuation.eta_per_m"),)
    """(follower, leader) pairs that share one value when both effects are in the stack: the light-to-scene
    path is attenuated by the same water as the scene-to-camera path (one water, one eta)."""
    normal_smooth_px: float = 24.0
    """Gaussian sigma (pixels) by which a range map is smoothed before surface normals are taken from it
    (:func:`normals_from_range`; only effects that read normals use them). On the auv preset (SGBM range, 640x480)
    the normals' median error against the truth was 15 deg at 3 px, 7.6 at 6, 2.8 at 16, 2.3 at 24, 3.2 at 48."""
    initial: tuple[dict, ...] = ()
    """Optional {name, params} entries giving starting (or, for fixed effects, held) values."""
    fixed_effects: tuple[str, ...] = ()
    """Effects whose parameters are held at their starting values. ``gain`` is added without a board."""
    samples_per_frame: int = 300
    """Pixels lifted to 3D per frame (dense correspondences)."""
    dark_fraction: float = 0.25
    """Fraction of those samples drawn among the frame's darkest 5 % of pixels (the dark-pixel prior)."""
    blur_px: float = 1.0
    """Smallest Gaussian blur (sigma, pixels) of the images colours are read from (0: no blur)."""
    footprint_m: float = 0.015
    """Colours are read from the image blurred by this sigma on the surface (metres), i.e. fx x this / depth
    pixels (clamped to the blur pyramid, blur_px x 1.5^0..5), so every view of a point averages the same patch of
    the scene whatever its range (a fixed pixel blur averages more texture in far views, which biases the
    attenuation). 0: blur_px everywhere."""
    margin_px: int = 6
    """Projections closer than this to the image border are not used."""
    range_tolerance: float = 0.02
    """Occlusion test: |frame's range - point distance| <= this x the distance."""
    max_views: int = 12
    """Views per point at most (the nearest frames in index order are kept first)."""
    board_inset: float = 0.3
    """Board patch quads are shrunk towards their centre by this fraction before averaging."""
    board_weight: float = 10.0
    """Weight of the board term (mean over board patch views) beside the correspondence term (mean over views).
    The board's rows are the least biased constraint (known J, patch means free of texture); on the demo the
    correspondences alone leave a reproducible bias of 1-2 % in eta and 10 % in red B_inf, which weight 10 removes
    (weight 1: eta 0.454/0.138/0.202, weight 10: 0.449/0.138/0.201 against 0.45/0.14/0.20)."""
    loss_scale: float = 0.01
    """Soft-L1 scale, linear colour units."""
    iterations: int = 150
    """L-BFGS iterations of a round of the full fit: rounds (a fresh L-BFGS history each) run until one lowers the
    loss by less than ``convergence_rtol`` or ``max_iterations`` are done. One round is not always enough: with
    ``vignetting_offcentre`` added the fit crawls along the B_inf-beta valley, and after 150 iterations red B_inf
    was 0.0337 (truth 0.030) at a loss above the truth's; 450 reached 0.0301."""
    max_iterations: int = 600
    """L-BFGS iterations of a fit at most (the main fit and each alternative); the estimate says whether it
    converged before."""
    convergence_rtol: float = 1e-3
    """A fit has converged when a round lowers its loss by less than this fraction."""
    bootstrap: int = 30
    """Bootstrap replicates over frames (0: none; intervals then absent)."""
    bootstrap_iterations: int = 5
    """L-BFGS iterations of each replicate, after a Newton step from the full fit (the full fit's Hessian)."""
    bootstrap_points: bool = True
    """Resample the surface points and the board's patches too (each one's views weigh Poisson(1) times): the
    views of one point (one patch) share its errors (texture, misregistration, the patch's colour), so frames
    alone are not independent units."""
    float32: bool = True
    """Bootstrap replicates evaluate the model in float32 (parameters and loss stay float64): twice as fast, the
    same spread. The main and the alternative fits always run in float64: in float32 L-BFGS can stop early in
    the flat B_inf-beta valley (red B_inf 0.033 instead of 0.030 on the demo)."""
    spec_alternatives: tuple[dict, ...] | None = None
    """Changes of this configuration (e.g. ``{"board_weight": 1.0}``) under which the fit is repeated; each
    parameter's largest change widens its interval (in quadrature with the bootstrap). None: board weight / 10
    with a board (how much the correspondences disagree with the board), else loss scale x 3."""
    range_scale_sd: float = 0.0
    """Relative 1-sigma uncertainty of the range maps' metric scale (e.g. the SfM stage's ``scale_spread``). A
    scale error s divides every coefficient in 1/m (eta, beta) by s, which no resampling sees: their intervals
    widen by 1.96 x this x value, in quadrature."""
    min_frames: int = 4
    """Frames with a pose and range needed."""
    min_range_coverage: float = 0.2
    """Mean fraction of pixels with range needed."""
    min_points: int = 200
    """Points seen in two views whose ranges differ by >= 0.1 m needed."""
    threads: int = field(default=1, metadata={"hash": False})
    """Torch threads of the fit (not hashed: the estimate does not depend on it)."""
    seed: int = 0
    """Seed of the pixel sampling and the bootstrap."""
    board_json: str = ""
    """A colour-board file (:func:`eval.colour.load_board_json`) for the pipeline's water stage; empty: the
    simulated survey's board when there is one, else none (then the gain is held)."""
    range_agreement: float = 0.01
    """The pipeline's correction: a pixel keeps its dense range where the fused mesh agrees within this
    fraction, else takes the mesh's (the estimate itself reads the dense range)."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bars (the pipeline's correction)."""


# --------------------------------------------------------------------------------- observations


@dataclass
class Observations:
    """The measurement table (one row per view): colour, geometry, point and frame; plus the board rows.

    Rows are sorted by point, then frame. ``points_world`` (P,3) is each point's world position (the lifted
    sample, or the SfM point) and ``normals_world`` (P,3) its surface normal (None when measured without normals).
    The water stage saves the table (:meth:`save`, ``06_water/observations.npz``) and the diagnose stage ranks its
    candidates on it (:func:`eval.diagnose_measure.measure_observations`): one table for both."""

    colour: np.ndarray      # (N,3) linear
    range_m: np.ndarray     # (N,)
    depth_m: np.ndarray     # (N,)
    pixel_uv: np.ndarray    # (N,2) (x + 0.5)/W, (y + 0.5)/H
    points_cam: np.ndarray  # (N,3)
    point: np.ndarray       # (N,) point index
    frame: np.ndarray       # (N,) frame index
    n_points: int
    image_wh: tuple[int, int]
    n_frames: int = 0       # frames of the survey (the length of the frames list; sizes per-frame parameters)
    board_colour: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    board_albedo: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    board_range_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    board_depth_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    board_pixel_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    board_points_cam: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    board_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    board_patch: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (B,) patch index
    normals_cam: np.ndarray | None = None        # (N,3) unit surface normal in the view's camera frame
    board_normals_cam: np.ndarray | None = None  # (B,3)
    points_world: np.ndarray | None = None       # (P,3) world position of each point
    normals_world: np.ndarray | None = None      # (P,3) its unit surface normal, world frame

    def save(self, path) -> None:
        """An npz of every array (float64, as fitted; fields that are None left out), written atomically."""
        import io
        from dataclasses import fields

        from watergan.io import atomic_write_bytes

        arrays = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None}
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **arrays)
        atomic_write_bytes(path, buffer.getvalue())

    @classmethod
    def load(cls, path) -> Observations:
        """The table :meth:`save` wrote."""
        with np.load(path) as data:
            values = {k: data[k] for k in data.files}
        values["n_points"], values["n_frames"] = int(values["n_points"]), int(values.get("n_frames", 0))
        values["image_wh"] = tuple(int(v) for v in values["image_wh"])
        return cls(**values)


def frame_normals(frame: WaterFrame, K: np.ndarray, smooth_px: float) -> np.ndarray:
    """(H,W,3) the frame's camera-frame normals: its own (``frame.normals_cam``), else those of its range smoothed by
    ``smooth_px`` (:func:`normals_from_range`; NaN where it has no range). A new array either way."""
    if frame.normals_cam is not None:
        return np.array(frame.normals_cam, np.float64)
    return normals_from_range(frame.range_m, K, smooth_px)


def _bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Values of (H,W[,C]) at sub-pixel positions (M,2) (OpenCV centres; positions inside the image)."""
    h, w = image.shape[:2]
    x = np.clip(xy[:, 0], 0, w - 1.001)
    y = np.clip(xy[:, 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    if image.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1])
            + fy * ((1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]))


def _check_inputs(frames: list[WaterFrame], K: np.ndarray, config: WaterConfig) -> list[int]:
    usable, coverage = [], []
    for k, f in enumerate(frames):
        if f.image.ndim != 3 or f.image.shape[2] != 3:
            raise WaterInputError(f"frame {f.name}: image must be (H,W,3) linear RGB, got {f.image.shape}")
        if f.range_m.shape != f.image.shape[:2]:
            raise WaterInputError(f"frame {f.name}: range map {f.range_m.shape} and image {f.image.shape[:2]} differ")
        cover = float(np.mean(np.isfinite(f.range_m) & (f.range_m > 0)))
        if f.world_from_cam is not None and np.isfinite(f.world_from_cam).all() and cover > 0:
            usable.append(k)
            coverage.append(cover)
    if len(usable) < config.min_frames:
        raise WaterInputError(
            f"only {len(usable)} of {len(frames)} frames have both an SfM pose and a dense range map (need "
            f"{config.min_frames}): give stereo frames (right/ with baseline_m in camera.json) or more overlap "
            f"between frames so SfM registers them, and nav_altitude_m in survey.json for a monocular survey's scale")
    if float(np.mean(coverage)) < config.min_range_coverage:
        raise WaterInputError(
            f"dense range covers {100 * np.mean(coverage):.0f} % of the pixels of the registered frames (need "
            f"{100 * config.min_range_coverage:.0f} %): give stereo frames, more overlap, or textured scenes the "
            f"dense stage can match")
    return usable


def measure(frames: list[WaterFrame], K: np.ndarray, tracks: SparseTracks | None = None, board=None,
            config: WaterConfig = WaterConfig(), normals: bool = False) -> Observations:
    """The measurement table of the module docstring (dense correspondences, tracks, board); with ``normals``
    each view's surface normal in its camera frame too (for effects that read them, e.g. ``artificial_light``)."""
    import cv2

    K = np.asarray(K, np.float64)
    usable = _check_inputs(frames, K, config)
    h, w = frames[usable[0]].image.shape[:2]
    rays = rays_cam(K, h, w)
    ray_norm = np.linalg.norm(rays, axis=-1)
    rng = np.random.default_rng([config.seed, 17])
    m = config.margin_px
    inner = np.zeros((h, w), bool)
    inner[m:h - m, m:w - m] = True

    # 1. lift samples of every frame to world points (with their surface normals, world frame)
    points, point_normals = [], []
    for k in usable:
        f = frames[k]
        r = clean_range(f.range_m)
        ok = inner & np.isfinite(r)
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            continue
        n = min(config.samples_per_frame, len(idx))
        n_dark = int(round(config.dark_fraction * n))
        lum = f.image.reshape(-1, 3)[idx].sum(1)
        dark = idx[lum <= np.quantile(lum, 0.05)]
        chosen = np.concatenate([rng.choice(idx, n - n_dark, replace=False),
                                 rng.choice(dark, min(n_dark, len(dark)), replace=False)])
        yy, xx = np.unravel_index(chosen, (h, w))
        pc = rays[yy, xx] / ray_norm[yy, xx, None] * r[yy, xx, None]
        pose = np.asarray(f.world_from_cam, np.float64)
        points.append(pc @ pose[:3, :3].T + pose[:3, 3])
        point_normals.append(frame_normals(f, K, config.normal_smooth_px)[yy, xx] @ pose[:3, :3].T if normals
                             else np.zeros((len(yy), 3)))
    if not points:
        raise WaterInputError("no frame has a pixel with range inside the image margin")
    xyz = np.concatenate(points)
    normals_world = np.concatenate(point_normals)

    # 2. views of every point in every frame (occlusion test with that frame's own range)
    rows = {key: [] for key in ("colour", "range", "depth", "uv", "pc", "nc", "point", "frame")}
    sigmas = (config.blur_px * 1.5 ** np.arange(6)) if config.blur_px > 0 else np.zeros(1)
    fx = float(K[0, 0])
    cache: dict[int, list[np.ndarray]] = {}

    def pyramid(k: int) -> list[np.ndarray]:
        if k not in cache:
            img = np.asarray(frames[k].image, np.float32)
            cache.clear()
            cache[k] = [cv2.GaussianBlur(img, (0, 0), float(s)) if s > 0 else img for s in sigmas]
        return cache[k]

    def sample(k: int, xy: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Colour at xy blurred by the footprint's size in pixels (interpolated between pyramid levels)."""
        levels = pyramid(k)
        if len(levels) == 1:
            return _bilinear(levels[0], xy).astype(np.float64)
        want = config.footprint_m * fx / depth if config.footprint_m > 0 else np.full(len(xy), sigmas[0])
        pos = np.clip(np.log(np.maximum(want, 1e-6) / sigmas[0]) / np.log(1.5), 0, len(sigmas) - 1.001)
        lo = np.floor(pos).astype(int)
        t = (pos - lo)[:, None]
        out = np.zeros((len(xy), 3))
        for i in np.unique(lo):
            sel = lo == i
            out[sel] = (1 - t[sel]) * _bilinear(levels[i], xy[sel]) + t[sel] * _bilinear(levels[i + 1], xy[sel])
        return out

    def add(k: int, pid: np.ndarray, pc: np.ndarray, xy: np.ndarray, nw: np.ndarray) -> None:
        rows["colour"].append(sample(k, xy, pc[:, 2]))
        rows["nc"].append(nw @ np.asarray(frames[k].world_from_cam, np.float64)[:3, :3])
        rows["range"].append(np.linalg.norm(pc, axis=1))
        rows["depth"].append(pc[:, 2])
        rows["uv"].append(np.stack([(xy[:, 0] + 0.5) / w, (xy[:, 1] + 0.5) / h], 1))
        rows["pc"].append(pc)
        rows["point"].append(pid)
        rows["frame"].append(np.full(len(pid), k, np.int64))

    for k in usable:
        f = frames[k]
        pose = np.asarray(f.world_from_cam, np.float64)
        pc = (xyz - pose[:3, 3]) @ pose[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = K[0, 0] * pc[:, 0] / z + K[0, 2]
            y = K[1, 1] * pc[:, 1] / z + K[1, 2]
        inside = (z > 0) & (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)
        sel = np.flatnonzero(inside)
        if len(sel) == 0:
            continue
        xy = np.stack([x[sel], y[sel]], 1)
        dist = np.linalg.norm(pc[sel], axis=1)
        r_map = clean_range(f.range_m)[np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)]
        seen = np.abs(r_map - dist) <= config.range_tolerance * dist
        sel, xy = sel[seen], xy[seen]
        if len(sel):
            add(k, sel, pc[sel], xy, normals_world[sel])

    n_dense = len(xyz)
    # 3. SfM tracks: their own observations (points appended after the dense ones); normals of the sparse cloud
    # (:func:`eval.diagnose_measure.pca_normals`, turned towards the mean centre of the frames that see a point)
    if tracks is not None and len(tracks.xyz):
        from eval.diagnose_measure import pca_normals

        use = np.isin(tracks.obs_frame, usable)
        centres = np.zeros((len(tracks.xyz), 3))
        seen = np.zeros(len(tracks.xyz))
        for k in np.unique(tracks.obs_frame[use]):
            sel = tracks.obs_point[use & (tracks.obs_frame == k)]
            centres[sel] += np.asarray(frames[k].world_from_cam, np.float64)[:3, 3]
            seen[sel] += 1
        track_normals = pca_normals(np.asarray(tracks.xyz, np.float64), centres / np.maximum(seen, 1)[:, None], 12) \
            if normals else np.zeros((len(tracks.xyz), 3))
        for k in np.unique(tracks.obs_frame[use]):
            sel = np.flatnonzero(use & (tracks.obs_frame == k))
            pose = np.asarray(frames[k].world_from_cam, np.float64)
            pc = (np.asarray(tracks.xyz, np.float64)[tracks.obs_point[sel]] - pose[:3, 3]) @ pose[:3, :3]
            xy = np.asarray(tracks.obs_xy[sel], np.float64)
            ok = (pc[:, 2] > 0) & (xy[:, 0] >= m) & (xy[:, 0] <= w - 1 - m) & (xy[:, 1] >= m) & (xy[:, 1] <= h - 1 - m)
            if ok.any():
                add(int(k), n_dense + tracks.obs_point[sel][ok], pc[ok], xy[ok],
                    track_normals[tracks.obs_point[sel][ok]])
        n_total = n_dense + len(tracks.xyz)
        xyz = np.concatenate([xyz, np.asarray(tracks.xyz, np.float64)])
        normals_world = np.concatenate([normals_world, track_normals])
    else:
        n_total = n_dense
    cache.clear()

    cat = {key: np.concatenate(v) for key, v in rows.items()}
    # keep points with >= 2 views, at most max_views each; drop views with clipped colour
    good = (cat["colour"] > 0.002).all(1) & (cat["colour"] < 0.98).all(1)
    order = np.lexsort((cat["frame"], cat["point"]))
    order = order[good[order]]
    pts = cat["point"][order]
    first = np.r_[0, np.flatnonzero(np.diff(pts)) + 1]
    rank = np.arange(len(pts)) - np.repeat(first, np.diff(np.r_[first, len(pts)]))
    order = order[rank < config.max_views]
    counts = np.bincount(cat["point"][order], minlength=n_total)
    order = order[counts[cat["point"][order]] >= 2]
    remap = np.full(n_total, -1, np.int64)
    used = np.unique(cat["point"][order])
    remap[used] = np.arange(len(used))
    obs = Observations(colour=cat["colour"][order], range_m=cat["range"][order], depth_m=cat["depth"][order],
                       pixel_uv=cat["uv"][order], points_cam=cat["pc"][order],
                       normals_cam=cat["nc"][order] if normals else None,
                       point=remap[cat["point"][order]],
                       frame=cat["frame"][order], n_points=len(used), image_wh=(w, h), n_frames=len(frames),
                       points_world=xyz[used], normals_world=normals_world[used] if normals else None)
    if board is not None:
        _add_board(obs, frames, usable, board, K, rays, ray_norm, config, normals)
    _check_diversity(obs, config)
    return obs


def _add_board(obs: Observations, frames: list[WaterFrame], usable: list[int], board, K: np.ndarray,
               rays: np.ndarray, ray_norm: np.ndarray, config: WaterConfig, normals: bool = False) -> None:
    """Board rows: per frame and visible patch, the mean raw colour inside the shrunk quad, its centroid and
    the median range there (patches with range on fewer than half their pixels are skipped)."""
    import cv2

    w, h = obs.image_wh
    rows = {key: [] for key in ("colour", "albedo", "range", "depth", "uv", "pc", "nc", "frame", "patch")}
    for k in usable:
        f = frames[k]
        quads = board.quads.get(f.name)
        if quads is None:
            continue
        r = clean_range(f.range_m)
        normal_map = frame_normals(f, K, config.normal_smooth_px) if normals else None
        for p, quad in enumerate(np.asarray(quads, np.float64)):
            if not np.isfinite(quad).all():
                continue
            centre = quad.mean(0)
            shrunk = centre + (1 - config.board_inset) * (quad - centre)
            mask = np.zeros((h, w), np.uint8)
            cv2.fillConvexPoly(mask, np.rint(shrunk * 16).astype(np.int32), 1, shift=4)
            inside = mask.astype(bool)
            if inside.sum() < 9 or np.isfinite(r[inside]).mean() < 0.5:
                continue
            colour = f.image[inside].mean(0)
            if (colour >= 0.98).any():
                continue
            ys, xs = np.nonzero(inside)
            xc, yc = xs.mean(), ys.mean()
            rr = float(np.nanmedian(r[inside]))
            ray = np.array([(xc - K[0, 2]) / K[0, 0], (yc - K[1, 2]) / K[1, 1], 1.0])
            pc = ray / np.linalg.norm(ray) * rr
            if normal_map is not None:
                n = np.nanmean(normal_map[inside], 0)
                rows["nc"].append(n / max(float(np.linalg.norm(n)), 1e-12))
            rows["colour"].append(colour)
            rows["albedo"].append(board.true_linear_rgb[p])
            rows["range"].append(rr)
            rows["depth"].append(pc[2])
            rows["uv"].append([(xc + 0.5) / w, (yc + 0.5) / h])
            rows["pc"].append(pc)
            rows["frame"].append(k)
            rows["patch"].append(p)
    if rows["colour"]:
        obs.board_colour = np.array(rows["colour"], np.float64)
        obs.board_albedo = np.array(rows["albedo"], np.float64)
        obs.board_range_m = np.array(rows["range"], np.float64)
        obs.board_depth_m = np.array(rows["depth"], np.float64)
        obs.board_pixel_uv = np.array(rows["uv"], np.float64)
        obs.board_points_cam = np.array(rows["pc"], np.float64)
        obs.board_normals_cam = np.array(rows["nc"], np.float64) if normals else None
        obs.board_frame = np.array(rows["frame"], np.int64)
        obs.board_patch = np.array(rows["patch"], np.int64)


def _check_diversity(obs: Observations, config: WaterConfig) -> None:
    lo = np.full(obs.n_points, np.inf)
    hi = np.full(obs.n_points, -np.inf)
    np.minimum.at(lo, obs.point, obs.range_m)
    np.maximum.at(hi, obs.point, obs.range_m)
    n = int(((hi - lo) >= 0.1).sum())
    if n < config.min_points:
        raise WaterInputError(
            f"only {n} surface points are seen from ranges 0.1 m or more apart (need {config.min_points}): the "
            f"attenuation cannot be told from the albedo. Give more overlap between frames, frames at several "
            f"altitudes, or stereo frames so more pixels have range")


# ------------------------------------------------------------------------------------------ fit


#: The effect that models a declared light rig when the configured stack has none.
RIG_EFFECT = "artificial_light"


def rig_lights(config: WaterConfig, lights: list[dict] | None) -> list[dict]:
    """The declared lights the fit models (none when ``config.light_rig`` is off)."""
    return list(lights or []) if config.light_rig else []


def build_stack(config: WaterConfig, n_frames: int | None = None, lights: list[dict] | None = None) -> Stack:
    """The stack to fit: ``config.effects`` by rank, starting values from ``config.initial``; parameters held per
    frame (``Param(per="frame")``, e.g. a plugin's auto-exposure) get ``n_frames`` rows. With declared ``lights``
    (survey.json's, see ``WaterConfig.light_rig``) the stack models the rig: ``RIG_EFFECT`` is added unless an
    effect with ``rig_params`` is listed, each such effect takes the declared rig values
    (:func:`watergan.formation.rig.rig_settings`) and one row per light of its other per-light parameters.
    ``config.tied_params`` are then tied (:func:`tie_parameters`)."""
    lights = rig_lights(config, lights)
    given = {e["name"]: dict(e.get("params", {})) for e in config.initial}
    names = list(dict.fromkeys(list(config.effects) + list(given)))
    if lights and not any(get(n).rig_params for n in names):
        names.append(RIG_EFFECT)
    entries = [{"name": n, "params": {**given.get(n, {}), **rig_settings(get(n), lights)}} for n in names]
    stack = Stack.ordered(entries, counts=Counts(frames=n_frames, lights=len(lights) or None)).to(torch.float64)
    tie_parameters(stack, config.tied_params)
    return stack


def tie_parameters(stack: Stack, tied: tuple[tuple[str, str], ...]) -> list[str]:
    """Make each follower parameter ("effect.param") the same tensor as its leader where both effects are in the
    stack (in place; the follower takes the leader's value): fitting the leader moves both. Returns the tied
    followers. Raises ValueError when the two differ in bounds or shape (one raw value cannot serve both)."""
    done = []
    for follower, leader in tied:
        (f_name, f_param), (l_name, l_param) = follower.split(".", 1), leader.split(".", 1)
        if f_name not in stack.names or l_name not in stack.names:
            continue
        f_effect, l_effect = stack[f_name], stack[l_name]
        f_spec, l_spec = f_effect._spec(f_param), l_effect._spec(l_param)
        if (f_spec.lower, f_spec.upper) != (l_spec.lower, l_spec.upper) or \
                f_effect.raw[f_param].shape != l_effect.raw[l_param].shape:
            raise ValueError(f"cannot tie {follower} to {leader}: their bounds or shapes differ")
        f_effect.raw[f_param] = l_effect.raw[l_param]
        done.append(follower)
    return done


def held_parameters(stack: Stack, config: WaterConfig, lights: list[dict] | None) -> dict[str, str]:
    """{"effect.param": why} of the parameters held inside fitted effects: the declared rig
    (:func:`watergan.formation.rig.held_rig`), ``config.held_params`` and the tied followers."""
    held = {}
    for name, params in held_rig(stack, rig_lights(config, lights)).items():
        held.update({f"{name}.{p}": "declared in survey.json's lights (a known setting, not fitted)" for p in params})
    for key in config.held_params:
        if key.split(".", 1)[0] in stack.names:
            held.setdefault(key, "held at its starting value (see WaterConfig.held_params)")
    for follower, leader in config.tied_params:
        if follower.split(".", 1)[0] in stack.names and leader.split(".", 1)[0] in stack.names:
            held[follower] = f"tied to {leader} (one water)"
    return held


def _state(range_m, depth_m, pixel_uv, points_cam, frame, image_wh, dtype=np.float64,
           normals_cam=None) -> FormationState:
    n = len(range_m)

    def col(a):
        return torch.from_numpy(np.ascontiguousarray(np.asarray(a, dtype).reshape(n, -1, 1, 1)))

    return FormationState(direct=torch.ones(n, 3, 1, 1, dtype=col(range_m).dtype), range_m=col(range_m),
                          depth_m=col(depth_m), pixel_uv=col(pixel_uv), image_wh=tuple(image_wh),
                          points_cam=col(points_cam), normals_cam=None if normals_cam is None else col(normals_cam),
                          frame_index=torch.from_numpy(np.asarray(frame, np.int64)))


def _affine(stack: Stack, state: FormationState) -> tuple[torch.Tensor, torch.Tensor]:
    """(A, C) of y = A J + C per observation (a batch of 1x1 images), (N,3)."""
    a, c = affine_images(stack, state)
    return a[:, :, 0, 0], c[:, :, 0, 0]


def _soft_l1(e: torch.Tensor, scale: float) -> torch.Tensor:
    return 2.0 * scale * scale * (torch.sqrt(1.0 + (e / scale) ** 2) - 1.0)


class _Problem:
    """The loss of the stack's free parameters given the observations and per-frame weights."""

    def __init__(self, stack: Stack, obs: Observations, config: WaterConfig, fixed: tuple[str, ...],
                 float32: bool = False, held: dict[str, tuple[str, ...]] | None = None) -> None:
        from eval.diagnose_fit import fitted_names

        self.stack, self.obs, self.config = stack, obs, config
        dt = np.float32 if float32 else np.float64
        self.state = _state(obs.range_m, obs.depth_m, obs.pixel_uv, obs.points_cam, obs.frame, obs.image_wh, dt,
                            obs.normals_cam)
        self.y = torch.from_numpy(obs.colour.astype(dt))
        self.point = torch.from_numpy(obs.point)
        self.has_board = len(obs.board_colour) > 0
        self.point_weight: torch.Tensor | None = None  # (P,) bootstrap weights of the points (None: all 1)
        self.patch_weight: torch.Tensor | None = None  # (patches,) bootstrap weights of the board's patches
        if self.has_board:
            self.board_state = _state(obs.board_range_m, obs.board_depth_m, obs.board_pixel_uv,
                                      obs.board_points_cam, obs.board_frame, obs.image_wh, dt, obs.board_normals_cam)
            self.board_y = torch.from_numpy(obs.board_colour.astype(dt))
            self.board_j = torch.from_numpy(obs.board_albedo.astype(dt))
        self.names = fitted_names(stack, replace(config, fixed_effects=tuple(fixed)), held or {})
        by_name = dict(stack.named_parameters(remove_duplicate=False))  # a tied parameter under each name
        self.theta = [by_name[n] for n in self.names]
        for p in stack.parameters():
            p.requires_grad_(False)
        for p in self.theta:
            p.requires_grad_(True)

    def albedo(self, a: torch.Tensor, c: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        n = self.obs.n_points
        num = torch.zeros(n, 3, dtype=a.dtype).index_add(0, self.point, w[:, None] * a * (self.y - c))
        den = torch.zeros(n, 3, dtype=a.dtype).index_add(0, self.point, w[:, None] * a * a)
        return (num / den.clamp_min(1e-12)).clamp_min(0.0)

    def loss(self, frame_weight: torch.Tensor) -> torch.Tensor:
        frame_weight = frame_weight.to(self.y.dtype)
        w = frame_weight[torch.from_numpy(self.obs.frame)]
        if self.point_weight is not None:
            w = w * self.point_weight.to(w.dtype)[self.point]
        a, c = _affine(self.stack, self.state)
        j = self.albedo(a, c, w)
        e = self.y - (a * j[self.point] + c)
        total = ((w[:, None] * _soft_l1(e, self.config.loss_scale)).sum() / w.sum().clamp_min(1e-12)).double()
        if self.has_board:
            wb = frame_weight[torch.from_numpy(self.obs.board_frame)]
            if self.patch_weight is not None:
                wb = wb * self.patch_weight.to(wb.dtype)[torch.from_numpy(self.obs.board_patch)]
            ab, cb = _affine(self.stack, self.board_state)
            eb = self.board_y - (ab * self.board_j + cb)
            total = total + self.config.board_weight * ((wb[:, None] * _soft_l1(eb, self.config.loss_scale)).sum()
                                                        / wb.sum().clamp_min(1e-12)).double()
        return total

    def minimise(self, frame_weight: torch.Tensor, iterations: int) -> float:
        with torch.no_grad():
            scale = abs(float(self.loss(frame_weight))) + 1e-30
        opt = torch.optim.LBFGS(self.theta, lr=1.0, max_iter=iterations, history_size=20,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-9 * scale)

        def closure():
            opt.zero_grad(set_to_none=True)
            loss = self.loss(frame_weight)
            loss.backward()
            return loss

        opt.step(closure)
        with torch.no_grad():
            return float(self.loss(frame_weight))

    def converge(self, frame_weight: torch.Tensor, config: WaterConfig) -> tuple[int, bool]:
        """Rounds of :meth:`minimise` (see ``WaterConfig.iterations``); returns (iterations, converged)."""
        loss = self.minimise(frame_weight, config.iterations)
        done = step = config.iterations
        while done + step <= config.max_iterations:
            before, loss = loss, self.minimise(frame_weight, step)
            done += step
            if before - loss <= config.convergence_rtol * abs(before):
                return done, True
        return done, False

    def flat(self) -> torch.Tensor:
        return torch.cat([p.detach().reshape(-1) for p in self.theta])

    def set_flat(self, flat: torch.Tensor) -> None:
        with torch.no_grad():
            i = 0
            for p in self.theta:
                p.copy_(flat[i:i + p.numel()].view_as(p))
                i += p.numel()

    def gradient(self, frame_weight: torch.Tensor) -> torch.Tensor:
        for p in self.theta:
            p.grad = None
        self.loss(frame_weight).backward()
        return torch.cat([p.grad.reshape(-1) for p in self.theta]).double()

    def hessian(self, frame_weight: torch.Tensor, step: float = 1e-3) -> torch.Tensor:
        """Central differences of the gradient in the raw parameters, symmetrised."""
        x0 = self.flat()
        n = len(x0)
        hess = torch.zeros(n, n, dtype=torch.float64)
        for i in range(n):
            d = torch.zeros_like(x0)
            d[i] = step
            self.set_flat(x0 + d)
            gp = self.gradient(frame_weight)
            self.set_flat(x0 - d)
            gm = self.gradient(frame_weight)
            hess[i] = (gp - gm) / (2 * step)
        self.set_flat(x0)
        return 0.5 * (hess + hess.T)

    def get_raw(self) -> list[torch.Tensor]:
        return [p.detach().clone() for p in self.theta]

    def set_raw(self, values: list[torch.Tensor]) -> None:
        with torch.no_grad():
            for p, v in zip(self.theta, values, strict=True):
                p.copy_(v)

    def physical(self) -> dict[str, np.ndarray]:
        """{"effect.param": value} of the free parameters."""
        out = {}
        for name in self.names:
            i, pname = int(name.split(".")[1]), name.rsplit(".", 1)[1]
            effect = self.stack.effects[i]
            out[f"{effect.name}.{pname}"] = effect.param(pname).detach().numpy().copy()
        return out


def _start_inside(problem: _Problem, margin: float = 0.01) -> None:
    limit = math.log(margin) - math.log1p(-margin)
    with torch.no_grad():
        for name, raw in zip(problem.names, problem.theta, strict=True):
            spec = problem.stack.effects[int(name.split(".")[1])]._spec(name.rsplit(".", 1)[1])
            raw.clamp_(limit, -limit) if spec.bounded_above else raw.clamp_(min=limit)


#: Which measurement pins each parameter of the built-in effects (for the JSON; see the module docstring).
PINNED_BY = {
    "attenuation.eta_per_m": "same point at several ranges (dense correspondences, tracks), altitude diversity",
    "backscatter.b_inf": "offsets that no albedo explains across ranges; dark pixels; the board (absolute level)",
    "backscatter.beta_per_m": "curvature of the offset over the survey's range span (weak)",
    "vignetting.a_margin": "same point at different image positions",
    "vignetting.b": "same point at different image positions",
    "vignetting.c": "same point at different image positions",
    "vignetting_offcentre.centre_uv": "same point at different image positions",
    "vignetting_offcentre.a_margin": "same point at different image positions; overall scale degenerate with strength",
    "vignetting_offcentre.b": "same point at different image positions; overall scale degenerate with strength",
    "vignetting_offcentre.c": "same point at different image positions; overall scale degenerate with strength",
    "vignetting_offcentre.strength": "ratios between channels only (s x polynomial: the scale is degenerate)",
    "gain.k": "the board's known colours (without a board: degenerate with the albedo scale, held fixed)",
    "artificial_light.offset_m": "declared in survey.json's lights (held)",
    "artificial_light.tilt_deg": "declared in survey.json's lights (held)",
    "artificial_light.beam_deg": "declared in survey.json's lights (held)",
    "artificial_light.power": "ratios between lights: brightness across the beams; level: degenerate with the gain "
                              "(held)",
    "artificial_light.eta_per_m": "tied to attenuation.eta_per_m (one water)",
    "artificial_light.ambient": "brightness that does not fall with the distance from the lights (other light)",
}


@dataclass
class WaterEstimate:
    """The fitted stack and every parameter's estimate with its 95 % interval.

    stack:        the fitted stack (use :meth:`Stack.to_config` to save it).
    params:       {"effect.param": {"value", "low", "high", "std", "p2_5", "p97_5", "units", "fitted",
                  "pinned_by"}}; fixed parameters have value only.
    fixed:        effects held at their values (e.g. gain without a board) and why.
    held:         {"effect.param": why} parameters held (a declared light rig, the lights' power) or tied to
                  another (the light path's eta to the attenuation's) inside fitted effects.
    tradeoffs:    [(a, b, correlation)] free parameter components whose bootstrap |correlation| > 0.95.
    n_points, n_observations, n_board, n_frames: sizes of the measurement table.
    rmse:         RMS residual of the views (linear colour); ``residuals``: per view (for plots).
    seconds:      wall time (measuring, fitting, bootstrap).
    """

    stack: Stack
    params: dict
    fixed: dict
    held: dict
    tradeoffs: list
    n_points: int
    n_observations: int
    n_board: int
    n_frames: int
    rmse: float
    seconds: dict
    alternatives: list = field(default_factory=list)
    iterations: int = 0
    """L-BFGS iterations of the main fit."""
    converged: bool = True
    """Whether the main fit converged (see ``WaterConfig.convergence_rtol``) within ``max_iterations``."""
    residuals: dict | None = None
    """Per view: residual (N,3) (observed - fitted, linear), range_m (N,), radius (N,) (distance from the
    image centre, 1 at the corners); not in :meth:`to_json`."""
    observations: Observations | None = None
    """The measurement table the estimate was fitted to (:func:`estimate_water` sets it; not in :meth:`to_json`:
    the water stage saves it beside water.json for the diagnosis)."""

    def to_json(self) -> dict:
        return {"stack": self.stack.to_config(), "params": self.params, "fixed": self.fixed, "held": self.held,
                "tradeoffs": self.tradeoffs, "n_points": self.n_points, "n_observations": self.n_observations,
                "n_board": self.n_board, "n_frames": self.n_frames, "rmse": self.rmse, "seconds": self.seconds,
                "iterations": self.iterations, "converged": self.converged,
                "interval": "95 %: estimate +- sqrt((1.96 x bootstrap std)^2 + specification^2 [+ (1.96 x "
                            "range scale sd x value)^2 for 1/m]); bootstrap over frames and points; specification: "
                            "largest change of the estimate under the alternative weightings "
                            + json.dumps(self.alternatives)}

    def summary(self) -> str:
        """One line: eta and B_inf with their intervals."""
        parts = []
        for key in ("attenuation.eta_per_m", "backscatter.b_inf"):
            if key in self.params and self.params[key].get("low") is not None:
                p = self.params[key]
                parts.append(f"{key.split('.')[1]} " + "/".join(
                    f"{v:.3f}[{lo:.3f},{hi:.3f}]" for v, lo, hi in zip(p["value"], p["low"], p["high"], strict=True)))
        unconverged = "" if self.converged else f", not converged in {self.iterations} iterations"
        return "water: " + "; ".join(parts) + f" (rmse {self.rmse:.4f}, {self.n_points} points{unconverged})"


def fit_observations(obs: Observations, config: WaterConfig = WaterConfig(),
                     lights: list[dict] | None = None) -> WaterEstimate:
    """Fit the stack to a measurement table and bootstrap over frames (see the module docstring). ``lights``:
    the light rig survey.json declares (see :func:`build_stack`)."""
    t0 = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(max(1, config.threads))
    try:
        frames = np.unique(np.concatenate([obs.frame, obs.board_frame]))
        n_frames_total = int(frames.max()) + 1
        stack = build_stack(config, obs.n_frames or n_frames_total, lights)
        fixed = {name: "held at its configured value" for name in config.fixed_effects}
        if len(obs.board_colour) == 0 and "gain" in stack.names:
            fixed["gain"] = "no board: degenerate with the albedo scale (and B_inf's level), held at its value"
        held = held_parameters(stack, config, lights)
        by_effect: dict[str, tuple[str, ...]] = {}
        for key in held:
            name, param = key.split(".", 1)
            by_effect[name] = (*by_effect.get(name, ()), param)
        problem = _Problem(stack, obs, config, tuple(fixed), held=by_effect)
        _start_inside(problem)
        fast = _Problem(stack, obs, config, tuple(fixed), float32=True, held=by_effect) if config.float32 \
            else problem
        ones = torch.zeros(n_frames_total, dtype=torch.float64)
        ones[torch.from_numpy(frames)] = 1.0
        iterations, converged = problem.converge(ones, config)
        best_raw = problem.get_raw()
        best = problem.physical()
        t_fit = time.perf_counter() - t0

        samples = []
        rng = np.random.default_rng([config.seed, 29])
        board_frames = np.unique(obs.board_frame)
        other = np.setdiff1d(frames, board_frames)
        n_patches = int(obs.board_patch.max()) + 1 if problem.has_board else 0
        if config.bootstrap:
            x0 = fast.flat()
            evals, evecs = torch.linalg.eigh(fast.hessian(ones))
            inv = (evecs / evals.clamp_min(evals.abs().max() * 1e-6 + 1e-300)) @ evecs.T
        for _ in range(config.bootstrap):
            wts = np.zeros(n_frames_total)
            for group in (board_frames, other):
                if len(group):
                    np.add.at(wts, rng.choice(group, len(group), replace=True), 1.0)
            weight = torch.from_numpy(wts)
            if config.bootstrap_points:
                fast.point_weight = torch.from_numpy(rng.poisson(1.0, obs.n_points).astype(np.float64))
                if n_patches:
                    fast.patch_weight = torch.from_numpy(rng.poisson(1.0, n_patches).astype(np.float64))
            fast.set_flat(x0)
            step = -(inv @ fast.gradient(weight))  # a Newton step from the full fit, halved until it helps
            with torch.no_grad():
                before = float(fast.loss(weight))
                for _ in range(6):
                    fast.set_flat(x0 + step)
                    if float(fast.loss(weight)) < before:
                        break
                    step = step / 2
                else:
                    fast.set_flat(x0)
            if config.bootstrap_iterations:
                fast.minimise(weight, config.bootstrap_iterations)
            samples.append(fast.physical())
        problem.set_raw(best_raw)
        fast.point_weight = fast.patch_weight = None
        t_boot = time.perf_counter() - t0 - t_fit
        alternatives = config.spec_alternatives
        if alternatives is None:
            alternatives = ({"board_weight": config.board_weight / 10},) if problem.has_board else \
                ({"loss_scale": config.loss_scale * 3},)
        spec = {}
        for change in alternatives:
            problem.config = replace(config, **change)
            problem.set_raw(best_raw)
            problem.converge(ones, problem.config)
            for key, value in problem.physical().items():
                spec[key] = np.maximum(spec.get(key, 0.0), np.abs(value - best[key]))
        problem.config = config
        problem.set_raw(best_raw)
        with torch.no_grad():
            a, c = _affine(stack, problem.state)
            j = problem.albedo(a, c, ones.to(a.dtype)[torch.from_numpy(obs.frame)])
            residual = (problem.y - (a * j[problem.point] + c)).numpy()
            rmse = float(np.sqrt((residual ** 2).mean()))
        for p in stack.parameters():
            p.requires_grad_(False)
        params, tradeoffs = _describe(stack, best, samples, fixed, spec, config.range_scale_sd)
        return WaterEstimate(stack=stack, params=params, fixed=fixed, held=held, tradeoffs=tradeoffs,
                             n_points=obs.n_points,
                             n_observations=len(obs.colour), n_board=len(obs.board_colour), n_frames=len(frames),
                             residuals={"residual": residual, "range_m": obs.range_m,
                                        "radius": np.hypot(*(2 * obs.pixel_uv - 1).T) / np.sqrt(2)},
                             rmse=rmse, seconds={"fit": round(t_fit, 2), "bootstrap": round(t_boot, 2),
                                                 "specification": round(time.perf_counter() - t0 - t_fit - t_boot, 2)},
                             alternatives=[dict(a) for a in alternatives], iterations=iterations,
                             converged=converged)
    finally:
        torch.set_num_threads(threads)


def _describe(stack: Stack, best: dict, samples: list[dict], fixed: dict, spec: dict,
              range_scale_sd: float) -> tuple[dict, list]:
    params = {}
    for effect in stack.effects:
        for p in effect.params:
            key = f"{effect.name}.{p.name}"
            value = effect.param(p.name).detach().numpy()
            entry = {"value": np.round(value, 6).tolist(), "units": p.units, "fitted": key in best,
                     "pinned_by": PINNED_BY.get(key, "")}
            if key in best and samples:
                stack_s = np.stack([s[key] for s in samples])
                std = stack_s.std(0, ddof=1) if len(samples) > 1 else np.zeros_like(value)
                shift = spec.get(key, np.zeros_like(value))
                scale = range_scale_sd * np.abs(value) if p.units == "1/m" else np.zeros_like(value)
                half = np.sqrt((1.96 * std) ** 2 + shift ** 2 + (1.96 * scale) ** 2)
                entry.update(std=np.round(std, 6).tolist(), specification=np.round(shift, 6).tolist(),
                             low=np.round(np.clip(value - half, p.lower, p.upper), 6).tolist(),
                             high=np.round(np.clip(value + half, p.lower, p.upper), 6).tolist(),
                             p2_5=np.round(np.percentile(stack_s, 2.5, 0), 6).tolist(),
                             p97_5=np.round(np.percentile(stack_s, 97.5, 0), 6).tolist())
            params[key] = entry
    tradeoffs = []
    if len(samples) > 2:
        keys = sorted(best)
        cols, labels = [], []
        for key in keys:
            flat = np.stack([np.atleast_1d(s[key]).ravel() for s in samples])
            for i in range(flat.shape[1]):
                cols.append(flat[:, i])
                labels.append(f"{key}[{i}]" if flat.shape[1] > 1 else key)
        mat = np.stack(cols, 1)
        sd = mat.std(0)
        ok = sd > 1e-12
        if ok.sum() > 1:
            corr = np.corrcoef(mat[:, ok].T)
            lab = [lab for lab, keep in zip(labels, ok, strict=True) if keep]
            for i in range(len(lab)):
                for j in range(i + 1, len(lab)):
                    if abs(corr[i, j]) > 0.95:
                        tradeoffs.append([lab[i], lab[j], round(float(corr[i, j]), 3)])
    return params, tradeoffs


def estimate_water(frames: list[WaterFrame], K: np.ndarray, tracks: SparseTracks | None = None, board=None,
                   config: WaterConfig = WaterConfig(), lights: list[dict] | None = None,
                   normals: bool = False) -> WaterEstimate:
    """The site's water (see the module docstring).

    frames:  the survey's frames (raw linear image, range map in metres, pose; see :class:`WaterFrame`).
    K:       (3,3) pinhole intrinsics of the images, pixels (OpenCV centres).
    tracks:  optional SfM tracks (:class:`SparseTracks`, frame indices into ``frames``).
    board:   optional :class:`eval.colour.Board` (true linear colours; pixel quads per frame name): pins the gain.
    lights:  the light rig survey.json declares (``lights``: per light offset_m, tilt_deg, beam_deg): modelled by
             ``artificial_light`` with the rig held (:func:`build_stack`, ``WaterConfig.light_rig``).
    normals: measure each view's surface normal even when the stack reads none (the water stage does, so that
             the diagnosis's candidates that read normals can be fitted to the same table; the fit is unchanged).
    The measurement table is kept in ``estimate.observations``.
    Raises :class:`WaterInputError` when the frames cannot pin the water (too few registered frames, too
    little range, too few points seen at different ranges)."""
    t0 = time.perf_counter()
    obs = measure(frames, K, tracks, board, config,
                  normals=normals or needs_normals(build_stack(config, len(frames), lights)))
    t_measure = time.perf_counter() - t0
    estimate = fit_observations(obs, config, lights)
    estimate.observations = obs
    estimate.seconds = {"measure": round(t_measure, 2), **estimate.seconds,
                        "total": round(time.perf_counter() - t0, 2)}
    return estimate


# ----------------------------------------------------------------------------------- correction


def correct_physics(image: np.ndarray, range_m: np.ndarray, stack: Stack | list[dict],
                    K: np.ndarray | None = None, frame_index: int = 0, normals_cam: np.ndarray | None = None,
                    normal_smooth_px: float = 24.0) -> tuple[np.ndarray, np.ndarray]:
    """Invert a stack that is affine in the in-air colour, pixel by pixel with each pixel's range:
    J = (I - C) / A, A = render(J = 1) - render(J = 0), C = render(J = 0); for the default stack
    J = (I / k * V - B_inf (1 - exp(-beta r))) * exp(eta r).

    image:   (H,W,3) raw linear RGB.
    range_m: (H,W) metres along the ray; NaN or <= 0 = no range.
    stack:   a :class:`Stack` or its configuration (e.g. ``WaterEstimate.stack``).
    K:       (3,3) intrinsics; gives effects the camera-frame points, depth and surface normals (needed by e.g.
             ``artificial_light``: J = (I - C) / A with A = k/V exp(-eta r) E(X, n), E the lights' irradiance);
             without it depth = range and no points.
    normals_cam: (H,W,3) unit normals in the camera frame (e.g. of a fused mesh); None with K:
             :func:`normals_from_range` of ``range_m`` smoothed by ``normal_smooth_px``.
    frame_index: the frame's index in the survey (the estimate's frames list): the row that parameters held
             per frame take.
    Returns (J (H,W,3) float32 linear, unclipped, NaN where there is no range; valid (H,W) bool). Pixels
    without range are marked, never guessed: fill their range first (e.g. from a fused mesh) to correct them."""
    a, c, valid = inverse_fields(range_m, stack, K, frame_index, normals_cam, normal_smooth_px)
    a, c = a[0].permute(1, 2, 0).numpy(), c[0].permute(1, 2, 0).numpy()
    image = np.asarray(image, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = (image - c) / a
    out[~valid] = np.nan
    return out.astype(np.float32), valid
