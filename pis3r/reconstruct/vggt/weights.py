"""Finding, fetching and loading VGGT checkpoints (spec §9).

Nothing here touches the network except :func:`fetch_weights`, which runs only when
the user asks for it (``pis3r fetch-weights vggt``).
"""

from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Mapping

from pis3r.errors import WeightsError, one_line

logger = logging.getLogger(__name__)

WEIGHTS_ENV = "PIS3R_VGGT_WEIGHTS"
HF_REPO = "facebook/VGGT-1B"
HF_FILES = ("model.safetensors", "model.pt")
FETCH_HINT = "get them with `pis3r fetch-weights vggt`"

if TYPE_CHECKING:  # torch is imported only when a model is loaded
    import torch

    from pis3r.reconstruct.vggt.model import VGGT


def find_weights(path: str | os.PathLike | None = None) -> Path | None:
    """Where the VGGT weights are: ``path`` if given, else ``$PIS3R_VGGT_WEIGHTS``, else the
    Hugging Face cache of ``facebook/VGGT-1B`` (``model.safetensors``, then ``model.pt``).

    An explicit path or variable is returned even when the file is missing, so that
    loading names it in its error. The cache lookup is local only (never downloads).
    """
    if path:
        return Path(path).expanduser()
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        return Path(env).expanduser()
    try:
        from huggingface_hub import constants
    except ImportError:
        return None
    # The repository's cache folder (Hugging Face's layout: ``models--owner--name``, from its
    # own constants) is absent on every machine that never fetched the weights: then the
    # answer is None without importing the download machinery (0.1 s of every classical
    # run's start).
    folder = constants.REPO_ID_SEPARATOR.join([f"{constants.REPO_TYPE_MODEL}s", *HF_REPO.split("/")])
    if not (Path(constants.HF_HUB_CACHE) / folder).is_dir():
        return None
    from huggingface_hub import try_to_load_from_cache

    for filename in HF_FILES:
        hit = try_to_load_from_cache(HF_REPO, filename)
        if isinstance(hit, str) and Path(hit).is_file():
            return Path(hit)
    return None


def fetch_weights() -> Path:
    """Download ``facebook/VGGT-1B/model.safetensors`` (≈5 GB) into the Hugging Face cache.

    Returns the local path (immediately when it is already cached). Raises
    :class:`WeightsError` with one line when it cannot be had (offline, no network...).
    """
    try:
        from huggingface_hub import constants, hf_hub_download
    except ImportError:
        raise WeightsError("huggingface_hub is not installed: `pip install huggingface_hub`") from None
    try:
        return Path(hf_hub_download(HF_REPO, HF_FILES[0]))
    except Exception as exc:  # network, offline mode, disk: all end the same way for the user
        offline = " (HF_HUB_OFFLINE is set)" if constants.HF_HUB_OFFLINE else ""
        raise WeightsError(
            f"cannot download {HF_REPO}/{HF_FILES[0]}{offline}: {one_line(exc, with_type=True)}; "
            f"download it where there is network and pass --weights PATH or set {WEIGHTS_ENV}"
        ) from None


# -- configuration from key shapes ------------------------------------------------------


def _count_indexed(shapes: Mapping[str, tuple], prefix: str) -> int:
    """Number of distinct ``{prefix}{i}.`` indices among the keys."""
    pattern = re.compile(re.escape(prefix) + r"(\d+)\.")
    return len({m.group(1) for key in shapes if (m := pattern.match(key))})


def infer_config(shapes: Mapping[str, tuple[int, ...]]) -> dict:
    """:class:`~pis3r.reconstruct.vggt.model.VGGT` keyword arguments that fit a checkpoint.

    ``shapes`` maps state-dict keys to tensor shapes. Widths, depths, head counts and
    which heads exist are read off the keys (the head count from the qk-norm width; the
    DINOv2 and camera-trunk blocks are assumed to use the same count, as VGGT-1B does).
    ``track_head.*`` keys are ignored.
    """
    try:
        embed_dim = shapes["aggregator.camera_token"][-1]
        num_register_tokens = shapes["aggregator.register_token"][2]
        patch_size = shapes["aggregator.patch_embed.patch_embed.proj.weight"][-1]
        grid = math.isqrt(shapes["aggregator.patch_embed.pos_embed"][1] - 1)
        head_dim = shapes["aggregator.frame_blocks.0.attn.q_norm.weight"][0]
        mlp_hidden = shapes["aggregator.frame_blocks.0.mlp.fc1.weight"][0]
    except KeyError as missing:
        raise WeightsError(f"not a VGGT checkpoint: it has no {missing.args[0]!r} tensor") from None
    config = dict(
        img_size=grid * patch_size,
        patch_size=patch_size,
        embed_dim=embed_dim,
        enable_camera="camera_head.token_norm.weight" in shapes,
        enable_point="point_head.norm.weight" in shapes,
        enable_depth="depth_head.norm.weight" in shapes,
        depth=_count_indexed(shapes, "aggregator.frame_blocks."),
        num_heads=embed_dim // head_dim,
        mlp_ratio=mlp_hidden / embed_dim,
        num_register_tokens=num_register_tokens,
        patch_embed_depth=_count_indexed(shapes, "aggregator.patch_embed.blocks."),
        camera_trunk_depth=_count_indexed(shapes, "camera_head.trunk."),
    )
    dense = "depth_head" if config["enable_depth"] else "point_head" if config["enable_point"] else None
    if dense is not None:
        config["dpt_features"] = shapes[f"{dense}.scratch.layer1_rn.weight"][0]
        config["dpt_out_channels"] = tuple(shapes[f"{dense}.projects.{k}.weight"][0] for k in range(4))
    return config


