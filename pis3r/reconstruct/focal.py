"""Focal length of two views: hypotheses, the prior, a rotation's focal (Brown–Lowe), the
interval of focals the matches cannot tell apart, and how to say that a focal is doubtful.

Pixel coordinates follow the OpenCV convention; ``K`` is ``(3, 3)`` with the principal point
at the image centre (:func:`pis3r.camera.intrinsics`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from pis3r.camera import focal_scaled, intrinsics, pixel_rays, undistorted_pixels
from pis3r.features import Matches
from pis3r.io import Photo
from pis3r.reconstruct.geometry import pixel_scale
from pis3r.reconstruct.robust_lsq import robust_least_squares

# Prior focal when neither the user, EXIF nor the two views give one: 1.2 x the longest
# side (about 45 deg horizontal field of view), COLMAP's prior.
FALLBACK_FOCAL_FACTOR = 1.2
# Two photos whose EXIF focals per pixel of their longest side agree this closely came through
# one lens at one zoom.
SAME_LENS = 0.01
# Focal / longest side of ordinary lenses (about 19 to 90 deg across the longest side):
# a self-calibrated focal outside is reported, since the cameras then are likely wrong.
PLAUSIBLE_FOCAL = (0.5, 3.0)
# The focal's interval: the focals whose fit (pose re-fitted at each) costs at most
# FOCAL_BOUND more than the fitted focal's (robust Cauchy cost at 1 px per 1024 px: about
# what a dozen matches 1 px off their lines cost), probed outward in steps of PROFILE_STEP
# up to LENS_REACH times the longest side, where it ends when the matches do not bound it.
# Matches are not noise alone (a turntable's pair costs 8 more at its true focal than at a
# third of it): a bound they draw must be clear. The weaker FOCAL_EVIDENCE (about three
# matches 1 px off) is what the fitted focal must win by at PROFILE_STEP either way for the
# matches to be said to prefer it.
FOCAL_BOUND = 10.0
FOCAL_EVIDENCE = 2.5
PROFILE_STEP = 1.25
LENS_REACH = (0.3, 6.0)
# A focal counts as determined by the photos when its interval lies within this factor of it
# either way; wider, every estimator's value comes with a warning.
DETERMINED_FACTOR = 1.25
# The source of a focal the user gave (``--focal``).
FLAG_SOURCE = "flag"
# How the warning of a focal the photos leave loose begins (more views may fix it).
UNDETERMINED_FOCAL = "these photos do not determine the focal length"


@dataclass(frozen=True)
class FocalInterval:
    """The reference focals (px) ``low`` to ``high`` that the evidence cannot tell apart;
    ``rotation_spread_deg``: how far the relative rotation moves across them (the pose's
    dependence on the focal: 0 where the focal is exact or does not move it); ``preferred``:
    whether the matches prefer the fitted focal to ``PROFILE_STEP`` times it either way by
    ``FOCAL_EVIDENCE`` (a minimum, however shallow)."""

    low: float
    high: float
    rotation_spread_deg: float = 0.0
    preferred: bool = True

    @staticmethod
    def exact(focal: float) -> "FocalInterval":
        return FocalInterval(focal, focal)

    @staticmethod
    def of_lenses(width: int, height: int) -> "FocalInterval":
        """What nothing but the lens range says: ``LENS_REACH`` times the longest side."""
        side = max(width, height)
        return FocalInterval(LENS_REACH[0] * side, LENS_REACH[1] * side, preferred=False)

    def determined(self, focal: float) -> bool:
        """Whether the interval lies within ``DETERMINED_FACTOR`` of ``focal`` both ways."""
        slack = 1 + 1e-9
        return self.low * DETERMINED_FACTOR * slack >= focal and self.high <= focal * DETERMINED_FACTOR * slack

    def scaled(self, factor: float) -> "FocalInterval":
        """The same interval for focals ``factor`` times these (another view of the pair)."""
        return replace(self, low=self.low * factor, high=self.high * factor)

    def within(self, other: "FocalInterval", focal: float) -> "FocalInterval":
        """This interval cut to ``other`` (the lens range, say), still holding ``focal``."""
        return replace(self, low=float(min(max(self.low, other.low), focal)),
                       high=float(max(min(self.high, other.high), focal)))

    def spanning(self, focal: float) -> "FocalInterval":
        """The interval widened to hold ``focal`` too."""
        return replace(self, low=min(self.low, focal), high=max(self.high, focal))

    def to_dict(self) -> dict:
        return {"interval_px": [round(self.low, 1), round(self.high, 1)],
                "rotation_spread_deg": round(self.rotation_spread_deg, 3)}


def focal_interval(focal: float, side: int, cost_along: Callable[[int], Callable[[float], tuple[float, float]]]
                   ) -> FocalInterval:
    """The :class:`FocalInterval` around a fitted reference ``focal`` (px) of a photo whose
    longest side is ``side``. ``cost_along(direction)`` (``+1`` longer, ``-1`` shorter) gives a
    function of a factor that returns the fit's rise of cost over the fitted focal's at
    ``focal * factor`` and the rotation's change (degrees) there; it is called with powers of
    ``PROFILE_STEP`` in turn (each fit may start from the one before), until the rise reaches
    ``FOCAL_BOUND`` or the factor leaves ``LENS_REACH``. Each end is where the rise crosses it
    (log-linear between probes), or the reach's end where it never does."""
    ends, spreads, preferred = [], [], True
    for direction in (-1, 1):
        rise_at = cost_along(direction)
        reach = max(0.0, direction * math.log(LENS_REACH[0 if direction < 0 else 1] * side / focal))
        preferred &= reach > 0.0
        step, end, spread = math.log(PROFILE_STEP), reach, 0.0
        previous, previous_rise, distance = 0.0, 0.0, step
        while previous < reach:
            distance = min(distance, reach)
            rise, turned = rise_at(math.exp(direction * distance))
            if previous == 0.0:
                preferred &= rise >= FOCAL_EVIDENCE
            if rise >= FOCAL_BOUND:
                end = previous + (FOCAL_BOUND - previous_rise) / (rise - previous_rise) * (distance - previous)
                spread = max(spread, turned * end / distance)
                break
            previous, previous_rise, spread = distance, max(rise, 0.0), max(spread, turned)
            distance += step
        ends.append(max(end, 0.0))
        spreads.append(spread)
    return FocalInterval(focal * math.exp(-ends[0]), focal * math.exp(ends[1]), max(spreads), preferred)


