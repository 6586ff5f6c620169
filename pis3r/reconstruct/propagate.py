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
- ``planes``: the scene's dominant planes (ground, facades: :func:`dominant_planes`,
  sequential RANSAC on the seeds in inverse depth) continue unbroken, each to the image
  edge or its horizon, over the part of the image it owns; ownership is a random walk
  (Grady 2006) on the same colour-weighted grid, seeded by the measured pixels each plane
  explains and by the off-plane ones, so a region inherits the surface of the measured
  region it is joined to. Where off-plane measurements own the pixel, ``planar`` fills.

Inverse depth is clamped from below by a far-plane prior, so surfaces extrapolated
past the horizon (sky, distant background) become very far instead of flipping
behind the camera.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import TYPE_CHECKING

import cv2
import numpy as np

if TYPE_CHECKING:
    import scipy.sparse as sp

# How depth is continued where one view sees the scene (module docstring).
DEPTH_FILLS = ("planar", "harmonic", "planes")
DEFAULT_DEPTH_FILL = "planar"
SOLVE_MAX_SIDE = 256
# SuperLU's supernode relaxation and panel width for the grid solves (screened_solve).
SUPERLU_RELAX = 6
SUPERLU_PANEL = 6
# The grid solves eliminate pixels in nested-dissection order (grid_dissection_order): blocks
# of at most this many pixels are not cut further.
DISSECTION_LEAF = 32
# The final solve of the plane fills has a prior at every pixel: conjugate gradients (Jacobi
# preconditioned, on the red-black reduced system, started from the prior) reach this relative
# residual in 90-100 iterations on the 256 px grid, a fifth of a factorisation's time; past
# CG_MAX_ITERATIONS the system is factorised after all.
CG_TOLERANCE = 1e-10
CG_MAX_ITERATIONS = 2000
PLANE_WINDOW = 7
PLANE_LEASH = 1.25
# Dominant planes: a seed lies on a plane when its inverse depth is within this relative
# residual; a plane must explain this share of the seeds; at most MAX_PLANES, each the
# best of PLANE_TRIALS random triples (seeded: the same pair always gets the same planes).
PLANE_TOLERANCE = 0.03
PLANE_MIN_SHARE = 0.1
MAX_PLANES = 4
PLANE_TRIALS = 256
PLANE_SAMPLE = 20_000
# A continued plane is not trusted beyond this many times the nearest measured inverse depth.
PLANE_NEAR_LIMIT = 4.0


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


def _screened_system(laplacian: sp.csr_matrix, weight: np.ndarray, smoothness: float) -> sp.csr_matrix:
    """``diag(weight) + smoothness * L`` ``(N, N)`` float64, CSR (``weight`` nudged off zero)."""
    import scipy.sparse as sp

    return (sp.diags(weight + 1e-9) + smoothness * laplacian).tocsr().astype(np.float64)


@lru_cache(maxsize=8)
def grid_dissection_order(height: int, width: int) -> np.ndarray:
    """``(height * width,)``, read-only: the pixels of a row-major ``height x width`` grid in
    nested-dissection order (George 1973): a block is cut in two by its middle two columns or
    rows (across its longer side), each half ordered the same way, the cut last; blocks of at
    most ``DISSECTION_LEAF`` pixels row by row. Eliminated in this order, a grid system's
    factor stays small (its dense parts are the cuts), which SuperLU's minimum-degree ordering
    only approaches, at the cost of computing it for every system. The cuts are two pixels
    wide so that they also cut the red-black reduced system (:class:`_RedBlack`), whose
    pixels are coupled two apart."""
    order: list[np.ndarray] = []
    # Depth first, both halves before their cut: blocks and the cuts waiting for them.
    stack: list = [(0, height, 0, width)]
    while stack:
        item = stack.pop()
        if isinstance(item, np.ndarray):
            order.append(item)
            continue
        top, bottom, left, right = item
        rows, cols = bottom - top, right - left
        if rows * cols <= DISSECTION_LEAF or min(rows, cols) < 5:
            order.append((np.arange(top, bottom)[:, None] * width + np.arange(left, right)).ravel())
            continue
        if cols >= rows:
            middle = (left + right) // 2 - 1
            halves = [(top, bottom, left, middle), (top, bottom, middle + 2, right)]
            cut = (np.arange(top, bottom)[:, None] * width + np.arange(middle, middle + 2)).ravel()
        else:
            middle = (top + bottom) // 2 - 1
            halves = [(top, middle, left, right), (middle + 2, bottom, left, right)]
            cut = (np.arange(middle, middle + 2)[:, None] * width + np.arange(left, right)).ravel()
        stack += [cut, halves[1], halves[0]]
    result = np.concatenate(order)
    result.flags.writeable = False
    return result


