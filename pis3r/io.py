"""Reading photos (any depth, channels, EXIF orientation) and writing outputs atomically."""

from __future__ import annotations

import io as _io
import json
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import cv2
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from pis3r import png
from pis3r.errors import InputError, OutputError

ImageLike = Union[str, os.PathLike, np.ndarray, Image.Image]

# Beyond this the decoded pixels alone would not fit in memory of a normal machine.
MAX_DECODE_PIXELS = 400_000_000

_EXIF_ORIENTATION = 0x0112
_EXIF_IFD = 0x8769
_FOCAL_LENGTH = 0x920A
_FOCAL_35MM = 0xA405
_FOCAL_PLANE_X_RES = 0xA20E
_FOCAL_PLANE_UNIT = 0xA210
_EXIF_WIDTH = 0xA002
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclass
class Photo:
    """A decoded input image and what its file said about the camera.

    ``pixels``: ``(H, W, 3)`` float32 RGB in ``[0, 1]``, EXIF orientation applied.
    ``focal_px``: focal length in pixels of ``pixels`` derived from EXIF, or ``None``.
    ``scale``: size of ``pixels`` relative to the photo as it was read (1 for that photo; a
    working copy's resize factor, :func:`downscaled`), so that a threshold set in the input
    photo's pixels means the same on a copy.
    """

    pixels: np.ndarray
    name: str
    focal_px: float | None = None
    focal_evidence: str = ""
    scale: float = 1.0

    @property
    def height(self) -> int:
        return self.pixels.shape[0]

    @property
    def width(self) -> int:
        return self.pixels.shape[1]


def downscaled(photo: Photo, factor: float) -> Photo:
    """``photo`` resized by ``factor`` < 1 (area averaging); its EXIF focal and its ``scale``
    scale with it."""
    size = (int(photo.width * factor), int(photo.height * factor))
    return Photo(
        cv2.resize(photo.pixels, size, interpolation=cv2.INTER_AREA),
        photo.name,
        photo.focal_px * factor if photo.focal_px else None,
        photo.focal_evidence,
        photo.scale * size[0] / photo.width,
    )

# A float image whose maximum is above this is on the 0..255 scale: resampling a [0, 1]
# image overshoots by far less, and a 0..255 image this dark is black either way.
FLOAT_255_ABOVE = 2.0


def to_float_rgb(array: np.ndarray, name: str = "image") -> np.ndarray:
    """Any ``(H, W)``, ``(H, W, 1|3|4)`` uint8/uint16/float array to ``(H, W, 3)`` float32 in [0, 1].

    Alpha is dropped (the colour underneath is kept); grey is repeated to RGB. A float
    array is taken to be in [0, 1] (a bicubic resize overshoots a little: clipped) unless
    its maximum exceeds ``FLOAT_255_ABOVE``, then it is 0..255 (or scaled by its maximum).
    """
    a = np.asarray(array)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise InputError(f"{name}: expected an (H, W) or (H, W, 3|4) image, got shape {a.shape}")
    a = a[..., :3]
    if a.shape[0] < 2 or a.shape[1] < 2:
        raise InputError(f"{name}: image is empty ({a.shape[1]}x{a.shape[0]} pixels)")
    if a.dtype == bool or np.issubdtype(a.dtype, np.unsignedinteger):
        # In [0, 1] by construction: scaled in place on one copy, nothing to clip (a 12 MP
        # photo's two extra float passes cost about 0.2 s).
        out = a.astype(np.float32)
        if a.dtype != bool:
            out /= float(np.iinfo(a.dtype).max)
        return out
    if np.issubdtype(a.dtype, np.integer):
        out = a.astype(np.float32) / float(np.iinfo(a.dtype).max)
    elif np.issubdtype(a.dtype, np.floating):
        out = a.astype(np.float32)
        if not np.all(np.isfinite(out)):
            raise InputError(f"{name}: image has NaN or infinite values")
        if out.size and out.max() > FLOAT_255_ABOVE:
            out = out / 255.0 if out.max() <= 255.0 else out / out.max()
    else:
        raise InputError(f"{name}: unsupported pixel type {a.dtype}")
    return np.ascontiguousarray(np.clip(out, 0.0, 1.0))


