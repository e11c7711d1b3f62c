"""RGB-D and underwater image datasets read from folders.

In-air RGB-D (what the generator turns into underwater images)::

    DIR/rgb/<stem>.png|.jpg|.jpeg|.tif|.tiff     colour, 8 or 16 bit, sRGB-encoded by default
    DIR/depth/<stem>.png                         16-bit PNG, millimetres (0 = no value)
    DIR/depth/<stem>.npy                         float array, metres
    DIR/depth/<stem>.mat                         MATLAB file with the key ``depth``, metres

paired by file stem (``color/`` is accepted for ``rgb/``; a folder holding ``rgbd/rgb`` and
``rgbd/depth``, such as a simulated survey, works too). Pinhole intrinsics are read from a
``camera.json`` (keys fx, fy, cx, cy, width, height; OpenCV pixel centres) in DIR or its parent
when there is one; without it range is taken as the depth.

Underwater images: every PNG, JPEG or TIFF (8 or 16 bit, any size) directly in a folder.

Images are resized to the training size with area interpolation and decoded from sRGB to linear
radiance (an option: ``encoding="linear"`` for images that already are). A bad file (unreadable,
truncated, NaN or negative depth, rgb/depth size mismatch, an rgb without a depth or vice versa)
raises :class:`DataError` naming it; with ``skip_bad=True`` it is skipped and listed in ``skipped``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from .io import (  # noqa: F401  (the data formats' readers and writers, re-exported for their users)
    DEPTH_SUFFIXES,
    ENCODINGS,
    IMAGE_SUFFIXES,
    DataError,
    atomic_write_bytes,
    depth_or_zero,
    encode_png,
    linear_to_srgb,
    read_depth,
    read_image,
    srgb_to_linear,
    write_depth_png,
    write_srgb8,
)
from .survey_files import read_survey_json

RGB_FOLDER_NAMES = ("rgb", "color")
#: Training size of WaterGAN (height, width), pixels.
TRAIN_HW = (48, 64)


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Pinhole intrinsics in pixels of a ``width`` x ``height`` image (OpenCV: pixel (i, j) centre at (i, j))."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def resized(self, height: int, width: int) -> PinholeIntrinsics:
        """The same camera for the image resized to ``height`` x ``width``:
        f' = f s, c' = (c + 0.5) s - 0.5 with s = new size / old size per axis."""
        sx, sy = width / self.width, height / self.height
        return PinholeIntrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                                 (self.cy + 0.5) * sy - 0.5, width, height)

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)

    @property
    def K(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view, degrees: 2 atan(W / (2 fx))."""
        return math.degrees(2 * math.atan(self.width / (2 * self.fx)))

    def to_json(self) -> dict:
        """The ``camera.json`` form (with the pixel-centre convention spelled out)."""
        return {"model": "PINHOLE", "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height, "hfov_deg": self.hfov_deg,
                "pixel_centres": "opencv: pixel (i, j) centre at (i, j); COLMAP convention is +0.5"}

    @classmethod
    def from_json(cls, d: dict) -> PinholeIntrinsics:
        """From a ``camera.json`` dict (keys fx, fy, cx, cy, width, height; others ignored)."""
        return cls(fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
                   width=int(d["width"]), height=int(d["height"]))


@dataclass(frozen=True)
class RgbdPair:
    """One in-air frame's files."""

    stem: str
    rgb: Path
    depth: Path


@dataclass(frozen=True)
class RgbdSet:
    """In-air RGB-D frames in memory.

    rgb:        (N,3,H,W) float32 linear radiance, 0..1.
    depth_m:    (N,1,H,W) float32 z-depth, metres (0 = no value).
    stems:      file stem of each frame.
    intrinsics: the camera at (H,W), or None (then range = depth).
    skipped:    "path: reason" for each pair left out with ``skip_bad``.
    """

    rgb: torch.Tensor
    depth_m: torch.Tensor
    stems: list[str]
    intrinsics: PinholeIntrinsics | None = None
    skipped: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ImageSet:
    """Underwater images in memory: images (N,3,H,W) float32 linear 0..1, their paths, skipped files."""

    images: torch.Tensor
    paths: list[Path]
    skipped: list[str] = field(default_factory=list)


def _check_encoding(encoding: str) -> None:
    if encoding not in ENCODINGS:
        raise DataError(f"image encoding must be one of {ENCODINGS}, got {encoding!r}")


def resize_image(image: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """(H,W,3) resized to ``size_hw`` with area interpolation (bicubic when enlarging)."""
    h, w = size_hw
    if image.shape[:2] == (h, w):
        return image
    enlarge = h > image.shape[0] or w > image.shape[1]
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_CUBIC if enlarge else cv2.INTER_AREA)


