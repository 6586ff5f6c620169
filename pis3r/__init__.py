"""pis3r: stitch photos taken from different positions into one true perspective image.

The one entry point is :func:`pis3r.stitch`; see its docstring, or ``pis3r --help``.
"""

__version__ = "0.1.0"

from pis3r.api import StitchResult, stitch  # noqa: E402
from pis3r.errors import Pis3rError  # noqa: E402

__all__ = ["stitch", "StitchResult", "Pis3rError", "__version__"]
