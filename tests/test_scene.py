"""The typed contract from a backend to the stitcher: Scene, View, DroppedView."""

from __future__ import annotations

import dataclasses
import pickle
import threading

import cv2
import numpy as np
import pytest

from pis3r.camera import Camera, intrinsics
from pis3r.scene import Deferred, DroppedView, Scene, View


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


def test_a_view_registered_to_another_view_lands_in_the_world_of_that_view():
    # World: camera a at R_a, t_a; camera c seen from a's frame at scale 1/2 of the world.
    R_a = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    anchor = Camera(np.diag([100.0, 100.0, 1.0]), R_a, np.array([0.3, -0.1, 0.2]), 8, 6)
    R_ca = cv2.Rodrigues(np.array([0.0, 0.3, 0.0]))[0]
    pair_view = dataclasses.replace(_view("c", t=(-0.5, 0.0, 0.1)),
                                    camera=Camera(anchor.K, R_ca, np.array([-0.5, 0.0, 0.1]), 8, 6))
    world = pair_view.rescaled(2.0).in_world_of(anchor)
    # A world point seen by c: its coordinates in a's frame (at the pair's scale) map to c's
    # pixel the same way before and after.
    X = np.array([0.4, 0.2, 5.0])
    in_anchor = R_a @ X + anchor.t  # world units, a's frame
    seen_from_pair = R_ca @ (in_anchor / 2.0) + pair_view.camera.t
    seen_in_world = world.camera.R @ X + world.camera.t
    assert np.allclose(seen_in_world, 2.0 * seen_from_pair)
    assert np.allclose(world.depth, 2.0 * pair_view.depth)
    # Anchored at the identity, it is a rescaling.
    same = pair_view.rescaled(3.0).in_world_of(Camera.identity(anchor.K, 8, 6))
    assert np.allclose(same.camera.t, pair_view.rescaled(3.0).camera.t) and np.allclose(same.camera.R, R_ca)


def test_a_deferred_depth_is_computed_once_at_its_first_read_and_pickles_as_its_value():
    calls = []

    def fill():
        calls.append(threading.get_ident())
        return np.full((6, 8), 2.0, np.float32), np.full((6, 8), 0.5, np.float32)

    filled = Deferred(fill)
    view = dataclasses.replace(_view("a"), depth=filled, confidence=filled)
    assert calls == [] and not filled.computed
    # Readers on several threads at once: one computes, all get its value.
    threads = [threading.Thread(target=lambda: view.confidence) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(calls) == 1 and filled.computed
    assert np.all(view.depth == 2.0) and np.all(view.confidence == 0.5) and len(calls) == 1
    assert np.allclose(view.rescaled(2.0).depth, 4.0) and np.allclose(view.world_points(), _view("a").world_points())
    copy = pickle.loads(pickle.dumps(view))
    assert np.all(copy.depth == 2.0) and np.all(copy.confidence == 0.5) and len(calls) == 1
    with pytest.raises(TypeError, match="depth"):
        View(np.zeros((6, 8, 3), np.float32), view.camera)  # still required fields
