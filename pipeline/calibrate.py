"""Intrinsics from the footage: COLMAP's self-calibration of focal length, principal point and lens on the survey.

A camera of which only the image size (and perhaps a guessed focal length or field of view) is known is calibrated by
the survey itself: SIFT features on up to ``SELFCAL_MAX_FRAMES`` consecutive frames from the middle of the survey,
sequential matching, incremental mapping with one OPENCV camera whose focal lengths, principal point and k1, k2, p1,
p2 every bundle adjustment refines (started from the guess, and from other focal lengths, ``FOCAL_TRIES``, while fewer
than ``ENOUGH_REGISTERED`` of the frames register: a start far off can stall the mapper after its first pair). The
camera model is then chosen by evidence: the model is adjusted again with each simpler model (SIMPLE_RADIAL: f, k1;
RADIAL: f, k1, k2) starting from OPENCV's values, and the simplest model whose mean reprojection error is within
``MODEL_TOLERANCE`` of OPENCV's is kept (a coefficient that lowers the error by less than that is not pinned by the
survey). How well it is pinned: each half of the registered frames is bundle-adjusted on its own, its focal length
started a tenth away from the whole survey's (:func:`_halves`), and the two halves' focal lengths are recorded beside
the whole survey's; halves more than ``HALVES_WARN_PCT`` apart are a warning (the survey does not pin the focal
length). The same frames give the same calibration run to run (within a fraction of a per cent: COLMAP's CPU
matcher is not bit-reproducible on every machine, docs/cameras.md): the frames enter COLMAP's database in name order
(:func:`pipeline.colmap.extract_in_order`: numbered as extraction's threads finish, the mapper, which breaks ties by
id, took another path from run to run), every RANSAC is seeded (the matches' two-view geometry included, which
otherwise draws from whichever worker thread's generator verifies the pair), and the mapper and every bundle
adjustment run on one thread (a multi-threaded solve sums in a varying order).

A lens the survey cannot hold is refused (:func:`check_plausible`): a tangential coefficient beyond
``MAX_TANGENTIAL``, a horizontal field of view outside ``HFOV_RANGE_DEG``, fx and fy differing by more than
``MAX_ASPECT_DIFF``, a principal point outside the middle ``PRINCIPAL_BOX`` of the image, or a radial distortion that
folds the image (the distorted radius stops growing with the undistorted one before the image's corner).
"""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError
from watergan.io import write_scene_mask

#: Starting focal lengths, as factors of the guess, that self-calibration tries in turn until it registers
#: ``ENOUGH_REGISTERED`` of the frames (the model with the most registered frames is kept).
FOCAL_TRIES = (1.0, 0.8, 1.25, 0.65, 1.5)
ENOUGH_REGISTERED = 0.8
#: Frames self-calibration maps at most (consecutive, from the middle of the survey).
SELFCAL_MAX_FRAMES = 100
#: A simpler camera model is kept when its reprojection error is at most this factor of OPENCV's.
MODEL_TOLERANCE = 1.05
#: The largest plausible |p1|, |p2| (a flat port's lens a little off-centre gives thousandths).
MAX_TANGENTIAL = 0.03
#: Plausible horizontal fields of view, degrees.
HFOV_RANGE_DEG = (10.0, 150.0)
#: The largest plausible |fx / fy - 1|.
MAX_ASPECT_DIFF = 0.1
#: The principal point must lie in the middle fraction of the image, in each axis.
PRINCIPAL_BOX = 0.4
#: Halves' focal lengths further apart than this (per cent of their mean) are a warning: the survey does not pin the
#: focal length.
HALVES_WARN_PCT = 5.0
#: Camera models tried, simplest first: COLMAP's name and its parameters after the intrinsics.
MODELS = {"SIMPLE_RADIAL": ("k1",), "RADIAL": ("k1", "k2"), "OPENCV": ("k1", "k2", "p1", "p2")}


def focal_guess_px(camera: dict) -> float | None:
    """The user's starting focal length in pixels: ``fx`` (and ``fy``), else ``hfov_deg`` (fx = w / 2 / tan(hfov/2));
    None without either."""
    if "fx" in camera:
        return float(math.sqrt(camera["fx"] * camera.get("fy", camera["fx"])))
    if "hfov_deg" in camera:
        return float(camera["width"] / 2 / math.tan(math.radians(camera["hfov_deg"]) / 2))
    return None


def needs_calibration(camera: dict) -> bool:
    """Whether camera.json leaves the intrinsics to the survey: fx, fy, cx or cy missing, or ``"calibrated":
    false``. A camera.json with all four and without that flag is a calibration, held fixed."""
    return camera.get("calibrated") is False or not {"fx", "fy", "cx", "cy"} <= set(camera)


