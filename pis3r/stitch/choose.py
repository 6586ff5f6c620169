"""Choosing the model by evidence from the pair itself: the crop protocol turned inward.

Several explanations can fit a pair: one homography (a rotation, or one plane: no focal
needed, exact where it holds), or a 3-D scene whose depth beyond the overlap is filled one
way or another. Thresholds on a parallax level cannot say which one predicts the unseen
part best. The pair can: a band of the reference inside its border (``BAND_FRACTION`` of
each side) is held back, each candidate stitches it from the inner part plus the other
views, at a reduced working size, and is scored against the reference's true pixels there.
The best candidate makes the real stitch; every score goes into ``report.json``. The band's
copies are matched with the features the whole photos are (SIFT, or ASIFT where SIFT finds
too few consistent matches): the band tests the pair as the stitch will see it.

The band score is the mean of two PSNRs (dB): one over the part of the band that any
candidate reaches (what no view sees says nothing about the models), where pixels a
candidate does not cover cost what guessing the band's mean colour would cost — reach is
rewarded only when it is right; and one over the pixels the candidate itself renders —
what the stitched extension will be judged on. Either alone picks badly where a model
covers little but well, or much but poorly.
"""

from __future__ import annotations

import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from pis3r.errors import Pis3rError, one_line
from pis3r.io import Photo, downscaled
from pis3r.reconstruct.classical import MULTI_VIEW_FEATURES, ClassicalReconstructor
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.propagate import DEFAULT_DEPTH_FILL, DEPTH_FILLS
from pis3r.scene import Scene
from pis3r.stitch.holes import fill_holes
from pis3r.stitch.render import render_to_canvas

# Share of the reference's width and height held back on each side.
BAND_FRACTION = 0.15
# The band test runs with every photo's longest side at most this (pixels), on the first
# BAND_VIEWS photos (the reference and the next).
BAND_WORK_SIDE = 480
BAND_VIEWS = 2
# ``auto``: the band chooses between the backend's own explanation (its degeneracy test:
# rotation, plane or 3-D, focal self-calibrated), one homography and APAP's local
# homographies (no focal, no depth): a 3-D model must predict the held-back band better
# than the warps to be used. ``band``: among every candidate (also the 3-D model with each
# depth fill, its focal self-calibrated or held at the prior). The others force one. The
# wider set is opt-in: whether the band tells a self-calibrated focal from the prior is
# close to a coin toss where they differ little on the band, and a wrong pick costs dB
# (see the README).
MODEL_CHOICES = ("auto", "band", "homography", "apap", "3d")
# The candidates that need no depth: one homography, or APAP's local homographies.
WARP_MODELS = ("homography", "apap")
DEFAULT_MODEL = "auto"
# The local homographies must predict the band better than every other candidate by this
# much (dB) to make the stitch: they have hundreds of parameters to a homography's eight,
# and band scores this close are the band's noise, not evidence (on the crop protocol the
# pairs where they then lost were 0.01-0.06 dB ahead on the band, those where they won
# 0.2-1.7 dB).
BAND_HANDICAP_DB = {"apap": 0.1}
# ``auto``: the band test chooses the 3-D model's depth fill too.
DEPTH_FILL_CHOICES = (*DEPTH_FILLS, "auto")
DEFAULT_DEPTH_FILL_CHOICE = DEFAULT_DEPTH_FILL


@dataclass(frozen=True)
class Candidate:
    """One explanation of the photos: ``model`` (``homography``, ``apap``, ``3d``, or ``auto``:
    the backend's test), for ``3d`` its ``depth_fill`` (:data:`pis3r.reconstruct.propagate.DEPTH_FILLS`),
    and how an unknown focal is found (``focal_rule``, :data:`pis3r.reconstruct.options.FOCAL_RULES`;
    ``None``: the backend's default)."""

    model: str
    depth_fill: str | None = None
    focal_rule: str | None = None

    @property
    def label(self) -> str:
        """``homography``, ``3d/<depth fill>``, with ``/<focal rule>`` when one is set."""
        return "/".join(part for part in (self.model, self.depth_fill, self.focal_rule) if part)

    def backend_options(self, base: ReconstructOptions) -> ReconstructOptions:
        return replace(base, model=self.model, depth_fill=self.depth_fill or base.depth_fill,
                       focal_rule=self.focal_rule or base.focal_rule)

    def to_dict(self) -> dict:
        return {"model": self.model, "depth_fill": self.depth_fill, "focal_rule": self.focal_rule}


