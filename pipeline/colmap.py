"""pycolmap at arm's length, for the stages that run it (sfm, dense, the survey's calibration): its log kept to
errors, a model read into :class:`eval.tracks.Tracks` and an OpenCV camera matrix, and the lens k1 a model would
refine.

Pixel convention: COLMAP puts the centre of pixel (column i, row j) at (i + 0.5, j + 0.5), OpenCV and everything
outside COLMAP at (i, j). A model is converted once, as it is read here (:func:`camera_matrix`,
:func:`build_tracks`); the camera given to COLMAP's feature extraction is converted the other way in
:func:`pipeline.sfm._extract_features`.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager

import numpy as np

from eval.tracks import Tracks


@contextmanager
def colmap_errors_only():
    """COLMAP's log (glog: thousands of INFO lines and boilerplate warnings for a survey) kept to its errors
    while the block runs; the level is restored after it."""
    import pycolmap

    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # glog: 0 INFO, 1 WARNING, 2 ERROR
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


@contextmanager
def stderr_to_null():
    """The process's standard error (file descriptor 2, where C++ logs) sent to /dev/null while the block runs."""
    sys.stderr.flush()
    saved = os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(null)
        os.close(saved)


def seeded_verification(seed: int):
    """COLMAP's two-view geometry options with every RANSAC seeded by ``seed``: the matches' verification is then the
    same run to run (unseeded, each pair draws from the generator of whichever worker thread verifies it)."""
    import pycolmap

    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.random_seed = seed
    return options


def extract_in_order(database, images_dir, names: list[str], reader, extraction) -> None:
    """SIFT features of the images ``names`` (one camera, ``reader``'s; on the CPU) into a new ``database``, the images
    entered first (COLMAP's import, one thread) so that their ids follow their sorted names. COLMAP's extraction
    alone numbers them as its threads finish, so the mapper, which breaks ties by id, would take another path run to
    run."""
    import pycolmap

    pycolmap.Database.open(str(database)).close()  # a new database: import_images takes an existing one
    pycolmap.import_images(database, images_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=names,
                           options=reader)
    pycolmap.extract_features(database, images_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def camera_matrix(rec) -> tuple[np.ndarray, int, int]:
    """The model's (first) camera as an OpenCV pinhole K (pixel centres at integers) and its width, height."""
    cam_model = rec.cameras[next(iter(rec.cameras))]
    fx, fy, cx, cy = (cam_model.focal_length_x, cam_model.focal_length_y,
                      cam_model.principal_point_x - 0.5, cam_model.principal_point_y - 0.5)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), cam_model.width, cam_model.height


def _pose_matrix(image) -> np.ndarray:
    """world_from_cam 4x4 of a pycolmap image (inverse of its cam_from_world)."""
    pose = np.eye(4)
    pose[:3, :] = image.cam_from_world().inverse().matrix()
    return pose


def build_tracks(rec, names: list[str], K: np.ndarray, width: int, height: int) -> Tracks:
    """The model ``rec``'s points and their observations as :class:`Tracks` over the images ``names`` (in that
    order; an image the model did not register has a NaN pose), observations in OpenCV's pixel convention
    (COLMAP's minus 0.5)."""
    index = {n: i for i, n in enumerate(names)}
    poses = np.full((len(names), 4, 4), np.nan)
    registered = np.zeros(len(names), bool)
    colmap_to_index = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        k = index[image.name]
        poses[k] = _pose_matrix(image)
        registered[k] = True
        colmap_to_index[image_id] = (k, image)
    ids, xyz, rgb, obs_point, obs_image, obs_xy = [], [], [], [], [], []
    for row, (pid, point) in enumerate(sorted(rec.points3D.items())):
        ids.append(pid)
        xyz.append(point.xyz)
        rgb.append(point.color)
        for el in point.track.elements:
            k, image = colmap_to_index[el.image_id]
            obs_point.append(row)
            obs_image.append(k)
            obs_xy.append(np.asarray(image.points2D[el.point2D_idx].xy) - 0.5)
    return Tracks(image_names=np.array(names), registered=registered, world_from_cam=poses, K=K,
                  width=width, height=height, point_id=np.array(ids, np.int64),
                  xyz=np.array(xyz, np.float64).reshape(-1, 3), rgb=np.array(rgb, np.uint8).reshape(-1, 3),
                  obs_point=np.array(obs_point, np.int64), obs_image=np.array(obs_image, np.int32),
                  obs_xy=np.array(obs_xy, np.float32).reshape(-1, 2))


def refined_k1(rec) -> float | None:
    """k1 of a SIMPLE_RADIAL camera fitted by bundle adjustment on a copy of the PINHOLE model ``rec`` (focal
    length and principal point held, poses and points free); None when its camera is not PINHOLE."""
    import pycolmap

    copy = pycolmap.Reconstruction(rec)
    for camera in copy.cameras.values():
        if camera.model != pycolmap.CameraModelId.PINHOLE:
            return None
        fx, fy, cx, cy = camera.params
        camera.model = pycolmap.CameraModelId.SIMPLE_RADIAL
        camera.params = [0.5 * (fx + fy), cx, cy, 0.0]
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = False
    options.refine_extra_params = True
    options.print_summary = False
    with stderr_to_null():  # the adjuster logs its start at INFO whatever glog's level
        pycolmap.bundle_adjustment(copy, options)
    return float(np.median([camera.params[3] for camera in copy.cameras.values()]))
