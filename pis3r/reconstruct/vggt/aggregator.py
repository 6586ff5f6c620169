"""The aggregator: DINOv2 patch tokens + camera/register tokens, then alternating
frame-wise and global attention with 2-D RoPE (spec §2).
"""

from __future__ import annotations

from typing import Iterable

import torch
from torch import nn

from pis3r.reconstruct.vggt.dinov2 import DinoV2
from pis3r.reconstruct.vggt.layers import Block
from pis3r.reconstruct.vggt.rope import rope_angles, token_positions

# ImageNet statistics; the model takes images in [0, 1] and normalises them itself.
RESNET_MEAN = (0.485, 0.456, 0.406)
RESNET_STD = (0.229, 0.224, 0.225)


def frame_slot_tokens(slots: torch.Tensor, batch: int, frames: int) -> torch.Tensor:
    """Per-frame special tokens from a two-slot table.

    ``slots (1, 2, X, C)``: slot 0 goes to the first frame of every scene, slot 1 to
    frames ``1..S-1``. Returns ``(B*S, X, C)``, frame-major inside each scene.
    """
    first = slots[:, :1].expand(batch, 1, *slots.shape[2:])
    others = slots[:, 1:].expand(batch, frames - 1, *slots.shape[2:])
    return torch.cat([first, others], dim=1).reshape(batch * frames, *slots.shape[2:])


class Aggregator(nn.Module):
    """Alternating-attention transformer over all frames of a scene.

    Per frame the tokens are ``[camera (1), registers (num_register_tokens), patches (h*w)]``.
    Round ``i`` runs ``frame_blocks[i]`` inside each frame and ``global_blocks[i]`` over
    all tokens of the scene; its output is ``[F_i, G_i]`` concatenated on channels.
    """

    def __init__(
        self,
        img_size: int = 518,
        patch_size: int = 14,
        embed_dim: int = 1024,
        depth: int = 24,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        num_register_tokens: int = 4,
        patch_embed_depth: int = 24,
        rope_freq: float = 100.0,
        init_value: float = 0.01,
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.rope_freq = rope_freq
        self.patch_start_idx = 1 + num_register_tokens
        self.patch_embed = DinoV2(
            img_size, patch_size, embed_dim, patch_embed_depth, num_heads, mlp_ratio, num_register_tokens
        )
        self.frame_blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, qk_norm=True, init_value=init_value) for _ in range(depth)
        )
        self.global_blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, qk_norm=True, init_value=init_value) for _ in range(depth)
        )
        # Slot 0: the first frame (it defines the world frame); slot 1: every other frame.
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, embed_dim) * 1e-6)
        self.register_token = nn.Parameter(torch.randn(1, 2, num_register_tokens, embed_dim) * 1e-6)
        self.reset_constants()

    def reset_constants(self, device: torch.device | str | None = None) -> None:
        """(Re)create the normalisation constants as **non-persistent** buffers.

        They are not in the checkpoint (a persistent buffer would break strict
        loading); a model built on the ``meta`` device gets real ones through this.
        """
        for name, value in (("_resnet_mean", RESNET_MEAN), ("_resnet_std", RESNET_STD)):
            self.register_buffer(name, torch.tensor(value, device=device).view(1, 1, 3, 1, 1), persistent=False)

    @property
    def depth(self) -> int:
        return len(self.frame_blocks)

    def forward(
        self, images: torch.Tensor, keep_layers: Iterable[int] | None = None
    ) -> tuple[list[torch.Tensor | None], int]:
        """Images ``(B, S, 3, H, W)`` in [0, 1] -> (outputs, ``patch_start_idx``).

        ``outputs`` has one entry per round, ``(B, S, P, 2*embed_dim)`` with
        ``P = patch_start_idx + h*w``. With ``keep_layers`` only those rounds are kept
        (the others are ``None``), which saves most activation memory and changes no number.
        """
        B, S, C_in, H, W = images.shape
        if C_in != 3:
            raise ValueError(f"expected 3 input channels, got {C_in}")
        keep = set(range(self.depth)) if keep_layers is None else {i % self.depth for i in keep_layers}

        images = ((images - self._resnet_mean) / self._resnet_std).reshape(B * S, C_in, H, W)
        patch_tokens = self.patch_embed(images)  # (B*S, h*w, C)
        tokens = torch.cat(
            [
                frame_slot_tokens(self.camera_token, B, S),
                frame_slot_tokens(self.register_token, B, S),
                patch_tokens,
            ],
            dim=1,
        )  # (B*S, P, C)
        _, P, C = tokens.shape

        head_dim = self.frame_blocks[0].attn.head_dim
        positions = token_positions(H // self.patch_size, W // self.patch_size, self.patch_start_idx, images.device)
        frame_angles = rope_angles(positions, head_dim, self.rope_freq)  # (P, head_dim)
        # Positions carry no frame index: the global sequence repeats the frame table.
        global_angles = frame_angles.repeat(S, 1)  # (S*P, head_dim)

        outputs: list[torch.Tensor | None] = [None] * self.depth
        for i, (frame_block, global_block) in enumerate(zip(self.frame_blocks, self.global_blocks)):
            tokens = frame_block(tokens.reshape(B * S, P, C), frame_angles)
            frame_out = tokens.reshape(B, S, P, C)
            tokens = global_block(tokens.reshape(B, S * P, C), global_angles)
            if i in keep:
                outputs[i] = torch.cat([frame_out, tokens.reshape(B, S, P, C)], dim=-1)
        return outputs, self.patch_start_idx