def focal_warning(focal: float, source: str, interval: FocalInterval, why: str = "") -> str:
    """The one line for a focal its ``interval`` leaves loose, whichever estimator gave it:
    the range, what the pose may move, and what would fix it."""
    spread = (f"; the exported rotation moves by up to {interval.rotation_spread_deg:.1f} deg across it"
              if interval.rotation_spread_deg >= 0.1 else "")
    return (f"{UNDETERMINED_FOCAL}{f' ({why})' if why else ''}: {focal:.0f} px ({source}), but anything from "
            f"{interval.low:.0f} to {interval.high:.0f} px fits them{spread}; the exported cameras depend on it: "
            "pass --focal, use photos with an EXIF focal, or add a third photo")


@dataclass(frozen=True)
class FocalHypothesis:
    """How the two views' focals relate: ``focal_b = ratio * focal_a``. ``focal_a``: known
    (flag, EXIF) or ``None`` (to be estimated, ``prior_a`` its prior); ``name`` says which
    relation it is, for the report."""

    ratio: float
    focal_a: float | None
    prior_a: float
    name: str

    def intrinsics(self, focal_a: float, size_a: tuple[int, int], size_b: tuple[int, int]):
        """``(K_a, K_b)`` for the reference focal ``focal_a``."""
        return intrinsics(focal_a, *size_a), intrinsics(self.ratio * focal_a, *size_b)


def known_focal(photo: Photo, flag: float | None) -> tuple[float | None, str]:
    """``(focal, source)`` of ``photo`` before any matching: ``--focal``'s (``flag``), else its
    EXIF's, else ``(None, "")``."""
    if flag:
        return float(flag), FLAG_SOURCE
    if photo.focal_px:
        return float(photo.focal_px), f"EXIF ({photo.focal_evidence})"
    return None, ""


def partner_focal(photo: Photo, ref: Photo, ref_focal: float | None, flag: float | None) -> float | None:
    """The known focal of ``photo`` paired with ``ref``, whose focal is ``ref_focal``: its own
    (:func:`known_focal`), unless its EXIF shows the lens of ``ref``'s EXIF and ``ref_focal`` is
    not that EXIF's (a first pair's rotation replaced it): then ``ref_focal``, per pixel of the
    longest side. One camera's photos keep one focal: around a turn of 17 photos whose
    reference's EXIF focal (2992 px) its first pair replaced by 2641, the others kept 2992 and
    the chained rotations missed the closing photo by 73 deg (35 with one focal)."""
    focal, _ = known_focal(photo, flag)
    if flag or focal is None or not ref_focal or not ref.focal_px:
        return focal
    per_pixel, ref_per_pixel = focal / max(photo.width, photo.height), ref.focal_px / max(ref.width, ref.height)
    if abs(per_pixel / ref_per_pixel - 1) > SAME_LENS:
        return focal
    return focal * ref_focal / ref.focal_px


