"""Focal length from one photo's vanishing points, for pairs whose matches leave the focal free.

Two views determine a focal only when their optical axes do not meet (Bougnoux's
degeneracy): a camera turned towards what it walks around, or a pair with few matches,
leaves the epipolar cost flat along the focal. Straight edges of buildings and rooms carry
the focal in each photo on its own: the vanishing points ``v1``, ``v2`` of two orthogonal
directions satisfy ``(v1 - c) . (v2 - c) = -f^2`` (``c`` the principal point). Each photo
is measured on its own, and a focal is trusted only where both photos of a pair give the
same one (:func:`agreed_focal`): edges that are not orthogonal, or vanishing points near
infinity, give a focal that lands anywhere, and two such focals rarely agree.

Pixel coordinates follow the OpenCV convention, the principal point at the image centre.
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np

# Edges are found on a copy at most this long (px): the focal needs no finer edges.
WORKING_SIDE = 1024
# Shortest edge kept, as a share of the working copy's longest side: short edges have
# directions too noisy to point at a vanishing point. At most the MAX_EDGES longest are
# kept: the vote over all candidates costs candidates x edges.
MIN_EDGE_SHARE = 0.03
MAX_EDGES = 250
# Fewer edges than this: no focal (two directions need a few edges each).
MIN_EDGES = 12
# Candidate vanishing points: intersections of every two of this many longest edges.
CANDIDATE_EDGES = 120
# An edge supports a vanishing point when the line from its midpoint to the point is within
# this angle of the edge.
EDGE_ANGLE_DEG = 1.5
# Vanishing points are taken one after the other, each from the edges the earlier ones left,
# while one gathers at least this share of all edges' length.
MAX_POINTS = 5
MIN_SUPPORT = 0.05
# Focals outside these multiples of the longest side are not lenses.
FOCAL_RANGE = (0.3, 4.0)
# A vanishing point farther from the centre than this many longest sides is too close to
# infinity to locate: its direction is known, its distance (which the focal needs) is not.
MAX_POINT_DISTANCE = 30.0
# A third vanishing point counts for a pair's focal when its direction is within this angle
# of the direction orthogonal to both.
THIRD_ANGLE_DEG = 3.0
# The two photos' focals (in the reference's pixels) must agree within this relative
# difference to be trusted.
PAIR_AGREEMENT = 0.15


def edge_segments(gray: np.ndarray) -> np.ndarray:
    """``(N, 4)`` straight edges ``x0, y0, x1, y1`` in pixels of ``gray`` ``(H, W)`` uint8, the
    longest first, at most ``MAX_EDGES``."""
    scale = min(1.0, WORKING_SIDE / max(gray.shape))
    small = gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    detector = cv2.ximgproc.createFastLineDetector(length_threshold=int(MIN_EDGE_SHARE * max(small.shape)),
                                                   do_merge=True)
    found = detector.detect(small)
    if found is None:
        return np.zeros((0, 4))
    edges = found.reshape(-1, 4).astype(np.float64) / scale
    return edges[np.argsort(-np.linalg.norm(edges[:, 2:] - edges[:, :2], axis=1), kind="stable")[:MAX_EDGES]]


def vanishing_points(edges: np.ndarray, width: int, height: int) -> list[tuple[np.ndarray, float]]:
    """The dominant vanishing points of ``edges`` ``(N, 4)`` in a ``width x height`` image:
    ``(v, support)`` with ``v`` ``(3,)`` homogeneous in centred pixels divided by the longest
    side (``v[2] = 0`` at infinity) and ``support`` the share of all edges' length it explains.
    Each is the candidate (an intersection of two long edges) that the most edge length
    points at, refined by least squares over those edges."""
    side = max(width, height)
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    start, end = (edges[:, :2] - centre) / side, (edges[:, 2:] - centre) / side
    lengths = np.linalg.norm(end - start, axis=1)
    midpoints, directions = 0.5 * (start + end), (end - start) / lengths[:, None]
    lines = np.cross(np.c_[start, np.ones(len(edges))], np.c_[end, np.ones(len(edges))])
    first, second = np.triu_indices(min(len(edges), CANDIDATE_EDGES), 1)
    candidates = _unit(np.cross(lines[first], lines[second]))
    supports = _supports(candidates, midpoints, directions)
    unexplained, total, found = np.ones(len(edges), bool), lengths.sum(), []
    for _ in range(MAX_POINTS):
        scores = (supports & unexplained) @ lengths
        best = int(np.argmax(scores))
        if scores[best] < MIN_SUPPORT * total:
            break
        members = supports[best] & unexplained
        # The point nearest (in the least-squares sense) to all its edges' lines, longer ones weighing more.
        weighted = lines[members] / np.linalg.norm(lines[members, :2], axis=1, keepdims=True)
        point = np.linalg.svd(weighted * np.sqrt(lengths[members])[:, None])[2][-1]
        found.append((point, float(scores[best] / total)))
        unexplained &= ~_supports(point[None], midpoints, directions)[0]
    return found


def photo_focal(gray: np.ndarray) -> float | None:
    """The focal (pixels) of ``gray`` ``(H, W)`` uint8 that makes two of its vanishing points
    orthogonal; ``None`` when no two can be (too few edges, points near infinity, or a focal
    outside ``FOCAL_RANGE``). Of several such pairs, the one with the most edge length wins,
    counting a third point where the pair's focal puts it (the third orthogonal direction):
    a true corner of a building or a room explains all three."""
    height, width = gray.shape
    edges = edge_segments(gray)
    if len(edges) < MIN_EDGES:
        return None
    points = vanishing_points(edges, width, height)
    best = None
    for (i, (v1, support_1)), (j, (v2, support_2)) in itertools.combinations(enumerate(points), 2):
        if min(abs(v1[2]), abs(v2[2])) * MAX_POINT_DISTANCE < max(np.linalg.norm(v1[:2]), np.linalg.norm(v2[:2])):
            continue
        squared = -float(v1[:2] @ v2[:2]) / (v1[2] * v2[2])
        if squared <= 0 or not FOCAL_RANGE[0] < np.sqrt(squared) < FOCAL_RANGE[1]:
            continue
        focal = np.sqrt(squared)
        third = np.cross(_direction(v1, focal), _direction(v2, focal))
        support = support_1 + support_2 + max(
            [s for k, (v, s) in enumerate(points)
             if k not in (i, j) and abs(_direction(v, focal) @ third) > np.cos(np.deg2rad(THIRD_ANGLE_DEG))],
            default=0.0)
        if best is None or support > best[1]:
            best = (float(focal) * max(width, height), support)
    return None if best is None else best[0]


def agreed_focal(focal_a: float | None, focal_b: float | None, ratio: float) -> float | None:
    """Photo a's focal (pixels) when the two photos' own focals agree within
    ``PAIR_AGREEMENT`` given ``focal_b = ratio * focal_a``: their geometric mean; else ``None``."""
    if focal_a is None or focal_b is None:
        return None
    focal_b /= ratio
    if abs(focal_a - focal_b) > PAIR_AGREEMENT * min(focal_a, focal_b):
        return None
    return float(np.sqrt(focal_a * focal_b))


def _supports(points: np.ndarray, midpoints: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """``(M, N)`` bool: whether the line from each edge's midpoint to each homogeneous point
    ``(M, 3)`` is within ``EDGE_ANGLE_DEG`` of the edge (``sin^2`` compared, no roots or
    divisions: this runs over every candidate and edge)."""
    towards_x = points[:, :1] - points[:, 2:] * midpoints[None, :, 0]
    towards_y = points[:, 1:2] - points[:, 2:] * midpoints[None, :, 1]
    cross = directions[None, :, 0] * towards_y
    cross -= directions[None, :, 1] * towards_x
    towards_x *= towards_x
    towards_y *= towards_y
    towards_x += towards_y
    towards_x *= np.sin(np.deg2rad(EDGE_ANGLE_DEG)) ** 2
    cross *= cross
    return cross < towards_x


def _direction(point: np.ndarray, focal: float) -> np.ndarray:
    """The unit direction in the camera, ``K^-1 v``, of a vanishing point ``(3,)`` (centred
    pixels over the longest side, as :func:`vanishing_points` gives it) at ``focal`` (same units)."""
    return _unit(np.array([point[0], point[1], focal * point[2]]))


def _unit(vectors: np.ndarray) -> np.ndarray:
    return vectors / (np.linalg.norm(vectors, axis=-1, keepdims=True) + 1e-12)
