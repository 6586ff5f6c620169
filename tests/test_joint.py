"""Joint refinement (bundle adjustment) of the pairs registered to the reference."""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import pis3r
from pis3r.features import Matches
from pis3r.reconstruct.joint import refine_jointly
from pis3r.reconstruct.tracks import match_tracks
from pis3r.reconstruct.focal import UNDETERMINED_FOCAL
from pis3r.reconstruct.pairs import PairGeometry

from .conftest import REAL, needs_real_data

WIDTH, HEIGHT, FOCAL = 640, 480, 1500.0


def _K(focal: float) -> np.ndarray:
    return np.array([[focal, 0.0, WIDTH / 2 - 0.5], [0.0, focal, HEIGHT / 2 - 0.5], [0.0, 0.0, 1.0]])


def _project(K, R, t, X):
    camera = X @ R.T + t
    return camera[:, :2] / camera[:, 2:] @ K[:2, :2].T + K[:2, 2]


def _turntable(count: int, step_deg: float = 8.0):
    """Cameras around an object 5 units away, ``step_deg`` apart: ``x_j = R_j X + t_j``."""
    centre = np.array([0.0, 0.0, 5.0])
    cameras = []
    for k in range(count):
        R = Rotation.from_euler("y", -k * step_deg, degrees=True).as_matrix()
        cameras.append((R, centre - R @ centre))
    return cameras


def _pair(K_used: np.ndarray, R: np.ndarray, t: np.ndarray, matches: Matches) -> PairGeometry:
    return PairGeometry("3d", "test", None, K_used, K_used, R, t / np.linalg.norm(t), None, np.eye(3), matches,
                        len(matches), "prior", (), {})


