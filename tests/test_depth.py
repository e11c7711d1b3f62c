"""Monocular vs stereo depth metrics on maps with a known scale and shift."""

import json

import numpy as np
import pytest

from eval.depth import (
    DepthCompareConfig,
    compare_depth,
    compare_depth_folders,
    fit_scale_shift,
    read_depth,
    write_depth_png,
)
from watergan.errors import UserInputError


def _reference(h=60, w=80, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    ref = 2.0 + 0.01 * x + 0.005 * y + 0.1 * rng.random((h, w))
    ref[:10, :10] = np.nan  # holes in the stereo map
    return ref


def test_scale_shift_recovered_exactly():
    ref = _reference()
    pred = (ref - 0.3) / 2.5  # ref = 2.5 pred + 0.3
    m, err = compare_depth(pred, ref, with_shift=True)
    assert m.scale == pytest.approx(2.5) and m.shift_m == pytest.approx(0.3)
    assert m.rmse_m < 1e-9 and m.abs_rel < 1e-9 and m.delta_125 == 1.0
    assert m.coverage == pytest.approx(1 - 100 / ref.size)
    assert np.isnan(err[:10, :10]).all() and np.nanmax(np.abs(err)) < 1e-9


def test_scale_only_leaves_shift_error():
    ref = _reference()
    pred = (ref - 0.3) / 2.5
    m, _ = compare_depth(pred, ref, with_shift=False)
    assert m.shift_m == 0.0
    assert m.rmse_m > 0.01  # a scale cannot absorb a shift
    s, _ = fit_scale_shift(pred[np.isfinite(ref)], ref[np.isfinite(ref)], False)
    assert m.scale == pytest.approx(s)


def test_known_error_values():
    ref = np.full((20, 20), 2.0)
    ref[:, 10:] = 4.0
    pred = ref.copy()
    pred[0, 0] = 3.0  # one pixel 1 m off, scale pinned by the others
    m, _ = compare_depth(pred, ref, fixed=(1.0, 0.0))
    assert m.rmse_m == pytest.approx(np.sqrt(1 / 400))
    assert m.rmse_over_range == pytest.approx(np.sqrt(1 / 400) / 2.0)
    assert m.abs_rel == pytest.approx(0.5 / 400)
    assert m.delta_125 == pytest.approx(399 / 400)


def test_too_few_valid_pixels_is_a_user_error():
    ref = np.full((10, 10), np.nan)
    with pytest.raises(UserInputError, match="valid"):
        compare_depth(np.ones((10, 10)), ref)


def test_folders_png_roundtrip_and_error_maps(tmp_path):
    pred_dir, ref_dir, out = tmp_path / "pred", tmp_path / "ref", tmp_path / "out"
    pred_dir.mkdir()
    ref_dir.mkdir()
    for k, scale in enumerate([2.0, 3.0]):
        ref = _reference(seed=k)
        write_depth_png(ref_dir / f"f{k}.png", ref)
        np.save(pred_dir / f"f{k}.npy", np.nan_to_num(ref / scale, nan=0.0))  # files: 0 = no value
    np.save(pred_dir / "orphan.npy", np.ones((60, 80)))
    assert np.nanmax(np.abs(read_depth(ref_dir / "f0.png") - _reference(seed=0))) <= 0.0005 + 1e-12

    result = compare_depth_folders(pred_dir, ref_dir, out, DepthCompareConfig(pred_dir=str(pred_dir)))
    assert result.alignment == "scale, per image"
    assert result.per_image["f0"].scale == pytest.approx(2.0, rel=1e-3)
    assert result.per_image["f1"].scale == pytest.approx(3.0, rel=1e-3)
    assert result.overall.rmse_m < 1e-3 and result.skipped == ["orphan"]
    assert len(result.error_maps) == 2 and all((out / "errors" / f"f{k}.png").is_file() for k in range(2))
    record = json.loads((out / "metrics.json").read_text())
    assert record["overall"]["n_valid"] == result.overall.n_valid

    glob = compare_depth_folders(pred_dir, ref_dir, out, DepthCompareConfig(pred_dir=str(pred_dir), per_image=False))
    assert glob.alignment == "scale, global" and glob.overall.rmse_m > 0.1  # one scale cannot fit both
