"""The focal that closes a turn (issue 41).

Photos of a full turn are chained photo to photo back to the reference, and each link's
rotation depends on the focal: at a focal 10 % long every link turns a little too far or too
little, and after 16 links the last photo misses the first by tens of degrees (the cathedral:
35 deg at the 2641 px its first pair's rotation chose, 3 deg at 2400 px). The first and the last
photo of a turn shot in order overlap, and the chains from the reference meet between two photos
taken one after the other opposite it: their own pair gives their relative rotation directly,
and the chained cameras must agree with it. :func:`closed_turn` searches the focal at which they
do where they do not (the chain rebuilt at each, the matches reused), and keeps it where the
turn closes within ``CLOSED_DEG``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from functools import cache

import numpy as np

from pis3r.camera import pixel_rays, rotation_angle_deg
from pis3r.errors import Pis3rError
from pis3r.io import Photo
from pis3r.reconstruct.focal import FLAG_SOURCE, FocalInterval
from pis3r.projection import level_rotation
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.scene import Scene

# A turn is closed where the chained cameras of its first and last photo agree with their own
# pair within this (degrees).
CLOSED_DEG = 5.0
# The focals searched: this factor either way of the one the chain was built with, narrowed by
# golden sections until the bracket is within FOCAL_TOLERANCE of its middle.
SEARCH_FACTOR = 1.3
FOCAL_TOLERANCE = 0.015
# Fewer photos than this make no turn; nor do views whose fields of view, around the level
# horizon, cover less than this many degrees of longitude.
MIN_TURN_PHOTOS = 5
MIN_TURN_DEG = 300.0


def closed_turn(scene: Scene, photos: list[Photo], order: list[int], options: ReconstructOptions,
                memo: dict) -> tuple[Scene, str]:
    """``(scene, line)``: the classical backend's ``scene`` of ``photos`` (built with ``options``
    and ``memo``; ``photos[k]`` is input ``order[k]``, the reference first), a turn
    (:func:`looks_like_a_turn`: the caller tells), at the focal that closes it, and the line
    that says so; ``scene`` itself and ``""`` where it closes already or no focal closes it.

    Input order is taken as shooting order: the chains from the reference meet across the turn,
    between two photos taken one after the other (cyclically). Of those pairs, the one whose
    chained cameras disagree most with its own pair closes it."""
    # Imported when run, as pis3r.reconstruct.base builds backends: a stitch by another backend
    # never loads this one.
    from pis3r.reconstruct.classical import MULTI_VIEW_FEATURES, ClassicalReconstructor

    if options.focal or scene.focal is None:
        return scene, ""
    count = len(order)

    # The closing pair's fit at the focal found serves both the choice of the pair and the search.
    @cache
    def pair_rotation(focal: float, first: int, last: int) -> np.ndarray:
        # Matched as the backend matches a set's later pairs (their SIFT features memoised).
        backend = ClassicalReconstructor(replace(options, focal=focal), memo)
        features = backend.features([photos[first], photos[last]], MULTI_VIEW_FEATURES)
        return backend.pair_geometry(*features, focal, FLAG_SOURCE, True, True, "SIFT", MULTI_VIEW_FEATURES).R

    gaps = {}
    for earlier in range(count):
        first, last = order.index(earlier), order.index((earlier + 1) % count)
        if first in scene.indices and last in scene.indices:
            try:
                gaps[first, last] = _closing_gap(scene, first, last, pair_rotation(scene.focal, first, last))
            except Pis3rError:
                continue
    if not gaps:
        return scene, ""
    first, last = max(gaps, key=gaps.get)
    return close_the_turn(scene, [photo.name for photo in photos], first, last,
                          lambda focal: ClassicalReconstructor(replace(options, focal=focal), memo).reconstruct(photos),
                          lambda focal: pair_rotation(focal, first, last))


def close_the_turn(scene: Scene, names: list[str], first: int, last: int, rebuild: Callable[[float], Scene],
                   pair_rotation: Callable[[float], np.ndarray]) -> tuple[Scene, str]:
    """:func:`closed_turn` with its two measurements given: ``rebuild(focal)``, the scene with
    every photo at that focal; ``pair_rotation(focal)``, the ``(3, 3)`` rotation from the camera
    at position ``first`` to the one at ``last`` that their own pair gives at that focal (raising
    :class:`pis3r.Pis3rError` where they do not overlap). ``names``: the photos', for the line."""
    found = scene.focal
    try:
        at_found = _closing_gap(scene, first, last, pair_rotation(found))
    except Pis3rError:
        return scene, ""
    if at_found <= CLOSED_DEG:
        return scene, ""
    tried: dict[float, float] = {}
    # Only the best scene so far is kept: each holds every photo's depth (a turn's: gigabytes).
    kept: list = [math.inf, None]

    def gap(log_focal: float) -> float:
        focal = math.exp(log_focal)
        if focal not in tried:
            try:
                built = rebuild(focal)
                tried[focal] = _closing_gap(built, first, last, pair_rotation(focal))
            except Pis3rError:
                tried[focal], built = math.inf, None
            if tried[focal] < kept[0]:
                kept[:] = [tried[focal], built]
            del built
        return tried[focal]

    # Golden sections on the log focal: the gap falls toward the closing focal from either side.
    ratio = (math.sqrt(5) - 1) / 2
    a, b = math.log(found / SEARCH_FACTOR), math.log(found * SEARCH_FACTOR)
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    while b - a > 2 * FOCAL_TOLERANCE:
        if gap(c) < gap(d):
            b, d = d, c
            c = b - ratio * (b - a)
        else:
            a, c = c, d
            d = a + ratio * (b - a)
    best = min(tried, key=tried.get)
    closed, built = kept
    if built is None or closed > CLOSED_DEG:
        return scene, ""
    closing = [focal for focal, value in tried.items() if value <= CLOSED_DEG]
    line = (f"the turn closes at a focal of {best:.0f} px: {names[first]} and {names[last]} agree within "
            f"{closed:.1f} deg ({at_found:.0f} deg apart at the {found:.0f} px the first pair gave)")
    return replace(built, focal_source=f"closes the turn ({names[first]} to {names[last]})",
                   focal_interval=FocalInterval(min(closing), max(closing))), line


