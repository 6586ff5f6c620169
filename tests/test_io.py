import io as _io

import cv2
import numpy as np
import pytest
from PIL import Image, ImageOps

from pis3r.errors import InputError, OutputError
from pis3r.io import encode_ply, read_image, to_float_rgb, to_uint8, write_bytes, write_png


def _pattern(h=20, w=30):
    rng = np.random.default_rng(0)
    return (rng.uniform(0, 255, (h, w, 3))).astype(np.uint8)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_matches_pillow(tmp_path, orientation):
    img = Image.fromarray(_pattern())
    exif = img.getexif()
    exif[0x0112] = orientation
    path = tmp_path / "o.jpg"
    img.save(path, quality=100, exif=exif)
    expected = np.asarray(ImageOps.exif_transpose(Image.open(path)).convert("RGB"), np.float32) / 255
    got = read_image(path).pixels
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, atol=2 / 255)


def test_sixteen_bit_grey_and_rgba(tmp_path):
    grey16 = (np.linspace(0, 65535, 20 * 30).reshape(20, 30)).astype(np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    out = read_image(tmp_path / "g16.png").pixels
    assert out.shape == (20, 30, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out[..., 0], grey16 / 65535.0, atol=1e-4)
    rgba = np.dstack([_pattern(), np.full((20, 30), 7, np.uint8)])
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    np.testing.assert_allclose(read_image(tmp_path / "a.png").pixels, _pattern() / 255.0, atol=1e-6)


def test_sixteen_bit_rgb_png(tmp_path):
    import cv2

    rgb16 = np.random.default_rng(3).integers(0, 65535, (10, 12, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "c16.png"), rgb16[..., ::-1])
    np.testing.assert_allclose(read_image(tmp_path / "c16.png").pixels, rgb16 / 65535.0, atol=1e-6)


@pytest.mark.parametrize("content", [b"", b"not an image at all", b"\x89PNG\r\n\x1a\n\x00\x00"])
def test_unreadable_files_raise_input_error(tmp_path, content):
    path = tmp_path / "bad.png"
    path.write_bytes(content)
    with pytest.raises(InputError):
        read_image(path)


def test_truncated_jpeg(tmp_path):
    buf = _io.BytesIO()
    Image.fromarray(_pattern(200, 300)).save(buf, "JPEG")
    path = tmp_path / "cut.jpg"
    path.write_bytes(buf.getvalue()[:200])
    with pytest.raises(InputError):
        read_image(path)


def test_exif_focal_35mm(tmp_path):
    img = Image.fromarray(_pattern(40, 60))
    exif = img.getexif()
    exif.get_ifd(0x8769)[0xA405] = 27
    img.save(tmp_path / "f.jpg", exif=exif)
    photo = read_image(tmp_path / "f.jpg")
    assert photo.focal_px == pytest.approx(27 / 36 * 60)


def test_array_conversion_rules():
    assert to_float_rgb(np.zeros((4, 5), np.uint8)).shape == (4, 5, 3)
    with pytest.raises(InputError):
        to_float_rgb(np.zeros((0, 5, 3), np.uint8))
    with pytest.raises(InputError):
        to_float_rgb(np.full((4, 4, 3), np.nan, np.float32))


def test_unsigned_integer_images_scale_exactly_by_their_type_maximum():
    """Every uint8 and uint16 level maps to level / max in float32, alpha dropped, as one
    contiguous array; booleans map to 0 and 1."""
    levels8 = np.arange(256, dtype=np.uint8)
    rgba = np.repeat(np.stack([levels8, levels8[::-1], levels8, np.zeros_like(levels8)], -1)[None], 2, axis=0)
    converted = to_float_rgb(rgba)
    assert converted.dtype == np.float32 and converted.flags.c_contiguous
    np.testing.assert_array_equal(converted[0, :, 0], np.arange(256, dtype=np.float32) / np.float32(255))
    np.testing.assert_array_equal(converted[0, :, 1], converted[0, ::-1, 0])
    levels16 = np.repeat(np.arange(0, 65536, 257, dtype=np.uint16)[None], 2, axis=0)
    np.testing.assert_array_equal(to_float_rgb(levels16)[0, :, 2], levels16[0].astype(np.float32) / np.float32(65535))
    np.testing.assert_array_equal(to_float_rgb(np.eye(3, dtype=bool))[..., 0], np.eye(3, dtype=np.float32))


def test_a_float_image_resized_bicubically_keeps_its_scale():
    # Bicubic upscaling of a [0, 1] image overshoots past 1 at sharp edges: still [0, 1], not 0..255.
    edge = np.zeros((8, 8, 3), np.float32)
    edge[:, 4:] = 1.0
    upscaled = cv2.resize(edge, (32, 32), interpolation=cv2.INTER_CUBIC)
    assert upscaled.max() > 1.05
    converted = to_float_rgb(upscaled)
    assert converted.max() == 1.0 and converted[:, -1].min() == 1.0
    np.testing.assert_allclose(to_float_rgb(edge * 255.0), edge)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError):
        write_png(blocker / "sub" / "a.png", np.zeros((2, 2, 3), np.float32))
    write_bytes(tmp_path / "ok.bin", b"123")
    assert {p.name for p in tmp_path.iterdir()} == {"file", "ok.bin"}


def test_ply_is_binary_little_endian_with_colours():
    data = encode_ply(np.array([[1.0, 2.0, 3.0]]), np.array([[1.0, 0.5, 0.0]]))
    header, body = data.split(b"end_header\n")
    assert b"binary_little_endian" in header and b"element vertex 1" in header
    xyz = np.frombuffer(body[:12], "<f4")
    np.testing.assert_array_equal(xyz, [1, 2, 3])
    assert list(body[12:]) == [255, 128, 0]


def test_to_uint8_rounds_to_the_nearest_level_and_clips_whatever_the_input_dtype():
    levels = np.array([[-0.2, 0.0, 0.3 / 255, 0.7 / 255, 1.6 / 255, 254.4 / 255, 254.6 / 255, 1.0, 1.3]])
    expected = np.array([[0, 0, 0, 1, 2, 254, 255, 255, 255]], np.uint8)
    for dtype in (np.float32, np.float64):
        np.testing.assert_array_equal(to_uint8(levels.astype(dtype)), expected)
    np.testing.assert_array_equal(to_uint8(np.array([[False, True]])), np.array([[0, 255]], np.uint8))
    image = np.random.default_rng(0).random((4, 5, 3), dtype=np.float32)
    assert to_uint8(image).shape == (4, 5, 3)
    assert image.max() < 1.0  # the input is left as it was
