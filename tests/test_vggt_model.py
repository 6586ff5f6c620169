"""VGGT network: architecture of the released checkpoint, the spec's traps, numerics.

The golden numbers below were produced by this implementation and checked, bit for
bit in float64, against a line-by-line transcription of the official
facebookresearch/vggt inference code with the same random weights (kept outside the
repository). Any change to the computation moves them.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from pis3r.reconstruct.vggt import VGGT
from pis3r.reconstruct.vggt.aggregator import frame_slot_tokens
from pis3r.reconstruct.vggt.dinov2 import resize_pos_embed
from pis3r.reconstruct.vggt.dpt import FeatureFusionBlock, ResidualConvUnit, dpt_position_embedding
from pis3r.reconstruct.vggt.graphs import CudaGraphCache, _Captured
from pis3r.reconstruct.vggt.layers import Block
from pis3r.reconstruct.vggt.model import SMALL_CONFIG
from pis3r.reconstruct.vggt.rope import apply_rope, rope_angles, token_positions


def randomized(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Every parameter drawn from a seeded generator (LayerNorm weights near 1, LayerScale
    near 0.5, tokens and tables O(0.5), matrices scaled by 1/sqrt(fan-in))."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            n = torch.randn(p.shape, generator=g, dtype=torch.float64)
            if p.dim() == 1 and "norm" in name and name.endswith("weight"):
                p.copy_(1 + 0.1 * n)
            elif name.endswith("gamma"):
                p.copy_(0.5 + 0.2 * n)
            elif p.dim() == 1:
                p.copy_(0.1 * n)
            elif name.endswith(("token", "tokens", "pos_embed")):
                p.copy_(0.5 * n)
            else:
                p.copy_(0.5 * n / (p[0].numel() ** 0.5))
    return model


def small_model(dtype=torch.float64, seed: int = 0) -> VGGT:
    return randomized(VGGT(**SMALL_CONFIG).to(dtype).eval(), seed)


def images(S: int = 3, H: int = 42, W: int = 70, dtype=torch.float64, seed: int = 1) -> torch.Tensor:
    return torch.rand(S, 3, H, W, generator=torch.Generator().manual_seed(seed), dtype=dtype)


def fingerprint(t: torch.Tensor, seed: int = 2) -> float:
    """A weighted sum that moves with any value at any position."""
    w = torch.rand(t.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return (t.double() * w).sum().item()


# -- the released architecture -----------------------------------------------------------


@pytest.fixture(scope="module")
def meta_1b() -> VGGT:
    with torch.device("meta"):
        return VGGT()


def test_1b_parameter_and_tensor_counts(meta_1b):
    state = meta_1b.state_dict()
    assert len(state) == 1403
    assert sum(t.numel() for t in state.values()) == 1_190_596_120
    groups = {
        "aggregator.camera_token": (1, 2_048),
        "aggregator.register_token": (1, 8_192),
        "aggregator.patch_embed.": (344, 304_372_736),
        "aggregator.frame_blocks.": (432, 302_364_672),
        "aggregator.global_blocks.": (432, 302_364_672),
        "camera_head.": (69, 216_174_610),
        "depth_head.": (62, 32_654_562),
        "point_head.": (62, 32_654_628),
    }
    for prefix, (tensors, params) in groups.items():
        members = [t for k, t in state.items() if k.startswith(prefix)]
        assert (len(members), sum(t.numel() for t in members)) == (tensors, params), prefix
    assert all(t.dtype == torch.float32 for t in state.values())
    assert meta_1b.track_head is None


def _spec_keys() -> set[str]:
    """Every state-dict key of VGGT-1B without its track head, from the patterns of spec §8."""
    wb = (".weight", ".bias")
    block = [f"{n}{s}" for n in ("norm1", "norm2", "attn.qkv", "attn.proj", "mlp.fc1", "mlp.fc2") for s in wb]
    block += ["ls1.gamma", "ls2.gamma"]
    qk_norm = [f"attn.{n}_norm{s}" for n in "qk" for s in wb]
    keys = {"aggregator.camera_token", "aggregator.register_token"}
    dino = "aggregator.patch_embed."
    keys |= {dino + k for k in ("cls_token", "pos_embed", "register_tokens", "mask_token")}
    keys |= {dino + "patch_embed.proj" + s for s in wb} | {dino + "norm" + s for s in wb}
    keys |= {f"{dino}blocks.{i}.{k}" for i in range(24) for k in block}
    for kind in ("frame", "global"):
        keys |= {f"aggregator.{kind}_blocks.{i}.{k}" for i in range(24) for k in block + qk_norm}
    cam = "camera_head."
    keys |= {f"{cam}trunk.{i}.{k}" for i in range(4) for k in block}
    keys |= {cam + "empty_pose_tokens"}
    for name in ("token_norm", "trunk_norm", "embed_pose", "poseLN_modulation.1", "pose_branch.fc1", "pose_branch.fc2"):
        keys |= {cam + name + s for s in wb}
    for head in ("depth_head.", "point_head."):
        convs = ["norm", *(f"projects.{k}" for k in range(4)), *(f"resize_layers.{k}" for k in (0, 1, 3))]
        convs += [f"scratch.refinenet{r}.resConfUnit1.conv{c}" for r in (1, 2, 3) for c in (1, 2)]
        convs += [f"scratch.refinenet{r}.resConfUnit2.conv{c}" for r in (1, 2, 3, 4) for c in (1, 2)]
        convs += [f"scratch.refinenet{r}.out_conv" for r in (1, 2, 3, 4)]
        convs += ["scratch.output_conv1", "scratch.output_conv2.0", "scratch.output_conv2.2"]
        keys |= {head + c + s for c in convs for s in wb}
        keys |= {f"{head}scratch.layer{k}_rn.weight" for k in range(1, 5)}
    return keys


def test_1b_has_exactly_the_spec_keys(meta_1b):
    assert set(meta_1b.state_dict()) == _spec_keys()


def test_1b_key_names_and_shapes(meta_1b):
    shapes = {k: tuple(t.shape) for k, t in meta_1b.state_dict().items()}
    expected = {
        "aggregator.camera_token": (1, 2, 1, 1024),
        "aggregator.register_token": (1, 2, 4, 1024),
        "aggregator.patch_embed.patch_embed.proj.weight": (1024, 3, 14, 14),
        "aggregator.patch_embed.cls_token": (1, 1, 1024),
        "aggregator.patch_embed.pos_embed": (1, 1370, 1024),
        "aggregator.patch_embed.register_tokens": (1, 4, 1024),
        "aggregator.patch_embed.mask_token": (1, 1024),
        "aggregator.patch_embed.norm.weight": (1024,),
        "aggregator.patch_embed.blocks.23.attn.qkv.weight": (3072, 1024),
        "aggregator.patch_embed.blocks.0.ls1.gamma": (1024,),
        "aggregator.patch_embed.blocks.0.mlp.fc1.weight": (4096, 1024),
        "aggregator.patch_embed.blocks.0.mlp.fc2.weight": (1024, 4096),
        "aggregator.frame_blocks.23.attn.q_norm.weight": (64,),
        "aggregator.global_blocks.0.attn.k_norm.bias": (64,),
        "aggregator.global_blocks.23.ls2.gamma": (1024,),
        "camera_head.trunk.3.attn.qkv.weight": (6144, 2048),
        "camera_head.trunk.0.mlp.fc1.weight": (8192, 2048),
        "camera_head.token_norm.weight": (2048,),
        "camera_head.trunk_norm.bias": (2048,),
        "camera_head.empty_pose_tokens": (1, 1, 9),
        "camera_head.embed_pose.weight": (2048, 9),
        "camera_head.poseLN_modulation.1.weight": (6144, 2048),
        "camera_head.pose_branch.fc1.weight": (1024, 2048),
        "camera_head.pose_branch.fc2.bias": (9,),
        "depth_head.norm.weight": (2048,),
        "depth_head.projects.0.weight": (256, 2048, 1, 1),
        "depth_head.projects.3.weight": (1024, 2048, 1, 1),
        "depth_head.resize_layers.0.weight": (256, 256, 4, 4),
        "depth_head.resize_layers.1.weight": (512, 512, 2, 2),
        "depth_head.resize_layers.3.weight": (1024, 1024, 3, 3),
        "depth_head.scratch.layer2_rn.weight": (256, 512, 3, 3),
        "depth_head.scratch.refinenet1.resConfUnit1.conv1.weight": (256, 256, 3, 3),
        "depth_head.scratch.refinenet4.resConfUnit2.conv2.bias": (256,),
        "depth_head.scratch.refinenet4.out_conv.weight": (256, 256, 1, 1),
        "depth_head.scratch.output_conv1.weight": (128, 256, 3, 3),
        "depth_head.scratch.output_conv2.0.weight": (32, 128, 3, 3),
        "depth_head.scratch.output_conv2.2.weight": (2, 32, 1, 1),
        "point_head.scratch.output_conv2.2.weight": (4, 32, 1, 1),
    }
    for key, shape in expected.items():
        assert shapes[key] == shape, key
    absent = [
        "depth_head.resize_layers.2.weight",
        "depth_head.scratch.refinenet4.resConfUnit1.conv1.weight",
        "depth_head.scratch.layer1_rn.bias",
        "aggregator.patch_embed.blocks.0.attn.q_norm.weight",
        "camera_head.trunk.0.attn.q_norm.weight",
        "camera_head.adaln_norm.weight",
        "aggregator._resnet_mean",
    ]
    assert not any(key in shapes for key in absent)
    assert not any(".blocks.0.0." in k or "trunk.blocks" in k for k in shapes)


def test_normalisation_buffers_exist_but_are_not_persistent(meta_1b):
    buffers = dict(meta_1b.named_buffers())
    assert set(buffers) == {"aggregator._resnet_mean", "aggregator._resnet_std"}
    assert not any("_resnet" in k for k in meta_1b.state_dict())
    model = VGGT(**SMALL_CONFIG)
    torch.testing.assert_close(model.aggregator._resnet_mean.flatten(), torch.tensor([0.485, 0.456, 0.406]))
    torch.testing.assert_close(model.aggregator._resnet_std.flatten(), torch.tensor([0.229, 0.224, 0.225]))


def test_layernorm_eps_per_location(meta_1b):
    agg = meta_1b.aggregator
    dino = agg.patch_embed
    assert all(b.norm1.eps == b.norm2.eps == 1e-6 for b in dino.blocks) and dino.norm.eps == 1e-6
    for block in [*agg.frame_blocks, *agg.global_blocks]:
        assert block.norm1.eps == block.norm2.eps == 1e-5
        assert block.attn.q_norm.eps == block.attn.k_norm.eps == 1e-5
        assert block.attn.q_norm.elementwise_affine
    cam = meta_1b.camera_head
    assert all(b.norm1.eps == 1e-5 for b in cam.trunk) and cam.token_norm.eps == cam.trunk_norm.eps == 1e-5
    assert cam.adaln_norm.eps == 1e-6 and not cam.adaln_norm.elementwise_affine
    assert meta_1b.depth_head.norm.eps == meta_1b.point_head.norm.eps == 1e-5
    assert isinstance(dino.blocks[0].mlp.act, torch.nn.GELU) and dino.blocks[0].mlp.act.approximate == "none"


def test_track_head_is_not_buildable():
    with pytest.raises(ValueError, match="track head"):
        VGGT(**SMALL_CONFIG, enable_track=True)


# -- traps, one by one ------------------------------------------------------------------


def test_trap_position_table_resize_is_antialiased_bicubic_in_fp32():
    table = torch.randn(1, 1 + 16, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = resize_pos_embed(table, 3, 5, is_square=False)  # rows shrink 4 -> 3: antialias matters
    grid = table[:, 1:].float().reshape(1, 4, 4, 8).permute(0, 3, 1, 2)
    expected = F.interpolate(grid, size=(3, 5), mode="bicubic", antialias=True, align_corners=False)
    expected = torch.cat([table[:, :1].float(), expected.permute(0, 2, 3, 1).reshape(1, 15, 8)], 1).double()
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    plain = F.interpolate(grid, size=(3, 5), mode="bicubic", antialias=False, align_corners=False)
    assert (expected[0, 1:].float() - plain.permute(0, 2, 3, 1).reshape(15, 8)).abs().max() > 1e-2
    # The table's own grid on a square image: untouched; on a non-square one: resized.
    assert resize_pos_embed(table, 4, 4, is_square=True) is table
    assert resize_pos_embed(table, 4, 4, is_square=False) is not table


def test_trap_residual_conv_unit_adds_the_rectified_input():
    torch.manual_seed(0)
    unit = ResidualConvUnit(4)
    x = torch.randn(1, 4, 5, 6)
    x_before = x.clone()
    out = unit(x)
    rect = F.relu(x_before)
    torch.testing.assert_close(out, unit.conv2(F.relu(unit.conv1(rect))) + rect)
    assert (out - (unit.conv2(F.relu(unit.conv1(rect))) + x_before)).abs().max() > 0.1
    torch.testing.assert_close(x, x_before)  # the caller's tensor is not modified


def test_trap_fusion_block_resizes_bilinear_align_corners():
    torch.manual_seed(0)
    block = FeatureFusionBlock(4)
    a, b = torch.randn(1, 4, 3, 5), torch.randn(1, 4, 3, 5)
    fused = block.resConfUnit2(a + block.resConfUnit1(b))
    expected = block.out_conv(F.interpolate(fused, size=(6, 10), mode="bilinear", align_corners=True))
    torch.testing.assert_close(block(a, b), expected)
    top = FeatureFusionBlock(4, has_residual=False)
    assert not hasattr(top, "resConfUnit1")
    torch.testing.assert_close(
        top(a, size=(7, 9)),
        top.out_conv(F.interpolate(top.resConfUnit2(a), size=(7, 9), mode="bilinear", align_corners=True)),
    )


def test_trap_rope_positions_have_offset_one_and_zero_for_special_tokens():
    pos = token_positions(2, 3, 5, torch.device("cpu"))
    assert pos.shape == (11, 2)
    assert pos[:5].eq(0).all()
    assert pos[5:].tolist() == [[1, 1], [1, 2], [1, 3], [2, 1], [2, 2], [2, 3]]


def _rope_reference(x: torch.Tensor, pos: torch.Tensor, base: float = 100.0) -> torch.Tensor:
    """Spec §4 written out: first half rotated by the row, second half by the column;
    inside a half, channel k pairs with channel k + D/4 at angle p * base^(-2k/(D/2))."""
    D = x.shape[-1]
    half, quarter = D // 2, D // 4
    out = x.clone()
    for axis in range(2):
        p = pos[:, axis].double()
        for k in range(quarter):
            theta = p * base ** (-2 * k / half)
            i, j = axis * half + k, axis * half + k + quarter
            a, b = x[..., i], x[..., j]
            out[..., i] = a * torch.cos(theta) - b * torch.sin(theta)
            out[..., j] = b * torch.cos(theta) + a * torch.sin(theta)
    return out


def test_trap_rope_rotates_rows_then_columns_rotate_half():
    pos = token_positions(3, 4, 2, torch.device("cpu"))
    x = torch.randn(2, 3, pos.shape[0], 16, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = apply_rope(x, rope_angles(pos, 16))
    torch.testing.assert_close(out, _rope_reference(x, pos), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(out[:, :, :2], x[:, :, :2])  # special tokens: identity
    swapped = apply_rope(x, rope_angles(pos.flip(-1), 16))
    assert (swapped - out).abs().max() > 0.1


def test_trap_rope_angles_are_fp32_then_cast():
    pos = token_positions(37, 37, 5, torch.device("cpu"))
    angles = rope_angles(pos, 64)
    assert angles.dtype == torch.float32 and angles.shape == (1374, 64)
    inv_freq = 1.0 / (100.0 ** (torch.arange(0, 32, 2).float() / 32))
    torch.testing.assert_close(angles[-1, :16], 37.0 * inv_freq, rtol=0, atol=0)
    torch.testing.assert_close(angles[-1, 16:32], angles[-1, :16], rtol=0, atol=0)


def test_trap_camera_and_register_token_slots():
    slots = torch.arange(2 * 3 * 2, dtype=torch.float32).reshape(1, 2, 3, 2)
    tokens = frame_slot_tokens(slots, batch=2, frames=3)
    assert tokens.shape == (6, 3, 2)
    for scene in range(2):
        torch.testing.assert_close(tokens[3 * scene], slots[0, 0])
        torch.testing.assert_close(tokens[3 * scene + 1], slots[0, 1])
        torch.testing.assert_close(tokens[3 * scene + 2], slots[0, 1])


def test_trap_first_frame_defines_the_world():
    model = small_model()
    x = images(S=3)
    with torch.no_grad():
        out = model(x)
        swapped = model(x[[1, 0, 2]])
    # Swapping frames 0 and 1 is not a mere permutation of the outputs.
    assert (swapped["pose_enc"][0, 1] - out["pose_enc"][0, 0]).abs().max() > 1e-3
    assert (swapped["depth"][0, 1] - out["depth"][0, 0]).abs().max() > 1e-6
    # Frames 1 and 2 share a slot: swapping them permutes the outputs exactly.
    with torch.no_grad():
        tail = model(x[[0, 2, 1]])
    torch.testing.assert_close(tail["pose_enc"][0, [0, 2, 1]], out["pose_enc"][0], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(tail["depth"][0, [0, 2, 1]], out["depth"][0], rtol=1e-10, atol=1e-12)


def test_trap_dpt_position_embedding_follows_spec_formula():
    h, w, C, aspect = 3, 5, 8, 70 / 42
    emb = dpt_position_embedding(h, w, C, aspect, torch.float32, torch.device("cpu"))
    assert emb.shape == (C, h, w) and emb.dtype == torch.float32
    sx, sy = aspect / math.sqrt(aspect**2 + 1), 1 / math.sqrt(aspect**2 + 1)
    xs = torch.linspace(-sx * (w - 1) / w, sx * (w - 1) / w, w).double()
    ys = torch.linspace(-sy * (h - 1) / h, sy * (h - 1) / h, h).double()
    omega = 100.0 ** (-torch.arange(C // 4, dtype=torch.float64) / (C // 4))
    for r in range(h):
        for c in range(w):
            ax, ay = xs[c] * omega, ys[r] * omega
            expected = torch.cat([ax.sin(), ax.cos(), ay.sin(), ay.cos()]).float()
            torch.testing.assert_close(emb[:, r, c], expected, rtol=0, atol=1e-7)


def test_trap_heads_run_in_fp32_under_autocast():
    model = small_model(torch.float32)
    x = images(S=2, dtype=torch.float32)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        tokens, start = model.aggregator(x[None])
        out = model(x)
    for key in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        assert out[key].dtype == torch.float32, key
    with torch.no_grad():
        fp32_pose = model.camera_head([t.float() if t is not None else None for t in tokens])[-1]
    torch.testing.assert_close(out["pose_enc"], fp32_pose)


def test_qk_norm_comes_before_rope():
    torch.manual_seed(0)
    block = Block(16, 2, qk_norm=True)
    x = torch.randn(1, 6, 16)
    angles = rope_angles(token_positions(1, 5, 1, torch.device("cpu")), 8)
    attn = block.attn
    qkv = attn.qkv(x).reshape(1, 6, 3, 2, 8).permute(2, 0, 3, 1, 4)
    q, k, v = apply_rope(attn.q_norm(qkv[0]), angles), apply_rope(attn.k_norm(qkv[1]), angles), qkv[2]
    weights = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(8), dim=-1)
    expected = attn.proj((weights @ v).transpose(1, 2).reshape(1, 6, 16))
    torch.testing.assert_close(attn(x, angles), expected, rtol=1e-5, atol=1e-6)


# -- numerics of the whole model ------------------------------------------------------------

GOLDEN_POSE_ENC = [
    [-0.17283500571862775, -0.31301538616672947, 0.27238211737231377, -0.10005570135064983,
     -0.7222961556960629, -0.5504041158736671, -0.03166524944387135, 0.5251312571207104, 0.785256317985056],
    [-0.9548389257504081, 0.0023868583875752553, 0.743123974433568, -1.010281464849339,
     -0.34164093872025514, 0.2796762106016704, 0.9579659175369964, 0.0, 0.7305267155326185],
    [-0.946447038649863, 0.0758079525224206, 0.7628444047407823, -1.0325731855160019,
     -0.3362789023487638, 0.26884437168005737, 0.9553645777670946, 0.0, 0.719114443587711],
]
GOLDEN_FINGERPRINTS = {
    "depth": 4667.918570699718,
    "depth_conf": 8445.075536391443,
    "world_points": -465.3817397694827,
    "world_points_conf": 8174.562716062049,
}


def test_golden_outputs_float64():
    """3 frames of 42x70 (the 4x4 position table shrinks on rows, grows on columns)."""
    with torch.no_grad():
        out = small_model()(images(S=3))
    golden = torch.tensor(GOLDEN_POSE_ENC, dtype=torch.float64)
    torch.testing.assert_close(out["pose_enc"][0], golden, rtol=1e-9, atol=1e-12)
    for key, value in GOLDEN_FINGERPRINTS.items():
        assert fingerprint(out[key]) == pytest.approx(value, rel=1e-10), key


def test_output_shapes_activations_and_determinism():
    model = small_model(torch.float32)
    x = images(S=2, H=28, W=42, dtype=torch.float32)
    with torch.no_grad():
        out = model(x)
        again = model(x)
    B, S, H, W = 1, 2, 28, 42
    shapes = {
        "pose_enc": (B, S, 9),
        "depth": (B, S, H, W, 1),
        "depth_conf": (B, S, H, W),
        "world_points": (B, S, H, W, 3),
        "world_points_conf": (B, S, H, W),
        "images": (B, S, 3, H, W),
    }
    for key, shape in shapes.items():
        assert tuple(out[key].shape) == shape, key
        assert torch.isfinite(out[key]).all(), key
        assert torch.equal(out[key], again[key]), key
    assert len(out["pose_enc_list"]) == 4 and out["pose_enc_list"][-1] is out["pose_enc"]
    assert (out["depth"] > 0).all() and (out["depth_conf"] > 1).all() and (out["world_points_conf"] > 1).all()
    assert (out["pose_enc"][..., 7:] >= 0).all()
    model.train()
    assert "images" not in model(x)


def test_batched_input_matches_scene_by_scene():
    model = small_model()
    a, b = images(S=2, seed=3), images(S=2, seed=4)
    with torch.no_grad():
        both = model(torch.stack([a, b]))
        alone = model(b)
    for key in ("pose_enc", "depth", "world_points_conf"):
        torch.testing.assert_close(both[key][1], alone[key][0], rtol=1e-10, atol=1e-12)


def test_keeping_only_used_rounds_changes_nothing():
    model = small_model()
    x = images(S=2)[None]
    with torch.no_grad():
        every, start = model.aggregator(x)
        kept, _ = model.aggregator(x, keep_layers=model._layers_used())
    assert all(t is not None for t in every)
    for i, t in enumerate(kept):
        if t is not None:
            torch.testing.assert_close(t, every[i], rtol=0, atol=0)
    assert start == 5 and every[0].shape == (1, 2, 5 + 3 * 5, 64)


# -- speed path: capturable forward, graph cache --------------------------------------------


class _HostTensorAudit(TorchDispatchMode):
    """Records every op that sees a tensor off the model's (meta) device."""

    def __init__(self) -> None:
        super().__init__()
        self.offenders: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        leaves = tree_leaves((args, kwargs, out))
        if any(isinstance(t, torch.Tensor) and t.device.type != "meta" for t in leaves):
            self.offenders.append(str(func))
        return out


