"""The ``absT_quaR_FoV`` pose encoding and camera matrices (spec §5.1).

Encoding ``(..., 9)``: translation ``t`` of the camera-from-world transform (0-2), a
rotation quaternion in XYZW order, scalar last, not necessarily unit (3-6), vertical
and horizontal fields of view in radians (7, 8). Matrices follow OpenCV:
``X_cam = R X_world + t``; the principal point is VGGT's ``(W/2, H/2)``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def quat_to_mat(quaternions: torch.Tensor) -> torch.Tensor:
    """XYZW quaternions ``(..., 4)`` -> rotation matrices ``(..., 3, 3)``.

    Uses ``s = 2 / |q|²``, so a non-unit quaternion is normalised implicitly.
    """
    x, y, z, w = torch.unbind(quaternions, -1)
    s = 2.0 / (quaternions * quaternions).sum(-1)
    m = torch.stack(
        (
            1 - s * (y * y + z * z),
            s * (x * y - z * w),
            s * (x * z + y * w),
            s * (x * y + z * w),
            1 - s * (x * x + z * z),
            s * (y * z - x * w),
            s * (x * z - y * w),
            s * (y * z + x * w),
            1 - s * (x * x + y * y),
        ),
        -1,
    )
    return m.reshape(quaternions.shape[:-1] + (3, 3))


def mat_to_quat(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(..., 3, 3)`` -> XYZW quaternions ``(..., 4)`` with ``w >= 0``.

    PyTorch3D's method: of the four candidate quaternions (one per largest diagonal
    combination) the best-conditioned one is picked.
    """
    if matrix.shape[-2:] != (3, 3):
        raise ValueError(f"expected (..., 3, 3) rotation matrices, got {tuple(matrix.shape)}")
    batch = matrix.shape[:-2]
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = torch.unbind(matrix.reshape(batch + (9,)), -1)
    traces = torch.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], -1
    )
    q_abs = torch.where(traces > 0, torch.sqrt(traces.clamp(min=0)), torch.zeros_like(traces))
    # Row i: the quaternion (r, i, j, k) multiplied by 2 * q_abs[i].
    by_rijk = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1),
        ],
        -2,
    )
    candidates = by_rijk / (2.0 * q_abs[..., None].clamp(min=0.1))
    best = F.one_hot(q_abs.argmax(-1), num_classes=4)[..., None].to(candidates.dtype)
    rijk = (candidates * best).sum(-2)
    xyzw = rijk[..., [1, 2, 3, 0]]
    return torch.where(xyzw[..., 3:4] < 0, -xyzw, xyzw)


def pose_encoding_to_extri_intri(
    pose_enc: torch.Tensor, image_size_hw: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, S, 9)`` encodings -> extrinsics ``(B, S, 3, 4)`` ``[R | t]`` and intrinsics ``(B, S, 3, 3)``.

    ``fx = (W/2) / tan(fov_w/2)``, ``fy = (H/2) / tan(fov_h/2)``, principal point
    ``(W/2, H/2)``. A FoV of 0 (the ReLU floor) gives an infinite focal length.
    """
    H, W = image_size_hw
    R = quat_to_mat(pose_enc[..., 3:7])
    extrinsics = torch.cat([R, pose_enc[..., :3, None]], dim=-1)
    fy = (H / 2.0) / torch.tan(pose_enc[..., 7] / 2.0)
    fx = (W / 2.0) / torch.tan(pose_enc[..., 8] / 2.0)
    zeros, ones = torch.zeros_like(fx), torch.ones_like(fx)
    intrinsics = torch.stack(
        [fx, zeros, torch.full_like(fx, W / 2), zeros, fy, torch.full_like(fx, H / 2), zeros, zeros, ones], -1
    ).reshape(fx.shape + (3, 3))
    return extrinsics, intrinsics


def extri_intri_to_pose_encoding(
    extrinsics: torch.Tensor, intrinsics: torch.Tensor, image_size_hw: tuple[int, int]
) -> torch.Tensor:
    """Inverse of :func:`pose_encoding_to_extri_intri`: ``(B, S, 3, 4)``, ``(B, S, 3, 3)`` -> ``(B, S, 9)``.

    ``fov_h = 2·atan((H/2)/fy)``, ``fov_w = 2·atan((W/2)/fx)``; the principal point is not encoded.
    """
    H, W = image_size_hw
    quat = mat_to_quat(extrinsics[..., :3, :3])
    fov_h = 2 * torch.atan((H / 2) / intrinsics[..., 1, 1])
    fov_w = 2 * torch.atan((W / 2) / intrinsics[..., 0, 0])
    return torch.cat([extrinsics[..., :3, 3], quat, fov_h[..., None], fov_w[..., None]], dim=-1)