def resize_depth(depth_m: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """(H,W) depth resized to ``size_hw``, averaging valid (> 0) pixels only, so holes do not pull
    values towards 0: d' = area(d) / area(d > 0). Enlarging uses nearest neighbours (no invented depth)."""
    h, w = size_hw
    if depth_m.shape == (h, w):
        return depth_m
    if h > depth_m.shape[0] or w > depth_m.shape[1]:
        return cv2.resize(depth_m, (w, h), interpolation=cv2.INTER_NEAREST)
    valid = (depth_m > 0).astype(np.float64)
    total = cv2.resize(depth_m * valid, (w, h), interpolation=cv2.INTER_AREA)
    weight = cv2.resize(valid, (w, h), interpolation=cv2.INTER_AREA)
    return np.where(weight > 1e-6, total / np.maximum(weight, 1e-6), 0.0)


def list_files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    """The files in ``folder`` with one of the (lower-case) suffixes, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)


def index_by_stem(files: list[Path], kind: str) -> dict[str, Path]:
    """{stem: path}; two files with one stem (a.png, a.jpg) are an error, never a silent choice."""
    out: dict[str, Path] = {}
    for p in files:
        if p.stem in out:
            raise DataError(f"two {kind} files share the stem '{p.stem}': {out[p.stem].name} and {p.name}; "
                            f"pairing by stem needs one each")
        out[p.stem] = p
    return out


def read_nav_altitudes(survey_json: str | Path, names: list[str] | None = None) -> dict[str, float]:
    """Image file name -> the navigation's altitude above the seafloor (metres) from a survey file
    holding ``nav_altitude_m`` (one value per frame) and ``frames`` (the frames' file names; absent:
    ``names``, in the same order). A missing file or key, a count that differs or a value that is not a
    positive number is an error naming the file."""
    path = Path(survey_json)
    if not path.is_file():
        raise DataError(f"navigation file {path} does not exist")
    survey = read_survey_json(path)
    if "nav_altitude_m" not in survey:
        raise DataError(f"navigation file {path} has no nav_altitude_m (the altimeter's reading per frame)")
    frames = survey.get("frames", names)
    if frames is None:
        raise DataError(f"navigation file {path} has no frames (the file name of each nav_altitude_m value)")
    altitudes = np.asarray(survey["nav_altitude_m"], dtype=np.float64).reshape(-1)
    if len(altitudes) != len(frames):
        raise DataError(f"navigation file {path}: {len(altitudes)} nav_altitude_m values for {len(frames)} frames")
    bad = [str(f) for f, a in zip(frames, altitudes, strict=True) if not (np.isfinite(a) and a > 0)]
    if bad:
        raise DataError(f"navigation file {path}: nav_altitude_m is not a positive number for {len(bad)} frames "
                        f"(e.g. {bad[0]})")
    return {str(f): float(a) for f, a in zip(frames, altitudes, strict=True)}


def read_nav_down(survey_json: str | Path, names: list[str] | None = None) -> dict[str, np.ndarray] | None:
    """Image file name -> the unit vector of "down" (gravity) in the camera's frame (x right, y down the image, z
    along the optical axis), as the vehicle's attitude sensor gives it, from a survey file's ``nav_down_cam`` (three
    numbers per frame, beside ``frames`` as :func:`read_nav_altitudes` reads them); None when the file has none (a
    nadir camera is then assumed: (0, 0, 1)). A count that differs, or a vector not of unit length within 1 % or
    pointing up the optical axis, is an error naming the file."""
    path = Path(survey_json)
    survey = read_survey_json(path) if path.is_file() else {}
    if "nav_down_cam" not in survey:
        return None
    frames = survey.get("frames", names)
    down = np.asarray(survey["nav_down_cam"], dtype=np.float64)
    if frames is None or down.ndim != 2 or down.shape != (len(frames), 3):
        raise DataError(f"navigation file {path}: nav_down_cam needs three numbers per frame "
                        f"({0 if frames is None else len(frames)} frames), got shape {down.shape}")
    norm = np.linalg.norm(down, axis=1)
    bad = [str(f) for f, n, d in zip(frames, norm, down, strict=True) if not (abs(n - 1) < 0.01 and d[2] > 0)]
    if bad:
        raise DataError(f"navigation file {path}: nav_down_cam is not a unit vector with a positive z (the camera "
                        f"looking downwards) for {len(bad)} frames (e.g. {bad[0]})")
    return {str(f): d / n for f, d, n in zip(frames, down, norm, strict=True)}


def rgbd_folders(folder: str | Path) -> tuple[Path, Path]:
    """The (rgb, depth) subfolders of an RGB-D folder (``DIR/rgb`` + ``DIR/depth``, or ``DIR/rgbd/...``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"RGB-D folder {folder} does not exist")
    for base in (folder, folder / "rgbd"):
        depth = base / "depth"
        for name in RGB_FOLDER_NAMES:
            if (base / name).is_dir() and depth.is_dir():
                return base / name, depth
    raise DataError(f"RGB-D folder {folder} needs subfolders rgb/ and depth/ (files paired by stem)")


