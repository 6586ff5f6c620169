"""VGGT: the aggregator plus camera, depth and point heads (spec §1).

Parameter names and shapes are those of the released ``facebook/VGGT-1B`` checkpoint,
so it loads with ``strict=True`` (without its ``track_head.*`` tensors: the track head
is not needed for stitching and is not built).
"""

from __future__ import annotations

import contextlib
import logging
from collections import OrderedDict
from typing import Iterable

import torch
from torch import nn

from pis3r.reconstruct.vggt.aggregator import Aggregator
from pis3r.reconstruct.vggt.camera_head import CameraHead
from pis3r.reconstruct.vggt.dpt import DPTHead
from pis3r.reconstruct.vggt.graphs import CudaGraphCache
from pis3r.reconstruct.vggt.layers import Block

logger = logging.getLogger(__name__)

TRACK_HEAD_PREFIX = "track_head."  # tensors of the track head, which pis3r does not build

RELEASED_DPT_LAYERS = (4, 11, 17, 23)

# A tiny variant with every code path of the 1B model (tests, CPU benchmarks): a 4x4
# position table (so usual inputs resize it both ways), 2 + 2 rounds, 32-wide tokens.
SMALL_CONFIG = dict(
    img_size=56,
    embed_dim=32,
    depth=2,
    num_heads=2,
    patch_embed_depth=2,
    dpt_features=8,
    dpt_out_channels=(8, 16, 32, 32),
)


def default_dpt_layers(depth: int) -> tuple[int, int, int, int]:
    """Aggregator rounds read by the DPT heads: the released ones for depth 24, else
    four rounds spread evenly from the first to the last (small test configurations)."""
    if depth == 24:
        return RELEASED_DPT_LAYERS
    return tuple(round(k * (depth - 1) / 3) for k in range(4))


def heads_in_fp32(device_type: str):
    """Autocast switched off for the heads (they run in fp32 on the fp32 tokens the
    aggregator returns); a no-op where the device has no autocast (e.g. ``meta``)."""
    if torch.amp.is_autocast_available(device_type):
        return torch.autocast(device_type=device_type, enabled=False)
    return contextlib.nullcontext()


