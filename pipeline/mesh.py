"""A 2.5D seafloor mesh, its texture and an orthophoto mosaic from the registered images.

Height field: points (the dense fused cloud when the dense stage made one, else the sparse SfM
points) are binned on a square grid of ``cell_m`` in the survey frame's x, y (z is up, see
pipeline.sfm); each occupied cell keeps its median height. The cell centres are triangulated
with a 2-D Delaunay triangulation (scipy) and triangles with an edge longer than
``max_edge_cells`` x ``cell_m`` are dropped (holes stay holes).

Texture = orthophoto: a north-up image (row 0 at the largest y) with ``texel_m`` metres per texel
over the mesh's x-y bounding box, snapped to the texel grid (texel (i, j) centred at (x0 + i t,
y1 - j t), x1 and y0 the last texel centres); planar UVs u = (x - x0) / (x1 - x0), v = (y - y0) /
(y1 - y0) run between the first and last texel centres (the exports shift them half a texel to the
glTF/OBJ convention, 0 and 1 at the image edges). Each image fills only the texels in the bounding
box of its footprint. The default texel is half the images' ground sampling: both resamplings
(image -> texture -> rendered view) are bilinear, and a texel at the ground sampling blurs visibly.
Each texel's surface point (x, y, z(x, y)) is projected into every registered image; its colour
is the weighted mean over the views that see it,

    w_view = (1 - rho^2)^p,   rho = |pixel - image centre| / half-diagonal,

a high power p (``blend_power``) picks the most central view almost exclusively while still
blending smoothly across the seams where two views are equally central. Occlusion is not tested
(a 2.5D seafloor seen from above is assumed).

Outputs (``07_mesh/``): ``mesh.glb`` (textured), ``obj/mesh.obj`` + ``mesh.mtl`` + texture PNG,
``mesh_colours.ply`` (vertex colours), ``mosaic.png`` + ``mosaic.pgw`` (world file: texel size,
rotation terms, -texel size, x and y of the upper-left texel's centre).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from watergan.errors import UserInputError


@dataclass(frozen=True)
class MeshConfig:
    """Meshing, texturing and mosaic options."""

    images_dir: str = ""
    """Images that colour the texture (raw or corrected; SfM's names); empty: ``00_survey/images``."""
    source: str = "auto"
    """Points to mesh: 'dense' (05_dense/fused_points.ply), 'sparse' (SfM points) or 'auto' (dense when present)."""
    cell_m: float = 0.0
    """Height-field grid cell, survey units (metres when scaled); 0: automatic (about 150 cells across)."""
    max_edge_cells: float = 4.0
    """Triangles with an edge longer than this many cells are dropped."""
    texel_m: float = 0.0
    """Texture / mosaic resolution, survey units per texel; 0: automatic (half the images' ground sampling,
    at most 3000 texels across). Texels at the ground sampling itself lose detail in the two resamplings
    (image -> texture -> view): on the demo survey the render-back PSNR drops from ~32.6 to ~27 dB."""
    blend_power: float = 8.0
    """Exponent p of the view weight (1 - rho^2)^p."""


@dataclass
class MeshResult:
    glb: str
    obj: str
    ply: str
    mosaic_png: str
    world_file: str
    n_vertices: int
    n_faces: int
    texel_m: float
    """Metres (survey units) per texel of the texture and mosaic."""
    mosaic_coverage: float
    """Fraction of mosaic texels seen by at least one image."""
    seconds: float


@dataclass
class HeightMesh:
    vertices: np.ndarray  # (V,3)
    faces: np.ndarray     # (F,3) int
    bounds: np.ndarray    # (2,2): [[x0, y0], [x1, y1]]

    def uv(self) -> np.ndarray:
        """Planar texture coordinates (V,2): 0 and 1 at the bounds (the first and last texel centres)."""
        return (self.vertices[:, :2] - self.bounds[0]) / (self.bounds[1] - self.bounds[0])

    def on_texel_grid(self, texel_m: float) -> HeightMesh:
        """The same mesh with bounds snapped to a texel grid: x0 and y1 kept, x1 and y0 moved out to the
        last texel centre, so that texel (column i, row j) has its centre at (x0 + i t, y1 - j t)."""
        (x0, y0), (x1, y1) = self.bounds
        width, height = _texel_count(x1 - x0, texel_m), _texel_count(y1 - y0, texel_m)
        bounds = np.array([[x0, y1 - (height - 1) * texel_m], [x0 + (width - 1) * texel_m, y1]])
        return HeightMesh(vertices=self.vertices, faces=self.faces, bounds=bounds)


def _texel_count(length: float, texel_m: float) -> int:
    """Texel centres needed to span ``length`` (the last centre at or beyond it)."""
    return int(np.ceil(length / texel_m - 1e-6)) + 1


def height_mesh(points: np.ndarray, cell_m: float, max_edge_cells: float = 4.0) -> HeightMesh:
    """2.5D Delaunay mesh of the per-cell median heights (see the module docstring)."""
    from scipy.spatial import Delaunay

    points = np.asarray(points, float)
    points = points[np.isfinite(points).all(1)]
    if len(points) < 3:
        raise UserInputError(f"only {len(points)} points to mesh: run sfm/dense first")
    cell = np.floor(points[:, :2] / cell_m).astype(np.int64)
    keys, inverse = np.unique(cell, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    splits = np.flatnonzero(np.diff(inverse[order])) + 1
    heights = np.array([np.median(points[idx, 2]) for idx in np.split(order, splits)])
    xy = (keys + 0.5) * cell_m
    if len(xy) < 3:
        raise UserInputError("the points cover fewer than 3 grid cells: choose a smaller cell size")
    tri = Delaunay(xy)
    faces = tri.simplices
    edges = np.stack([np.linalg.norm(xy[faces[:, i]] - xy[faces[:, (i + 1) % 3]], axis=1) for i in range(3)], 1)
    faces = faces[edges.max(1) <= max_edge_cells * cell_m]
    used = np.unique(faces)
    remap = np.full(len(xy), -1)
    remap[used] = np.arange(len(used))
    vertices = np.column_stack([xy[used], heights[used]])
    faces = remap[faces]
    # counter-clockwise seen from above: normals point up (+z)
    cross = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    flip = cross[:, 2] < 0
    faces[flip] = faces[flip][:, ::-1]
    bounds = np.array([vertices[:, :2].min(0), vertices[:, :2].max(0)])
    return HeightMesh(vertices=vertices, faces=faces.astype(np.int64), bounds=bounds)


def surface_heights(mesh: HeightMesh, xy: np.ndarray) -> np.ndarray:
    """Mesh height at positions (N,2): vertical rays cast down onto the mesh (open3d); NaN where
    no triangle lies below (holes, outside)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    top = float(mesh.vertices[:, 2].max()) + 1.0
    rays = np.zeros((len(xy), 6), np.float32)
    rays[:, :2], rays[:, 2], rays[:, 5] = xy, top, -1.0
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    return np.where(np.isfinite(t_hit), top - t_hit, np.nan)


def _footprint_window(world_from_cam: np.ndarray, K: np.ndarray, width: int, height: int,
                      z_range: tuple[float, float], upper_left_xy: tuple[float, float], texel_m: float,
                      shape: tuple[int, int]) -> tuple[slice, slice]:
    """Rows and columns of the orthophoto grid (row 0 at y = upper_left y, column 0 at x = upper_left x)
    that the image can see: the bounding box of its corner rays between the surface's lowest and
    highest heights (plus a texel). The whole grid when a corner ray does not point down."""
    full = slice(0, shape[0]), slice(0, shape[1])
    corners = np.array([[0, 0, 1], [width - 1, 0, 1], [width - 1, height - 1, 1], [0, height - 1, 1]], float)
    dirs = (np.linalg.inv(K) @ corners.T).T @ world_from_cam[:3, :3].T
    if (dirs[:, 2] >= -1e-9).any():
        return full
    centre = world_from_cam[:3, 3]
    xy = np.concatenate([centre[:2] + ((z - centre[2]) / dirs[:, 2])[:, None] * dirs[:, :2] for z in z_range])
    if not np.isfinite(xy).all():
        return full
    x0, y1 = upper_left_xy
    c0, c1 = np.floor((xy[:, 0].min() - x0) / texel_m) - 1, np.ceil((xy[:, 0].max() - x0) / texel_m) + 2
    r0, r1 = np.floor((y1 - xy[:, 1].max()) / texel_m) - 1, np.ceil((y1 - xy[:, 1].min()) / texel_m) + 2
    return (slice(int(np.clip(r0, 0, shape[0])), int(np.clip(r1, 0, shape[0]))),
            slice(int(np.clip(c0, 0, shape[1])), int(np.clip(c1, 0, shape[1]))))


def orthophoto(mesh: HeightMesh, texel_m: float, tracks, images_dir: Path, blend_power: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """Blended orthophoto (H,W,3) uint8 over the mesh bounds (row 0 = largest y) and its coverage
    mask (H,W); see the module docstring."""
    import cv2
    from tqdm import tqdm

    (x0, y0), (x1, y1) = mesh.bounds
    width, height = _texel_count(x1 - x0, texel_m), _texel_count(y1 - y0, texel_m)
    xs = x0 + texel_m * np.arange(width)
    ys = y1 - texel_m * np.arange(height)
    gx, gy = np.meshgrid(xs, ys)
    z = surface_heights(mesh, np.column_stack([gx.ravel(), gy.ravel()])).reshape(height, width)
    surface = np.stack([gx, gy, z], -1).astype(np.float64)
    acc = np.zeros((height, width, 3))
    weight = np.zeros((height, width))
    K = tracks.K
    half_diag = 0.5 * np.hypot(tracks.width, tracks.height)
    centre = np.array([(tracks.width - 1) / 2, (tracks.height - 1) / 2])
    z_range = (float(np.nanmin(z)), float(np.nanmax(z))) if np.isfinite(z).any() else (0.0, 0.0)
    for k in tqdm(np.flatnonzero(tracks.registered), desc="texture", unit="image"):
        pose = tracks.world_from_cam[k]
        rows, cols = _footprint_window(pose, K, tracks.width, tracks.height, z_range, (x0, y1), texel_m,
                                       (height, width))
        if rows.start >= rows.stop or cols.start >= cols.stop:
            continue
        image = cv2.imread(str(images_dir / str(tracks.image_names[k])), cv2.IMREAD_COLOR)
        if image is None:
            raise UserInputError(f"cannot read {images_dir / str(tracks.image_names[k])}")
        pc = (surface[rows, cols] - pose[:3, 3]) @ pose[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[..., 0] / pc[..., 2] + K[0, 2]
            v = K[1, 1] * pc[..., 1] / pc[..., 2] + K[1, 2]
            rho2 = ((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / half_diag**2
        seen = (pc[..., 2] > 0) & (u >= 0) & (u <= tracks.width - 1) & (v >= 0) & (v <= tracks.height - 1)
        if not seen.any():
            continue
        w = np.where(seen, np.clip(1 - rho2, 0, 1) ** blend_power, 0.0)
        sample = cv2.remap(image[..., ::-1].astype(np.float32), np.nan_to_num(u).astype(np.float32),
                           np.nan_to_num(v).astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        acc[rows, cols] += w[..., None] * sample
        weight[rows, cols] += w
    covered = weight > 0
    mosaic = np.zeros((height, width, 3), np.uint8)
    mosaic[covered] = np.clip(np.rint(acc[covered] / weight[covered, None]), 0, 255).astype(np.uint8)
    return mosaic, covered


def write_world_file(path: Path, texel_m: float, upper_left_centre_xy: tuple[float, float]) -> None:
    """ESRI world file: A (x size), D, B (rotation, 0), E (-y size), C, F (upper-left texel centre)."""
    from pipeline.workspace import atomic_write_text

    x, y = upper_left_centre_xy
    atomic_write_text(path, f"{texel_m:.10f}\n0.0\n0.0\n{-texel_m:.10f}\n{x:.10f}\n{y:.10f}\n")


def export_mesh(mesh: HeightMesh, texture: np.ndarray, out_dir: Path) -> tuple[Path, Path, Path]:
    """Write mesh.glb (textured), obj/mesh.obj + mesh.mtl + texture, mesh_colours.ply (vertex colours)."""
    import trimesh
    from PIL import Image

    from pipeline.workspace import atomic_write_bytes

    image = Image.fromarray(texture)
    uv = mesh.uv()
    h, w = texture.shape[:2]
    # uv 0 and 1 are the first and last texel centres, while glTF/OBJ put 0 and 1 at the image's edges;
    # image row 0 is the largest y, and glTF/OBJ v runs upwards from the image's bottom row
    uv_image = np.column_stack([(uv[:, 0] * (w - 1) + 0.5) / w, (uv[:, 1] * (h - 1) + 0.5) / h])
    material = trimesh.visual.material.SimpleMaterial(image=image, name="mosaic")
    textured = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces,
                               visual=trimesh.visual.TextureVisuals(uv=uv_image, material=material), process=False)
    glb = out_dir / "mesh.glb"
    atomic_write_bytes(glb, textured.export(file_type="glb"))

    obj_dir = out_dir / "obj"
    obj_dir.mkdir(parents=True, exist_ok=True)
    text, files = trimesh.exchange.obj.export_obj(textured, include_texture=True, return_texture=True,
                                                  mtl_name="mesh.mtl")
    atomic_write_bytes(obj_dir / "mesh.obj", text.encode())
    for name, data in files.items():
        atomic_write_bytes(obj_dir / name, data)

    col = np.clip(np.rint(uv[:, 0] * (w - 1)), 0, w - 1).astype(int)
    row = np.clip(np.rint((1 - uv[:, 1]) * (h - 1)), 0, h - 1).astype(int)
    colours = np.column_stack([texture[row, col], np.full(len(uv), 255, np.uint8)])
    coloured = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, vertex_colors=colours, process=False)
    ply = out_dir / "mesh_colours.ply"
    atomic_write_bytes(ply, coloured.export(file_type="ply"))
    return glb, obj_dir / "mesh.obj", ply


def render_back(mesh: HeightMesh, texture: np.ndarray, world_from_cam: np.ndarray, K: np.ndarray,
                width: int, height: int) -> np.ndarray:
    """The textured mesh seen from a camera (H,W,3) float 0..255, NaN where no surface is hit or the
    texture has no colour: rays through the pixel centres (OpenCV convention) are cast against the mesh
    (open3d) and the hit's (x, y) is looked up bilinearly in the orthophoto, whose texel centres span
    the mesh's bounds (``mesh.on_texel_grid(texel_m)``, as the mesh stage textures it)."""
    import cv2
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    dirs_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    dirs = dirs_cam @ world_from_cam[:3, :3].T
    origins = np.broadcast_to(world_from_cam[:3, 3], dirs.shape)
    rays = o3d.core.Tensor(np.concatenate([origins, dirs], -1).astype(np.float32))
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    hit = origins + dirs * t_hit[..., None]
    th, tw = texture.shape[:2]
    (x0, y0), (x1, y1) = mesh.bounds
    # texel centres: column i at x0 + i (x1 - x0) / (tw - 1), row j at y1 - j (y1 - y0) / (th - 1)
    hit_ok = np.isfinite(t_hit)
    col = np.where(hit_ok, (hit[..., 0] - x0) / (x1 - x0) * (tw - 1), -2.0).astype(np.float32)
    row = np.where(hit_ok, (y1 - hit[..., 1]) / (y1 - y0) * (th - 1), -2.0).astype(np.float32)
    kw = dict(borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    colour = cv2.remap(np.ascontiguousarray(texture, np.float32), col, row, cv2.INTER_LINEAR, **kw)
    # texels no image saw are black: keep pixels whose four bilinear neighbours were all seen
    seen = cv2.remap((texture.reshape(th, tw, -1).max(-1) > 0).astype(np.float32), col, row, cv2.INTER_LINEAR, **kw)
    ok = hit_ok & (seen > 0.999)
    out = np.full((height, width, 3), np.nan)
    out[ok] = colour.reshape(height, width, -1)[ok]
    return out


def run_mesh_folder(tracks, images_dir: str | Path, out_dir: str | Path, cfg: MeshConfig,
                    dense_points_ply: Path | None = None) -> MeshResult:
    """Mesh, texture, exports and mosaic (see the module docstring)."""
    import cv2

    from pipeline.workspace import atomic_write_bytes

    start = time.perf_counter()
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if cfg.source not in ("auto", "dense", "sparse"):
        raise UserInputError(f"source must be 'auto', 'dense' or 'sparse', not '{cfg.source}'")
    use_dense = cfg.source == "dense" or (cfg.source == "auto" and dense_points_ply is not None
                                          and dense_points_ply.is_file())
    if use_dense:
        import open3d as o3d

        if dense_points_ply is None or not dense_points_ply.is_file():
            raise UserInputError("no fused dense points: run the dense stage or use --source sparse")
        points = np.asarray(o3d.io.read_point_cloud(str(dense_points_ply)).points)
    else:
        points = tracks.xyz[tracks.track_lengths() >= 3]
    extent = float((np.percentile(points[:, :2], 99, axis=0) - np.percentile(points[:, :2], 1, axis=0)).max())
    cell = cfg.cell_m or extent / 150
    mesh = height_mesh(points, cell, cfg.max_edge_cells)
    depth = float(np.median(tracks.depths()))
    ground_sampling = depth / float(tracks.K[0, 0])
    texel = cfg.texel_m or max(extent / 3000, ground_sampling / 2)
    mesh = mesh.on_texel_grid(texel)
    mosaic, covered = orthophoto(mesh, texel, tracks, images_dir, cfg.blend_power)
    glb, obj, ply = export_mesh(mesh, mosaic, out_dir)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(mosaic[..., ::-1]))
    if not ok:
        raise OSError("could not encode the mosaic")
    mosaic_png = out_dir / "mosaic.png"
    atomic_write_bytes(mosaic_png, png.tobytes())
    world_file = out_dir / "mosaic.pgw"
    write_world_file(world_file, texel, (float(mesh.bounds[0, 0]), float(mesh.bounds[1, 1])))
    return MeshResult(glb=str(glb), obj=str(obj), ply=str(ply), mosaic_png=str(mosaic_png), world_file=str(world_file),
                      n_vertices=len(mesh.vertices), n_faces=len(mesh.faces), texel_m=texel,
                      mosaic_coverage=float(covered.mean()), seconds=time.perf_counter() - start)


def run_mesh(ws, cfg: MeshConfig) -> MeshResult:
    """Workspace stage: tracks from ``04_sfm``, dense points from ``05_dense``; outputs in ``07_mesh``."""
    from pipeline.sfm import Tracks

    tracks = Tracks.load(ws.stage_dir("sfm") / "tracks.npz")
    images_dir = Path(cfg.images_dir) if cfg.images_dir else ws.stage_dir("survey") / "images"
    result = run_mesh_folder(tracks, images_dir, ws.stage_dir("mesh"), cfg, ws.stage_dir("dense") / "fused_points.ply")
    for name in ("glb", "obj", "ply", "mosaic_png", "world_file"):
        setattr(result, name, ws.relative(getattr(result, name)))
    return result
