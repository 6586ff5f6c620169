"""The reconstruction protocol and the static table of backends.

A backend turns photos into a :class:`~pis3r.scene.Scene`: one camera and a dense
depth/confidence map per photo, world frame = the first photo's camera. Backends are
imported only when built, so choosing one never loads another's dependencies.
"""

from __future__ import annotations

from typing import Callable, Protocol

from pis3r.errors import InputError
from pis3r.io import Photo
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.scene import Scene


class Reconstructor(Protocol):
    """What every backend offers. ``photos[0]`` is the reference (world frame)."""

    name: str

    def reconstruct(self, photos: list[Photo]) -> Scene:  # pragma: no cover - protocol
        ...


def _classical(options: ReconstructOptions, memo: dict | None) -> Reconstructor:
    from pis3r.reconstruct.classical import ClassicalReconstructor

    return ClassicalReconstructor(options, memo)


def _vggt(options: ReconstructOptions, memo: dict | None) -> Reconstructor:
    from pis3r.reconstruct.vggt.backend import VGGTBackend

    return VGGTBackend(options)


# Each builder takes the options and a memo of work already done on the same photo objects
# (the classical backend's features and matches; a learned backend has none to reuse).
BACKENDS: dict[str, Callable[[ReconstructOptions, dict | None], Reconstructor]] = {
    "classical": _classical, "vggt": _vggt}
# ``auto``: VGGT when its weights are found, else the weight-free classical backend.
BACKEND_CHOICES = ("auto", *BACKENDS)
DEFAULT_BACKEND = "auto"


def resolve_backend_name(name: str, options: ReconstructOptions) -> str:
    """``auto`` -> ``vggt`` when VGGT weights can be found, else ``classical``."""
    if name != "auto":
        return name
    from pis3r.reconstruct.vggt.weights import find_weights

    return "vggt" if find_weights(options.weights) is not None else "classical"


def create_backend(name: str, options: ReconstructOptions | None = None, memo: dict | None = None) -> Reconstructor:
    """Build backend ``name`` (``auto`` resolved first) with ``options``; ``memo``: see
    :data:`BACKENDS`."""
    options = options or ReconstructOptions()
    name = resolve_backend_name(name, options)
    if name not in BACKENDS:
        raise InputError(f"unknown backend {name!r}; choose one of {', '.join(BACKEND_CHOICES)}")
    return BACKENDS[name](options, memo)