def test_forward_uses_no_host_data():
    """On the ``meta`` device any data-dependent op (``.item()``, ``int(t)``, ``.cpu()``)
    fails and any tensor made on the host shows up: the forward has neither, so on CUDA
    it makes no host<->device copy or sync and can be captured in a CUDA graph."""
    with torch.device("meta"):
        model = VGGT(**SMALL_CONFIG).eval()
        x = torch.empty(1, 2, 3, 42, 70)
    audit = _HostTensorAudit()
    with torch.no_grad(), audit:
        out = model(x)
    assert audit.offenders == []
    assert out["depth"].shape == (1, 2, 42, 70, 1)


class _FakeGraph:
    def __init__(self) -> None:
        self.replays = 0
        self.was_reset = False

    def replay(self) -> None:
        self.replays += 1

    def reset(self) -> None:
        self.was_reset = True


def test_graph_cache_is_keyed_by_shape_and_autocast_and_evicts_lru(monkeypatch):
    captured = []

    def fake_capture(fn, images, autocast):
        entry = _Captured(_FakeGraph(), images.clone(), fn(images))
        captured.append((tuple(images.shape), autocast, entry))
        return entry

    cache = CudaGraphCache(capacity=2)
    monkeypatch.setattr(cache, "_capture", fake_capture)

    def fn(images):
        pose = images.sum(dim=(-1, -2, -3))
        return {"pose_enc": pose, "pose_enc_list": [pose]}

    a, b, c = torch.ones(1, 2, 3, 4, 4), torch.ones(1, 3, 3, 4, 4), torch.ones(1, 4, 3, 4, 4)
    out = cache.run(fn, a)
    assert out["pose_enc_list"][-1] is out["pose_enc"]  # one copy of a shared output
    cache.run(fn, a)
    assert len(captured) == 1 and captured[0][2].graph.replays == 2
    cache.run(fn, b)
    cache.run(fn, a)  # a becomes the most recent
    cache.run(fn, c)  # evicts b
    assert len(cache) == 2 and captured[1][2].graph.was_reset and not captured[0][2].graph.was_reset
    cache.run(fn, b)
    assert len(captured) == 4
    cache.clear()
    assert len(cache) == 0


