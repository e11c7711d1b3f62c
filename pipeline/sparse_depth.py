"""Depth from the sparse points where stereo between neighbours cannot give it: a camera moving along its view.

Neighbour stereo rectifies a pair about its baseline; when the camera moves along its optical axis (a crawler or an
ROV looking forward) the epipoles fall inside the frames and rectification has nothing to match along. The SfM
points still cover the scene densely on a textured floor, and each is seen from several positions. So a frame's
depth map is interpolated from the sparse points it observes:

    z(x) = sum_i w_i(x) z_i   over the Delaunay triangle of the observations' pixels that holds x (barycentric w),

z_i the point's depth in the frame's camera. A triangle with an edge longer than ``max_edge_frac`` of the image's
diagonal spans a gap in the points (the far wall's untextured band, open water) and is left empty; a point whose
depth differs from the median of its ``neighbours`` nearest observations by more than ``outlier_frac`` (a wrong
triangulation) is dropped first. The map is computed on a grid ``grid_step`` pixels apart and resampled bilinearly.
"""

from __future__ import annotations

import numpy as np


def pair_is_forward(world_from_left: np.ndarray, world_from_right: np.ndarray, max_angle_deg: float = 45.0) -> bool:
    """Whether the baseline of two poses is within ``max_angle_deg`` of the left camera's optical axis (then the
    epipole is in or near the frame and rectified stereo fails)."""
    baseline = world_from_right[:3, 3] - world_from_left[:3, 3]
    norm = np.linalg.norm(baseline)
    if norm == 0:
        return True
    axis = world_from_left[:3, 2]
    return abs(float(baseline @ axis)) / norm > np.cos(np.radians(max_angle_deg))


def sparse_depth(xy: np.ndarray, z: np.ndarray, width: int, height: int, max_edge_frac: float = 0.08,
                 neighbours: int = 8, outlier_frac: float = 0.15, grid_step: int = 4) -> np.ndarray:
    """(H,W) depth interpolated from observations at pixels ``xy`` (N,2) with depths ``z`` (N,), NaN where no kept
    triangle covers a pixel (see the module docstring)."""
    import cv2
    from scipy.spatial import Delaunay, cKDTree

    out = np.full((height, width), np.nan)
    good = np.isfinite(z) & (z > 0) & (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & \
        (xy[:, 1] <= height - 1)
    xy, z = np.asarray(xy, float)[good], np.asarray(z, float)[good]
    if len(z) < 4:
        return out
    _, near = cKDTree(xy).query(xy, k=min(neighbours + 1, len(z)))
    local = np.median(z[near[:, 1:]], axis=1)
    keep = np.abs(z / local - 1) <= outlier_frac
    xy, z = xy[keep], z[keep]
    if len(z) < 4:
        return out
    try:
        tri = Delaunay(xy)
    except Exception:  # noqa: BLE001  collinear or degenerate points: no map
        return out
    corners = xy[tri.simplices]
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(1)
    long_edge = edges > max_edge_frac * np.hypot(width, height)
    gx, gy = np.meshgrid(np.arange(0, width + grid_step - 1, grid_step, dtype=float).clip(max=width - 1),
                         np.arange(0, height + grid_step - 1, grid_step, dtype=float).clip(max=height - 1))
    grid = np.stack([gx.ravel(), gy.ravel()], 1)
    simplex = tri.find_simplex(grid)
    inside = (simplex >= 0)
    inside[inside] = ~long_edge[simplex[inside]]
    values = np.full(len(grid), np.nan)
    s = simplex[inside]
    transform = tri.transform[s]
    bary = np.einsum("nij,nj->ni", transform[:, :2], grid[inside] - transform[:, 2])
    weights = np.concatenate([bary, 1 - bary.sum(1, keepdims=True)], 1)
    values[inside] = (weights * z[tri.simplices[s]]).sum(1)
    coarse = values.reshape(gx.shape)
    valid = np.isfinite(coarse).astype(np.float32)
    filled = np.nan_to_num(coarse).astype(np.float32)
    map_x = (np.arange(width, dtype=np.float32) / grid_step)[None].repeat(height, 0)
    map_y = (np.arange(height, dtype=np.float32) / grid_step)[:, None].repeat(width, 1)
    weight = cv2.remap(valid, map_x, map_y, cv2.INTER_LINEAR)
    total = cv2.remap(filled * valid, map_x, map_y, cv2.INTER_LINEAR)
    near_valid = cv2.remap(valid, map_x, map_y, cv2.INTER_NEAREST) > 0
    ok = near_valid & (weight > 0.5)
    out[ok] = total[ok] / weight[ok]
    return out
