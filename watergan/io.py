"""File I/O every layer shares: atomic writes, JSON of dataclasses, PNG images, depth maps and the scene mask (a
survey folder's image list, camera.json and survey.json: :mod:`watergan.survey_files`).

Depth maps, one convention everywhere:
- on disk a depth (or range) map is a single-channel 16-bit PNG of millimetres, ``0`` = no value
  (``.npy`` in metres and ``.mat`` with the key ``depth`` are read too);
- in memory it is float64 metres with ``NaN`` where there is no value (:func:`read_depth`). The
  nets take 0 for "no value" in their input tensors: :func:`depth_or_zero` converts at that boundary.

Every write goes through a temporary file in the same folder renamed into place (``os.replace``),
so a reader sees the old or the new content, never a partial one.
"""

from __future__ import annotations

import dataclasses
import enum
import errno
import functools
import json
import os
import struct
import tempfile
import threading
import types
import typing
import zlib
from enum import StrEnum
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import UserInputError

try:  # a fast encoder of 8-bit RGB PNGs (a dependency; OpenCV's encoder where its wheel is missing)
    import fpng_py as _fpng
except ImportError:  # pragma: no cover
    _fpng = None

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
DEPTH_SUFFIXES = (".png", ".npy", ".mat")
class Encoding(StrEnum):
    """How image files store colour: sRGB-encoded (decoded to linear on reading) or linear."""

    srgb = "srgb"
    linear = "linear"


ENCODINGS = tuple(Encoding)
#: The eight bytes every PNG file starts with.
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: zlib's level of :func:`encode_grey16_png` by default: stored (the fastest; benchmarks/RESULTS/speed-and-scale.md,
#: "A 16-bit PNG writer for the corrected frames' depth").
GREY16_ZLIB_LEVEL = 0
#: Largest distance a 16-bit millimetre PNG holds, metres.
MAX_DEPTH_PNG_M = 65.535


class DataError(UserInputError):
    """A data file or folder that cannot be used (the message names it and says what to do)."""


# ---------------------------------------------------------------------------------------- writes
class WriteError(UserInputError):
    """An output that could not be written (a full disk, no permission): the message names the path."""


_UMASK_LOCK = threading.Lock()


def file_mode() -> int:
    """The mode a new file gets under the process's umask (0644 under umask 022), as ``open`` would give it. The
    umask is read by setting it and setting it back, under a lock: two threads writing at once (correct's lanes)
    must not read each other's momentary 0, nor leave it set."""
    with _UMASK_LOCK:
        mask = os.umask(0)
        os.umask(mask)
    return 0o666 & ~mask


