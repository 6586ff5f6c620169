"""Camera head: iterative refinement of a 9-number pose encoding per frame (spec §5)."""

from __future__ import annotations

import torch
from torch import nn

from pis3r.reconstruct.vggt.activations import activate_pose
from pis3r.reconstruct.vggt.layers import Block, Mlp

POSE_ENCODING_DIM = 9  # absT_quaR_FoV: translation 3, quaternion (XYZW) 4, FoV (h, w) 2


class CameraHead(nn.Module):
    """Reads the camera token of the last aggregator round and refines a pose 4 times.

    Each pass restarts from the normalised camera tokens ``t``, modulates them with the
    embedding of the previous raw (pre-activation) estimate (adaLN: shift, scale, gate),
    runs the trunk — attention across the ``S`` camera tokens of a scene — and adds a
    delta to the estimate.
    """

    def __init__(
        self,
        dim_in: int = 2048,
        trunk_depth: int = 4,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        init_value: float = 0.01,
        num_iterations: int = 4,
    ) -> None:
        super().__init__()
        self.num_iterations = num_iterations
        self.trunk = nn.Sequential(
            *(Block(dim_in, num_heads, mlp_ratio, init_value=init_value) for _ in range(trunk_depth))
        )
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, POSE_ENCODING_DIM))
        self.embed_pose = nn.Linear(POSE_ENCODING_DIM, dim_in)
        # Index 0 is the SiLU; the checkpoint's key is `poseLN_modulation.1`.
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim_in, 3 * dim_in))
        self.adaln_norm = nn.LayerNorm(dim_in, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim_in, dim_in // 2, POSE_ENCODING_DIM)

    def forward(self, tokens_list: list[torch.Tensor | None]) -> list[torch.Tensor]:
        """Aggregator outputs (the last is ``(B, S, P, dim_in)``) -> ``num_iterations`` x ``(B, S, 9)``."""
        tokens = self.token_norm(tokens_list[-1][:, :, 0])  # camera tokens (B, S, dim_in)
        B, S, _ = tokens.shape
        raw = None
        encodings = []
        for _ in range(self.num_iterations):
            if raw is None:
                conditioning = self.embed_pose(self.empty_pose_tokens.expand(B, S, -1))
            else:
                conditioning = self.embed_pose(raw.detach())
            shift, scale, gate = self.poseLN_modulation(conditioning).chunk(3, dim=-1)
            modulated = gate * (self.adaln_norm(tokens) * (1 + scale) + shift) + tokens
            delta = self.pose_branch(self.trunk_norm(self.trunk(modulated)))
            raw = delta if raw is None else raw + delta
            encodings.append(activate_pose(raw))
        return encodings
