import numpy as np

from pis3r.stitch.holes import fill_holes, hole_mask


def test_only_pixels_inside_the_closing_are_inpainted():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (60, 80, 3)).astype(np.float32)
    occupied = np.zeros((60, 80), bool)
    occupied[10:50, 10:40] = True
    occupied[20:22, 15:35] = False  # a thin crack inside: must be filled
    image[~occupied] = 0
    filled = fill_holes(image, occupied, radius=3, background=(0.2, 0.3, 0.4))
    assert filled.hole[20:22, 15:35].all()
    assert not filled.hole[:, 45:].any()  # far outside the closing: background
    np.testing.assert_array_equal(filled.image[occupied], image[occupied])
    np.testing.assert_allclose(filled.image[5, 70], [0.2, 0.3, 0.4])
    assert np.all(filled.image[20:22, 15:35] > 0.05)  # inpainted from neighbours, not black


def test_hole_mask_is_closing_minus_occupancy():
    occupied = np.zeros((30, 30), bool)
    occupied[5:25, 5:25] = True
    occupied[14, 14] = False
    holes = hole_mask(occupied, 2)
    assert holes[14, 14] and holes.sum() == 1
