"""The reconstruction protocol and the registry of backends.

A backend turns photos into a :class:`~pis3r.scene.Scene`: one camera and a dense
depth/confidence map per photo, world frame = the first photo's camera.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Protocol

from pis3r.errors import InputError
from pis3r.io import Photo
from pis3r.scene import Scene


@dataclass
class ReconstructOptions:
    """Settings every backend receives; each uses the ones that concern it.

    ``focal``: focal length in pixels of the input photos (overrides EXIF and
    self-calibration); ``device``: ``"cpu"``, ``"cuda"`` or ``"auto"``;
    ``weights``: a weight file for learned backends; ``conf_threshold``: drop points
    whose confidence is below it (``0`` keeps all, as the paper does);
    ``depth_fill``: how the classical backend fills depth where only one view sees
    the scene (``"planar"`` or ``"harmonic"``, see :mod:`pis3r.reconstruct.propagate`).
    """

    focal: float | None = None
    device: str = "auto"
    weights: str | os.PathLike | None = None
    conf_threshold: float = 0.0
    depth_fill: str = "planar"


class Reconstructor(Protocol):
    """What every backend offers. ``photos[0]`` is the reference (world frame)."""

    name: str

    def reconstruct(self, photos: list[Photo]) -> Scene:  # pragma: no cover - protocol
        ...


_REGISTRY: dict[str, Callable[[ReconstructOptions], Reconstructor]] = {}


def register(name: str):
    """Class decorator: make a backend constructible by name from ReconstructOptions."""

    def add(factory):
        _REGISTRY[name] = factory
        return factory

    return add


def backend_names() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY)


def resolve_backend_name(name: str, options: ReconstructOptions) -> str:
    """``auto`` -> ``vggt`` when VGGT weights can be found, else ``classical``."""
    if name != "auto":
        return name
    _load_builtin()
    if "vggt" in _REGISTRY:
        from pis3r.reconstruct.vggt import find_weights

        if find_weights(options.weights) is not None:
            return "vggt"
    return "classical"


def create_backend(name: str, options: ReconstructOptions | None = None) -> Reconstructor:
    """Build backend ``name`` (``auto`` resolved first) with ``options``."""
    options = options or ReconstructOptions()
    name = resolve_backend_name(name, options)
    _load_builtin()
    if name not in _REGISTRY:
        raise InputError(f"unknown backend {name!r}; choose one of auto, {', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[name](options)


def resolve_device(device: str) -> str:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise InputError("--device cuda was asked for but no CUDA GPU is available")
    return device


def _load_builtin() -> None:
    # Imported lazily so that `import pis3r` stays light.
    from pis3r.reconstruct import classical  # noqa: F401

    try:
        from pis3r.reconstruct import vggt  # noqa: F401
    except ImportError:
        pass