def focal_hypotheses(size_a: tuple[int, int], size_b: tuple[int, int], focal_a: float | None,
                     focal_b: float | None) -> list[FocalHypothesis]:
    """The focal relations worth testing for photos of sizes ``(width, height)`` with known
    focals (or ``None``).

    Both known: that. Otherwise the photos are assumed to come from one camera: same size,
    same focal; different sizes are either a crop (same focal in pixels) or a resized copy
    (same field of view), and both are tried — the pair's geometry decides. The prior of a
    crop refers to the larger photo (the uncropped frame is at least that large)."""
    side_a, side_b = max(size_a), max(size_b)
    prior = FALLBACK_FOCAL_FACTOR * side_a
    if focal_a is not None and focal_b is not None:
        return [FocalHypothesis(focal_b / focal_a, focal_a, prior, "known")]
    relations = [(1.0, "same focal", FALLBACK_FOCAL_FACTOR * max(side_a, side_b))]
    if size_a != size_b:
        relations[0] = (1.0, "same focal in pixels (a crop)", relations[0][2])
        relations.append((side_b / side_a, "same field of view (a resized copy)", prior))
    if focal_b is not None:  # the reference's focal follows from the other's
        return [FocalHypothesis(ratio, focal_b / ratio, p, name) for ratio, name, p in relations]
    return [FocalHypothesis(ratio, focal_a, p, name) for ratio, name, p in relations]


def focals_from_homography(H: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]):
    """``(focal_a, focal_b)`` (pixels, each ``None`` when undetermined) of a camera rotating
    about its centre, from the homography ``H`` ``(3, 3)`` a -> b between pixels of images of
    sizes ``(width, height)``.

    Brown & Lowe's closed form (Shum & Szeliski 2000), as OpenCV's
    ``cv2.detail.focalsFromHomography`` (whose Python binding returns nothing): ``K_b^-1 H K_a``
    is a rotation, so the rows of ``H`` (centred pixels) give ``focal_a`` and its columns
    ``focal_b``, each from two orthogonality / equal-norm conditions, the better conditioned kept."""
    centre_a = np.array([[1, 0, (size_a[0] - 1) / 2], [0, 1, (size_a[1] - 1) / 2], [0, 0, 1.0]])
    centre_b = np.array([[1, 0, (size_b[0] - 1) / 2], [0, 1, (size_b[1] - 1) / 2], [0, 0, 1.0]])
    h = (np.linalg.inv(centre_b) @ H @ centre_a).ravel()

    def root(numerator_1, denominator_1, numerator_2, denominator_2):
        with np.errstate(divide="ignore", invalid="ignore"):
            v1, v2 = numerator_1 / denominator_1, numerator_2 / denominator_2
        if v1 < v2:
            v1, v2 = v2, v1
        if v1 > 0 and v2 > 0:
            return float(np.sqrt(v1 if abs(denominator_1) > abs(denominator_2) else v2))
        return float(np.sqrt(v1)) if v1 > 0 else None

    focal_a = root(-h[2] * h[5], h[0] * h[3] + h[1] * h[4],
                   h[5] ** 2 - h[2] ** 2, h[0] ** 2 + h[1] ** 2 - h[3] ** 2 - h[4] ** 2)
    focal_b = root(-(h[0] * h[1] + h[3] * h[4]), h[6] * h[7],
                   h[0] ** 2 + h[3] ** 2 - h[1] ** 2 - h[4] ** 2, (h[7] - h[6]) * (h[7] + h[6]))
    return focal_a, focal_b


def rotation_focal(H: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int], ratio: float) -> float | None:
    """The reference's focal of a rotation homography when ``focal_b = ratio * focal_a``:
    the geometric mean of what rows and columns of ``H`` say (:func:`focals_from_homography`)."""
    focal_a, focal_b = focals_from_homography(H, size_a, size_b)
    estimates = [f for f in (focal_a, None if focal_b is None else focal_b / ratio) if f is not None]
    return float(np.exp(np.mean(np.log(estimates)))) if estimates else None


