"""One exception hierarchy for everything pis3r refuses to do.

The CLI prints ``str(error)`` on one line and exits with ``error.exit_code``;
library callers catch :class:`Pis3rError`.
"""


class Pis3rError(Exception):
    """Root of every error pis3r raises on purpose."""

    exit_code = 1


class InputError(Pis3rError):
    """An input image (or argument) cannot be used: unreadable, empty, too few..."""

    exit_code = 2


class InvalidOptionError(InputError):
    """An option of a stitch has a value outside its allowed choices or range."""


class NotEnoughOverlapError(InputError):
    """The images share too little of the scene to be registered."""


class ReconstructionError(Pis3rError):
    """Geometry could not be recovered from images that were otherwise fine."""

    exit_code = 3


class WeightsError(Pis3rError):
    """A model weight file is missing, corrupt or does not fit the model."""

    exit_code = 4


class OutputError(Pis3rError):
    """Results could not be written (unwritable directory, full disk...)."""

    exit_code = 5


def one_line(exc: BaseException, with_type: bool = False) -> str:
    """The first line of an exception's message (its class name when the message is empty),
    after ``ClassName: `` with ``with_type`` (for errors of libraries, whose type says most)."""
    text = str(exc).strip().splitlines()
    if not text:
        return exc.__class__.__name__
    return f"{exc.__class__.__name__}: {text[0].strip()}" if with_type else text[0].strip()
