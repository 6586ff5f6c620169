"""As-projective-as-possible local homographies: APAP's moving DLT (Zaragoza et al., TPAMI 2014).

One homography explains a rotation or a plane exactly; a scene with depth it explains only
on average. Moving DLT fits, at every cell of a grid, the homography of all matches
weighted by their distance to the cell: near matches it follows the scene's local
surface, far from them it relaxes to the global fit. It needs no focal and no depth, so
where a pair's focal or depth beyond the overlap is unsure it is often the better
prediction of the extension (``--model apap``; ``--model band`` lets the held-back band
choose it, :mod:`pis3r.stitch.choose`).

- global DLT (eq. 3-5): ``h = argmin ||A h||`` s.t. ``||h|| = 1``, on Hartley-normalised
  matches, ``A`` stacks two rows per match;
- moving DLT (eq. 7-9): at each cell centre ``x*``, ``h* = argmin ||W* A h||`` with
  ``W* = diag(w_1, w_1, ..., w_N, w_N)`` and ``w_i = max(exp(-||x* - x_i|| / sigma^2), gamma)``.
  (Eq. 8 prints the distance squared; the public Python port of APAP runs this kernel with
  ``sigma = 8.5`` px on images of about 720 px diagonal, which is what ``KERNEL_LENGTH``
  says relative to the image. ``gamma`` keeps a cell far from every match at the global fit.)

``||W A h||^2 = h^T (sum_i w_i^2 M_i) h`` with ``M_i = a_i1^T a_i1 + a_i2^T a_i2`` (9 x 9), so
every cell's solution is the eigenvector of the smallest eigenvalue of one weighted sum of
the ``M_i``: one matrix product over all cells, then a batched ``eigh``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pis3r.dlt import dlt_blocks, hartley_normalisation, smallest_eigenvectors
from pis3r.io import Photo
from pis3r.reconstruct.geometry import pixel_scale

# Moving-DLT kernel: its length ``sigma^2`` as a share of the image diagonal, and its floor.
KERNEL_LENGTH = 0.1
GAMMA = 0.0015
# Cells of the grid along the image's longer side: each cell is 2.5 % of it, a quarter of
# the kernel's length (APAP lays 100 cells over a canvas about three photos wide).
GRID_CELLS = 40
# Matches used at most (the weighted sums cost cells x matches x 81); a fixed draw.
MAX_MATCHES = 3000
# The ``apap`` model keeps the matches one homography explains within this many pixels of
# the photo as read (APAP's loose RANSAC step, as its public port runs it on the stitching
# literature's photos of up to about 1 MP), or within the same share of a photo larger than
# 1024 x 768 (:func:`local_warp_threshold`).
LOCAL_WARP_THRESHOLD_PX = 10.0


def moving_dlt(
    pts_src: np.ndarray, pts_dst: np.ndarray, centres: np.ndarray, sigma: float, gamma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Local homographies (src px -> dst px) ``(C, 3, 3)`` at ``centres`` ``(C, 2)`` (src px)
    and the global one ``(3, 3)``, from matches ``(N, 2)``, ``(N, 2)``; ``sigma`` (px) and
    ``gamma`` as in the module docstring."""
    T_src, T_dst = hartley_normalisation(pts_src), hartley_normalisation(pts_dst)
    src = pts_src @ T_src[:2, :2].T + T_src[:2, 2]
    dst = pts_dst @ T_dst[:2, :2].T + T_dst[:2, 2]
    blocks = dlt_blocks(src, dst).reshape(len(src), 81)
    denormalise = np.linalg.inv(T_dst)

    def to_pixels(h: np.ndarray) -> np.ndarray:
        H = denormalise @ h.reshape(-1, 3, 3) @ T_src
        return H / H[:, 2:3, 2:3]

    global_h = to_pixels(smallest_eigenvectors(blocks.sum(axis=0).reshape(1, 9, 9)))[0]
    distance = np.hypot(centres[:, :1] - pts_src[:, 0], centres[:, 1:] - pts_src[:, 1])
    weights = np.maximum(np.exp(-distance / sigma**2), gamma)
    # ||W A h||^2 weights each match's two rows by w_i^2.
    local = smallest_eigenvectors((weights**2 @ blocks).reshape(-1, 9, 9))
    return to_pixels(local), global_h


