"""PNG encoding on both cores (pis3r.png): files any decoder reads back exactly."""

import io
import zlib

import numpy as np
import pytest
from PIL import Image

from pis3r import png


def _decoded(data: bytes) -> np.ndarray:
    # PIL: a decoder of its own (not OpenCV's libpng), strict about checksums and chunk CRCs.
    with Image.open(io.BytesIO(data)) as image:
        image.load()
        return np.asarray(image)


@pytest.mark.parametrize("shape", [(1, 1), (5, 7), (37, 20, 3), (41, 9, 4), (30, 11, 1)])
def test_pixels_come_back_exactly(shape, monkeypatch):
    """Grey, RGB and RGBA, in blocks of 8 rows (so most images have several, the last partial)."""
    monkeypatch.setattr(png, "BLOCK_ROWS", 8)
    pixels = np.random.default_rng(sum(shape)).integers(0, 256, shape).astype(np.uint8)
    decoded = _decoded(png.encode(pixels))
    np.testing.assert_array_equal(decoded, pixels.reshape(decoded.shape))


def test_a_photo_like_image_compresses():
    """A smooth gradient with noise: the Sub filter leaves small differences that deflate well."""
    rows, cols = np.mgrid[0:300, 0:400]
    noise = np.random.default_rng(0).integers(0, 3, (300, 400, 3))
    pixels = ((rows[..., None] + cols[..., None] + noise) % 256).astype(np.uint8)
    data = png.encode(pixels)
    np.testing.assert_array_equal(_decoded(data), pixels)
    assert len(data) < 0.5 * pixels.size  # unfiltered, zlib keeps 0.6 of it


@pytest.mark.parametrize("lengths", [(0, 0), (0, 10), (10, 0), (1, 1), (1000, 70000), (65521, 3)])
def test_adler32_combine_is_the_checksum_of_the_joined_bytes(lengths):
    rng = np.random.default_rng(lengths[1])
    first, second = (rng.integers(0, 256, n).astype(np.uint8).tobytes() for n in lengths)
    assert png.adler32_combine(zlib.adler32(first), zlib.adler32(second), len(second)) == zlib.adler32(first + second)


@pytest.mark.parametrize("pixels", [np.zeros((4, 4), np.float32), np.zeros((4, 4, 2), np.uint8),
                                    np.zeros((0, 4, 3), np.uint8), np.zeros(4, np.uint8)])
def test_what_png_cannot_hold_is_refused(pixels):
    with pytest.raises(ValueError, match="PNG pixels"):
        png.encode(pixels)