@dataclass(frozen=True)
class RotationFit:
    """A pure rotation ``x_b ~ K_b R K_a^-1 x_a`` fitted to matches: ``R`` ``(3, 3)``,
    ``K_a``, ``K_b``, and ``residuals`` ``(N,)``, the transfer error a -> b in pixels of b;
    ``radial``: the lens's radial distortion term where it was fitted too
    (:func:`pis3r.camera.undistorted_pixels`; 0 otherwise)."""

    R: np.ndarray
    K_a: np.ndarray
    K_b: np.ndarray
    residuals: np.ndarray
    radial: float = 0.0


def aligned_rotation(matches: Matches, K_a: np.ndarray, K_b: np.ndarray) -> np.ndarray:
    """``(3, 3)`` the rotation that best aligns the unit rays of ``pts_a`` (through ``K_a``) with
    those of ``pts_b`` (through ``K_b``): Kabsch, no weights, every match counted."""
    rays_a, rays_b = pixel_rays(matches.pts_a, K_a), pixel_rays(matches.pts_b, K_b)
    u_a = rays_a / np.linalg.norm(rays_a, axis=1, keepdims=True)
    u_b = rays_b / np.linalg.norm(rays_b, axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(u_b.T @ u_a)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def fit_rotation(matches: Matches, K_a: np.ndarray, K_b: np.ndarray, refine_focal: bool,
                 radial: bool = False) -> RotationFit:
    """Robust least squares (soft L1, 1 px at 1024 px) of the rotation taking rays of a to
    rays of b, starting from the rays' :func:`aligned_rotation`; with
    ``refine_focal`` both focals scale together (their ratio is kept); with ``radial``, one
    radial distortion term both photos share is fitted too (one lens), the transfer error then
    measured between the undistorted pixels."""
    R0 = aligned_rotation(matches, K_a, K_b)
    scale = pixel_scale(*K_b[:2, 2] * 2)

    def unpack(p):
        factor = np.exp(p[3]) if refine_focal else 1.0
        R = cv2.Rodrigues(np.asarray(p[:3], np.float64))[0] @ R0
        return R, focal_scaled(K_a, factor), focal_scaled(K_b, factor)

    # Homogeneous once: the solver evaluates the residuals dozens of times, each parameter moved.
    pixels_a = np.hstack([matches.pts_a, np.ones((len(matches), 1))])

    def transfer(p):
        R, Ka, Kb = unpack(p)
        source, target = pixels_a, matches.pts_b
        if radial:
            source = np.hstack([undistorted_pixels(matches.pts_a, p[-1], K_a), pixels_a[:, 2:]])
            target = undistorted_pixels(target, p[-1], K_b)
        projected = source @ (Kb @ R @ np.linalg.inv(Ka)).T
        with np.errstate(divide="ignore", invalid="ignore"):
            return projected[:, :2] / projected[:, 2:] - target

    def residuals(p):
        return np.nan_to_num(transfer(p), nan=1e6, posinf=1e6, neginf=-1e6).ravel()

    p, _ = robust_least_squares(residuals, np.zeros(3 + refine_focal + radial), loss="soft_l1", scale=scale,
                                max_evaluations=100)
    R, Ka, Kb = unpack(p)
    return RotationFit(R, Ka, Kb, np.linalg.norm(np.nan_to_num(transfer(p), nan=1e6), axis=1),
                       float(p[-1]) if radial else 0.0)


def plausible_focal(focal: float, width: int, height: int) -> bool:
    """Whether ``focal`` (px) of a photo of that size is ``PLAUSIBLE_FOCAL`` times its longest side."""
    return PLAUSIBLE_FOCAL[0] <= focal / max(width, height) <= PLAUSIBLE_FOCAL[1]


def plausibility_warning(focal: float, width: int, height: int, source: str) -> str | None:
    """One line when a ``focal`` (px) the photos gave (``source``: how, whose words before any
    parenthesis the line names) of a photo of that size lies outside ``PLAUSIBLE_FOCAL`` times
    its longest side; ``None`` otherwise. The line says how the focal was found, not that it was
    measured: a loose fit outside ordinary lenses is no self-calibration."""
    if plausible_focal(focal, width, height):
        return None
    factor = focal / max(width, height)
    low, high = PLAUSIBLE_FOCAL
    return (f"the focal length {focal:.0f} px ({source.split(' (')[0]}) is {factor:.2f} x the longest side "
            f"(ordinary lenses: {low}-{high} x): the cameras are likely wrong; pass --focal if you know it")
