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


def _floor_with_mound(altitude=2.0, h=60, w=80, mound_m=0.3):
    """A nadir camera (f = 60 px) over a level seafloor ``altitude`` below, a mound rising ``mound_m`` towards
    the camera over the image's centre: the camera and the camera-z depth and height above the floor of each pixel."""
    from watergan.data import PinholeIntrinsics

    camera = PinholeIntrinsics(60.0, 60.0, (w - 1) / 2, (h - 1) / 2, w, h)
    y, x = np.mgrid[0:h, 0:w]
    bump = mound_m * np.clip(1 - ((x - w / 2) ** 2 + (y - h / 2) ** 2) / 12.0**2, 0, None)
    return camera, altitude - bump, bump


def test_planes_beside_the_net_over_all_and_relief_pixels(tmp_path):
    """A level floor with a mound: the flat seafloor at the navigation's altitude is exact off the mound and wrong
    on it by the mound's height; a net that sees the mound is exact on it, one that predicts the floor's shape is
    as wrong as the floor (ratio 1); the best plane is the floor (the mound is a small share of the points)."""
    from eval.depth import BEST_PLANE, FLOOR, FLOOR_ALIGNED, NET, RELIEF_M, Navigation, best_plane
    from watergan.formation.inverse import flat_floor_depth

    camera, ref, bump = _floor_with_mound()
    mound = bump > 0.05
    np.testing.assert_allclose(flat_floor_depth(2.0, camera.K, 60, 80), 2.0)
    plane, distance = best_plane(np.where(bump > 0, np.nan, ref), camera.K)
    np.testing.assert_allclose(plane, 2.0, atol=1e-9)
    assert np.nanmax(distance) < 1e-9

    tilted = flat_floor_depth(2.0, camera.K, 60, 80, np.array([0.0, np.sin(0.3), np.cos(0.3)]))
    plane, distance = best_plane(tilted, camera.K)  # a tilted floor is a plane too
    np.testing.assert_allclose(plane, tilted, rtol=1e-9)

    ref_dir, seen, floor_like = tmp_path / "ref", tmp_path / "seen", tmp_path / "floor"
    for folder in (ref_dir, seen, floor_like):
        folder.mkdir()
    write_depth_png(ref_dir / "f0.png", ref)
    np.save(seen / "f0.npy", ref / 4.0)  # a relative depth with the mound, any scale
    np.save(floor_like / "f0.npy", np.full_like(ref, 0.5))
    nav = Navigation(camera, {"f0": 2.0})
    good = compare_depth_folders(seen, ref_dir, tmp_path / "a", DepthCompareConfig(pred_dir=str(seen)), nav)
    assert set(good.sources) == {NET, FLOOR, FLOOR_ALIGNED, BEST_PLANE} and good.ratio_to == FLOOR_ALIGNED
    assert good.sources[FLOOR].alignment == "none" and good.sources[FLOOR_ALIGNED].alignment == "scale, per image"
    assert good.relief_fraction == pytest.approx(mound.mean(), abs=0.01)
    assert good.sources[NET].relief.rmse_m < 1e-3
    relief = best_plane(ref, camera.K)[1] > RELIEF_M  # the mound's pixels, as the plane through it all sees them
    assert (relief == mound).mean() > 0.99
    floor_on_mound = np.sqrt(np.mean((2.0 - ref[relief]) ** 2))  # the floor misses the mound by its height
    assert good.sources[FLOOR].relief.rmse_m == pytest.approx(floor_on_mound, rel=0.01)
    assert good.relief_rmse_ratio < 0.01
    assert (tmp_path / "a" / "errors_floor" / "f0.png").is_file()
    flat = compare_depth_folders(floor_like, ref_dir, tmp_path / "b", DepthCompareConfig(pred_dir=str(floor_like)),
                                 nav)
    assert flat.relief_rmse_ratio == pytest.approx(1.0, rel=1e-6) and flat.all_rmse_ratio == pytest.approx(1.0)

    metric = compare_depth_folders(seen, ref_dir, tmp_path / "m", DepthCompareConfig(pred_dir=str(seen), metric=True),
                                   nav)  # as it is: a quarter of the depth
    assert metric.ratio_to == FLOOR and FLOOR_ALIGNED not in metric.sources and metric.alignment == "none"
    assert metric.overall.rmse_m == pytest.approx(np.sqrt(np.mean((0.75 * ref) ** 2)), rel=1e-3)
    no_nav = compare_depth_folders(seen, ref_dir, tmp_path / "c", DepthCompareConfig(pred_dir=str(seen)),
                                   Navigation(camera))
    assert set(no_nav.sources) == {NET, BEST_PLANE} and no_nav.ratio_to == BEST_PLANE
