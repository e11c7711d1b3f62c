"""Simulated sites: a seafloor heightfield with rocks (or reef mounds), textured from real photographs,
optionally covered in part by colonies of other colours (corals, algae, sponges), and a 24-patch
colour-checker board lying on it.

World frame: z up, metres. The seafloor is z = h(x, y) over a rectangle centred on the origin;
it is exactly flat (z = 0) in a disc around the board, which lies ``lift_m`` above it, face up.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d

from watergan.io import linear_to_srgb, srgb_to_linear

#: Photographs that scikit-image ships (offline), usable as albedo detail.
TEXTURES = ("gravel", "grass", "brick", "coffee", "immunohistochemistry", "rocket", "moon")

COLOURCHECKER = "ColorChecker24 - After November 2014"

#: ``Part.kind`` of the seafloor and of the board.
SEAFLOOR, BOARD = "seafloor", "board"


@dataclass(frozen=True)
class BoardConfig:
    """A 6 x 4 colour-checker board with black gaps, face up on the seafloor."""

    centre_xy_m: tuple[float, float] = (0.35, -0.45)
    """Board centre in world x, y, metres."""
    yaw_deg: float = 18.0
    """Rotation of the board's long (column) axis from world +x about +z, degrees."""
    width_m: float = 0.6
    """Board width along its long axis (6 patches and 7 gaps), metres."""
    gap_ratio: float = 0.2
    """Width of a black gap divided by a patch's side."""
    lift_m: float = 0.02
    """Height of the board face above the (flat) seafloor under it, metres."""
    gap_albedo: float = 0.02
    """Linear albedo of the black gaps and border (all channels)."""

    @property
    def patch_m(self) -> float:
        """Side of one square patch, metres: width = 6 p + 7 g p."""
        return self.width_m / (6 + 7 * self.gap_ratio)

    @property
    def gap_m(self) -> float:
        return self.gap_ratio * self.patch_m

    @property
    def height_m(self) -> float:
        """Board extent along its short (row) axis, metres: 4 patches and 5 gaps."""
        return 4 * self.patch_m + 5 * self.gap_m


@dataclass(frozen=True)
class SceneConfig:
    """A seafloor site: size, relief, rocks, albedo texture and the colour board."""

    size_x_m: float = 14.0
    """Extent of the seafloor along world x, metres (centred on 0)."""
    size_y_m: float = 10.0
    """Extent of the seafloor along world y, metres (centred on 0)."""
    grid_spacing_m: float = 0.05
    """Spacing of the heightfield's vertices, metres."""
    relief_m: float = 0.12
    """Standard deviation of the gentle relief (sum of random plane waves), metres."""
    relief_wavelength_m: tuple[float, float] = (1.5, 6.0)
    """Range of the relief waves' wavelengths, metres."""
    n_rocks: int = 7
    """Number of rocks (smooth elliptical bumps), placed away from the board."""
    rock_radius_m: tuple[float, float] = (0.15, 0.45)
    """Range of rock radii (Gaussian sigma of the bump), metres."""
    rock_height_m: tuple[float, float] = (0.08, 0.3)
    """Range of rock heights, metres."""
    texel_m: float = 0.005
    """Size of one texture pixel on the seafloor (planar mapping by world x, y), metres."""
    detail_texture: str = "gravel"
    """Main detail photograph, one of TEXTURES."""
    overlay_texture: str = "grass"
    """Second photograph, mapped rotated and at another scale to break the repetition."""
    tint_linear: tuple[float, float, float] = (0.42, 0.35, 0.24)
    """Mean linear albedo of the sediment (sandy by default)."""
    rock_tint_linear: tuple[float, float, float] = (0.16, 0.15, 0.13)
    """Mean linear albedo of the rocks."""
    colour_variation: float = 0.18
    """Relative amplitude of the low-frequency (metre-scale) albedo variation."""
    detail_contrast: float = 1.2
    """Exponent on the normalised detail photograph (larger = stronger texture)."""
    board: BoardConfig | None = field(default_factory=BoardConfig)
    """The colour board, or None for a site without one."""
    cover_palette_linear: tuple[tuple[float, float, float], ...] = ()
    """Linear albedos of the colonies (corals, algae, sponges) that cover part of the floor; empty: none."""
    cover_fraction: float = 0.0
    """Share of the floor the colonies cover (0..1); rocks and mounds are covered first."""
    cover_patch_m: float = 0.5
    """Correlation length of the colony patches, metres (a colony's typical size)."""