def write_failed(path: str | Path, exc: OSError) -> WriteError:
    """The one-line error for an output ``path`` that could not be written."""
    why = exc.strerror or str(exc)
    full = exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EIO)
    hint = "free some space" if full else "check the folder can be written"
    return WriteError(f"cannot write {path}: {why}; {hint} and rerun (nothing half-written was kept)")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and ``os.replace``; the file gets the
    umask's mode (:func:`file_mode`). A failed write (a full disk) leaves the old file, or none, and raises
    :class:`WriteError` naming the path."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise write_failed(path, exc) from exc
    try:
        os.fchmod(fd, file_mode())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise write_failed(path, exc) from exc
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def to_jsonable(value: Any, for_hash: bool = False) -> Any:
    """Dataclasses as dicts, paths as strings, enums as their values, numpy values as numbers and lists;
    ``for_hash`` leaves out dataclass fields marked ``metadata={"hash": False}`` (where work runs, progress
    bars: not what a stage computes)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name), for_hash) for f in dataclasses.fields(value)
                if not (for_hash and f.metadata.get("hash") is False)}
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {str(k): to_jsonable(v, for_hash) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v, for_hash) for v in value]
    return value


def from_jsonable(cls: Any, data: Any) -> Any:
    """Rebuild a value of type ``cls`` from :func:`to_jsonable`'s output: dataclasses (nested ones
    too) from dicts, tuples from lists, paths and enums from strings, null in a float field as NaN. A dataclass
    given a key it does not have is an error naming both (a result or configuration from another version)."""
    if data is None:
        return float("nan") if cls is float or cls == "float" else None  # a non-finite number, written as null
    if isinstance(cls, types.UnionType) or typing.get_origin(cls) is typing.Union:
        options = [h for h in typing.get_args(cls) if h is not type(None)]
        cls = options[0] if len(options) == 1 else Any
    if dataclasses.is_dataclass(cls) and isinstance(data, dict):
        hints = typing.get_type_hints(cls)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"{cls.__name__} has no field {sorted(unknown)}; it has {sorted(names)}")
        return cls(**{k: from_jsonable(hints[k], v) for k, v in data.items()})
    origin = typing.get_origin(cls)
    if origin is tuple and isinstance(data, list):
        args = typing.get_args(cls)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(from_jsonable(args[0], v) for v in data)
        return tuple(from_jsonable(a, v) for a, v in zip(args, data, strict=False)) if args else tuple(data)
    if origin is list and isinstance(data, list):
        (arg,) = typing.get_args(cls) or (Any,)
        return [from_jsonable(arg, v) for v in data]
    if isinstance(cls, type) and issubclass(cls, Path):
        return Path(data)
    if isinstance(cls, type) and issubclass(cls, enum.Enum):
        return cls(data)
    return data


def non_finite(value: Any, where: str = "") -> tuple[str, float] | None:
    """The first (key path, value) of a NaN or infinite number in a JSON-ready value (:func:`to_jsonable`'s); None
    when every number is finite."""
    if isinstance(value, float) and not np.isfinite(value):
        return where or "the value", value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = non_finite(item, f"{where}[{key}]" if isinstance(key, int) else f"{where}.{key}" if where else key)
        if found:
            return found
    return None


def _null_for_non_finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _null_for_non_finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_null_for_non_finite(v) for v in value]
    return value


def atomic_write_json(path: str | Path, value: Any, finite: bool = False) -> None:
    """JSON (dataclasses and paths converted) with sorted keys: the same value gives the same bytes. Always valid
    JSON: a NaN or infinite number (a measurement with no value) is written as null, which :func:`from_jsonable`
    reads back as NaN into a float field; ``finite``: such a number is a :class:`DataError` naming the file and the
    key instead (a survey file, whose every value must be a number)."""
    data = to_jsonable(value)
    bad = non_finite(data) if finite else None
    if bad:
        raise DataError(f"cannot write {path}: {bad[0]} is {bad[1]}, not a finite number (from the input it was "
                        f"read from: fix that value there)")
    atomic_write_text(path, json.dumps(_null_for_non_finite(data), indent=2, sort_keys=True, allow_nan=False) + "\n")


def read_json(path: str | Path, what: str = "file") -> Any:
    """A JSON file; a missing or malformed file is a :class:`DataError` naming it."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{what} {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{what} {path} is not valid JSON ({exc}); fix or re-export it") from exc


