"""Output activations of the heads (spec §5, §6)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def inverse_log_transform(y: torch.Tensor) -> torch.Tensor:
    """``sign(y) * (exp(|y|) - 1)``, computed with ``expm1`` as the official code does."""
    return torch.sign(y) * torch.expm1(torch.abs(y))


def activate_pose(pose_enc: torch.Tensor) -> torch.Tensor:
    """``absT_quaR_FoV`` activation of a raw encoding ``(..., 9)``.

    Translation (0-2) and quaternion (3-6) are linear; the two fields of view (7-8)
    go through ReLU.
    """
    return torch.cat([pose_enc[..., :3], pose_enc[..., 3:7], F.relu(pose_enc[..., 7:])], dim=-1)


def activate_dense(out: torch.Tensor, activation: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a DPT output ``(N, C, H, W)`` into values ``(N, H, W, C-1)`` and confidence ``(N, H, W)``.

    The last channel is the confidence, activated ``1 + exp(c)`` (always > 1). Values:
    ``"exp"`` (depth) or ``"inv_log"`` (points).
    """
    fmap = out.permute(0, 2, 3, 1)
    values, conf = fmap[..., :-1], fmap[..., -1]
    if activation == "exp":
        values = torch.exp(values)
    elif activation == "inv_log":
        values = inverse_log_transform(values)
    else:
        raise ValueError(f"unknown dense activation {activation!r}")
    return values, 1 + conf.exp()
