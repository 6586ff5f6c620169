"""Stage 4: the residual denoising diffusion refiner (RDDM, shared/specs/rddm.md).

Public: :func:`refine_canvas` (refine a stitched canvas), :func:`default_weights_path`
(the weights shipped in ``pis3r/refine/weights/``, or ``None``).
"""

from pis3r.refine.canvas import refine_canvas
from pis3r.refine.model import default_weights_path

# ``auto`` refines when the refiner's weights are installed. Off by default: the shipped
# CPU-trained refiner does not yet improve results (MODEL_CARD.md).
REFINE_METHODS = ("none", "rddm", "auto")
DEFAULT_REFINE = "none"


def resolve_refine(method: str, weights) -> str:
    """``auto`` -> ``rddm`` when refiner weights are given or installed, else ``none``."""
    if method == "auto":
        return "rddm" if weights is not None or default_weights_path() is not None else "none"
    return method


__all__ = ["refine_canvas", "default_weights_path", "resolve_refine", "REFINE_METHODS", "DEFAULT_REFINE"]
