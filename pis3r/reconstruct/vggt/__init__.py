"""The project's own VGGT (facebook/VGGT-1B, checkpoint-exact) and its reconstruction backend.

This package offers :func:`find_weights`, :func:`fetch_weights` and :func:`load_vggt`;
the model class :class:`VGGT` is imported on first use (the backend is
:class:`pis3r.reconstruct.vggt.backend.VGGTBackend`).
"""

from __future__ import annotations

from pis3r.reconstruct.vggt.weights import WEIGHTS_ENV, fetch_weights, find_weights, load_vggt

__all__ = ["VGGT", "WEIGHTS_ENV", "fetch_weights", "find_weights", "load_vggt"]


def __getattr__(name: str):
    if name == "VGGT":
        from pis3r.reconstruct.vggt.model import VGGT

        return VGGT
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
