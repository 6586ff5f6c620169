"""pis3r.parallax: the level grows with the parallax, real pairs agree with their documented class."""

import pytest

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


def _sources_classes():
    classes = {}
    for line in (REAL / "SOURCES.md").read_text().splitlines():
        cells = [c.strip() for c in line.split("|")]
        if len(cells) > 7 and list((REAL / cells[1]).glob("ref.*")):
            classes[cells[1]] = cells[6]
    return classes


def test_estimate_as_json_names_its_class_parallax_class():
    estimate = ParallaxEstimate("slight", 0.5, 0.7, 1.0, 2.0, 100, 90)
    assert list(estimate.to_dict())[:3] == ["parallax_class", "label", "level"]
    assert estimate.to_dict()["parallax_class"] == "slight" and estimate.to_dict()["label"] == "slight parallax"


@pytest.mark.slow
@needs_real_data
def test_real_pairs_agree_with_their_documented_class():
    """Clear-cut pairs only: SOURCES.md marks borderline calls, which may go either way."""
    agree, total = 0, 0
    for name, label in _sources_classes().items():
        if "borderline" in label or "planar" in label:
            continue
        expected = "rotation" if label.startswith("pure rotation") else "slight" if label.startswith("slight") else "large"
        pair = REAL / name
        est = estimate_parallax(read_image(next(pair.glob("ref.*"))).pixels, read_image(next(pair.glob("tgt.*"))).pixels)
        total += 1
        agree += est.parallax_class == expected
    assert total >= 10
    assert agree / total >= 0.8
