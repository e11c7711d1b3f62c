"""A stack's inverse at every pixel of a range map: the fields A, C of y = A J + C.

Every built-in effect but the learned scattering is affine in the in-air colour J, so a stack rendered at
J = 0 and J = 1 gives the recorded colour of any J: y = A J + C, with C = render(J = 0) (backscatter, after the
sensor's effects) and A = render(J = 1) - C (the direct signal's gain: gain, vignetting, transmission, lights).
The inverse J = (y - C) / A is what the physics correction (:func:`correct_physics`)
applies, and what the RGB-D restorer starts from (:mod:`watergan.nets.restorer`): both take the fields from
:func:`inverse_fields`, so the two corrections invert the same water the same way.

A stack that ends in an invertible output map (``Effect.output_map``: the camera's ``tone_curve``, y = T(F'(J)))
is affine once the image is linearised: T^-1(y) = A J + C, with A and C those of F', the stack before the map. The
fields here are then F''s (:meth:`Stack.output_map`), and :func:`linearise_image` gives T^-1(y): the correction is
J = (T^-1(y) - C) / A, exact.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np
import torch

from .stack import Stack
from .state import FormationState, MissingInputError, pixel_grid, state_from_rgbd, vector_length


def rays_cam(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(H,W,3) K^-1 (x, y, 1) (z = 1)."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)


def flat_floor_range(altitude_m: float, K: np.ndarray, h: int, w: int,
                     down_cam: np.ndarray | None = None) -> np.ndarray:
    """(H,W) the range (metres) of a flat, level seafloor ``altitude_m`` below the camera, along each pixel's ray
    d = K^-1 (x, y, 1): r = a |d| / (d . g), g the unit "down" in the camera frame (``down_cam``; None: a nadir
    camera, g = (0, 0, 1), r = a |d|). Rays at or above the horizon (d . g <= 1 % of |d|) take 100 a."""
    unit = camera_unit_rays(K, h, w)
    g = np.array([0.0, 0.0, 1.0]) if down_cam is None else np.asarray(down_cam, np.float64)
    return altitude_m / np.maximum(unit @ (g / np.linalg.norm(g)), 0.01)


@functools.lru_cache(maxsize=8)
def unit_rays(intrinsics: tuple[float, float, float, float], h: int, w: int) -> np.ndarray:
    """(H,W,3) read-only unit vectors along each pixel's ray of a camera (fx, fy, cx, cy): :func:`rays_cam` over its
    length, kept for the last few cameras and sizes (a survey's frames share one)."""
    fx, fy, cx, cy = intrinsics
    rays = rays_cam(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), h, w)
    unit = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    unit.flags.writeable = False
    return unit


def camera_unit_rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    """(H,W,3) read-only unit vectors along each pixel's ray of the camera matrix ``K`` (:func:`unit_rays`)."""
    return unit_rays(_intrinsics(np.asarray(K, np.float64)), h, w)


def flat_floor_depth(altitude_m: float, K: np.ndarray, h: int, w: int,
                     down_cam: np.ndarray | None = None, range_m: np.ndarray | None = None) -> np.ndarray:
    """(H,W) camera-z depth (metres) of the same seafloor: :func:`flat_floor_range` (or ``range_m``, where the caller
    holds it) over each ray's length |K^-1 (x, y, 1)|."""
    unit_z = camera_unit_rays(K, h, w)[..., 2]  # 1 / |K^-1 (x, y, 1)|
    return (flat_floor_range(altitude_m, K, h, w, down_cam) if range_m is None else range_m) * unit_z


def clean_range(r: np.ndarray) -> np.ndarray:
    """A range map (metres) as float64 with NaN wherever it holds no range (NaN, inf or <= 0)."""
    r = np.asarray(r, np.float64)
    return np.where(np.isfinite(r) & (r > 0), r, np.nan)


#: Pixels per sigma of the grid :func:`normals_from_range` smooths on: a Gaussian of sigma s px is computed on a grid
#: s // 8 times coarser than the image (a sigma of at least 8 of its cells), since the smoothed surface has no finer
#: detail.
NORMAL_GRID_PX_PER_SIGMA = 8.0


