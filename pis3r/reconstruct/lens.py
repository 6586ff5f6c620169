"""A lens that bends straight lines: its radial distortion, measured where a turn shows it, and
the photos with it taken out (issue 39).

Every stage of pis3r models a pinhole camera. A phone's lens may push a photo's corners out by
several percent, and where the photos are a hand-held turn, a pinhole pose trades part of the turn
for a sideways step to explain them: around a full turn of 17 phone photos
(``benchmarks/turn_loop.py``) each pair's pose came out 2-7 deg too wide at its EXIF focal, the
loop 82 deg from closing. Two photos with a baseline cannot tell a lens's distortion from the
scene's depth; a turn can. Where a rotation with one radial term (:func:`pis3r.camera.undistorted_pixels`)
explains the matches of two photos whose focal is known (:func:`turn_through_lens`), that term is
the lens's. Where it is large enough to matter, every photo of that lens is resampled as a pinhole
camera would have taken it (:func:`undistorted_photo`) before anything else sees it
(:func:`lens_corrected`): the stitch is then a true pinhole image, and the pairs a rotation explains
are that rotation (``ReconstructOptions.turn``, :func:`turned_pose`).
Around that turn, 16 of the 17 pairs are corrected and come out 0.1-1.7 deg from it (median 0.4),
the loop 7.9 deg from closing (82 before), the one left (its matches fit no rotation with a lens's
term: 4.4 px) 4.9 deg.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from pis3r.camera import intrinsics, undistorted_pixels
from pis3r.features import Matches
from pis3r.io import Photo
from pis3r.reconstruct import geometry
from pis3r.reconstruct.focal import SAME_LENS, RotationFit, fit_rotation, known_focal
from pis3r.reconstruct.matching import ConsistentMatches
from pis3r.reconstruct.options import ReconstructOptions

# A rotation with one radial distortion term explains a pair's matches where its median transfer
# error is at most this (px at 1024 px): the 17 pairs of a hand-held turn through a phone's lens
# 1.0-2.4 px but one (4.4); the Strecha and ScanNet pairs, with baselines, 7 and more. Its term
# counts from LENS_NEGLIGIBLE (about the share a corner moves) up to LENS_RADIAL: that phone's
# lens 0.04-0.08; where a rotation with a larger term fits, the term stands for parallax, not a
# lens (four of the turntable's neighbouring views: 2.0-2.9 px with terms of 0.8-2.1).
LENS_FIT_PX = 3.0
LENS_NEGLIGIBLE = 0.01
LENS_RADIAL = 0.15
# The photos are resampled from this term on (the phone's turn: 0.039-0.082; lpc-plantain, a
# baseline whose far wall a rotation with a term explains to 2.9 px: 0.019), and where the term
# explains the matches LENS_GAIN times better (median transfer error) than a pinhole turning at any
# focal does: a wrong focal is the other way to bend a turn's matches. Which way it bends them
# sets the margin. The common ways a known focal is wrong (a crop, digital zoom recorded as the
# optical focal, a focal in mm read as a 35 mm equivalent) make the photo narrower than the focal
# says, which a turn at that focal shows as a term above 0 (lpc-APAP-garden, EXIF 750 px: +0.11,
# 1.25 x better than a pinhole at 983 px; left as it is). A term below 0 is the lens of a phone or
# a wide zoom pushing the corners out, and nothing common makes a focal too long: a clear gain is
# enough (the phone's turn at its EXIF focal: a pinhole at 0.85-0.94 x it fits 1.17-2.03 x worse,
# 16 of 16 pairs whose turn the term explains; the same phone's Palazzo set 1.19-2.14 on 7 of 10,
# 0.89-1.08 on the others).
LENS_CORRECTED = 0.03
LENS_GAIN = {"in": 1.3, "out": 1.1}
# Rows of a photo whose resampling map is computed at once (memory: a 12 MP photo's map alone is
# 100 MB; its float64 temporaries would be ten times that).
MAP_ROWS = 256


def turn_through_lens(inliers: Matches, K_a: np.ndarray, K_b: np.ndarray, size_a: tuple[int, int]
                      ) -> RotationFit | None:
    """The rotation with one radial term both photos share (:func:`pis3r.reconstruct.focal.fit_rotation`)
    fitted to the epipolar ``inliers`` at ``K_a``, ``K_b`` (``size_a``: the reference's
    ``(width, height)``), where it explains them (``LENS_FIT_PX``) with a term from
    ``LENS_NEGLIGIBLE`` to ``LENS_RADIAL``; else ``None``."""
    if len(inliers) < 8:
        return None
    fit = fit_rotation(inliers, K_a, K_b, refine_focal=False, radial=True)
    return fit if explains(fit, size_a) and LENS_NEGLIGIBLE <= abs(fit.radial) <= LENS_RADIAL else None


def turned_pose(inliers: Matches, K_a: np.ndarray, K_b: np.ndarray, size_a: tuple[int, int]) -> np.ndarray | None:
    """The rotation ``(3, 3)`` at ``K_a``, ``K_b`` that explains the epipolar ``inliers`` of a pair
    of a known turn (``LENS_FIT_PX``, as it explained the lens's turn); ``None`` where none does.
    A turn has no depth to find: an essential matrix or a homography's plane fitted to it trades
    part of the turn for a sideways step. Around the phone's hand-held turn of 17 photos
    (``benchmarks/turn_loop.py``), their lens taken out, the exported essential matrices and planes
    were up to 4.2 deg from the turn the loop closes on, where the rotation is within 1.7 deg on
    every pair; a baseline fitted under that rotation points along the optical axis (it explains
    what the lens left, not a step) and puts half the points behind the camera."""
    fit = fit_rotation(inliers, K_a, K_b, refine_focal=False)
    return fit.R if explains(fit, size_a) else None


def explains(fit: RotationFit, size_a: tuple[int, int]) -> bool:
    """Whether the rotation ``fit`` explains its matches as a turn does: median transfer error at
    most ``LENS_FIT_PX`` at 1024 px (``size_a``: the reference's ``(width, height)``)."""
    return bool(np.median(fit.residuals) <= LENS_FIT_PX * geometry.pixel_scale(*size_a))


def pinhole_zoom(radial: float) -> float:
    """How much longer the focal of the pinhole photo is than the lens's: a lens that pushes the
    corners out (``radial`` below 0) saw less than its frame; zoomed by ``1 / (1 + radial)``, every
    pixel of the pinhole photo is one the lens saw (the corners last). 1 otherwise."""
    return 1.0 / (1.0 + radial) if radial < 0 else 1.0


def undistorted_photo(photo: Photo, radial: float, focal: float) -> Photo:
    """``photo`` (taken at ``focal`` px through a lens with the ``radial`` term) as a pinhole camera
    at ``focal * pinhole_zoom(radial)`` sees the same view, same size, principal point at the
    centre, its EXIF focal (if any) zoomed alike."""
    zoom = pinhole_zoom(radial)
    height, width = photo.height, photo.width
    K = intrinsics(focal, width, height)
    centre = K[:2, 2]
    # The lens moves a pixel along its ray from the centre only: one table of where it put each
    # distance of the pinhole photo (monotone for any term LENS_RADIAL allows) serves every pixel,
    # measured along one ray with the lens's own model (pis3r.camera.undistorted_pixels).
    seen = np.linspace(0.0, 1.5 * np.sqrt(float(centre @ centre)), 4096)
    along_x = np.column_stack([centre[0] + seen, np.full_like(seen, centre[1])])
    pinhole = (undistorted_pixels(along_x, radial, K)[:, 0] - centre[0]) * zoom
    maps = np.empty((height, width, 2), np.float32)
    offset_x = np.arange(width, dtype=np.float32) - np.float32(centre[0])
    for top in range(0, height, MAP_ROWS):
        offset_y = np.arange(top, min(top + MAP_ROWS, height), dtype=np.float32)[:, None] - np.float32(centre[1])
        distance = np.hypot(offset_x[None, :], offset_y)
        # Near the centre the lens's scale is 1 / zoom (the table's first step is no ratio).
        scale = np.where(distance > 1.0, np.interp(distance, pinhole, seen) / np.maximum(distance, 1.0), 1.0 / zoom)
        maps[top:top + len(offset_y), :, 0] = centre[0] + offset_x[None, :] * scale
        maps[top:top + len(offset_y), :, 1] = centre[1] + offset_y * scale
    pixels = cv2.remap(photo.pixels, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return replace(photo, pixels=pixels, focal_px=photo.focal_px * zoom if photo.focal_px else None)


@dataclass(frozen=True)
class LensCorrection:
    """The lens's ``radial`` term the photos were corrected for, measured on the first pair, and
    the ``zoom`` of their focal (:func:`pinhole_zoom`)."""

    radial: float
    zoom: float

    def to_dict(self) -> dict:
        return {"radial": round(self.radial, 4), "focal_zoom": round(self.zoom, 4),
                "model": "pinhole pixel = c + (x - c) (1 + radial |x - c|^2 / |c|^2), c the centre"}


def one_lens_focal(photos: list[Photo], options: ReconstructOptions) -> float | None:
    """The reference's known focal (:func:`pis3r.reconstruct.focal.known_focal`) where every photo
    is known to come through its lens: one size, and the focal given, or EXIF focals that agree
    (``SAME_LENS``); else ``None``."""
    ref = photos[0]
    focal, _ = known_focal(ref, options.focal)
    if focal is None or any((photo.width, photo.height) != (ref.width, ref.height) for photo in photos):
        return None
    if not options.focal and any(not photo.focal_px or abs(photo.focal_px / ref.focal_px - 1) > SAME_LENS
                                 for photo in photos):
        return None
    return focal


def lens_corrected(photos: list[Photo], options: ReconstructOptions, first_inliers: Matches
                   ) -> tuple[list[Photo], ReconstructOptions, LensCorrection] | None:
    """``photos`` (the reference first) with their lens's distortion taken out, the options at
    their zoomed focal, and the correction; ``None`` where the photos keep theirs: their lens is
    not known to be one (sizes or EXIF focals per pixel differ, or no focal is known), or the
    first pair's epipolar ``first_inliers`` show no turn through a lens that matters
    (``LENS_CORRECTED``), or one that a pinhole at another focal explains about as well
    (``LENS_GAIN``, by whether the lens would push the corners out or in)."""
    ref, focal = photos[0], one_lens_focal(photos, options)
    if focal is None:
        return None
    K = intrinsics(focal, ref.width, ref.height)
    fit = turn_through_lens(first_inliers, K, K, (ref.width, ref.height))
    if fit is None or abs(fit.radial) < LENS_CORRECTED:
        return None
    pinhole = fit_rotation(first_inliers, K, K, refine_focal=True)
    if np.median(pinhole.residuals) < LENS_GAIN["out" if fit.radial < 0 else "in"] * np.median(fit.residuals):
        return None
    correction = LensCorrection(fit.radial, pinhole_zoom(fit.radial))
    corrected = [undistorted_photo(photo, fit.radial, focal) for photo in photos]
    zoomed = options.focal * correction.zoom if options.focal else None
    return corrected, replace(options, focal=zoomed, turn=True), correction


def pinhole_photos(photos: list[Photo], options: ReconstructOptions,
                   matched_with: Callable[[Photo, Photo], ConsistentMatches]
                   ) -> tuple[list[Photo], ReconstructOptions, LensCorrection | None]:
    """``photos`` (the reference first) and ``options`` as the classical backend should see them:
    corrected for their lens where :func:`lens_corrected` finds a turn through one on the first
    pair's consistent matches (``matched_with``: the backend's,
    :meth:`pis3r.reconstruct.classical.ClassicalReconstructor.matched_with`, asked only where one
    lens is known), with the correction; else as they are and ``None``."""
    if one_lens_focal(photos, options) is None:
        return photos, options, None
    first = matched_with(*photos[:2])
    return lens_corrected(photos, options, first.matches.subset(first.inliers)) or (photos, options, None)