@dataclass(frozen=True)
class BandScore:
    """How well ``candidate`` predicted the held-back band: ``psnr`` (dB, over the whole
    band), ``coverage`` (share of the band it rendered or inpainted), ``scene_model``: the
    model its scene of the band had (``homography``, ``apap``, ``3d``); ``error``: why it could
    not stitch the band (then ``psnr`` is ``-inf`` and ``scene_model`` empty)."""

    candidate: Candidate
    psnr: float
    coverage: float
    error: str = ""
    scene_model: str = ""

    @property
    def tested(self) -> Candidate:
        """The candidate as the band saw it: the backend's own test (``auto``) may decide
        otherwise on the whole photos than on the band's copies, and what makes the stitch
        must be what predicted the band."""
        candidate = self.candidate
        if candidate.model != "auto":
            return candidate
        if self.scene_model == "homography":
            return Candidate("homography")
        return Candidate("3d", candidate.depth_fill, candidate.focal_rule)

    def to_dict(self) -> dict:
        finite = math.isfinite(self.psnr)
        return {**self.candidate.to_dict(), "band_psnr": round(self.psnr, 3) if finite else None,
                "band_coverage": round(self.coverage, 4), "band_model": self.scene_model or None,
                **({"error": self.error} if self.error else {})}


@dataclass(frozen=True)
class ModelChoice:
    """The candidate that makes the stitch, every band score (empty when nothing was to
    choose: a forced model, or a backend without a choice), the features the band's copies
    were matched with (``detector``; empty without a band test) and, when the chosen
    candidate was reconstructed from the whole photos during the band test, its ``scene``
    (``None``: the stitch reconstructs it)."""

    chosen: Candidate | None
    scores: tuple[BandScore, ...] = ()
    detector: str = ""
    scene: Scene | None = None

    def to_dict(self) -> dict:
        return {
            "chosen": self.chosen.to_dict() if self.chosen else None,
            "band_fraction": BAND_FRACTION,
            "work_side": BAND_WORK_SIDE,
            "detector": self.detector or None,
            "candidates": [score.to_dict() for score in self.scores],
        }


def candidates(model: str, depth_fill: str) -> list[Candidate]:
    """The candidates allowed by the ``--model`` and ``--depth-fill`` choices (a single one:
    forced, no band test). The backend's own explanation comes first: it wins a tie."""
    fills = DEPTH_FILLS if depth_fill == "auto" else (depth_fill,)
    named = depth_fill == "auto"  # a fixed fill is the backend options' already
    warps = [Candidate("homography"), Candidate("apap")]
    if model == "auto":
        return [*(Candidate("auto", fill if named else None) for fill in fills), *warps]
    found = warps if model == "band" else [Candidate(model)] if model in ("homography", "apap") else []
    if model in ("band", "3d"):
        found += [Candidate("3d", fill) for fill in fills]
    if model == "band":
        found += [Candidate("3d", fill, "prior") for fill in fills]
    return found


def choose_model(photos: list[Photo], backend: str, base: ReconstructOptions, model: str = DEFAULT_MODEL,
                 depth_fill: str = DEFAULT_DEPTH_FILL_CHOICE, memo: dict | None = None) -> ModelChoice:
    """Score every allowed candidate on the held-back band of ``photos[0]`` (the reference)
    and return the best. Only the classical backend has a choice (learned backends predict
    one 3-D scene); with one candidate no band test runs. If no candidate can stitch the
    band, ``chosen`` is None: the backend decides. ``memo``: that of the reconstruction of
    ``photos`` that will make the stitch (:class:`ClassicalReconstructor`): the features
    and matches of the first two photos, which say which detector the band uses, are
    computed into it once, and the other photos' features detected into it while the band
    test runs. With ``model`` ``auto`` and a ``memo``, the backend's own explanation in its
    3-D form (what most pairs stitch with) is reconstructed from the whole photos into it on
    a thread meanwhile: ``scene`` when that candidate is chosen. The band test runs mostly on
    one core, and the memo then holds what it would hold had the stitch reconstructed it
    after the test (the thread has ended when this returns; it seeds OpenCV's random state
    itself, on top of the first two photos' matches as the stitch would find them)."""
    allowed = candidates(model, depth_fill) if backend == "classical" else []
    if len(allowed) <= 1:
        return ModelChoice(allowed[0] if allowed else None)
    # The model is chosen once per stitch: on the reference and the next photo, so the test
    # costs the same for two photos or eleven.
    small = [_working_size(photo) for photo in photos[:BAND_VIEWS]]
    inner, margin, band = _hold_back_band(small[0])
    # The photos are detected on both cores; then the band's copies while the photos are
    # matched (mostly on one core).
    band_photos, band_memo = [inner, *small[1:]], {}
    stitching = ClassicalReconstructor(base, memo)
    stitching.features(photos[:BAND_VIEWS])
    with ThreadPoolExecutor(1) as pool:
        copies = pool.submit(ClassicalReconstructor(base, band_memo).features, band_photos)
        found = stitching.matched_with(photos[0], photos[1])
        copies.result()
    if memo is not None and len(photos) > BAND_VIEWS:
        # The other photos' features, which the stitch reads next (as it detects them:
        # ClassicalReconstructor.reconstruct), are found meanwhile on a core the band test
        # leaves idle part of the time.
        stitching.detect_in_background(photos[BAND_VIEWS:], MULTI_VIEW_FEATURES)
    guess = Candidate("3d", allowed[0].depth_fill, allowed[0].focal_rule) if model == "auto" else None
    with ThreadPoolExecutor(1) as speculation:
        whole = speculation.submit(_whole_scene, guess, photos, base, memo) if guess and memo is not None else None
        scores = _band_scores(allowed, band_photos, band_memo, small[0], margin, band,
                              replace(base, detector=found.detector, turn_deg=found.turn_deg))
        scene = whole.result() if whole is not None else None
    best = best_score(scores)
    if not math.isfinite(scores[best].psnr):
        return ModelChoice(None, scores, found.detector)
    chosen = scores[best].tested
    return ModelChoice(chosen, scores, found.detector, scene if chosen == guess else None)


