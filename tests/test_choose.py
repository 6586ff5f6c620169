"""Model choice by a held-back band of the reference (pis3r.stitch.choose)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import pis3r
from pis3r.features import Matches
from pis3r.io import Photo
from pis3r.reconstruct.matching import ConsistentMatches
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.stitch.choose import BAND_HANDICAP_DB, BandScore, Candidate, band_psnr, best_score, candidates, choose_model


def test_band_psnr_rewards_right_pixels_and_charges_uncovered_ones_a_mean_guess():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 1, (20, 30, 3)).astype(np.float32)
    band = np.zeros((20, 30), bool)
    band[:, :6] = True
    everywhere = np.ones((20, 30), bool)
    assert band_psnr(truth, everywhere, truth, band) == pytest.approx(100.0)
    nothing = band_psnr(np.zeros_like(truth), ~everywhere, truth, band)
    assert nothing == pytest.approx(10 * math.log10(1 / truth[band].var(axis=0).mean()), rel=1e-5)
    wrong = band_psnr(1.0 - truth, everywhere, truth, band)
    assert wrong < nothing < 100.0
    half = everywhere.copy()
    half[:10] = False
    assert nothing < band_psnr(truth, half, truth, band) < 100.0


def test_candidates_follow_the_model_and_depth_fill_choices():
    assert candidates("band", "auto") == [Candidate("homography"), Candidate("apap"), Candidate("3d", "planar"),
                                          Candidate("3d", "harmonic"), Candidate("3d", "planes"),
                                          Candidate("3d", "planar", "prior"), Candidate("3d", "harmonic", "prior"),
                                          Candidate("3d", "planes", "prior")]
    # The default: the backend's own explanation first (it wins a tie), then one homography
    # and APAP's local homographies.
    assert candidates("auto", "planar") == [Candidate("auto"), Candidate("homography"), Candidate("apap")]
    assert candidates("auto", "auto") == [Candidate("auto", "planar"), Candidate("auto", "harmonic"),
                                          Candidate("auto", "planes"), Candidate("homography"), Candidate("apap")]
    assert candidates("3d", "auto") == [Candidate("3d", "planar"), Candidate("3d", "harmonic"),
                                        Candidate("3d", "planes")]
    assert candidates("band", "harmonic") == [Candidate("homography"), Candidate("apap"), Candidate("3d", "harmonic"),
                                              Candidate("3d", "harmonic", "prior")]
    assert candidates("homography", "planar") == [Candidate("homography")]
    assert candidates("apap", "auto") == [Candidate("apap")]


def test_nothing_to_choose_runs_no_band_test():
    photos = [Photo(np.zeros((8, 8, 3), np.float32), "a"), Photo(np.zeros((8, 8, 3), np.float32), "b")]
    forced = choose_model(photos, "classical", ReconstructOptions(), model="homography")
    assert forced.chosen == Candidate("homography") and forced.scores == ()
    assert choose_model(photos, "vggt", ReconstructOptions(), model="band").chosen is None
    assert choose_model(photos, "vggt", ReconstructOptions(), model="auto").scores == ()


def test_when_no_candidate_can_stitch_the_band_the_backend_decides():
    blank = [Photo(np.zeros((64, 64, 3), np.float32), "a"), Photo(np.zeros((64, 64, 3), np.float32), "b")]
    choice = choose_model(blank, "classical", ReconstructOptions(), model="auto")
    assert choice.chosen is None and len(choice.scores) == 3
    assert all(score.psnr == -math.inf and score.error for score in choice.scores)


@pytest.mark.parametrize("model, labels", [
    ("band", ["homography", "apap", "3d/planar", "3d/harmonic", "3d/planes", "3d/planar/prior",
              "3d/harmonic/prior", "3d/planes/prior"]),
    ("auto", ["auto/planar", "auto/harmonic", "auto/planes", "homography", "apap"]),
])
def test_the_best_band_score_makes_the_stitch_and_the_report_lists_every_candidate(small_pair, model, labels):
    # Two crops of one photo: the target is exactly a shift of the reference's image plane.
    result = pis3r.stitch(list(small_pair), backend="classical", model=model, depth_fill="auto")
    choice = result.report["model_choice"]
    assert [Candidate(c["model"], c["depth_fill"], c["focal_rule"]).label for c in choice["candidates"]] == labels
    scores = [c["band_psnr"] if c["band_psnr"] is not None else -math.inf for c in choice["candidates"]]
    handicapped = [score - BAND_HANDICAP_DB.get(c["model"], 0.0) for c, score in zip(choice["candidates"], scores)]
    best = choice["candidates"][int(np.argmax(handicapped))]
    if best["model"] == "auto":
        # The backend's own test stands for the model it made on the band: that one stitches.
        assert choice["chosen"]["model"] in ("homography", "3d")
    else:
        # The report rounds the scores: candidates that tie there may be either.
        tied = [c for c, score in zip(choice["candidates"], handicapped) if score == max(handicapped)]
        assert choice["chosen"] in [{key: c[key] for key in ("model", "depth_fill", "focal_rule")} for c in tied]
    assert result.report["model"] == choice["chosen"]["model"]
    # A shift of the image plane is a homography: it predicts the band nearly exactly, within
    # 1 dB of the best 3-D candidate (the dominant-plane fill reconstructs that plane too).
    homography = scores[labels.index("homography")]
    assert homography >= max(scores) - 1.0 and homography > 25


def test_the_backends_homography_stands_for_the_forced_one(small_pair, monkeypatch):
    """A shift of the image plane: the backend's own test picks the homography model too, so
    one band render stands for both and they score the same. The warps are reconstructed
    first (their bands render while a 3-D scene would be built)."""
    from pis3r.stitch import choose

    reconstructed, rendered = [], []
    band_scene, render_band = choose._band_scene, choose._render_band
    monkeypatch.setattr(choose, "_band_scene", lambda candidate, *args: reconstructed.append(candidate) or
                        band_scene(candidate, *args))
    monkeypatch.setattr(choose, "_render_band", lambda scene, *args: rendered.append(scene.model) or
                        render_band(scene, *args))
    photos = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip(small_pair, "ab")]
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto")
    assert reconstructed == [Candidate("homography"), Candidate("apap"), Candidate("auto")]
    assert rendered == ["homography", "apap"]
    assert [score.candidate for score in choice.scores] == [Candidate("auto"), Candidate("homography"),
                                                            Candidate("apap")]
    # The backend's test made a homography on the band: that, not the test, makes the stitch.
    assert choice.scores[0].psnr == choice.scores[1].psnr and choice.chosen == Candidate("homography")


def test_the_band_test_reads_the_reference_and_the_next_photo_only(small_pair, monkeypatch):
    """The model is chosen once per stitch: its cost must not grow with the number of photos."""
    from pis3r.reconstruct.classical import ClassicalReconstructor

    seen = []
    original = ClassicalReconstructor.reconstruct
    monkeypatch.setattr(ClassicalReconstructor, "reconstruct",
                        lambda self, photos: seen.append(len(photos)) or original(self, photos))
    photos = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip(small_pair * 2, "abcd")]
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto")
    assert len(choice.scores) == 3 and set(seen) == {2}


def test_the_band_matches_its_copies_as_the_whole_photos_are_and_the_stitch_reuses_them(small_pair, monkeypatch):
    """The band's small copies find fewer SIFT inliers than the photos: left to themselves
    they would retry with ASIFT and test a pair matched unlike the stitch. The photos' own
    features and matches, found for that, are the stitch's: each photo is detected once."""
    from pis3r.reconstruct import classical, matching

    detected, band_detectors = [], []
    original_detect, original_reconstruct = matching.detect, classical.ClassicalReconstructor.reconstruct
    monkeypatch.setattr(matching, "detect", lambda image: detected.append(image.shape[:2]) or original_detect(image))
    photos = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip(small_pair, "ab")]

    def reconstruct(self, found):
        # The band's reconstructions (of its copies; the whole photos are reconstructed beside them).
        if found[0] is not photos[0]:
            band_detectors.append(self.options.detector)
        return original_reconstruct(self, found)

    monkeypatch.setattr(classical.ClassicalReconstructor, "reconstruct", reconstruct)
    whole = classical.ClassicalReconstructor(ReconstructOptions()).matched_with(*photos).detector
    detected.clear()
    memo = {}
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto", memo=memo)
    assert choice.detector == whole and set(band_detectors) == {whole}
    assert choice.to_dict()["detector"] == whole
    band_count = len(detected) - 2
    classical.ClassicalReconstructor(ReconstructOptions(), memo).reconstruct(photos)
    assert len(detected) == band_count + 2 and band_count == 2