def normals_from_range(range_m: np.ndarray, K: np.ndarray, smooth_px: float = 24.0) -> np.ndarray:
    """(H,W,3) unit surface normals in the camera frame from a range map (metres along each ray; NaN or <= 0 =
    none): z = r / |K^-1 (x, y, 1)|, smoothed by a Gaussian of sigma ``smooth_px`` over the pixels with range
    (blur(z) / blur(valid)), then the normals of :func:`watergan.formation.state_from_rgbd` (cross product of
    the lifted points' central differences, turned to face the camera). NaN where the pixel has no range.

    With ``smooth_px`` >= 16 the smoothing and the normals are computed on a grid ``step`` =
    ``smooth_px // NORMAL_GRID_PX_PER_SIGMA`` times coarser (at most an eighth of the image's sides; z and the valid
    mask area-averaged onto it, the intrinsics scaled with it, sigma ``smooth_px / step`` there) and the normals
    resampled bilinearly to the image."""
    import cv2

    K = np.asarray(K, np.float64)
    r = clean_range(range_m)
    h, w = r.shape
    z = r / np.linalg.norm(rays_cam(K, h, w), axis=-1)
    valid = np.isfinite(z)
    if not valid.any():
        return np.full((h, w, 3), np.nan)
    z_filled, weight = np.where(valid, z, 0.0), valid.astype(np.float64)
    step = max(1, min(int(smooth_px // NORMAL_GRID_PX_PER_SIGMA), h // 8, w // 8))
    hs, ws = -(-h // step), -(-w // step)
    scale = np.array([ws / w, hs / h])
    if step > 1:
        z_filled = cv2.resize(z_filled, (ws, hs), interpolation=cv2.INTER_AREA)
        weight = cv2.resize(weight, (ws, hs), interpolation=cv2.INTER_AREA)
    if smooth_px > 0:
        num = cv2.GaussianBlur(z_filled, (0, 0), float(smooth_px) / step)
        den = cv2.GaussianBlur(weight, (0, 0), float(smooth_px) / step)
        z_filled = np.where(den > 1e-3, num / np.maximum(den, 1e-3), 0.0)
    z_filled = np.where(z_filled > 0, z_filled, float(np.median(z[valid])))
    f, c = K[[0, 1], [0, 1]] * scale, (K[[0, 1], [2, 2]] + 0.5) * scale - 0.5  # OpenCV centres on the grid
    state = state_from_rgbd(torch.zeros(1, 3, hs, ws, dtype=torch.float64), torch.from_numpy(z_filled)[None, None],
                            f[0], f[1], c[0], c[1])
    normals = state.normals_cam[0].permute(1, 2, 0).numpy()
    if step > 1:
        normals = cv2.resize(normals, (w, h), interpolation=cv2.INTER_LINEAR)
        normals = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    else:
        normals = normals.copy()  # the state's tensor is not the caller's array
    normals[~valid] = np.nan
    return normals


def needs_normals(stack: Stack) -> bool:
    """Whether an effect of the stack reads surface normals (it raises MissingInputError naming normals_cam on a
    state without them)."""
    one = torch.ones(1, 1, 1, 1, dtype=torch.float64)
    state = FormationState(direct=torch.ones(1, 3, 1, 1, dtype=torch.float64), range_m=2 * one, depth_m=2 * one,
                           pixel_uv=torch.full((1, 2, 1, 1), 0.5, dtype=torch.float64), image_wh=(2, 2),
                           points_cam=torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64).view(1, 3, 1, 1),
                           frame_index=torch.zeros(1, dtype=torch.long))
    try:
        with torch.no_grad():
            stack.to(torch.float64).render(state)
    except MissingInputError as exc:
        return "normals_cam" in str(exc)
    return False


def affine_state(state: FormationState) -> FormationState:
    """``state`` as :func:`affine_images` renders it: J = 0 then J = 1 in one batch of twice its size (the fields of
    one image are left to broadcast over both, so its range and position terms are computed once; a batch of
    several has each field repeated)."""
    direct = torch.cat([torch.zeros_like(state.direct), torch.ones_like(state.direct)])
    b = state.direct.shape[0]
    doubled = {} if b == 1 else {
        f.name: torch.cat([t, t]) for f in fields(state)
        if f.name not in ("direct", "backscatter") and isinstance(t := getattr(state, f.name), torch.Tensor)
        and t.ndim > 0 and t.shape[0] == b}
    return state.replace(direct=direct, backscatter=None, **doubled)


def affine_images(stack: Stack, state: FormationState,
                  doubled: FormationState | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(A, C) of y = A J + C, (B,3,H,W): the stack rendered at J = 1 and J = 0, in one render of
    :func:`affine_state` (``doubled``: that state, made once by a caller that renders the same views again). The
    whole stack, its output map included (callers that linearise take :meth:`Stack.output_map`'s rest first)."""
    both = stack.render(affine_state(state) if doubled is None else doubled)
    b = both.shape[0] // 2
    return both[b:] - both[:b], both[:b]


def inverse_fields(range_m: np.ndarray, stack: Stack | list[dict], K: np.ndarray | None = None,
                   frame_index: int | Sequence[int] = 0, normals_cam: np.ndarray | None = None,
                   normal_smooth_px: float = 24.0,
                   dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """(A, C, valid): the fields of y = A J + C at every pixel of a range map (with an output map, of T^-1(y) = A J + C:
    the module docstring), A and C (1,3,H,W) tensors of ``dtype``
    (float32 is twice as fast, for the restorer; float64 for the physics correction), ``valid``
    (H,W) where the map holds range (elsewhere A and C are those of a 1 m range: mark those pixels, never use them).

    range_m: (H,W) metres along the ray; NaN or <= 0 = no range.
    stack:   a :class:`Stack` or its configuration.
    K:       (3,3) intrinsics; gives effects the camera-frame points, depth and surface normals (needed by e.g.
             ``artificial_light``: A = k/V exp(-eta r) E(X, n), E the lights' irradiance); without it depth = range
             and no points (an effect that needs them raises :class:`MissingInputError`).
    normals_cam: (H,W,3) unit normals in the camera frame (e.g. of a fused mesh); None with K:
             :func:`normals_from_range` of ``range_m`` smoothed by ``normal_smooth_px``, when the stack reads normals.
    frame_index: the frame's index in the survey: the row that parameters held per frame take; several: the
             fields of the same pixels in each of those frames, a batch of them (B,3,H,W)."""
    if not isinstance(stack, Stack):
        stack = Stack.from_config(stack)
    stack = stack.output_map()[0]
    r = clean_range(range_m)
    h, w = r.shape
    valid = np.isfinite(r)
    r_filled = np.where(valid, r, 1.0)
    fields = {}
    if K is not None:
        rays = rays_cam(np.asarray(K, np.float64), h, w)
        pc = rays / np.linalg.norm(rays, axis=-1, keepdims=True) * r_filled[..., None]
        fields["points_cam"] = torch.from_numpy(pc.transpose(2, 0, 1)[None].copy())
        fields["depth_m"] = torch.from_numpy(pc[..., 2][None, None].copy())
        if normals_cam is not None or needs_normals(stack):
            n = normals_from_range(r, K, normal_smooth_px) if normals_cam is None else \
                np.asarray(normals_cam, np.float64)
            n = np.where(np.isfinite(n), n, np.array([0.0, 0.0, -1.0]))
            fields["normals_cam"] = torch.from_numpy(n.transpose(2, 0, 1)[None].copy())
    else:
        fields["depth_m"] = torch.from_numpy(r_filled[None, None].copy())
    frames = torch.as_tensor(np.atleast_1d(np.asarray(frame_index, np.int64)))
    b = len(frames)
    state = FormationState(direct=torch.zeros(b, 3, h, w, dtype=dtype),
                           range_m=torch.from_numpy(r_filled[None, None].copy()).to(dtype).expand(b, 1, h, w),
                           pixel_uv=pixel_grid(h, w, b, dtype), image_wh=(w, h),
                           valid=torch.from_numpy(valid)[None, None].expand(b, 1, h, w), frame_index=frames,
                           **{k: v.to(dtype).expand(b, *v.shape[1:]) for k, v in fields.items()})
    stack = stack.to(dtype)
    with torch.no_grad():
        a, c = affine_images(stack, state)
    return a, c, valid


#: The probe :func:`frame_affines` evaluates both stacks on: (rows, columns) of pixels, ranges spread over 0.5-6 m.
PROBE_HW = (6, 8)


def frame_affines(stack: Stack, base: Stack, frames: Sequence[int], K: np.ndarray | None, height: int, width: int,
                  tol: float = 1e-6) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Per frame of ``frames``, (s, t), each (3,): a stack's fields at that survey frame as those of ``base`` (the
    same stack without its effects that hold a value per frame) mapped by y -> s y + t per channel, A_f = s A and
    C_f = s C + t, as a gain or exposure per frame acts (``frame_gain``: s = exp(g'_f), t = 0). The inverse is then
    the base's applied to (I - t) / s. Measured on a probe of ``PROBE_HW`` pixels of an image of ``height`` x
    ``width`` with intrinsics K at ranges 0.5-6 m, the stack rendered there for every frame in one batch, the base
    once; None for a frame whose effects do not act so within ``tol`` (relative) anywhere on the probe (they vary over
    the image or with range: then the exact fields)."""
    from watergan.data import PinholeIntrinsics

    rows, cols = PROBE_HW
    probe_K = None if K is None else PinholeIntrinsics(*_intrinsics(K), width, height).resized(rows, cols).K
    r = np.linspace(0.5, 6.0, rows * cols).reshape(cols, rows).T.copy()  # ranges across rows and columns
    a_f, c_f, _ = inverse_fields(r, stack, probe_K, list(frames))
    a_b, c_b, _ = inverse_fields(r, base, probe_K, 0)
    s = (a_f / a_b).flatten(2)  # (B,3,P)
    t = (c_f - s.view_as(c_f) * c_b).flatten(2)
    out = []
    for s_k, t_k, c_k in zip(s, t, c_f, strict=True):
        scale = float(c_k.abs().max()) + 1e-12
        if float((s_k - s_k.mean(1, keepdim=True)).abs().max()) > tol * float(s_k.abs().max()) or \
                float((t_k - t_k.mean(1, keepdim=True)).abs().max()) > tol * scale:
            out.append(None)
        else:
            out.append((s_k.mean(1).numpy(), t_k.mean(1).numpy()))
    return out


#: The grid of :class:`FieldTable`: (rows, columns) of pixel positions, corner to corner.
LUT_POSITIONS = (49, 65)
#: The grid's step in range, metres.
LUT_RANGE_STEP_M = 0.05
#: A table's range span is widened by this on each side (metres) and rounded outwards to multiples of
#: ``LUT_RANGE_ROUND_M``, so that the next frames' ranges, nearer or farther, are still covered: a survey's frames
#: then share one table instead of rebuilding it as each new extreme comes.
LUT_RANGE_MARGIN_M = 1.0
LUT_RANGE_ROUND_M = 0.5


def _intrinsics(K: np.ndarray | None) -> tuple[float, float, float, float] | None:
    """(fx, fy, cx, cy) of a 3x3 camera matrix (None: None)."""
    return None if K is None else (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))


@dataclass
class FieldTable:
    """The inverse's log gain g = -ln A and offset o = -C / A per channel of a stack, on a grid of pixel positions
    (``LUT_POSITIONS``, corner to corner) by ranges (``r_lo_m`` to ``r_hi_m`` every ``LUT_RANGE_STEP_M`` or less),
    for images of one size and camera, interpolated trilinearly in (x, y, r) at each pixel (:meth:`sample`). For
    stacks whose fields depend on the pixel's position and range alone (not on surface normals: check
    :func:`needs_normals`). With K the grid's points and depths come from the pixels' rays, as in
    :func:`inverse_fields`. The fields are smooth in all three (exp(eta r), polynomial falloffs), so a coarse grid
    interpolates them closely (its accuracy on the demo: benchmarks/RESULTS/corrections.md). A table is built once and
    sampled for every frame it covers: building one evaluates the stack at 100k-300k grid points.

    Most stacks' fields are sums of a few products of a function of range and a function of position (attenuation
    and backscatter in range times falloffs and gains over the image): per channel, the table's (range x position)
    matrix is then of low rank, T = sum_k U_k(r) V_k(x, y). Where ``LOW_RANK_MAX`` terms reproduce the table within
    ``LOW_RANK_TOL``, :meth:`sample` evaluates that sum instead of trilinear interpolation: the V_k bilinear at each
    pixel (once per image size), the U_k looked up every ``CURVE_STEP_M`` of range: the same values to the tolerance
    and the curves' step, for less work per pixel (speeds: benchmarks/RESULTS/speed-and-scale.md)."""

    table: torch.Tensor
    """(1,6,R,rows,cols) float32: g then o per channel."""
    width: int
    height: int
    r_lo_m: float
    r_hi_m: float
    K: tuple[float, float, float, float] | None
    """The intrinsics (fx, fy, cx, cy) the table was built with (None: depth = range)."""
    curves: torch.Tensor | None = None
    """(6k, n) float32: the range functions U_k of each channel (:func:`factorised`) every ``CURVE_STEP_M`` from
    ``r_lo_m``; None: the table is not of low rank."""
    maps: torch.Tensor | None = None
    """(1, 6k, rows, cols) float32: the position functions V_k on the grid, beside ``curves``."""
    _grid_xy: torch.Tensor | None = field(default=None, repr=False)
    _maps_hw: torch.Tensor | None = field(default=None, repr=False)

    @classmethod
    def build(cls, stack: Stack, width: int, height: int, K: np.ndarray | None, r_lo_m: float, r_hi_m: float,
              positions: tuple[int, int] = LUT_POSITIONS, range_step_m: float = LUT_RANGE_STEP_M) -> FieldTable:
        """The table of ``stack`` for ``width`` x ``height`` images with intrinsics K (3x3, or None), over ranges
        ``r_lo_m``..``r_hi_m`` (metres)."""
        w, h = width, height
        r_hi_m = max(r_hi_m, r_lo_m + 1e-3)
        rows, cols = positions
        xs = torch.linspace(0.0, w - 1.0, cols, dtype=torch.float64)
        ys = torch.linspace(0.0, h - 1.0, rows, dtype=torch.float64)
        rs = torch.linspace(r_lo_m, r_hi_m, max(2, int(np.ceil((r_hi_m - r_lo_m) / range_step_m)) + 1),
                            dtype=torch.float64)
        r_grid, y_grid, x_grid = torch.meshgrid(rs, ys, xs, indexing="ij")  # (ranges, rows, cols)
        shape = (1, 1, len(rs) * rows, cols)
        uv = torch.stack([(x_grid + 0.5) / w, (y_grid + 0.5) / h]).reshape(1, 2, len(rs) * rows, cols)
        fields = {"depth_m": r_grid.reshape(shape)}
        if K is not None:
            K = np.asarray(K, np.float64)
            ray = torch.stack([(x_grid - K[0, 2]) / K[0, 0], (y_grid - K[1, 2]) / K[1, 1], torch.ones_like(x_grid)])
            points = ray / vector_length(ray, 0) * r_grid
            fields = {"points_cam": points.reshape(1, 3, len(rs) * rows, cols), "depth_m": points[2].reshape(shape)}
        state = FormationState(direct=torch.zeros(1, 3, len(rs) * rows, cols, dtype=torch.float64),
                               range_m=r_grid.reshape(shape), pixel_uv=uv, image_wh=(w, h),
                               frame_index=torch.tensor([0]), **fields)
        with torch.no_grad():  # with an output map, the fields of T^-1(y) (the module docstring)
            a, c = affine_images(stack.output_map()[0].to(torch.float64), state)
        a = a.clamp_min(1e-12)
        table = torch.cat([-torch.log(a), -c / a], dim=1).reshape(1, 6, len(rs), rows, cols)
        return cls(table.float(), w, h, float(rs[0]), float(rs[-1]), _intrinsics(K), *factorised(table[0], rs))

    def serves(self, height: int, width: int, K: np.ndarray | None) -> bool:
        """Whether the table is for images of this size and these intrinsics (3x3, or None)."""
        return (height, width) == (self.height, self.width) and _intrinsics(K) == self.K

    def covers(self, range_m: torch.Tensor, K: np.ndarray | None) -> bool:
        """Whether the table serves range maps (B,1,H,W) of these intrinsics: same size and camera, ranges within."""
        return (self.serves(*range_m.shape[-2:], K) and float(range_m.min()) >= self.r_lo_m
                and float(range_m.max()) <= self.r_hi_m)

    def sample(self, range_m: torch.Tensor) -> torch.Tensor:
        """(B,6,H,W) the fields at every pixel of range maps (B,1,H,W) (metres, holes filled), in their dtype and
        on their device; ranges outside the table take its nearest range."""
        b, _, h, w = range_m.shape
        if self.curves is not None:
            return self._sample_factorised(range_m)
        if self._grid_xy is None:  # the pixels' places in the table, the same for every frame
            py, px = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                                    indexing="ij")
            self._grid_xy = torch.stack([2.0 * px / max(w - 1, 1) - 1.0, 2.0 * py / max(h - 1, 1) - 1.0], dim=-1)
        xy = self._grid_xy.to(range_m.device, range_m.dtype)
        rz = 2.0 * (range_m[:, 0] - self.r_lo_m) / (self.r_hi_m - self.r_lo_m) - 1.0
        grid = torch.cat([xy.expand(b, h, w, 2), rz[..., None]], dim=-1)
        table = self.table.to(range_m.device, range_m.dtype)
        return torch.nn.functional.grid_sample(table.expand(b, -1, -1, -1, -1), grid[:, None], mode="bilinear",
                                               padding_mode="border", align_corners=True)[:, :, 0]

    def _sample_factorised(self, range_m: torch.Tensor) -> torch.Tensor:
        """:meth:`sample` as sum_k U_k(r) V_k(x, y) per channel (the class docstring)."""
        b, _, h, w = range_m.shape
        device, dtype = range_m.device, range_m.dtype
        if self._maps_hw is None or self._maps_hw.shape[-2:] != (h, w):  # V_k at every pixel, as trilinear takes them
            self._maps_hw = torch.nn.functional.interpolate(self.maps, size=(h, w), mode="bilinear",
                                                            align_corners=True)[0]
        maps, curves = self._maps_hw.reshape(-1, h * w).to(device, dtype), self.curves.to(device, dtype)
        terms = len(curves) // 6
        index = ((range_m.reshape(-1) - self.r_lo_m) / CURVE_STEP_M).round_().clamp_(0, curves.shape[1] - 1).int()
        values = torch.index_select(curves, 1, index).view(6, terms, b, h * w)  # every curve in one gather
        maps = maps.view(6, terms, 1, h * w)
        out = values[:, 0] * maps[:, 0]
        for k in range(1, terms):
            out.addcmul_(values[:, k], maps[:, k])
        return out.transpose(0, 1).reshape(b, 6, h, w)


#: Largest number of range-by-position products :func:`factorised` takes per channel.
LOW_RANK_MAX = 3
#: Largest difference from the table (log gain, linear offset) that the products may leave.
LOW_RANK_TOL = 1e-5
#: The range functions' step in :meth:`FieldTable.sample`, metres: within half of it a field moves by eta * 0.5 mm
#: (a few 1e-4 of the gain at eta = 0.5 /m).
CURVE_STEP_M = 1e-3


def factorised(table: torch.Tensor, ranges_m: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """(curves (6k, n), maps (1, 6k, rows, cols)), both float32, of a field table (6, R, rows, cols) at ``ranges_m``
    (R,): per channel the fewest terms k <= ``LOW_RANK_MAX`` (the same for every channel) whose truncated singular
    value decomposition T_c = sum_k U_ck(r) V_ck(x, y) is within ``LOW_RANK_TOL`` of the table everywhere, U
    resampled every ``CURVE_STEP_M`` by linear interpolation; (None, None) when no such k exists."""
    channels, count, rows, cols = table.shape
    svds = [leading_svd(table[c].reshape(count, rows * cols), LOW_RANK_MAX) for c in range(channels)]
    for k in range(1, LOW_RANK_MAX + 1):
        error = max(float(((u[:, :k] * s[:k]) @ vh[:k] - table[c].reshape(count, -1)).abs().max())
                    for c, (u, s, vh) in enumerate(svds))
        if error <= LOW_RANK_TOL:
            break
    else:
        return None, None
    fine = np.arange(float(ranges_m[0]), float(ranges_m[-1]) + CURVE_STEP_M, CURVE_STEP_M)
    r = ranges_m.numpy()
    curves = [np.interp(fine, r, (u[:, j] * s[j]).numpy()) for u, s, _ in svds for j in range(k)]
    maps = torch.cat([vh[:k] for _, _, vh in svds]).reshape(1, channels * k, rows, cols)
    return torch.from_numpy(np.stack(curves)).float(), maps.float()


def leading_svd(m: torch.Tensor, k: int, oversample: int = 2,
                power_iterations: int = 2) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(u, s, vh) of the leading k + ``oversample`` singular triplets of an (R, P) matrix (fewer where it is smaller),
    by a randomised range finder (Halko, Martinsson and Tropp 2011: Q = orth(M Omega), ``power_iterations`` times
    Q = orth(M M^T Q), then the SVD of Q^T M) with a fixed seed, so the same table gives the same factors. Where the
    singular values fall fast, as the water's tables' do, the leading triplets match a full SVD's to rounding, at a
    tenth of its cost; :func:`factorised` checks the truncation against the table itself either way."""
    q = min(k + oversample, *m.shape)
    omega = torch.randn(m.shape[1], q, generator=torch.Generator().manual_seed(0), dtype=m.dtype)
    basis = torch.linalg.qr(m @ omega)[0]
    for _ in range(power_iterations):
        basis = torch.linalg.qr(m @ (m.T @ basis))[0]
    u, s, vh = torch.linalg.svd(basis.T @ m, full_matrices=False)
    return basis @ u, s, vh


def range_span(range_m: torch.Tensor, margin_m: float = LUT_RANGE_MARGIN_M,
               round_m: float = LUT_RANGE_ROUND_M) -> tuple[float, float]:
    """(least, largest) range of maps (metres), widened by ``margin_m`` and rounded outwards to multiples of
    ``round_m`` (least >= 0)."""
    lo, hi = float(range_m.min()) - margin_m, float(range_m.max()) + margin_m
    return max(0.0, np.floor(lo / round_m) * round_m), np.ceil(hi / round_m) * round_m


def linearise_image(image: np.ndarray, stack: Stack | list[dict]) -> np.ndarray:
    """T^-1(image) (float64, the image's shape) of the stack's output map (the module docstring); the image itself
    (as float64) when the stack has none."""
    curve = (stack if isinstance(stack, Stack) else Stack.from_config(stack)).output_map()[1]
    image = np.asarray(image, np.float64)
    if curve is None:
        return image
    with torch.no_grad():
        return curve.to(torch.float64).linearise(torch.from_numpy(image)).numpy()


SIGNAL_FLOOR = 0.01
"""Share s of a pixel's own signal a correction keeps where the veil it removes reaches the pixel's value:
J = max(I - C, s I) / A (with the log gain g = -ln A and offset o = -C / A: max(exp(g) I + o, s exp(g) I)). A pixel
darker than the estimated veil (a shadow, a dark object, the veil over-estimated there) stays dark with its texture
instead of turning black."""


def correct_physics(image: np.ndarray, range_m: np.ndarray, stack: Stack | list[dict],
                    K: np.ndarray | None = None, frame_index: int = 0, normals_cam: np.ndarray | None = None,
                    normal_smooth_px: float = 24.0, signal_floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Invert a stack that is affine in the in-air colour, pixel by pixel with each pixel's range:
    J = (I - C) / A, A = render(J = 1) - render(J = 0), C = render(J = 0); for the default stack
    J = (I / k * V - B_inf (1 - exp(-beta r))) * exp(eta r). A stack ending in an output map T (a tone curve) has
    I replaced by T^-1(I) (:func:`linearise_image`) and A, C those of the rest: exact again.

    image:   (H,W,3) raw linear RGB.
    range_m: (H,W) metres along the ray; NaN or <= 0 = no range.
    stack:   a :class:`Stack` or its configuration (e.g. the water estimate's stack).
    K:       (3,3) intrinsics; gives effects the camera-frame points, depth and surface normals (needed by e.g.
             ``artificial_light``: J = (I - C) / A with A = k/V exp(-eta r) E(X, n), E the lights' irradiance);
             without it depth = range and no points.
    normals_cam: (H,W,3) unit normals in the camera frame (e.g. of a fused mesh); None with K:
             :func:`normals_from_range` of ``range_m`` smoothed by ``normal_smooth_px``.
    frame_index: the frame's index in the survey (the water estimate's frames list): the row that parameters held
             per frame take.
    signal_floor: s > 0 gives J = max(I - C, s I) / A, as the correct stage writes it (:data:`SIGNAL_FLOOR`).
    Returns (J (H,W,3) float32 linear, unclipped, NaN where there is no range; valid (H,W) bool). Pixels
    without range are marked, never guessed: fill their range first (e.g. from a fused mesh) to correct them."""
    a, c, valid = inverse_fields(range_m, stack, K, frame_index, normals_cam, normal_smooth_px)
    a, c = a[0].permute(1, 2, 0).numpy(), c[0].permute(1, 2, 0).numpy()
    image = linearise_image(image, stack)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.maximum(image - c, signal_floor * image) / a if signal_floor > 0 else (image - c) / a
    out[~valid] = np.nan
    return out.astype(np.float32), valid
