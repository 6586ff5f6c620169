"""The typed contract from a backend to the stitcher: Scene, View, DroppedView."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pis3r.camera import Camera, intrinsics
from pis3r.scene import DroppedView, Scene, View


def _view(name: str, t=(0.0, 0.0, 0.0)) -> View:
    camera = Camera(intrinsics(50.0, 8, 6), np.eye(3), np.asarray(t, float), 8, 6)
    depth = np.full((6, 8), 2.0, np.float32)
    return View(np.zeros((6, 8, 3), np.float32), camera, depth, np.ones((6, 8), np.float32), name)


def test_in_input_order_renumbers_views_and_dropped_without_touching_the_original():
    # The backend saw inputs in the order [2, 0, 3, 1] (reference 2 first) and dropped its 3rd photo.
    scene = Scene((_view("c"), _view("a"), _view("b")), indices=(0, 1, 3), dropped=(DroppedView(2, "d", "no overlap"),))
    ordered = scene.in_input_order([2, 0, 3, 1])
    assert [v.name for v in ordered.views] == ["a", "b", "c"] and ordered.indices == (0, 1, 2)
    assert ordered.dropped == (DroppedView(3, "d", "no overlap"),)
    assert ordered.position(2) == 2 and ordered.views[ordered.position(2)].name == "c"
    assert scene.indices == (0, 1, 3) and [v.name for v in scene.views] == ["c", "a", "b"]


def test_contracts_are_immutable_and_rescaling_makes_a_new_view():
    view = _view("a", t=(1.0, 0.0, 0.0))
    with pytest.raises(dataclasses.FrozenInstanceError):
        view.depth = view.depth * 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        Scene((view,)).views = ()
    scaled = view.rescaled(3.0)
    assert np.allclose(scaled.camera.t, [3.0, 0.0, 0.0]) and np.allclose(scaled.depth, 6.0)
    assert np.allclose(view.camera.t, [1.0, 0.0, 0.0]) and np.allclose(view.depth, 2.0)
    # The whole world scales: every point of the view moves to 3x its position.
    assert np.allclose(scaled.world_points(), 3.0 * view.world_points(), atol=1e-5)


def test_indices_must_match_the_views():
    with pytest.raises(ValueError, match="2 views but 1 indices"):
        Scene((_view("a"), _view("b")), indices=(0,))
    assert Scene((_view("a"), _view("b"))).indices == (0, 1)
