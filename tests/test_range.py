"""pipeline.range: each pixel's range (the dense range, the fused mesh's where it has none or disagrees), the frames
the water's fine grid is measured on, and the correction's normals; the range stage on the session's tiny survey."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from eval.observations import WaterFrame
from watergan.formation.inverse import flat_floor_range

W, H = 96, 72
K = np.array([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1.0]])


def looking_down(altitude_m: float) -> np.ndarray:
    """A camera at (0, 0, altitude) looking straight down at the seafloor z = 0 (camera y = world -y)."""
    m = np.eye(4)
    m[:3, :3] = np.diag([1.0, -1.0, -1.0])
    m[:3, 3] = [0.0, 0.0, altitude_m]
    return m


def seafloor_mesh(path: Path) -> Path:
    """The seafloor z = 0, 4 m x 4 m, as a fused mesh's PLY."""
    import open3d as o3d

    plane = o3d.geometry.TriangleMesh()
    plane.vertices = o3d.utility.Vector3dVector(np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], float))
    plane.triangles = o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]]))
    o3d.io.write_triangle_mesh(str(path), plane)
    return path


@pytest.fixture(scope="module")
def range_workspace():
    """The session's small simulated stereo survey (tests/test_sfm.py: 10 frames of 320x240, real pycolmap SfM)
    with the dense stage run on it (its depth maps and fused mesh)."""
    from test_sfm import survey_and_sfm

    from pipeline.dense import DenseConfig

    survey, ws, _ = survey_and_sfm()
    ws.run("dense", DenseConfig(progress=False))
    return survey, ws


def test_the_range_stage_writes_each_frames_range_map_from_the_dense_range_and_the_mesh(range_workspace, capsys):
    """`watergan range --workspace WS` writes a map per frame: the dense range where the fused mesh agrees, the mesh's
    where the dense range has none (or disagrees by more than 1 %); a second run is skipped; the water stage takes its
    normals' smoothing from it."""
    from eval.tracks import Tracks
    from pipeline.cli import main
    from pipeline.range import water_frame
    from pipeline.water import WaterStage, range_settings
    from watergan.io import read_millimetres

    survey, ws = range_workspace
    assert main(["range", "--workspace", str(ws.root), "--no-progress", "--force"]) == 0
    result = ws.result("range")
    assert f"range: {result.n_frames} range maps" in capsys.readouterr().out
    names = sorted(p.name for p in (survey / "images").iterdir())
    assert result.n_frames == len(names) and sorted(p.name for p in ws.path(result.range_dir).iterdir()) == names
    assert 0.0 < result.mesh_fraction < 0.5 and result.range_missing < 0.2
    assert ws.path(result.range_dir).parent == ws.folder("range")

    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    frame = water_frame(tracks, 0, survey / "images", ws.path(ws.result("dense").depth_dir))
    mapped = read_millimetres(ws.path(result.range_dir) / f"{Path(frame.name).stem}.png") / 1000.0
    dense = np.nan_to_num(frame.range_m.astype(np.float64))
    both = (dense > 0) & (mapped > 0)
    kept = both & (np.abs(mapped - dense) <= 0.0015)  # the dense range, to the millimetre of the file
    assert kept.sum() > 0.5 * both.sum()
    assert (np.abs(mapped[both & ~kept] / dense[both & ~kept] - 1) > 0.009).all()  # the mesh's where they disagree
    assert ((dense == 0) & (mapped > 0)).any()  # the mesh's where the dense range has none

    stamp = (ws.folder("range") / "result.json").stat().st_mtime_ns
    assert main(["range", "--workspace", str(ws.root), "--no-progress"]) == 0  # done: printed, not rerun
    assert (ws.folder("range") / "result.json").stat().st_mtime_ns == stamp
    assert range_settings(ws, WaterStage()).measure.normal_smooth_px == result.normal_smooth_px


def test_the_water_stage_needs_the_range_stage(tmp_path):
    """A workspace with the sfm and dense stages but no range maps: the water stage says to run the range stage."""
    from pipeline.dense import DenseConfig, DenseResult
    from pipeline.sfm import SfmConfig, SfmResult
    from pipeline.stages import STAGES
    from pipeline.water import WaterStage
    from pipeline.workspace import Workspace
    from watergan.errors import UserInputError

    ws = Workspace(tmp_path / "ws")
    ws.save("sfm", SfmConfig(), SfmResult(model_dir="", tracks=f"{STAGES['sfm'].folder}/tracks.npz", n_images=3,
                                          n_registered=3, n_points=0, mean_track_length=0.0,
                                          mean_reprojection_error_px=0.0, matching="", scale_method="stereo",
                                          scale_factor=1.0, scale_spread=0.0, seconds=0.0))
    ws.save("dense", DenseConfig(), DenseResult(depth_dir="", pairs={}, coverage={}, mean_coverage=1.0))
    with pytest.raises(UserInputError, match="the water estimate needs the range stage .*watergan range --workspace"):
        ws.run("water", WaterStage(progress=False))


