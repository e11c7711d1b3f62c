"""Structure from motion with pycolmap: once, on the raw images; every later measurement reuses it.

Steps: SIFT features -> matching (sequential with quadratic overlap for image sequences, which
also links neighbouring survey lines, or exhaustive for small sets) -> incremental or global mapping
(known PINHOLE intrinsics from ``camera.json`` held fixed, or estimated) -> the largest model is
moved into a *survey frame* and given a metric scale:

    survey frame:  origin at the median sparse point, z = normal of the plane fitted to the sparse
                   points (oriented towards the cameras), x = main direction of camera travel;
    p_survey = s R (p_colmap - o)

with the scale ``s`` from, in order of preference (``scale="auto"``; board only when a board file is given; the
survey frame and every source: :mod:`pipeline.scale`):

    stereo:    a rectified stereo rig (``right/`` frames, ``baseline_m`` in camera.json). Sparse
               observations are matched along their row in the right frame (normalised cross
               correlation, sub-pixel peak); z_stereo = fx b / disparity; s = median(z_stereo / z_sfm).
    board:     a board of known size (``board_json``: per image, pixel corners of the board's four outer
               corners, or of each patch of a colour board in eval.colour's board-file format, with the
               true size ``width_m``/``height_m`` or ``patch_side_m``). Each corner seen in >= 2 registered
               views is triangulated with the SfM poses (linear DLT); every edge with both ends
               triangulated gives a sample true / measured length; s = median of the samples.
    altitude:  navigation altitudes (``nav_altitude_m`` in survey.json):
               s = median(altitude_nav) / median(n . (C_i - o)), camera heights above the sparse points'
               median height.
    track:     a position track (``nav_position_m`` in survey.json, from navigation.csv's x_m, y_m[, z_m]): a robust
               similarity between the camera centres and the positions (:mod:`pipeline.scale`).
    height:    a camera at a known height over a floor (``camera_height_m`` in survey.json): s = that height over
               the cameras' median distance to the floor plane of the sparse points (:mod:`pipeline.scale`).
    none:      no metric scale: the unit is the sparse observations' median depth (s = 1 / that depth), so
               depths are of order 1 whatever COLMAP's arbitrary scale; every stage says "unscaled".

Outputs (``01_sfm/``): ``sparse/`` (COLMAP binary model in the survey frame), ``tracks.npz``
(:class:`Tracks`: points, observations, poses, intrinsics) and ``database.db``.

Pixel convention everywhere outside COLMAP: OpenCV, the centre of pixel (column i, row j) is at
(i, j). COLMAP puts it at (i + 0.5, j + 0.5); the conversion happens once, in :mod:`pipeline.colmap`.
"""

from __future__ import annotations

import shutil
import sys
import time
import zlib  # noqa: F401  must load before pycolmap: pycolmap first makes Python's zlib corrupt the heap
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from eval.tracks import Tracks
from watergan.data import read_nav_altitudes
from watergan.errors import UserInputError
from watergan.lens import OPENCV, Lens
from watergan.progress import say
from watergan.survey_files import image_files, read_camera_json, read_survey_json

from .colmap import (
    build_tracks,
    camera_matrix,
    colmap_errors_only,
    extract_in_order,
    refined_k1,
    seeded_verification,
)
from .overlay import overlay_warning, still_features
from .scale import (
    altitude_scale,
    board_scale,
    height_scale,
    read_board_corners,
    stereo_scale,
    survey_frame,
    track_scale,
)


class Matching(StrEnum):
    """Feature matching of SfM."""

    auto = "auto"
    sequential = "sequential"
    exhaustive = "exhaustive"


class Mapper(StrEnum):
    """How SfM recovers the poses from the matches."""

    incremental = "incremental"
    hierarchical = "hierarchical"
    global_ = "global"


class ScaleSource(StrEnum):
    """Where SfM's metric scale comes from."""

    auto = "auto"
    stereo = "stereo"
    board = "board"
    altitude = "altitude"
    track = "track"
    height = "height"
    none = "none"