# ---------------------------------------------------------------------------------------- images
def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 decoding: L = V / 12.92 for V <= 0.04045, else ((V + 0.055) / 1.055)^2.4."""
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 encoding: V = 12.92 L for L <= 0.0031308, else 1.055 L^(1/2.4) - 0.055."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def read_image(path: Path, encoding: str = "srgb", dtype: type = np.float64) -> np.ndarray:
    """An RGB image file (8- or 16-bit PNG, JPEG or TIFF) as (H,W,3) linear radiance 0..1 of ``dtype`` (float64 or
    float32; ``encoding`` linear: the stored values scaled to 0..1)."""
    return stored_as(read_stored(path), encoding, dtype)


#: The first bytes of each image format the pipeline reads, and of others a user may bring (named in the error).
_MAGIC = ((PNG_SIGNATURE, "PNG"), (b"\xff\xd8\xff", "JPEG"), (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"),
          (b"II+\x00", "TIFF"), (b"MM\x00+", "TIFF"), (b"GIF8", "GIF"), (b"BM", "BMP"))
#: Each format's file name suffixes.
_FORMAT_SUFFIXES = {"PNG": (".png",), "JPEG": (".jpg", ".jpeg"), "TIFF": (".tif", ".tiff")}
#: How :func:`read_pixels` decodes: as stored (its channels and bit depth), 8-bit BGR, 8-bit grey.
_READ_FLAGS = {"stored": cv2.IMREAD_UNCHANGED, "bgr8": cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION,
               "grey8": cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION}


def image_format(data: bytes) -> str | None:
    """An image file's format by its first bytes (PNG, JPEG, TIFF; GIF, BMP, WebP, HEIF named too); None when
    they are none of these."""
    for magic, name in _MAGIC:
        if data.startswith(magic):
            return name
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    if data[4:8] == b"ftyp" and data[8:12] in (b"heic", b"heix", b"mif1", b"msf1", b"avif"):
        return "HEIF"
    return None


def read_pixels(path: Path, form: str = "stored", kind: str = "image", formats: str = "PNG, JPEG or TIFF"
                ) -> np.ndarray:
    """The one reading of an image file, every stage's: OpenCV's array of its pixels as stored, never turned by an
    EXIF orientation tag (the camera's own pixel grid, the one COLMAP reads and a camera.json describes). ``form``:
    stored (its channels and bit depth), bgr8 (8-bit BGR), grey8 (8-bit grey). DataErrors name the ``kind`` of file
    (image, mask) and the ``formats`` it should be in: a file whose first bytes are another format's than its name
    says (a JPEG named .png) is named as what it is."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read {kind} {path}: {exc}") from exc
    found = image_format(data)
    named = next((f for f, suffixes in _FORMAT_SUFFIXES.items() if path.suffix.lower() in suffixes), None)
    if found is None:
        what = "empty" if not data else f"not a readable {formats} file (it starts with {data[:8]!r})"
        raise DataError(f"{kind} {path} is {what}; re-export or remove it")
    if found != named:
        fix = (f"rename it to {path.stem}{_FORMAT_SUFFIXES[found][0]}" if found in formats else
               f"save it as {formats} (e.g. mogrify -format {_FORMAT_SUFFIXES[named or 'PNG'][0][1:]} {path.name})")
        raise DataError(f"{kind} {path} is a {found} file named {path.suffix or 'without a suffix'}: {fix}")
    if not is_complete(path, data):
        raise DataError(f"{kind} {path} is truncated (no end marker); re-export or remove it")
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), _READ_FLAGS[form])
    if decoded is None:
        raise DataError(f"{kind} {path} is not a readable {formats} file")
    return decoded


def _decode(path: Path, kind: str, formats: str) -> np.ndarray:
    """:func:`read_pixels` as stored."""
    return read_pixels(path, "stored", kind, formats)


def read_bgr8(path: Path) -> np.ndarray:
    """(H,W,3) uint8 BGR of an image file (a 16-bit one scaled to 8 bits, grey made colour), as stored
    (:func:`read_pixels`)."""
    return read_pixels(path, "bgr8")


def read_grey8(path: Path, kind: str = "image") -> np.ndarray:
    """(H,W) uint8 grey of an image file (a mask, or a frame for matching), as stored (:func:`read_pixels`)."""
    return read_pixels(path, "grey8", kind)


EXIF_ORIENTATION_TAG = 0x0112
#: What each EXIF orientation other than 1 asks a viewer to do to the stored pixels.
EXIF_TURNS = {2: "mirror", 3: "turn 180 deg", 4: "flip", 5: "transpose", 6: "turn 90 deg clockwise",
              7: "transverse", 8: "turn 90 deg anticlockwise"}


