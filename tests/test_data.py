"""RGB-D and underwater folders: every file format, every bad input, resizing and encoding."""

import json

import cv2
import numpy as np
import pytest
import scipy.io
import torch

from watergan.data import (
    DataError,
    PinholeIntrinsics,
    linear_to_srgb,
    load_rgbd,
    load_underwater,
    read_depth,
    read_nav_altitudes,
    resize_depth,
    srgb_to_linear,
    write_depth_png,
    write_srgb8,
)
from watergan.errors import UserInputError

H, W = 24, 32


def _rgb8(seed: int, h: int = H, w: int = W) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _write_rgb(path, rgb: np.ndarray) -> None:
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _depth_m(seed: int, h: int = H, w: int = W) -> np.ndarray:
    return 1.0 + 3.0 * np.random.default_rng(seed).random((h, w))


def make_rgbd(root, n: int = 3, depth_format: str = "png", h: int = H, w: int = W):
    """root/rgb/*.png + root/depth/*.<format>; returns (rgbs uint8, depths metres)."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgbs, depths = [], []
    for i in range(n):
        rgb, depth = _rgb8(i, h, w), np.round(_depth_m(i, h, w), 3)
        _write_rgb(root / "rgb" / f"{i:04d}.png", rgb)
        if depth_format == "png":
            assert cv2.imwrite(str(root / "depth" / f"{i:04d}.png"), np.rint(depth * 1000).astype(np.uint16))
        elif depth_format == "npy":
            np.save(root / "depth" / f"{i:04d}.npy", depth)
        else:
            scipy.io.savemat(root / "depth" / f"{i:04d}.mat", {"depth": depth})
        rgbs.append(rgb)
        depths.append(depth)
    return rgbs, depths


@pytest.mark.parametrize("depth_format", ["png", "npy", "mat"])
def test_rgbd_formats_native_size(tmp_path, depth_format):
    rgbs, depths = make_rgbd(tmp_path, 3, depth_format)
    data = load_rgbd(tmp_path, size_hw=(H, W))
    assert data.rgb.shape == (3, 3, H, W) and data.depth_m.shape == (3, 1, H, W)
    assert data.rgb.dtype == torch.float32 and data.stems == ["0000", "0001", "0002"]
    np.testing.assert_allclose(data.depth_m[1, 0].numpy(), depths[1], atol=1e-6)
    np.testing.assert_allclose(data.rgb[2].numpy().transpose(1, 2, 0), srgb_to_linear(rgbs[2] / 255.0), atol=1e-6)
    assert data.intrinsics is None and data.skipped == []


def test_rgbd_resized_to_training_size_and_intrinsics(tmp_path):
    make_rgbd(tmp_path / "survey" / "rgbd", 2, h=96, w=128)
    (tmp_path / "survey" / "camera.json").write_text(json.dumps(
        {"fx": 100.0, "fy": 100.0, "cx": 63.5, "cy": 47.5, "width": 128, "height": 96}))
    data = load_rgbd(tmp_path / "survey")  # a folder holding rgbd/ works; camera.json from the parent
    assert data.rgb.shape == (2, 3, 48, 64)
    assert data.intrinsics == PinholeIntrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)
    assert 1.0 < data.depth_m.min() and data.depth_m.max() < 4.0


def test_rgbd_linear_encoding_and_color_folder(tmp_path):
    rgbs, _ = make_rgbd(tmp_path, 1)
    (tmp_path / "rgb").rename(tmp_path / "color")
    data = load_rgbd(tmp_path, size_hw=(H, W), encoding="linear")
    np.testing.assert_allclose(data.rgb[0].numpy().transpose(1, 2, 0), rgbs[0] / 255.0, atol=1e-6)
    with pytest.raises(DataError, match="encoding"):
        load_rgbd(tmp_path, encoding="gamma")


def test_underwater_jpeg_tiff_16bit_any_size(tmp_path):
    rgb = _rgb8(5, 6, 8).repeat(10, 0).repeat(10, 1)  # smooth blocks: JPEG keeps them
    _write_rgb(tmp_path / "a.jpg", rgb)
    _write_rgb(tmp_path / "b.tiff", rgb)
    _write_rgb(tmp_path / "c.png", rgb.astype(np.uint16) * 257)  # 16-bit, same values
    _write_rgb(tmp_path / "d.png", _rgb8(6, 100, 90))
    (tmp_path / "notes.txt").write_text("ignored")
    data = load_underwater(tmp_path)
    assert data.images.shape == (4, 3, 48, 64) and [p.name for p in data.paths] == ["a.jpg", "b.tiff", "c.png",
                                                                                    "d.png"]
    expected = cv2.resize(srgb_to_linear(rgb / 255.0), (64, 48), interpolation=cv2.INTER_AREA).transpose(2, 0, 1)
    np.testing.assert_allclose(data.images[1].numpy(), expected, atol=1e-5)  # tiff is lossless
    np.testing.assert_allclose(data.images[2].numpy(), expected, atol=1e-5)  # 16-bit scaled by 65535
    assert (data.images[0] - data.images[1]).abs().mean() < 0.05  # jpeg: lossy, close


def test_srgb_round_trip_and_writers(tmp_path):
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    depth = _depth_m(0)
    write_depth_png(tmp_path / "d.png", depth)
    np.testing.assert_allclose(read_depth(tmp_path / "d.png"), depth, atol=5e-4)
    write_srgb8(tmp_path / "i.png", np.full((4, 5, 3), 0.5))
    assert list(tmp_path.glob(".*tmp*")) == []
    with pytest.raises(DataError, match="65.535"):
        write_depth_png(tmp_path / "far.png", np.full((2, 2), 70.0))


def test_decoding_and_encoding_by_table_and_fast_codecs(tmp_path):
    """The stored levels' decoding by table (8 and 16 bits), sRGB encoding in torch, 8-bit PNGs through fpng and
    16-bit grey ones through our writer give the values of the plain NumPy and OpenCV routes."""
    from watergan.io import encode_png, quantise, read_stored, srgb_levels, stored_as

    rng = np.random.default_rng(3)
    for dtype, top in ((np.uint8, 255), (np.uint16, 65535)):
        levels = rng.integers(0, top + 1, (9, 11, 3)).astype(dtype)
        cv2.imwrite(str(tmp_path / "f.png"), levels)  # OpenCV's BGR order: RGB is levels reversed
        stored = read_stored(tmp_path / "f.png")
        np.testing.assert_array_equal(stored, levels)
        rgb = levels[..., ::-1].astype(np.float64) / top
        np.testing.assert_array_equal(stored_as(stored, "linear", np.float32), rgb.astype(np.float32))
        np.testing.assert_allclose(stored_as(stored, "srgb"), srgb_to_linear(rgb), rtol=1e-12, atol=1e-15)
    linear = np.concatenate([np.linspace(-0.1, 1.2, 200_001), rng.random(100_000), 1e-4 * rng.random(100_000),
                             [np.nan]]).astype(np.float32)
    for bits in (8, 16):  # against float64 NumPy: exact from float64; from float32 exact at 8 bits (the table),
        # as close as NumPy's own float32 route at 16; NaN gives 0
        truth = quantise(linear_to_srgb(np.nan_to_num(linear.astype(np.float64))), bits).astype(int)
        np.testing.assert_array_equal(srgb_levels(linear.astype(np.float64), bits), truth)
        fast = srgb_levels(linear, bits).astype(int)
        plain = quantise(linear_to_srgb(np.nan_to_num(linear)), bits).astype(int)
        if bits == 8:
            np.testing.assert_array_equal(fast, truth)
        assert np.abs(fast - truth).max() <= 1  # float32 rounding at a level's edge
        assert np.mean(fast != truth) <= max(2 * np.mean(plain != truth), 5e-5)
    image = rng.integers(0, 256, (13, 17, 3)).astype(np.uint8)
    grey16 = rng.integers(0, 65536, (13, 17)).astype(np.uint16)  # every byte difference, wrapping modulo 256
    ramp16 = np.rint(np.linspace(0, 65535, 13)[:, None] * np.linspace(0.2, 1, 17)).astype(np.uint16)
    # fpng (8-bit RGB), our own writer (16-bit grey) and OpenCV (the rest)
    for array in (image, image[..., 0], image.astype(np.uint16) * 257, grey16, ramp16, grey16[:1, :1]):
        decoded = cv2.imdecode(np.frombuffer(encode_png(array), np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(decoded[..., ::-1] if array.ndim == 3 else decoded, array)


def test_resize_depth_ignores_holes():
    depth = np.full((4, 4), 2.0)
    depth[:2, :2] = 0.0
    out = resize_depth(depth, (2, 2))
    assert out[0, 0] == 0.0 and np.allclose(out[1:, 1:], 2.0) and out[0, 1] == 2.0


# ---------------------------------------------------------------------------------------------- bad input
def _corrupt(root, case: str) -> str:
    """Break the RGB-D folder in one way; return the name the error must mention."""
    if case == "rgb_without_depth":
        _write_rgb(root / "rgb" / "0009.png", _rgb8(9))
        return "0009.png"
    if case == "depth_without_rgb":
        np.save(root / "depth" / "0009.npy", _depth_m(9))
        return "0009.npy"
    if case == "unreadable_rgb":
        (root / "rgb" / "0001.png").write_bytes(b"not an image at all")
        return "0001.png"
    if case == "truncated_png":
        data = (root / "rgb" / "0001.png").read_bytes()
        (root / "rgb" / "0001.png").write_bytes(data[: len(data) // 2])
        return "0001.png"
    if case == "truncated_depth_png":
        data = (root / "depth" / "0001.png").read_bytes()
        (root / "depth" / "0001.png").write_bytes(data[:-20])
        return "0001.png"
    if case == "nan_depth":
        (root / "depth" / "0001.png").unlink()
        bad = _depth_m(1)
        bad[3, 4] = np.nan
        np.save(root / "depth" / "0001.npy", bad)
        return "0001.npy"
    if case == "negative_depth":
        (root / "depth" / "0001.png").unlink()
        scipy.io.savemat(root / "depth" / "0001.mat", {"depth": _depth_m(1) - 2.5})
        return "0001.mat"
    if case == "mat_without_key":
        (root / "depth" / "0001.png").unlink()
        scipy.io.savemat(root / "depth" / "0001.mat", {"z": _depth_m(1)})
        return "0001.mat"
    if case == "truncated_npy":
        (root / "depth" / "0001.png").unlink()
        np.save(root / "depth" / "0001.npy", _depth_m(1))
        data = (root / "depth" / "0001.npy").read_bytes()
        (root / "depth" / "0001.npy").write_bytes(data[:200])
        return "0001.npy"
    if case == "eight_bit_depth_png":
        assert cv2.imwrite(str(root / "depth" / "0001.png"), np.full((H, W), 3, np.uint8))
        return "0001.png"
    if case == "size_mismatch":
        assert cv2.imwrite(str(root / "depth" / "0001.png"), np.full((H + 2, W), 1500, np.uint16))
        return "0001.png"
    raise AssertionError(case)


BAD_CASES = ["rgb_without_depth", "depth_without_rgb", "unreadable_rgb", "truncated_png", "truncated_depth_png",
             "nan_depth", "negative_depth", "mat_without_key", "truncated_npy", "eight_bit_depth_png",
             "size_mismatch"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_rgbd_named_error_or_counted_skip(tmp_path, case):
    make_rgbd(tmp_path, 3)
    name = _corrupt(tmp_path, case)
    with pytest.raises(UserInputError, match=name.replace(".", r"\.")):
        load_rgbd(tmp_path, size_hw=(H, W))
    data = load_rgbd(tmp_path, size_hw=(H, W), skip_bad=True)
    assert len(data.skipped) == 1 and name in data.skipped[0]
    good = {"0000", "0001", "0002"} - ({"0001"} if case not in ("rgb_without_depth", "depth_without_rgb") else set())
    assert data.stems == sorted(good) and data.rgb.shape[0] == len(good)


def test_duplicate_stems_and_missing_folders(tmp_path):
    make_rgbd(tmp_path / "a", 2)
    _write_rgb(tmp_path / "a" / "rgb" / "0000.jpg", _rgb8(0))
    with pytest.raises(DataError, match="0000"):
        load_rgbd(tmp_path / "a")
    with pytest.raises(DataError, match="rgb/ and depth/"):
        load_rgbd(tmp_path)
    with pytest.raises(DataError, match="does not exist"):
        load_underwater(tmp_path / "nowhere")
    with pytest.raises(DataError, match="subfolders"):
        load_underwater(tmp_path)


@pytest.mark.parametrize("case", ["garbage", "truncated_jpeg", "grey"])
def test_bad_underwater_image(tmp_path, case):
    _write_rgb(tmp_path / "good.png", _rgb8(0))
    bad = tmp_path / ("bad.jpg" if case != "grey" else "bad.png")
    if case == "garbage":
        bad.write_bytes(b"\xff\xd8 garbage \xff\xd9")
    elif case == "truncated_jpeg":
        _write_rgb(bad, _rgb8(1))
        bad.write_bytes(bad.read_bytes()[:-100])
    else:
        assert cv2.imwrite(str(bad), np.zeros((H, W), np.uint8))
    with pytest.raises(DataError, match="bad"):
        load_underwater(tmp_path)
    data = load_underwater(tmp_path, skip_bad=True)
    assert data.images.shape[0] == 1 and len(data.skipped) == 1 and "bad" in data.skipped[0]


def test_navigation_altitudes_by_frame_name(tmp_path):
    path = tmp_path / "survey.json"
    path.write_text(json.dumps({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.5, 3.0]}))
    assert read_nav_altitudes(path) == {"a.png": 2.5, "b.png": 3.0}
    path.write_text(json.dumps({"nav_altitude_m": [2.5, 3.0]}))  # no frames: the names given, in order
    assert read_nav_altitudes(path, ["x.png", "y.png"]) == {"x.png": 2.5, "y.png": 3.0}


@pytest.mark.parametrize("survey, message", [
    ({"frames": ["a.png"]}, "no nav_altitude_m"),
    ({"nav_altitude_m": [2.0]}, "no frames"),
    ({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.0]}, "1 nav_altitude_m values for 2 frames"),
    ({"frames": ["a.png", "b.png"], "nav_altitude_m": [2.0, -1.0]}, "not a positive number for 1 frames .e.g. b.png"),
    ({"frames": ["a.png"], "nav_altitude_m": [None]}, "not a positive number"),
])
def test_bad_navigation_is_named(tmp_path, survey, message):
    path = tmp_path / "survey.json"
    path.write_text(json.dumps(survey))
    with pytest.raises(DataError, match=message):
        read_nav_altitudes(path)
    with pytest.raises(DataError, match="does not exist"):
        read_nav_altitudes(tmp_path / "missing.json")


def test_frames_are_found_by_name_or_in_another_format(tmp_path):
    """A corrected set written in another format than the survey's (PNG of a JPEG survey) is found by stem; two
    files of one stem are ambiguous and the asked name comes back, for the caller's message."""
    from watergan.io import frame_file, read_image, write_srgb_image

    linear = np.random.default_rng(0).uniform(0, 1, (8, 10, 3))
    write_srgb_image(tmp_path / "a.tif", linear, 16)
    write_srgb_image(tmp_path / "b.jpg", linear, 16)  # JPEG: 8 bits whatever is asked
    assert cv2.imread(str(tmp_path / "a.tif"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert cv2.imread(str(tmp_path / "b.jpg"), cv2.IMREAD_UNCHANGED).dtype == np.uint8
    np.testing.assert_allclose(read_image(tmp_path / "a.tif"), linear, atol=1e-4)
    assert frame_file(tmp_path, "a.png") == tmp_path / "a.tif" and frame_file(tmp_path, "b.jpg") == tmp_path / "b.jpg"
    write_srgb_image(tmp_path / "a.png", linear)
    assert frame_file(tmp_path, "a.jpg") == tmp_path / "a.jpg" and frame_file(tmp_path, "c.png") == tmp_path / "c.png"
