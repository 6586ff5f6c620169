"""Transformer parts shared by the DINOv2 encoder, the aggregator and the camera head.

Parameter names follow the released checkpoint: ``norm1``, ``attn.qkv``,
``attn.q_norm``/``attn.k_norm``, ``attn.proj``, ``ls1.gamma``, ``norm2``,
``mlp.fc1``/``mlp.fc2``, ``ls2.gamma``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pis3r.reconstruct.vggt.rope import apply_rope


class LayerScale(nn.Module):
    """Per-channel scale ``x * gamma``; ``gamma (dim,)``."""

    def __init__(self, dim: int, init_value: float = 1e-5) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init_value)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Mlp(nn.Module):
    """``fc2(GELU(fc1(x)))`` with the exact (erf) GELU."""

    def __init__(self, in_features: int, hidden_features: int, out_features: int | None = None) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_features, out_features or in_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Attention(nn.Module):
    """Multi-head self-attention with a fused ``qkv`` projection.

    ``qkv`` output channels are ordered ``(3, heads, head_dim)``: all of q, then k,
    then v. Optional qk-norm (LayerNorm over the head dim, eps 1e-5, with affine) is
    applied per head before RoPE; attention itself is
    ``scaled_dot_product_attention`` with its default ``1/sqrt(head_dim)`` scale.
    """

    def __init__(self, dim: int, num_heads: int, qk_norm: bool = False) -> None:
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"dim {dim} is not divisible by {num_heads} heads")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.q_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, rope_angles: torch.Tensor | None = None) -> torch.Tensor:
        """``x (B, N, C)`` -> ``(B, N, C)``; ``rope_angles (N, head_dim)`` or ``None``."""
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)  # each (B, heads, N, head_dim)
        q, k = self.q_norm(q), self.k_norm(k)
        if rope_angles is not None:
            q = apply_rope(q, rope_angles)
            k = apply_rope(k, rope_angles)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, N, C))


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale on both residual branches.

    ``x = x + ls1(attn(norm1(x)))``; ``x = x + ls2(mlp(norm2(x)))``.
    ``norm_eps`` is 1e-6 in DINOv2 and 1e-5 elsewhere (a real difference, see spec §2.3).
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        mlp_ratio: float = 4.0,
        qk_norm: bool = False,
        norm_eps: float = 1e-5,
        init_value: float = 1e-5,
    ) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qk_norm=qk_norm)
        self.ls1 = LayerScale(dim, init_value)
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, init_value)

    def forward(self, x: torch.Tensor, rope_angles: torch.Tensor | None = None) -> torch.Tensor:
        """``x (B, N, C)`` -> ``(B, N, C)``."""
        x = x + self.ls1(self.attn(self.norm1(x), rope_angles))
        return x + self.ls2(self.mlp(self.norm2(x)))
