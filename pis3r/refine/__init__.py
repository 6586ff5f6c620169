"""Stage 4: the residual denoising diffusion refiner (RDDM, shared/specs/rddm.md).

This package's top level holds the stage's settings and imports no torch, so that the
options, the CLI's ``--help`` and a stitch that does not refine start without it. The
refiner itself: :func:`pis3r.refine.canvas.refine_canvas` (refine a stitched canvas).
"""

from __future__ import annotations

from pathlib import Path

# ``auto`` refines when the refiner's weights are installed. Off by default: the shipped
# CPU-trained refiner does not yet improve results (MODEL_CARD.md).
REFINE_METHODS = ("none", "rddm", "auto")
DEFAULT_REFINE = "none"
# Pixels the refiner may change (pis3r.refine.canvas), chosen by the refinement ablation
# (pis3r/refine/weights/MODEL_CARD.md).
REGIONS = ("holes", "all")
DEFAULT_REGION = "holes"
DEFAULT_STEPS = 5

SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "rddm.safetensors"


def default_weights_path() -> Path | None:
    """The refiner weights shipped inside the package, or ``None`` when they are absent."""
    return SHIPPED_WEIGHTS if SHIPPED_WEIGHTS.is_file() else None


def resolve_refine(method: str, weights) -> str:
    """``auto`` -> ``rddm`` when refiner weights are given or installed, else ``none``."""
    if method == "auto":
        return "rddm" if weights is not None or default_weights_path() is not None else "none"
    return method


__all__ = ["default_weights_path", "resolve_refine", "REFINE_METHODS", "DEFAULT_REFINE", "REGIONS",
           "DEFAULT_REGION", "DEFAULT_STEPS"]