def exif_orientation(path: Path) -> int:
    """An image file's EXIF orientation (1 to 8; 1, the stored pixels upright, without a tag or a readable header).
    Read from the header alone; :func:`read_pixels` never applies it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            value = image.getexif().get(EXIF_ORIENTATION_TAG, 1)
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError):
        return 1
    return value if value in range(1, 9) else 1


def read_stored(path: Path) -> np.ndarray:
    """An RGB image file's stored levels, (H,W,3) uint8 or uint16 in OpenCV's BGR order (an alpha channel dropped),
    decoded once for :func:`stored_as`; a DataError says what is wrong with the file."""
    image = _decode(path, "image", "PNG, JPEG or TIFF")
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise DataError(f"image {path} has shape {image.shape}; expected a colour (RGB) image")
    if image.dtype not in (np.uint8, np.uint16):
        raise DataError(f"image {path} has sample type {image.dtype}; expected 8- or 16-bit integers")
    return image[..., :3]


def levels_bits(levels: np.ndarray) -> int:
    """8 or 16: the bit depth of :func:`read_stored`'s levels."""
    return 16 if levels.dtype == np.uint16 else 8


def stored_as(levels: np.ndarray, encoding: str = "srgb", dtype: type = np.float64) -> np.ndarray:
    """(H,W,3) RGB 0..1 of ``dtype`` from :func:`read_stored`'s BGR levels: ``encoding`` srgb, each level through its
    decoded (linear) value; linear, the stored values scaled to 0..1."""
    if encoding not in ENCODINGS:
        raise DataError(f"image encoding must be one of {ENCODINGS}, got {encoding!r}")
    scale = 255.0 if levels.dtype == np.uint8 else 65535.0
    if encoding == "srgb":  # BGR -> RGB, each stored level through its decoded value
        table = srgb_decode_table(int(scale) + 1, np.dtype(dtype).name)
    else:
        table = _level_table(int(scale) + 1, np.dtype(dtype).name)
    if levels.dtype == np.uint8:  # OpenCV's swap and table lookup: several times faster than NumPy's
        return cv2.LUT(cv2.cvtColor(np.ascontiguousarray(levels), cv2.COLOR_BGR2RGB), table)
    return np.take(table, levels[..., ::-1])


@functools.lru_cache(maxsize=4)
def _level_table(levels: int, dtype: str) -> np.ndarray:
    """(levels,) of ``dtype``: each stored level v / (levels - 1), as dividing the level in ``dtype`` gives it."""
    table = np.arange(levels).astype(dtype) / np.array(levels - 1, dtype)
    table.flags.writeable = False
    return table


@functools.cache
def srgb_decode_table(levels: int, dtype: str = "float64") -> np.ndarray:
    """(levels,) of ``dtype``: :func:`srgb_to_linear` of each stored level v / (levels - 1) of an 8-bit (256) or
    16-bit (65536) image, the values decoding computes level by level; looking them up is several times faster."""
    table = srgb_to_linear(np.arange(levels) / (levels - 1.0)).astype(dtype)
    table.flags.writeable = False
    return table


def is_jpeg(path: str | Path) -> bool:
    """Whether a file name is a JPEG's (.jpg or .jpeg, any case)."""
    return Path(path).suffix.lower() in (".jpg", ".jpeg")


def output_bits(path: str | Path, bit_depth: int) -> int:
    """The bits per sample a frame written to ``path`` keeps of ``bit_depth``: 8 for a JPEG, else all of them."""
    return 8 if is_jpeg(path) else bit_depth


def is_complete(path: Path, data: bytes) -> bool:
    """False for a PNG without its IEND chunk or a JPEG without its end-of-image marker (truncated); the format
    by the file's first bytes (:func:`image_format`)."""
    found = image_format(data)
    if found == "PNG":
        return data.rstrip(b"\0").endswith(b"IEND\xaeB`\x82")
    if found == "JPEG":
        return data.rstrip(b"\0\r\n ").endswith(b"\xff\xd9")
    return True


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))


