"""The Python API: every kind of input, and the README's example run as written."""

import re
from pathlib import Path

import numpy as np
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
