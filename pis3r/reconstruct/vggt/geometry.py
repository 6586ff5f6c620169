"""Camera geometry on VGGT outputs: SE(3) inverse, depth unprojection, re-anchoring (spec §12)."""

from __future__ import annotations

import torch


def closed_form_inverse_se3(extrinsics: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms ``(..., 3, 4)`` ``[R | t]`` -> ``(..., 3, 4)`` ``[Rᵀ | -Rᵀ t]``."""
    R_t = extrinsics[..., :3, :3].transpose(-1, -2)
    return torch.cat([R_t, -R_t @ extrinsics[..., :3, 3:]], dim=-1)


def unproject_depth_map_to_point_map(
    depth: torch.Tensor, extrinsics: torch.Tensor, intrinsics: torch.Tensor
) -> torch.Tensor:
    """World points ``(S, H, W, 3)`` of z-depth maps ``(S, H, W)`` (or ``(S, H, W, 1)``).

    Pixel ``(u, v)`` at integer coordinates ``u = 0..W-1``, ``v = 0..H-1`` becomes
    ``X_cam = ((u - cx) d / fx, (v - cy) d / fy, d)`` and ``X_world = Rᵀ (X_cam - t)``,
    with ``extrinsics (S, 3, 4)`` camera-from-world and ``intrinsics (S, 3, 3)``.
    """
    if depth.dim() == 4:
        depth = depth[..., 0]
    S, H, W = depth.shape
    v, u = torch.meshgrid(
        torch.arange(H, dtype=depth.dtype, device=depth.device),
        torch.arange(W, dtype=depth.dtype, device=depth.device),
        indexing="ij",
    )
    fx, fy = intrinsics[:, 0, 0, None, None], intrinsics[:, 1, 1, None, None]
    cx, cy = intrinsics[:, 0, 2, None, None], intrinsics[:, 1, 2, None, None]
    cam = torch.stack([(u - cx) * depth / fx, (v - cy) * depth / fy, depth], dim=-1)  # (S, H, W, 3)
    cam_to_world = closed_form_inverse_se3(extrinsics)  # (S, 3, 4)
    rotated = torch.einsum("sij,shwj->shwi", cam_to_world[:, :, :3], cam)
    return rotated + cam_to_world[:, None, None, :, 3]


def relative_to_first(extrinsics: torch.Tensor) -> torch.Tensor:
    """Re-express camera-from-world poses ``(S, 3, 4)`` in the first camera's frame.

    With the first pose ``[R0 | t0]`` the new world is ``X' = R0 X + t0``, so camera ``i``
    becomes ``[Ri R0ᵀ | ti - Ri R0ᵀ t0]``; the first one is set to exactly ``[I | 0]``.
    Depths are unchanged (each stays in its own camera frame).
    """
    R0, t0 = extrinsics[0, :, :3], extrinsics[0, :, 3]
    R = extrinsics[:, :, :3] @ R0.T
    t = extrinsics[:, :, 3] - (R @ t0[:, None])[..., 0]
    out = torch.cat([R, t[..., None]], dim=-1)
    out[0] = torch.eye(3, 4, dtype=out.dtype, device=out.device)
    return out
