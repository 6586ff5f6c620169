"""The refiner as shipped: a UNet plus the diffusion settings it was trained with,
saved as one fp16 safetensors file whose metadata holds those settings."""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch

from pis3r.errors import WeightsError
from pis3r.refine.rddm import OBJECTIVE_CHANNELS, Schedule, linear_schedule
from pis3r.refine.unet import UNet, UNetConfig

FORMAT = "pis3r-rddm/1"


@dataclass
class Refiner:
    """``net`` predicts ``objective`` outputs for the ``schedule`` with ``noise_scale`` (spec
    §2.3: training and sampling must agree on it); ``train_size`` is the crop size it saw."""

    net: UNet
    objective: str
    noise_scale: float
    train_steps: int = 1000
    train_size: int = 128

    @property
    def schedule(self) -> Schedule:
        return linear_schedule(self.train_steps, self.noise_scale)

    def metadata(self) -> dict[str, str]:
        return {
            "format": FORMAT,
            "unet": json.dumps(self.net.config.to_dict()),
            "objective": self.objective,
            "noise_scale": repr(self.noise_scale),
            "train_steps": str(self.train_steps),
            "train_size": str(self.train_size),
        }


def new_refiner(config: UNetConfig, objective: str = "pred_res_noise", noise_scale: float = 1.0,
                train_size: int = 128) -> Refiner:  # fmt: skip
    """A freshly initialised refiner whose UNet outputs what ``objective`` needs."""
    config = UNetConfig.from_dict({**config.to_dict(), "out_channels": OBJECTIVE_CHANNELS[objective]})
    return Refiner(UNet(config), objective, float(noise_scale), train_size=train_size)


def save_refiner(refiner: Refiner, path: str | Path, state: dict[str, torch.Tensor] | None = None) -> Path:
    """Write ``state`` (default: the net's own weights) as fp16 safetensors with the settings."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = refiner.net.state_dict() if state is None else state
    tensors = {name: value.detach().to("cpu", torch.float16).contiguous() for name, value in state.items()}
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=refiner.metadata())
    tmp.replace(path)
    path.chmod(0o644)  # safetensors creates 0600 files; weights are meant to be shared
    return path


def load_refiner(path: str | Path, device: str | torch.device = "cpu") -> Refiner:
    """Load a refiner written by :func:`save_refiner` (fp32 on ``device``, eval mode).

    Raises :class:`WeightsError` with a one-line message naming the file when it is
    missing, unreadable or not a pis3r RDDM file.
    """
    path = Path(path)
    if not path.is_file():
        raise WeightsError(
            f"refiner weights not found: {path} (reinstall pis3r, train them with "
            f"'pis3r train-refiner {path.name}', or use --refine none)"
        )
    return _load_cached(str(path.resolve()), path.stat().st_mtime_ns, str(torch.device(device)))


@lru_cache(maxsize=4)
def _load_cached(path: str, mtime_ns: int, device: str) -> Refiner:
    from safetensors import safe_open

    try:
        with safe_open(path, framework="pt") as handle:
            meta = handle.metadata() or {}
            if meta.get("format") != FORMAT:
                raise ValueError(f"metadata format is {meta.get('format')!r}, expected {FORMAT!r}")
            state = {name: handle.get_tensor(name).float() for name in handle.keys()}
        refiner = Refiner(
            UNet(UNetConfig.from_dict(json.loads(meta["unet"]))),
            meta["objective"],
            float(meta["noise_scale"]),
            int(meta["train_steps"]),
            int(meta["train_size"]),
        )
        refiner.net.load_state_dict(state)
    except Exception as exc:  # safetensors, json and torch each raise their own kinds
        reason = (" ".join(str(exc).split()) or type(exc).__name__)[:200]
        raise WeightsError(f"refiner weights {path} are corrupt or not a pis3r RDDM file: {reason}") from exc
    refiner.net.to(device).eval()
    return refiner
