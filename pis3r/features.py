"""Sparse correspondences: SIFT keypoints, RootSIFT descriptors, mutual ratio-test matching."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

# Detection runs on images resized so their longest side is at most this; the
# keypoints are scaled back to full-resolution pixels.
DETECT_MAX_SIDE = 1280


@dataclass
class Features:
    """``points`` ``(N, 2)`` float64 full-resolution pixels; ``descriptors`` ``(N, 128)`` float32 RootSIFT."""

    points: np.ndarray
    descriptors: np.ndarray


@dataclass
class Matches:
    """Corresponding pixels ``pts_a``, ``pts_b``: ``(N, 2)`` float64 each."""

    pts_a: np.ndarray
    pts_b: np.ndarray

    def __len__(self) -> int:
        return len(self.pts_a)

    def subset(self, keep: np.ndarray) -> "Matches":
        return Matches(self.pts_a[keep], self.pts_b[keep])


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float RGB in [0, 1] to ``(H, W)`` uint8 luminance."""
    return cv2.cvtColor(np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def detect(image: np.ndarray, max_features: int = 8000, max_side: int = DETECT_MAX_SIDE) -> Features:
    """SIFT keypoints with RootSIFT descriptors (L1-normalise, square root) of ``(H, W, 3)`` ``image``."""
    gray = to_gray_u8(image)
    scale = min(1.0, max_side / max(gray.shape))
    if scale < 1.0:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.02)
    keypoints, desc = sift.detectAndCompute(gray, None)
    if desc is None or len(keypoints) == 0:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    desc = desc / (np.abs(desc).sum(axis=1, keepdims=True) + 1e-7)
    desc = np.sqrt(desc).astype(np.float32)
    pts = np.array([kp.pt for kp in keypoints], dtype=np.float64)
    pts = (pts + 0.5) / scale - 0.5
    return Features(pts, desc)


def match(a: Features, b: Features, ratio: float = 0.85) -> Matches:
    """Mutual nearest neighbours that also pass Lowe's ratio test in both directions."""
    if len(a.points) < 2 or len(b.points) < 2:
        return Matches(np.zeros((0, 2)), np.zeros((0, 2)))
    da = torch.from_numpy(a.descriptors)
    db = torch.from_numpy(b.descriptors)
    # RootSIFT vectors have unit L2 norm, so squared distance = 2 - 2 cos.
    dist = (2.0 - 2.0 * da @ db.T).clamp_min(0.0).sqrt()
    best_ab, idx_ab = dist.topk(2, dim=1, largest=False)
    best_ba, idx_ba = dist.topk(2, dim=0, largest=False)
    i = torch.arange(len(da))
    j = idx_ab[:, 0]
    mutual = idx_ba[0, j] == i
    ratio_a = best_ab[:, 0] < ratio * best_ab[:, 1]
    ratio_b = best_ba[0, j] < ratio * best_ba[1, j]
    keep = (mutual & ratio_a & ratio_b).numpy()
    ia, ib = i.numpy()[keep], j.numpy()[keep]
    return Matches(a.points[ia], b.points[ib])


def match_images(image_a: np.ndarray, image_b: np.ndarray) -> Matches:
    """Detect and match in one call."""
    return match(detect(image_a), detect(image_b))