def _exif_focal(exif: Image.Exif, width: int, height: int) -> tuple[float | None, str]:
    sub = exif.get_ifd(_EXIF_IFD) if exif else {}
    f35 = sub.get(_FOCAL_35MM)
    if f35:
        # 35-mm equivalent: the long side of a full-frame sensor is 36 mm.
        return float(f35) / 36.0 * max(width, height), f"EXIF 35mm-equivalent {float(f35):g} mm"
    f_mm = sub.get(_FOCAL_LENGTH)
    res = sub.get(_FOCAL_PLANE_X_RES)
    unit = _UNIT_MM.get(int(sub.get(_FOCAL_PLANE_UNIT, 2) or 2))
    exif_w = sub.get(_EXIF_WIDTH)
    if f_mm and res and unit:
        px_per_mm = float(res) / unit
        focal = float(f_mm) * px_per_mm
        if exif_w:
            focal *= max(width, height) / float(exif_w)
        if np.isfinite(focal) and focal > 0:
            return focal, f"EXIF focal length {float(f_mm):g} mm + focal-plane resolution"
    return None, ""


def read_image(source: ImageLike, name: str | None = None) -> Photo:
    """Decode a path, numpy array or PIL image into a :class:`Photo`.

    Files: EXIF orientation applied, 8/16-bit, grey and RGBA converted, EXIF focal read.
    Raises :class:`InputError` with one line for anything unreadable.
    """
    if isinstance(source, np.ndarray):
        return Photo(to_float_rgb(source, name or "array"), name or "array")
    if isinstance(source, Image.Image):
        img = ImageOps.exif_transpose(source)
        return Photo(_pil_to_float(img, name or "image"), name or "image")
    path = Path(source)
    label = name or path.name
    if not path.is_file():
        raise InputError(f"{path}: no such image file")
    data = path.read_bytes()
    if not data:
        raise InputError(f"{path}: file is empty")
    exif = None
    try:
        with _open_image(data) as probe:
            if probe.width * probe.height > MAX_DECODE_PIXELS:
                raise InputError(
                    f"{path}: {probe.width}x{probe.height} is too large to decode "
                    f"(limit {MAX_DECODE_PIXELS // 1_000_000} MP)"
                )
            exif = probe.getexif()
    except Image.DecompressionBombError:
        raise InputError(f"{path}: image is too large to decode safely") from None
    except (UnidentifiedImageError, OSError, ValueError):
        exif = None
    try:
        decoded = cv2.imdecode(
            np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION
        )
    except cv2.error:
        raise InputError(f"{path}: not a readable image (too large or corrupt)") from None
    if decoded is None:
        try:
            with _open_image(data) as img:
                img.load()
                pixels = _pil_to_float(ImageOps.exif_transpose(img), label)
        except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as exc:
            raise InputError(f"{path}: not a readable image ({exc.__class__.__name__})") from None
    else:
        if decoded.ndim == 3 and decoded.shape[2] >= 3:
            decoded = cv2.cvtColor(decoded, cv2.COLOR_BGRA2RGBA if decoded.shape[2] == 4 else cv2.COLOR_BGR2RGB)
        pixels = _apply_orientation(to_float_rgb(decoded, label), exif)
    focal, evidence = _exif_focal(exif, pixels.shape[1], pixels.shape[0]) if exif else (None, "")
    return Photo(pixels, label, focal, evidence)


