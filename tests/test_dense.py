"""Dense SGBM depth on the simulated stereo survey: coverage and error against rendered depth."""

import numpy as np
import pytest
from test_sfm import survey_and_sfm

from eval.depth import read_depth
from eval.tracks import Tracks
from pipeline.dense import (
    DenseConfig,
    ply_complete,
    rectified_pair_depth,
    rectifying_rotation,
    refine_disparity,
    run_dense,
    run_dense_folder,
    write_checked,
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
