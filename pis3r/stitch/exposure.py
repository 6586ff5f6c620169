"""Exposure and vignetting: how a view's colours become the reference camera's.

A pixel records ``e * V(t) * L``: the scene's radiance ``L``, the shot's exposure ``e`` (per
channel: white balance too) and the lens's falloff ``V`` at ``t``, the tangent of the angle
between the ray and the optical axis (``|x - c| / f``: the same for any camera with that
lens, whatever its pixel count). ``V(t) = 1 + a t^2 + b t^4`` (``V(0) = 1``), one lens for all
views. A view's colour ``I_v`` at a canvas pixel ``x`` becomes the reference's
``I_v * g * V(t_ref(x)) / V(t_v)`` with ``g = e_ref / e_v``: the colour the reference camera
would have recorded there, falloff included, so the extension continues the reference's
own vignetting instead of breaking it at the border.

Where a view lands inside the reference both colours are known, and
``log I_ref - log I_v = log g + log V(t_ref) - log V(t_v)`` is fitted to them (robust least
squares). Without the falloff a single gain soaks it up: the overlap of two shifted photos
lies near the centre of one and the edge of the other, so the gain measured there is off
everywhere else (by 20 % on ``lpc-APAP-garden``). The falloff is kept only when the radii on
the two sides differ enough to tell it from the gain (``MIN_RADIUS_SPREAD``) and it is a
lens's: darker off axis, never brighter (the fit is constrained so), and above
``MIN_FALLOFF`` at the widest angle; otherwise the gain alone, the median
ratio, as before. Beyond the widest angle either photo saw, ``V`` is held at its value there.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Gains outside this range are not an exposure difference but a mismatch.
GAIN_RANGE = (0.5, 2.0)
# Colours this close to black or white say nothing about a ratio (noise, clipping).
USABLE_RANGE = (0.02, 0.98)
# Samples needed for any fit.
MIN_SAMPLES = 100
# A falloff is fitted only when t^2 of the two sides of the samples differ by at least this
# (standard deviation): otherwise it cannot be told from the gain.
MIN_RADIUS_SPREAD = 0.01
# The falloff of a lens at the widest angle: never below this.
MIN_FALLOFF = 0.3
# Six parameters are pinned down by a few thousand samples: the falloff is fitted on at most
# this many (evenly spread over the overlap), the gain alone on all.
FIT_SAMPLES = 4000
# Robust loss scale on log ratios: about 5 % (misregistered or occluded samples are outliers).
LOG_RATIO_SCALE = 0.05
# The robust fit stops when a step lowers its cost by less than this share, or after this
# many steps.
FIT_TOLERANCE = 1e-10
FIT_MAX_STEPS = 50
# Which of the fit's five parameters (three log gains, two of the falloff) are bounded below by 0.
_BOUNDED = np.arange(5) >= 3


@dataclass(frozen=True)
class Exposure:
    """A view's colours in the reference's terms: ``gain`` ``(3,)`` per channel, the lens's
    ``falloff`` ``(a, b)`` (zero: none), valid up to ``t2_max`` (larger ``t^2`` are held there)."""

    gain: np.ndarray
    falloff: tuple[float, float] = (0.0, 0.0)
    t2_max: float = 0.0

    def vignetting(self, t2: np.ndarray) -> np.ndarray:
        """``V`` at squared tangents ``t2`` (any shape), float32."""
        a, b = self.falloff
        # 1 + t2 (a + b t2), in place on one float32 copy: canvases of tens of megapixels.
        t2 = np.minimum(np.asarray(t2, np.float32), np.float32(self.t2_max))
        out = t2 * np.float32(b)
        out += np.float32(a)
        out *= t2
        out += np.float32(1.0)
        return out

    def apply(self, colours: np.ndarray, t2_ref: np.ndarray, t2_view: np.ndarray) -> np.ndarray:
        """View colours ``(..., N, 3)`` float32 brought to the reference, in place (and returned):
        at pixels whose squared tangents are ``t2_ref`` in the reference camera and ``t2_view``
        in the view (both ``(..., N)``), multiplied by ``V(t2_ref) / V(t2_view)`` and the gain.
        Each row of ``N`` colours must be contiguous (any C-contiguous array or a window of one)."""
        ratio = self.vignetting(t2_ref)
        ratio /= self.vignetting(t2_view)
        # OpenCV multiplies three channels by one factor at memory speed, numpy's broadcast of a
        # (..., 1) factor several times slower: on a canvas of tens of megapixels that is tenths
        # of a second. Both see the colours as rows of N pixels, without a copy.
        pixels = np.reshape(colours, (-1, colours.shape[-2], 3), copy=False)
        factor = cv2.cvtColor(np.reshape(ratio, pixels.shape[:2]), cv2.COLOR_GRAY2RGB)
        cv2.multiply(pixels, factor, dst=pixels)
        self.apply_gain(pixels)
        return colours

    def apply_gain(self, colours: np.ndarray) -> np.ndarray:
        """Colours ``(..., N, 3)`` float32 (rows of ``N`` contiguous) multiplied by the gain
        alone, in place (and returned): the whole :meth:`apply` of an exposure without falloff."""
        cv2.multiply(colours, (*(float(g) for g in self.gain), 0.0), dst=colours)
        return colours

    def to_dict(self) -> dict:
        return {"gain": [round(float(g), 4) for g in self.gain], "falloff": [round(c, 4) for c in self.falloff],
                "t2_max": round(self.t2_max, 4)}


NEUTRAL = Exposure(np.ones(3, np.float32))


def squared_tangents(pixels: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``(...)`` squared tangent of each pixel's ray off the optical axis, for ``pixels``
    ``(..., 2)`` of a camera with intrinsics ``K`` ``(3, 3)``."""
    # In the pixels' own precision, in place: on a canvas of tens of megapixels the float64
    # temporaries of a mixed expression cost more than sampling the colours.
    dx = pixels[..., 0] - float(K[0, 2])
    dx /= float(K[0, 0])
    dx *= dx
    dy = pixels[..., 1] - float(K[1, 2])
    dy /= float(K[1, 1])
    dy *= dy
    dx += dy
    return dx.astype(np.float32, copy=False)