def _open_image(data: bytes) -> Image.Image:
    """Pillow's lazy open, without its decompression-bomb warning: pis3r has its own pixel
    limits (:data:`MAX_DECODE_PIXELS` here, downscaling of huge inputs in the stitch)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        return Image.open(_io.BytesIO(data))


def _pil_to_float(img: Image.Image, name: str) -> np.ndarray:
    if img.mode in ("I;16", "I;16B", "I;16L"):
        return to_float_rgb(np.asarray(img, dtype=np.uint16), name)
    if img.mode == "I":
        return to_float_rgb(np.asarray(img).astype(np.float32) / 65535.0, name)
    if img.mode == "F":
        return to_float_rgb(np.asarray(img, dtype=np.float32), name)
    return to_float_rgb(np.asarray(img.convert("RGBA" if "A" in img.mode else "RGB")), name)


def _apply_orientation(pixels: np.ndarray, exif: Image.Exif | None) -> np.ndarray:
    orientation = int(exif.get(_EXIF_ORIENTATION, 1)) if exif else 1
    ops = {
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: np.transpose(a, (1, 0, 2)),
        6: lambda a: np.rot90(a, -1),
        7: lambda a: np.transpose(a[::-1, ::-1], (1, 0, 2)),
        8: lambda a: np.rot90(a, 1),
    }
    op = ops.get(orientation)
    return np.ascontiguousarray(op(pixels)) if op else pixels


# Rows converted at a time by per-pixel conversions (to_uint8, features.to_gray_u8, a view's exposure): their
# float temporaries stay small and in cache. One temporary of a whole 6 MP photo is 72 MB of
# fresh pages: 0.13 s for a conversion that takes 0.02 s block by block.
CONVERT_ROWS = 128


def by_row_blocks(image: np.ndarray, out: np.ndarray, convert) -> np.ndarray:
    """``out`` filled with ``convert`` of ``image``, ``CONVERT_ROWS`` rows at a time (for a
    per-pixel ``convert``: the same values as one call on the whole image)."""
    for top in range(0, image.shape[0], CONVERT_ROWS):
        out[top:top + CONVERT_ROWS] = convert(image[top:top + CONVERT_ROWS])
    return out


def to_uint8(image: np.ndarray) -> np.ndarray:
    """``(H, W[, 3])`` float in [0, 1] to uint8 with rounding."""
    return by_row_blocks(image, np.empty(image.shape, np.uint8), _rounded_u8)


def _rounded_u8(block: np.ndarray) -> np.ndarray:
    # One float32 temporary, rounded and clipped in place.
    scaled = np.multiply(np.asarray(block, dtype=np.float32), np.float32(255.0))
    np.rint(scaled, out=scaled)
    np.clip(scaled, 0, 255, out=scaled)
    return scaled.astype(np.uint8)


def _atomic_write(path: Path, write) -> None:
    """Write through a temp file in the same directory, then rename into place."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
        # mkstemp creates owner-only files; give the result the usual permissions.
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an ``(H, W)``, ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA image (float in [0, 1]
    or uint8), 8 bits a channel, compressed on both cores (:mod:`pis3r.png`)."""
    return png.encode(image if image.dtype == np.uint8 else to_uint8(image))


def write_bytes(path: Path, data: bytes) -> None:
    _atomic_write(path, lambda h: h.write(data))


def write_png(path: Path, image: np.ndarray) -> None:
    write_bytes(path, encode_png(image))


def encode_json(data: dict) -> bytes:
    """Indented UTF-8 JSON; NaN/inf are refused, since they are not JSON."""
    return (json.dumps(data, indent=2, allow_nan=False) + "\n").encode()


def write_json(path: Path, data: dict) -> None:
    write_bytes(path, encode_json(data))


def encode_ply(points: np.ndarray, colors: np.ndarray) -> bytes:
    """Binary little-endian PLY of ``(N, 3)`` float points and ``(N, 3)`` colours in [0, 1]."""
    points = np.asarray(points, dtype="<f4").reshape(-1, 3)
    rgb = to_uint8(np.asarray(colors).reshape(-1, 3))
    record = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )
    table = np.empty(len(points), dtype=record)
    table["x"], table["y"], table["z"] = points.T
    table["red"], table["green"], table["blue"] = rgb.T
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    return header.encode("ascii") + table.tobytes()

