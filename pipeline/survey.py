"""The survey stage: check a user's survey folder before any training starts, link it into the
workspace (never copy or change it), and find or render the in-air RGB-D set WaterGAN learns from.

The survey folder is what a user has: ``images/`` (one camera), optional ``right/`` (the stereo
rig's right frames, same names), ``camera.json`` (intrinsics, optional ``baseline_m``), optional
``survey.json`` and optional ``rgbd/`` (an in-air RGB-D set: ``rgb/`` + ``depth/``).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from watergan.data import IMAGE_SUFFIXES, DataError, list_files, read_image
from watergan.errors import UserInputError
from watergan.io import (
    EXIF_TURNS,
    SCENE_MASK_PNG,
    atomic_write_bytes,
    atomic_write_json,
    exif_orientation,
    read_json,
    read_pixels,
    scene_mask_from,
    write_scene_mask,
)
from watergan.lens import LENS_KEYS, Lens, camera_matrix, distortion_of, undistort_image
from watergan.survey_files import read_camera_json, read_survey_json

from .calibrate import check_plausible, focal_guess_px, lens_problems, needs_calibration, self_calibrate
from .navigation import NAVIGATION_CSV, navigation_from_log
from .workspace import Workspace


def survey_navigation(survey_dir: Path, images: list[str]) -> dict:
    """The survey file's content (``survey.json``, checked; {} without one) with the navigation of the log beside it
    (``navigation.csv``, :mod:`pipeline.navigation`) for its frames (``frames``, else the ``images`` in order)."""
    declared = read_survey_json(survey_dir / "survey.json") if (survey_dir / "survey.json").is_file() else {}
    log = survey_dir / NAVIGATION_CSV
    if log.is_file():
        frames = declared.get("frames") or sorted(images)
        declared = {**declared, "frames": frames, **navigation_from_log(log, frames, declared.get("frame_time_s"))}
    return declared


def check_survey(survey_dir: Path) -> dict:
    """Refuse a survey folder that cannot be processed, before any training starts: a missing
    ``images/`` folder, fewer than 3 images, unreadable or truncated files, images of different
    sizes, ``right/`` frames that do not pair with ``images/`` by name, a missing or malformed ``camera.json``,
    a malformed ``survey.json`` (its light rig included) or one whose frames name an image that is not there, a
    navigation log (``navigation.csv``) that does not reach every frame. Returns a summary."""
    survey_dir = Path(survey_dir)
    images_dir = survey_dir / "images"
    if not survey_dir.is_dir():
        raise UserInputError(f"survey folder {survey_dir} does not exist")
    if not images_dir.is_dir():
        raise UserInputError(f"survey folder {survey_dir} has no images/ folder: put the frames in {images_dir}")
    files = list_files(images_dir, IMAGE_SUFFIXES)
    if len(files) < 3:
        raise UserInputError(f"{images_dir} holds {len(files)} image(s) (PNG, JPEG or TIFF); a survey needs at least 3")
    sizes: dict[tuple[int, int], list[str]] = {}
    bad = []
    for path in files:
        try:
            image = read_image(path)
        except DataError as exc:
            bad.append(str(exc))
            continue
        sizes.setdefault(image.shape[:2], []).append(path.name)
    if bad:
        raise UserInputError(f"{len(bad)} unreadable image(s) in {images_dir}; fix or remove them:\n  "
                             + "\n  ".join(bad))
    if len(sizes) > 1:
        listing = "; ".join(f"{w}x{h}: {len(n)} (e.g. {n[0]})" for (h, w), n in sizes.items())
        first, second, *_ = sizes
        turned = " (some turned a quarter: keep every frame's pixels as the camera stored them; an EXIF orientation " \
            "tag may say how to show them)" if len(sizes) == 2 and second == first[::-1] else ""
        raise UserInputError(f"images in {images_dir} have different sizes ({listing}); one camera per survey{turned}")
    right_dir = survey_dir / "right"
    stereo = right_dir.is_dir()
    if stereo:
        left = {p.name for p in files}
        right = {p.name for p in list_files(right_dir, IMAGE_SUFFIXES)}
        if left != right:
            missing = sorted(left ^ right)[:5]
            raise UserInputError(f"right/ and images/ in {survey_dir} do not pair by file name (e.g. "
                                 f"{', '.join(missing)}); remove right/ for a single camera")
    if not (survey_dir / "camera.json").is_file():
        raise UserInputError(f"{survey_dir} has no camera.json: give the image size (width, height: SfM then "
                             f"calibrates the camera on the survey) or the intrinsics (fx, fy, cx, cy, width, height)")
    # malformed JSON, a missing key or a bad value: an error
    cam = read_camera_json(survey_dir / "camera.json", partial=True)
    (h, w), = sizes
    if (cam["width"], cam["height"]) != (w, h):
        oriented = exif_oriented(files)
        why = (f" as stored ({len(oriented)} carry an EXIF orientation that shows them turned, e.g. "
               f"{next(iter(oriented))}; every stage reads the stored pixels, as SfM does: give camera.json for "
               f"them)") if oriented and (cam["width"], cam["height"]) == (h, w) else ""
        raise UserInputError(f"camera file {survey_dir / 'camera.json'} is for {cam['width']}x{cam['height']} images; "
                             f"the images in {images_dir} are {w}x{h}{why}")
    check_given_camera(survey_dir / "camera.json", cam)
    survey_scene_mask(survey_dir, cam)
    declared = survey_navigation(survey_dir, [p.name for p in files])
    if (survey_dir / "survey.json").is_file():
        named = {p.name for p in files}
        absent = [f for f in declared.get("frames") or [] if f not in named]
        if absent:
            raise UserInputError(f"survey file {survey_dir / 'survey.json'} lists {len(absent)} frame(s) with no image "
                                 f"in {images_dir} (e.g. {absent[0]}): add the images or remove them from its "
                                 f"frames (and their navigation values)")
        if "lights" in declared:
            from watergan.formation.effects.artificial_light import check_rig

            try:
                check_rig(declared["lights"])
            except ValueError as exc:
                raise UserInputError(f"survey file {survey_dir / 'survey.json'}: lights: {exc}") from exc
    return {"n_images": len(files), "width": w, "height": h, "stereo": stereo,
            "simulated": (survey_dir / "truth" / "effects.json").is_file()}


def exif_oriented(files: list[Path]) -> dict[str, int]:
    """{name: EXIF orientation} of the frames whose tag asks a viewer to turn or mirror them (not 1;
    :func:`watergan.io.exif_orientation`). Every stage reads the pixels as stored (:func:`watergan.io.read_pixels`),
    as COLMAP does, so one camera model holds for every frame whatever the tag."""
    return {p.name: o for p in files if (o := exif_orientation(p)) != 1}


def check_given_camera(path: Path, camera: dict) -> None:
    """Refuse the intrinsics camera.json gives when no camera has them (:func:`pipeline.calibrate.lens_problems`, the
    check SfM's lenses pass): a calibration held fixed in full, a starting focal length by its field of view alone."""
    if not needs_calibration(camera):
        check_plausible(camera, given=path)
        return
    guess = focal_guess_px(camera)
    if guess is not None:
        w, h = camera["width"], camera["height"]
        problems = lens_problems({"width": w, "height": h, "fx": guess, "fy": guess, "cx": (w - 1) / 2,
                                  "cy": (h - 1) / 2})
        if problems:
            raise UserInputError(f"camera file {path}: the starting focal length is not a camera's: {problems[0]}. "
                                 f"Give fx in pixels of these {w}x{h} frames, or hfov_deg, or neither (SfM then "
                                 f"tries its own start)")


@dataclass(frozen=True)
class SurveyConfig:
    """Where the survey is, and the in-air RGB-D set WaterGAN learns from."""

    survey_dir: str
    """The survey folder (images/, optional right/, camera.json, optional survey.json and rgbd/)."""
    rgbd_dir: str = ""
    """In-air RGB-D set for WaterGAN (rgb/ + depth/); empty: the survey's rgbd/ folder, else a generic
    seafloor set rendered by the simulator into the workspace."""
    seed: int = 0
    """Seed of the generic RGB-D set (and of the lens's estimation)."""
    estimate_lens: bool = False
    """SfM estimates the lens's distortion on 30 of the frames, starting from camera.json's lens (its model refined)
    or, without one, from OpenCV's k1, k2, p1, p2 at 0; the frames are then undistorted with it."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Progress bars (undistorting a lens's frames)."""

    def __post_init__(self) -> None:
        # absolute folders: `./S` and `S` are the same survey (and the same configuration hash)
        object.__setattr__(self, "survey_dir", str(Path(self.survey_dir).resolve()))
        if self.rgbd_dir:
            object.__setattr__(self, "rgbd_dir", str(Path(self.rgbd_dir).resolve()))


def check_survey_config(cfg: SurveyConfig) -> None:
    """The survey stage's input check (:func:`check_survey`)."""
    check_survey(Path(cfg.survey_dir))


@dataclass
class SurveyResult:
    n_images: int
    width: int
    height: int
    stereo: bool
    """Whether the survey has right/ frames."""
    simulated: bool
    """Whether it is a simulated survey with truth/."""
    rgbd_dir: str
    """The in-air RGB-D set WaterGAN uses (workspace-relative when it is in the workspace, else absolute); empty:
    none given, the gan stage renders a generic seafloor set."""
    survey_dir: str
    """The survey folder (absolute); the workspace's survey folder links to it."""
    navigation: bool = False
    """Whether survey.json gives each frame's altitude (``nav_altitude_m``)."""
    undistorted: dict = field(default_factory=dict)
    """The lens removed from the frames (``lens_model`` and its coefficients, :mod:`watergan.lens`): every stage
    after this one works in the undistorted pinhole geometry (the workspace's images/, right/ and camera.json);
    empty: none."""
    lens_estimate: dict = field(default_factory=dict)
    """SfM's estimation of the lens (:func:`pipeline.sfm.estimate_lens`: frames, registered, reprojection error,
    seconds, the start); empty: the lens is camera.json's."""
    self_calibration: dict = field(default_factory=dict)
    """SfM's calibration of the camera on the survey (:func:`pipeline.calibrate.self_calibrate`: the model chosen
    and each model's reprojection error, each half's focal length); empty: camera.json's intrinsics held."""
    scene_mask: str = ""
    """The scene mask in the frames' (undistorted) geometry (:func:`watergan.io.write_scene_mask`, workspace-relative);
    empty: every pixel is the scene."""


def survey_scene_mask(survey_dir: Path, camera: dict):
    """The survey's scene mask in the raw frames' geometry (:func:`watergan.io.scene_mask_from`: ``mask.png`` in the
    survey folder, less camera.json's ``mask_rects_px``); None without either."""
    png = survey_dir / SCENE_MASK_PNG
    try:
        return scene_mask_from(int(camera["width"]), int(camera["height"]), png if png.is_file() else None,
                               camera.get("mask_rects_px"))
    except DataError as exc:
        rects = "rectangle" in str(exc) or "mask_rects_px" in str(exc)
        raise UserInputError(f"camera file {survey_dir / 'camera.json'}: {exc}" if rects else
                             f"survey {survey_dir}: {exc}") from None


def undistort_frames(survey: Path, target: Path, camera: dict, lens: Lens, progress: bool = True) -> None:
    """The survey's frames (images/, right/) undistorted into the workspace's survey folder (same names, format and
    bit depth; :func:`watergan.lens.undistort_image`)."""
    import cv2
    from tqdm import tqdm

    K = camera_matrix(camera)
    for folder in ("images", "right"):
        if not (survey / folder).is_dir():
            continue
        (target / folder).mkdir(exist_ok=True)
        for path in tqdm(list_files(survey / folder, IMAGE_SUFFIXES), desc=f"undistort {folder}", unit="frame",
                         disable=not progress):
            image = read_pixels(path)
            ok, data = cv2.imencode(path.suffix, undistort_image(image, K, lens))
            if not ok:
                raise DataError(f"cannot encode the undistorted {path}")
            atomic_write_bytes(target / folder / path.name, data.tobytes())


def link_survey(survey: Path, target: Path, written: set[str]) -> None:
    """Link the survey folder's images, right, camera.json, survey.json and truth into the workspace's ``target``
    folder, but those in ``written`` (the workspace writes its own: a link left there is removed); a link left by a run
    on another survey folder is replaced. Nothing of the survey's is changed."""
    for name in ("images", "right", "camera.json", "survey.json", "truth"):
        if name in written:  # the workspace's own version, written by the stage
            if (target / name).is_symlink():
                (target / name).unlink()
            continue
        src, dst = survey / name, target / name
        if dst.is_symlink() and dst.resolve() != src.resolve():
            dst.unlink()  # a link left by a run on another survey folder
        if src.exists() and not dst.exists():
            dst.symlink_to(src)


def rgbd_set(cfg: SurveyConfig, survey: Path) -> Path | None:
    """The in-air RGB-D set (rgb/ + depth/): ``cfg.rgbd_dir``, else the survey's ``rgbd/``, else None (the gan
    stage renders a generic seafloor set, :func:`pipeline.gan.generic_rgbd`)."""
    rgbd = Path(cfg.rgbd_dir) if cfg.rgbd_dir else survey / "rgbd"
    if (rgbd / "rgb").is_dir():
        return rgbd
    if cfg.rgbd_dir:
        raise UserInputError(f"in-air RGB-D folder {rgbd} has no rgb/ folder (rgb/ + depth/, paired by name)")
    return None


def calibrated_camera(survey: Path, names: list[str], camera: dict, target: Path, seed: int,
                      mask: np.ndarray | None) -> tuple[dict, Lens | None, dict]:
    """The camera calibrated by SfM on the survey's frames (:func:`pipeline.calibrate.self_calibrate`, working in
    ``target/selfcal``): its camera.json keys, its lens and the calibration's record; printed."""
    found, calibration = self_calibrate(survey / "images", names, camera, target / "selfcal", seed, mask)
    camera = {**{k: v for k, v in camera.items() if k not in ("fx", "fy", "cx", "cy", "hfov_deg")}, **found}
    lens = distortion_of(camera)
    halves = calibration["halves"]
    print(f"survey: SfM calibrated the camera on {calibration['registered']} frames: {calibration['model']}, "
          f"fx {camera['fx']:.1f} fy {camera['fy']:.1f} cx {camera['cx']:.1f} cy {camera['cy']:.1f} px, "
          + ", ".join(f"{k} {camera[k]:+.4f}" for k in ("k1", "k2", "p1", "p2"))
          + f" (reprojection {calibration['reprojection_px']:.3f} px; the halves' focal lengths differ by "
          f"{halves['focal_diff_pct']:.1f} %)", file=sys.stderr, flush=True)
    if calibration["warning"]:
        print(calibration["warning"], file=sys.stderr, flush=True)
    return camera, lens, calibration


def estimated_lens(survey: Path, names: list[str], camera: dict, lens: Lens | None, target: Path,
                   seed: int) -> tuple[Lens, dict]:
    """The lens SfM estimates on the survey's frames from the declared one (:func:`pipeline.sfm.estimate_lens`, working
    in ``target/lens_sfm``) and its record; checked plausible and printed."""
    from .sfm import estimate_lens

    lens, estimate = estimate_lens(survey / "images", names, camera, lens, target / "lens_sfm", seed)
    check_plausible({**camera, **lens.to_json()})
    print(f"survey: SfM's lens on {estimate['registered']} frames: {lens.model} "
          + ", ".join(f"{k} {v:+.4f}" for k, v in lens.to_json().items() if k != "lens_model")
          + f" (reprojection {estimate['reprojection_px']:.3f} px)", file=sys.stderr, flush=True)
    return lens, estimate


def run_survey(ws: Workspace, cfg: SurveyConfig) -> SurveyResult:
    """Check the survey and link it into ``00_survey`` (nothing of the user's is copied or changed);
    render a generic in-air RGB-D set when none is given."""
    survey, target = Path(cfg.survey_dir).resolve(), ws.stage_dir("survey").resolve()
    summary = check_survey(survey)
    oriented = exif_oriented(list_files(survey / "images", IMAGE_SUFFIXES))
    if oriented:
        first, turn = next(iter(oriented.items()))
        print(f"survey: {len(oriented)} frame(s) carry an EXIF orientation that asks a viewer to turn or mirror them "
              f"(e.g. {first}: {turn}, {EXIF_TURNS[turn]}); every stage reads the pixels as the camera stored them, as "
              f"SfM does, so one camera model holds for every frame; the corrected frames are written as stored",
              file=sys.stderr, flush=True)
    logged = (survey / NAVIGATION_CSV).is_file()
    camera = read_camera_json(survey / "camera.json", partial=True)
    calibrate = needs_calibration(camera)
    lens = None if calibrate else distortion_of(camera)
    mask = survey_scene_mask(survey, camera)
    # the workspace's own camera.json: pinhole after undistortion or calibration, or COLMAP's form read into named keys
    own_camera = lens is not None or cfg.estimate_lens or calibrate or "params" in read_json(survey / "camera.json")
    if own_camera and survey == target:
        raise UserInputError(f"{survey} is a workspace's survey folder and its camera.json has a lens or COLMAP's "
                             f"params: run on the survey folder itself, so that the workspace gets its own frames "
                             f"and camera.json")
    if survey != target:
        written = ({"survey.json"} if logged else set()) | ({"camera.json"} if own_camera else set()) | \
            ({"images", "right"} if lens is not None or cfg.estimate_lens or calibrate else set())
        link_survey(survey, target, written)
    rgbd = rgbd_set(cfg, survey)
    names = [p.name for p in list_files(survey / "images", IMAGE_SUFFIXES)]
    estimate, calibration = {}, {}
    if calibrate:
        camera, lens, calibration = calibrated_camera(survey, names, camera, target, cfg.seed, mask)
    elif cfg.estimate_lens:
        lens, estimate = estimated_lens(survey, names, camera, lens, target, cfg.seed)
    if lens is not None:
        undistort_frames(survey, target, camera, lens, cfg.progress)
    if own_camera:
        dropped = (*LENS_KEYS, "model", "calibrated", "mask_rects_px")
        pinhole = {k: v for k, v in camera.items() if k not in dropped}
        atomic_write_json(target / "camera.json", {**pinhole, **({"undistorted": lens.to_json()} if lens else {}),
                                                   **({"self_calibration": calibration} if calibration else {}),
                                                   **({"lens_estimated": True} if estimate else {})})
    mask_path = ""
    if mask is not None:
        if lens is not None:
            mask = undistort_image(mask.astype(np.uint8) * 255, camera_matrix(camera), lens) > 127
        write_scene_mask(target / "scene_mask.png", mask)
        mask_path = ws.relative(target / "scene_mask.png")
    declared = survey_navigation(survey, names)
    if logged:
        if survey == target:
            raise UserInputError(f"{survey} holds a navigation log: run on the survey folder, not on a workspace's "
                                 f"{ws.stage('survey').folder}")
        atomic_write_json(target / "survey.json", declared, finite=True)
    navigation = "nav_altitude_m" in declared
    inside = rgbd is not None and rgbd.resolve().is_relative_to(ws.root.resolve())
    return SurveyResult(**summary, rgbd_dir="" if rgbd is None else ws.relative(rgbd) if inside else str(rgbd),
                        survey_dir=str(survey),
                        navigation=navigation, undistorted=lens.to_json() if lens is not None else {},
                        lens_estimate=estimate, self_calibration=calibration, scene_mask=mask_path)