@dataclass(frozen=True)
class Part:
    """One triangle mesh of the scene (its index is the ray caster's geometry id)."""

    kind: str
    vertices: np.ndarray       # (V,3) float32, world metres
    triangles: np.ndarray      # (T,3) uint32
    vertex_normals: np.ndarray  # (V,3) float32, unit, world


@dataclass(frozen=True)
class Board:
    """The colour board's truth. Patch ``i`` is row ``i // 6``, column ``i % 6`` of the chart."""

    names: list[str]
    corners_world: np.ndarray  # (24,4,3) metres; per patch: top-left, top-right, bottom-right, bottom-left
    linear_rgb: np.ndarray     # (24,3) linear sRGB albedo 0..1
    srgb: np.ndarray           # (24,3) sRGB-encoded 0..1
    outline_world: np.ndarray  # (4,3) the board's outer corners, same order
    config: BoardConfig

    def to_json(self) -> dict:
        return {
            "chart": COLOURCHECKER,
            "corner_order": "top-left, top-right, bottom-right, bottom-left (board rows run top to bottom)",
            "patch_side_m": self.config.patch_m,
            "gap_m": self.config.gap_m,
            "outline_world": self.outline_world.tolist(),
            "patches": [
                {"index": i, "name": n, "corners_world": self.corners_world[i].tolist(),
                 "linear_rgb": self.linear_rgb[i].tolist(), "srgb": self.srgb[i].tolist()}
                for i, n in enumerate(self.names)
            ],
        }


def colourchecker_colours() -> tuple[list[str], np.ndarray]:
    """The 24 patch names and linear sRGB colours (0..1, clipped): xyY -> XYZ (chart illuminant)
    -> linear sRGB (D65, Bradford adaptation)."""
    import colour

    checker = colour.CCS_COLOURCHECKERS[COLOURCHECKER]
    names = list(checker.data)
    xyz = colour.xyY_to_XYZ(np.array([checker.data[n] for n in names]))
    rgb = colour.XYZ_to_RGB(xyz, "sRGB", illuminant=checker.illuminant,
                            chromatic_adaptation_transform="Bradford", apply_cctf_encoding=False)
    return names, np.clip(rgb, 0.0, 1.0)


