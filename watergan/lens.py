"""Lens distortion: OpenCV's two models, read from ``camera.json`` (by name, or as COLMAP's camera model and
parameters) and removed once.

A pixel's normalised pinhole coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy), r^2 = x^2 + y^2, are seen at

* ``"opencv"`` (k1, k2, p1, p2, k3 and optionally k4, k5, k6, the rational form)::

    x_d = x c + 2 p1 x y + p2 (r^2 + 2 x^2),   y_d = y c + p1 (r^2 + 2 y^2) + 2 p2 x y,
    c = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)

  (k1 < 0: barrel, a wide lens behind a flat port; k1 > 0: pincushion);
* ``"fisheye"`` (k1, k2, k3, k4; OpenCV's fisheye, COLMAP's OPENCV_FISHEYE), the angle theta = atan(r) seen at
  theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8): (x_d, y_d) = (x, y) theta_d / r.

The pipeline undistorts every frame once, in the survey stage, to the same intrinsics without distortion
(:func:`undistort_image`), so every stage after it projects with the pinhole model and its outputs (corrected
frames, mesh, mosaic) are in that undistorted geometry (a fisheye's periphery beyond the pinhole frame is left out).
One geometry keeps COLMAP, the dense stereo, the water's ranges and the mosaic on one projection; the price is one
bilinear resampling of each frame. The simulator renders through the lens by casting each pixel's ray
(:func:`undistorted_points`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

OPENCV, FISHEYE = "opencv", "fisheye"
#: camera.json's coefficient keys of each model, in OpenCV's order.
MODEL_KEYS = {OPENCV: ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), FISHEYE: ("k1", "k2", "k3", "k4")}
#: Every camera.json key that describes the lens (removed from the workspace's undistorted camera.json).
LENS_KEYS = ("lens_model",) + MODEL_KEYS[OPENCV]

#: COLMAP's camera models (its parameter order; principal point with pixel centres at +0.5): the model, the
#: focal length keys their first parameters give, and the camera.json coefficient keys of the rest.
COLMAP_MODELS = {
    "SIMPLE_PINHOLE": (OPENCV, ("f",), ()),
    "PINHOLE": (OPENCV, ("fx", "fy"), ()),
    "SIMPLE_RADIAL": (OPENCV, ("f",), ("k1",)),
    "RADIAL": (OPENCV, ("f",), ("k1", "k2")),
    "OPENCV": (OPENCV, ("fx", "fy"), ("k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (OPENCV, ("fx", "fy"), MODEL_KEYS[OPENCV]),
    "SIMPLE_RADIAL_FISHEYE": (FISHEYE, ("f",), ("k1",)),
    "RADIAL_FISHEYE": (FISHEYE, ("f",), ("k1", "k2")),
    "OPENCV_FISHEYE": (FISHEYE, ("fx", "fy"), MODEL_KEYS[FISHEYE]),
}


@dataclass(frozen=True)
class Lens:
    """A lens's distortion: ``model`` (``"opencv"`` or ``"fisheye"``) and its coefficients in OpenCV's order
    (:data:`MODEL_KEYS`; the opencv model's k4-k6 only when one is not 0)."""

    model: str
    coefficients: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in MODEL_KEYS:
            raise ValueError(f"lens model {self.model!r}: expected one of {', '.join(MODEL_KEYS)}")
        keys = MODEL_KEYS[self.model]
        if len(self.coefficients) > len(keys):
            raise ValueError(f"the {self.model} lens has {len(keys)} coefficients, got {len(self.coefficients)}")
        values = tuple(float(c) for c in self.coefficients) + (0.0,) * (len(keys) - len(self.coefficients))
        if self.model == OPENCV and not any(values[5:]):
            values = values[:5]
        object.__setattr__(self, "coefficients", values)

    @property
    def array(self) -> np.ndarray:
        """The coefficients as OpenCV takes them."""
        return np.asarray(self.coefficients, np.float64)

    def to_json(self) -> dict:
        """camera.json's keys: ``lens_model`` and the coefficients by name."""
        return {"lens_model": self.model, **dict(zip(MODEL_KEYS[self.model], self.coefficients, strict=False))}

    def to_colmap(self, camera: dict) -> tuple[str, list[float]]:
        """COLMAP's model and parameters for this lens and camera.json's intrinsics (fx, fy, cx, cy): OPENCV (k3 and
        the rational terms 0), FULL_OPENCV or OPENCV_FISHEYE."""
        intrinsics = [camera["fx"], camera["fy"], camera["cx"] + 0.5, camera["cy"] + 0.5]
        if self.model == FISHEYE:
            return "OPENCV_FISHEYE", intrinsics + list(self.coefficients)
        if any(self.coefficients[4:]):
            return "FULL_OPENCV", intrinsics + list((self.coefficients + (0.0,) * 3)[:8])
        return "OPENCV", intrinsics + list(self.coefficients[:4])


def distortion_of(camera: dict) -> Lens | None:
    """The lens of a camera.json dict (``lens_model``, default opencv, and its coefficient keys; a fisheye's
    missing coefficients are 0, its equidistant projection); None for the opencv model without a coefficient
    other than 0 (a pinhole camera)."""
    model = camera.get("lens_model", OPENCV)
    lens = Lens(model, tuple(float(camera.get(k, 0.0)) for k in MODEL_KEYS[model]))
    return lens if model == FISHEYE or any(lens.coefficients) else None


def camera_from_colmap(model: str, params: list, where: str) -> dict:
    """camera.json's named keys (fx, fy, cx, cy in OpenCV's pixel convention, the lens) of COLMAP's camera
    ``model`` and ``params``; an unsupported model or a wrong number of parameters is a ValueError naming
    ``where``."""
    if model not in COLMAP_MODELS:
        raise ValueError(f"{where}: COLMAP camera model {model!r} is not supported; use one of "
                         f"{', '.join(COLMAP_MODELS)}")
    lens_model, focal, coefficient_keys = COLMAP_MODELS[model]
    names = [*focal, "cx", "cy", *coefficient_keys]
    if len(params) != len(names):
        raise ValueError(f"{where}: COLMAP's {model} takes {len(names)} parameters ({', '.join(names)}), "
                         f"got {len(params)}")
    values = dict(zip(names, (float(p) for p in params), strict=True))
    f = values.pop("f", None)
    camera = {"fx": f, "fy": f} if f is not None else {}
    camera.update(values)
    camera["cx"], camera["cy"] = camera["cx"] - 0.5, camera["cy"] - 0.5
    if coefficient_keys:
        camera["lens_model"] = lens_model
    return camera


def camera_matrix(camera: dict) -> np.ndarray:
    """(3,3) K of a camera.json dict."""
    return np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])