class VGGT(nn.Module):
    """Visual Geometry Grounded Transformer; ``VGGT()`` is the released 1B configuration.

    The first six parameters have the official names and meaning (``enable_track``
    must stay False: pis3r has no track head). The keyword-only ones describe smaller
    variants of the same architecture (:func:`pis3r.reconstruct.vggt.weights.infer_config`
    reads them off a checkpoint). ``cuda_graphs``: on CUDA, in eval mode and without
    autograd, replay the forward from shape-keyed CUDA graphs (same kernels, same numbers,
    no per-kernel launch cost).
    """

    def __init__(
        self,
        img_size: int = 518,
        patch_size: int = 14,
        embed_dim: int = 1024,
        enable_camera: bool = True,
        enable_point: bool = True,
        enable_depth: bool = True,
        enable_track: bool = False,
        *,
        depth: int = 24,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        num_register_tokens: int = 4,
        patch_embed_depth: int = 24,
        camera_trunk_depth: int = 4,
        dpt_features: int = 256,
        dpt_out_channels: Iterable[int] = (256, 512, 1024, 1024),
        dpt_layers: Iterable[int] | None = None,
        cuda_graphs: bool = True,
    ) -> None:
        super().__init__()
        if enable_track:
            raise ValueError("pis3r's VGGT has no track head; build it with enable_track=False")
        dpt_layers = tuple(dpt_layers) if dpt_layers is not None else default_dpt_layers(depth)
        dpt_out_channels = tuple(dpt_out_channels)
        self.config = dict(
            img_size=img_size,
            patch_size=patch_size,
            embed_dim=embed_dim,
            enable_camera=enable_camera,
            enable_point=enable_point,
            enable_depth=enable_depth,
            depth=depth,
            num_heads=num_heads,
            mlp_ratio=mlp_ratio,
            num_register_tokens=num_register_tokens,
            patch_embed_depth=patch_embed_depth,
            camera_trunk_depth=camera_trunk_depth,
            dpt_features=dpt_features,
            dpt_out_channels=dpt_out_channels,
            dpt_layers=dpt_layers,
        )
        self.aggregator = Aggregator(
            img_size,
            patch_size,
            embed_dim,
            depth=depth,
            num_heads=num_heads,
            mlp_ratio=mlp_ratio,
            num_register_tokens=num_register_tokens,
            patch_embed_depth=patch_embed_depth,
        )
        head_dim_in = 2 * embed_dim
        self.camera_head = (
            CameraHead(head_dim_in, camera_trunk_depth, num_heads, mlp_ratio) if enable_camera else None
        )

        def dpt(output_dim: int, activation: str) -> DPTHead:
            return DPTHead(head_dim_in, patch_size, output_dim, activation, dpt_features, dpt_out_channels, dpt_layers)

        self.point_head = dpt(4, "inv_log") if enable_point else None
        self.depth_head = dpt(2, "exp") if enable_depth else None
        self.track_head = None
        self.cuda_graphs = cuda_graphs
        self._graphs = CudaGraphCache()

    # -- forward ---------------------------------------------------------------------

    def forward(self, images: torch.Tensor, query_points: torch.Tensor | None = None) -> dict:
        """Images ``(S, 3, H, W)`` or ``(B, S, 3, H, W)``, RGB in [0, 1] (H, W multiples of 14).

        Returns ``pose_enc (B, S, 9)``, ``pose_enc_list`` (one per camera-head pass),
        ``depth (B, S, H, W, 1)``, ``depth_conf (B, S, H, W)``, ``world_points
        (B, S, H, W, 3)``, ``world_points_conf (B, S, H, W)`` and, in eval mode, ``images``
        (the 5-D input). The aggregator runs under the caller's autocast; the heads run
        in fp32. ``query_points`` is accepted for signature compatibility and ignored
        (there is no track head, as in the official model built without one).
        """
        if images.dim() == 4:
            images = images.unsqueeze(0)
        if self._use_graphs(images):
            predictions = self._graphs.run(self.predict, images)
        else:
            predictions = self.predict(images)
        if not self.training:
            predictions["images"] = images
        return predictions

    def predict(self, images: torch.Tensor) -> dict:
        """The network proper on ``(B, S, 3, H, W)``: a dict of tensors, nothing else.

        Only the aggregator rounds the heads read are kept.
        """
        tokens_list, patch_start_idx = self.aggregator(images, keep_layers=self._layers_used())
        predictions: dict = {}
        with heads_in_fp32(images.device.type):
            if self.camera_head is not None:
                pose_enc_list = self.camera_head(tokens_list)
                predictions["pose_enc"] = pose_enc_list[-1]
                predictions["pose_enc_list"] = pose_enc_list
            if self.depth_head is not None:
                predictions["depth"], predictions["depth_conf"] = self.depth_head(tokens_list, images, patch_start_idx)
            if self.point_head is not None:
                predictions["world_points"], predictions["world_points_conf"] = self.point_head(
                    tokens_list, images, patch_start_idx
                )
        return predictions

    def _layers_used(self) -> set[int]:
        layers: set[int] = set()
        if self.camera_head is not None:
            layers.add(self.aggregator.depth - 1)
        for head in (self.depth_head, self.point_head):
            if head is not None:
                layers.update(head.intermediate_layer_idx)
        return layers

    def _use_graphs(self, images: torch.Tensor) -> bool:
        return (
            self.cuda_graphs
            and images.is_cuda
            and not self.training
            and not torch.is_grad_enabled()
            and not torch.compiler.is_compiling()
            and not torch.cuda.is_current_stream_capturing()
        )

    # -- speed knobs -----------------------------------------------------------------

    def compile_blocks(self, **compile_kwargs) -> VGGT:
        """``torch.compile`` every transformer block in place (regional compilation).

        Blocks of one kind share their compiled code. It fuses the LayerNorm, RoPE,
        GELU and residual element-wise work around the matmuls (values move by float
        rounding only). Works with CUDA-graph replay: compilation happens in the
        warm-up runs before capture.
        """
        for module in self.modules():
            if isinstance(module, Block):
                module.compile(**compile_kwargs)
        self._graphs.clear()
        return self

    def _apply(self, fn, recurse: bool = True):
        # Moving or casting the model replaces its tensors: captured graphs would point
        # at the old ones.
        self._graphs.clear()
        return super()._apply(fn, recurse)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """``nn.Module.load_state_dict``, except that ``track_head.*`` entries (in the
        released checkpoint and in an official model's state dict) are skipped with a log
        line: this model has no track head. Every other key must match as usual."""
        skipped = [k for k in state_dict if k.startswith(TRACK_HEAD_PREFIX)]
        if skipped:
            logger.info("skipped %d track_head.* tensors: pis3r's VGGT has no track head", len(skipped))
            kept = OrderedDict((k, v) for k, v in state_dict.items() if not k.startswith(TRACK_HEAD_PREFIX))
            if hasattr(state_dict, "_metadata"):
                kept._metadata = state_dict._metadata
            state_dict = kept
        self._graphs.clear()
        return super().load_state_dict(state_dict, strict=strict, assign=assign)