def find_rgbd_pairs(folder: str | Path, skip_bad: bool = False) -> tuple[list[RgbdPair], list[str]]:
    """The frames of an RGB-D folder paired by stem, and the unpaired files skipped (``skip_bad``).

    An rgb without a depth file (or a depth without an rgb) is an error naming it, unless ``skip_bad``.
    """
    rgb_dir, depth_dir = rgbd_folders(folder)
    rgbs = index_by_stem(list_files(rgb_dir, IMAGE_SUFFIXES), "rgb")
    depths = index_by_stem(list_files(depth_dir, DEPTH_SUFFIXES), "depth")
    unpaired = [f"{rgbs[s]}: no depth file with stem '{s}' in {depth_dir}" for s in sorted(set(rgbs) - set(depths))]
    unpaired += [f"{depths[s]}: no rgb file with stem '{s}' in {rgb_dir}" for s in sorted(set(depths) - set(rgbs))]
    if unpaired and not skip_bad:
        more = f" (and {len(unpaired) - 1} more)" if len(unpaired) > 1 else ""
        raise DataError(f"unpaired RGB-D file {unpaired[0]}{more}; fix the folder or pass skip_bad")
    pairs = [RgbdPair(s, rgbs[s], depths[s]) for s in sorted(set(rgbs) & set(depths))]
    if not pairs:
        raise DataError(f"RGB-D folder {folder} has no rgb/depth pairs ({len(rgbs)} rgb, {len(depths)} depth files)")
    return pairs, unpaired


def read_pair(pair: RgbdPair, encoding: str = "srgb") -> tuple[np.ndarray, np.ndarray]:
    """One frame at its native size: (H,W,3) linear rgb and (H,W) depth in metres (0: no value), sizes checked."""
    rgb = read_image(pair.rgb, encoding)
    depth = depth_or_zero(read_depth(pair.depth))  # the generator takes 0 for "no value"
    if rgb.shape[:2] != depth.shape:
        raise DataError(f"size mismatch: rgb {pair.rgb} is {rgb.shape[1]}x{rgb.shape[0]} but depth "
                        f"{pair.depth} is {depth.shape[1]}x{depth.shape[0]} (width x height)")
    return rgb, depth


def read_intrinsics(folder: str | Path) -> PinholeIntrinsics | None:
    """Intrinsics from ``camera.json`` in the RGB-D folder or its parent, or None when there is none."""
    folder = Path(folder)
    for path in (folder / "camera.json", folder.parent / "camera.json"):
        if path.is_file():
            try:
                return PinholeIntrinsics.from_json(json.loads(path.read_text()))
            except (ValueError, KeyError, TypeError) as exc:
                raise DataError(f"camera file {path} needs numbers fx, fy, cx, cy, width, height: {exc}") from exc
    return None


def _to_tensor(images: list[np.ndarray]) -> torch.Tensor:
    array = np.stack([im if im.ndim == 3 else im[..., None] for im in images]).transpose(0, 3, 1, 2)
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


def load_rgbd(folder: str | Path, size_hw: tuple[int, int] = TRAIN_HW, encoding: str = "srgb",
              skip_bad: bool = False) -> RgbdSet:
    """Every RGB-D frame of ``folder`` resized to ``size_hw``, in memory (see the module docstring)."""
    _check_encoding(encoding)
    pairs, skipped = find_rgbd_pairs(folder, skip_bad)
    rgbs, depths, stems, native_hw = [], [], [], set()
    for pair in pairs:
        try:
            rgb, depth = read_pair(pair, encoding)
        except DataError as exc:
            if not skip_bad:
                raise
            skipped.append(str(exc))
            continue
        native_hw.add(depth.shape)
        rgbs.append(resize_image(rgb, size_hw))
        depths.append(resize_depth(depth, size_hw))
        stems.append(pair.stem)
    if not stems:
        raise DataError(f"RGB-D folder {folder}: every pair was bad ({len(skipped)} skipped): {skipped[:3]}")
    intrinsics = read_intrinsics(folder)
    if intrinsics is not None:
        if {(intrinsics.height, intrinsics.width)} != native_hw:
            raise DataError(f"camera.json describes {intrinsics.width}x{intrinsics.height} images but the "
                            f"RGB-D frames in {folder} are {sorted(native_hw)} (height, width)")
        intrinsics = intrinsics.resized(*size_hw)
    return RgbdSet(_to_tensor(rgbs), _to_tensor(depths), stems, intrinsics, skipped)


def load_underwater(folder: str | Path, size_hw: tuple[int, int] = TRAIN_HW, encoding: str = "srgb",
                    skip_bad: bool = False) -> ImageSet:
    """Every image directly in ``folder`` resized to ``size_hw`` (area interpolation), linear, in memory."""
    _check_encoding(encoding)
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"underwater image folder {folder} does not exist")
    files = list_files(folder, IMAGE_SUFFIXES)
    if not files:
        subfolders = sorted(p.name for p in folder.iterdir() if p.is_dir())
        hint = f" (it has subfolders {subfolders}: pass one of them)" if subfolders else ""
        raise DataError(f"underwater image folder {folder} holds no PNG, JPEG or TIFF images{hint}")
    images, paths, skipped = [], [], []
    for path in files:
        try:
            images.append(resize_image(read_image(path, encoding), size_hw))
            paths.append(path)
        except DataError as exc:
            if not skip_bad:
                raise
            skipped.append(str(exc))
    if not images:
        raise DataError(f"underwater image folder {folder}: every image was bad ({len(skipped)} skipped)")
    return ImageSet(_to_tensor(images), paths, skipped)