def _whole_scene(candidate: Candidate, photos: list[Photo], base: ReconstructOptions, memo: dict) -> Scene | None:
    """The scene ``candidate`` makes of the whole ``photos`` with the stitch's ``memo``, or
    ``None`` where it cannot (the stitch then says why, if it is chosen)."""
    try:
        return ClassicalReconstructor(candidate.backend_options(base), memo).reconstruct(photos)
    except Pis3rError:
        return None


def _band_scores(allowed: list[Candidate], band_photos: list[Photo], band_memo: dict, ref: Photo,
                 margin: tuple[int, int], band: np.ndarray, base: ReconstructOptions) -> tuple[BandScore, ...]:
    """Every candidate's score on the held-back ``band`` ``(h, w)`` of ``ref`` (the reference at
    the working size), from ``band_photos``: its inner part (at ``margin``) and the other
    photos at the working size, whose features ``band_memo`` holds."""
    # The candidates are reconstructed here one after the other, as their shared memo and
    # OpenCV's random state (both per thread) expect, while another thread renders the bands
    # of those before: rendering is mostly Mesa's and OpenCV's threads, reconstructing mostly
    # this one. The warps' scenes take hundredths of a second, a 3-D scene tenths: built first,
    # their bands render while the 3-D scenes are built. Every estimate starts from one seed
    # and shares the memo (pis3r.reconstruct.pairs.estimate_pair), so the order changes no scene.
    order = sorted(range(len(allowed)), key=lambda k: allowed[k].model not in WARP_MODELS)
    pending: dict[int, Future] = {}
    homography: Future | None = None
    with ThreadPoolExecutor(1) as pool:
        for k in order:
            scene = _band_scene(allowed[k], band_photos, base, band_memo)
            # A scene of the homography model renders the pair's homography whichever candidate
            # asked for it: one render stands for the backend's own choice and the forced one.
            is_homography = isinstance(scene, Scene) and scene.model == "homography"
            if is_homography and homography is not None:
                pending[k] = homography
                continue
            pending[k] = pool.submit(_render_band, scene, band_photos[0], band.shape, margin)
            if is_homography:
                homography = pending[k]
        renders = [pending[k].result() for k in range(len(allowed))]
    reached = band & np.any([covered for _, covered, _, _ in renders], axis=0)
    return tuple(
        BandScore(candidate, -math.inf, 0.0, error) if error else
        BandScore(candidate, band_score(predicted, covered, ref.pixels, reached), float(covered[band].mean()),
                  scene_model=scene_model)
        for candidate, (predicted, covered, error, scene_model) in zip(allowed, renders)
    )


def best_score(scores: tuple[BandScore, ...]) -> int:
    """Index of the candidate that makes the stitch: the best band score once each is
    handicapped by ``BAND_HANDICAP_DB`` for its model (the first of equals)."""
    return max(range(len(scores)), key=lambda k: scores[k].psnr - BAND_HANDICAP_DB.get(scores[k].candidate.model, 0.0))


