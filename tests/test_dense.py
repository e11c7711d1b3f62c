"""Dense SGBM depth on the simulated stereo survey: coverage and error against rendered depth; implausible depths
dropped, never fatal."""

import numpy as np
import pytest
from test_sfm import survey_and_sfm

from eval.depth import read_depth
from eval.tracks import Tracks
from pipeline.dense import (
    DenseConfig,
    PairJob,
    frame_far_limit,
    pair_depth,
    ply_complete,
    rectified_pair_depth,
    rectifying_rotation,
    refine_disparity,
    run_dense,
    run_dense_folder,
    write_checked,
    write_frame_depth,
)


@pytest.fixture(scope="module")
def sfm():
    return survey_and_sfm()


def _errors(survey, depth_dir, names):
    coverage, errors = [], []
    for name in names:
        depth = read_depth(depth_dir / name)
        true = read_depth(survey / "truth" / "depth" / name)
        valid = np.isfinite(depth) & np.isfinite(true)
        coverage.append(valid.mean())
        errors.append(np.abs(depth[valid] - true[valid]) / true[valid])
    return float(np.mean(coverage)), np.concatenate(errors)


def test_rig_sgbm_coverage_and_error(sfm):
    survey, ws, _ = sfm
    record = ws.run("dense", DenseConfig())
    result = record
    assert set(result.pairs.values()) == {"rig"} and not result.skipped
    coverage, rel = _errors(survey, ws.path(result.depth_dir), result.pairs)
    assert coverage > 0.7 and result.mean_coverage == pytest.approx(coverage, abs=0.01)
    assert np.median(rel) < 0.005  # about 0.05 px of disparity at 11 px (SGBM alone: ~0.015)
    assert result.n_fused_points > 1000 and ws.path(result.mesh_ply).is_file()
    true_max = max(np.nanmax(read_depth(survey / "truth" / "depth" / name)) for name in result.pairs)
    assert set(result.far_limit_m) == set(result.too_far_fraction) == set(result.pairs)
    assert min(result.far_limit_m.values()) > true_max and result.mean_too_far_fraction < 0.001


def test_neighbour_pairs_without_rig(sfm, tmp_path):
    survey, ws, record = sfm
    tracks = Tracks.load(ws.path(record.tracks))
    result = run_dense_folder(tracks, survey / "images", tmp_path, DenseConfig(pairs="neighbours", fuse=False))
    assert all(partner != "rig" and partner != name for name, partner in result.pairs.items())
    coverage, rel = _errors(survey, tmp_path / "depth", result.pairs)
    assert coverage > 0.25 and np.median(rel) < 0.01


def test_rectification_of_a_pure_x_baseline_is_identity():
    left = np.eye(4)
    right = np.eye(4)
    right[0, 3] = 0.2
    R, b = rectifying_rotation(left, right)
    assert b == pytest.approx(0.2) and np.allclose(R, np.eye(3))


