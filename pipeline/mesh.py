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

Non-2.5D scenes (``mesh_kind="tsdf"``; 'auto' picks it when fewer than ``height_field_fraction`` of
the points have a normal with |n_z| > 0.5, i.e. the points are not a height field, and the dense
stage left a fused mesh): the TSDF mesh of ``02_dense/fused_mesh.ply`` (decimated to at most
``max_faces``) is unwrapped with xatlas (texels of ``texel_m``, at most ``max_texture_px`` a side).
Each atlas texel is found by casting a ray onto the UV triangles (open3d), which gives its triangle and
barycentric coordinates, hence its 3D point and face normal. The point is projected into every view;
a view counts when the point is in front, inside the image and not occluded (its camera depth within
2 % of the mesh's depth rendered at that pixel), with weight (1 - rho^2)^p |cos theta| (theta between
the normal and the direction to the camera). Texels no view sees stay black; colours are grown a few
texels into the empty atlas space so that bilinear lookups at chart edges do not pull in black.
The orthophoto mosaic is still made from the 2.5D height field.

Outputs (``09_mesh/``): ``mesh.glb`` (textured), ``obj/mesh.obj`` + ``mesh.mtl`` + texture PNG,
``mesh_colours.ply`` (vertex colours), ``mosaic.png`` + ``mosaic.pgw`` (world file: texel size,
rotation terms, -texel size, x and y of the upper-left texel's centre), ``mosaic.tif`` (the mosaic as an RGBA
GeoTIFF, alpha 0 where no image saw the texel) and ``dem.tif`` (the height field's z at each texel, float32
metres, NaN off the mesh), both on the mosaic's grid in the survey's local metric frame
(:func:`write_geotiff`).

