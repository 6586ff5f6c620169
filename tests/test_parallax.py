"""pis3r.parallax: the level grows with the parallax, real pairs agree with their documented class."""

import pytest

from pis3r.eval.cases import class_from_text, parallax_labels_from_sources
from pis3r.io import read_image
from pis3r.parallax import ParallaxEstimate, classify_level, estimate_parallax
from pis3r.synth.cases import make_case
from tests.conftest import REAL, needs_real_data


def test_level_grows_with_parallax():
    levels = {kind: estimate_parallax(*(lambda c: (c.ref, c.tgt))(make_case(7, (480, 360), kind))).level
              for kind in ("rotation", "slight", "large")}
    assert levels["rotation"] < levels["slight"] < levels["large"]
    assert classify_level(levels["rotation"]) == "rotation"
    assert classify_level(levels["large"]) == "large"


def test_estimate_as_json_names_its_class_parallax_class():
    estimate = ParallaxEstimate("slight", 0.5, 0.7, 1.0, 2.0, 100, 90)
    assert list(estimate.to_dict())[:3] == ["parallax_class", "label", "level"]
    assert estimate.to_dict()["parallax_class"] == "slight" and estimate.to_dict()["label"] == "slight parallax"


@pytest.mark.slow
@needs_real_data
def test_real_pairs_agree_with_their_documented_class():
    """Clear-cut pairs of the uncalibrated table only: SOURCES.md marks borderline calls,
    which may go either way."""
    agree, total = 0, 0
    for name, label in parallax_labels_from_sources(REAL / "SOURCES.md").items():
        if "borderline" in label or "planar" in label:
            continue
        expected = class_from_text(label)
        pair = REAL / name
        if not list(pair.glob("ref.*")):
            continue
        est = estimate_parallax(read_image(next(pair.glob("ref.*"))).pixels, read_image(next(pair.glob("tgt.*"))).pixels)
        total += 1
        agree += est.parallax_class == expected
    assert total >= 10
    assert agree / total >= 0.8