def _shifted_pair(disparity: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random texture (240x320) and the same texture moved left by ``disparity`` pixels."""
    import cv2

    rng = np.random.default_rng(seed)
    texture = cv2.resize((rng.random((60, 80)) * 255).astype(np.float32), (320, 240), interpolation=cv2.INTER_CUBIC)
    shift = np.array([[1.0, 0, -disparity], [0, 1, 0]])
    right = cv2.warpAffine(texture, shift, (320, 240), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return np.clip(texture, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("disparity", [16.0, 16.3, 16.5])
def test_fronto_parallel_plane_depth(disparity):
    left, right = _shifted_pair(disparity)
    K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
    pose_r = np.eye(4)
    pose_r[0, 3] = 0.2
    depth = rectified_pair_depth(left, right, K, np.eye(4), pose_r, (2.0, 3.0), DenseConfig())
    inner = depth[20:-20, 40:-40]
    true = 200 * 0.2 / disparity  # z = f b / d, about 2.5
    assert np.isfinite(inner).mean() > 0.9 and np.nanmedian(inner) == pytest.approx(true, rel=0.002)


def test_subpixel_refinement_removes_pixel_locking():
    left, right = _shifted_pair(12.3, seed=1)
    start = np.full(left.shape, 12.0, np.float32)  # an integer-locked initial estimate
    start[:5] = np.nan
    refined = refine_disparity(left.astype(np.float32), right.astype(np.float32), start, sigma=2.5)
    inner = refined[20:-20, 40:-40]
    assert np.isnan(refined[:5]).all() and np.isfinite(inner).all()
    assert np.median(np.abs(inner - 12.3)) < 0.01


def test_patch_match_without_cuda_is_a_clear_error(sfm):
    import pycolmap

    from pipeline.dense import dense_method
    from watergan.errors import UserInputError

    _, ws, _ = sfm
    if pycolmap.has_cuda:
        pytest.skip("pycolmap has CUDA here")
    assert dense_method("auto") == "sgbm" and dense_method("sgbm") == "sgbm"
    with pytest.raises(UserInputError, match="patch_match needs pycolmap built with CUDA"):
        run_dense(ws, DenseConfig(method="patch_match"))
    with pytest.raises(UserInputError, match="method must be"):
        dense_method("mvs")


def test_read_colmap_array(tmp_path):
    from pipeline.dense import read_colmap_array

    depth = np.arange(12, dtype=np.float32).reshape(3, 4)
    path = tmp_path / "a.geometric.bin"
    path.write_bytes(b"4&3&1&" + depth.astype("<f4").tobytes())  # COLMAP: x fastest, then y, then channel
    assert np.array_equal(read_colmap_array(path), depth)


def test_a_mesh_file_cut_short_is_an_error_and_not_kept(tmp_path):
    """open3d reports a file cut short (a full disk) as written: the fused geometry is renamed into place only when
    the file is as long as its header says."""
    import open3d as o3d

    from watergan.io import WriteError

    rng = np.random.default_rng(0)
    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(rng.random((50, 3), np.float32)))
    cloud.point.colors = o3d.core.Tensor(rng.random((50, 3), np.float32))
    write_checked(tmp_path / "points.ply", cloud, o3d.t.io.write_point_cloud)
    assert o3d.t.io.read_point_cloud(str(tmp_path / "points.ply")).point.positions.shape[0] == 50
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_sphere(0.5))
    write_checked(tmp_path / "mesh.ply", mesh, o3d.t.io.write_triangle_mesh)
    assert ply_complete(tmp_path / "mesh.ply")

    def cut_short(path, geometry):
        o3d.t.io.write_point_cloud(path, geometry)
        with open(path, "r+b") as f:
            f.truncate(f.seek(0, 2) - 7)
        return True

    with pytest.raises(WriteError, match=r"cannot write .*fused.ply: open3d.s file is shorter than its header says "
                                         r"\(a full disk\?\); free some space"):
        write_checked(tmp_path / "fused.ply", cloud, cut_short)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.ply", "points.ply"]


def test_wild_depths_are_dropped_and_counted_never_fatal(tmp_path):
    """Depths beyond the far limit (a mismatch on open water), beyond what the millimetre PNG holds, infinite, NaN or
    negative are written as no value and read back as such, with the scene mask's pixels; the far limit is a
    multiple of the frame's 99th-percentile sparse depth (the survey's for a frame with few points), never more than
    the PNG holds."""
    from watergan.io import MAX_DEPTH_PNG_M, DataError, write_depth_png

    depth = np.full((20, 30), 2.0)
    wild = [(0, 0, 1e6), (0, 1, 70.0), (1, 1, 9.0), (2, 2, np.inf), (3, 3, np.nan), (4, 4, -1.0), (5, 5, 0.0)]
    for y, x, value in wild:
        depth[y, x] = value
    scene = np.ones(depth.shape, bool)
    scene[-2:] = False
    kept, coverage, too_far = write_frame_depth(tmp_path / "d.png", depth, 6.0, scene)
    back = read_depth(tmp_path / "d.png")
    gone = ~scene
    for y, x, _ in wild:
        gone[y, x] = True
    assert np.isnan(back[gone]).all() and np.isnan(kept[gone]).all()
    assert (back[~gone] == 2.0).all() and (kept[~gone] == 2.0).all()
    assert too_far == pytest.approx(3 / scene.sum()) and coverage == pytest.approx((~gone).sum() / scene.sum())
    write_frame_depth(tmp_path / "e.png", depth, 1e9)  # a limit beyond the PNG's: 70 m still dropped
    assert np.isnan(read_depth(tmp_path / "e.png")[0, :2]).all() and read_depth(tmp_path / "e.png")[1, 1] == 9.0
    assert write_frame_depth(tmp_path / "f.png", np.full((4, 4), 8.0), 6.0)[1:] == (0.0, 1.0)
    assert not (tmp_path / "f.png").exists()  # no depth: nothing written
    with pytest.raises(DataError, match="65.535"):  # the writer itself still refuses a caller's far value
        write_depth_png(tmp_path / "far.png", np.full((2, 2), 70.0))
    assert frame_far_limit(np.full(20, 2.0), np.full(100, 5.0), 3.0) == pytest.approx(6.0)
    assert frame_far_limit(np.full(5, 2.0), np.full(100, 5.0), 3.0) == pytest.approx(15.0)
    assert frame_far_limit(np.full(20, 40.0), np.full(100, 5.0), 3.0) == MAX_DEPTH_PNG_M


def test_a_pair_s_depth_beyond_the_far_limit_or_outside_the_scene_is_no_value(tmp_path):
    """A fronto-parallel plane at 2.46 m: with a far limit of 2 m every depth is dropped (nothing written, counted as
    too far); with the scene mask leaving out the left half, those pixels have no depth and the coverage is the
    scene's."""
    import cv2

    from watergan.io import write_scene_mask

    left, right = _shifted_pair(16.3)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    K = np.array([[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]])
    pose_r = np.eye(4)
    pose_r[0, 3] = 0.2
    scene = np.ones(left.shape, bool)
    scene[:, :160] = False
    write_scene_mask(tmp_path / "scene.png", scene)

    def job(far_limit_m, mask=None):
        return PairJob("l.png", tmp_path / "l.png", tmp_path / "r.png", "rig", K, np.eye(4), pose_r, (2.0, 3.0),
                       DenseConfig(), tmp_path / "depth.png", far_limit_m, mask)

    cover, too_far, depth = pair_depth(job(2.0))
    assert (cover, depth) == (0.0, None) and too_far > 0.7 and not (tmp_path / "depth.png").exists()
    cover, too_far, depth = pair_depth(job(65.535, tmp_path / "scene.png"))
    back = read_depth(tmp_path / "depth.png")
    assert np.isnan(back[:, :160]).all() and np.isnan(depth[:, :160]).all() and too_far == 0.0
    assert cover == pytest.approx(np.isfinite(back).sum() / scene.sum()) and cover > 0.8
    assert np.nanmedian(back) == pytest.approx(200 * 0.2 / 16.3, rel=0.002)


