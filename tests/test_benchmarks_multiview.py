"""The helpers of benchmarks/multiview_pose.py (issue 12, item 3): pycolmap's bundle adjustment
run from pis3r's joint start recovers what pis3r's own fit does, and the pose errors measured
against a GT are the angles they claim. Nothing is timed here."""


import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pis3r.camera import Camera
from pis3r.reconstruct.joint import refine_jointly
from pis3r.reconstruct.tracks import joint_start

from .conftest import load_benchmark
from .test_joint import FOCAL, _scene

multiview = load_benchmark("multiview_pose")


def test_pycolmap_from_the_joint_start_finds_the_focal_and_poses_pis3r_finds():
    """A turntable whose pairs have half the true focal and rotations 2 deg off: from the same
    start, pycolmap's bundle adjustment and pis3r's fit agree with the GT and each other."""
    pairs, cameras, _ = _scene(4, FOCAL / 2, noise_px=0.3, seed=4)
    start = joint_start(pairs)
    assert start is not None and start.views == (1, 2, 3)
    R, t, focal, median_px = multiview.colmap_fit(start, refine_focal=True, loss_scale_px=1.0)
    fit = refine_jointly(pairs, refine_focal=True)
    assert focal == pytest.approx(FOCAL, rel=0.01) and focal == pytest.approx(FOCAL / 2 * fit.focal_factor, rel=2e-3)
    assert median_px == pytest.approx(fit.after_px, rel=0.1) and median_px < 0.5
    for n, j in enumerate(start.views):
        R_gt, t_gt = cameras[j]
        assert multiview.rotation_error_deg(R[n], R_gt) < 0.05
        assert multiview.direction_error_deg(t[n], t_gt) < 0.3
        assert multiview.rotation_error_deg(R[n], fit.pairs[j].R) < 0.02


def test_pose_errors_are_relative_to_the_reference_and_in_degrees():
    K = np.diag([100.0, 100.0, 1.0])
    turn = Rotation.from_euler("y", 10, degrees=True).as_matrix()
    gt = {0: Camera(K, turn, np.array([0.0, 0.0, 1.0]), 10, 10),
          1: Camera(K, np.eye(3), np.array([1.0, 0.0, 0.0]), 10, 10)}
    R_gt, t_gt = multiview.relative(gt[1].R, gt[1].t, gt[0].R, gt[0].t)
    off = Rotation.from_euler("x", 3, degrees=True).as_matrix()
    across = np.cross(t_gt, [0.0, 1.0, 0.0])
    errors = multiview.pose_errors({1: (off @ R_gt, 5 * across)}, gt, 0)
    assert errors[1] == pytest.approx((3.0, 90.0))
    # The scale of a translation is free.
    assert multiview.pose_errors({1: (R_gt, 5 * t_gt)}, gt, 0)[1] == pytest.approx((0.0, 0.0), abs=1e-5)


def test_position_errors_are_after_the_best_scale_and_relative_to_the_distances():
    K = np.diag([100.0, 100.0, 1.0])
    gt = {0: Camera(K, np.eye(3), np.zeros(3), 10, 10), 1: Camera(K, np.eye(3), np.array([-1.0, 0.0, 0.0]), 10, 10),
          2: Camera(K, np.eye(3), np.array([0.0, -1.0, 0.0]), 10, 10)}
    # The same centres at another scale: no error.
    exact = {1: (np.eye(3), np.array([-3.0, 0.0, 0.0])), 2: (np.eye(3), np.array([0.0, -3.0, 0.0]))}
    assert multiview.position_errors(exact, gt, 0) == pytest.approx({1: 0.0, 2: 0.0}, abs=1e-9)
    # One centre 10 % of the distance off across: 10 % at the best scale (1 here).
    off = {1: (np.eye(3), np.array([-1.0, -0.1, 0.0])), 2: (np.eye(3), np.array([0.0, -1.0, 0.0]))}
    errors = multiview.position_errors(off, gt, 0)
    assert errors[1] == pytest.approx(10.0, rel=0.01) and errors[2] < 1.0