def test_the_band_turns_its_copies_upright_as_the_whole_photos_were(small_pair, monkeypatch):
    """Where the whole photos' winning matches are ALIKED's on the other photo turned upright,
    the band's copies (the same two cameras) are matched by ALIKED turned by as much."""
    from pis3r.reconstruct import classical

    seen = []
    original_reconstruct = classical.ClassicalReconstructor.reconstruct
    aliked = ConsistentMatches(Matches(np.zeros((0, 2)), np.zeros((0, 2))), np.zeros(0, bool), "ALIKED", turn_deg=25.0)
    monkeypatch.setattr(classical.ClassicalReconstructor, "matched_with", lambda self, ref, other: aliked)
    monkeypatch.setattr(classical.ClassicalReconstructor, "reconstruct", lambda self, found: seen.append(
        (self.options.detector, self.options.turn_deg)) or original_reconstruct(self, found))
    photos = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip(small_pair, "ab")]
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto")
    assert choice.detector == "ALIKED" and set(seen) == {("ALIKED", 25.0)}


def test_the_backends_3d_explanation_is_reconstructed_during_the_band_test_and_used_when_it_wins(small_pair,
                                                                                                 monkeypatch):
    """With the default model the whole photos are reconstructed in the backend's 3-D form
    while the band is tested: when that candidate wins, the stitch takes that scene, the one
    it would have reconstructed after the test; when a warp wins, the stitch reconstructs."""
    from pis3r.reconstruct.classical import ClassicalReconstructor
    from pis3r.stitch import choose
    from tests.analytic import planes_scene, render, two_view_cameras

    pair = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip(small_pair, "ab")]
    warp = choose_model(pair, "classical", ReconstructOptions(), model="auto", memo={})
    assert warp.chosen == Candidate("homography") and warp.scene is None
    # Two planes seen from two places: the backend's own explanation is 3-D on the band; it wins.
    images = [render(planes_scene(), camera)[0] for camera in two_view_cameras()]
    photos = [Photo(image, name) for image, name in zip(images, "ab")]
    monkeypatch.setattr(choose, "best_score", lambda scores: 0)
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto", memo={})
    assert choice.chosen == Candidate("3d") and choice.scene is not None
    memo = {}
    ClassicalReconstructor(ReconstructOptions(), memo).matched_with(*photos)
    after = ClassicalReconstructor(Candidate("3d").backend_options(ReconstructOptions()), memo).reconstruct(photos)
    for view, expected in zip(choice.scene.views, after.views):
        np.testing.assert_array_equal(view.camera.R, expected.camera.R)
        np.testing.assert_array_equal(view.camera.K, expected.camera.K)
        np.testing.assert_array_equal(view.depth, expected.depth)
    # The stitch reconstructs the whole photos once.
    whole = []
    original = ClassicalReconstructor.reconstruct

    def reconstruct(self, found):
        if found[0].width == images[0].shape[1]:
            whole.append(self.options.model)
        return original(self, found)

    monkeypatch.setattr(ClassicalReconstructor, "reconstruct", reconstruct)
    result = pis3r.stitch(images, backend="classical")
    assert whole == ["3d"] and result.report["model_choice"]["chosen"]["model"] == "3d"