def test_sparse_depth_interpolates_a_plane_and_leaves_gaps_and_outliers_out():
    """Depth from the sparse points a frame sees (a forward-moving camera's): on a tilted plane the interpolation
    is within 0.1 % of the plane's depth (2 % at the edges of the points' cover), a band without points stays empty,
    a wrong point is dropped; a baseline along the view direction is a forward pair, one across it is not."""
    from pipeline.sparse_depth import pair_is_forward, sparse_depth

    rng = np.random.default_rng(0)
    w, h = 160, 120
    xy = rng.uniform([0, 0], [w - 1, h - 1], (1500, 2))
    xy = xy[(xy[:, 1] < 40) | (xy[:, 1] > 70)]  # no point in rows 40-70

    def plane(x, y):
        return 2.0 + 0.01 * x + 0.02 * y

    z = plane(xy[:, 0], xy[:, 1])
    z[0] *= 3.0  # one wrong triangulation
    depth = sparse_depth(xy, z, w, h, max_edge_frac=0.1)
    yy, xx = np.mgrid[0:h, 0:w]
    truth = plane(xx, yy)
    inside = np.isfinite(depth)
    assert inside[10:30, 10:150].mean() > 0.95 and inside[50:60].mean() == 0
    error = np.abs(depth[inside] / truth[inside] - 1)
    assert np.median(error) < 0.001 and error.max() < 0.02  # the largest at the edges of the points' cover
    forward, sideways = np.eye(4), np.eye(4)
    forward[:3, 3] = [0.0, 0.05, 1.0]
    sideways[:3, 3] = [1.0, 0.0, 0.1]
    assert pair_is_forward(np.eye(4), forward) and not pair_is_forward(np.eye(4), sideways)