@dataclass(frozen=True)
class SfmConfig:
    """Structure-from-motion options."""

    images_dir: str = ""
    """Folder of the raw images; empty: the workspace's survey images."""
    camera_json: str = ""
    """Intrinsics (fx, fy, cx, cy in OpenCV pixel convention, width, height[, baseline_m]); empty:
    camera.json beside the images folder. Missing file: intrinsics are estimated."""
    fix_intrinsics: bool = True
    """Hold the known PINHOLE intrinsics fixed (True) or refine them in bundle adjustment."""
    matching: Matching = Matching.auto
    """'sequential' (ordered sequence, quadratic overlap), 'exhaustive' (all pairs), or 'auto':
    exhaustive up to the exhaustive-max-images option's count of images, else sequential."""
    sequential_overlap: int = 10
    """Sequential matching with quadratic overlap: each image is matched with the images 1, 2, 4, ...,
    2^(overlap - 1) ahead, which reaches neighbouring survey lines (so an image has log2(images) pairs at most)."""
    exhaustive_max_images: int = 40
    """'auto' matching uses exhaustive matching up to this many images."""
    mapper: Mapper = Mapper.incremental
    """'incremental' (COLMAP's: images registered one at a time, bundle adjustment as the model grows),
    'hierarchical' (overlapping clusters of at most 500 images mapped incrementally side by side, then merged) or
    'global' (GLOMAP's, in pycolmap: rotation averaging and global positioning of every image at once, then one
    bundle adjustment)."""
    max_features: int = 4096
    """SIFT features per image at most."""
    init_min_tri_angle_deg: float = 8.0
    """Smallest triangulation angle of the initial pair, degrees (COLMAP's default 16 suits
    wide baselines; seafloor surveys at 80 % overlap have about 10 degrees between neighbours)."""
    min_pose_inliers: int = 15
    """A frame is registered when its pose has at least this many inlier 2D-3D matches (COLMAP: 30) and a tenth of its
    matches are inliers (COLMAP: a quarter): a survey's last frame after a gap in the recording still joins."""
    min_registered_fraction: float = 0.5
    """Fewer registered images than this fraction of all images is an error."""
    scale: ScaleSource = ScaleSource.auto
    """Metric scale from 'stereo', 'board' (known board size), 'altitude' (navigation), 'track' (positions per frame),
    'height' (camera_height_m), 'none', or 'auto' (the first of these the survey has, in that order)."""
    board_json: str = ""
    """Board file for the 'board' scale: JSON {"images": {file name: [[x, y] x 4] outer corners, or per patch
    [[x, y] x 4] | null}, "width_m", "height_m" | "patch_side_m", ...} (pixels, OpenCV convention; the
    evaluation's colour-board files qualify once they carry the size). Empty: no board."""
    board_width_m: float = 0.0
    """True board (or patch) extent along corners 0-1 and 2-3, metres; 0: from the board file."""
    board_height_m: float = 0.0
    """True extent along corners 1-2 and 3-0, metres; 0: from the board file (or the width's option)."""
    right_dir: str = ""
    """Folder of the stereo rig's right frames (same names); empty: right/ beside the images folder."""
    survey_json: str = ""
    """Navigation file with nav_altitude_m per frame; empty: survey.json beside the images folder."""
    seed: int = 0
    """Random seed of COLMAP's RANSAC and mapper."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Print a one-line summary when SfM ends (COLMAP's own log is kept to its errors either way)."""