def test_forcing_a_model_skips_the_band_test(small_pair):
    result = pis3r.stitch(list(small_pair), backend="classical", model="3d", depth_fill="harmonic")
    assert result.report["model_choice"]["candidates"] == []
    assert result.report["model_choice"]["chosen"] == {"model": "3d", "depth_fill": "harmonic", "focal_rule": None}
    default = pis3r.stitch(list(small_pair), backend="classical")
    assert [c["model"] for c in default.report["model_choice"]["candidates"]] == ["auto", "homography", "apap"]


def test_the_local_homographies_must_beat_the_others_by_their_handicap():
    def scores(apap_psnr):
        return (BandScore(Candidate("auto"), 20.0, 1.0), BandScore(Candidate("homography"), 20.2, 1.0),
                BandScore(Candidate("apap"), apap_psnr, 1.0))

    margin = BAND_HANDICAP_DB["apap"]
    assert best_score(scores(20.2 + margin / 2)) == 1  # ahead, but within the band's noise
    assert best_score(scores(20.2 + 2 * margin)) == 2
    assert best_score(scores(-math.inf)) == 1
    # Equal scores: the first candidate (the backend's own explanation) wins.
    assert best_score((BandScore(Candidate("auto"), 20.0, 1.0), BandScore(Candidate("homography"), 20.0, 1.0))) == 0


