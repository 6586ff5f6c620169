"""What every reconstruction backend receives (a slice of :class:`pis3r.StitchOptions`)."""

from __future__ import annotations

import os
from dataclasses import dataclass

from pis3r.reconstruct.propagate import DEFAULT_DEPTH_FILL

# Points whose confidence (0..1) is below this are dropped; 0 keeps all, as the paper does.
DEFAULT_CONF_THRESHOLD = 0.0
# ``auto``: the backend's own degeneracy test; ``homography`` (rotation or one plane),
# ``apap`` (the homography's cameras, the views placed by local homographies) or ``3d``
# force a model where the backend has a choice (the classical one).
RECONSTRUCT_MODELS = ("auto", "homography", "apap", "3d")
# An unknown focal of a pair with a baseline: ``calibrated`` from the matches (essential
# matrix + refinement), or held at the ``prior`` (1.2 x the longest side). Two views with
# little parallax leave the focal weakly determined, and a wrong self-calibration bends the
# extension; which rule predicts the picture better is for the held-back band to say.
FOCAL_RULES = ("calibrated", "prior")
# Which matcher finds a pair's correspondences (issue 40): ``sift`` (ASIFT where SIFT finds too
# few epipolar inliers), ``xfeat`` (XFeat + LighterGlue, about a second a pair), ``aliked``
# (ALIKED + LightGlue at 1024 px, about six: :mod:`pis3r.learned_features`) or ``auto``: SIFT,
# and where too few of its matches agree, SIFT's, ASIFT's and XFeat's pooled
# (:func:`pis3r.reconstruct.matching.consistent_matches`), then judged against ALIKED's by the
# pose each gives (:func:`pis3r.reconstruct.hypotheses.judged_matches`). ALIKED is not pooled: added
# to the pool of the three ScanNet pairs that need it, it moved their poses 4.4 / 3.3 / 14.3 deg
# to 53.7 / 2.3 / 9.1 deg, and alone it swaps which pairs it gets right (0737 1.2 deg, 0726 90
# deg); judged, each pair keeps the pose that explains more of both sets' matches.
MATCHERS = ("auto", "sift", "xfeat", "aliked")
DEFAULT_MATCHER = "auto"
# Which features made a pair's matches: ``auto``, the matcher's rule; ``SIFT``, ``ASIFT``,
# ``XFeat`` or ``ALIKED`` alone, or the first three ``pooled``. The held-back band test uses the detector the whole
# photos used: its small copies find fewer SIFT inliers and would otherwise test a pair matched
# differently from the stitch.
FEATURE_DETECTORS = ("auto", "SIFT", "ASIFT", "XFeat", "ALIKED", "pooled")


@dataclass(frozen=True)
class ReconstructOptions:
    """Settings every backend receives; each uses the ones that concern it.

    ``focal``: focal length in pixels of the input photos (overrides EXIF and
    self-calibration); ``device``: ``"auto"``, ``"cpu"`` or ``"cuda"`` (resolved by the backends
    that use one: the classical backend does not);
    ``weights``: a weight file for learned backends; ``conf_threshold``: drop points
    whose confidence is below it; ``depth_fill``: how the classical backend fills depth
    where only one view sees the scene (:data:`pis3r.reconstruct.propagate.DEPTH_FILLS`);
    ``model``: one of :data:`RECONSTRUCT_MODELS`; ``focal_rule``: one of :data:`FOCAL_RULES`;
    ``fill_reference``: whether the reference view's depth is filled where the other views do
    not see it (the held-back band test renders only the other views: there it is not);
    ``matcher``: one of :data:`MATCHERS`; ``detector``: one of :data:`FEATURE_DETECTORS`;
    ``turn_deg``: with a learned ``detector``, how far the other photo is turned upright before
    the network matches it (the held-back band test turns its copies as the whole photos were);
    ``turn``: the photos are a turn through one lens, measured where it was taken out
    (:mod:`pis3r.reconstruct.lens`): a pair a rotation explains is that rotation, rendered as one.
    """

    focal: float | None = None
    device: str = "cpu"
    weights: str | os.PathLike | None = None
    conf_threshold: float = DEFAULT_CONF_THRESHOLD
    depth_fill: str = DEFAULT_DEPTH_FILL
    model: str = "auto"
    focal_rule: str = "calibrated"
    fill_reference: bool = True
    matcher: str = DEFAULT_MATCHER
    detector: str = "auto"
    turn_deg: float = 0.0
    turn: bool = False