def encode_grey16_png(image: np.ndarray, level: int = GREY16_ZLIB_LEVEL) -> bytes:
    """PNG bytes of an (H,W) uint16 array (greyscale, 16 bits): every row filtered by PNG's "Up" filter (each byte less
    the byte above it, modulo 256), then deflated by zlib at ``level`` (0: stored, no compression; the fastest
    writer of a per-frame output, e.g. the corrected frames' relative depth). Any PNG reader decodes it."""
    h, w = image.shape
    raw = np.ascontiguousarray(image, ">u2").view(np.uint8).reshape(h, 2 * w)
    rows = np.empty((h, 2 * w + 1), np.uint8)
    rows[:, 0] = 2  # filter type: Up
    rows[0, 1:] = raw[0]
    np.subtract(raw[1:], raw[:-1], out=rows[1:, 1:])  # uint8 arithmetic wraps modulo 256, as the filter does
    header = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)  # 16-bit grey, deflate, adaptive filters, no interlace
    return (PNG_SIGNATURE + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), level))
            + _png_chunk(b"IEND", b""))


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (H,W) or (H,W,3) RGB uint8/uint16 array: 8-bit RGB through fpng (Geldreich's encoder, about
    six times faster than OpenCV's at about 10 % larger files; any PNG reader decodes them) where it is installed,
    the rest through OpenCV (which stores BGR: swapped here)."""
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"PNG images must be uint8 or uint16, got {image.dtype}")
    if _fpng is not None and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3 and image.size:
        h, w = image.shape[:2]
        encoded = _fpng.fpng_encode_image_to_memory(np.ascontiguousarray(image).tobytes(), w, h, 3)
        if encoded:
            return bytes(encoded)
    data = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(data))
    if not ok:
        raise OSError(f"could not encode a {image.dtype} image of shape {image.shape} as PNG")
    return buffer.tobytes()


def write_png(path: str | Path, image: np.ndarray) -> None:
    """An (H,W) or (H,W,3) RGB uint8/uint16 array as a PNG file, atomically."""
    atomic_write_bytes(path, encode_png(image))


def read_png(path: str | Path) -> np.ndarray:
    """A PNG as written by :func:`write_png` (RGB order, its own bit depth)."""
    image = read_pixels(Path(path), kind="image", formats="PNG")
    return image[..., ::-1].copy() if image.ndim == 3 else image


def quantise(values: np.ndarray, bit_depth: int) -> np.ndarray:
    """Values in 0..1 (clipped) rounded to the nearest unsigned integer of ``bit_depth`` (8 or 16) bits,
    round(v (2^bits - 1))."""
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    return np.rint(np.clip(values, 0.0, 1.0) * (2**bit_depth - 1)).astype(dtype)


#: JPEG quality of written frames (a corrected set in the input's JPEG format).
JPEG_QUALITY = 95


def encode_image(suffix: str, image: np.ndarray) -> bytes:
    """Bytes of an (H,W,3) RGB uint8/uint16 array in the format of a file suffix: PNG and TIFF keep 8 or 16 bits,
    JPEG (quality ``JPEG_QUALITY``) takes 8."""
    suffix = suffix.lower()
    if suffix == ".png":
        return encode_png(image)
    if suffix not in (".jpg", ".jpeg", ".tif", ".tiff"):
        raise ValueError(f"cannot write images as {suffix!r}: use .png, .jpg or .tif")
    if is_jpeg(suffix) and image.dtype != np.uint8:
        raise TypeError("JPEG images are 8-bit: quantise to 8 bits first")
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if is_jpeg(suffix) else []
    ok, buffer = cv2.imencode(suffix, cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise OSError(f"could not encode a {image.dtype} image of shape {image.shape} as {suffix}")
    return buffer.tobytes()


SRGB8_BINS = 4096
"""Bins of linear light 0..1 in :func:`srgb_levels`'s 8-bit table: narrower than the closest two of the 8-bit levels'
edges (1 / (255 x 12.92) apart, at the dark end), so that each bin holds at most one edge."""


@functools.lru_cache(maxsize=2)
def _srgb8_table(dtype: str) -> tuple:
    """Per bin of ``SRGB8_BINS`` over linear 0..1: the 8-bit level at the bin's lower end (uint8) and the edge of the
    next level (the linear value whose sRGB code is that level + 1/2, rounded up to ``dtype``; inf past level 255)."""
    import torch

    edges = srgb_to_linear((np.arange(1, 256) - 0.5) / 255.0)  # level k from edges[k - 1] up
    low = np.searchsorted(edges, np.arange(SRGB8_BINS) / SRGB8_BINS, side="right")
    above = np.append(edges, np.inf)[low]
    rounded = above.astype(dtype)
    rounded = np.where(rounded < above, np.nextafter(rounded, np.inf, dtype=dtype), rounded)  # x >= it iff x >= edge
    return torch.from_numpy(low.astype(np.uint8)), torch.from_numpy(rounded)


def srgb_levels(linear_rgb: np.ndarray, bit_depth: int) -> np.ndarray:
    """quantise(linear_to_srgb(linear_rgb), bit_depth) for a float32 or float64 array (NaN: 0). At 8 bits by table:
    each value's bin of ``SRGB8_BINS`` gives the level at its lower end, plus one where the value reaches the next
    level's edge (the same levels as float64 NumPy, for float32 input too, in about half the time of the curve). At
    16 bits the curve, computed in torch in the input's dtype with the power as exp(ln(x) / 2.4), each step in place
    (three times faster than NumPy's power on a CPU; from float32, one level off about as often as NumPy's float32
    route)."""
    import torch

    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
    x = torch.from_numpy(np.ascontiguousarray(linear_rgb))
    if bit_depth == 8:
        low, above = _srgb8_table(str(linear_rgb.dtype))
        flat = x.reshape(-1)
        bins = flat.mul(SRGB8_BINS).nan_to_num_(0.0).clamp_(0, SRGB8_BINS - 1).to(torch.int32)
        levels = torch.index_select(low, 0, bins).add_(flat >= torch.index_select(above, 0, bins))
        return levels.reshape(x.shape).numpy()
    top = 2.0**bit_depth - 1.0
    x = x.nan_to_num(0.0).clamp_(0.0, 1.0)
    dark = x <= 0.0031308
    curve = torch.clamp(x, min=0.0031308).log_().mul_(1 / 2.4).exp_().mul_(1.055 * top).sub_(0.055 * top)
    return torch.where(dark, x.mul_(12.92 * top), curve).round_().to(torch.int32).numpy().astype(np.uint16)


def write_srgb_image(path: str | Path, linear_rgb: np.ndarray, bit_depth: int = 8) -> None:
    """Linear (H,W,3) 0..1 (clipped; NaN: 0) sRGB-encoded and quantised to ``bit_depth`` (8 or 16; JPEG: 8) bits
    (:func:`srgb_levels`), in the format of the path's suffix (PNG, TIFF or JPEG), atomically."""
    path = Path(path)
    rgb = srgb_levels(linear_rgb, output_bits(path, bit_depth))
    atomic_write_bytes(path, encode_image(path.suffix, rgb))


def frame_file(folder: Path, name: str) -> Path:
    """The file of frame ``name`` in ``folder``: ``folder/name``, else the one image file with its stem (a frame
    written in another format: a JPEG survey's corrected PNGs); ``folder/name`` when there is none, for the
    caller's message."""
    path = folder / name
    if path.is_file():
        return path
    stem = Path(name).stem
    found = [folder / f"{stem}{s}" for s in IMAGE_SUFFIXES if (folder / f"{stem}{s}").is_file()]
    return found[0] if len(found) == 1 else path


def write_srgb_png(path: str | Path, linear_rgb: np.ndarray, bit_depth: int = 8) -> None:
    """Linear (H,W,3) 0..1 sRGB-encoded and quantised to ``bit_depth`` (8 or 16) bits as a PNG, atomically."""
    write_png(path, srgb_levels(linear_rgb, bit_depth))


def write_srgb8(path: str | Path, linear_rgb: np.ndarray) -> None:
    """Linear (H,W,3) 0..1 as an 8-bit sRGB PNG, atomically (:func:`write_srgb_png` at 8 bits)."""
    write_srgb_png(path, linear_rgb, 8)


# ---------------------------------------------------------------------------------------- depth
def depth_within(depth_m: np.ndarray, far_limit_m: float = MAX_DEPTH_PNG_M) -> tuple[np.ndarray, np.ndarray]:
    """A depth or range map (H,W) (metres) kept where it holds a plausible value: (a float64 copy with NaN wherever
    it is NaN, infinite, <= 0 or beyond ``far_limit_m``, which is taken as at most ``MAX_DEPTH_PNG_M``; (H,W) bool,
    True where a finite value beyond the limit was dropped). What it returns :func:`write_depth_png` always stores:
    every writer of a map computed from data passes its depths through it first."""
    depth = np.array(depth_m, np.float64)
    with np.errstate(invalid="ignore"):
        too_far = np.isfinite(depth) & (depth > min(far_limit_m, MAX_DEPTH_PNG_M))
        depth[~(np.isfinite(depth) & (depth > 0)) | too_far] = np.nan
    return depth, too_far


def write_depth_png(path: str | Path, depth_m: np.ndarray) -> None:
    """(H,W) metres as a 16-bit PNG of millimetres, atomically: NaN, infinite or <= 0 is stored as 0 (no
    value), values are rounded to 1 mm (at least 1 mm where valid); above 65.535 m is an error (a caller's
    mistake: maps computed from data are kept within it by :func:`depth_within` first)."""
    depth_m = np.asarray(depth_m, np.float64)
    valid = np.isfinite(depth_m) & (depth_m > 0)
    if (depth_m[valid] > MAX_DEPTH_PNG_M).any():
        raise DataError(f"distance above {MAX_DEPTH_PNG_M} m cannot be stored in the 16-bit millimetre PNG {path}")
    mm = np.where(valid, np.clip(np.rint(np.where(valid, depth_m, 0.0) * 1000.0), 1, 65535), 0)
    write_png(path, mm.astype(np.uint16))


def read_millimetres(path: Path) -> np.ndarray:
    """(H,W) uint16 of a single-channel 16-bit PNG in millimetres (0 = no value), as the water stage writes range
    maps; a DataError says what is wrong with the file."""
    raw = _decode(path, "depth", "PNG")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DataError(f"depth {path} is a {raw.dtype} PNG of shape {raw.shape}; expected a "
                        f"single-channel 16-bit PNG in millimetres")
    return raw


def _load_depth_array(path: Path) -> np.ndarray:
    suffix = path.suffix.lower()
    if suffix == ".png":
        raw = read_millimetres(path)
        depth = raw.astype(np.float64) / 1000.0
        depth[raw == 0] = np.nan
        return depth
    if suffix == ".npy":
        return np.load(path, allow_pickle=False)
    if suffix == ".mat":
        import scipy.io

        mat = scipy.io.loadmat(path)
        if "depth" not in mat:
            keys = sorted(k for k in mat if not k.startswith("__"))
            raise DataError(f"depth {path} has no key 'depth' (keys: {keys})")
        return mat["depth"]
    raise DataError(f"depth {path}: unsupported format {suffix} (use {', '.join(DEPTH_SUFFIXES)})")


def read_depth(path: str | Path) -> np.ndarray:
    """A depth or range file as (H,W) float64 metres with NaN where there is no value.

    Formats: 16-bit PNG in millimetres (0 = no value), ``.npy`` in metres or ``.mat`` with the key
    ``depth`` in metres (0 = no value in both). A file holding NaN, infinite or negative values is an
    error (a user's array with NaNs is ambiguous: mark missing pixels with 0)."""
    path = Path(path)
    try:
        depth = _load_depth_array(path)
    except DataError:
        raise
    except (OSError, ValueError, NotImplementedError, TypeError) as exc:
        raise DataError(f"cannot read depth {path}: {type(exc).__name__}: {exc}") from exc
    depth = np.asarray(depth)
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
        raise DataError(f"depth {path} has shape {depth.shape} and type {depth.dtype}; expected an (H,W) number array")
    depth = depth.astype(np.float64)
    if path.suffix.lower() != ".png":
        if not np.isfinite(depth).all():
            raise DataError(f"depth {path} contains NaN or infinite values; use 0 for pixels without depth")
        if (depth < 0).any():
            raise DataError(f"depth {path} contains negative values (min {depth.min():.3g} m)")
        depth[depth == 0] = np.nan
    return depth


def z_to_range(depth_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Ray length r = z |K^-1 (x, y, 1)| of camera z-depth (H,W) (NaN stays NaN)."""
    h, w = depth_m.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return depth_m * np.sqrt(((xs - K[0, 2]) / K[0, 0]) ** 2 + ((ys - K[1, 2]) / K[1, 1]) ** 2 + 1.0)


def depth_or_zero(depth_m: np.ndarray) -> np.ndarray:
    """NaN (no value) as 0, the form the nets take as input."""
    return np.nan_to_num(depth_m, nan=0.0)


# ---------------------------------------------------------------------------------------- scene mask
#: The survey folder's mask image: nonzero where a pixel is the scene, 0 where it is not (a burned-in timestamp, the
#: vehicle's frame, a port's edge); one image for every frame.
SCENE_MASK_PNG = "mask.png"


def scene_mask_from(width: int, height: int, mask_png: Path | None = None,
                    rects_px: list | None = None) -> np.ndarray | None:
    """(H,W) bool, True where a pixel is the scene: the mask image's nonzero pixels (any channel), less every
    rectangle ``[x0, y0, x1, y1]`` (pixels, x1 and y1 excluded). None when neither is given. A mask of another size,
    an unreadable one, ``rects_px`` that is not a list of rectangles, a rectangle that is not four numbers, one
    with x1 <= x0 or y1 <= y0 (an [x, y, width, height] given for corners) and one reaching outside the frame are
    DataErrors naming it."""
    if mask_png is None and rects_px is None:
        return None
    if rects_px is not None and not isinstance(rects_px, list | tuple):
        raise DataError(f"mask_rects_px = {rects_px!r} is not a list of rectangles: give [[x0, y0, x1, y1], ...] in "
                        f"pixels (x1, y1 excluded)")
    mask = np.ones((height, width), bool)
    if mask_png is not None:
        image = _decode(Path(mask_png), "mask", "PNG")
        if image.shape[:2] != (height, width):
            raise DataError(f"mask {mask_png} is {image.shape[1]}x{image.shape[0]}; the frames are {width}x{height}")
        mask &= (image.reshape(height, width, -1) > 0).any(axis=2)
    for rect in rects_px or []:
        if not (isinstance(rect, list | tuple) and len(rect) == 4 and all(is_number(v) for v in rect)):
            raise DataError(f"mask rectangle {rect!r} is not [x0, y0, x1, y1] in pixels")
        x0, y0, x1, y1 = (int(round(v)) for v in rect)
        if x1 <= x0 or y1 <= y0:
            raise DataError(f"mask rectangle {list(rect)} has x1 <= x0 or y1 <= y0: give its corners [x0, y0, x1, y1] "
                            f"(an [x, y, width, height] is [{x0}, {y0}, {x0 + x1}, {y0 + y1}])")
        if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
            raise DataError(f"mask rectangle {list(rect)} reaches outside the {width}x{height} frame (x 0-{width}, "
                            f"y 0-{height}): give it in the frames' pixels")
        mask[y0:y1, x0:x1] = False
    if not mask.any():
        raise DataError("the scene mask leaves no pixel of the scene: white (nonzero) marks the scene in mask.png")
    return None if mask_png is None and not rects_px else mask


def write_scene_mask(path: str | Path, mask: np.ndarray) -> None:
    """(H,W) bool scene mask as an 8-bit PNG (255 scene, 0 not the scene), atomically."""
    write_png(path, np.where(mask, 255, 0).astype(np.uint8))


def read_scene_mask(path: str | Path | None) -> np.ndarray | None:
    """The workspace's scene mask (:func:`write_scene_mask`) as (H,W) bool, True where a pixel is the scene; None
    for an empty path (every pixel is the scene)."""
    if not path:
        return None
    image = _decode(Path(path), "scene mask", "PNG")
    return image.reshape(*image.shape[:2], -1).max(axis=2) > 0


def is_number(value: Any) -> bool:
    """A finite int or float (not a bool, string or list)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)
