"""The per-image stages on a Dask cluster give the same outputs as a local run.

A ``distributed.LocalCluster`` with two worker processes (``processes=True``: every function and
argument shipped to a worker really is pickled and imported there) runs correction, dense depth,
the baselines and the colour sampling; their files and arrays are compared with the local run's.
The 3D stages reuse the session's small simulated survey and its SfM (tests/test_sfm.py)."""

import json
import shutil
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SCRATCH
from test_sfm import survey_and_sfm

from eval.colour import observation_colours
from eval.tables import EvaluateConfig
from eval.tracks import Tracks
from pipeline.dense import DenseConfig, run_dense_folder
from pipeline.evaluate import run_evaluate
from pipeline.workspace import Workspace
from watergan.errors import UserInputError
from watergan.nets.restorer import Restorer, RestorerWidths
from watergan.parallel import chunks, map_tasks, rows_by_label
from watergan.restore_folder import correct_folder
from watergan.train_restorer import save_restorer

TINY = RestorerWidths(depth_core=(4, 6, 8, 8), colour_core=(4, 6, 8, 8), full_res=4)


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded worker processes; yields (client, scheduler address)."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as local, \
            Client(local, set_as_default=False) as client:
        yield client, local.scheduler_address


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name not in ("summary.json", "result.json", "config.json")}


def test_local_map_keeps_order_and_chunks():
    assert map_tasks(abs, [-3, 1, -2], progress=False) == [3, 1, 2]
    assert chunks(list(range(5)), 2) == [[0, 1], [2, 3], [4]]
    rows = rows_by_label(np.array([2, 0, 2, 1, 0]), [0, 1, 2, 3])
    assert [r.tolist() for r in rows] == [[1, 4], [3], [0, 2], []]


def test_bad_scheduler_is_a_clear_error_quickly():
    began = time.perf_counter()
    with pytest.raises(UserInputError, match="tcp://127.0.0.1:9"):
        map_tasks(abs, [1], "tcp://127.0.0.1:9", progress=False, timeout_s=1)
    with pytest.raises(UserInputError, match="not a Dask scheduler address"):
        map_tasks(abs, [1], "nonsense", progress=False)
    assert time.perf_counter() - began < 10


@pytest.mark.slow
def test_correction_on_the_cluster_matches_local(cluster, tmp_path):
    client, _ = cluster
    save_restorer(tmp_path / "model" / "restorer.pt", Restorer(TINY, depth_hw=(16, 16)).eval())
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(1)
    for k in range(5):
        cv2.imwrite(str(images / f"f{k}.png"), rng.integers(0, 256, (37, 45, 3), dtype=np.uint8))
    cv2.imwrite(str(images / "g16.png"), rng.integers(0, 65536, (40, 48, 3), dtype=np.uint16))
    (images / "h_garbage.png").write_bytes(b"not an image")

    local = correct_folder(tmp_path / "model", images, tmp_path / "local", batch_size=2, progress=False)
    remote = correct_folder(tmp_path / "model", images, tmp_path / "remote", batch_size=2, progress=False,
                            scheduler=client, chunk_size=3)  # chunks of 4: batches as locally
    assert (remote.corrected, remote.already_done, len(remote.failed)) == (6, 0, 1) == \
        (local.corrected, local.already_done, len(local.failed))
    assert "h_garbage.png" in remote.failed[0]
    expected, got = _files(tmp_path / "local"), _files(tmp_path / "remote")
    assert sorted(got) == sorted(expected) and len(got) == 18
    for name in expected:
        if name.endswith(".npy"):
            a, b = (np.load(folder / name) for folder in (tmp_path / "local", tmp_path / "remote"))
            assert np.allclose(a, b, atol=1e-6), name
        else:
            a, b = (cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED).astype(int)
                    for folder in (tmp_path / "local", tmp_path / "remote"))
            assert np.abs(a - b).max() <= 1, name  # one quantisation step at most (torch's thread count)
    again = correct_folder(tmp_path / "model", images, tmp_path / "remote", progress=False, scheduler=client)
    assert again.corrected == 0 and again.already_done == 6


@pytest.mark.slow
def test_dense_depth_on_the_cluster_matches_local(cluster, tmp_path):
    _, address = cluster
    survey, ws, record = survey_and_sfm()
    tracks = Tracks.load(ws.path(record.tracks))
    baseline = json.loads((survey / "camera.json").read_text())["baseline_m"]
    args = (tracks, survey / "images")
    local = run_dense_folder(*args, tmp_path / "local", DenseConfig(fuse=False), baseline, survey / "right")
    remote = run_dense_folder(*args, tmp_path / "remote", DenseConfig(fuse=False, scheduler=address), baseline,
                              survey / "right")
    assert remote.pairs == local.pairs and remote.coverage == local.coverage and remote.skipped == local.skipped
    assert len(local.pairs) == 10
    assert _files(tmp_path / "remote") == _files(tmp_path / "local")


@pytest.mark.slow
def test_baselines_and_colour_sampling_on_the_cluster_match_local(cluster):
    client, address = cluster
    survey, shared, record = survey_and_sfm()
    tracks = Tracks.load(shared.path(record.tracks))
    runs = {}
    for label, scheduler in (("local", ""), ("remote", address)):
        ws = Workspace(Path(tempfile.mkdtemp(prefix=f"watergan-par-{label}-", dir=SCRATCH)) / "ws")
        shutil.copytree(survey, ws.folder("survey"))
        shutil.copytree(shared.folder("sfm"), ws.folder("sfm"))
        cfg = EvaluateConfig(methods=("raw", "gray_world", "jaffe", "seathru", "oracle"), range_source="truth",
                             scheduler=scheduler)
        result = run_evaluate(ws, cfg)
        runs[label] = ws.folder("eval"), result
    (local_dir, local), (remote_dir, remote) = runs["local"], runs["remote"]
    assert remote.methods == local.methods == ["raw", "gray_world", "jaffe", "seathru", "oracle"]
    assert _files(remote_dir / "baselines") == _files(local_dir / "baselines")
    assert len(_files(local_dir / "baselines")) == 50
    with np.load(local_dir / "consistency_points.npz") as a, np.load(remote_dir / "consistency_points.npz") as b:
        assert sorted(a) == sorted(b) and all(np.array_equal(a[m], b[m]) for m in a)
    assert remote.consistency_variance == local.consistency_variance
    assert remote.mean_board_distance == local.mean_board_distance

    here = observation_colours(tracks, survey / "images")
    there = observation_colours(tracks, survey / "images", scheduler=client, chunk_size=3)
    assert np.isfinite(here).any() and np.array_equal(here, there, equal_nan=True)
