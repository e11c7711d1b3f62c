"""2.5D mesh, texture, exports (GLB/OBJ/PLY) and the orthophoto mosaic."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from test_sfm import survey_and_sfm

from eval.tracks import Tracks
from pipeline.mesh import MeshConfig, height_mesh, render_back, surface_heights


@pytest.fixture(scope="module")
def sfm():
    return survey_and_sfm()


@pytest.fixture(scope="module")
def meshed(sfm):
    survey, ws, _ = sfm
    return survey, ws, ws.run("mesh", MeshConfig(images_dir=str(survey / "images"), source="sparse"))


def test_textured_glb_loads_back(meshed):
    _, ws, result = meshed
    scene = trimesh.load(ws.path(result.glb))
    geometry = next(iter(scene.geometry.values()))
    assert len(geometry.faces) == result.n_faces > 100
    assert geometry.visual.kind == "texture" and geometry.visual.material.baseColorTexture is not None
    assert geometry.visual.uv.min() >= 0 and geometry.visual.uv.max() <= 1


def test_obj_ply_and_mosaic_files(meshed):
    _, ws, result = meshed
    obj = ws.path(result.obj)
    assert {p.suffix for p in obj.parent.iterdir()} >= {".obj", ".mtl", ".png"}
    assert "mtllib mesh.mtl" in obj.read_text()
    ply = trimesh.load(ws.path(result.ply))
    assert ply.visual.kind == "vertex" and len(ply.visual.vertex_colors) == result.n_vertices
    mosaic = cv2.imread(str(ws.path(result.mosaic_png)))
    assert mosaic is not None and result.mosaic_coverage > 0.2
    world = [float(x) for x in ws.path(result.world_file).read_text().split()]
    assert len(world) == 6 and world[0] == pytest.approx(result.texel_m) and world[3] == -world[0]


def test_mosaic_and_dem_geotiffs_share_the_world_file_s_grid(meshed):
    """mosaic.tif (RGBA) and dem.tif carry GeoTIFF's pixel scale and tie point: the upper-left texel's centre is
    the world file's, its corner half a texel up and left; a local metric frame (user-defined CRS in metres)."""
    import tifffile

    _, ws, result = meshed
    world = [float(x) for x in ws.path(result.world_file).read_text().split()]
    png = cv2.imread(str(ws.path(result.mosaic_png)))[..., ::-1]
    for name, channels in ((result.mosaic_tif, 4), (result.dem_tif, 1)):
        with tifffile.TiffFile(ws.path(name)) as tif:
            page = tif.pages[0]
            data = page.asarray()
            scale = page.tags["ModelPixelScaleTag"].value
            tie = page.tags["ModelTiepointTag"].value
            keys = page.tags["GeoKeyDirectoryTag"].value
        assert data.shape[:2] == png.shape[:2] and (data.shape[2] if data.ndim == 3 else 1) == channels
        assert scale[0] == pytest.approx(result.texel_m) and scale[1] == pytest.approx(result.texel_m)
        assert tie[3] == pytest.approx(world[4] - world[0] / 2) and tie[4] == pytest.approx(world[5] + world[0] / 2)
        assert 3072 in keys[4::4] and 9001 in keys[7::4]  # a user-defined CRS in metres
    assert result.crs == "" and not ws.path(result.world_file).with_suffix(".png.aux.xml").exists()
    with tifffile.TiffFile(ws.path(result.mosaic_tif)) as tif:
        rgba = tif.pages[0].asarray()
    np.testing.assert_array_equal(rgba[..., :3], png)
    assert ((rgba[..., 3] > 0).mean()) == pytest.approx(result.mosaic_coverage)
    dem = tifffile.imread(ws.path(result.dem_tif))
    assert dem.dtype == np.float32 and np.isfinite(dem).mean() > 0.2


