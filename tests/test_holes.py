import cv2
import numpy as np

from pis3r.io import to_uint8
from pis3r.stitch.holes import disk, fill_holes, hole_groups, hole_mask


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


def test_inpainting_box_by_box_gives_the_pixels_of_one_pass_over_the_canvas():
    rng = np.random.default_rng(1)
    image = rng.uniform(0, 1, (240, 320, 3)).astype(np.float32)
    occupied = np.ones((240, 320), bool)
    occupied[:, 280:] = False  # background beside the canvas
    for y, x in rng.integers(5, 230, (60, 2)):  # scattered cracks, some close together
        occupied[y : y + rng.integers(1, 4), x % 270 : x % 270 + rng.integers(3, 12)] = False
    image[~occupied] = 0
    filled = fill_holes(image, occupied, radius=3)
    hole = hole_mask(occupied, 3)
    near = cv2.dilate(hole.astype(np.uint8), disk(6)) > 0
    unknown = (hole | (near & ~occupied)).astype(np.uint8)
    whole = cv2.inpaint(to_uint8(image), unknown, 5, cv2.INPAINT_TELEA)
    assert hole.sum() > 300 and len(hole_groups(near, 5)) > 10
    # Equal up to the order in which fast marching visits pixels at equal distance (a tie
    # the whole canvas breaks differently from one box).
    same = np.all(to_uint8(filled.image)[hole] == whole[hole], axis=1)
    assert same.mean() > 0.99


def test_in_place_fills_the_canvas_itself_with_the_same_pixels():
    rng = np.random.default_rng(2)
    image = rng.uniform(0, 1, (120, 160, 3)).astype(np.float32)
    occupied = np.ones((120, 160), bool)
    occupied[:, 140:] = False
    for y, x in rng.integers(5, 110, (30, 2)):  # cracks close enough for their boxes to overlap
        occupied[y : y + 2, x : x + rng.integers(3, 9)] = False
    image[~occupied] = 0  # the background a rendered canvas holds
    expected = fill_holes(image, occupied, radius=3)
    mine = image.copy()
    filled = fill_holes(mine, occupied, radius=3, in_place=True)
    assert filled.image is mine
    boxes = hole_groups(cv2.dilate(filled.hole.astype(np.uint8), disk(6)) > 0, 5)
    assert any(a[0].start < b[0].stop and b[0].start < a[0].stop and a[1].start < b[1].stop
               and b[1].start < a[1].stop for i, a in enumerate(boxes) for b in boxes[i + 1:])
    np.testing.assert_array_equal(filled.hole, expected.hole)
    np.testing.assert_array_equal(filled.image, expected.image)
