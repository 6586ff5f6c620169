"""The helpers of benchmarks/turn_loop.py (issue 39): a turn's loop closes only at the focal it
was taken with, and the summary counts what it claims. Nothing is timed here."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pis3r.camera import intrinsics
from pis3r.features import Matches
from pis3r.reconstruct.focal import aligned_rotation

from .conftest import load_benchmark

turn_loop = load_benchmark("turn_loop")

FOCAL, WIDTH, HEIGHT, STEPS = 500.0, 480, 360, 12


def _turn_matches(rng) -> list[Matches]:
    """Matches of far points between each photo of a camera turned 30 deg at a time through a
    full circle and the next, the last with the first, 0.3 px off."""
    K = intrinsics(FOCAL, WIDTH, HEIGHT)
    step = Rotation.from_euler("y", 360.0 / STEPS, degrees=True).as_matrix()
    matches = []
    for _ in range(STEPS):
        pixels_a = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], (600, 2))
        rays = np.column_stack([pixels_a, np.ones(len(pixels_a))]) @ np.linalg.inv(K).T @ step.T
        pixels_b = rays[:, :2] / rays[:, 2:] * FOCAL + K[:2, 2]
        seen = np.all((pixels_b >= 0) & (pixels_b <= [WIDTH - 1, HEIGHT - 1]), axis=1) & (rays[:, 2] > 0)
        noise = rng.normal(0.0, 0.3, (2, int(seen.sum()), 2))
        matches.append(Matches(pixels_a[seen] + noise[0], pixels_b[seen] + noise[1]))
    return matches


def test_the_loop_closes_at_the_focal_the_turn_was_taken_with():
    matches = _turn_matches(np.random.default_rng(2))
    focal, rotations, closure = turn_loop.loop_reference(matches, WIDTH, HEIGHT)
    assert focal == pytest.approx(FOCAL, rel=0.01) and closure < 0.5
    assert sum(np.degrees(Rotation.from_matrix(R).magnitude()) for R in rotations) == pytest.approx(360.0, abs=1.0)
    # At a focal 10 % short, each turn is fitted wider and the loop overshoots.
    short = intrinsics(0.9 * FOCAL, WIDTH, HEIGHT)
    assert turn_loop.closure_deg([aligned_rotation(pair, short, short) for pair in matches]) > 10.0


def test_the_closure_is_the_angle_of_the_composed_turns():
    quarter = Rotation.from_euler("y", 90.0, degrees=True).as_matrix()
    assert turn_loop.closure_deg([quarter] * 4) == pytest.approx(0.0, abs=1e-6)
    tilted = Rotation.from_euler("x", 3.0, degrees=True).as_matrix() @ quarter
    assert turn_loop.closure_deg([tilted, quarter, quarter, quarter]) == pytest.approx(3.0, abs=1e-6)
    assert turn_loop.loop_pairs(3) == [(0, 1), (1, 2), (2, 0)]


def test_the_summary_counts_cameras_far_off_that_are_called_reliable():
    quarter = Rotation.from_euler("y", 90.0, degrees=True).as_matrix()
    row = {"R": quarter, "angle": 90.0, "off_reference": 1.0, "reliable": True, "warnings": 0, "exif_replaced": False}
    rows = [row, {**row, "off_reference": 6.0}, {**row, "off_reference": 7.0, "reliable": False, "warnings": 1},
            {**row, "exif_replaced": True}]
    line = turn_loop.summary(rows)
    assert line["closure"] == pytest.approx(0.0, abs=1e-6) and line["angle_sum"] == pytest.approx(360.0)
    assert (line["silent"], line["warned"], line["exif_replaced"], line["refused"]) == (1, 1, 1, 0)
    assert line["median_off"] == pytest.approx(3.5)
    refused = turn_loop.summary([*rows[:3], {"pair": "3-0", "refused": "too few matches"}])
    assert refused["closure"] is None and refused["angle_sum"] is None and refused["refused"] == 1
