"""Depth fill where one view sees the scene (pis3r.reconstruct.propagate)."""

import numpy as np
import pytest

from pis3r.reconstruct.propagate import (
    DEPTH_FILLS,
    _grid_laplacian,
    anchored_solve,
    dominant_planes,
    grid_dissection_order,
    propagate_inverse_depth,
    screened_solve,
)

H, W = 120, 160


@pytest.fixture(scope="module")
def facade_and_ground():
    """Inverse depth ``(H, W)`` of a slanted facade above a ground plane (each exactly affine
    in the pixel), an RGB guide that colours them apart, and the seeds: the left 60 %."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    facade = 0.1 + 0.0004 * (u - W / 2)
    ground = (v - H / 2) / (1.5 * 150.0)
    on_ground = ground > facade
    idepth = np.where(on_ground, ground, facade)
    rng = np.random.default_rng(0)
    guide = np.where(on_ground[..., None], [0.25, 0.5, 0.2], [0.6, 0.6, 0.62]).astype(np.float32)
    guide += rng.normal(0, 0.01, guide.shape).astype(np.float32)
    seeds = u < 0.6 * W
    return idepth, guide, seeds, on_ground


def test_dominant_planes_finds_the_facade_and_the_ground(facade_and_ground):
    idepth, _, seeds, on_ground = facade_and_ground
    noisy = idepth * (1 + np.random.default_rng(1).normal(0, 0.005, idepth.shape))
    planes, owners = dominant_planes(noisy, seeds, seeds.astype(np.float64))
    assert len(planes) == 2
    # Each seed is owned by the plane it lies on; the ground and the facade are told apart.
    ground_label = np.bincount(owners[seeds & on_ground]).argmax()
    facade_label = np.bincount(owners[seeds & ~on_ground]).argmax()
    assert ground_label != facade_label
    assert (owners[seeds & on_ground] == ground_label).mean() > 0.95
    assert (owners[~seeds] == -1).all()


def test_planes_continue_both_surfaces_into_the_unseen_part(facade_and_ground):
    idepth, guide, seeds, _ = facade_and_ground
    measured = np.where(seeds, idepth, 0.0).astype(np.float32)
    errors = {}
    for method in DEPTH_FILLS:
        filled, conf = propagate_inverse_depth(measured, seeds.astype(np.float32), guide, method=method)
        unseen = ~seeds
        errors[method] = float(np.median(np.abs(filled[unseen] - idepth[unseen]) / idepth[unseen]))
        assert np.array_equal(filled[seeds], measured[seeds])  # measurements are kept
        assert (conf[unseen] <= 0.5).all()
    # The planes are exact where they continue (within the edge-aware smoothing at the seam).
    assert errors["planes"] < 0.01
    assert errors["planes"] < 0.5 * min(errors["planar"], errors["harmonic"])


def test_no_dominant_plane_falls_back_to_the_planar_fill():
    # Inverse depths spread over a factor 10: no plane explains 10 % of them within 3 %.
    idepth = (0.05 + 0.5 * np.random.default_rng(2).random((H, W))).astype(np.float32)
    seeds = np.zeros((H, W), bool)
    seeds[:, :80] = True
    conf = seeds.astype(np.float32)
    planes, owners = dominant_planes(idepth, seeds, conf)
    assert len(planes) == 0 and (owners[seeds] == 0).all()
    guide = np.full((H, W, 3), 0.5, np.float32)
    measured = np.where(seeds, idepth, 0).astype(np.float32)
    np.testing.assert_array_equal(propagate_inverse_depth(measured, conf, guide, method="planes")[0],
                                  propagate_inverse_depth(measured, conf, guide, method="planar")[0])


@pytest.mark.parametrize("shape", [(40, 50), (7, 9), (1, 12)])
def test_screened_solve_solves_the_grid_system(shape):
    """The red-black reduction and the factorisation's settings (dissection order, no
    pivoting, narrow panels) still solve the screened system exactly, with seeds on a tenth
    of a colour-edged grid and several right-hand sides, on even and odd grids."""
    rng = np.random.default_rng(3)
    size = shape[0] * shape[1]
    guide = rng.random((*shape, 3)).astype(np.float32)
    laplacian = _grid_laplacian(guide, 0.08)
    weight = np.where(rng.random(size) < 0.1, rng.random(size), 0.0)
    weight[0] = 0.5  # one seed at least
    seeds = rng.random((size, 3))
    solved = screened_solve(laplacian, seeds, weight, 1.0, shape)
    system = np.diag(weight + 1e-9) + laplacian.toarray()
    expected = np.linalg.solve(system, weight[:, None] * seeds)
    assert np.allclose(solved, expected, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("shape", [(1, 9), (2, 2), (3, 7), (17, 5), (40, 50)])
def test_grid_dissection_order_is_a_permutation(shape):
    order = grid_dissection_order(*shape)
    np.testing.assert_array_equal(np.sort(order), np.arange(shape[0] * shape[1]))


def test_grid_dissection_order_keeps_the_factor_small():
    """Eliminated in dissection order, a grid system's LU factors hold less than half the
    entries they hold in row-major order (whose fill is the grid's width in every column)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    height, width = 60, 80
    laplacian = _grid_laplacian(np.full((height, width, 3), 0.5, np.float32), 0.08)
    system = (laplacian + 0.01 * sp.eye(height * width)).tocsr()

    def factor_entries(order):
        permuted = system[order][:, order].tocsc()
        factor = splu(permuted, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        return factor.L.nnz + factor.U.nnz

    dissected = factor_entries(grid_dissection_order(height, width))
    row_major = factor_entries(np.arange(height * width))
    assert dissected < 0.5 * row_major


def test_anchored_solve_matches_the_factorisation_and_falls_back_to_it(monkeypatch):
    """With a prior weight at every pixel, conjugate gradients give the factorised answer;
    when they cannot converge in the iterations allowed, the system is factorised instead."""
    from pis3r.reconstruct import propagate

    rng = np.random.default_rng(4)
    guide = rng.random((60, 80, 3)).astype(np.float32)
    laplacian = _grid_laplacian(guide, 0.08)
    weight = np.where(rng.random(60 * 80) < 0.1, rng.random(60 * 80), 0.0) + 0.02
    target = rng.random(60 * 80)
    expected = screened_solve(laplacian, target[:, None], weight, 1.0, (60, 80))[:, 0]
    np.testing.assert_allclose(anchored_solve(laplacian, target, weight, 1.0, target, (60, 80)), expected, rtol=1e-7)
    monkeypatch.setattr(propagate, "CG_MAX_ITERATIONS", 1)
    np.testing.assert_allclose(anchored_solve(laplacian, target, weight, 1.0, target, (60, 80)), expected, rtol=1e-12)
