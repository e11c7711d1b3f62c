"""Ray-cast rendering of a scene (open3d tensor RaycastingScene, CPU, headless) and the
formation state of a rendered frame.

Per pixel: the ray d (unit, world) from the camera centre o hits the scene at t (metres, since d is
unit), so range = t, point = o + t d, depth = z of the point in the camera frame. Normals are the
hit triangle's vertex normals interpolated with the barycentric coordinates (smooth shading).
In-air linear RGB: J = albedo (a + (1 - a) max(0, n . up)), with a = ``ambient`` (so a flat,
up-facing surface renders to exactly its albedo).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch

from watergan.formation import FormationState, pixel_grid

from .camera import Intrinsics, pixel_rays_cam
from .scene import Scene

UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class RenderConfig:
    """Shading of the in-air image and the water column above the site."""

    ambient: float = 0.3
    """Fraction of the in-air illumination independent of the surface slope (a in J = albedo (a +
    (1 - a) max(0, n . up)))."""
    site_depth_m: float = 20.0
    """Depth of the world datum z = 0 below the water surface, metres (water depth = this - z)."""


@dataclass(frozen=True)
class View:
    """One rendered frame; arrays are (H,W,...) float32 in metres / linear units. Pixels without a
    hit have ``valid`` False, zero colour and zero distances, and ``part`` = -1."""

    world_from_cam: np.ndarray  # (4,4)
    range_m: np.ndarray         # (H,W)
    depth_m: np.ndarray         # (H,W) camera z
    points_world: np.ndarray    # (H,W,3)
    points_cam: np.ndarray      # (H,W,3)
    normals_world: np.ndarray   # (H,W,3) unit
    normals_cam: np.ndarray     # (H,W,3) unit
    albedo: np.ndarray          # (H,W,3) linear
    inair: np.ndarray           # (H,W,3) linear in-air RGB J
    part: np.ndarray            # (H,W) int: index into scene.parts, -1 where no hit
    valid: np.ndarray           # (H,W) bool


def make_raycaster(scene: Scene) -> o3d.t.geometry.RaycastingScene:
    """A ray caster holding every part of the scene; geometry id i is ``scene.parts[i]``."""
    caster = o3d.t.geometry.RaycastingScene()
    for i, part in enumerate(scene.parts):
        gid = caster.add_triangles(o3d.core.Tensor(np.ascontiguousarray(part.vertices, np.float32)),
                                   o3d.core.Tensor(np.ascontiguousarray(part.triangles, np.uint32)))
        if gid != i:
            raise RuntimeError(f"ray caster gave geometry id {gid} to part {i}")
    return caster


def render_view(caster: o3d.t.geometry.RaycastingScene, scene: Scene, intr: Intrinsics,
                world_from_cam: np.ndarray, config: RenderConfig, rays_cam: np.ndarray | None = None) -> View:
    """Render one frame with a single ``cast_rays`` call over all pixels; ``rays_cam`` (H,W,3): each pixel's unit
    ray in the camera frame (a lens's, :func:`eval.synth.camera.lens_rays_cam`; default the pinhole's)."""
    rotation = world_from_cam[:3, :3].astype(np.float32)
    origin = world_from_cam[:3, 3].astype(np.float32)
    dirs = (pixel_rays_cam(intr) if rays_cam is None else rays_cam).astype(np.float32) @ rotation.T
    rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], -1)
    hit = caster.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
    t = hit["t_hit"].numpy()
    valid = np.isfinite(t)
    t = np.where(valid, t, np.float32(0.0))
    part = np.where(valid, hit["geometry_ids"].numpy().astype(np.int64), -1)
    points = origin + t[..., None] * dirs

    # smooth normals: barycentric blend of the hit triangle's vertex normals (all parts stacked)
    triangles, vertex_normals, first_triangle = scene.stacked_triangles
    prim = first_triangle[np.maximum(part, 0)] + hit["primitive_ids"].numpy().astype(np.int64)
    corners = triangles[np.where(valid, prim, 0)]
    bary = hit["primitive_uvs"].numpy()
    u, v = bary[..., 0:1], bary[..., 1:2]
    normals = ((1 - u - v) * vertex_normals[corners[..., 0]] + u * vertex_normals[corners[..., 1]]
               + v * vertex_normals[corners[..., 2]])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals[~valid] = 0.0

    albedo = scene.albedo(points, part)
    points_cam = (points - origin) @ rotation
    points_cam[~valid] = 0.0
    points[~valid] = 0.0
    return View(world_from_cam=world_from_cam, range_m=t, depth_m=np.ascontiguousarray(points_cam[..., 2]),
                points_world=points, points_cam=points_cam, normals_world=normals,
                normals_cam=normals @ rotation, albedo=albedo,
                inair=shade(albedo, normals, config.ambient).astype(np.float32), part=part, valid=valid)


def shade(albedo: np.ndarray, normals_world: np.ndarray, ambient: float) -> np.ndarray:
    """J = albedo (a + (1 - a) max(0, n . up)), linear."""
    cosine = np.clip(normals_world @ UP, 0.0, None)[..., None]
    return albedo * (ambient + (1 - ambient) * cosine)


def _chw(array: np.ndarray) -> torch.Tensor:
    a = array if array.ndim == 3 else array[..., None]
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1), dtype=np.float32))[None]


def frame_state(view: View, frame_index: int, site_depth_m: float) -> FormationState:
    """The formation state of a rendered frame with every field set; water_depth_m = site_depth_m -
    world z of the scene point (0 where there is no hit)."""
    h, w = view.range_m.shape
    water_depth = np.where(view.valid, site_depth_m - view.points_world[..., 2], 0.0)
    return FormationState(
        direct=_chw(view.inair),
        range_m=_chw(view.range_m),
        pixel_uv=pixel_grid(h, w, 1),
        image_wh=(w, h),
        depth_m=_chw(view.depth_m),
        points_cam=_chw(view.points_cam),
        normals_cam=_chw(view.normals_cam),
        points_world=_chw(view.points_world),
        normals_world=_chw(view.normals_world),
        water_depth_m=_chw(water_depth),
        frame_index=torch.tensor([frame_index], dtype=torch.long),
        valid=torch.from_numpy(view.valid)[None, None],
    )