def undistorted_points(pixels: np.ndarray, K: np.ndarray, lens: Lens) -> np.ndarray:
    """(N,2) normalised pinhole coordinates (x, y) of distorted pixels (N,2), by OpenCV's iteration run to
    convergence (its default five steps leave a wide lens's corners pixels off)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    points = np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2)
    undistort = cv2.fisheye.undistortPoints if lens.model == FISHEYE else cv2.undistortPoints
    return undistort(points, K, lens.array, criteria=criteria).reshape(-1, 2)


def distorted_pixels(xy: np.ndarray, K: np.ndarray, lens: Lens) -> np.ndarray:
    """(N,2) pixels at which the lens shows normalised pinhole coordinates (N,2) (the inverse of
    :func:`undistorted_points`)."""
    points = np.concatenate([np.asarray(xy, np.float64).reshape(-1, 2), np.ones((len(xy), 1))], 1).reshape(-1, 1, 3)
    project = cv2.fisheye.projectPoints if lens.model == FISHEYE else cv2.projectPoints
    pixels, _ = project(points, np.zeros(3), np.zeros(3), K, lens.array)
    return pixels.reshape(-1, 2)


def undistort_image(image: np.ndarray, K: np.ndarray, lens: Lens) -> np.ndarray:
    """The frame as the pinhole camera K without distortion sees it (same size and dtype; bilinear; pixels whose ray
    falls outside the distorted frame are 0)."""
    h, w = image.shape[:2]
    if lens.model == FISHEYE:
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, lens.array, np.eye(3), K, (w, h), cv2.CV_32FC1)
    else:
        map_x, map_y = cv2.initUndistortRectifyMap(K, lens.array, None, K, (w, h), cv2.CV_32FC1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
