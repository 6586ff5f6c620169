"""Depth where only one view sees the scene: edge-aware propagation of measured
inverse depth into the rest of the image.

Both strategies solve a screened, colour-weighted Laplacian system (the
"colorisation" solve of Levin et al. 2004) on a coarse grid:

    minimise  sum_i c_i (x_i - s_i)^2 + lambda * sum_(i~j) w_ij (x_i - x_j)^2

- ``harmonic``: x = inverse depth itself. Outside the seeds this extrapolates a
  *constant* inverse depth, so slanted planes (ground, facades) shear.
- ``planar``: x = the parameters (a, b, c) of local planes in inverse depth,
  ``1/z = a u + b v + c`` (a plane in 3-D is exactly such an affine function of the
  pixel), fitted around every seed. Propagating the planes and evaluating them
  continues ground and facades linearly into the unseen part (held within a
  factor ``PLANE_LEASH`` of the harmonic solution, so mixed or noisy planes cannot
  run away); a final screened solve keeps the measured values where they exist.

Inverse depth is clamped from below by a far-plane prior, so surfaces extrapolated
past the horizon (sky, distant background) become very far instead of flipping
behind the camera.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

# How depth is continued where one view sees the scene (module docstring).
DEPTH_FILLS = ("planar", "harmonic")
DEFAULT_DEPTH_FILL = "planar"
SOLVE_MAX_SIDE = 256
PLANE_WINDOW = 7
PLANE_LEASH = 1.25


def _grid_laplacian(guide: np.ndarray, sigma: float) -> sp.csr_matrix:
    """Weighted graph Laplacian ``(N, N)`` of the 4-neighbour grid of ``guide (h, w, 3)``."""
    # scipy only where depth is solved for: importing pis3r stays fast (issue 12).
    import scipy.sparse as sp

    h, w = guide.shape[:2]
    idx = np.arange(h * w).reshape(h, w)
    lab = cv2.cvtColor(guide.astype(np.float32), cv2.COLOR_RGB2LAB) / np.array([100.0, 127.0, 127.0], np.float32)
    rows, cols, vals = [], [], []
    for a, b in (
        (idx[:, :-1], idx[:, 1:]),
        (idx[:-1, :], idx[1:, :]),
    ):
        diff = lab.reshape(-1, 3)[a.ravel()] - lab.reshape(-1, 3)[b.ravel()]
        weight = np.exp(-np.sum(diff * diff, axis=1) / (2 * sigma**2)) + 1e-4
        rows += [a.ravel(), b.ravel()]
        cols += [b.ravel(), a.ravel()]
        vals += [weight, weight]
    rows, cols, vals = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    W = sp.csr_matrix((vals, (rows, cols)), shape=(h * w, h * w))
    return sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W


def screened_solve(laplacian: sp.csr_matrix, seeds: np.ndarray, weight: np.ndarray, smoothness: float) -> np.ndarray:
    """Solve ``(diag(weight) + smoothness * L) x = weight * seeds`` for ``seeds (N, k)``."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    A = (sp.diags(weight + 1e-9) + smoothness * laplacian).tocsc().astype(np.float64)
    # Minimum-degree ordering suits the symmetric grid system (faster than COLAMD).
    return splu(A, permc_spec="MMD_AT_PLUS_A").solve(np.ascontiguousarray(weight[:, None] * seeds, dtype=np.float64))


