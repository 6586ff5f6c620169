"""COLMAP text export read back by pycolmap, and points.ply read back by a strict PLY parser."""

import json

import numpy as np
import pycolmap

from pis3r.colmap import colmap_quaternion, colmap_text_files


def test_quaternion_is_colmap_order_with_positive_w():
    angle = np.deg2rad(30.0)
    R = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    np.testing.assert_allclose(colmap_quaternion(R), [np.cos(angle / 2), np.sin(angle / 2), 0, 0], atol=1e-12)
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(20, random_state=0).as_matrix():
        q = colmap_quaternion(R)
        assert q[0] >= 0
        np.testing.assert_allclose(Rotation.from_quat([*q[1:], q[0]]).as_matrix(), R, atol=1e-12)


def test_pycolmap_reads_cameras_poses_and_points(small_result, tmp_path):
    for name, data in colmap_text_files(small_result.scene, small_result.camera, max_points=500).items():
        (tmp_path / name).write_bytes(data)
    model = pycolmap.Reconstruction(str(tmp_path))
    cameras = [view.camera for view in small_result.scene.views] + [small_result.camera]
    assert model.num_cameras() == model.num_images() == len(cameras)
    assert model.num_points3D() == 500
    for index, expected in enumerate(cameras, start=1):
        camera = model.cameras[index]
        assert (camera.width, camera.height) == (expected.width, expected.height)
        K = expected.K.copy()
        K[:2, 2] += 0.5  # COLMAP's pixel centres are at +0.5
        np.testing.assert_allclose(camera.calibration_matrix(), K, atol=1e-9)
        image = model.images[index]
        assert image.camera_id == index
        pose = image.cam_from_world()
        np.testing.assert_allclose(pose.rotation.matrix(), expected.R, atol=1e-9)
        np.testing.assert_allclose(pose.translation, expected.t, atol=1e-9)
    assert model.images[len(cameras)].name == "stitched.png"
    # The points are a subset of the reconstruction, colours included.
    points, _ = small_result.point_cloud()
    sample = np.array([p.xyz for p in model.points3D.values()])
    lo, hi = points.min(axis=0), points.max(axis=0)
    assert np.all((sample >= lo - 1e-4) & (sample <= hi + 1e-4))


def test_cli_writes_colmap_and_a_strictly_valid_ply(small_pair, tmp_path):
    from click.testing import CliRunner
    from PIL import Image

    from pis3r.cli import main

    paths = []
    for index, array in enumerate(small_pair):
        paths.append(str(tmp_path / f"view {index}.png"))
        Image.fromarray(array).save(paths[-1])
    out = tmp_path / "out"
    run = CliRunner().invoke(main, ["stitch", *paths, "-o", str(out), "--ply", "--mesh", "--colmap",
                                    str(out / "sparse"), "--quiet", "--backend", "classical"])
    assert run.exit_code == 0, run.output
    model = pycolmap.Reconstruction(str(out / "sparse"))
    assert sorted(image.name for image in model.images.values()) == ["stitched.png", "view_0.png", "view_1.png"]
    points, colors = read_ply_strict(out / "points.ply")
    assert len(points) > 1000 and colors.shape == points.shape and np.isfinite(points).all()
    assert colors.std() > 3
    assert model.num_points3D() == min(len(points), 100_000)
    from tests.test_render import read_mesh_ply_strict

    vertices, rgb, faces = read_mesh_ply_strict((out / "mesh.ply").read_bytes())
    assert len(faces) > 1000 and faces.max() < len(vertices) and np.isfinite(vertices).all()
    report = json.loads((out / "report.json").read_text())
    assert [s["view"] for s in report["surfaces"]] and all(s["rendered"] > 0 for s in report["surfaces"])
    # Every rendered view says how its colours were brought to the reference's.
    assert [e["view"] for e in report["exposures"]] == [s["view"] for s in report["surfaces"]]
    assert all(0.5 <= g <= 2.0 for e in report["exposures"] for g in e["gain"])


def read_ply_strict(path):
    """Parse a binary little-endian xyz+rgb PLY, failing on anything that deviates from
    the format (Open3D is not a dependency: it weighs about 1 GB with what it pulls in)."""
    data = path.read_bytes()
    header, _, body = data.partition(b"end_header\n")
    lines = header.decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    assert lines[2].startswith("element vertex ")
    count = int(lines[2].split()[2])
    assert lines[3:] == [
        "property float x", "property float y", "property float z",
        "property uchar red", "property uchar green", "property uchar blue",
    ]
    record = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    assert len(body) == count * record.itemsize
    table = np.frombuffer(body, record)
    return (np.stack([table["x"], table["y"], table["z"]], 1),
            np.stack([table["r"], table["g"], table["b"]], 1).astype(float))