def test_render_back_matches_an_image(meshed):
    survey, ws, result = meshed
    tracks = Tracks.load(ws.stage_dir("sfm") / "tracks.npz")
    points = tracks.xyz[tracks.track_lengths() >= 3]
    extent = float((np.percentile(points[:, :2], 99, 0) - np.percentile(points[:, :2], 1, 0)).max())
    mesh = height_mesh(points, extent / 150).on_texel_grid(result.texel_m)
    texture = cv2.imread(str(ws.path(result.mosaic_png)))[..., ::-1]
    assert texture.shape[:2] == (round((mesh.bounds[1, 1] - mesh.bounds[0, 1]) / result.texel_m) + 1,
                                 round((mesh.bounds[1, 0] - mesh.bounds[0, 0]) / result.texel_m) + 1)
    k = 4
    rendered = render_back(mesh, texture, tracks.world_from_cam[k], tracks.K, tracks.width, tracks.height)
    image = cv2.imread(str(survey / "images" / str(tracks.image_names[k])))[..., ::-1].astype(float)
    valid = np.isfinite(rendered).all(-1) & (rendered.sum(-1) > 0)
    assert valid.mean() > 0.2
    psnr = 10 * np.log10(255.0**2 / np.mean((rendered[valid] - image[valid]) ** 2))
    assert psnr > 26  # ~28 dB; nearest-texel look-up and unsnapped texel bounds gave ~24


def test_height_mesh_of_a_tilted_plane():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 2, (4000, 2))
    points = np.column_stack([xy, 0.1 * xy[:, 0] + 0.5])
    mesh = height_mesh(points, 0.05)
    normals = np.cross(mesh.vertices[mesh.faces[:, 1]] - mesh.vertices[mesh.faces[:, 0]],
                       mesh.vertices[mesh.faces[:, 2]] - mesh.vertices[mesh.faces[:, 0]])
    assert (normals[:, 2] > 0).all()
    z = surface_heights(mesh, np.array([[1.0, 1.0], [5.0, 5.0]]))
    assert z[0] == pytest.approx(0.6, abs=0.01) and np.isnan(z[1])


def test_cli_commands_on_the_workspace(meshed, capsys, tmp_path):
    import argparse

    from pipeline.cli_3d import add_commands

    survey, ws, _ = meshed
    parser = argparse.ArgumentParser()
    add_commands(parser.add_subparsers(dest="command", required=True), [])
    for argv in (["sfm", "--workspace", str(ws.root)],
                 ["mosaic", "--workspace", str(ws.root), "--source", "sparse", "--images-dir", str(survey / "images")],
                 ["consistency", "--workspace", str(ws.root), "--out", str(tmp_path / "colour"), "--folders",
                  f"raw={survey / 'images'}", "--folders", f"inair={survey / 'truth' / 'inair'}", "--truth-dir",
                  str(survey)]):
        args = parser.parse_args(argv)
        assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "registered 10 of 10" in out and "mosaic:" in out and "CIEDE2000" in out
    assert (tmp_path / "colour" / "colour.json").is_file()  # where it was told, not in a stage's folder
    with pytest.raises(SystemExit):  # consistency writes only where it is told (--out)
        parser.parse_args(["consistency", "--workspace", str(ws.root), "--folders", "raw=x"])


def test_the_texture_takes_the_frames_the_correct_stage_names(sfm, tmp_path):
    """Without --images-dir the mesh stage reads only the correct stage's result (its ``mesh_images``)."""
    from pipeline.workspace import Workspace
    from watergan.errors import UserInputError

    survey, shared, _ = sfm
    import shutil

    ws = Workspace(tmp_path / "ws")
    ws.folder("survey").symlink_to(survey)
    shutil.copytree(shared.folder("sfm"), ws.folder("sfm"))
    with pytest.raises(UserInputError, match="needs the correct stage"):
        ws.run("mesh", MeshConfig(source="sparse"))


def test_texel_grid_and_exported_uvs_follow_the_texel_centres(tmp_path):
    from pipeline.mesh import HeightMesh, export_mesh

    vertices = np.array([[0.0, 0.0, 0.0], [1.03, 0.0, 0.0], [1.03, 0.51, 0.0], [0.0, 0.51, 0.0]])
    faces, bounds = np.array([[0, 1, 2], [0, 2, 3]]), np.array([[0, 0], [1.03, 0.51]])
    mesh = HeightMesh(vertices=vertices, faces=faces, bounds=bounds)
    snapped = mesh.on_texel_grid(0.1)
    assert np.allclose(snapped.bounds, [[0.0, 0.51 - 0.6], [1.1, 0.51]])  # 12 x 7 texel centres, 0.1 apart
    texture = np.zeros((7, 12, 3), np.uint8)
    texture[0, 0] = texture[-1, -1] = 255
    glb, _, _ = export_mesh(snapped, texture, tmp_path)
    geometry = next(iter(trimesh.load(glb).geometry.values()))
    # glTF/OBJ uv 0..1 spans the image edges: the vertex at x0, y1 sits on texel (0, 0)'s centre
    corner = np.flatnonzero(np.all(np.isclose(geometry.vertices[:, :2], [0.0, 0.51]), axis=1))[0]
    assert np.allclose(geometry.visual.uv[corner], [0.5 / 12, 1 - 0.5 / 7])


