"""VGGT pose encoding, unprojection, re-anchoring and preprocessing, on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from PIL import Image

from pis3r.io import to_uint8
from pis3r.reconstruct.vggt.geometry import (
    closed_form_inverse_se3,
    relative_to_first,
    unproject_depth_map_to_point_map,
)
from pis3r.reconstruct.vggt.pose_encoding import (
    extri_intri_to_pose_encoding,
    mat_to_quat,
    pose_encoding_to_extri_intri,
    quat_to_mat,
)
from pis3r.reconstruct.vggt.preprocess import preprocess_images

S2 = math.sqrt(0.5)


def encoding(t, q, fov_h, fov_w) -> torch.Tensor:
    return torch.tensor([[[*t, *q, fov_h, fov_w]]], dtype=torch.float64)


# -- quaternions ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "quat, matrix",
    [
        ((0, 0, 0, 1), np.eye(3)),
        ((0, 0, 0, 3.5), np.eye(3)),  # non-unit: normalised implicitly
        ((0, 0, S2, S2), [[0, -1, 0], [1, 0, 0], [0, 0, 1]]),  # +90° about z
        ((S2, 0, 0, S2), [[1, 0, 0], [0, 0, -1], [0, 1, 0]]),  # +90° about x
        ((0, 2 * S2, 0, 2 * S2), [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),  # +90° about y, |q| = 2
        ((1, 0, 0, 0), [[1, 0, 0], [0, -1, 0], [0, 0, -1]]),  # 180° about x
    ],
)
def test_quaternion_xyzw_to_matrix(quat, matrix):
    R = quat_to_mat(torch.tensor(quat, dtype=torch.float64))
    np.testing.assert_allclose(R.numpy(), np.asarray(matrix, dtype=np.float64), atol=1e-12)


def test_matrix_to_quaternion_round_trip_and_sign():
    q = torch.randn(200, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    back = mat_to_quat(quat_to_mat(q))
    assert (back[:, 3] >= 0).all()
    torch.testing.assert_close(back, torch.where(q[:, 3:] < 0, -q, q), rtol=0, atol=1e-12)
    half_turn = mat_to_quat(torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)))
    torch.testing.assert_close(half_turn, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))


# -- pose encoding <-> matrices ------------------------------------------------------------


def test_identity_encoding_gives_identity_pose_and_centred_intrinsics():
    ext, K = pose_encoding_to_extri_intri(encoding((0, 0, 0), (0, 0, 0, 1), math.pi / 2, math.pi / 2), (300, 400))
    assert ext.shape == (1, 1, 3, 4) and K.shape == (1, 1, 3, 3)
    np.testing.assert_allclose(ext[0, 0].numpy(), np.eye(3, 4), atol=1e-12)
    np.testing.assert_allclose(K[0, 0].numpy(), [[200, 0, 200], [0, 150, 150], [0, 0, 1]], atol=1e-9)


def test_fov_to_focal_and_back():
    H, W = 294, 518
    fov_h, fov_w = 2 * math.atan(147 / 300.0), 2 * math.atan(259 / 250.0)
    ext, K = pose_encoding_to_extri_intri(encoding((1, -2, 3), (0, 0, S2, S2), fov_h, fov_w), (H, W))
    np.testing.assert_allclose([K[0, 0, 0, 0].item(), K[0, 0, 1, 1].item()], [250.0, 300.0], rtol=1e-12)
    np.testing.assert_allclose([K[0, 0, 0, 2].item(), K[0, 0, 1, 2].item()], [W / 2, H / 2])  # VGGT: W/2, not (W-1)/2
    np.testing.assert_allclose(ext[0, 0, :, 3].numpy(), [1, -2, 3])
    np.testing.assert_allclose(ext[0, 0, :, :3].numpy(), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    back = extri_intri_to_pose_encoding(ext, K, (H, W))
    torch.testing.assert_close(back, encoding((1, -2, 3), (0, 0, S2, S2), fov_h, fov_w), rtol=0, atol=1e-12)


def test_zero_fov_gives_infinite_focal():
    _, K = pose_encoding_to_extri_intri(encoding((0, 0, 0), (0, 0, 0, 1), 0.0, 1.0), (10, 10))
    assert math.isinf(K[0, 0, 1, 1].item()) and math.isfinite(K[0, 0, 0, 0].item())


# -- unprojection and re-anchoring -----------------------------------------------------------


def test_unproject_hand_case():
    depth = torch.full((1, 2, 3), 2.0, dtype=torch.float64)
    K = torch.tensor([[[2.0, 0, 1], [0, 4.0, 0.5], [0, 0, 1]]], dtype=torch.float64)
    ext = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]], dtype=torch.float64)
    pts = unproject_depth_map_to_point_map(depth, ext, K)
    assert pts.shape == (1, 2, 3, 3)
    np.testing.assert_allclose(pts[0, 0, 0].numpy(), [(0 - 1) * 2 / 2, (0 - 0.5) * 2 / 4, 2])
    np.testing.assert_allclose(pts[0, 1, 2].numpy(), [(2 - 1) * 2 / 2, (1 - 0.5) * 2 / 4, 2])
    # A camera rotated 90° about z and shifted: X_world = Rᵀ (X_cam - t).
    R = quat_to_mat(torch.tensor([0, 0, S2, S2], dtype=torch.float64))
    t = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    moved = unproject_depth_map_to_point_map(depth, torch.cat([R, t[:, None]], 1)[None], K)
    np.testing.assert_allclose(moved[0].numpy(), ((pts[0] - t) @ R).numpy(), atol=1e-12)


def test_closed_form_inverse_se3():
    R = quat_to_mat(torch.tensor([0.3, -0.2, 0.5, 0.8], dtype=torch.float64))
    T = torch.cat([R, torch.tensor([[1.0], [2.0], [3.0]], dtype=torch.float64)], 1)
    inv = closed_form_inverse_se3(T)
    full = torch.eye(4, dtype=torch.float64)
    full[:3] = T
    np.testing.assert_allclose(inv.numpy(), torch.linalg.inv(full)[:3].numpy(), atol=1e-12)


def test_relative_to_first_anchors_the_world_exactly_and_keeps_geometry():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(3, 4, generator=g, dtype=torch.float64)
    ext = torch.cat([quat_to_mat(q), torch.randn(3, 3, 1, generator=g, dtype=torch.float64)], -1)
    rel = relative_to_first(ext)
    assert torch.equal(rel[0], torch.eye(3, 4, dtype=torch.float64))
    depth = 1 + torch.rand(3, 4, 5, generator=g, dtype=torch.float64)
    K = torch.tensor([[10.0, 0, 2], [0, 10.0, 1.5], [0, 0, 1]], dtype=torch.float64).expand(3, 3, 3)
    world = unproject_depth_map_to_point_map(depth, ext, K)
    anchored = unproject_depth_map_to_point_map(depth, rel, K)
    R0, t0 = ext[0, :, :3], ext[0, :, 3]
    np.testing.assert_allclose(anchored.numpy(), (world @ R0.T + t0).numpy(), atol=1e-10)


# -- preprocessing ------------------------------------------------------------------------


def photo(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((h, w, 3), dtype=np.float32)


def test_crop_mode_sizes_and_pil_bicubic():
    pixels = photo(60, 80)
    batch, (p,) = preprocess_images([pixels], "crop")
    assert batch.shape == (1, 3, 392, 518) and batch.dtype == np.float32
    resized = Image.fromarray(to_uint8(pixels)).resize((518, 392), Image.Resampling.BICUBIC)
    expected = np.asarray(resized) / np.float32(255)
    np.testing.assert_array_equal(batch[0].transpose(1, 2, 0), expected.astype(np.float32))
    assert (p.offset_x, p.offset_y, p.box) == (0, 0, (0, 0, 517, 391))


def test_crop_mode_centre_crops_tall_photos():
    batch, (p,) = preprocess_images([photo(90, 70)], "crop")  # 518 x 672 -> central 518 rows
    assert batch.shape == (1, 3, 518, 518)
    assert p.offset_y == -77 and p.box == (0, 0, 517, 517)


def test_height_rounding_is_python_round_half_even():
    # 41 * 518 / 74 / 14 = 20.5 exactly: Python's round gives 20 (floor(x + 0.5) would give 21).
    batch, _ = preprocess_images([photo(41, 74)], "crop")
    assert batch.shape[-2:] == (280, 518)


def test_pad_mode_pads_white_and_mixed_sizes_are_centred():
    batch, (tall, wide) = preprocess_images([photo(90, 70), photo(60, 80)], "pad")
    assert batch.shape == (2, 3, 518, 518)
    # Portrait: 406 x 518 centred horizontally on white.
    assert (tall.offset_x, tall.offset_y, tall.box) == (56, 0, (56, 0, 461, 517))
    assert np.all(batch[0][:, :, :56] == 1.0) and np.all(batch[0][:, :, 462:] == 1.0)
    assert (wide.offset_x, wide.offset_y) == (0, 63)
    mixed, (a, b) = preprocess_images([photo(60, 80), photo(90, 70)], "crop")
    assert mixed.shape == (2, 3, 518, 518) and a.offset_y == 63 and b.offset_y == -77
    assert np.all(mixed[0][:, :63] == 1.0)


def test_placement_maps_cameras_and_maps_back_to_the_photo():
    _, (p,) = preprocess_images([photo(90, 70)], "crop")
    # A camera in model pixels and the same camera in photo pixels project consistently.
    K_model = np.array([[400.0, 0, 259], [0, 410.0, 259], [0, 0, 1]])
    K_photo = p.intrinsics_to_photo(K_model)
    X = np.array([[0.3, -0.2, 2.0], [-0.1, 0.4, 3.0]])
    uv_model = (X @ K_model.T)[:, :2] / X[:, 2:]
    uv_photo = (X @ K_photo.T)[:, :2] / X[:, 2:]
    mx, my = p.to_model(uv_photo[:, 0], uv_photo[:, 1])
    np.testing.assert_allclose(np.stack([mx, my], 1), uv_model, atol=1e-9)
    # A linear ramp in model pixels is a linear ramp on the photo; cropped rows are unseen.
    ys, xs = np.mgrid[0:518, 0:518].astype(np.float64)
    ramp = (2 * xs + 3 * ys).astype(np.float32)
    back, seen = p.to_photo(ramp)
    assert back.shape == (90, 70) and seen.shape == (90, 70)
    gx, gy = p.to_model(np.arange(70.0)[None, :], np.arange(90.0)[:, None])
    np.testing.assert_allclose(back[seen], (2 * gx + 3 * gy)[seen], rtol=1e-5)
    assert not seen[0].any() and not seen[-1].any() and seen[45].all()


def test_preprocess_rejects_bad_input():
    from pis3r.errors import InputError

    with pytest.raises(InputError):
        preprocess_images([], "crop")
    with pytest.raises(InputError):
        preprocess_images([photo(10, 10)], "stretch")
