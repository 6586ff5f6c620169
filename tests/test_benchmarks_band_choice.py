"""benchmarks/band_choice.py (issue 11): what the held-back band's choice costs per pair
against each model forced. Nothing is timed here."""

import math

import cv2
import pytest

from pis3r.eval.cases import load_crop_case
from tests.conftest import load_benchmark

band_choice = load_benchmark("band_choice")


@pytest.fixture(scope="module")
def crop_case(tmp_path_factory):
    """The crop protocol on two overlapping views of one photo (a shift of the image plane)."""
    from skimage import data

    folder = tmp_path_factory.mktemp("pair")
    photo = data.astronaut()
    cv2.imwrite(str(folder / "ref.png"), cv2.cvtColor(photo[100:360, 40:360], cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(folder / "tgt.png"), cv2.cvtColor(photo[130:390, 120:440], cv2.COLOR_RGB2BGR))
    return load_crop_case(folder, 0.6, "rotation", "test", "astronaut")


def test_each_band_candidate_is_paired_with_the_forced_model_it_stands_for(crop_case):
    row = band_choice.evaluate_pair(crop_case)
    assert [label for label, _, _ in row.scores] == ["auto", "homography", "apap"]
    assert all(math.isfinite(band) for _, band, _ in row.scores)
    # The backend's own test stands for the model it made on the band; the others for themselves.
    assert row.scores[0][2] in ("homography", "3d") and [m for _, _, m in row.scores[1:]] == ["homography", "apap"]
    assert set(row.forced) == set(band_choice.FORCED_MODELS)
    assert all(not score.error for score in (row.auto, *row.forced.values()))
    # The default stitch is the chosen model's stitch: forcing that model gives the same picture.
    assert row.chosen in band_choice.FORCED_MODELS
    assert row.forced[row.chosen].psnr == pytest.approx(row.auto.psnr, abs=0.01)
    assert row.regret == pytest.approx(row.forced[row.best].psnr - row.auto.psnr)
    assert row.regret >= -0.01
    # One homography is exact for a shift: it predicts the extension well.
    assert row.forced["homography"].psnr > 25


def _row(name, chosen_psnr, forced):
    score = band_choice.CropScore
    return band_choice.PairChoice(name, "slight", (), "homography", score(chosen_psnr),
                                  {model: score(value) for model, value in forced.items()})


def test_the_class_summary_counts_the_pairs_a_better_model_would_have_won_by_more_than_the_regret_bar():
    rows = [_row("right", 20.0, {"homography": 20.0, "apap": 19.0, "3d": 18.0}),
            _row("wrong", 15.0, {"homography": 15.0, "apap": 15.5, "3d": 17.0})]
    summary = band_choice.class_summary(rows)
    assert summary["pairs"] == 2 and summary["regretful"] == 1
    assert summary["chosen"] == pytest.approx(17.5) and summary["best"] == pytest.approx(18.5)
    assert summary["apap"] == pytest.approx(17.25)
    assert rows[1].best == "3d" and rows[1].regret == pytest.approx(2.0)
