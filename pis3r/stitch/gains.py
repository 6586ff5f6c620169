"""Exposure gains of many views solved together over all their overlaps (issue 41).

On a perspective canvas every view overlaps the reference, and its gain and lens falloff are
fitted there (:mod:`pis3r.stitch.exposure`). Around a turn most views never meet the reference:
their gains come from their neighbours. Brown and Lowe's gain compensation (IJCV 2007, section
6) weighs every pair of views by the pixels they share: for each channel, the gains ``g`` minimise

    sum over pairs (i, j) of N_ij ((g_i I_ij - g_j I_ji)^2 / sigma_N^2 + (1 - g_i)^2 / sigma_g^2)

where ``N_ij`` is their overlap's pixel count and ``I_ij`` view ``i``'s mean colour there; the
second term keeps the gains near 1 where the overlaps leave them free. The quadratic's minimum is
one linear solve. The gains are then divided by their geometric mean: the turn comes out at its
photos' average exposure, the reference's gain included. Pinned to the reference instead, the
cathedral's 16 other photos were brought to its exposure, 0.6-0.9 x theirs (it faces the lit
apse): the whole turn darker, NIQE 3.62 against 3.27 at the average (and 3.33 with no gains;
OpenCV's Stitcher 3.47; all four on one rectangle of each result, README). A panorama keeps the reference's rays, not its colours.
"""

from __future__ import annotations

import numpy as np

from pis3r.stitch.exposure import GAIN_RANGE

# sigma_N and sigma_g of the cost above, on colours in [0, 1]. Brown and Lowe's sigma_g, 0.1,
# weighs the prior about as much as the overlaps (their I^2 / sigma_N^2 at mid-grey): it pulls
# the gains halfway back to 1 (a ring of views 0.8-1.1 x the reference's exposure came out
# 0.91-1.12 x where 0.91-1.25 x was right). 1.0 leaves the overlaps to decide and still holds a
# view that overlaps nothing at 1.
GAIN_NOISE = 10.0 / 255.0
GAIN_SPREAD = 1.0


def overlap_statistics(colours: list[np.ndarray], valid: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(N (n, n), I (n, n, 3))``: for each pair of the ``n`` views, the pixels where both are
    ``valid`` (each ``(H, W)`` bool on one canvas) and view ``i``'s mean colour there (its
    ``colours`` ``(H, W, 3)``)."""
    n = len(colours)
    counts = np.zeros((n, n))
    means = np.zeros((n, n, 3))
    for i in range(n):
        for j in range(i + 1, n):
            both = valid[i] & valid[j]
            counts[i, j] = counts[j, i] = both.sum()
            if counts[i, j]:
                means[i, j] = colours[i][both].mean(axis=0)
                means[j, i] = colours[j][both].mean(axis=0)
    return counts, means


def solve_gains(counts: np.ndarray, means: np.ndarray) -> np.ndarray:
    """``(n, 3)`` gains per view and channel minimising the module's cost for the overlaps
    ``counts`` and ``means`` (:func:`overlap_statistics`), their geometric mean 1, each within
    :data:`pis3r.stitch.exposure.GAIN_RANGE`."""
    n = len(counts)
    alpha, beta = 1.0 / GAIN_NOISE**2, 1.0 / GAIN_SPREAD**2
    gains = np.ones((n, 3))
    for channel in range(3):
        intensity = means[..., channel]
        # A view that overlaps nothing keeps gain 1 (a pixel's worth of prior).
        A = np.diag(beta * (counts.sum(axis=1) + 1.0) + 2 * alpha * (intensity**2 * counts).sum(axis=1))
        A -= 2 * alpha * intensity * intensity.T * counts
        b = beta * (counts.sum(axis=1) + 1.0)
        gains[:, channel] = np.linalg.solve(A, b)
    return np.clip(gains / np.exp(np.log(gains).mean(axis=0)), *GAIN_RANGE)
