"""pis3r: stitch photos taken from different positions into one true perspective image.

The one entry point is :func:`pis3r.stitch`; its options are :class:`pis3r.StitchOptions`.
See their docstrings, or ``pis3r --help``.
"""

__version__ = "0.1.0"

from pis3r.api import stitch  # noqa: E402
from pis3r.errors import InvalidOptionError, Pis3rError  # noqa: E402
from pis3r.options import StitchOptions  # noqa: E402
from pis3r.result import StitchResult  # noqa: E402

__all__ = ["stitch", "StitchOptions", "StitchResult", "Pis3rError", "InvalidOptionError", "__version__"]