@dataclass
class SfmResult:
    model_dir: str
    """COLMAP binary model (cameras.bin, images.bin, points3D.bin) in the survey frame."""
    tracks: str
    """tracks.npz: see :class:`Tracks`."""
    n_images: int
    """Images in the input folder."""
    n_registered: int
    """Images with a pose."""
    n_points: int
    """Sparse 3D points."""
    mean_track_length: float
    """Mean number of observations per point."""
    mean_reprojection_error_px: float
    """Mean reprojection error of the sparse points, pixels."""
    matching: str
    """The matching that was used."""
    scale_method: str
    """'stereo', 'board', 'altitude', 'track', 'height' or 'none': where the metric scale came from."""
    scale_factor: float
    """s in p_survey = s R (p_colmap - o)."""
    scale_spread: float
    """Median absolute deviation / median of the per-sample scale estimates (0 for 'none')."""
    seconds: float
    """Wall time of the stage."""
    phase_seconds: dict[str, float] = field(default_factory=dict)
    """Wall time of each step: "features", "matching", "mapping", "survey_frame" (scale and tracks) and "writing"."""
    scale_detail: dict = field(default_factory=dict)
    """The track scale's residual (m), frames used and kept, and its halves (:func:`pipeline.scale.track_halves`);
    the camera height's halves (:func:`pipeline.scale.height_halves`); empty for the other sources."""
    still_features: dict = field(default_factory=dict)
    """Features that stay still while the scene moves, without a scene mask (:func:`pipeline.overlay.still_features`:
    the box to mask, the matches, the moving pairs); empty: none."""
    lens_source: str = ""
    """What removed a lens from the frames before SfM: "" (nothing), "camera.json", "estimated" (the survey stage's
    estimate with the focal length held) or "self-calibrated"."""
    scene_mask: str = ""
    """The survey's scene mask (workspace-relative; features only where it is the scene); empty: none."""
    lens_k1: float | None = None
    """How distorted the frames look: k1 of a one-coefficient radial camera (COLMAP's SIMPLE_RADIAL, OpenCV's k1)
    that bundle adjustment fits on the model with the known intrinsics held (:func:`refined_k1`); near 0 for
    pinhole or undistorted frames. None: the intrinsics were estimated (their model has its own k)."""

    @property
    def looks_distorted(self) -> bool:
        """SfM's refined k1 exceeds ``DISTORTED_K1``: camera.json lacks the lens's distortion."""
        return self.lens_k1 is not None and abs(self.lens_k1) > DISTORTED_K1

    def summary(self) -> str:
        """One line: registration, points, track length, reprojection error, matching, scale, time, and a warning
        when the frames look distorted."""
        scale = ("unscaled (unit: the median sparse depth)" if self.scale_method == "none" else
                 f"scale from {self.scale_method} (x{self.scale_factor:.4g}, spread {100 * self.scale_spread:.1f} %"
                 + (f", residual {self.scale_detail['residual_m']:.3f} m" if "residual_m" in self.scale_detail
                    else "") + ")")
        line = (f"sfm: registered {self.n_registered} of {self.n_images} images, {self.n_points} points "
                f"(mean track {self.mean_track_length:.1f}, reprojection {self.mean_reprojection_error_px:.2f} px), "
                f"{self.matching} matching, {scale}, {self.seconds:.1f} s")
        return "\n".join([line, *self.warnings()])

    def warnings(self) -> list[str]:
        """What to do: the frames look distorted; features stay still (an overlay to mask)."""
        return ([distortion_warning(self.lens_k1, self.lens_source)] if self.looks_distorted else []) + \
            ([overlay_warning(self.still_features)] if self.still_features else [])


#: |k1| above which the frames look distorted to SfM (a moderate wide lens behind a flat port: -0.1 to -0.3).
DISTORTED_K1 = 0.02


def distortion_warning(k1: float, lens_source: str = "") -> str:
    """What to do when SfM's refined k1 says the frames are distorted, by what already removed a lens
    (``lens_source``: :attr:`SfmResult.lens_source`): never the step that already ran."""
    fix = {"": "give the lens in camera.json (OpenCV's k1, k2, p1, p2, k3, a fisheye's k1..k4, or COLMAP's model and "
                "params), or leave the intrinsics out of camera.json (or set \"calibrated\": false) so that SfM "
                "calibrates focal length and lens together on the survey",
           "camera.json": "the lens in camera.json does not undo it: check its coefficients, or set \"calibrated\": "
                          "false in camera.json so that SfM calibrates focal length and lens together on the survey",
           "estimated": "the lens estimated with the focal length held does not undo it: set \"calibrated\": false "
                        "in camera.json so that SfM calibrates focal length and lens together on the survey",
           "self-calibrated": "the survey's own calibration does not undo it: give a calibration made on a target "
                              "(fx, fy, cx, cy and the lens, with \"calibrated\": true)"}[lens_source]
    return (f"sfm: the frames look distorted (SfM's refined k1 = {k1:+.3f}, where an undistorted camera gives "
            f"about 0): {fix}; until then the water and the corrections carry the distortion's error on image "
            f"position")