def _local_planes(idepth: np.ndarray, conf: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Confidence-weighted least-squares plane ``a u + b v + c`` of inverse depth around
    every pixel (box window). Returns ``params (h, w, 3)`` and fit weight ``(h, w)``."""
    h, w = idepth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ksize = (2 * radius + 1, 2 * radius + 1)

    def box(x):
        return cv2.boxFilter(x, cv2.CV_64F, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)

    c = conf.astype(np.float64)
    z = idepth.astype(np.float64)
    s1, su, sv = box(c), box(c * u), box(c * v)
    suu, suv, svv = box(c * u * u), box(c * u * v), box(c * v * v)
    sz, suz, svz = box(c * z), box(c * u * z), box(c * v * z)
    M = np.stack(
        [np.stack([suu, suv, su], -1), np.stack([suv, svv, sv], -1), np.stack([su, sv, s1], -1)], -2
    )
    rhs = np.stack([suz, svz, sz], -1)
    M = M + np.eye(3) * 1e-6 * (s1[..., None, None] + 1e-9)
    params = np.linalg.solve(M, rhs[..., None])[..., 0]
    pred = params[..., 0] * u + params[..., 1] * v + params[..., 2]
    # Weight a fit by its support and by how well the plane explains the seed.
    support = np.clip(s1 / (0.3 * ksize[0] * ksize[1]), 0, 1)
    residual = np.abs(pred - z) / (np.abs(z) + 1e-9)
    weight = np.where(c > 0, support * c * np.exp(-((residual / 0.05) ** 2)), 0.0)
    return params, weight


def propagate_inverse_depth(
    idepth: np.ndarray,
    conf: np.ndarray,
    guide: np.ndarray,
    method: str = DEFAULT_DEPTH_FILL,
    smoothness: float = 1.0,
    sigma: float = 0.08,
) -> tuple[np.ndarray, np.ndarray]:
    """Fill ``idepth (h, w)`` (0 where unmeasured) everywhere.

    ``conf (h, w)`` in [0, 1] weighs the measurements; ``guide (h, w, 3)`` float RGB
    steers propagation along colour edges. Returns the dense inverse depth and a
    confidence map (measured pixels keep theirs; propagated ones decay with distance
    from the seeds, at most 0.5).
    """
    h, w = idepth.shape
    scale = min(1.0, SOLVE_MAX_SIDE / max(h, w))
    sh, sw = max(2, round(h * scale)), max(2, round(w * scale))
    # Area-average the measurements with their confidence so thin seeds survive.
    num = cv2.resize(idepth * conf, (sw, sh), interpolation=cv2.INTER_AREA)
    den = cv2.resize(conf, (sw, sh), interpolation=cv2.INTER_AREA)
    small_conf = np.clip(den, 0, 1)
    small = np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0)
    small_guide = cv2.resize(guide, (sw, sh), interpolation=cv2.INTER_AREA)
    L = _grid_laplacian(small_guide, sigma)
    seeds = small_conf > 0.05
    if not seeds.any():
        raise ValueError("no depth measurements to propagate")
    far = 0.25 * float(np.quantile(small[seeds], 0.02))

    weight = np.where(seeds, small_conf, 0.0).ravel()
    if method not in DEPTH_FILLS:
        raise ValueError(f"unknown propagation method {method!r}")
    solved = screened_solve(L, np.stack([small.ravel(), weight], -1), weight, smoothness)
    dense, reach = solved[:, 0], solved[:, 1]
    if method == "planar":
        params, plane_w = _local_planes(small, np.where(seeds, small_conf, 0.0), PLANE_WINDOW)
        pw = plane_w.ravel()
        fields = screened_solve(L, params.reshape(-1, 3), pw, smoothness)
        v, u = np.mgrid[0:sh, 0:sw].astype(np.float64)
        planar = fields[:, 0] * u.ravel() + fields[:, 1] * v.ravel() + fields[:, 2]
        # Far from their seeds, mixed or noisy planes can run away; stay within a
        # factor PLANE_LEASH of the harmonic solution (in inverse depth).
        harmonic = np.maximum(dense, far)
        planar = np.clip(planar, harmonic / PLANE_LEASH, harmonic * PLANE_LEASH)
        # Measurements where they exist, the extrapolated planes elsewhere.
        prior = 0.02
        blended = (weight * small.ravel() + prior * planar) / (weight + prior)
        dense = screened_solve(L, blended[:, None], weight + prior, smoothness)[:, 0]
    dense = np.maximum(dense.reshape(sh, sw), far)
    reach = np.clip(reach.reshape(sh, sw), 0, 1)
    dense = cv2.resize(dense.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    reach = cv2.resize(reach.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    measured = (conf > 0.05) & (idepth > 0)
    out = np.where(measured, idepth, dense).astype(np.float32)
    out_conf = np.where(measured, conf, 0.5 * reach).astype(np.float32)
    return out, out_conf
