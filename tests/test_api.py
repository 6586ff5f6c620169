"""The Python API: every kind of input, and the README's example run as written."""

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import pis3r

README = Path(__file__).resolve().parents[1] / "README.md"


def test_paths_arrays_and_pil_images_give_the_same_result(small_pair, small_result, tmp_path):
    paths = []
    for index, array in enumerate(small_pair):
        paths.append(tmp_path / f"{index}.png")
        Image.fromarray(array).save(paths[-1])
    from_paths = pis3r.stitch(paths, backend="classical")
    from_pil = pis3r.stitch([Image.open(p) for p in paths], backend="classical")
    for result in (from_paths, from_pil):
        assert result.ref_offset == small_result.ref_offset
        np.testing.assert_array_equal(result.image, small_result.image)
        np.testing.assert_array_equal(result.mask, small_result.mask)
    assert [v.name for v in from_paths.scene.views] == ["0.png", "1.png"]
    h, w = small_pair[0].shape[:2]
    x, y = small_result.ref_offset
    np.testing.assert_array_equal(pis3r.io.to_uint8(small_result.image[y:y + h, x:x + w]), small_pair[0])


def test_readme_python_example_runs(tmp_path, monkeypatch):
    section = README.read_text().split("## Use from Python", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})
    out = tmp_path / "out" / "python"
    assert {p.name for p in out.iterdir()} >= {"stitched.png", "mask.png", "camera.json", "report.json", "points.ply"}
    assert {p.name for p in (out / "sparse").iterdir()} == {"cameras.txt", "images.txt", "points3D.txt"}


def test_an_image_that_cannot_be_registered_is_dropped_with_its_reason(small_pair):
    crops = small_pair
    unrelated = np.random.default_rng(0).integers(0, 255, (160, 190, 3), dtype=np.uint8)
    results = pis3r.stitch([crops[0], unrelated, crops[1]], ref="all", backend="classical")
    assert [r.ref_index for r in results] == [0, 2]
    report = results[0].report
    assert [d["index"] for d in report["dropped"]] == [1]
    assert "do not overlap enough" in report["dropped"][0]["reason"]
    assert any("dropped image 1" in w for w in report["warnings"])
    assert [c["index"] for c in results[0].camera_json()["inputs"]] == [0, 2]


def test_a_set_s_stitch_says_how_each_photo_was_placed(small_pair, capsys):
    unrelated = np.random.default_rng(0).integers(0, 255, (160, 190, 3), dtype=np.uint8)
    result = pis3r.stitch([small_pair[1], unrelated, small_pair[0]], ref=2, backend="classical", quiet=False)
    lines = [line for line in capsys.readouterr().err.splitlines() if "photo " in line and " of 3 " in line]
    inliers = result.scene.views[0].pose_confidence.inliers
    assert lines[0] == (f"[pis3r] photo 1 of 3 (image_0): placed on {inliers} matches, rotation within "
                        f"{result.scene.views[0].pose_confidence.uncertainty_deg:.1f} deg")
    assert lines[1] == "[pis3r] photo 3 of 3 (image_2): the reference"
    assert len(lines) == 2  # the unrelated photo is dropped, with its warning
    assert any("dropped image 1" in w for w in result.report["warnings"])


def test_large_inputs_are_downscaled_and_the_report_says_so(small_pair, monkeypatch):
    from pis3r import api

    monkeypatch.setattr(api, "MAX_INPUT_PIXELS", 20_000)
    result = pis3r.stitch(list(small_pair), backend="classical")
    assert any("downscaled" in w for w in result.report["warnings"])
    view = result.scene.views[0].image
    assert view.shape[0] * view.shape[1] <= 20_000


def test_of_several_unreadable_inputs_the_first_in_input_order_is_reported(small_pair, tmp_path):
    # The photos are decoded two at a time; the empty file fails first, but it comes second.
    good, corrupt, empty = tmp_path / "good.png", tmp_path / "corrupt.jpg", tmp_path / "empty.jpg"
    Image.fromarray(small_pair[0]).save(good)
    corrupt.write_bytes(b"\xff\xd8 not a JPEG" * 1000)
    empty.write_bytes(b"")
    with pytest.raises(pis3r.Pis3rError, match="corrupt.jpg"):
        pis3r.stitch([good, corrupt, empty], backend="classical")


def test_reference_index_and_report(small_pair):
    result = pis3r.stitch(list(small_pair), ref=1, backend="classical", blend="none")
    assert result.ref_index == 1
    ox, oy = result.ref_offset
    h, w = small_pair[1].shape[:2]
    np.testing.assert_allclose(result.image[oy:oy + h, ox:ox + w], small_pair[1] / 255.0, atol=1e-6)
    assert result.report["parallax"]["parallax_class"] == "rotation"
    assert result.report["model"] == "homography"
    assert sum(result.report["fractions"].values()) == pytest.approx(1.0, abs=1e-3)


def test_bad_reference_index(small_pair):
    from pis3r.errors import InputError

    with pytest.raises(InputError):
        pis3r.stitch(list(small_pair), ref=5)


def test_the_reference_s_partners_come_nearest_in_input_order_first():
    """A turn's middle photo as the reference meets its neighbours first, not input 0 from the
    far side of the turn (the band test and the first focal come from its first partner)."""
    from pis3r.api import reference_first

    assert reference_first(5, 0) == [0, 1, 2, 3, 4]
    assert reference_first(6, 3) == [3, 2, 4, 1, 5, 0]
    assert reference_first(3, 1) == [1, 0, 2]
    assert reference_first(3, "all") == [0, 1, 2]