def test_the_survey_frames_are_read_on_demand(range_workspace, monkeypatch):
    """The frames are read when indexed and only the last CACHED_FRAMES kept: a long survey's frames are never all in
    memory, and what is read is what water_frame reads."""
    import pipeline.range as ranges
    from eval.tracks import Tracks

    survey, ws = range_workspace
    tracks = Tracks.load(ws.path(ws.result("sfm").tracks))
    depth = ws.path(ws.result("dense").depth_dir)
    monkeypatch.setattr(ranges, "CACHED_FRAMES", 2)
    frames = ranges.water_frames(tracks, ws.stage_dir("survey") / "images", depth)
    assert len(frames) == len(tracks.image_names) > 2
    first = frames[0]
    assert frames[0] is first and frames[-1] is frames[len(frames) - 1]
    for f in frames:
        assert f.image.shape[:2] == f.range_m.shape
    assert frames[0] is not first  # pushed out of the cache by the loop, read again
    alone = ranges.water_frame(tracks, 0, ws.stage_dir("survey") / "images", depth)
    np.testing.assert_array_equal(frames[0].image, alone.image)
    np.testing.assert_array_equal(frames[0].range_m, alone.range_m)
    with pytest.raises(IndexError):
        frames[len(frames)]


def test_the_correction_range_prefers_the_fused_mesh_where_the_dense_range_disagrees(tmp_path):
    """Dense range kept where the fused mesh agrees within 1 %; the mesh's range where the dense range is missing
    or off (an outlier); a frame without a pose keeps its dense range. The fine grid's frames take the range maps'
    range only where the dense range is missing."""
    from pipeline.range import MeshFilledFrames, correction_range, mesh_range, write_range_maps

    mesh_ply = seafloor_mesh(tmp_path / "fused_mesh.ply")
    m = looking_down(2.0)
    true_range = flat_floor_range(2.0, K, H, W)
    dense = true_range * 1.004  # agrees within 1 %
    dense[:10] = np.nan  # no dense range
    dense[30:40, 30:40] *= 1.1  # an outlier patch
    frame = WaterFrame(name="a.png", image=np.zeros((H, W, 3), np.float32), range_m=dense.astype(np.float32),
                       world_from_cam=m)
    r, from_mesh, _ = correction_range(frame, K, mesh_ply, agreement=0.01)
    kept = np.ones((H, W), bool)
    kept[:10] = False
    kept[30:40, 30:40] = False
    np.testing.assert_allclose(r[kept], dense[kept], rtol=1e-6)
    np.testing.assert_allclose(r[~kept], true_range[~kept], rtol=1e-4)
    np.testing.assert_array_equal(from_mesh, ~kept)
    no_pose = WaterFrame(name="b.png", image=frame.image, range_m=frame.range_m, world_from_cam=None)
    r, from_mesh, _ = correction_range(no_pose, K, mesh_ply, agreement=0.01)
    assert not from_mesh.any() and np.isnan(r[:10]).all()

    # the range maps as the stage writes them (millimetres), and the fine grid's frames measured on them: the mesh's
    # range only where the dense range has none (the outlier patch stays), with normals
    maps = tmp_path / "range"
    mesh_share, missing = write_range_maps(maps, [frame, no_pose], K, mesh_ply, 0.01, progress=False)
    assert mesh_share == pytest.approx((~kept).mean() / 2) and missing == pytest.approx(10 / H / 2)
    filled = MeshFilledFrames([frame, no_pose], K, maps, smooth_px=4.0)
    assert MeshFilledFrames([frame], K, maps, None)[0].normals_cam is None  # a stack that reads none
    np.testing.assert_allclose(filled[0].range_m[10:], dense[10:], rtol=1e-6)
    np.testing.assert_allclose(filled[0].range_m[:10], true_range[:10], atol=1e-3)
    assert filled[0].normals_cam.shape == (H, W, 3) and np.isfinite(filled[0].normals_cam).all()
    assert filled[1] is no_pose and MeshFilledFrames([frame], K, None, 4.0)[0] is frame
    some = np.zeros((H, W), bool)
    some[5, 7] = some[40, 3] = True  # rays cast for these pixels only
    cast, _ = mesh_range(mesh_ply, frame, K, None, where=some)
    np.testing.assert_allclose(cast[some], true_range[some], rtol=1e-4)
    assert np.isnan(cast[~some]).all()


def test_the_correction_takes_its_normals_from_the_dense_range_not_across_the_mesh_seams():
    """Where the correction's range switched to the mesh with a 2 % step, the normals of that range tilt along
    the seam; the correction's normals are the dense range's, and the mesh range's only where the dense has none."""
    from pipeline.range import correction_normals
    from watergan.formation.inverse import normals_from_range

    true_range = flat_floor_range(2.0, K, H, W)  # a level floor 2 m below
    dense = true_range.copy()
    dense[:, :20] = np.nan  # no dense range: the mesh fills it
    combined = true_range.copy()
    combined[25:50, 35:65] *= 1.02  # the mesh's range where it disagreed with the dense by 2 %
    frame = WaterFrame(name="a.png", image=np.zeros((H, W, 3), np.float32), range_m=dense.astype(np.float32),
                       world_from_cam=None)
    floor = np.array([0.0, 0.0, -1.0])  # facing the camera

    def tilt_deg(normals):
        return np.degrees(np.arccos(np.clip(normals @ floor, -1.0, 1.0)))

    assert tilt_deg(normals_from_range(combined, K, 4)).max() > 5.0  # the seam
    normals = correction_normals(frame, combined, K, 4)
    assert np.isfinite(normals).all()
    assert tilt_deg(normals).max() < 0.5
