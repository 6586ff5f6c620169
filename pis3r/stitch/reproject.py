"""Superseded by :mod:`pis3r.stitch.render`; ``pis3r/eval/apap.py`` still imports the canvas cap from here."""

from pis3r.stitch.render import DEFAULT_MAX_CANVAS_SCALE  # noqa: F401
