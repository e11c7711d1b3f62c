"""Pinhole cameras: intrinsics, poses and (un)projection (numpy).

Camera frame: OpenCV (x right, y down, z forward), metres. A pose is ``world_from_cam``, the 4x4
matrix mapping camera coordinates to world coordinates: p_w = R p_c + t, so t is the camera centre.
Pixel coordinates follow OpenCV: the centre of pixel (column i, row j) is at (i, j), so
u = fx X/Z + cx, v = fy Y/Z + cy with cx = (W - 1)/2, cy = (H - 1)/2 for a centred principal point
(COLMAP puts pixel centres at +0.5: add 0.5 to cx, cy there).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from watergan.data import PinholeIntrinsics as Intrinsics  # one pinhole camera type for simulator and learning


@dataclass(frozen=True)
class CameraConfig:
    """The survey camera."""

    width_px: int = 640
    """Image width, pixels."""
    height_px: int = 480
    """Image height, pixels."""
    hfov_deg: float = 70.0
    """Horizontal field of view (in water, i.e. of the housing + lens system), degrees."""
    distortion: tuple[float, ...] = ()
    """The lens's distortion coefficients in OpenCV's order for ``lens_model`` (:mod:`watergan.lens`: k1, k2, p1,
    p2, k3 or the fisheye's k1..k4); empty: a pinhole camera. The images are rendered through it and camera.json
    gives it; the truth stays in the pinhole geometry."""
    lens_model: str = "opencv"
    """``"opencv"`` or ``"fisheye"``."""

    @property
    def lens(self):
        """The :class:`watergan.lens.Lens`, None for a pinhole camera."""
        from watergan.lens import Lens

        return Lens(self.lens_model, self.distortion) if self.distortion else None


def intrinsics_from_fov(width: int, height: int, hfov_deg: float) -> Intrinsics:
    """fx = fy = (W/2) / tan(hfov/2), principal point at the image centre ((W-1)/2, (H-1)/2)."""
    if width < 2 or height < 2:
        raise ValueError(f"image size must be at least 2x2 pixels, got {width}x{height}")
    if not 1.0 < hfov_deg < 179.0:
        raise ValueError(f"hfov_deg must be between 1 and 179 degrees, got {hfov_deg}")
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height)


def intrinsics_for(camera: CameraConfig) -> Intrinsics:
    return intrinsics_from_fov(camera.width_px, camera.height_px, camera.hfov_deg)


def make_pose(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """4x4 ``world_from_cam`` from the camera's rotation (columns: camera axes in world) and centre."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = centre
    return pose


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: [R t]^-1 = [R^T, -R^T t]."""
    inv = np.eye(4)
    inv[:3, :3] = pose[:3, :3].T
    inv[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inv


@functools.lru_cache(maxsize=8)
def pixel_rays_cam(intr: Intrinsics) -> np.ndarray:
    """(H,W,3) unit ray directions in the camera frame through each pixel centre:
    d = n / |n|, n = ((i - cx)/fx, (j - cy)/fy, 1). Cached: treat the result as read-only."""
    i, j = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    n = np.stack([(i - intr.cx) / intr.fx, (j - intr.cy) / intr.fy, np.ones_like(i)], -1)
    rays = n / np.linalg.norm(n, axis=-1, keepdims=True)
    rays.flags.writeable = False
    return rays


def lens_rays_cam(intr: Intrinsics, lens) -> np.ndarray:
    """(H,W,3) unit ray directions in the camera frame through each pixel centre of a camera seeing through
    ``lens`` (a :class:`watergan.lens.Lens`; :func:`watergan.lens.undistorted_points`)."""
    from watergan.lens import undistorted_points

    i, j = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    K = np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])
    xy = undistorted_points(np.stack([i.ravel(), j.ravel()], 1), K, lens)
    n = np.concatenate([xy, np.ones((len(xy), 1))], 1).reshape(intr.height, intr.width, 3)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def world_to_cam(points_world: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """p_c = R^T (p_w - t) for points (...,3)."""
    return (np.asarray(points_world, float) - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]


def project(points_world: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (...,2) and camera z (...) of world points (...,3): u = fx X/Z + cx,
    v = fy Y/Z + cy. Points behind the camera (z <= 0) get NaN pixel coordinates."""
    pc = world_to_cam(points_world, world_from_cam)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([intr.fx * pc[..., 0] / z + intr.cx, intr.fy * pc[..., 1] / z + intr.cy], -1)
    uv[z <= 0] = np.nan
    return uv, z


def unproject(uv: np.ndarray, depth_m: np.ndarray, world_from_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """World points (...,3) at pixel coordinates (...,2) with camera z ``depth_m`` (...):
    p_c = z ((u - cx)/fx, (v - cy)/fy, 1), p_w = R p_c + t."""
    uv = np.asarray(uv, float)
    z = np.asarray(depth_m, float)
    pc = np.stack([(uv[..., 0] - intr.cx) / intr.fx * z, (uv[..., 1] - intr.cy) / intr.fy * z, z], -1)
    return pc @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
