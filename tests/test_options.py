"""StitchOptions is the one source of defaults and choices: every interface agrees with it."""

from __future__ import annotations

import dataclasses
import json
import math
import warnings

import click
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

import pis3r
from pis3r import InvalidOptionError, StitchOptions
from pis3r.cli import main
from pis3r.options import OPTION_NAMES, flag


def _click_params(command_name: str) -> dict[str, click.Parameter]:
    return {param.name: param for param in main.commands[command_name].params}


@pytest.mark.parametrize("command_name", ["stitch", "batch"])
def test_cli_defaults_and_choices_are_the_dataclass_ones(command_name):
    params = _click_params(command_name)
    names = [name for name in OPTION_NAMES if command_name == "stitch" or name != "ref"]
    assert set(names) <= set(params), set(names) - set(params)
    for name in names:
        param, spec = params[name], StitchOptions.field(name)
        assert param.opts == [flag(name)]
        assert param.default == spec.default, name
        choices = spec.metadata["choices"]
        if choices is not None:
            assert tuple(param.type.choices) == choices, name
        assert param.help == spec.metadata["help"]


def test_web_form_offers_the_dataclass_choices():
    from fastapi.testclient import TestClient

    from pis3r.web.app import FORM_OPTIONS, create_app

    with TestClient(create_app()) as client:
        offered = client.get("/api/options").json()
    assert set(offered) == set(FORM_OPTIONS)
    for name, option in offered.items():
        assert option["default"] == StitchOptions.default(name)
        assert tuple(option["choices"]) == StitchOptions.choices(name)


def test_defaults_come_from_the_stage_modules():
    from pis3r.stitch.blend import DEFAULT_BLEND
    from pis3r.stitch.holes import DEFAULT_HOLE_RADIUS
    from pis3r.stitch.render import DEFAULT_MAX_CANVAS_SCALE

    options = StitchOptions()
    assert (options.max_canvas_scale, options.hole_radius, options.blend) == (
        DEFAULT_MAX_CANVAS_SCALE, DEFAULT_HOLE_RADIUS, DEFAULT_BLEND)
    assert dataclasses.is_dataclass(options) and options.__dataclass_params__.frozen


@pytest.mark.parametrize("changes, message", [
    ({"focal": -500}, "--focal must be a number > 0"),
    ({"focal": math.nan}, "--focal must be a number"),
    ({"focal": "wide"}, "--focal must be a number"),
    ({"max_canvas_scale": 0.5}, "--max-canvas-scale must be a number in 1..10"),
    ({"conf_threshold": 1.5}, "--conf-threshold must be a number in 0..1"),
    ({"hole_radius": 2.5}, "--hole-radius must be an integer"),
    ({"refine_steps": 0}, "--refine-steps must be a number in 1..100"),
    ({"blend": "smear"}, "--blend must be one of none, feather, multiband"),
    ({"backend": "dust3r"}, "--backend must be one of auto, classical, vggt"),
    ({"ref": -1}, "--ref must be an image index"),
    ({"ref": "first"}, "--ref must be an image index"),
    ({"blend_into_reference": "yes"}, "--blend-into-reference must be true or false"),
])
def test_bad_values_are_one_line_errors(changes, message):
    with pytest.raises(InvalidOptionError, match=message) as error:
        StitchOptions(**changes)
    assert "\n" not in str(error.value)


def test_replace_validates_and_refuses_unknown_names():
    options = StitchOptions().replace(blend="none", ref="2")
    assert (options.blend, options.ref) == ("none", 2)
    with pytest.raises(InvalidOptionError, match="unknown stitch option: colour"):
        options.replace(colour="red")
    with pytest.raises(InvalidOptionError, match="--focal"):
        options.replace(focal=0)


def test_stitch_takes_options_and_overrides(small_pair):
    with pytest.raises(InvalidOptionError, match="--focal"):
        pis3r.stitch(list(small_pair), focal=-500)
    with pytest.raises(InvalidOptionError, match="unknown stitch option"):
        pis3r.stitch(list(small_pair), StitchOptions(), not_an_option=1)


def test_cli_rejects_a_negative_focal_in_one_line(small_pair, tmp_path):
    paths = []
    for index, image in enumerate(small_pair):
        paths.append(tmp_path / f"{index}.png")
        Image.fromarray(image).save(paths[-1])
    result = CliRunner().invoke(main, ["stitch", *map(str, paths), "-o", str(tmp_path / "out"), "--focal", "-500"])
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines() == ["pis3r: error: --focal must be a number > 0, got -500.0"]
    assert not (tmp_path / "out").exists()


def test_library_warnings_become_report_lines_not_raw_output(small_pair, tmp_path, monkeypatch, capfd):
    """A warning raised inside a stage (here: numpy's, from a patched stage) and Pillow's
    decompression-bomb check reach neither stderr as Python's two-line form nor the caller."""
    from pis3r import api

    fill_holes = api.fill_holes

    def noisy_fill_holes(*args, **kwargs):
        np.float32(1.0) / np.float32(0.0)
        return fill_holes(*args, **kwargs)

    monkeypatch.setattr(api, "fill_holes", noisy_fill_holes)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 20_000)  # warns at 190x160, errors only at 2x
    paths = []
    for index, image in enumerate(small_pair):
        paths.append(tmp_path / f"{index}.png")
        Image.fromarray(image).save(paths[-1])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = pis3r.stitch([str(p) for p in paths], backend="classical", quiet=False)
    stderr = capfd.readouterr().err
    assert "RuntimeWarning: divide by zero" in " ".join(result.report["warnings"])
    assert "DecompressionBomb" not in stderr and "warnings.warn" not in stderr and ".py:" not in stderr
    assert "[pis3r] warning: RuntimeWarning: divide by zero" in stderr
    report = tmp_path / "out" / "report.json"
    result.save(report.parent)
    assert json.loads(report.read_text())["warnings"] == result.report["warnings"]


def test_cli_turns_any_python_warning_into_one_line(monkeypatch):
    from pis3r import cli

    @cli.main.command("warn-once", hidden=True)
    def warn_once():
        warnings.warn("something odd", UserWarning)

    try:
        result = CliRunner().invoke(main, ["warn-once"])
    finally:
        cli.main.commands.pop("warn-once")
    assert result.exit_code == 0
    assert result.stderr.splitlines() == ["pis3r: warning: UserWarning: something odd"]


def test_a_warning_during_a_stage_gets_its_own_line(capsys):
    from pis3r.progress import StageTimer, WarningLog

    timer = StageTimer()
    log = WarningLog(timer)
    with timer.stage("read images"):
        log.add("a.jpg: downscaled")
        log.add("a.jpg: downscaled")
    with timer.stage("blend"):
        pass
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "[pis3r] read images ..."
    assert lines[1] == "[pis3r] warning: a.jpg: downscaled"
    assert lines[2].startswith("[pis3r] read images done ") and lines[3].startswith("[pis3r] blend ... ")
    assert len(lines) == 4 and log.lines == ["a.jpg: downscaled"]
