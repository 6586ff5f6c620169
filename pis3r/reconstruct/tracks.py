"""The tracks of a multi-view registration's pairs and where their joint fit starts
(:mod:`pis3r.reconstruct.joint`).

A pair joins a view to its anchor: the reference, or a view it is chained to. The tracks are
the pairs' matches linked through the keypoints they share; the start places each view through
its pair and anchor, the pair's unknown scale tied to the points already placed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pis3r.camera import pixel_rays
from pis3r.features import Matches
from pis3r.reconstruct.pairs import PairGeometry

# A view joins the fit through at least this many points it shares with views already in it.
MIN_SHARED_POINTS = 20
# Matches nearer than this (depth along the anchor's ray, relative) to the anchor camera's
# plane, or behind a camera, are left out of the start.
MIN_DEPTH = 1e-6


@dataclass(frozen=True)
class JointStart:
    """Where a joint fit starts. Cameras: 0 the reference (the world frame), then ``c = 1..V``
    the views ``views[c - 1]`` (view indices, each after its anchor), with intrinsics ``K``
    ``(V + 1, 3, 3)``. Observations: ``point`` ``(N,)`` of the ``P`` points seen at ``xy``
    ``(N, 2)`` in ``camera`` ``(N,)``. Unknowns: the views' ``R`` ``(V, 3, 3)`` and ``t``
    ``(V, 3)`` (``x = R X + t``), the points ``X`` ``(P, 3)``."""

    views: tuple[int, ...]
    K: np.ndarray
    camera: np.ndarray
    point: np.ndarray
    xy: np.ndarray
    R: np.ndarray
    t: np.ndarray
    X: np.ndarray


def joint_start(pairs: dict[int, PairGeometry], anchors: dict[int, int] | None = None) -> JointStart | None:
    """The start of the joint fit of the 3-D ``pairs`` (view index -> its geometry with its
    anchor: view ``anchors[j]``, the reference (0) where absent; all with the reference's focal
    scale; pairs of other models are left out): the tracks (:func:`match_tracks`) of their
    matches, each view placed through its pair and anchor at the scale the points already placed
    give it (:func:`_start`). A chained view follows its anchor into the fit or out of it.
    ``None`` where fewer than two views share enough points to be fitted together."""
    anchors = anchors or {}
    solid = {j for j, pair in pairs.items() if pair.model == "3d"}
    order = sorted(j for j in solid if anchors.get(j, 0) == 0)
    for j in anchors:
        if j in solid and anchors[j] in [0, *order]:
            order.append(j)
    if len(order) < 2:
        return None
    camera_of = {0: 0, **{j: c for c, j in enumerate(order, start=1)}}
    edges = [(camera_of[anchors.get(j, 0)], camera_of[j], pairs[j]) for j in order]
    K = np.stack([edges[0][2].K_a] + [pair.K_b for _, _, pair in edges])
    nodes = match_tracks([(a, b, pair.inliers) for a, b, pair in edges])
    start = _start(edges, K, nodes)
    if start is None:
        return None
    placed, R, t, X, measured = start
    *_, camera, point, xy = nodes
    keep = placed[camera] & measured & np.isfinite(X[point, 0])
    # One observation of a track per camera: a track that reaches two keypoints of one photo
    # keeps the first.
    _, first = np.unique(point[keep] * len(K) + camera[keep], return_index=True)
    rows = np.flatnonzero(keep)[np.sort(first)]
    used, renumber = np.unique(point[rows], return_inverse=True)
    joined = np.flatnonzero(placed[1:]) + 1
    slot = np.zeros(len(K), np.int64)
    slot[joined] = np.arange(1, len(joined) + 1)
    return JointStart(tuple(order[c - 1] for c in joined), np.concatenate([K[:1], K[joined]]), slot[camera[rows]],
                      renumber.ravel(), xy[rows], R[joined], t[joined], X[used])


def match_tracks(edges: list[tuple[int, int, Matches]]):
    """The tracks of the matches ``edges`` (camera ``a``, camera ``b``, matches ``a`` -> ``b``):
    the keypoints (camera, pixel) linked by any match, connected. Returns the keypoints of each
    match's ends ``(E,)`` and ``(E,)`` (the edges' matches in order), and per distinct keypoint
    its ``camera`` ``(N,)``, ``track`` ``(N,)`` and pixel ``xy`` ``(N, 2)``, the keypoints
    sorted by camera, then pixel."""
    # Only multi-view stitches get here: importing pis3r stays fast.
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count = sum(len(m) for *_, m in edges)
    ends = np.concatenate([np.column_stack([np.full(len(m), a, float), m.pts_a]) for a, _, m in edges]
                          + [np.column_stack([np.full(len(m), b, float), m.pts_b]) for _, b, m in edges])
    keys, node = np.unique(ends, axis=0, return_inverse=True)
    node = node.ravel()
    link = coo_matrix((np.ones(count), (node[:count], node[count:])), shape=(len(keys), len(keys)))
    _, track = connected_components(link, directed=False)
    return node[:count], node[count:], keys[:, 0].astype(np.int64), track, keys[:, 1:]


def _start(edges, K, nodes):
    """Start of the fit: each view placed through its pair and anchor, the pair's scale tied
    by the median depth ratio over the points already placed (the first pair's is 1), in
    rounds while views are placed. Returns the cameras placed ``(C,)``, their ``R``
    ``(C, 3, 3)`` and ``t`` ``(C, 3)``, each track's point ``(T, 3)`` (NaN where no placed pair
    measured it) and whether each keypoint took part in a measurement ``(N,)``; ``None`` where
    fewer than two views are placed."""
    node_a, node_b, camera, track, xy = nodes
    cameras, tracks = len(K), int(track.max()) + 1
    R, t = np.broadcast_to(np.eye(3), (cameras, 3, 3)).copy(), np.zeros((cameras, 3))
    placed = np.zeros(cameras, bool)
    placed[0] = True
    spans = np.cumsum([0] + [len(pair.inliers) for *_, pair in edges])
    known = np.full((tracks, 3), np.nan)
    measured = np.zeros(len(camera), bool)
    estimates = []
    remaining, progress = list(range(len(edges))), True
    while progress:
        progress = False
        for e in [e for e in remaining if placed[edges[e][0]]]:
            a, b, pair = edges[e]
            depth, ends = _pair_depths(pair), slice(spans[e], spans[e + 1])
            valid, tracks_e = depth > 0, track[node_a[ends]]
            scale = 1.0
            if placed.sum() > 1:
                shared = valid & np.isfinite(known[tracks_e, 0])
                if shared.sum() < MIN_SHARED_POINTS:
                    continue
                # The placed points' depth along the anchor's rays, over the pair's.
                scale = float(np.median((known[tracks_e[shared]] @ R[a].T + t[a])[:, 2] / depth[shared]))
                if not scale > 0:
                    continue
            R[b], t[b], placed[b] = pair.R @ R[a], pair.R @ t[a] + scale * pair.t, True
            points = (pixel_rays(pair.inliers.pts_a[valid], pair.K_a) * (scale * depth[valid])[:, None] - t[a]) @ R[a]
            known[tracks_e[valid]] = points
            measured[node_a[ends][valid]] = measured[node_b[ends][valid]] = True
            estimates.append((tracks_e[valid], points))
            remaining.remove(e)
            progress = True
    if placed.sum() < 3:
        return None
    return placed, R, t, _track_points(estimates, placed, R, t, K, (camera, track, xy), tracks), measured


def _pair_depths(pair: PairGeometry) -> np.ndarray:
    """``(E,)``: each inlier's depth along its ray in the pair's first view ``a`` (its unit
    translation's scale), 0 where undetermined or behind."""
    ray = pixel_rays(pair.inliers.pts_a, pair.K_a) @ pair.R.T
    seen = pixel_rays(pair.inliers.pts_b, pair.K_b)
    # The depth d along the ray that puts d R r + t on the ray seen in b.
    across, offset = np.cross(seen, ray), np.cross(seen, pair.t)
    d = -np.sum(across * offset, axis=1) / np.maximum(np.sum(across * across, axis=1), 1e-300)
    return np.where(np.isfinite(d) & (d > MIN_DEPTH), d, 0.0)


def _track_points(estimates, placed, R, t, K, keypoints, tracks: int) -> np.ndarray:
    """``(T, 3)``: each track's point on the ray of its first keypoint in a placed camera (the
    reference's where it has one), at the mean inverse depth, along that ray, of the estimates
    the pairs made of it (``estimates``: (tracks, points) per pair); NaN where none did."""
    camera, track, xy = keypoints
    on = np.flatnonzero(placed[camera])
    _, first = np.unique(track[on], return_index=True)
    owner = np.full(tracks, -1)
    owner[track[on][first]] = on[first]
    ids = np.concatenate([ids for ids, _ in estimates])
    points = np.concatenate([points for _, points in estimates])
    cam = camera[owner[ids]]
    z = np.einsum("nj,nj->n", R[cam, 2], points) + t[cam, 2]
    ahead = z > 0
    inverse = np.bincount(ids[ahead], 1.0 / z[ahead], tracks)
    count = np.bincount(ids[ahead], minlength=tracks)
    X = np.full((tracks, 3), np.nan)
    seen = count > 0
    first_cam = camera[owner[seen]]
    pixels = np.column_stack([xy[owner[seen]], np.ones(int(seen.sum()))])
    rays = np.einsum("nij,nj->ni", np.linalg.inv(K)[first_cam], pixels)
    local = rays * (count[seen] / inverse[seen])[:, None] - t[first_cam]
    X[seen] = np.einsum("nji,nj->ni", R[first_cam], local)
    return X