def camera_json_of(model: str, params: list[float], width: int, height: int) -> dict:
    """camera.json's keys (fx, fy, cx, cy in OpenCV's pixel convention, the opencv lens's coefficients by name) of
    COLMAP's camera ``model`` and ``params`` (:data:`MODELS`; COLMAP's principal point at pixel centres + 0.5)."""
    coefficients = dict(zip(MODELS[model], params[-len(MODELS[model]):], strict=True))
    if model == "OPENCV":
        fx, fy, cx, cy = params[:4]
    else:
        fx = fy = params[0]
        cx, cy = params[1:3]
    return {"fx": float(fx), "fy": float(fy), "cx": float(cx) - 0.5, "cy": float(cy) - 0.5, "width": int(width),
            "height": int(height), "lens_model": "opencv",
            **{k: float(coefficients.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2")}}


def distorted_radius(camera: dict, r: np.ndarray) -> np.ndarray:
    """The normalised radius at which the lens of a camera.json dict shows the pinhole radius ``r``
    (:mod:`watergan.lens`): opencv r c(r) (its rational form), fisheye theta_d(atan r); tangential terms aside."""
    k = [float(camera.get(key, 0.0)) for key in ("k1", "k2", "k3", "k4", "k5", "k6")]
    if camera.get("lens_model") == "fisheye":
        theta = np.arctan(r)
        return theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    return r * (1 + k[0] * r**2 + k[1] * r**4 + k[2] * r**6) / (1 + k[3] * r**2 + k[4] * r**4 + k[5] * r**6)


def lens_problems(camera: dict) -> list[str]:
    """What makes a camera.json dict's intrinsics and lens implausible (see the module docstring), each with its value;
    empty for a plausible camera. Folding: the distorted radius must grow with the pinhole one (over the pinhole
    angles 0 to 90 deg) until it reaches the image's farthest corner."""
    w, h = camera["width"], camera["height"]
    fx, fy, cx, cy = camera["fx"], camera["fy"], camera["cx"], camera["cy"]
    problems = []
    p = max(abs(camera.get("p1", 0.0)), abs(camera.get("p2", 0.0)))
    if p > MAX_TANGENTIAL:
        problems.append(f"a tangential coefficient of {p:.3f} (a real lens gives under {MAX_TANGENTIAL})")
    hfov = math.degrees(2 * math.atan(w / 2 / fx))
    if not HFOV_RANGE_DEG[0] <= hfov <= HFOV_RANGE_DEG[1]:
        problems.append(f"fx {fx:.0f} px, a horizontal field of view of {hfov:.0f} deg on {w:g} px (plausible: "
                        f"{HFOV_RANGE_DEG[0]:g}-{HFOV_RANGE_DEG[1]:g})")
    if abs(fx / fy - 1) > MAX_ASPECT_DIFF:
        problems.append(f"fx {fx:.0f} and fy {fy:.0f} px differ by {100 * abs(fx / fy - 1):.0f} %")
    if abs(cx - (w - 1) / 2) > PRINCIPAL_BOX / 2 * w or abs(cy - (h - 1) / 2) > PRINCIPAL_BOX / 2 * h:
        problems.append(f"the principal point ({cx:.0f}, {cy:.0f}) far from the image's centre "
                        f"({(w - 1) / 2:.0f}, {(h - 1) / 2:.0f})")
    corner = math.hypot(max(cx, w - 1 - cx) / fx, max(cy, h - 1 - cy) / fy)  # distorted, normalised
    rd = distorted_radius(camera, np.tan(np.radians(np.linspace(0.0, 89.9, 9000))))
    reach = np.flatnonzero(rd >= corner)
    if not len(reach) or not (np.diff(rd[:reach[0] + 1]) > 0).all():
        named = ", ".join(f"{k} {camera[k]:+.3f}" for k in ("k1", "k2", "k3", "k4", "k5", "k6") if camera.get(k))
        problems.append(f"{named or 'the lens'} fold the image before its corner (the distortion stops growing "
                        f"outwards)")
    return problems


def check_plausible(camera: dict, given: Path | None = None) -> None:
    """Refuse a lens that cannot be a camera's (:func:`lens_problems`), with what was found and what to do: the lens
    SfM found on the survey, or ``given``'s (a camera.json the user wrote, held fixed)."""
    problems = lens_problems(camera)
    if not problems:
        return
    if given is not None:
        raise UserInputError(f"camera file {given} is not a plausible camera: " + "; ".join(problems) + ". Give the "
                             f"calibration of these {camera['width']}x{camera['height']} frames (pixels as stored; "
                             f"COLMAP's params in its order), or drop fx, fy, cx, cy and the lens (or set "
                             f"\"calibrated\": false) so that SfM calibrates the camera on the survey")
    raise UserInputError("the lens SfM found on the survey is not plausible: " + "; ".join(problems) + ". Check "
                         "that the frames are one camera's and overlap; give a starting focal length (fx, or "
                         "hfov_deg, in camera.json) or the calibrated intrinsics with \"calibrated\": true")


def _reprojection_with(rec, model: str, start: dict) -> tuple[float, list[float]]:
    """Mean reprojection error (px) and parameters of a copy of ``rec`` adjusted with camera ``model`` from the
    intrinsics ``start`` (camera.json's keys), focal length, principal point and coefficients refined."""
    import pycolmap

    copy = pycolmap.Reconstruction(rec)
    f = math.sqrt(start["fx"] * start["fy"])
    pp = [start["cx"] + 0.5, start["cy"] + 0.5]
    params = {"SIMPLE_RADIAL": [f, *pp, start["k1"]], "RADIAL": [f, *pp, start["k1"], start["k2"]],
              "OPENCV": [start["fx"], start["fy"], *pp, start["k1"], start["k2"], start["p1"], start["p2"]]}[model]
    for camera in copy.cameras.values():
        camera.model = getattr(pycolmap.CameraModelId, model)
        camera.params = params
    camera = _adjust_all(copy)
    return float(copy.compute_mean_reprojection_error()), [float(v) for v in camera.params]


def _adjust_all(rec):
    """Bundle adjustment of ``rec`` in place with every intrinsic free (COLMAP's log kept out); its camera."""
    import pycolmap

    from .colmap import stderr_to_null

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = True
    options.print_summary = False
    options.ceres.solver_options.num_threads = 1  # reproducible: see the module docstring
    with stderr_to_null():
        pycolmap.bundle_adjustment(rec, options)
    return rec.cameras[next(iter(rec.cameras))]


def _set_camera(database: Path, params: list[float]) -> None:
    """The database's (one) camera's parameters set to ``params`` (COLMAP's order)."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        camera = db.read_all_cameras()[0]
        camera.params = params
        db.update_camera(camera)
    finally:
        db.close()


def _map(database: Path, images_dir: Path, out_dir: Path, names: list[str], seed: int):
    """Incremental mapping of ``names`` with every intrinsic refined, the mapper free to start again from another pair
    when one stalls; the model with the most registered frames."""
    import pycolmap

    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    options.num_threads = 1  # reproducible: see the module docstring
    options.multiple_models = True  # a first pair that stalls is not the end: the mapper starts again elsewhere
    options.min_model_size = 3
    options.image_names = names
    options.mapper.init_min_tri_angle = 8.0
    options.ba_refine_focal_length = options.ba_refine_extra_params = options.ba_refine_principal_point = True
    models = pycolmap.incremental_mapping(database, images_dir, out_dir, options)
    return max(models.values(), key=lambda r: r.num_reg_images()) if models else None


#: The halves' bundle adjustments start from the whole survey's focal length times this, so that each half's own
#: observations, not the start, decide where it ends.
HALF_START_FACTOR = 1.1


def _halves(rec, registered: list[str], w: int, h: int) -> dict:
    """How well the survey pins the focal length: for each half of the ``registered`` frames (name order), a copy of
    the whole model without the other half's frames (their observations and the points they alone held removed),
    its camera started at ``HALF_START_FACTOR`` times the found focal length and bundle-adjusted with every intrinsic
    free. Returns per half its frames and focal length, and their difference in per cent of their mean
    (``focal_diff_pct``)."""
    import pycolmap

    halves = {}
    for half, part in (("first", registered[:len(registered) // 2]), ("second", registered[len(registered) // 2:])):
        copy = pycolmap.Reconstruction(rec)
        keep = set(part)
        for image_id in list(copy.reg_image_ids()):
            image = copy.image(image_id)
            if image.name not in keep:
                copy.deregister_frame(image.frame_id)
        for camera in copy.cameras.values():
            params = list(camera.params)
            params[0] *= HALF_START_FACTOR
            params[1] *= HALF_START_FACTOR
            camera.params = params
        found = camera_json_of("OPENCV", list(_adjust_all(copy).params), w, h)
        halves[half] = {"registered": copy.num_reg_images(),
                        "focal_px": round(math.sqrt(found["fx"] * found["fy"]), 2)}
    focal = [halves[k]["focal_px"] for k in ("first", "second")]
    halves["focal_diff_pct"] = round(100 * abs(focal[0] - focal[1]) / (0.5 * sum(focal)), 2)
    return halves


def halves_warning(halves: dict) -> str:
    """The warning when the halves' focal lengths (:func:`_halves`) are more than ``HALVES_WARN_PCT`` apart, with
    what to do; empty when they agree."""
    if halves["focal_diff_pct"] <= HALVES_WARN_PCT:
        return ""
    return (f"survey: warning: the two halves of the frames give focal lengths {halves['first']['focal_px']:.1f} and "
            f"{halves['second']['focal_px']:.1f} px, {halves['focal_diff_pct']:.1f} % apart (more than "
            f"{HALVES_WARN_PCT:g} %): the survey does not pin the focal length, and the scale, depths and water "
            f"inherit its error; give fx (or hfov_deg) in camera.json, or frames seen from more varied positions "
            f"(turns, changes of height)")


def self_calibrate(images_dir: Path, names: list[str], camera: dict, work_dir: Path, seed: int = 0,
                   mask: np.ndarray | None = None) -> tuple[dict, dict]:
    """The survey's intrinsics and lens by SfM (see the module docstring), starting from camera.json's focal guess
    (:func:`focal_guess_px`; COLMAP's 1.2 times the larger side without one) and principal point (the image's centre
    without one). ``mask``: (H,W) bool, features only where it is True (the scene). Works in ``work_dir`` (removed
    after).

    Returns camera.json's keys of the chosen model (:func:`camera_json_of`) and a summary: frames, registered,
    reprojection_px, model, models (each model's reprojection error), halves (each half's registered frames and
    focal length, and their difference in per cent), warning (:func:`halves_warning`), focal_guess_px, seconds."""
    import pycolmap

    from .colmap import colmap_errors_only, extract_in_order, seeded_verification

    started = time.perf_counter()
    w, h = int(camera["width"]), int(camera["height"])
    first = max(0, len(names) // 2 - SELFCAL_MAX_FRAMES // 2)
    subset = names[first:first + SELFCAL_MAX_FRAMES]
    guess = focal_guess_px(camera)
    f0 = guess if guess is not None else 1.2 * max(w, h)
    cx0, cy0 = camera.get("cx", (w - 1) / 2) + 0.5, camera.get("cy", (h - 1) / 2) + 0.5
    shutil.rmtree(work_dir, ignore_errors=True)
    work_dir.mkdir(parents=True)
    database = work_dir / "selfcal.db"
    try:
        with colmap_errors_only():
            reader = pycolmap.ImageReaderOptions(camera_model="OPENCV")  # its start: FOCAL_TRIES below
            if mask is not None:
                write_scene_mask(work_dir / "mask.png", mask)
                reader.camera_mask_path = str(work_dir / "mask.png")
            extraction = pycolmap.FeatureExtractionOptions()
            extraction.sift.max_num_features = 4096
            pycolmap.set_random_seed(seed)
            extract_in_order(database, images_dir, subset, reader, extraction)
            pairing = pycolmap.SequentialPairingOptions(overlap=10, quadratic_overlap=True)
            pycolmap.match_sequential(database, pairing_options=pairing, verification_options=seeded_verification(seed),
                                      device=pycolmap.Device.cpu)
            rec, n_reg = None, 0
            for factor in FOCAL_TRIES:  # a start far from the focal length can stall the mapper after its first pair
                _set_camera(database, [f0 * factor, f0 * factor, cx0, cy0, 0, 0, 0, 0])
                tried = _map(database, images_dir, work_dir / "all", subset, seed)
                if tried is not None and tried.num_reg_images() > n_reg:
                    rec, n_reg = tried, tried.num_reg_images()
                if n_reg >= ENOUGH_REGISTERED * len(subset):
                    break
            if n_reg < max(3, len(subset) // 2):
                raise UserInputError(f"self-calibration registered {n_reg} of {len(subset)} frames: SfM cannot "
                                     f"calibrate this camera on the survey; give its intrinsics in camera.json "
                                     f"(fx, fy, cx, cy and the lens)")
            params = [float(v) for v in rec.cameras[next(iter(rec.cameras))].params]
            registered = sorted(rec.image(i).name for i in rec.reg_image_ids())
        halves = _halves(rec, registered, w, h)
        opencv = camera_json_of("OPENCV", params, w, h)
        errors, fits = {}, {}
        for model in MODELS:
            errors[model], fits[model] = _reprojection_with(rec, model, opencv)
        chosen = next(m for m in MODELS if errors[m] <= MODEL_TOLERANCE * errors["OPENCV"])
        found = camera_json_of(chosen, fits[chosen], w, h)
        check_plausible(found)
    finally:
        shutil.rmtree(work_dir, ignore_errors=True)
    summary = {"frames": len(subset), "registered": n_reg, "reprojection_px": round(errors[chosen], 4),
               "model": chosen, "models": {m: round(e, 4) for m, e in errors.items()}, "halves": halves,
               "warning": halves_warning(halves), "focal_guess_px": round(guess, 2) if guess is not None else None,
               "seconds": round(time.perf_counter() - started, 1)}
    return found, summary