def test_graph_capture_failure_falls_back_to_eager(monkeypatch):
    cache = CudaGraphCache()

    def failing_capture(fn, images, autocast):
        raise RuntimeError("operation not permitted when stream is capturing")

    monkeypatch.setattr(cache, "_capture", failing_capture)
    x = torch.ones(2, 2)
    assert torch.equal(cache.run(lambda t: {"y": t * 2}, x)["y"], x * 2)
    monkeypatch.setattr(cache, "_capture", lambda *a: pytest.fail("retried a failed capture"))
    assert torch.equal(cache.run(lambda t: {"y": t * 2}, x)["y"], x * 2)


def test_graphs_only_on_cuda_inference_and_cleared_when_tensors_change():
    model = small_model(torch.float32)
    assert not model._use_graphs(torch.empty(1, 1, 3, 14, 14))
    model._graphs._graphs[("fake",)] = _Captured(_FakeGraph(), torch.empty(0), {})
    model.double()
    assert len(model._graphs) == 0
    model._graphs._graphs[("fake",)] = _Captured(_FakeGraph(), torch.empty(0), {})
    model.load_state_dict(model.state_dict())
    assert len(model._graphs) == 0


def test_load_state_dict_skips_only_track_head_entries(caplog):
    source = small_model(torch.float32)
    state = source.state_dict()
    state["track_head.tracker.updateformer.virual_tracks"] = torch.zeros(1, 4, 1, 8)
    target = VGGT(**SMALL_CONFIG)
    with caplog.at_level("INFO", logger="pis3r.reconstruct.vggt.model"):
        target.load_state_dict(state)  # strict
    assert any("skipped 1 track_head.* tensors" in r.getMessage() for r in caplog.records)
    assert all(torch.equal(a, b) for a, b in zip(target.state_dict().values(), source.state_dict().values()))
    state["aggregator.extra"] = torch.zeros(1)
    with pytest.raises(RuntimeError, match="aggregator.extra"):
        target.load_state_dict(state)