def grid_squared_tangents(K: np.ndarray, rows: slice, cols: slice) -> np.ndarray:
    """``(len(rows), len(cols))`` :func:`squared_tangents` of the pixel grid ``rows x cols``
    (``slice`` s with explicit ``start``, ``stop`` and optionally ``step``), by rows and columns
    apart: no coordinate arrays of the grid's size."""
    dx = (np.arange(cols.start, cols.stop, cols.step or 1) - K[0, 2]) / K[0, 0]
    dy = (np.arange(rows.start, rows.stop, rows.step or 1) - K[1, 2]) / K[1, 1]
    return (dy * dy).astype(np.float32)[:, None] + (dx * dx).astype(np.float32)[None, :]


def corner_t2(K: np.ndarray, width: int, height: int) -> float:
    """The largest squared tangent of a ``width x height`` camera with intrinsics ``K``."""
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
    return float(squared_tangents(corners, K).max())


def fit_exposure(reference: np.ndarray, view: np.ndarray, t2_ref: np.ndarray, t2_view: np.ndarray,
                 t2_max: float) -> Exposure:
    """The :class:`Exposure` taking ``view`` colours ``(N, 3)`` to ``reference`` colours ``(N, 3)``
    at samples with squared tangents ``t2_ref``, ``t2_view`` ``(N,)`` (module docstring);
    ``t2_max``: the widest angle either camera sees. :data:`NEUTRAL` with too few samples."""
    usable = ((view > USABLE_RANGE[0]) & (view < USABLE_RANGE[1])
              & (reference > USABLE_RANGE[0]) & (reference < USABLE_RANGE[1])).all(axis=1)
    if int(usable.sum()) < MIN_SAMPLES:
        return NEUTRAL
    log_ratio = np.log(reference[usable]) - np.log(view[usable])
    median_gain = Exposure(np.exp(np.median(log_ratio, axis=0)).clip(*GAIN_RANGE).astype(np.float32))
    s_ref, s_view = t2_ref[usable].astype(np.float64), t2_view[usable].astype(np.float64)
    if float(np.std(s_ref - s_view)) < MIN_RADIUS_SPREAD:
        return median_gain
    step = max(1, len(log_ratio) // FIT_SAMPLES)
    start = np.concatenate([np.log(median_gain.gain), [0.0, 0.0]])
    p = _fit_gain_and_falloff(log_ratio[::step], s_ref[::step], s_view[::step], t2_max, start)
    a, b = _falloff(p, t2_max)
    candidate = Exposure(np.exp(p[:3]).clip(*GAIN_RANGE).astype(np.float32), (float(a), float(b)), t2_max)
    if float(candidate.vignetting(np.float32(t2_max))) < MIN_FALLOFF:
        return median_gain
    return candidate


def _falloff(p: np.ndarray, t2_max: float) -> tuple[float, float]:
    """``(a, b)`` of ``V`` from the fit's parameters ``p`` ``(5,)``. A lens darkens monotonically
    off axis: V's slope in t^2, a + 2 b t^2, is <= 0 on [0, t2_max]. With a = -p[3] and
    a + 2 b t2_max = -p[4] that is p[3], p[4] >= 0 (plain bounds), so a fit cannot trade a gain
    for a falloff that dips and rises again."""
    return -p[3], (p[3] - p[4]) / (2.0 * t2_max)


def _fit_gain_and_falloff(log_ratio: np.ndarray, s_ref: np.ndarray, s_view: np.ndarray, t2_max: float,
                          start: np.ndarray) -> np.ndarray:
    """Parameters ``p`` ``(5,)`` (log gains per channel, then the falloff's, :func:`_falloff`) that
    minimise the soft-L1 cost (scale ``LOG_RATIO_SCALE``) of the residuals ``p[c] + log V(s_ref)
    - log V(s_view) - log_ratio[:, c]`` (``log_ratio`` ``(N, 3)``; ``s_ref``, ``s_view`` ``(N,)``
    squared tangents), with ``p[3], p[4] >= 0``, from ``start``.

    Newton's method on the robust cost: the residuals' Gauss-Newton matrix weighted by the
    loss's curvature (the loss is convex in a residual), five unknowns solved directly. A
    falloff parameter at its bound that the step would push below it is held there; a step
    is cut back to the bounds, then halved until the cost falls. Five to eight steps where
    scipy's ``least_squares`` took 7-12 evaluations, each with a numerical Jacobian, and
    tenths of a second per stitch; both reach the same minimum."""
    def residuals(p):
        a, b = _falloff(p, t2_max)
        logs, slopes = [], []
        for s in (s_ref, s_view):
            v = 1.0 + a * s + b * s * s
            # log V is floored at V = 1e-3, flat there.
            live = v > 1e-3
            inverse = np.where(live, 1.0 / np.where(live, v, 1.0), 0.0)
            logs.append(np.log(np.maximum(v, 1e-3)))
            slopes.append(np.stack([(s * s / (2.0 * t2_max) - s) * inverse, -s * s / (2.0 * t2_max) * inverse], 1))
        return p[:3] + (logs[0] - logs[1])[:, None] - log_ratio, slopes[0] - slopes[1]

    def cost(r):
        return float(np.sum(np.sqrt(1.0 + (r / LOG_RATIO_SCALE) ** 2) - 1.0))

    p = np.asarray(start, np.float64).copy()
    r, dr = residuals(p)
    current = cost(r)
    for _ in range(FIT_MAX_STEPS):
        q = 1.0 + (r / LOG_RATIO_SCALE) ** 2
        slope = 1.0 / np.sqrt(q)
        curvature = slope / q
        matrix = np.zeros((5, 5))
        matrix[:3, :3] = np.diag(curvature.sum(axis=0))
        matrix[:3, 3:] = curvature.T @ dr
        matrix[3:, :3] = matrix[:3, 3:].T
        matrix[3:, 3:] = dr.T @ (dr * curvature.sum(axis=1)[:, None])
        gradient = np.concatenate([(slope * r).sum(axis=0), dr.T @ (slope * r).sum(axis=1)])
        step = _bounded_newton_step(matrix, gradient, p)
        if step is None:
            break
        shrinking = _BOUNDED & (step < 0.0)
        length = min([1.0, *(p[shrinking] / -step[shrinking])])
        for _ in range(30):
            trial = p + length * step
            trial[3:] = np.maximum(trial[3:], 0.0)
            trial_r, trial_dr = residuals(trial)
            trial_cost = cost(trial_r)
            if trial_cost <= current:
                break
            length *= 0.5
        else:
            break
        done = current - trial_cost <= FIT_TOLERANCE * current
        p, r, dr, current = trial, trial_r, trial_dr, trial_cost
        if done:
            break
    return p


def _bounded_newton_step(matrix: np.ndarray, gradient: np.ndarray, p: np.ndarray) -> np.ndarray | None:
    """The step ``(5,)`` solving ``matrix @ step = -gradient`` with every falloff parameter of ``p``
    that is at its bound (0) and would go below it held there, one or both (at most three
    solves); None when the system is singular (the samples do not tell the parameters apart)."""
    free = np.ones(5, bool)
    while True:
        step = np.zeros(5)
        try:
            step[free] = -np.linalg.solve(matrix[np.ix_(free, free)], gradient[free])
        except np.linalg.LinAlgError:
            return None
        held = free & _BOUNDED & (p <= 0.0) & (step < 0.0)
        if not held.any():
            return step
        free &= ~held