def _board_frame(cfg: BoardConfig) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (2,2) from board (u along columns, v along rows upward) to world x, y, and centre."""
    a = np.deg2rad(cfg.yaw_deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]), np.asarray(cfg.centre_xy_m, float)


def make_board(cfg: BoardConfig) -> Board:
    names, linear = colourchecker_colours()
    rot, centre = _board_frame(cfg)
    p, g = cfg.patch_m, cfg.gap_m
    half_w, half_h = cfg.width_m / 2, cfg.height_m / 2
    corners = []
    for i in range(24):
        row, col = divmod(i, 6)
        u0 = -half_w + g + col * (p + g)
        v0 = half_h - g - row * (p + g)
        corners.append([(u0, v0), (u0 + p, v0), (u0 + p, v0 - p), (u0, v0 - p)])
    outline = np.array([(-half_w, half_h), (half_w, half_h), (half_w, -half_h), (-half_w, -half_h)])

    def to_world(uv: np.ndarray) -> np.ndarray:
        xy = uv @ rot.T + centre
        return np.concatenate([xy, np.full(xy.shape[:-1] + (1,), cfg.lift_m)], axis=-1)

    return Board(names=names, corners_world=to_world(np.array(corners)), linear_rgb=linear,
                 srgb=linear_to_srgb(linear), outline_world=to_world(outline), config=cfg)


@functools.cache
def load_texture(name: str, contrast: float = 1.0) -> np.ndarray:
    """A scikit-image photograph as a seamless linear detail map D^contrast, (H,W,3) float32, where D
    is the photograph normalised to mean 1 (grey photographs repeated over the channels; colour
    ones keep their hue). Seamless: T = w P + (1 - w) roll(P, H/2, W/2) with w = sin^2(pi x/W)
    sin^2(pi y/H), which is 0 on the tile border, where the rolled copy continues across the wrap;
    the blend is rescaled to the photograph's contrast."""
    import skimage.data

    if name not in TEXTURES:
        raise ValueError(f"unknown texture '{name}'; choose one of {', '.join(TEXTURES)}")
    image = getattr(skimage.data, name)().astype(np.float64) / 255.0
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    linear = srgb_to_linear(image[..., :3])
    linear = cv2.GaussianBlur(linear, (0, 0), 0.6)  # soften JPEG blocking before magnification
    h, w = linear.shape[:2]
    weight = (np.sin(np.pi * (np.arange(h) + 0.5) / h)[:, None] ** 2
              * np.sin(np.pi * (np.arange(w) + 0.5) / w)[None, :] ** 2)[..., None]
    blend = weight * linear + (1 - weight) * np.roll(linear, (h // 2, w // 2), axis=(0, 1))
    mean = linear.mean(axis=(0, 1))
    spread = np.sqrt(weight**2 + (1 - weight) ** 2)  # std of a blend of two independent patterns
    seamless = mean + (blend - mean) / spread
    detail = np.power((seamless / max(linear.mean(), 1e-6)).clip(0.02, None), contrast)
    return np.ascontiguousarray(detail, dtype=np.float32)


@dataclass(frozen=True)
class _Rocks:
    centres: np.ndarray  # (K,2)
    radii: np.ndarray    # (K,2) sigma along the rock's own axes
    angles: np.ndarray   # (K,)
    heights: np.ndarray  # (K,)

    def bumps(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(K, ...) normalised bump shapes exp(-0.5 |A (p - c)|^2), 1 at a rock's top."""
        out = []
        for (cx, cy), (rx, ry), a in zip(self.centres, self.radii, self.angles, strict=True):
            dx, dy = x - cx, y - cy
            s = (np.cos(a) * dx + np.sin(a) * dy) / rx
            t = (-np.sin(a) * dx + np.cos(a) * dy) / ry
            out.append(np.exp(-0.5 * (s * s + t * t)))
        return np.array(out).reshape((len(self.heights),) + np.shape(x))


class Scene:
    """A built site: meshes (``parts``, ray-caster geometry id = index), analytic height, albedo.

    Build with :func:`build_scene`.
    """

    def __init__(self, config: SceneConfig, seed: int) -> None:
        self.config = config
        self.seed = seed
        rng = np.random.default_rng([seed, 11])
        c = config
        self.board = make_board(c.board) if c.board is not None else None
        # flat disc around the board: relief weight w = smoothstep over [r0, r0 + 1 m]
        if self.board is not None:
            self._flat_centre = np.asarray(c.board.centre_xy_m, float)
            self._flat_r0 = 0.5 * np.hypot(c.board.width_m, c.board.height_m) + 0.15
        # relief: sum of plane waves z = sum a_k cos(k . p + phi_k), scaled to std relief_m
        n_waves = 6
        wavelengths = rng.uniform(*c.relief_wavelength_m, n_waves)
        directions = rng.uniform(0, np.pi, n_waves)
        self._wave_k = (2 * np.pi / wavelengths)[:, None] * np.stack([np.cos(directions), np.sin(directions)], 1)
        self._wave_phase = rng.uniform(0, 2 * np.pi, n_waves)
        amps = wavelengths / wavelengths.sum()
        self._wave_amp = c.relief_m * amps / np.sqrt(0.5 * (amps**2).sum())
        self._rocks = self._place_rocks(rng)
        # albedo: a colour raster (sediment/rock tint x low-frequency variation) and texture placement
        self._base_spacing = 0.02
        self._base_origin = np.array([-c.size_x_m / 2 - 1.0, -c.size_y_m / 2 - 1.0])
        self._base = self._base_raster(rng)
        self._overlay_angle = rng.uniform(0, 2 * np.pi)
        self._overlay_scale = rng.uniform(1.3, 1.6)
        self._offsets = rng.uniform(0, 512, 4)
        if c.cover_palette_linear and c.cover_fraction > 0:  # drawn last: a site without colonies is unchanged
            self._base = self._cover(rng, self._base)
        self.parts = [self._seafloor_part()]
        if self.board is not None:
            self.parts.append(self._board_part())

    # ----- geometry -------------------------------------------------------------------------
    def _place_rocks(self, rng: np.random.Generator) -> _Rocks:
        c = self.config
        centres = []
        while len(centres) < c.n_rocks:
            half = np.array([c.size_x_m / 2 - 0.5, c.size_y_m / 2 - 0.5])
            p = rng.uniform(-half, half)
            if self.board is None or np.linalg.norm(p - self._flat_centre) > self._flat_r0 + 1.2:
                centres.append(p)
        k = c.n_rocks
        r = rng.uniform(*c.rock_radius_m, k)
        return _Rocks(centres=np.array(centres).reshape(k, 2),
                      radii=np.stack([r, r * rng.uniform(0.6, 1.0, k)], 1),
                      angles=rng.uniform(0, np.pi, k), heights=rng.uniform(*c.rock_height_m, k))

    def _base_raster(self, rng: np.random.Generator) -> np.ndarray:
        """(rows, cols, 3) linear colour on a ``_base_spacing`` grid: tint x (1 + v (L + 0.35 C)), with
        L, C smooth unit-variance noise fields (correlation length ~1 m) and tint blended from
        sediment to rock by the rock mask."""
        c = self.config
        coarse = 0.4
        shape = (int((c.size_y_m + 2) / coarse) + 2, int((c.size_x_m + 2) / coarse) + 2)
        lum = cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 2.0)
        chroma = cv2.GaussianBlur(rng.standard_normal(shape + (3,)), (0, 0), 3.0)
        lf = 1 + c.colour_variation * (lum[..., None] / lum.std() + 0.35 * chroma / chroma.std())
        rows = int((c.size_y_m + 2) / self._base_spacing) + 1
        cols = int((c.size_x_m + 2) / self._base_spacing) + 1
        gx, gy = np.meshgrid(self._base_origin[0] + self._base_spacing * np.arange(cols),
                             self._base_origin[1] + self._base_spacing * np.arange(rows))
        lf = cv2.resize(lf.astype(np.float32), (cols, rows), interpolation=cv2.INTER_CUBIC).clip(0.3, None)
        rock = self._rocks.bumps(gx, gy).max(0) if len(self._rocks.heights) else np.zeros_like(gx)
        rock = np.clip((rock - 0.25) / 0.3, 0.0, 1.0)[..., None]
        tint = (1 - rock) * np.asarray(c.tint_linear) + rock * np.asarray(c.rock_tint_linear)
        return (tint * lf).astype(np.float32)

    def _cover(self, rng: np.random.Generator, base: np.ndarray) -> np.ndarray:
        """The colour raster with colonies: where a smooth field F = N_0 + 2 m (N_0 unit-variance noise of
        correlation length ``cover_patch_m``, m the rock/mound mask) exceeds its (1 - ``cover_fraction``)
        quantile, the tint is the palette colour k = argmax_k N_k (K more such fields, one per colour),
        times the raster's own low-frequency variation (base / tint). Outside the board's flat disc only."""
        c = self.config
        rows, cols = base.shape[:2]
        coarse = c.cover_patch_m / 3
        shape = (int((c.size_y_m + 2) / coarse) + 2, int((c.size_x_m + 2) / coarse) + 2)
        k = len(c.cover_palette_linear)

        def field() -> np.ndarray:
            noise = cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 1.5)
            return cv2.resize((noise / noise.std()).astype(np.float32), (cols, rows), interpolation=cv2.INTER_CUBIC)

        gx, gy = np.meshgrid(self._base_origin[0] + self._base_spacing * np.arange(cols),
                             self._base_origin[1] + self._base_spacing * np.arange(rows))
        mound = self._rocks.bumps(gx, gy).max(0) if len(self._rocks.heights) else np.zeros_like(gx)
        cover = field() + 2.0 * mound
        covered = (cover > np.quantile(cover, 1 - c.cover_fraction)) & (self._flat_weight(gx, gy) > 0)
        colour = np.argmax(np.stack([field() for _ in range(k)]), axis=0)
        palette = np.asarray(c.cover_palette_linear, np.float32)
        rock = np.clip((mound - 0.25) / 0.3, 0.0, 1.0)[..., None]
        tint = (1 - rock) * np.asarray(c.tint_linear) + rock * np.asarray(c.rock_tint_linear)
        variation = base / np.maximum(tint, 1e-6)
        return np.where(covered[..., None], palette[colour] * variation, base).astype(np.float32)

    def _flat_weight(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """0 in the disc around the board, rising smoothly (smoothstep) to 1 over the next metre."""
        if self.board is None:
            return np.ones(np.shape(x))
        d = np.hypot(x - self._flat_centre[0], y - self._flat_centre[1])
        s = np.clip(d - self._flat_r0, 0.0, 1.0)
        return s * s * (3 - 2 * s)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Seafloor height z = w(x,y) [sum_k a_k cos(k_k . p + phi_k) + sum_j h_j bump_j(x,y)], metres,
        where w is the flat-disc weight around the board."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        phase = self._wave_k[:, 0, None] * x.ravel() + self._wave_k[:, 1, None] * y.ravel() + self._wave_phase[:, None]
        relief = (self._wave_amp[:, None] * np.cos(phase)).sum(0).reshape(x.shape)
        rocks = np.tensordot(self._rocks.heights, self._rocks.bumps(x, y), axes=1) if len(self._rocks.heights) else 0.0
        return self._flat_weight(x, y) * (relief + rocks)

    def _seafloor_part(self) -> Part:
        c = self.config
        nx = int(round(c.size_x_m / c.grid_spacing_m)) + 1
        ny = int(round(c.size_y_m / c.grid_spacing_m)) + 1
        xs = np.linspace(-c.size_x_m / 2, c.size_x_m / 2, nx)
        ys = np.linspace(-c.size_y_m / 2, c.size_y_m / 2, ny)
        gx, gy = np.meshgrid(xs, ys)
        z = self.height(gx, gy)
        dzdy, dzdx = np.gradient(z, ys, xs)
        normals = np.stack([-dzdx, -dzdy, np.ones_like(z)], -1)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b, cc, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        tris = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, cc], -1).reshape(-1, 3)])
        return Part(kind=SEAFLOOR, vertices=np.stack([gx, gy, z], -1).reshape(-1, 3).astype(np.float32),
                    triangles=tris.astype(np.uint32), vertex_normals=normals.reshape(-1, 3).astype(np.float32))

    def _board_part(self) -> Part:
        corners = self.board.outline_world.astype(np.float32)
        return Part(kind=BOARD, vertices=corners, triangles=np.array([[0, 3, 2], [0, 2, 1]], np.uint32),
                    vertex_normals=np.tile(np.array([0, 0, 1], np.float32), (4, 1)))

    @functools.cached_property
    def stacked_triangles(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every part's triangles in one array (vertex indices offset into the stacked vertex
        normals), the stacked vertex normals, and the index of each part's first triangle."""
        offsets = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        first = np.cumsum([0] + [len(p.triangles) for p in self.parts])[:-1]
        triangles = np.concatenate([p.triangles.astype(np.int64) + o
                                    for p, o in zip(self.parts, offsets[:-1], strict=True)])
        return triangles, np.concatenate([p.vertex_normals for p in self.parts]), first

    # ----- albedo ---------------------------------------------------------------------------
    def albedo(self, points_world: np.ndarray, part_index: np.ndarray) -> np.ndarray:
        """Linear albedo (...,3) at world points (...,3) lying on ``parts[part_index]`` (...);
        points with another index (no hit) get 0."""
        lead = points_world.shape[:-1]
        points = points_world.reshape(-1, 3)
        index = np.asarray(part_index).reshape(-1)
        out = np.zeros((len(points), 3), np.float32)
        for i, part in enumerate(self.parts):
            mask = index == i
            if mask.any():
                sample = self._seafloor_albedo if part.kind == SEAFLOOR else self._board_albedo
                out[mask] = sample(points[mask])
        return out.reshape(lead + (3,))

    def _seafloor_albedo(self, p: np.ndarray) -> np.ndarray:
        """albedo = clip(base(x,y) D1^g D2^(g/2), 0, 0.9) for points (N,3): base is the colour raster
        (sediment/rock tint x low-frequency variation), D1, D2 the normalised photographs mapped
        planarly (texel ``texel_m``; D2 rotated and rescaled), g = ``detail_contrast``."""
        c = self.config
        n = len(p)
        block = 1024  # cv2.remap wants 2-D maps shorter than 32767 on each side
        rows = -(-n // block)
        x = np.zeros(rows * block, np.float32)
        y = np.zeros(rows * block, np.float32)
        x[:n], y[:n] = p[:, 0], p[:, 1]
        x, y = x.reshape(rows, block), y.reshape(rows, block)
        d1 = _sample_wrapped(load_texture(c.detail_texture, c.detail_contrast), x / c.texel_m + self._offsets[0],
                             -y / c.texel_m + self._offsets[1])
        ca, sa = np.cos(self._overlay_angle), np.sin(self._overlay_angle)
        s2 = c.texel_m * self._overlay_scale
        d2 = _sample_wrapped(load_texture(c.overlay_texture, 0.5 * c.detail_contrast),
                             (ca * x + sa * y) / s2 + self._offsets[2], (-sa * x + ca * y) / s2 + self._offsets[3])
        base = cv2.remap(self._base, ((x - self._base_origin[0]) / self._base_spacing).astype(np.float32),
                         ((y - self._base_origin[1]) / self._base_spacing).astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
        return np.clip(base * d1 * d2, 0.0, 0.9).reshape(-1, 3)[:n]

    def _board_albedo(self, p: np.ndarray) -> np.ndarray:
        """Patch colour inside a patch square, ``gap_albedo`` in the gaps and border."""
        cfg = self.board.config
        rot, centre = _board_frame(cfg)
        uv = (p[:, :2].astype(np.float64) - centre) @ rot
        pitch = cfg.patch_m + cfg.gap_m
        a = uv[:, 0] + cfg.width_m / 2 - cfg.gap_m    # from the first column's left edge
        b = cfg.height_m / 2 - cfg.gap_m - uv[:, 1]   # from the first row's top edge
        col, row = np.floor(a / pitch).astype(int), np.floor(b / pitch).astype(int)
        inside = ((col >= 0) & (col < 6) & (row >= 0) & (row < 4)
                  & (a - col * pitch < cfg.patch_m) & (b - row * pitch < cfg.patch_m))
        out = np.full((len(p), 3), cfg.gap_albedo, np.float32)
        out[inside] = self.board.linear_rgb[row[inside] * 6 + col[inside]]
        return out

    # ----- exports --------------------------------------------------------------------------
    def legacy_mesh(self) -> o3d.geometry.TriangleMesh:
        """All parts as one legacy open3d mesh with vertex normals and albedo vertex colours."""
        vertices, triangles, normals, colours = [], [], [], []
        offset = 0
        for i, part in enumerate(self.parts):
            vertices.append(part.vertices)
            triangles.append(part.triangles.astype(np.int64) + offset)
            normals.append(part.vertex_normals)
            colours.append(self.albedo(part.vertices, np.full(len(part.vertices), i)))
            offset += len(part.vertices)
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.concatenate(vertices).astype(np.float64)),
                                         o3d.utility.Vector3iVector(np.concatenate(triangles).astype(np.int32)))
        mesh.vertex_normals = o3d.utility.Vector3dVector(np.concatenate(normals).astype(np.float64))
        mesh.vertex_colors = o3d.utility.Vector3dVector(linear_to_srgb(np.concatenate(colours)))
        return mesh


def _sample_wrapped(texture: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear sample of a tiling texture at fractional (col, row) pixel coordinates."""
    h, w = texture.shape[:2]
    return cv2.remap(texture, np.mod(col, w).astype(np.float32), np.mod(row, h).astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def build_scene(config: SceneConfig, seed: int) -> Scene:
    """The site for ``config``; the same seed gives the same relief, rocks and texture placement."""
    if config.grid_spacing_m <= 0 or config.texel_m <= 0:
        raise ValueError("grid_spacing_m and texel_m must be positive")
    if not 0.0 <= config.cover_fraction <= 1.0 or config.cover_patch_m <= 0:
        raise ValueError("cover_fraction must be in 0..1 and cover_patch_m positive")
    for name in (config.detail_texture, config.overlay_texture):
        if name not in TEXTURES:
            raise ValueError(f"unknown texture '{name}'; choose one of {', '.join(TEXTURES)}")
    return Scene(config, seed)
