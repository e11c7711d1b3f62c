"""The state that flows through a formation stack.

Every tensor is laid out ``(B, C, H, W)``. Images are the usual case; the diagnosis passes per-point
observations as ``(N, C, 1, 1)`` (one observation per batch element, so per-frame fields such as
``frame_index`` vary per observation); every effect that acts pixel by pixel accepts them.

Signals are linear (not sRGB encoded), in relative radiance units where the in-air scene is 0..1.

Conventions: camera frame is OpenCV's (x right, y down, z forward, metres); world frame is z up,
metres. ``range_m`` is the Euclidean distance from the camera centre to the scene point along the
pixel's ray, ``depth_m`` its z in the camera frame.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import torch

from ..errors import UserInputError


class MissingInputError(UserInputError):
    """An effect needs a field of the state that the data in hand does not provide."""


@dataclass(frozen=True)
class FormationState:
    """What an effect reads and writes.

    direct:          (B,3,H,W) the signal from the scene that has reached the camera so far
                     (starts as the in-air image J).
    backscatter:     (B,3,H,W) light scattered into the ray by the water (starts at zero).
    range_m:         (B,1,H,W) camera-to-scene distance along the ray, metres.
    depth_m:         (B,1,H,W) scene z in the camera frame, metres (optional).
    pixel_uv:        (B,2,H,W) pixel centre as a fraction of image width and height, 0..1.
    image_wh:        (width, height) in pixels of the full image the coordinates refer to.
    points_cam:      (B,3,H,W) scene point in the camera frame, metres (optional).
    normals_cam:     (B,3,H,W) unit surface normal in the camera frame (optional).
    points_world:    (B,3,H,W) scene point in the world frame (z up), metres (optional).
    normals_world:   (B,3,H,W) unit surface normal in the world frame (optional).
    water_depth_m:   (B,1,H,W) depth of the scene point below the water surface, metres (optional).
    frame_index:     (B,) integer frame number within the survey (optional).
    z:               (B,Z) noise vector for learned effects (optional; WaterGAN's z).
    beta_d_per_m:    (B,3,1,1) direct-signal attenuation coefficient, written by ``attenuation``
                     for effects that relate to it (optional).
    valid:           (B,1,H,W) bool, pixels with a scene behind them (optional).
    """

    direct: torch.Tensor
    range_m: torch.Tensor
    pixel_uv: torch.Tensor
    image_wh: tuple[int, int]
    backscatter: torch.Tensor | None = None
    depth_m: torch.Tensor | None = None
    points_cam: torch.Tensor | None = None
    normals_cam: torch.Tensor | None = None
    points_world: torch.Tensor | None = None
    normals_world: torch.Tensor | None = None
    water_depth_m: torch.Tensor | None = None
    frame_index: torch.Tensor | None = None
    z: torch.Tensor | None = None
    beta_d_per_m: torch.Tensor | None = None
    valid: torch.Tensor | None = None

    def __post_init__(self) -> None:
        self._check_shapes()
        if not torch.isfinite(self.range_m).all():
            raise ValueError("state.range_m contains NaN or infinite values: mask or fill them first")

    def _check_shapes(self) -> None:
        if self.direct.ndim != 4 or self.direct.shape[1] != 3:
            raise ValueError(f"direct must be (B,3,H,W), got {tuple(self.direct.shape)}")
        b, _, h, w = self.direct.shape
        if self.backscatter is None:
            object.__setattr__(self, "backscatter", torch.zeros_like(self.direct))
        for name in ("range_m", "pixel_uv", "depth_m", "points_cam", "normals_cam", "points_world",
                     "normals_world", "water_depth_m", "valid"):
            t = getattr(self, name)
            if t is not None and (t.ndim != 4 or t.shape[0] not in (1, b) or t.shape[2:] != (h, w)):
                raise ValueError(
                    f"state.{name} has shape {tuple(t.shape)}; expected (B,C,{h},{w}) to match direct"
                )

    @property
    def image(self) -> torch.Tensor:
        """The image the camera records: direct + backscatter."""
        return self.direct + self.backscatter

    def replace(self, **changes) -> FormationState:
        """A copy with some fields replaced (effects never modify a state in place), checked as a new state is; the
        range is checked for NaN only when it is replaced (a stack replaces the state once per effect)."""
        if "range_m" in changes:
            return dataclasses.replace(self, **changes)
        unknown = changes.keys() - self.__dataclass_fields__.keys()
        if unknown:
            raise TypeError(f"FormationState has no field {sorted(unknown)}")
        new = copy.copy(self)
        for name, value in changes.items():
            object.__setattr__(new, name, value)
        new._check_shapes()
        return new

    def need(self, field: str, effect: str) -> torch.Tensor:
        """The named field, or a clear error saying which effect needs it."""
        value = getattr(self, field)
        if value is None:
            raise MissingInputError(
                f"effect '{effect}' needs state.{field}, which this data does not provide "
                f"(the survey simulator provides every field; RGB-D data gives range, depth and, "
                f"with intrinsics, points and normals)"
            )
        return value

    @property
    def dtype(self) -> torch.dtype:
        return self.direct.dtype

    @property
    def device(self) -> torch.device:
        return self.direct.device


def pixel_grid(height: int, width: int, batch: int = 1, dtype=torch.float32, device=None) -> torch.Tensor:
    """(B,2,H,W) pixel centres as fractions of the image: u = (x + 0.5)/W, v = (y + 0.5)/H."""
    v, u = torch.meshgrid(
        (torch.arange(height, dtype=dtype, device=device) + 0.5) / height,
        (torch.arange(width, dtype=dtype, device=device) + 0.5) / width,
        indexing="ij",
    )
    return torch.stack([u, v])[None].expand(batch, 2, height, width)


def normalised_radius(pixel_uv: torch.Tensor, image_wh: tuple[int, int],
                      centre_uv: torch.Tensor | tuple[float, float] = (0.5, 0.5)) -> torch.Tensor:
    """(B,1,H,W) distance from ``centre_uv`` in pixels divided by the half diagonal (1 at a corner
    for the image centre): r = |((u - cu) W, (v - cv) H)| / (0.5 sqrt(W^2 + H^2))."""
    w, h = image_wh
    cu, cv = (centre_uv[..., 0], centre_uv[..., 1]) if isinstance(centre_uv, torch.Tensor) else centre_uv
    dx = (pixel_uv[:, 0:1] - cu) * w
    dy = (pixel_uv[:, 1:2] - cv) * h
    return torch.sqrt(dx * dx + dy * dy + 1e-12) / (0.5 * math.hypot(w, h))


def vector_length(t: torch.Tensor, dim: int) -> torch.Tensor:
    """The length sqrt(x^2 + y^2 + z^2) of the 3-vectors along ``dim`` (kept, of size 1). The same as
    ``t.norm(dim=dim, keepdim=True)`` to rounding; torch's norm over a dimension that is not the last is many times
    slower on a CPU (benchmarks/RESULTS/speed-and-scale.md)."""
    return torch.sqrt(dot3(t, t, dim))


def dot3(a: torch.Tensor, b: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """a . b of the 3-vectors along ``dim`` (kept, of size 1; ``a`` and ``b`` broadcast): ``(a * b).sum(dim,
    keepdim=True)`` to rounding, without torch's slow reduction over a dimension of three on a CPU."""
    a0, a1, a2 = a.unbind(dim)
    b0, b1, b2 = b.unbind(dim)
    return (a0 * b0 + a1 * b1 + a2 * b2).unsqueeze(dim)


def state_from_rgbd(rgb_linear: torch.Tensor, depth_m: torch.Tensor, fx: float, fy: float,
                    cx: float, cy: float, image_wh: tuple[int, int] | None = None) -> FormationState:
    """A state from in-air linear RGB (B,3,H,W) and z-depth (B,1,H,W) with pinhole intrinsics in
    pixels of the given images: points_cam = depth * K^-1 [x, y, 1], range = |points_cam|, normals
    from the cross product of the points' image-space gradients."""
    b, _, h, w = rgb_linear.shape
    if not torch.isfinite(depth_m).all() or (depth_m < 0).any():
        raise ValueError("depth contains NaN, infinite or negative values")
    ys, xs = torch.meshgrid(torch.arange(h, dtype=depth_m.dtype), torch.arange(w, dtype=depth_m.dtype),
                            indexing="ij")
    ray = torch.stack([(xs - cx) / fx, (ys - cy) / fy, torch.ones_like(xs)])[None]
    points = depth_m * ray
    du = torch.nn.functional.pad(points[..., :, 2:] - points[..., :, :-2], (1, 1, 0, 0), mode="replicate")
    dv = torch.nn.functional.pad(points[..., 2:, :] - points[..., :-2, :], (0, 0, 1, 1), mode="replicate")
    normals = torch.linalg.cross(dv, du, dim=1)
    normals = normals / vector_length(normals, 1).clamp_min(1e-12)
    # face the camera: a visible surface's normal points against the ray (z < 0 in camera frame)
    normals = torch.where(normals[:, 2:3] > 0, -normals, normals)
    return FormationState(
        direct=rgb_linear,
        range_m=vector_length(points, 1),
        depth_m=depth_m,
        pixel_uv=pixel_grid(h, w, b, rgb_linear.dtype),
        image_wh=image_wh or (w, h),
        points_cam=points,
        normals_cam=normals,
        valid=depth_m > 0,
    )