def _working_size(photo: Photo) -> Photo:
    factor = BAND_WORK_SIDE / max(photo.width, photo.height)
    return downscaled(photo, factor) if factor < 1.0 else photo


def _hold_back_band(ref: Photo) -> tuple[Photo, tuple[int, int], np.ndarray]:
    """The inner part of ``ref`` (a photo of the same camera, principal point still centred),
    its offset ``(x, y)`` in ``ref`` and the band ``(h, w)`` bool outside it."""
    bx, by = round(BAND_FRACTION * ref.width), round(BAND_FRACTION * ref.height)
    inner = Photo(np.ascontiguousarray(ref.pixels[by:ref.height - by, bx:ref.width - bx]), ref.name,
                  ref.focal_px, ref.focal_evidence, ref.scale)
    band = np.ones((ref.height, ref.width), bool)
    band[by:ref.height - by, bx:ref.width - bx] = False
    return inner, (bx, by), band


def _band_scene(candidate: Candidate, photos: list[Photo], base: ReconstructOptions, memo: dict) -> Scene | str:
    """The scene ``candidate`` makes of ``photos`` (the inner part of the reference first), or
    the line saying why it cannot. ``memo`` is shared by the candidates."""
    try:
        # The band is rendered from the other views: the reference's depth is not filled.
        options = replace(candidate.backend_options(base), fill_reference=False)
        return ClassicalReconstructor(options, memo).reconstruct(photos)
    except Pis3rError as exc:
        return one_line(exc)


def _render_band(scene: Scene | str, inner: Photo, shape: tuple[int, int],
                 margin: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, str, str]:
    """What ``scene`` (of ``inner``, the reference's inner part at ``margin``, and the other
    views) predicts on the reference's grid ``shape``: ``(h, w, 3)`` colours, ``(h, w)`` bool
    covered, the error line when ``scene`` is one (nothing covered then), and the scene's
    model (``""`` then)."""
    height, width = shape
    if isinstance(scene, str):
        return np.zeros((height, width, 3), np.float32), np.zeros(shape, bool), scene, ""
    # The canvas must reach the band on every side: it is the inner part grown by the band.
    scale = max(width / inner.width, height / inner.height) + 0.01
    canvas = render_to_canvas(scene, 0, scale)
    filled = fill_holes(canvas.image, canvas.occupied, in_place=True)
    x0, y0 = canvas.ref_offset[0] - margin[0], canvas.ref_offset[1] - margin[1]
    predicted, covered = _window(filled.image, canvas.occupied | filled.hole, x0, y0, width, height)
    return predicted, covered, "", scene.model


def _window(image: np.ndarray, known: np.ndarray, x0: int, y0: int, width: int, height: int):
    """``(height, width)`` window of a canvas at ``(x0, y0)``, unknown where the canvas ends."""
    out = np.zeros((height, width, 3), np.float32)
    inside = np.zeros((height, width), bool)
    sx0, sy0 = max(0, x0), max(0, y0)
    sx1, sy1 = min(image.shape[1], x0 + width), min(image.shape[0], y0 + height)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = image[sy0:sy1, sx0:sx1]
        inside[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = known[sy0:sy1, sx0:sx1]
    return out, inside


def band_score(predicted: np.ndarray, covered: np.ndarray, truth: np.ndarray, reached: np.ndarray) -> float:
    """The band score (module docstring) of ``predicted`` ``(h, w, 3)`` where ``covered``
    ``(h, w)``, on the ``reached`` ``(h, w)`` part of the band; ``-inf`` if it covers none of it."""
    own = reached & covered
    if not own.any():
        return -math.inf
    return 0.5 * (band_psnr(predicted, covered, truth, reached) + band_psnr(predicted, covered, truth, own))


def band_psnr(predicted: np.ndarray, covered: np.ndarray, truth: np.ndarray, band: np.ndarray) -> float:
    """PSNR (dB) of ``predicted`` ``(h, w, 3)`` against ``truth`` over ``band`` ``(h, w)``;
    where ``covered`` is False a pixel costs the band's colour variance (a mean-colour guess)."""
    true_band = truth[band]
    if true_band.size == 0:
        return -math.inf
    guess_cost = float(true_band.var(axis=0).mean())
    errors = ((predicted[band] - true_band) ** 2).mean(axis=1)
    errors = np.where(covered[band], errors, guess_cost)
    mse = max(float(errors.mean()), 1e-10)
    return 10.0 * math.log10(1.0 / mse)
