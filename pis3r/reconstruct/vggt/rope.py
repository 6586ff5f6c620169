"""2-D rotary position embedding (RoPE) of the aggregator's frame and global blocks.

Every token carries an integer position ``(row, col)``: patch tokens of grid cell
``(r, c)`` get ``(r + 1, c + 1)`` and the special (camera, register) tokens get
``(0, 0)``, whose rotation is the identity. The same table serves every frame,
because positions carry no frame index.

Of a head's ``D`` channels, the first half is rotated by the row and the second
half by the column. Inside a half of ``D/2`` channels the "rotate-half" pairing is
used: channel ``k`` pairs with channel ``k + D/4``, at angle ``p * f_k`` with
``f_k = base^(-2k / (D/2))``.

Everything here is built with device-side torch ops from Python integers, so a
forward pass neither copies from the host nor synchronises (CUDA-graph safe).
"""

from __future__ import annotations

import torch


def token_positions(grid_h: int, grid_w: int, num_special: int, device: torch.device) -> torch.Tensor:
    """Integer ``(row, col)`` positions of one frame's tokens, ``(num_special + grid_h*grid_w, 2)``.

    Special tokens sit at ``(0, 0)``; patches are row-major at ``(r + 1, c + 1)``.
    """
    index = torch.arange(grid_h * grid_w, device=device)
    patches = torch.stack([index // grid_w + 1, index % grid_w + 1], dim=-1)
    special = torch.zeros(num_special, 2, dtype=patches.dtype, device=device)
    return torch.cat([special, patches], dim=0)


def rope_angles(positions: torch.Tensor, head_dim: int, base: float = 100.0) -> torch.Tensor:
    """fp32 rotation angles ``(N, head_dim)`` for positions ``(N, 2)``.

    Layout of the last axis: ``[θ_row, θ_row, θ_col, θ_col]`` with ``head_dim/4``
    frequencies each, i.e. exactly the per-channel angle of the rotate-half rule.
    Angles are fp32 whatever the token dtype (they are cast before ``cos``/``sin``).
    """
    half = head_dim // 2
    exponents = torch.arange(0, half, 2, device=positions.device).float() / half
    inv_freq = 1.0 / (base**exponents)  # (half/2,)
    theta = positions.float()[..., None] * inv_freq  # (N, 2, half/2)
    theta = torch.cat([theta, theta], dim=-1)  # (N, 2, half): [θ, θ] per axis
    return theta.flatten(-2)  # (N, head_dim): row half, then column half


def rotate_halves(x: torch.Tensor) -> torch.Tensor:
    """The rotate-half partner ``[-b, a]`` inside each of the two halves of the last axis.

    ``x (..., D)`` with halves ``[a_row, b_row, a_col, b_col]`` (``D/4`` each) becomes
    ``[-b_row, a_row, -b_col, a_col]``.
    """
    a_row, b_row, a_col, b_col = x.chunk(4, dim=-1)
    return torch.cat([-b_row, a_row, -b_col, a_col], dim=-1)


def apply_rope(x: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Rotate queries or keys ``(B, heads, N, D)`` by per-token ``angles (N, D)`` (fp32).

    The angles are cast to the tokens' dtype before taking ``cos``/``sin``, and the
    result is ``x·cos + rotate_halves(x)·sin``, element for element the official order.
    """
    angles = angles.to(x.dtype)
    return x * angles.cos() + rotate_halves(x) * angles.sin()