def test_tsdf_mesh_with_atlas_uvs(sfm, tmp_path):
    from pipeline.dense import DenseConfig
    from pipeline.mesh import is_height_field, run_mesh_folder

    survey, ws, _ = sfm
    ws.run("dense", DenseConfig())  # skipped when tests/test_dense.py made it already
    tracks = Tracks.load(ws.stage_dir("sfm") / "tracks.npz")
    dense = ws.stage_dir("dense")
    result = run_mesh_folder(tracks, survey / "images", tmp_path, MeshConfig(mesh_kind="tsdf"),
                             dense / "fused_points.ply", dense / "fused_mesh.ply")
    assert result.mesh_kind == "tsdf"
    scene = trimesh.load(result.glb)
    geometry = next(iter(scene.geometry.values()))
    assert len(geometry.faces) == result.n_faces > 100
    assert geometry.visual.kind == "texture"
    texture = np.asarray(geometry.visual.material.baseColorTexture)
    assert texture.ndim == 3 and texture.shape[0] > 16 and texture[..., :3].max() > 0
    uv = geometry.visual.uv
    assert uv.min() >= 0 and uv.max() <= 1
    # the seafloor is a height field: auto keeps the 2.5D path for it; a vertical wall is not one
    rng = np.random.default_rng(0)
    assert is_height_field(tracks.xyz)
    assert not is_height_field(np.column_stack([rng.uniform(0, 1, 2000), np.zeros(2000), rng.uniform(0, 1, 2000)]))


def _rotation(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s], [s, c]])


def test_a_georeferenced_mosaic_places_the_cameras_at_their_positions(meshed, tmp_path):
    """survey.json's crs and positions (the truth camera centres turned by a 37-degree heading and moved to UTM
    numbers): the GeoTIFFs' ModelTransformation takes each camera centre's mosaic pixel to its given position within
    a few cm, the fitted rotation is the heading less the survey frame's own (from the cameras' orientations), the
    GeoKeys name the EPSG code, and the world file carries the same placement."""
    import json

    import tifffile

    from eval.synth import load_truth
    from pipeline.cli_3d import georeference_line
    from pipeline.mesh import run_mesh_folder

    survey, ws, local = meshed
    truth = load_truth(survey)
    heading, offset = 37.0, np.array([500000.0, 5000000.0])
    en = truth.world_from_cam[:, :2, 3] @ _rotation(heading).T + offset
    survey_json = tmp_path / "survey.json"
    survey_json.write_text(json.dumps({"frames": truth.frames, "crs": "EPSG:32633", "nav_easting_m": en[:, 0].tolist(),
                                       "nav_northing_m": en[:, 1].tolist()}))
    tracks = Tracks.load(ws.stage_dir("sfm") / "tracks.npz")
    result = run_mesh_folder(tracks, survey / "images", tmp_path / "out",
                             MeshConfig(images_dir=str(survey / "images"), source="sparse", progress=False),
                             survey_json=survey_json)
    assert result.crs == "EPSG:32633" and result.georef_frames == 10 and not result.georef_warning
    assert abs(result.georef_scale - 1) < 0.02 and result.georef_rms_m < 0.03
    # the survey frame's own heading in the truth's world, from the cameras' orientations alone
    index = {name: k for k, name in enumerate(truth.frames)}
    names = [str(n) for n in tracks.image_names]
    reg = np.flatnonzero(tracks.registered)
    truth_k = [index[names[k]] for k in reg]
    turn = sum(tracks.world_from_cam[k, :3, :3] @ truth.world_from_cam[t, :3, :3].T
               for k, t in zip(reg, truth_k, strict=True))
    frame_deg = np.degrees(np.arctan2(turn[1, 0], turn[0, 0]))
    assert abs((result.georef_rotation_deg - (heading - frame_deg) + 180) % 360 - 180) < 0.5
    # each camera centre's pixel in the local mosaic (its world file), through the ModelTransformation
    a, _, _, e, c, f = (float(v) for v in ws.path(local.world_file).read_text().split())
    xy = tracks.world_from_cam[reg, :2, 3]
    pixel = np.column_stack([(xy[:, 0] - c) / a + 0.5, (xy[:, 1] - f) / e + 0.5, np.zeros(len(xy)), np.ones(len(xy))])
    for name in (result.mosaic_tif, result.dem_tif):
        with tifffile.TiffFile(name) as tif:
            tags = tif.pages[0].tags
            matrix = np.array(tags["ModelTransformationTag"].value).reshape(4, 4)
            keys = tags["GeoKeyDirectoryTag"].value
            assert "ModelPixelScaleTag" not in tags and "ModelTiepointTag" not in tags
        geokeys = {keys[i]: keys[i + 3] for i in range(4, len(keys), 4)}
        assert geokeys == {1024: 1, 1025: 1, 3072: 32633, 3076: 9001}
        placed = (pixel @ matrix.T)[:, :2]
        assert np.abs(placed - en[truth_k]).max() < 0.05
    world = [float(v) for v in Path(result.world_file).read_text().split()]
    np.testing.assert_allclose(world[:4], [matrix[0, 0], matrix[1, 0], matrix[0, 1], matrix[1, 1]], rtol=1e-9)
    np.testing.assert_allclose(world[4:], (matrix @ [0.5, 0.5, 0, 1])[:2], atol=1e-6)
    assert "<SRS>EPSG:32633</SRS>" in (tmp_path / "out" / "mosaic.png.aux.xml").read_text()
    assert "georeferenced in EPSG:32633: rotation" in georeference_line(result)


