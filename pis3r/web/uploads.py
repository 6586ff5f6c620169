"""Checking uploaded photos before they are queued: size, pixel count, decodability, names.

Client file names are never used as paths: they are reduced to a safe base name
(``../../etc/passwd`` -> ``passwd``) used only as a label inside the job's folder.
"""

from __future__ import annotations

import io as _io
import re
from typing import BinaryIO

from PIL import Image, UnidentifiedImageError

from pis3r.errors import InputError

CHUNK_BYTES = 1 << 20
MAX_NAME_LENGTH = 80


class UploadTooLargeError(InputError):
    """An upload is over the server's byte or pixel limit."""


def safe_name(filename: str | None, index: int) -> str:
    """A base name of ``[A-Za-z0-9._-]`` characters, no leading dots, never empty."""
    base = re.split(r"[\\/]", filename or "")[-1]
    base = re.sub(r"[^A-Za-z0-9._-]", "_", base).lstrip(".")[-MAX_NAME_LENGTH:]
    return base or f"image_{index}"


def read_limited(stream: BinaryIO, name: str, max_bytes: int) -> bytes:
    """All of ``stream``, refusing (without reading on) once it passes ``max_bytes``."""
    chunks, total = [], 0
    while chunk := stream.read(CHUNK_BYTES):
        total += len(chunk)
        if total > max_bytes:
            raise UploadTooLargeError(f"{name}: larger than the limit of {max_bytes // 2**20} MB")
        chunks.append(chunk)
    if not total:
        raise InputError(f"{name}: file is empty")
    return b"".join(chunks)


def check_image(data: bytes, name: str, max_pixels: int) -> tuple[int, int]:
    """``(width, height)`` of an encoded image that decodes fully and has at most ``max_pixels``."""
    try:
        with Image.open(_io.BytesIO(data)) as image:
            width, height = image.size
            if width * height > max_pixels:
                raise UploadTooLargeError(
                    f"{name}: {width}x{height} is above the limit of {max_pixels / 1e6:g} megapixels")
            image.load()
    except Image.DecompressionBombError:
        raise UploadTooLargeError(f"{name}: image is too large to decode safely") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        raise InputError(f"{name}: not an image (or a corrupt one)") from None
    return width, height