@lru_cache(maxsize=8)
def _red_black(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The red pixels (row + column even) of a row-major ``height x width`` grid and the black
    ones in :func:`grid_dissection_order`, ``(R,)`` and ``(B,)``."""
    order = grid_dissection_order(height, width)
    red = (order // width + order % width) % 2 == 0
    return np.sort(order[red]), order[~red]


class _RedBlack:
    """The screened system ``A x = b`` (``A`` ``(N, N)``, ``b`` ``(N,)`` or ``(N, k)``) of a
    row-major ``grid`` ``(h, w)`` whose pixels are coupled to their four neighbours only, reduced
    to its black pixels: a red pixel (row + column even) is coupled to black ones only, so its
    equation gives it from them, and substituted into theirs, leaves the black pixels' system
    ``reduced`` ``(B, B)`` with right-hand side ``rhs`` (exact; each black pixel is now
    coupled to the eight around it, its unknowns in :func:`grid_dissection_order`). Half the
    unknowns: a factorisation takes about a fifth less time than the whole grid's (the reduced
    system is denser), and conjugate gradients converge in about two thirds of the steps."""

    def __init__(self, A: sp.csr_matrix, b: np.ndarray, grid: tuple[int, int]) -> None:
        import scipy.sparse as sp

        self.red, self.black = _red_black(*grid)
        self.b = b
        self.inverse_red = (1.0 / A.diagonal()[self.red]).reshape(-1, *[1] * (b.ndim - 1))
        black_rows = A[self.black]
        self.black_red = black_rows[:, self.red]
        elimination = self.black_red @ sp.diags(self.inverse_red.ravel()) @ self.black_red.T
        self.reduced = black_rows[:, self.black] - elimination
        self.rhs = np.ascontiguousarray(b[self.black] - self.black_red @ (self.inverse_red * b[self.red]), np.float64)

    def solution(self, black: np.ndarray) -> np.ndarray:
        """``x`` ``(N,)`` or ``(N, k)`` from its black pixels' values ``black`` ``(B, ...)``."""
        x = np.empty(self.b.shape, np.float64)
        x[self.black] = black
        x[self.red] = self.inverse_red * (self.b[self.red] - self.black_red.T @ black)
        return x


def screened_solve(laplacian: sp.csr_matrix, seeds: np.ndarray, weight: np.ndarray, smoothness: float,
                   grid: tuple[int, int]) -> np.ndarray:
    """Solve ``(diag(weight) + smoothness * L) x = weight * seeds`` for ``seeds (N, k)``, where
    ``L`` couples each of the ``N = h * w`` pixels of the row-major ``grid`` ``(h, w)`` to its
    four neighbours only (:func:`_grid_laplacian`): reduced to the black pixels
    (:class:`_RedBlack`), factorised in :func:`grid_dissection_order`."""
    from scipy.sparse.linalg import splu

    system = _RedBlack(_screened_system(laplacian, weight, smoothness), weight[:, None] * seeds, grid)
    # Symmetric positive definite: no pivoting, which keeps the order. Narrow panels suit a
    # grid's small supernodes (SuperLU's defaults took a third more time on the whole grid).
    factor = splu(system.reduced.tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, relax=SUPERLU_RELAX,
                  panel_size=SUPERLU_PANEL, options={"SymmetricMode": True})
    return system.solution(factor.solve(system.rhs))