def test_georeference_fit_errors_and_warnings():
    """Fewer than 3 positions or positions that do not spread: an error; a straight line is enough; a scale far
    from 1, a large residual or positions that fit better mirrored: a warning."""
    from pipeline.georeference import GeoreferenceError, fit_georeference, survey_positions

    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (8, 2))
    en = xy @ _rotation(-120.0).T + [400000.0, 6000000.0]
    fit = fit_georeference(xy, en, "epsg:32760")
    assert fit.crs == "EPSG:32760" and fit.rotation_deg == pytest.approx(-120.0) and fit.scale == pytest.approx(1.0)
    assert fit.rms_m < 1e-6 and not fit.warning
    np.testing.assert_allclose(fit.apply(xy), en, atol=1e-6)
    line = np.column_stack([np.linspace(0, 10, 5), np.zeros(5)])
    assert fit_georeference(line, line @ _rotation(30.0).T, "EPSG:32633").rotation_deg == pytest.approx(30.0)
    with pytest.raises(GeoreferenceError, match="at least 3 registered frames with a position; 2 have one"):
        fit_georeference(xy[:2], en[:2], "EPSG:32633")
    with pytest.raises(GeoreferenceError, match="cannot fix the survey's rotation"):
        fit_georeference(xy, np.tile(en[:1], (8, 1)) + rng.normal(0, 0.001, (8, 2)), "EPSG:32633")
    assert "scale 1.200 is 20 % from 1" in fit_georeference(xy, 1.2 * en, "EPSG:32633").warning
    assert "RMS residual" in fit_georeference(xy, en + rng.normal(0, 1.0, en.shape), "EPSG:32633").warning
    assert "easting and northing swapped" in fit_georeference(xy, en[:, ::-1], "EPSG:32633").warning
    with pytest.raises(GeoreferenceError, match="3 positions for 4 frames"):
        survey_positions({"crs": "EPSG:32633", "nav_easting_m": [1.0] * 3, "nav_northing_m": [1.0] * 3},
                         ["a", "b", "c", "d"])


def test_a_fit_that_fails_leaves_the_local_frame_with_a_warning(meshed, tmp_path, capsys):
    """Positions for only 2 of the frames: the mosaic is written in the local frame, the result says why."""
    import json

    from pipeline.mesh import run_mesh_folder

    survey, ws, _ = meshed
    tracks = Tracks.load(ws.stage_dir("sfm") / "tracks.npz")
    names = [str(n) for n in tracks.image_names][:2]
    survey_json = tmp_path / "survey.json"
    survey_json.write_text(json.dumps({"frames": names, "crs": "EPSG:32633", "nav_easting_m": [5e5, 5e5 + 1],
                                       "nav_northing_m": [5e6, 5e6]}))
    result = run_mesh_folder(tracks, survey / "images", tmp_path / "out",
                             MeshConfig(images_dir=str(survey / "images"), source="sparse", progress=False),
                             survey_json=survey_json)
    assert result.crs == "" and result.georef_warning.startswith("not georeferenced: georeferencing needs at least 3")
    assert "warning: georeference: not georeferenced" in capsys.readouterr().err
