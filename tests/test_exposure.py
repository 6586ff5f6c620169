"""Exposure and lens falloff: a view's colours brought to the reference camera's."""

import numpy as np
import pytest

from pis3r.stitch import exposure
from pis3r.stitch.exposure import (MIN_FALLOFF, NEUTRAL, Exposure, corner_t2, fit_exposure, grid_squared_tangents,
                                   squared_tangents)
from pis3r.camera import intrinsics

GAIN = np.array([1.3, 1.2, 0.9])


def _samples(falloff, n=4000, t2_max=0.4, shift=0.15, seed=0):
    """Radiances seen at squared tangents ``t2_ref`` by the reference and ``t2_view`` by a view
    with exposure ``1 / GAIN`` relative to it, both through a lens ``1 + a t^2 + b t^4``."""
    rng = np.random.default_rng(seed)
    t2_ref = rng.uniform(0, t2_max - shift, n)
    t2_view = t2_ref + shift * rng.uniform(0.2, 1.0, n)
    radiance = rng.uniform(0.1, 0.7, (n, 3))
    lens = Exposure(np.ones(3), falloff, t2_max)
    reference = radiance * lens.vignetting(t2_ref)[:, None]
    view = radiance / GAIN * lens.vignetting(t2_view)[:, None]
    return reference, view, t2_ref, t2_view, t2_max


def test_recovers_gain_and_falloff_of_a_vignetted_pair():
    reference, view, t2_ref, t2_view, t2_max = _samples((-0.6, 0.2))
    fitted = fit_exposure(reference, view, t2_ref, t2_view, t2_max)
    np.testing.assert_allclose(fitted.gain, GAIN, rtol=0.01)
    t2 = np.linspace(0, t2_max, 9)
    np.testing.assert_allclose(fitted.vignetting(t2), 1 - 0.6 * t2 + 0.2 * t2 ** 2, atol=0.01)
    # The view's colours become the reference's.
    np.testing.assert_allclose(fitted.apply(view.astype(np.float32), t2_ref, t2_view), reference, atol=0.01)


def test_a_falloff_needs_a_spread_of_radii_else_the_median_gain():
    rng = np.random.default_rng(1)
    t2 = rng.uniform(0, 0.3, 2000)
    reference = rng.uniform(0.1, 0.7, (2000, 3))
    fitted = fit_exposure(reference, reference / GAIN, t2, t2 + 0.001 * rng.uniform(size=2000), 0.4)
    assert fitted.falloff == (0.0, 0.0)
    np.testing.assert_allclose(fitted.gain, GAIN, rtol=1e-3)


def test_the_fit_never_makes_a_lens_brighter_off_axis():
    # Colour ratios that dip and rise again (a tone curve, not a lens): the fitted falloff
    # still only darkens outward.
    reference, view, t2_ref, t2_view, t2_max = _samples((-3.0, 8.0), t2_max=0.3, shift=0.1)
    fitted = fit_exposure(reference, view, t2_ref, t2_view, t2_max)
    assert any(fitted.falloff)
    assert (np.diff(fitted.vignetting(np.linspace(0, t2_max, 50))) <= 1e-6).all()


def test_a_falloff_darker_than_any_lens_is_refused(monkeypatch):
    reference, view, t2_ref, t2_view, t2_max = _samples((-1.9, 0.5), t2_max=0.5, shift=0.2)
    assert Exposure(np.ones(3), (-1.9, 0.5), t2_max).vignetting(np.array(t2_max)) < MIN_FALLOFF
    fitted = fit_exposure(reference, view, t2_ref, t2_view, t2_max)
    assert fitted.falloff == (0.0, 0.0)
    # Allowed, the same samples give that falloff: the refusal is the limit's doing.
    monkeypatch.setattr(exposure, "MIN_FALLOFF", 0.05)
    assert fit_exposure(reference, view, t2_ref, t2_view, t2_max).falloff != (0.0, 0.0)


def test_falloff_is_held_beyond_the_widest_angle_seen():
    lens = Exposure(np.ones(3), (-0.5, 0.0), 0.4)
    assert lens.vignetting(np.array(2.0)) == pytest.approx(0.8)
    np.testing.assert_allclose(lens.apply(np.ones((1, 3), np.float32), np.array([3.0]), np.array([0.0])),
                               [[0.8, 0.8, 0.8]], rtol=1e-6)


@pytest.mark.parametrize("bad", ["few", "clipped"])
def test_neutral_without_enough_usable_samples(bad):
    reference, view, t2_ref, t2_view, t2_max = _samples((-0.6, 0.2), n=50 if bad == "few" else 2000)
    if bad == "clipped":
        view = np.ones_like(view)
    assert fit_exposure(reference, view, t2_ref, t2_view, t2_max) is NEUTRAL