@dataclass(frozen=True)
class LocalWarp:
    """Where the pixels of one view land in the image of another (``onto``: that view's
    index, as in :attr:`pis3r.scene.Scene.indices`): ``homographies`` ``(rows, cols, 3, 3)``,
    one per ``cell``-pixel square of the view, each taking this view's pixels to ``onto``'s."""

    homographies: np.ndarray
    cell: int
    onto: int

    def apply(self, pixels: np.ndarray) -> np.ndarray:
        """``(N, 2)`` float32 positions in ``onto``'s image of ``pixels`` ``(N, 2)`` of this
        view (each by its cell's homography); NaN where that homography sends it to infinity
        or behind (a non-positive denominator)."""
        rows, cols = self.homographies.shape[:2]
        col = np.clip((pixels[:, 0] // self.cell).astype(np.int64), 0, cols - 1)
        row = np.clip((pixels[:, 1] // self.cell).astype(np.int64), 0, rows - 1)
        H = self.homographies[row, col]
        homogeneous = np.einsum("nij,nj->ni", H, np.hstack([pixels, np.ones((len(pixels), 1))]))
        with np.errstate(divide="ignore", invalid="ignore"):
            mapped = homogeneous[:, :2] / homogeneous[:, 2:]
        mapped[homogeneous[:, 2] <= 0] = np.nan
        return mapped.astype(np.float32)


def local_warp_threshold(photo: Photo) -> float:
    """The ``apap`` model's loose homography threshold in pixels of ``photo``:
    ``LOCAL_WARP_THRESHOLD_PX`` in pixels of the photo as read, or the same share of a photo
    read larger than 1024 x 768, scaled to a working copy (``Photo.scale``: the held-back band
    test's copies keep the matches the whole photo would). Pixels, not a share of every photo:
    on the crop protocol, scaling the 10 px down with photos smaller than 1024 x 768 dropped
    matches the local fits need (``ela-DFW_desk`` 500 x 375: 23.98 -> 26.77 dB with APAP's
    local homographies forced; no pair lost more than 0.1 dB)."""
    read_size = photo.width / photo.scale, photo.height / photo.scale
    return LOCAL_WARP_THRESHOLD_PX * photo.scale * max(1.0, pixel_scale(*read_size))


def fit_local_warp(pts_view: np.ndarray, pts_onto: np.ndarray, width: int, height: int, onto: int,
                   onto_diagonal: float) -> LocalWarp:
    """The moving-DLT warp of a ``width x height`` view onto view ``onto`` (an image of
    ``onto_diagonal`` px) from matches ``(N, 2)`` (view px) -> ``(N, 2)`` (``onto`` px), at
    least 4, on a grid of ``GRID_CELLS`` along the longer side. The kernel is
    ``KERNEL_LENGTH`` of the diagonal of the image the view is placed onto: that is the
    picture whose structure it follows."""
    if len(pts_view) > MAX_MATCHES:
        keep = np.random.default_rng(0).choice(len(pts_view), MAX_MATCHES, replace=False)
        pts_view, pts_onto = pts_view[keep], pts_onto[keep]
    cell = max(1, math.ceil(max(width, height) / GRID_CELLS))
    cols, rows = -(-width // cell), -(-height // cell)
    cy, cx = np.mgrid[0:rows, 0:cols]
    centres = np.stack([cx.ravel(), cy.ravel()], axis=1) * cell + (cell - 1) / 2.0
    sigma = math.sqrt(KERNEL_LENGTH * onto_diagonal)
    local, _ = moving_dlt(pts_view, pts_onto, centres, sigma, GAMMA)
    return LocalWarp(local.reshape(rows, cols, 3, 3), cell, onto)
