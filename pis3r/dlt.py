"""The direct linear transform of a homography, in pieces that batch: Hartley normalisation,
each match's ``(9, 9)`` block of ``A^T A``, and the smallest eigenvector of a sum of blocks.

A homography ``h`` (9 entries, ``||h|| = 1``) fits weighted matches best where
``h^T (sum_i w_i M_i) h`` is smallest; the moving DLT of :mod:`pis3r.reconstruct.local_warp`
sums every match per grid cell, the least-quantile fit of :mod:`pis3r.robust` four per draw.
"""

from __future__ import annotations

import numpy as np


def hartley_normalisation(points: np.ndarray) -> np.ndarray:
    """``(3, 3)`` similarity moving ``(N, 2)`` points to zero mean, mean distance sqrt(2)."""
    centre = points.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.linalg.norm(points - centre, axis=1).mean(), 1e-12)
    return np.array([[scale, 0.0, -scale * centre[0]], [0.0, scale, -scale * centre[1]], [0.0, 0.0, 1.0]])


def dlt_blocks(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``M_i = a_i1^T a_i1 + a_i2^T a_i2`` ``(N, 9, 9)`` for ``dst ~ H src`` (normalised
    ``(N, 2)`` points), where ``a_i1, a_i2`` are the two DLT rows of match ``i``."""
    x, y = src[:, 0], src[:, 1]
    u, v = dst[:, 0], dst[:, 1]
    zero, one = np.zeros_like(x), np.ones_like(x)
    row1 = np.stack([zero, zero, zero, -x, -y, -one, v * x, v * y, v], axis=1)
    row2 = np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], axis=1)
    return row1[:, :, None] * row1[:, None, :] + row2[:, :, None] * row2[:, None, :]


def smallest_eigenvectors(matrices: np.ndarray) -> np.ndarray:
    """Unit eigenvectors ``(B, 9)`` of the smallest eigenvalue of symmetric ``(B, 9, 9)``."""
    _, vectors = np.linalg.eigh(matrices)
    return vectors[:, :, 0]