def test_squared_tangents_of_a_camera():
    K = intrinsics(100.0, 201, 101)
    pixels = np.array([[K[0, 2], K[1, 2]], [K[0, 2] + 100, K[1, 2]], [K[0, 2] + 30, K[1, 2] + 40]])
    np.testing.assert_allclose(squared_tangents(pixels, K), [0.0, 1.0, 0.25], atol=1e-6)
    # Integer pixels and float32 pixels (a raster's) give the same tangents.
    np.testing.assert_allclose(squared_tangents(pixels.astype(np.int64), K), [0.0, 1.0, 0.25], atol=1e-6)
    np.testing.assert_allclose(squared_tangents(pixels.astype(np.float32), K), [0.0, 1.0, 0.25], atol=1e-6)
    assert corner_t2(K, 201, 101) == pytest.approx((100 ** 2 + 50 ** 2) / 100 ** 2)
    # A strided window of the grid, by rows and columns apart, is the same per pixel.
    ys, xs = np.mgrid[7:90:4, 30:181:5]
    np.testing.assert_allclose(grid_squared_tangents(K, slice(7, 90, 4), slice(30, 181, 5)),
                               squared_tangents(np.stack([xs, ys], -1).astype(np.float64), K), rtol=1e-6)


def test_a_gain_alone_multiplies_each_channel_in_place():
    colours = np.random.default_rng(7).random((5, 4, 3)).astype(np.float32)
    gain = np.array([0.8, 1.0, 1.25], np.float32)
    expected = colours * gain
    assert Exposure(gain).apply_gain(colours) is colours
    np.testing.assert_array_equal(colours, expected)


def _noisy_log_ratios(falloff, n, t2_max, shift, seed):
    """:func:`_samples` as log colour ratios, with 1 % noise and a fifth of them outliers."""
    reference, view, t2_ref, t2_view, _ = _samples(falloff, n=n, t2_max=t2_max, shift=shift, seed=seed)
    rng = np.random.default_rng(seed + 1)
    view = view * np.exp(rng.normal(0, 0.01, view.shape))
    outliers = rng.uniform(size=n) < 0.2
    view[outliers] *= rng.uniform(0.5, 1.5, (int(outliers.sum()), 1))
    return np.log(reference) - np.log(view), t2_ref, t2_view


@pytest.mark.parametrize("falloff, seed, shift", [((-0.6, 0.2), 0, 0.1), ((-3.0, 8.0), 0, 0.1), ((0.0, 0.8), 1, 0.15)])
def test_the_robust_fit_reaches_the_minimum_scipy_finds(falloff, seed, shift):
    """The fit's soft-L1 cost is scipy's ``least_squares`` optimum (same loss, scale and
    bounds), to its tolerance: an interior minimum, one on a bound (a falloff that would rise
    again), and one on both bounds that the fit reaches holding one falloff parameter, then
    the other (a lens that would brighten off axis: no falloff at all)."""
    from scipy.optimize import least_squares

    t2_max = 0.4
    log_ratio, s_ref, s_view = _noisy_log_ratios(falloff, 2000, t2_max, shift, seed)

    def residuals(p):
        a, b = exposure._falloff(p, t2_max)
        log_v = [np.log(np.maximum(1 + a * s + b * s * s, 1e-3)) for s in (s_ref, s_view)]
        return (p[:3] + (log_v[0] - log_v[1])[:, None] - log_ratio).ravel()

    def cost(p):
        return float(np.sum(np.sqrt(1 + (residuals(p) / exposure.LOG_RATIO_SCALE) ** 2) - 1))

    start = np.concatenate([np.median(log_ratio, axis=0), [0.0, 0.0]])
    ours = exposure._fit_gain_and_falloff(log_ratio, s_ref, s_view, t2_max, start)
    theirs = least_squares(residuals, start, bounds=([-np.inf] * 3 + [0, 0], np.inf), loss="soft_l1",
                           f_scale=exposure.LOG_RATIO_SCALE).x
    assert (ours[3:] >= 0).all()
    assert cost(ours) <= cost(theirs) * (1 + 1e-8)
    np.testing.assert_allclose(ours, theirs, rtol=1e-3, atol=1e-4)


def test_samples_that_do_not_tell_the_falloff_end_the_fit_where_it_started():
    """Every sample on the axis on both sides: the falloff is undetermined (a singular system),
    and the fit returns its start instead of raising."""
    log_ratio = np.log(np.full((500, 3), 1.1))
    start = np.array([0.05, 0.1, 0.0, 0.0, 0.0])
    zero = np.zeros(500)
    np.testing.assert_array_equal(exposure._fit_gain_and_falloff(log_ratio, zero, zero, 0.4, start), start)
