"""Reconstruction backends: photos -> Scene."""

from pis3r.reconstruct.base import (
    Reconstructor,
    ReconstructOptions,
    backend_names,
    create_backend,
    register,
    resolve_backend_name,
    resolve_device,
)

__all__ = [
    "Reconstructor",
    "ReconstructOptions",
    "backend_names",
    "create_backend",
    "register",
    "resolve_backend_name",
    "resolve_device",
]