def looks_like_a_turn(scene: Scene) -> bool:
    """Whether ``scene`` has ``MIN_TURN_PHOTOS`` views or more whose fields of view cover at
    least ``MIN_TURN_DEG`` of longitude (:func:`longitudes_covered`)."""
    return len(scene.views) >= MIN_TURN_PHOTOS and longitudes_covered(scene) >= MIN_TURN_DEG


def longitudes_covered(scene: Scene) -> float:
    """Degrees of longitude, around the views' common vertical, that their fields of view cover
    (each view's from its left to its right edge at the height of its centre)."""
    frame = level_rotation([view.camera.R for view in scene.views])
    covered = np.zeros(360, bool)
    for view in scene.views:
        camera = view.camera
        edges = pixel_rays(np.array([[0.0, (camera.height - 1) / 2], [camera.width - 1.0, (camera.height - 1) / 2]]),
                           camera.K) @ (frame @ camera.R.T).T
        left, right = np.degrees(np.arctan2(edges[:, 0], edges[:, 2]))
        span = (right - left) % 360
        covered[np.round(left + np.arange(int(np.ceil(span)) + 1)).astype(int) % 360] = True
    return float(covered.sum())


def _closing_gap(scene: Scene, first: int, last: int, rotation) -> float:
    """Degrees between the rotation from position ``first``'s camera to ``last``'s in ``scene``
    and ``rotation``; infinite where either photo is not in the scene."""
    if first not in scene.indices or last not in scene.indices:
        return math.inf
    R_first = scene.views[scene.indices.index(first)].camera.R
    R_last = scene.views[scene.indices.index(last)].camera.R
    return rotation_angle_deg(rotation @ (R_last @ R_first.T).T)