Georeferenced (``survey.json`` names a ``crs`` and gives the frames' positions: :mod:`pipeline.georeference`):
the same grid (rows still along the survey frame's -y, so rotated in the CRS) is placed by the fitted similarity.
The GeoTIFFs carry a ModelTransformation (pixel (col, row), corner of the upper-left texel at (0, 0), ->
(easting, northing)) and the CRS's EPSG code, the world file its rotation terms, and ``mosaic.png.aux.xml``
(GDAL's side file) names the CRS for the PNG; the DEM's heights stay the survey frame's z (up, metres, origin at
the points' median), not depths or elevations of the CRS.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np

from eval.sampling import bilinear
from watergan.errors import UserInputError
from watergan.io import frame_file, read_bgr8


class PointSource(StrEnum):
    """Points the mesh is built from."""

    auto = "auto"
    dense = "dense"
    sparse = "sparse"


class MeshKind(StrEnum):
    """Kind of mesh."""

    auto = "auto"
    height_field = "2.5d"
    tsdf = "tsdf"


@dataclass(frozen=True)
class MeshConfig:
    """Meshing, texturing and mosaic options."""

    images_dir: str = ""
    """Images that colour the texture (raw or corrected; SfM's names); empty: the set the correct stage names
    for the mesh."""
    source: PointSource = PointSource.auto
    """Points to mesh: 'dense' (02_dense/fused_points.ply), 'sparse' (SfM points) or 'auto' (dense when present)."""
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
    mesh_kind: MeshKind = MeshKind.auto
    """'2.5d' (height-field Delaunay, planar UVs), 'tsdf' (the dense stage's fused mesh, xatlas UVs) or
    'auto' (tsdf when the points are not a height field and a fused mesh exists)."""
    height_field_fraction: float = 0.8
    """'auto': the points are a height field when at least this fraction has |normal z| > 0.5."""
    max_faces: int = 20_000
    """'tsdf': the fused mesh is decimated (quadric) to at most this many faces before unwrapping (xatlas
    takes ~6 s for 20k faces, ~130 s for 80k, on 2 cores; the texture carries the detail)."""
    max_texture_px: int = 4096
    """'tsdf': the atlas side in texels at most (the texel grows to fit)."""
    progress: bool = field(default=True, metadata={"hash": False})
    """Show progress bars."""


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
    mesh_kind: str = "2.5d"
    """'2.5d' or 'tsdf': which mesh was textured and exported."""
    mosaic_tif: str = ""
    """The mosaic as a GeoTIFF (RGBA: alpha 0 where no image saw the texel) in the survey's local metric frame."""
    dem_tif: str = ""
    """The surface's height at each mosaic texel (float32 metres, NaN off the mesh) as a GeoTIFF on the same
    grid."""
    crs: str = ""
    """"EPSG:<code>" the GeoTIFFs and world file are in (:mod:`pipeline.georeference`); empty: the survey's local
    metric frame."""
    georef_rotation_deg: float = 0.0
    """Counter-clockwise angle from the survey frame's x axis to east (georeferenced only)."""
    georef_scale: float = 1.0
    """CRS metres per survey-frame unit, fitted (georeferenced only)."""
    georef_rms_m: float = 0.0
    """RMS distance between the cameras placed by the fit and the navigation's positions (georeferenced only)."""
    georef_frames: int = 0
    """Registered frames with a position, the fit's samples."""
    georef_warning: str = ""
    """Why the georeference is doubtful or was not made (then the outputs are in the local frame); empty: none."""


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


def orthophoto(mesh: HeightMesh, texel_m: float, tracks, images_dir: Path, blend_power: float,
               progress: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blended orthophoto (H,W,3) uint8 over the mesh bounds (row 0 = largest y), its coverage
    mask (H,W) and the surface's height z at each texel centre (H,W; NaN off the mesh); see the module
    docstring."""
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
    for k in tqdm(np.flatnonzero(tracks.registered), desc="texture", unit="image", disable=not progress):
        pose = tracks.world_from_cam[k]
        rows, cols = _footprint_window(pose, K, tracks.width, tracks.height, z_range, (x0, y1), texel_m,
                                       (height, width))
        if rows.start >= rows.stop or cols.start >= cols.stop:
            continue
        path = frame_file(images_dir, str(tracks.image_names[k]))
        image = read_bgr8(path)
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
    return mosaic, covered, z


#: GeoTIFF tags (GeoTIFF 1.1, OGC 19-008): pixel scale, tie point, geokey directory, ASCII parameters, GDAL's no-data.
PIXEL_SCALE, TIE_POINT, GEO_KEYS, GEO_ASCII, GDAL_NODATA = 33550, 33922, 34735, 34737, 42113
#: GeoTIFF's model transformation: 16 doubles, a row-major 4x4 from raster (col, row, 0, 1) to model (E, N, 0, 1).
MODEL_TRANSFORMATION = 34264
#: The citation of the user-defined projected CRS of the survey's local frame.
LOCAL_FRAME = "watergan survey frame: local metric x (columns), y (rows up), metres|"


def raster_to_model(texel_m: float, upper_left_centre_xy: tuple[float, float], georef=None) -> np.ndarray:
    """The 2x3 affine from raster (col, row; pixel-is-area: the upper-left texel's corner at (0, 0), its centre at
    (0.5, 0.5)) to the survey frame's (x, y), or with ``georef`` (:class:`pipeline.georeference.Georeference`) to
    (easting, northing)."""
    x, y = upper_left_centre_xy
    local = np.array([[texel_m, 0.0, x - texel_m / 2], [0.0, -texel_m, y + texel_m / 2]])
    if georef is None:
        return local
    linear = georef.linear()
    return np.column_stack([linear @ local[:, :2], linear @ local[:, 2] + np.asarray(georef.translation_m)])


def write_geotiff(path: Path, image: np.ndarray, texel_m: float, upper_left_centre_xy: tuple[float, float],
                  georef=None) -> None:
    """``image`` (H,W[,C]; row 0 at the largest y) as a GeoTIFF in the survey's local metric frame, atomically:
    pixel scale ``texel_m``, the upper-left texel's centre at ``upper_left_centre_xy`` (pixel-is-area: its corner
    half a texel up and left), a user-defined projected CRS in metres (GIS opens it as an unknown local frame with
    true distances). With ``georef`` (:class:`pipeline.georeference.Georeference`) the grid is placed in its CRS:
    a ModelTransformation (:func:`raster_to_model`; pixel scale and tie point when it does not rotate) and the
    CRS's EPSG code. A float image's NaN is declared as no-data."""
    import io

    import tifffile

    from watergan.io import atomic_write_bytes

    affine = raster_to_model(texel_m, upper_left_centre_xy, georef)
    if affine[0, 1] == 0.0 and affine[1, 0] == 0.0 and affine[0, 0] > 0 > affine[1, 1]:
        placement = [(PIXEL_SCALE, "d", 3, (affine[0, 0], -affine[1, 1], 0.0), False),
                     (TIE_POINT, "d", 6, (0.0, 0.0, 0.0, affine[0, 2], affine[1, 2], 0.0), False)]
    else:
        matrix = [*affine[0, :2], 0.0, affine[0, 2], *affine[1, :2], 0.0, affine[1, 2], 0.0, 0.0, 0.0, 0.0,
                  0.0, 0.0, 0.0, 1.0]
        placement = [(MODEL_TRANSFORMATION, "d", 16, tuple(float(v) for v in matrix), False)]
    if georef is None:
        ascii_params = LOCAL_FRAME
        keys = [1, 1, 0, 5,
                1024, 0, 1, 1,                          # GTModelTypeGeoKey: projected
                1025, 0, 1, 1,                          # GTRasterTypeGeoKey: pixel is area
                1026, GEO_ASCII, len(ascii_params), 0,  # GTCitationGeoKey
                3072, 0, 1, 32767,                      # ProjectedCSTypeGeoKey: user-defined
                3076, 0, 1, 9001]                       # ProjLinearUnitsGeoKey: metre
        tags = [*placement, (GEO_KEYS, "H", len(keys), keys, False), (GEO_ASCII, "s", 0, ascii_params, False)]
    else:
        keys = [1, 1, 0, 4,
                1024, 0, 1, 1,                          # GTModelTypeGeoKey: projected
                1025, 0, 1, 1,                          # GTRasterTypeGeoKey: pixel is area
                3072, 0, 1, georef.epsg,                # ProjectedCSTypeGeoKey: the EPSG code
                3076, 0, 1, 9001]                       # ProjLinearUnitsGeoKey: metre
        tags = [*placement, (GEO_KEYS, "H", len(keys), keys, False)]
    if image.dtype.kind == "f":
        tags.append((GDAL_NODATA, "s", 0, "nan", False))
    buffer = io.BytesIO()
    photometric = "rgb" if image.ndim == 3 else "minisblack"
    tifffile.imwrite(buffer, image, photometric=photometric, compression="zlib",
                     extrasamples=("unassalpha",) if image.ndim == 3 and image.shape[2] == 4 else None,
                     extratags=tags)
    atomic_write_bytes(path, buffer.getvalue())


def write_world_file(path: Path, texel_m: float, upper_left_centre_xy: tuple[float, float], georef=None) -> None:
    """ESRI world file: A (x size), D, B (rotation, 0), E (-y size), C, F (upper-left texel centre). With ``georef``
    (:class:`pipeline.georeference.Georeference`) in its CRS: A, D the easting and northing a column adds, B, E
    those a row adds, C, F the upper-left texel centre's easting and northing; and ``<image>.aux.xml`` beside it
    (GDAL's side file) names the CRS (removed when there is none)."""
    from watergan.io import atomic_write_text

    x, y = upper_left_centre_xy
    aux = path.with_suffix(".png.aux.xml")
    if georef is None:
        atomic_write_text(path, f"{texel_m:.10f}\n0.0\n0.0\n{-texel_m:.10f}\n{x:.10f}\n{y:.10f}\n")
        aux.unlink(missing_ok=True)
        return
    (a, b, _), (d, e, _) = affine = raster_to_model(texel_m, upper_left_centre_xy, georef)
    c, f = affine @ (0.5, 0.5, 1.0)
    atomic_write_text(path, "".join(f"{float(v)!r}\n" for v in (a, d, b, e, c, f)))
    atomic_write_text(aux, f"<PAMDataset>\n  <SRS>{georef.crs}</SRS>\n</PAMDataset>\n")


def export_mesh(mesh: HeightMesh, texture: np.ndarray, out_dir: Path) -> tuple[Path, Path, Path]:
    """Write mesh.glb (textured), obj/mesh.obj + mesh.mtl + texture, mesh_colours.ply (vertex colours)."""
    uv = mesh.uv()
    h, w = texture.shape[:2]
    # uv 0 and 1 are the first and last texel centres, while glTF/OBJ put 0 and 1 at the image's edges;
    # image row 0 is the largest y, and glTF/OBJ v runs upwards from the image's bottom row
    uv_image = np.column_stack([(uv[:, 0] * (w - 1) + 0.5) / w, (uv[:, 1] * (h - 1) + 0.5) / h])
    return export_textured(mesh.vertices, mesh.faces, uv_image, texture, out_dir)


def export_textured(vertices: np.ndarray, faces: np.ndarray, uv_image: np.ndarray, texture: np.ndarray,
                    out_dir: Path) -> tuple[Path, Path, Path]:
    """The exports of :func:`export_mesh` for any mesh with glTF/OBJ texture coordinates (V,2): 0 and 1
    at the image edges, v up from the bottom row. Vertex colours: the texel under each vertex's UV."""
    import trimesh
    from PIL import Image

    from watergan.io import atomic_write_bytes

    image = Image.fromarray(texture)
    h, w = texture.shape[:2]
    material = trimesh.visual.material.SimpleMaterial(image=image, name="mosaic")
    textured = trimesh.Trimesh(vertices=vertices, faces=faces,
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

    col = np.clip(np.floor(uv_image[:, 0] * w), 0, w - 1).astype(int)
    row = np.clip(np.floor((1 - uv_image[:, 1]) * h), 0, h - 1).astype(int)
    colours = np.column_stack([texture[row, col], np.full(len(uv_image), 255, np.uint8)])
    coloured = trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colours, process=False)
    ply = out_dir / "mesh_colours.ply"
    atomic_write_bytes(ply, coloured.export(file_type="ply"))
    return glb, obj_dir / "mesh.obj", ply


def is_height_field(points: np.ndarray, fraction: float = 0.8, neighbours: int = 20) -> bool:
    """Whether points (N,3) look like a height field over the survey frame's x-y: at least ``fraction``
    of the normals (open3d, ``neighbours`` nearest points) have |n_z| > 0.5."""
    import open3d as o3d

    points = np.asarray(points, float)
    points = points[np.isfinite(points).all(1)]
    if len(points) < neighbours:
        return True
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(neighbours))
    return float(np.mean(np.abs(np.asarray(cloud.normals)[:, 2]) > 0.5)) >= fraction


def atlas_unwrap(vertices: np.ndarray, faces: np.ndarray, texel_m: float, max_texture_px: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int], float]:
    """xatlas UV unwrap with about ``texel_m`` per texel (larger when the atlas would exceed
    ``max_texture_px``). Returns (vertices (V',3) split at seams, faces, uv (V',2) with 0 and 1 at the
    atlas edges and v down the image rows, atlas (height, width) in texels, texel_m used)."""
    import xatlas

    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    texel_m = max(texel_m, float(np.sqrt(2.0 * area) / (0.9 * max_texture_px)))  # ~50 % packing efficiency
    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.texels_per_unit, pack.padding, pack.bilinear = 1.0 / texel_m, 2, True
    atlas.generate(pack_options=pack)  # resolution 0: the atlas size follows the texel
    vmapping, new_faces, uv = atlas[0]
    return (vertices[vmapping], new_faces.astype(np.int64), np.asarray(uv, np.float64),
            (int(atlas.height), int(atlas.width)), texel_m)


def atlas_texture(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, size: tuple[int, int], tracks,
                  images_dir: Path, blend_power: float, grow_texels: int = 4, progress: bool = True
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Texture (H,W,3) uint8 of an unwrapped mesh and its coverage mask (see the module docstring)."""
    import cv2
    import open3d as o3d
    from tqdm import tqdm

    height, width = size
    # texel -> triangle and barycentrics: rays cast down onto the UV triangles laid out at z = 0
    flat = o3d.t.geometry.RaycastingScene()
    flat.add_triangles(o3d.core.Tensor(np.column_stack([uv * [width, height], np.zeros(len(uv))]).astype(np.float32)),
                       o3d.core.Tensor(faces.astype(np.uint32)))
    ti, tj = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.zeros((height, width, 6), np.float32)
    rays[..., 0], rays[..., 1], rays[..., 2], rays[..., 5] = ti, tj, 1.0, -1.0
    hit = flat.cast_rays(o3d.core.Tensor(rays))
    inside = np.isfinite(hit["t_hit"].numpy())
    prim = hit["primitive_ids"].numpy()[inside].astype(np.int64)
    bary = hit["primitive_uvs"].numpy()[inside].astype(np.float64)
    tri = vertices[faces[prim]]
    points = (1 - bary.sum(1))[:, None] * tri[:, 0] + bary[:, :1] * tri[:, 1] + bary[:, 1:] * tri[:, 2]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    K, w_img, h_img = tracks.K, tracks.width, tracks.height
    u_grid, v_grid = np.meshgrid(np.arange(w_img, dtype=np.float64), np.arange(h_img, dtype=np.float64))
    rays_cam = np.stack([(u_grid - K[0, 2]) / K[0, 0], (v_grid - K[1, 2]) / K[1, 1], np.ones_like(u_grid)], -1)
    half_diag = 0.5 * np.hypot(w_img, h_img)
    centre = np.array([(w_img - 1) / 2, (h_img - 1) / 2])
    acc, weight = np.zeros((len(points), 3)), np.zeros(len(points))
    for k in tqdm(np.flatnonzero(tracks.registered), desc="texture", unit="image", disable=not progress):
        pose = tracks.world_from_cam[k]
        pc = (points - pose[:3, 3]) @ pose[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
            v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        seen = (pc[:, 2] > 0) & (u >= 0) & (u <= w_img - 1) & (v >= 0) & (v <= h_img - 1)
        if not seen.any():
            continue
        # occlusion: the mesh's camera depth at the pixel (rays K^-1 (u, v, 1): t_hit is the camera z)
        cam_rays = np.concatenate([np.broadcast_to(pose[:3, 3], rays_cam.shape), rays_cam @ pose[:3, :3].T], -1)
        depth = scene.cast_rays(o3d.core.Tensor(cam_rays.astype(np.float32)))["t_hit"].numpy()
        idx = np.flatnonzero(seen)
        nearest = depth[np.rint(v[idx]).astype(int), np.rint(u[idx]).astype(int)]
        idx = idx[np.abs(pc[idx, 2] - nearest) <= 0.02 * pc[idx, 2]]
        if not len(idx):
            continue
        path = frame_file(images_dir, str(tracks.image_names[k]))
        image = read_bgr8(path)
        rho2 = ((u[idx] - centre[0]) ** 2 + (v[idx] - centre[1]) ** 2) / half_diag**2
        to_cam = pose[:3, 3] - points[idx]
        cos = np.abs(np.einsum("ni,ni->n", normals[idx], to_cam)) / np.linalg.norm(to_cam, axis=1)
        wk = np.clip(1 - rho2, 0, 1) ** blend_power * cos
        acc[idx] += wk[:, None] * bilinear(image[..., ::-1].astype(np.float64), np.stack([u[idx], v[idx]], 1))
        weight[idx] += wk
    colours = np.zeros((height, width, 3))
    covered = np.zeros((height, width), bool)
    ok = weight > 0
    colours[np.flatnonzero(inside.ravel())[ok] // width, np.flatnonzero(inside.ravel())[ok] % width] = \
        acc[ok] / weight[ok, None]
    covered[inside] = ok
    filled = covered.astype(np.float64)
    for _ in range(grow_texels):  # grow colours into the empty atlas space (bilinear lookups at chart edges)
        total = cv2.boxFilter(colours * filled[..., None], -1, (3, 3), normalize=False)
        count = cv2.boxFilter(filled, -1, (3, 3), normalize=False)
        grow = (filled == 0) & (count > 0)
        colours[grow] = total[grow] / count[grow, None]
        filled[grow] = 1
    return np.clip(np.rint(colours), 0, 255).astype(np.uint8), covered


def tsdf_textured_mesh(mesh_ply: Path, tracks, images_dir: Path, texel_m: float, cfg: MeshConfig, out_dir: Path
                       ) -> tuple[tuple[Path, Path, Path], int, int, float]:
    """Decimate, unwrap, texture and export the fused TSDF mesh. Returns (exports, vertices, faces, texel)."""
    import open3d as o3d

    if not mesh_ply.is_file():
        raise UserInputError(f"no fused TSDF mesh at {mesh_ply}: run the dense stage (with fusion) first")
    legacy = o3d.io.read_triangle_mesh(str(mesh_ply))
    legacy.remove_duplicated_vertices()
    legacy.remove_degenerate_triangles()
    legacy.remove_unreferenced_vertices()
    if len(legacy.triangles) > cfg.max_faces:
        legacy = legacy.simplify_quadric_decimation(cfg.max_faces)
    vertices, faces = np.asarray(legacy.vertices, np.float64), np.asarray(legacy.triangles, np.int64)
    if len(faces) == 0:
        raise UserInputError(f"the fused mesh {mesh_ply} has no faces")
    vertices, faces, uv, size, texel = atlas_unwrap(vertices, faces, texel_m, cfg.max_texture_px)
    texture, _ = atlas_texture(vertices, faces, uv, size, tracks, images_dir, cfg.blend_power,
                               progress=cfg.progress)
    exports = export_textured(vertices, faces, np.column_stack([uv[:, 0], 1 - uv[:, 1]]), texture, out_dir)
    return exports, len(vertices), len(faces), texel


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
                    dense_points_ply: Path | None = None, dense_mesh_ply: Path | None = None,
                    survey_json: Path | None = None) -> MeshResult:
    """Mesh, texture, exports and mosaic (see the module docstring); georeferenced when the survey file
    ``survey_json`` names a crs and gives positions (a fit that fails leaves the local frame, with a warning)."""
    import cv2

    from watergan.io import atomic_write_bytes

    from .georeference import GeoreferenceError, georeference_tracks

    start = time.perf_counter()
    try:
        georef, georef_warning = (georeference_tracks(tracks, survey_json) if survey_json else None), ""
    except GeoreferenceError as exc:
        georef, georef_warning = None, f"not georeferenced: {exc}"
    if georef is not None:
        georef_warning = georef.warning
    if georef_warning:
        print(f"mesh: warning: georeference: {georef_warning}", file=sys.stderr, flush=True)
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if cfg.source not in ("auto", "dense", "sparse"):
        raise UserInputError(f"source must be 'auto', 'dense' or 'sparse', not '{cfg.source}'")
    if cfg.mesh_kind not in ("auto", "2.5d", "tsdf"):
        raise UserInputError(f"mesh_kind must be 'auto', '2.5d' or 'tsdf', not '{cfg.mesh_kind}'")
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
    mosaic, covered, heights = orthophoto(mesh, texel, tracks, images_dir, cfg.blend_power, cfg.progress)
    kind = cfg.mesh_kind
    if kind == "auto":
        has_fused = dense_mesh_ply is not None and dense_mesh_ply.is_file()
        kind = "tsdf" if has_fused and not is_height_field(points, cfg.height_field_fraction) else "2.5d"
    if kind == "tsdf":
        (glb, obj, ply), n_vertices, n_faces, _ = tsdf_textured_mesh(
            dense_mesh_ply if dense_mesh_ply is not None else Path("fused_mesh.ply"), tracks, images_dir, texel,
            cfg, out_dir)
    else:
        glb, obj, ply = export_mesh(mesh, mosaic, out_dir)
        n_vertices, n_faces = len(mesh.vertices), len(mesh.faces)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(mosaic[..., ::-1]))
    if not ok:
        raise OSError("could not encode the mosaic")
    mosaic_png = out_dir / "mosaic.png"
    atomic_write_bytes(mosaic_png, png.tobytes())
    world_file = out_dir / "mosaic.pgw"
    upper_left = (float(mesh.bounds[0, 0]), float(mesh.bounds[1, 1]))
    write_world_file(world_file, texel, upper_left, georef)
    alpha = np.where(covered, 255, 0).astype(np.uint8)[..., None]
    write_geotiff(out_dir / "mosaic.tif", np.concatenate([mosaic, alpha], -1), texel, upper_left, georef)
    write_geotiff(out_dir / "dem.tif", heights.astype(np.float32), texel, upper_left, georef)
    placed = {} if georef is None else {
        "crs": georef.crs, "georef_rotation_deg": georef.rotation_deg, "georef_scale": georef.scale,
        "georef_rms_m": georef.rms_m, "georef_frames": georef.n_frames}
    return MeshResult(glb=str(glb), obj=str(obj), ply=str(ply), mosaic_png=str(mosaic_png), world_file=str(world_file),
                      mosaic_tif=str(out_dir / "mosaic.tif"), dem_tif=str(out_dir / "dem.tif"),
                      n_vertices=n_vertices, n_faces=n_faces, texel_m=texel, mosaic_coverage=float(covered.mean()),
                      seconds=time.perf_counter() - start, mesh_kind=kind, georef_warning=georef_warning, **placed)


def run_mesh(ws, cfg: MeshConfig) -> MeshResult:
    """Workspace stage: tracks from the sfm stage, fused points and mesh from the dense stage when it ran, the
    frames the correct stage names for the mesh (unless ``images_dir``), the survey file's crs and positions
    (``00_survey/survey.json``); outputs in the stage's folder."""
    from eval.tracks import Tracks

    tracks = Tracks.load(ws.path(ws.require("sfm", "mesh").tracks))
    if cfg.images_dir:
        images_dir = Path(cfg.images_dir)
    else:
        images_dir = ws.path(ws.require("correct", "the texture without --images-dir").mesh_images)
    dense = ws.result("dense")
    points, mesh = (ws.path(dense.points_ply), ws.path(dense.mesh_ply)) if dense and dense.points_ply else (None, None)
    result = run_mesh_folder(tracks, images_dir, ws.stage_dir("mesh"), cfg, points, mesh,
                             ws.folder("survey") / "survey.json")
    for name in ("glb", "obj", "ply", "mosaic_png", "world_file", "mosaic_tif", "dem_tif"):
        setattr(result, name, ws.relative(getattr(result, name)))
    return result
