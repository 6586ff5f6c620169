"""Stage 4: the residual denoising diffusion refiner (RDDM, shared/specs/rddm.md).

Public: :func:`refine_canvas` (refine a stitched canvas), :func:`default_weights_path`
(the weights shipped in ``pis3r/refine/weights/``, or ``None``).
"""

from pis3r.refine.canvas import refine_canvas
from pis3r.refine.model import default_weights_path

__all__ = ["refine_canvas", "default_weights_path"]
