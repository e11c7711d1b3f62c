"""Lens distortion: OpenCV's model (k1, k2, p1, p2, k3), read from ``camera.json`` and removed once.

A pixel's normalised pinhole coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy) are seen at

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2),
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y,   r^2 = x^2 + y^2

(k1 < 0: barrel, a wide lens behind a flat port; k1 > 0: pincushion). The pipeline undistorts every frame once, in
the survey stage, to the same intrinsics without distortion (:func:`undistort_image`), so every stage after it
projects with the pinhole model and its outputs (corrected frames, mesh, mosaic) are in that undistorted geometry.
The simulator renders through the lens by casting each pixel's ray (:func:`undistorted_points`).
"""

from __future__ import annotations

import cv2
import numpy as np

#: camera.json's distortion keys, OpenCV's order.
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")


def distortion_of(camera: dict) -> np.ndarray | None:
    """(5,) OpenCV coefficients of a camera.json dict, None when it gives none or all are 0."""
    coefficients = np.array([float(camera.get(k, 0.0)) for k in DISTORTION_KEYS])
    return coefficients if np.any(coefficients != 0) else None


def camera_matrix(camera: dict) -> np.ndarray:
    """(3,3) K of a camera.json dict."""
    return np.array([[camera["fx"], 0.0, camera["cx"]], [0.0, camera["fy"], camera["cy"]], [0.0, 0.0, 1.0]])


def undistorted_points(pixels: np.ndarray, K: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """(N,2) normalised pinhole coordinates (x, y) of distorted pixels (N,2), by OpenCV's iteration run to
    convergence (its default five steps leave a wide lens's corners pixels off)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    points = cv2.undistortPoints(np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2), K,
                                 np.asarray(distortion, np.float64), criteria=criteria)
    return points.reshape(-1, 2)


def undistort_image(image: np.ndarray, K: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """The frame as the pinhole camera K without distortion sees it (same size and dtype; bilinear; pixels whose ray
    falls outside the distorted frame are 0)."""
    h, w = image.shape[:2]
    map_x, map_y = cv2.initUndistortRectifyMap(K, np.asarray(distortion, np.float64), None, K, (w, h), cv2.CV_32FC1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