def anchored_solve(laplacian: sp.csr_matrix, target: np.ndarray, weight: np.ndarray, smoothness: float,
                   start: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """:func:`screened_solve` for one right-hand side ``target (N,)`` whose ``weight (N,)`` is
    positive at every pixel, by conjugate gradients (Jacobi preconditioned, on the reduced
    system of :class:`_RedBlack`) from ``start (N,)``. Returns ``(N,)``.

    The weight bounds the system's eigenvalues from below, so CG converges in a hundred or
    so matrix products whatever the grid; a system with unanchored pixels is better
    factorised (:func:`screened_solve`), and that is what this falls back to if CG does not
    converge."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import cg

    system = _RedBlack(_screened_system(laplacian, weight, smoothness), np.asarray(weight * target, np.float64), grid)
    reduced = system.reduced.tocsr()
    solved, info = cg(reduced, system.rhs, x0=np.asarray(start, np.float64)[system.black], rtol=CG_TOLERANCE,
                      atol=0.0, M=sp.diags(1.0 / reduced.diagonal()), maxiter=CG_MAX_ITERATIONS)
    if info != 0:
        return screened_solve(laplacian, target[:, None], weight, smoothness, grid)[:, 0]
    return system.solution(solved)


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
    planes, owners = dominant_planes(small, seeds, small_conf) if method == "planes" else (np.zeros((0, 3)), None)
    # One system, several right-hand sides: the harmonic fill, its reach and, for
    # ``planes``, every label's share of the random walk (planes, then off-plane).
    labels = [(owners.ravel() == k) * weight for k in range(len(planes) + 1)] if len(planes) else []
    with ThreadPoolExecutor(1) as worker:
        # SuperLU releases the GIL: the plane fields' factorisation overlaps this one.
        first = worker.submit(screened_solve, L, np.stack([small.ravel(), weight, *labels], -1), weight, smoothness,
                              (sh, sw))
        if method in ("planar", "planes"):
            params, plane_w = _local_planes(small, np.where(seeds, small_conf, 0.0), PLANE_WINDOW)
            fields = screened_solve(L, params.reshape(-1, 3), plane_w.ravel(), smoothness, (sh, sw))
        solved = first.result()
    dense, reach = solved[:, 0], solved[:, 1]
    v, u = np.mgrid[0:sh, 0:sw].astype(np.float64)
    if method in ("planar", "planes"):
        planar = fields[:, 0] * u.ravel() + fields[:, 1] * v.ravel() + fields[:, 2]
        # Far from their seeds, mixed or noisy planes can run away; stay within a
        # factor PLANE_LEASH of the harmonic solution (in inverse depth).
        harmonic = np.maximum(dense, far)
        planar = np.clip(planar, harmonic / PLANE_LEASH, harmonic * PLANE_LEASH)
        if len(planes):
            planar = _continue_planes(planar, planes, solved[:, 2:], u.ravel(), v.ravel(), far,
                                      PLANE_NEAR_LIMIT * float(small[seeds].max()))
        # Measurements where they exist, the extrapolated planes elsewhere.
        prior = 0.02
        blended = (weight * small.ravel() + prior * planar) / (weight + prior)
        dense = anchored_solve(L, blended, weight + prior, smoothness, blended, (sh, sw))
    dense = np.maximum(dense.reshape(sh, sw), far)
    reach = np.clip(reach.reshape(sh, sw), 0, 1)
    dense = cv2.resize(dense.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    reach = cv2.resize(reach.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    measured = (conf > 0.05) & (idepth > 0)
    out = np.where(measured, idepth, dense).astype(np.float32)
    out_conf = np.where(measured, conf, 0.5 * reach).astype(np.float32)
    return out, out_conf


def dominant_planes(idepth: np.ndarray, seeds: np.ndarray, conf: np.ndarray,
                    tolerance: float = PLANE_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Sequential RANSAC for planes ``1/z = a u + b v + c`` among the ``seeds`` ``(h, w)``
    bool of ``idepth`` ``(h, w)`` (weights ``conf``): the plane that explains the most seeds
    within ``tolerance`` (relative), refitted on them by weighted least squares, then the
    next among the rest, while one explains ``PLANE_MIN_SHARE`` of all seeds.

    Returns ``planes`` ``(K, 3)`` and ``owners`` ``(h, w)`` int: the plane each seed lies
    on, ``K`` for off-plane seeds (``-1`` where there is no seed)."""
    rng = np.random.default_rng(0)
    h, w = idepth.shape
    rows, cols = np.nonzero(seeds)
    design = np.stack([cols, rows, np.ones_like(cols)], 1).astype(np.float64)
    z, c = idepth[rows, cols].astype(np.float64), conf[rows, cols].astype(np.float64)
    free = np.ones(len(z), bool)
    planes, owner = [], np.full(len(z), -1, np.int64)
    while len(planes) < MAX_PLANES and free.sum() >= PLANE_MIN_SHARE * len(z) >= 3:
        pool = np.flatnonzero(free)
        scored = rng.choice(pool, min(len(pool), PLANE_SAMPLE), replace=False)
        triples = pool[rng.integers(0, len(pool), (PLANE_TRIALS, 3))]
        systems = design[triples]
        # Collinear or repeated triples determine no plane.
        solvable = np.abs(np.linalg.det(systems)) > 1e-6
        if not solvable.any():
            break
        hypotheses = np.linalg.solve(systems[solvable], z[triples][solvable][..., None])[..., 0]
        residual = np.abs(hypotheses @ design[scored].T - z[scored]) <= tolerance * z[scored]
        best = hypotheses[int(np.argmax(residual.sum(axis=1)))]
        on = free & (np.abs(design @ best - z) <= tolerance * z)
        if on.sum() < 3:
            break
        sw = np.sqrt(c[on])
        plane = np.linalg.lstsq(design[on] * sw[:, None], z[on] * sw, rcond=None)[0]
        on = free & (np.abs(design @ plane - z) <= tolerance * z)
        if on.sum() < PLANE_MIN_SHARE * len(z):
            break
        owner[on] = len(planes)
        planes.append(plane)
        free &= ~on
    owner[free] = len(planes)
    owners = np.full((h, w), -1, np.int64)
    owners[rows, cols] = owner
    return np.array(planes).reshape(-1, 3), owners


def _continue_planes(planar, planes, shares, u, v, far, near_limit):
    """``planar`` ``(N,)`` with every pixel whose largest random-walk share ``shares``
    ``(N, K + 1)`` is a plane's (not the off-plane column) set to that plane's inverse
    depth at ``(u, v)``, where it lies between ``far`` and ``near_limit``."""
    winner = np.argmax(shares, axis=1)
    on_plane = winner < len(planes)
    value = np.einsum("nk,nk->n", planes[np.minimum(winner, len(planes) - 1)], np.stack([u, v, np.ones_like(u)], 1))
    usable = on_plane & (value > far) & (value < near_limit)
    return np.where(usable, value, planar)
