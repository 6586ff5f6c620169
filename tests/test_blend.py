"""Blending across the reference border: an exposure step is smoothed, the reference kept."""

import cv2
import numpy as np
import pytest

from pis3r.errors import InputError
from pis3r.stitch.blend import blend_reference_border, border_distance, local_gain

OFFSET, SIZE = (80, 50), (160, 120)  # reference at canvas (x, y), (w, h)


@pytest.fixture(scope="module")
def exposure_step():
    """A textured 220x320 canvas: the reference exact, the other views 30% darker and vignetted."""
    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur(rng.random((220, 320, 3)).astype(np.float32), (0, 0), 3)
    scene = 0.2 + 0.6 * (scene - scene.min()) / (scene.max() - scene.min())
    xs = np.linspace(0, 1, 320, dtype=np.float32)[None, :, None]
    others = scene * (0.65 + 0.1 * xs)
    (x0, y0), (w, h) = OFFSET, SIZE
    window = (slice(y0, y0 + h), slice(x0, x0 + w))
    canvas = others.copy()
    canvas[window] = scene[window]
    return canvas, others[window].copy(), window


def border_step(image, window) -> float:
    """Mean absolute jump across the left and right reference edges."""
    rows, cols = window
    left = np.abs(image[rows, cols.start] - image[rows, cols.start - 1]).mean()
    right = np.abs(image[rows, cols.stop - 1] - image[rows, cols.stop]).mean()
    return float(left + right) / 2


def blend(canvas, under, method, **kwargs):
    editable = np.ones(canvas.shape[:2], bool)
    return blend_reference_border(canvas, OFFSET, under, np.ones(under.shape[:2], bool), editable, method, **kwargs)


@pytest.mark.parametrize("method", ["feather", "multiband"])
def test_blend_removes_the_exposure_step_and_keeps_the_reference(exposure_step, method):
    canvas, under, window = exposure_step
    out = blend(canvas, under, method)
    assert border_step(out, window) < 0.25 * border_step(canvas, window)
    np.testing.assert_array_equal(out[window], canvas[window])
    # Far from the reference the other views keep their own colours.
    np.testing.assert_allclose(out[:, :5], canvas[:, :5], atol=1e-6)
    assert out.dtype == np.float32 and out.min() >= 0 and out.max() <= 1


@pytest.mark.parametrize("method", ["feather", "multiband"])
def test_in_place_blends_the_canvas_itself_as_a_copy_would(exposure_step, method):
    canvas, under, _ = exposure_step
    expected = blend(canvas, under, method)
    mine = canvas.copy()
    out = blend(mine, under, method, in_place=True)
    assert out is mine
    np.testing.assert_array_equal(out, expected)


def test_none_is_bit_identical(exposure_step):
    canvas, under, _ = exposure_step
    assert blend(canvas, under, "none") is canvas


def test_blend_into_reference_changes_only_its_border(exposure_step):
    canvas, under, window = exposure_step
    out = blend(canvas, under, "feather", into_reference=True)
    inner = out[window]
    assert not np.array_equal(inner[:, 0], canvas[window][:, 0])
    np.testing.assert_array_equal(inner[20:-20, 20:-20], canvas[window][20:-20, 20:-20])
    assert border_step(out, window) < 0.25 * border_step(canvas, window)


def test_background_stays_and_unknown_method_is_refused(exposure_step):
    canvas, under, _ = exposure_step
    editable = np.zeros(canvas.shape[:2], bool)
    out = blend_reference_border(canvas, OFFSET, under, np.ones(under.shape[:2], bool), editable)
    np.testing.assert_array_equal(out, canvas)
    with pytest.raises(InputError, match="--blend"):
        blend(canvas, under, "poisson")


def test_border_distance_signs():
    distance = border_distance((5, 6), (2, 1), (2, 3))
    assert distance[2, 2] == 1 and distance[2, 0] == -2 and distance[0, 0] == pytest.approx(-np.hypot(2, 1))


@pytest.mark.parametrize("into_reference", [False, True])
def test_feather_is_the_ramp_between_toned_and_original_layers_at_every_pixel(exposure_step, into_reference):
    # The definition, computed densely over the whole canvas; the stage computes it only
    # where pixels can change. Half of the overlap is missing, so the original layer
    # beneath the reference mixes the other views' colours and the reference's.
    canvas, under, window = exposure_step
    under_valid = np.zeros(under.shape[:2], bool)
    under_valid[:, ::2] = True
    editable = np.ones(canvas.shape[:2], bool)
    editable[:10] = False
    out = blend_reference_border(canvas, OFFSET, under, under_valid, editable, "feather", into_reference)
    (x0, y0), (w, h) = OFFSET, SIZE
    band = 0.1 * min(h, w)
    gain = local_gain(canvas[window], under, under_valid, sigma=band / 2)
    rows = np.clip(np.arange(canvas.shape[0]) - y0, 0, h - 1)
    cols = np.clip(np.arange(canvas.shape[1]) - x0, 0, w - 1)
    toned = np.clip(canvas * gain[rows[:, None], cols[None, :]], 0, 1)
    toned[window] = canvas[window]
    original = canvas.copy()
    original[window] = np.where(under_valid[..., None], under, canvas[window])
    distance = border_distance(canvas.shape[:2], OFFSET, SIZE)
    weight = np.clip(0.5 + distance / (2 * band) if into_reference else 1 + distance / band, 0, 1)[..., None]
    expected = np.clip(weight * toned + (1 - weight) * original, 0, 1)
    changeable = editable.copy()
    changeable[window] = into_reference
    expected = np.where(changeable[..., None], expected, canvas)
    np.testing.assert_allclose(out, expected, atol=1e-6)