#: Consecutive frames from the middle of the survey SfM estimates a lens on (:func:`estimate_lens`).
LENS_FRAMES = 30


def estimate_lens(images_dir: Path, names: list[str], camera: dict, start: Lens | None, work_dir: Path,
                  seed: int = 0) -> tuple[Lens, dict]:
    """The lens of distorted frames, refined by SfM: up to ``LENS_FRAMES`` consecutive frames from the middle of
    ``names``, matched sequentially and mapped incrementally with one camera of ``start``'s model and coefficients
    (OpenCV's k1, k2, p1, p2 from 0 when None; :meth:`watergan.lens.Lens.to_colmap`), its fx, fy, cx, cy held from
    ``camera`` and its coefficients refined by every bundle adjustment. The poses and the seafloor's relief seen
    from several positions pin the coefficients; the focal length, which trades with them, stays as given.
    Works in ``work_dir`` (removed after). Returns the lens and a summary (frames, registered, reprojection error
    in pixels, seconds, the start)."""
    import pycolmap

    started = time.perf_counter()
    lens = start if start is not None else Lens(OPENCV, ())
    first = max(0, len(names) // 2 - LENS_FRAMES // 2)
    subset = names[first:first + LENS_FRAMES]
    cfg = SfmConfig(matching=Matching.sequential, seed=seed, progress=False)
    shutil.rmtree(work_dir, ignore_errors=True)
    (work_dir / "raw").mkdir(parents=True)
    try:
        with colmap_errors_only():
            _extract_features(work_dir / "lens.db", images_dir, subset, camera, cfg, lens)
            _match_features(work_dir / "lens.db", subset, cfg)
            options = _incremental_options(camera, cfg)
            options.ba_refine_extra_params = options.mapper.abs_pose_refine_extra_params = True
            options.num_threads = 1  # the same lens run to run (pipeline.calibrate's module docstring)
            models = pycolmap.incremental_mapping(work_dir / "lens.db", images_dir, work_dir / "raw", options)
            rec, n_reg = _largest_model(models, subset, cfg)
    except UserInputError as exc:
        raise UserInputError(f"estimating the lens: {exc}; or give the lens in camera.json") from None
    finally:
        shutil.rmtree(work_dir, ignore_errors=True)
    refined = Lens(lens.model, tuple(float(c) for c in rec.cameras[next(iter(rec.cameras))].params[4:]))
    summary = {"frames": len(subset), "registered": n_reg,
               "reprojection_px": round(float(rec.compute_mean_reprojection_error()), 4),
               "seconds": round(time.perf_counter() - started, 1), "start": start.to_json() if start else None}
    return refined, summary


def check_board(cfg: SfmConfig) -> None:
    """The sfm stage's input check: the board file it names, when it names one (:func:`read_board_corners`)."""
    if cfg.board_json:
        read_board_corners(Path(cfg.board_json), cfg.board_width_m, cfg.board_height_m)


def run_sfm_folder(images_dir: str | Path, out_dir: str | Path, cfg: SfmConfig,
                   scene_mask: Path | None = None) -> SfmResult:
    """SfM on a folder of images; outputs in ``out_dir`` (see the module docstring): features (only where
    ``scene_mask``, a PNG nonzero on the scene, allows), matches, incremental mapping, the survey frame and scale,
    then the model and tracks written."""
    start = time.perf_counter()
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    names, cam = _sfm_inputs(images_dir, cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    database = out_dir / "database.db"
    phases, mark = {}, time.perf_counter()

    def lap(phase: str) -> None:
        nonlocal mark
        now = time.perf_counter()
        phases[phase], mark = round(now - mark, 2), now

    with colmap_errors_only():
        say(f"extracting the features of {len(names)} frames")
        _extract_features(database, images_dir, names, cam, cfg, mask_png=scene_mask)
        lap("features")
        say("matching the features")
        matching = _match_features(database, names, cfg)
        lap("matching")
        say(f"mapping ({Mapper(cfg.mapper).value}): registering the frames, bundle adjustment")
        raw_dir = out_dir / "colmap_raw"
        mapping = {Mapper.incremental: _map_incrementally, Mapper.hierarchical: _map_hierarchically,
                   Mapper.global_: _map_globally}[Mapper(cfg.mapper)]
        rec, n_reg = mapping(database, images_dir, raw_dir, names, cam, cfg)
        lens_k1 = refined_k1(rec) if cam is not None else None
        camera = rec.cameras[next(iter(rec.cameras))]
        still = still_features(database, camera.width, camera.height, images_dir) if scene_mask is None else None
        lap("mapping")
    say("the survey frame and its scale")
    tracks, method, scale, spread, detail = _to_survey_frame(rec, names, images_dir, cam, cfg)
    lap("survey_frame")
    model_dir = _write_sfm(rec, tracks, out_dir, raw_dir)
    lap("writing")
    result = SfmResult(model_dir=str(model_dir), tracks=str(out_dir / "tracks.npz"), n_images=len(names),
                       n_registered=n_reg, n_points=len(tracks.xyz),
                       mean_track_length=float(rec.compute_mean_track_length()),
                       mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
                       matching=matching, scale_method=method, scale_factor=scale, scale_spread=spread,
                       seconds=time.perf_counter() - start, phase_seconds=phases, lens_k1=lens_k1,
                       scale_detail=detail, lens_source=_lens_source(cam), still_features=still or {})
    if cfg.progress:
        print(result.summary(), file=sys.stderr, flush=True)
    else:
        for warning in result.warnings():
            print(warning, file=sys.stderr, flush=True)
    return result


def _sfm_inputs(images_dir: Path, cfg: SfmConfig) -> tuple[list[str], dict | None]:
    """The folder's image names (at least 3) and the camera (``cfg.camera_json``, else ``camera.json`` beside
    the folder; None: none)."""
    names = image_files(images_dir)
    cam = read_camera_json(Path(cfg.camera_json) if cfg.camera_json else images_dir.parent / "camera.json")
    if len(names) < 3:
        raise UserInputError(f"{images_dir} holds {len(names)} images; SfM needs at least 3 overlapping images")
    return names, cam


def _lens_source(cam: dict | None) -> str:
    """What removed a lens from the frames SfM sees (:attr:`SfmResult.lens_source`), by the workspace's camera.json."""
    if not cam or "undistorted" not in cam:
        return ""
    if "self_calibration" in cam:
        return "self-calibrated"
    return "estimated" if cam.get("lens_estimated") else "camera.json"


def _extract_features(database: Path, images_dir: Path, names: list[str], cam: dict | None, cfg: SfmConfig,
                      lens: Lens | None = None, mask_png: Path | None = None) -> None:
    """SIFT features (at most ``max_features`` per image, seeded; none where ``mask_png`` is 0) into a new
    ``database``: one camera from ``cam`` (COLMAP's pixel-centre convention), PINHOLE or ``lens``'s model
    (:meth:`watergan.lens.Lens.to_colmap`), else one SIMPLE_RADIAL camera to estimate."""
    import pycolmap

    database.unlink(missing_ok=True)
    if cam is not None:
        model, params = lens.to_colmap(cam) if lens is not None else \
            ("PINHOLE", [cam["fx"], cam["fy"], cam["cx"] + 0.5, cam["cy"] + 0.5])
        reader = pycolmap.ImageReaderOptions(camera_model=model, camera_params=",".join(str(float(v)) for v in params))
    else:
        reader = pycolmap.ImageReaderOptions(camera_model="SIMPLE_RADIAL")
    if mask_png is not None:
        reader.camera_mask_path = str(mask_png)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = cfg.max_features
    pycolmap.set_random_seed(cfg.seed)
    extract_in_order(database, images_dir, names, reader, extraction)


def _match_features(database: Path, names: list[str], cfg: SfmConfig) -> str:
    """Match the database's features, exhaustively or sequentially (``cfg.matching``; "auto": exhaustive up
    to ``exhaustive_max_images``); returns the matching used."""
    import pycolmap

    matching = cfg.matching
    if matching == "auto":
        matching = "exhaustive" if len(names) <= cfg.exhaustive_max_images else "sequential"
    if matching == "exhaustive":
        pycolmap.match_exhaustive(database, verification_options=seeded_verification(cfg.seed),
                                  device=pycolmap.Device.cpu)
    elif matching == "sequential":
        pairing = pycolmap.SequentialPairingOptions(overlap=cfg.sequential_overlap, quadratic_overlap=True)
        pycolmap.match_sequential(database, pairing_options=pairing, verification_options=seeded_verification(cfg.seed),
                                  device=pycolmap.Device.cpu)
    else:
        raise UserInputError(f"matching must be 'auto', 'sequential' or 'exhaustive', not '{cfg.matching}'")
    return matching


#: The smallest share of a frame's 2D-3D matches that its pose must hold as inliers to be registered.
MIN_POSE_INLIER_RATIO = 0.1

#: Growth of the model (registered frames or points) that triggers the incremental mapper's next global bundle
#: adjustment: fewer global adjustments on a long survey, the local ones still after every image.
GLOBAL_BA_GROWTH = 1.4


def _incremental_options(cam: dict | None, cfg: SfmConfig):
    """COLMAP's incremental mapper options: seeded, one model, intrinsics held when known and ``fix_intrinsics``;
    the global bundle adjustment run when the model has grown by ``GLOBAL_BA_GROWTH`` since the last (COLMAP: 1.1)
    and without the points that add no coverage (``ba_global_ignore_redundant_points3D``)."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.ba_global_frames_ratio = options.ba_global_points_ratio = GLOBAL_BA_GROWTH
    options.mapper.ba_global_ignore_redundant_points3D = True
    options.random_seed = cfg.seed
    options.multiple_models = False
    options.min_model_size = 3
    options.mapper.init_min_tri_angle = cfg.init_min_tri_angle_deg
    options.mapper.abs_pose_min_num_inliers = cfg.min_pose_inliers
    options.mapper.abs_pose_min_inlier_ratio = MIN_POSE_INLIER_RATIO
    fixed = cam is not None and cfg.fix_intrinsics
    options.ba_refine_focal_length = not fixed
    options.ba_refine_extra_params = not fixed
    options.ba_refine_principal_point = False
    options.mapper.abs_pose_refine_focal_length = not fixed
    options.mapper.abs_pose_refine_extra_params = not fixed
    return options


def _map_incrementally(database: Path, images_dir: Path, raw_dir: Path, names: list[str], cam: dict | None,
                       cfg: SfmConfig):
    """Incremental mapping (:func:`_incremental_options`) into a fresh ``raw_dir``; returns the model with the most
    registered images and their count (an error naming what to try when fewer than ``min_registered_fraction`` of
    the images, or 3, are registered)."""
    import pycolmap

    shutil.rmtree(raw_dir, ignore_errors=True)
    raw_dir.mkdir()
    models = pycolmap.incremental_mapping(database, images_dir, raw_dir, _incremental_options(cam, cfg))
    return _largest_model(models, names, cfg)


def _map_hierarchically(database: Path, images_dir: Path, raw_dir: Path, names: list[str], cam: dict | None,
                        cfg: SfmConfig):
    """Hierarchical mapping: the images split into overlapping clusters of at most ``HIERARCHICAL_LEAF_IMAGES``,
    each mapped incrementally (:func:`_incremental_options`), the clusters' models merged; returns what
    :func:`_map_incrementally` returns."""
    import pycolmap

    options = pycolmap.HierarchicalPipelineOptions()
    options.incremental_options = _incremental_options(cam, cfg)
    options.clustering_options.leaf_max_num_images = HIERARCHICAL_LEAF_IMAGES
    shutil.rmtree(raw_dir, ignore_errors=True)
    raw_dir.mkdir()
    return _largest_model(pycolmap.hierarchical_mapping(database, images_dir, raw_dir, options), names, cfg)


#: Largest cluster of hierarchical mapping (COLMAP's default): a survey of fewer images is mapped as one cluster.
HIERARCHICAL_LEAF_IMAGES = 500


def _map_globally(database: Path, images_dir: Path, raw_dir: Path, names: list[str], cam: dict | None,
                  cfg: SfmConfig):
    """Global mapping (GLOMAP's rotation averaging and global positioning, seeded; intrinsics held when known and
    ``fix_intrinsics``) into a fresh ``raw_dir``; returns what :func:`_map_incrementally` returns."""
    import pycolmap

    options = pycolmap.GlobalPipelineOptions()
    options.random_seed = cfg.seed
    options.mapper.random_seed = cfg.seed
    options.multiple_models = False
    options.min_model_size = 3
    fixed = cam is not None and cfg.fix_intrinsics
    options.mapper.bundle_adjustment.refine_focal_length = not fixed
    options.mapper.bundle_adjustment.refine_extra_params = not fixed
    options.mapper.bundle_adjustment.refine_principal_point = False
    shutil.rmtree(raw_dir, ignore_errors=True)
    raw_dir.mkdir()
    return _largest_model(pycolmap.global_mapping(database, images_dir, raw_dir, options), names, cfg)


def _largest_model(models: dict, names: list[str], cfg: SfmConfig):
    """The model with the most registered images and their count; an error naming what to try when fewer than
    ``min_registered_fraction`` of the images, or 3, are registered."""
    rec = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
    n_reg = rec.num_reg_images() if rec is not None else 0
    if n_reg < max(3, cfg.min_registered_fraction * len(names)):
        hint = ("try exhaustive matching (--matching exhaustive), a larger --sequential-overlap, "
                "a lower --init-min-tri-angle-deg, the other --mapper, more features, or images with more overlap "
                "and texture")
        raise UserInputError(f"SfM registered only {n_reg} of {len(names)} images "
                             f"(need {max(3, int(np.ceil(cfg.min_registered_fraction * len(names))))}): {hint}")
    return rec, n_reg


def _to_survey_frame(rec, names: list[str], images_dir: Path, cam: dict | None,
                     cfg: SfmConfig) -> tuple[Tracks, str, float, float, dict]:
    """Move ``rec`` into the survey frame (:func:`survey_frame`, from points seen in >= 3 views when there
    are 10) and scale it (:func:`_choose_scale`); returns its tracks and the scale's method, factor, spread and
    detail."""
    import pycolmap

    K, width, height = camera_matrix(rec)
    tracks = build_tracks(rec, names, K, width, height)
    centres = tracks.world_from_cam[tracks.registered, :3, 3]
    good = tracks.track_lengths() >= 3
    R, origin = survey_frame(tracks.xyz[good] if good.sum() >= 10 else tracks.xyz, centres)
    rotated = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), -R @ origin)
    rec.transform(rotated)
    tracks = build_tracks(rec, names, K, width, height)
    method, scale, spread, detail = _choose_scale(cfg, tracks, images_dir, cam, good)
    rec.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(np.eye(3)), np.zeros(3)))
    return build_tracks(rec, names, K, width, height), method, scale, spread, detail


def _write_sfm(rec, tracks: Tracks, out_dir: Path, raw_dir: Path) -> Path:
    """Write ``sparse/`` (the COLMAP binary model) and ``tracks.npz``; remove the mapper's ``raw_dir``.
    Returns the model folder."""
    model_dir = out_dir / "sparse"
    shutil.rmtree(model_dir, ignore_errors=True)
    model_dir.mkdir()
    rec.write_binary(str(model_dir))
    shutil.rmtree(raw_dir, ignore_errors=True)
    tracks.save(out_dir / "tracks.npz")
    return model_dir


def _choose_scale(cfg: SfmConfig, tracks: Tracks, images_dir: Path, cam: dict | None,
                  good: np.ndarray) -> tuple[str, float, float, dict]:
    """(method, s, spread, detail) following ``cfg.scale`` (see the module docstring; detail: the track's, else
    empty)."""
    root = images_dir.parent
    right_dir = Path(cfg.right_dir) if cfg.right_dir else root / "right"
    survey_path = Path(cfg.survey_json) if cfg.survey_json else root / "survey.json"
    has_stereo = cam is not None and "baseline_m" in cam and right_dir.is_dir()
    survey = read_survey_json(survey_path) if survey_path.is_file() else {}
    has_altitude = "nav_altitude_m" in survey
    choices = {"auto": ["stereo", "board", "altitude", "track", "height", "none"], "stereo": ["stereo"],
               "board": ["board"], "altitude": ["altitude"], "track": ["track"], "height": ["height"], "none": ["none"]}
    points = tracks.xyz[good] if good.sum() >= 10 else tracks.xyz
    if cfg.scale not in choices:
        raise UserInputError(f"scale must be one of {', '.join(choices)}, not '{cfg.scale}'")
    for method in choices[cfg.scale]:
        if method == "stereo":
            if has_stereo:
                s, spread = stereo_scale(tracks, images_dir, right_dir, float(cam["baseline_m"]))
                return method, s, spread, {}
            if cfg.scale == "stereo":
                raise UserInputError(f"stereo scale needs right frames in {right_dir} and baseline_m in camera.json")
        elif method == "board":
            if cfg.board_json:
                quads, width_m, height_m = read_board_corners(Path(cfg.board_json), cfg.board_width_m,
                                                              cfg.board_height_m)
                s, spread = board_scale(tracks, quads, width_m, height_m)
                return method, s, spread, {}
            if cfg.scale == "board":
                raise UserInputError("board scale needs a board file with pixel corners (--board-json) and its "
                                     "true size")
        elif method == "altitude":
            if has_altitude:
                by_name = read_nav_altitudes(survey_path, [str(n) for n in tracks.image_names])
                reg = [k for k in np.flatnonzero(tracks.registered) if tracks.image_names[k] in by_name]
                if len(reg) >= 3:
                    alt = np.array([by_name[tracks.image_names[k]] for k in reg], float)
                    s, spread = altitude_scale(points, tracks.world_from_cam[reg, :3, 3], alt)
                    return method, s, spread, {}
            if cfg.scale == "altitude":
                raise UserInputError(f"altitude scale needs nav_altitude_m per frame in {survey_path}")
        elif method == "track":
            if "nav_position_m" in survey:
                return ("track", *track_scale(tracks, survey, survey_path))
            if cfg.scale == "track":
                raise UserInputError(f"track scale needs nav_position_m per frame in {survey_path} (navigation.csv "
                                     f"with x_m, y_m[, z_m] or easting_m, northing_m)")
        elif method == "height":
            if "camera_height_m" in survey:
                centres = tracks.world_from_cam[tracks.registered, :3, 3]
                return ("height", *height_scale(points, centres, float(survey["camera_height_m"])))
            if cfg.scale == "height":
                raise UserInputError(f"height scale needs camera_height_m (the camera's height over the floor, "
                                     f"metres) in {survey_path}")
        else:
            depths = tracks.depths()
            depths = depths[np.isfinite(depths) & (depths > 0)]
            return "none", (1.0 / float(np.median(depths)) if depths.size else 1.0), 0.0, {}
    raise AssertionError("unreachable")


def run_sfm(ws, cfg: SfmConfig) -> SfmResult:
    """Workspace stage: images from ``cfg.images_dir`` or ``00_survey/images``; outputs in ``01_sfm``; features
    only on the survey's scene mask when it has one."""
    images_dir = Path(cfg.images_dir) if cfg.images_dir else ws.stage_dir("survey") / "images"
    survey = ws.result("survey")
    mask = survey.scene_mask if survey is not None else ""
    result = run_sfm_folder(images_dir, ws.stage_dir("sfm"), cfg, ws.path(mask) if mask else None)
    result.model_dir, result.tracks = ws.relative(result.model_dir), ws.relative(result.tracks)
    result.scene_mask = mask
    return result
