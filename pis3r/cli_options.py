"""Click options generated from :class:`pis3r.StitchOptions`: one definition of every
stitch option's flag, default, choices, range and help, for every command that has it."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import click

from pis3r.options import StitchOptions, flag


def click_option(name: str) -> Callable:
    """The click option for ``StitchOptions`` field ``name`` (``--max-canvas-scale`` for
    ``max_canvas_scale``), with the field's default, choices, range and help."""
    spec = StitchOptions.field(name)
    meta, default = spec.metadata, spec.default
    settings: dict[str, Any] = {"help": meta["help"], "default": default, "show_default": default is not None}
    if name == "ref":
        # An index or "all": StitchOptions parses it, with the same message as for the API.
        settings.update(type=str, metavar="INDEX|all")
    elif meta["choices"] is not None:
        settings["type"] = click.Choice(list(meta["choices"]))
    elif meta["kind"] is bool:
        settings.update(is_flag=True, show_default=False)
    elif meta["kind"] is Path:
        settings["type"] = click.Path(dir_okay=False, path_type=Path)
    elif meta["kind"] in (int, float):
        # The range is checked by StitchOptions itself (one message for every interface).
        settings["type"] = meta["kind"]
    return click.option(flag(name), name, **settings)


def click_options(*names: str) -> Callable:
    """Decorator adding the click options of ``names`` in that order."""

    def decorate(command: Callable) -> Callable:
        for name in reversed(names):
            command = click_option(name)(command)
        return command

    return decorate