def test_a_candidate_that_cannot_stitch_the_band_scores_minus_infinity():
    score = BandScore(Candidate("3d", "planar"), -math.inf, 0.0, "no essential matrix")
    assert score.to_dict() == {"model": "3d", "depth_fill": "planar", "focal_rule": None, "band_psnr": None,
                               "band_coverage": 0.0, "band_model": None, "error": "no essential matrix"}


def test_the_backends_own_test_stands_for_the_model_it_made_on_the_band():
    """What predicted the band makes the stitch: ``auto`` becomes the model its band scene had."""
    auto = Candidate("auto", "planes")
    assert BandScore(auto, 20.0, 1.0, scene_model="homography").tested == Candidate("homography")
    assert BandScore(auto, 20.0, 1.0, scene_model="3d").tested == Candidate("3d", "planes")
    assert BandScore(Candidate("apap"), 20.0, 1.0, scene_model="apap").tested == Candidate("apap")
    assert BandScore(auto, 20.0, 1.0, scene_model="3d").to_dict()["band_model"] == "3d"


def test_the_band_copies_features_are_detected_once_for_every_candidate(small_pair, monkeypatch):
    """The band's two copies are detected while the photos are matched; every candidate's
    reconstruction reuses them: four detections in all (two photos, two copies)."""
    import pis3r.reconstruct.classical as classical

    detected = []
    original = classical.PhotoFeatures
    monkeypatch.setattr(classical, "PhotoFeatures", lambda photo, *cap: detected.append(photo.pixels.shape) or
                        original(photo, *cap))
    photos = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip(small_pair, "ab")]
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto")
    assert len(choice.scores) == 3 and len(detected) == 4


def test_later_photos_are_detected_during_the_band_test_and_reused(small_pair, monkeypatch):
    """With a third photo, its features are detected on a thread while the band is tested,
    into the stitch's memo: the reconstruction that follows detects nothing again (five
    detections in all: three photos, two band copies)."""
    import pis3r.reconstruct.classical as classical

    detected = []
    original = classical.PhotoFeatures
    monkeypatch.setattr(classical, "PhotoFeatures",
                        lambda photo, *cap: detected.append(photo.name) or original(photo, *cap))
    third = np.ascontiguousarray(small_pair[1][:, ::-1])
    photos = [Photo(np.asarray(image, np.float32) / 255.0, name) for image, name in zip((*small_pair, third), "abc")]
    memo: dict = {}
    choice = choose_model(photos, "classical", ReconstructOptions(), model="auto", memo=memo)
    assert ("features", id(photos[2]), classical.MULTI_VIEW_FEATURES) in memo
    reconstructor = classical.ClassicalReconstructor(choice.chosen.backend_options(ReconstructOptions()), memo)
    reconstructor.features(photos[:2])
    reconstructor.features(photos[2:], classical.MULTI_VIEW_FEATURES)
    assert sorted(detected) == ["a", "a", "b", "b", "c"]