# -- loading ------------------------------------------------------------------------------


class _Checkpoint:
    """Uniform, lazy access to a ``.safetensors`` or a ``torch.save``d state dict."""

    def __init__(self, path: Path) -> None:
        self.path = path
        if path.suffix == ".safetensors":
            from safetensors import safe_open

            self._file = safe_open(str(path), framework="pt", device="cpu")
            self.shapes = {k: tuple(self._file.get_slice(k).get_shape()) for k in self._file.keys()}
            self._tensors = None
        else:
            import torch

            # mmap: tensors stay file-backed until moved, so RAM never holds two copies.
            state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
            if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor) for v in state.values()):
                raise ValueError("the file does not hold a flat state dict of tensors")
            self._tensors = dict(state)
            self.shapes = {k: tuple(v.shape) for k, v in self._tensors.items()}

    def tensors(self, keys: list[str]) -> Iterator[tuple[str, torch.Tensor]]:
        """One tensor at a time, read from the file only when asked for."""
        for key in keys:
            yield key, (self._tensors[key] if self._tensors is not None else self._file.get_tensor(key))


def load_vggt(path: str | os.PathLike, device: str | torch.device = "cpu") -> VGGT:
    """Build :class:`VGGT` to fit the checkpoint at ``path`` and load it strictly.

    ``path``: ``model.safetensors`` or ``model.pt`` of ``facebook/VGGT-1B`` (or any
    checkpoint of the same architecture; its configuration is inferred from the key
    shapes). The model is built on the ``meta`` device and every tensor is read, cast
    to float32 and moved to ``device`` one by one, then assigned — never two copies of
    the weights in memory. ``track_head.*`` tensors are skipped (logged); everything
    else must match exactly. Returns the model in eval mode without gradients.

    Raises :class:`WeightsError` (one line, naming the file) when the file is missing,
    unreadable or does not fit.
    """
    import torch

    from pis3r.reconstruct.vggt.model import TRACK_HEAD_PREFIX, VGGT

    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"VGGT weights not found: {path} ({FETCH_HINT}, or pass --weights PATH)")
    try:
        checkpoint = _Checkpoint(path)
    except Exception as exc:  # corrupt or foreign files fail in many library-specific ways
        raise WeightsError(
            f"{path}: not a readable VGGT checkpoint ({one_line(exc, with_type=True)}); {FETCH_HINT}"
        ) from None
    skipped = [k for k in checkpoint.shapes if k.startswith(TRACK_HEAD_PREFIX)]
    if skipped:
        count = sum(math.prod(checkpoint.shapes[k]) for k in skipped)
        logger.info(
            "%s: skipped %d track_head.* tensors (%d parameters): pis3r's VGGT has no track head",
            path, len(skipped), count,
        )
    try:
        config = infer_config(checkpoint.shapes)
    except WeightsError as exc:
        raise WeightsError(f"{path}: {exc}; {FETCH_HINT}") from None
    with torch.device("meta"):
        model = VGGT(**config)
    keys = [k for k in checkpoint.shapes if not k.startswith(TRACK_HEAD_PREFIX)]
    try:
        state = {k: t.to(device=device, dtype=torch.float32) for k, t in checkpoint.tensors(keys)}
    except Exception as exc:
        raise WeightsError(f"{path}: cannot read its tensors ({one_line(exc, with_type=True)}); {FETCH_HINT}") from None
    try:
        model.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as exc:
        raise WeightsError(f"{path}: does not fit the VGGT architecture ({_mismatch(model, state, exc)})") from None
    model.aggregator.reset_constants(device)
    return model.eval().requires_grad_(False)


def _mismatch(model: VGGT, state: Mapping, error: RuntimeError) -> str:
    """One line on why a strict load failed: missing/unexpected keys, else the first size mismatch."""
    expected, given = set(model.state_dict()), set(state)
    missing, unexpected = sorted(expected - given), sorted(given - expected)
    if missing or unexpected:
        return "; ".join(
            f"{len(keys)} {kind}" + (f", e.g. {', '.join(keys[:3])}" if keys else "")
            for kind, keys in (("missing", missing), ("unexpected", unexpected))
        )
    return next((line.strip() for line in str(error).splitlines() if "mismatch" in line), one_line(error, with_type=True))