def _scene(count: int, focal_used: float, noise_px: float, seed: int = 0, rotation_error_deg: float = 2.0):
    """Pairs of a turntable scene as a pairwise estimate leaves them: the focal wrong, each
    rotation ``rotation_error_deg`` off, each translation direction a little off; the GT
    cameras; and the points each view sees."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1.0, -1.0, 4.0], [1.0, 1.0, 6.0], (600, 3))
    cameras = _turntable(count)
    K = _K(FOCAL)
    ref_xy = _project(K, np.eye(3), np.zeros(3), X)
    pairs, points = {}, {}
    for j, (R, t) in enumerate(cameras[1:], start=1):
        # Each view sees its own random two thirds of the points.
        seen = rng.random(len(X)) < 0.67
        xy = _project(K, R, t, X[seen]) + rng.normal(0.0, noise_px, (seen.sum(), 2))
        wrong = Rotation.from_rotvec(np.radians(rotation_error_deg) * rng.normal(size=3) / math.sqrt(3)).as_matrix()
        pairs[j] = _pair(_K(focal_used), wrong @ R, t + rng.normal(0.0, 0.02, 3) * np.linalg.norm(t),
                         Matches(ref_xy[seen], xy))
        points[j] = X[seen]
    return pairs, cameras, points


def _errors(pairs, cameras):
    rotation, direction = [], []
    for j, pair in pairs.items():
        R, t = cameras[j]
        rotation.append(np.degrees(np.linalg.norm(Rotation.from_matrix(pair.R @ R.T).as_rotvec())))
        direction.append(np.degrees(math.acos(np.clip(pair.t @ t / np.linalg.norm(t), -1.0, 1.0))))
    return max(rotation), max(direction)


def test_the_poses_and_a_wrong_focal_are_recovered_together():
    """Half the true focal (what one narrow pair self-calibrates on the temple) and rotations
    2 deg off: the views together give the focal within half a percent and the poses within
    hundredths of a degree."""
    pairs, cameras, _ = _scene(5, FOCAL / 2, noise_px=0.3)
    assert _errors(pairs, cameras)[0] > 1.0
    pairs[1] = replace(pairs[1], warnings=(f"{UNDETERMINED_FOCAL} (...); assumed 750 px", "few inliers"))
    fit = refine_jointly(pairs, refine_focal=True)
    seen = np.unique(np.concatenate([pair.inliers.pts_a for pair in pairs.values()]), axis=0)
    assert fit is not None and fit.points == len(seen) and len(fit.pairs) == 4
    assert fit.focal_factor * FOCAL / 2 == pytest.approx(FOCAL, rel=0.005)
    for pair in fit.pairs.values():
        assert pair.K_a[0, 0] == pytest.approx(FOCAL, rel=0.005) and pair.K_b[1, 1] == pair.K_a[1, 1]
        # The principal point stays where it was.
        np.testing.assert_array_equal(pair.K_a[:2, 2], _K(FOCAL)[:2, 2])
        assert np.linalg.norm(pair.t) == pytest.approx(1.0) and "refined over 5 views jointly" in pair.focal_source
        assert pair.focal_views == 5
    rotation, direction = _errors(fit.pairs, cameras)
    assert rotation < 0.05 and direction < 0.3
    assert fit.after_px < 0.5 < fit.before_px
    # The pair's warning that it leaves the focal free no longer holds; others do.
    assert fit.pairs[1].warnings == ("few inliers",)
    interval = fit.pairs[1].focal_interval
    assert interval.low < FOCAL < interval.high and fit.pairs[1].focal_determined
    # Refined again (with views chained to these), a pair says so once.
    again = refine_jointly(fit.pairs, refine_focal=True)
    assert again.focal_factor == pytest.approx(1.0, abs=1e-3)
    assert again.pairs[2].focal_source == "prior; refined over 5 views jointly"


def test_a_known_focal_is_kept():
    pairs, cameras, _ = _scene(4, FOCAL, noise_px=0.3, seed=1)
    fit = refine_jointly(pairs, refine_focal=False)
    assert fit.focal_factor == 1.0 and all(pair.K_a[0, 0] == FOCAL for pair in fit.pairs.values())
    assert all(pair.focal_source == "prior" and pair.focal_views == 2 for pair in fit.pairs.values())
    kept = refine_jointly({**pairs, 1: replace(pairs[1], warnings=(UNDETERMINED_FOCAL,))}, refine_focal=False)
    assert kept.pairs[1].warnings == (UNDETERMINED_FOCAL,)
    # 2 deg off before; what 0.3 px of noise leaves of a 24 deg field of view after.
    assert _errors(pairs, cameras)[0] > 1.0 and _errors(fit.pairs, cameras)[0] < 0.15


def test_a_view_that_shares_no_point_with_the_others_keeps_its_own_pair():
    pairs, *_ = _scene(4, FOCAL, noise_px=0.3, seed=2)
    lonely = pairs[3]
    # Its reference points are none of the others'.
    pairs[3] = _pair(lonely.K_a, lonely.R, lonely.t, Matches(lonely.inliers.pts_a + 0.25, lonely.inliers.pts_b))
    fit = refine_jointly(pairs, refine_focal=True)
    assert fit.views == 2 and fit.pairs[3] is pairs[3] and fit.pairs[1] is not pairs[1] and fit.pairs[2] is not pairs[2]
    assert refine_jointly({1: pairs[1], 3: pairs[3]}, refine_focal=True) is None


def test_tracks_link_the_matches_through_the_keypoints_they_share():
    """Two views matched with the reference and a third chained to the second: a keypoint of
    the reference seen twice, and one of the second view matched onwards, are one track each."""
    a = Matches(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([[5.0, 5.0], [6.0, 6.0]]))
    b = Matches(np.array([[3.0, 4.0], [8.0, 9.0]]), np.array([[1.0, 1.0], [2.0, 2.0]]))
    c = Matches(np.array([[2.0, 2.0], [7.0, 7.0]]), np.array([[0.0, 0.0], [9.0, 9.0]]))
    ends_a, ends_b, camera, track, xy = match_tracks([(0, 1, a), (0, 2, b), (2, 3, c)])
    np.testing.assert_array_equal(camera, [0, 0, 0, 1, 1, 2, 2, 2, 3, 3])
    np.testing.assert_array_equal(xy[ends_a], np.concatenate([a.pts_a, b.pts_a, c.pts_a]))
    np.testing.assert_array_equal(xy[ends_b], np.concatenate([a.pts_b, b.pts_b, c.pts_b]))
    np.testing.assert_array_equal(camera[ends_b], [1, 1, 2, 2, 3, 3])
    # (3, 4) in the reference is seen by views 1 and 2; (8, 9) by view 2 and, through it, view 3.
    assert track[ends_a[1]] == track[ends_a[2]] == track[ends_b[1]] == track[ends_b[2]]
    assert track[ends_a[3]] == track[ends_b[3]] == track[ends_a[4]] == track[ends_b[4]]
    assert len(np.unique(track)) == 4


def test_a_view_chained_to_another_is_refined_with_it():
    """The last view of a turntable shares no point with the reference: chained to the view
    before it, it is placed and refined through it (its pose relative to that view's)."""
    pairs, cameras, seen = _scene(4, FOCAL / 2, noise_px=0.3, seed=3)
    rng = np.random.default_rng(3)
    X = rng.uniform([-1.0, -1.0, 4.0], [1.0, 1.0, 6.0], (400, 3))
    (R_a, t_a), (R_b, t_b) = cameras[3], _turntable(5)[4]
    R_rel, t_rel = R_b @ R_a.T, t_b - R_b @ R_a.T @ t_a
    K = _K(FOCAL)
    # The anchor's keypoints of the chain are its keypoints with the reference, where both see them.
    shared = pairs[3].inliers
    xy_b = _project(K, R_b, t_b, seen[3])
    chain = Matches(np.concatenate([shared.pts_b, _project(K, R_a, t_a, X)]),
                    np.concatenate([xy_b, _project(K, R_b, t_b, X)]) + rng.normal(0.0, 0.3, (len(shared) + len(X), 2)))
    wrong = Rotation.from_rotvec(np.radians([1.5, -1.0, 0.5])).as_matrix()
    pairs[4] = _pair(_K(FOCAL / 2), wrong @ R_rel, t_rel, chain)
    fit = refine_jointly(pairs, refine_focal=True, anchors={4: 3})
    assert fit is not None and fit.views == 4
    assert fit.focal_factor * FOCAL / 2 == pytest.approx(FOCAL, rel=0.01)
    chained = fit.pairs[4]
    assert np.degrees(np.linalg.norm(Rotation.from_matrix(chained.R @ R_rel.T).as_rotvec())) < 0.1
    assert math.degrees(math.acos(np.clip(chained.t @ t_rel / np.linalg.norm(t_rel), -1, 1))) < 0.5
    # Without its anchor the chained view stays out.
    alone = refine_jointly({j: pairs[j] for j in (1, 2, 4)}, refine_focal=True, anchors={4: 3})
    assert alone.views == 2 and alone.pairs[4] is pairs[4]


def test_views_that_only_translate_do_not_determine_the_focal():
    """Cameras that move without turning (a critical motion: the views' rays keep their
    directions, whatever the focal): the joint fit's interval spans the lens range and says so."""
    rng = np.random.default_rng(4)
    X = rng.uniform([-1.0, -1.0, 4.0], [1.0, 1.0, 6.0], (600, 3))
    ref_xy = _project(_K(FOCAL), np.eye(3), np.zeros(3), X)
    pairs = {j: _pair(_K(FOCAL / 2), np.eye(3), t, Matches(ref_xy, _project(_K(FOCAL), np.eye(3), t, X)
                                                           + rng.normal(0.0, 0.3, (len(X), 2))))
             for j, t in enumerate(([-0.6, 0.1, 0.0], [-0.3, -0.4, 0.2], [0.4, 0.3, -0.1]), start=1)}
    fit = refine_jointly(pairs, refine_focal=True)
    pair = fit.pairs[1]
    assert not pair.focal_determined and pair.focal_interval.high / pair.focal_interval.low > 10
    assert pair.focal_interval.low <= FOCAL <= pair.focal_interval.high
    [warning] = [line for line in pair.warnings if line.startswith(UNDETERMINED_FOCAL)]
    assert "4 views refined together" in warning


def _temple_fit_against_gt(views: tuple[int, int]) -> dict:
    """Temple view 13 and ``views`` stitched: both registered in one fit of two views, the
    focal within 3 % of the GT's and each rotation within 1 deg; the fit's report entry."""
    from pis3r.eval.cases import calibrated_views

    folder = REAL / "middlebury-templeRing"
    gt = {}
    for view in views:
        _, (gt[13], gt[view]) = calibrated_views(folder, (13, view))
    result = pis3r.stitch([folder / "images" / f"templeR{v:04d}.png" for v in (13, *views)], backend="classical")
    scene, fit = result.scene, result.report["details"]["joint_refinement"]
    assert scene.indices == (0, 1, 2) and fit["views"] == 2
    assert scene.focal == pytest.approx(gt[13].K[0, 0], rel=0.03)
    # The fit's interval holds the GT focal and is narrow enough to call it determined.
    assert scene.focal_interval.low <= gt[13].K[0, 0] <= scene.focal_interval.high
    assert scene.focal_summary()["determined"] and not any("focal length" in w for w in scene.warnings)
    for view, camera in zip(views, (scene.views[1].camera, scene.views[2].camera)):
        R_gt = gt[view].R @ gt[13].R.T
        assert np.degrees(np.linalg.norm(Rotation.from_matrix(camera.R @ R_gt.T).as_rotvec())) < 1.0
    return fit


@needs_real_data
def test_three_temple_views_fix_the_focal_one_pair_cannot():
    """Middlebury's temple (narrow field of view, no EXIF): one pair self-calibrates about half
    the GT focal (1520 px) and poses 4-7 deg off; the three views together find both."""
    assert _temple_fit_against_gt((14, 15))["median_reprojection_px"][1] < 0.5


@needs_real_data
def test_a_temple_view_chained_through_another_is_refined_with_it():
    """Temple views 13, 15 and 19: 19 shares too few matches with 13 and is chained through 15.
    One pair fixes no focal (about half the GT's, the poses 15-22 deg off); the chained pair
    joins the fit and, with it, does."""
    _temple_fit_against_gt((15, 19))


@needs_real_data
def test_the_depth_flows_are_found_once_each_while_the_poses_are_refined(monkeypatch):
    """The flows do not depend on the poses: with three or more photos they are found on a
    thread of their own while the joint fit runs, and the depth measurement reuses them."""
    import threading

    from pis3r.io import read_image
    from pis3r.reconstruct import views
    from pis3r.reconstruct.classical import ClassicalReconstructor
    from pis3r.reconstruct.options import ReconstructOptions

    found = []

    def pair_flows(*args):
        found.append(threading.current_thread().name)
        return real_pair_flows(*args)

    real_pair_flows = views.pair_flows
    monkeypatch.setattr(views, "pair_flows", pair_flows)
    folder = REAL / "middlebury-templeRing" / "images"
    photos = [read_image(folder / f"templeR{v:04d}.png") for v in (13, 14, 15)]
    scene = ClassicalReconstructor(ReconstructOptions()).reconstruct(photos)
    assert scene.indices == (0, 1, 2) and scene.info["joint_refinement"]["views"] == 2
    assert len(found) == 2 and "pis3r-flows" in found


@needs_real_data
def test_the_views_the_fit_places_are_scaled_as_it_places_them(monkeypatch):
    """The joint fit gives every fitted pair's baseline: the views are scaled by it, not by a
    median depth ratio measured again on the reference (or the anchor) for each pair (on the
    fountain, ref 5, view 10's camera was then 5.1 % of its distance off the GT, 0.8 % now;
    Herz-Jesus, ref 0, with a chained view: 4.3 %, 1.1 % now)."""
    from pis3r.io import read_image
    from pis3r.reconstruct import classical
    from pis3r.reconstruct.options import ReconstructOptions

    fits = []
    real_refine = classical.refine_jointly
    monkeypatch.setattr(classical, "refine_jointly", lambda *args: fits.append(real_refine(*args)) or fits[-1])
    folder = REAL / "middlebury-templeRing" / "images"
    photos = [read_image(folder / f"templeR{v:04d}.png") for v in (13, 14, 15)]
    scene = classical.ClassicalReconstructor(ReconstructOptions()).reconstruct(photos)
    (fit,) = fits
    distance = [float(np.linalg.norm(view.camera.t)) for view in scene.views[1:]]
    assert distance[1] / distance[0] == pytest.approx(fit.baselines[2] / fit.baselines[1], rel=1e-9)
    # A view chained to another (19 through 15) too: its baseline from its anchor's camera.
    photos = [read_image(folder / f"templeR{v:04d}.png") for v in (13, 15, 19)]
    fits.clear()
    anchor, chained = classical.ClassicalReconstructor(ReconstructOptions()).reconstruct(photos).views[1:]
    R = chained.camera.R @ anchor.camera.R.T
    baseline = np.linalg.norm(chained.camera.t - R @ anchor.camera.t) / np.linalg.norm(anchor.camera.t)
    assert baseline == pytest.approx(fits[-1].baselines[2] / fits[-1].baselines[1], rel=1e-9)
