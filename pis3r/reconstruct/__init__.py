"""Reconstruction backends: photos -> Scene."""

from pis3r.reconstruct.base import BACKEND_CHOICES, BACKENDS, Reconstructor, create_backend, resolve_backend_name
from pis3r.reconstruct.options import ReconstructOptions

__all__ = ["BACKENDS", "BACKEND_CHOICES", "Reconstructor", "ReconstructOptions", "create_backend", "resolve_backend_name"]
