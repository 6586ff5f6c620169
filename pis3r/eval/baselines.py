"""The stitchers under evaluation, each behind one contract and run in its own process.

Every method is a function ``(reference, target) -> MethodOutput`` on ``(H, W, 3)`` float32
RGB images. :func:`run_method` runs one in a fresh Python process with a time limit, so a
crash (even a segfault in native code), a hang or a refusal of a peer becomes a
:class:`MethodFailure` — a registration failure in the tables, as in the paper — and never
takes the evaluation down.

Methods: ``pis3r`` (classical backend), ``opencv`` (``cv2.Stitcher`` PANORAMA),
``opencv-scans`` (``cv2.Stitcher`` SCANS), ``stitching`` (the PyPI package), ``apap``
(:mod:`pis3r.eval.apap`).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pis3r.errors import Pis3rError
from pis3r.io import to_uint8

DEFAULT_TIMEOUT_S = 300.0


class MethodFailure(Pis3rError):
    """A method crashed, timed out or refused the pair; the message says which."""


@dataclass(frozen=True)
class MethodOutput:
    """One method's stitched canvas.

    ``image`` ``(h, w, 3)`` float32 RGB in [0, 1]; ``filled`` ``(h, w)`` bool (pixels the
    method produced); ``ref_offset`` ``(x, y)``: canvas pixel of the reference's pixel
    (0, 0) when the method knows it exactly (else ``None``); ``seconds``: wall time of the
    method itself.
    """

    image: np.ndarray
    filled: np.ndarray
    ref_offset: tuple[int, int] | None
    seconds: float


def _bgr(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR)


def _from_bgr_canvas(canvas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV stitchers paint the background black and export no mask: filled = non-black."""
    image = cv2.cvtColor(canvas, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    return image, canvas.max(axis=2) > 0


def stitch_pis3r(reference: np.ndarray, target: np.ndarray) -> MethodOutput:
    """pis3r with the weight-free classical backend on CPU."""
    from pis3r.api import stitch

    start = time.perf_counter()
    result = stitch([reference, target], ref=0, backend="classical", device="cpu")
    seconds = time.perf_counter() - start
    return MethodOutput(result.image, result.mask > 0, tuple(int(v) for v in result.ref_offset), seconds)


def _opencv(mode: int):
    def stitch_opencv(reference: np.ndarray, target: np.ndarray) -> MethodOutput:
        start = time.perf_counter()
        status, canvas = cv2.Stitcher_create(mode).stitch([_bgr(reference), _bgr(target)])
        seconds = time.perf_counter() - start
        if status != cv2.Stitcher_OK or canvas is None:
            raise MethodFailure(f"cv2.Stitcher refused the pair (status {status})")
        return MethodOutput(*_from_bgr_canvas(canvas), None, seconds)

    return stitch_opencv


def stitch_stitching(reference: np.ndarray, target: np.ndarray) -> MethodOutput:
    """The ``stitching`` package with the canvas left uncropped (its default crops to the
    largest interior rectangle, which throws the extension away) and SIFT features."""
    from stitching import Stitcher
    from stitching.stitching_error import StitchingError

    start = time.perf_counter()
    try:
        canvas = Stitcher(detector="sift", crop=False).stitch([_bgr(reference), _bgr(target)])
    except StitchingError as exc:
        raise MethodFailure(f"stitching refused the pair: {exc}") from None
    return MethodOutput(*_from_bgr_canvas(canvas), None, time.perf_counter() - start)


def stitch_apap(reference: np.ndarray, target: np.ndarray) -> MethodOutput:
    from pis3r.eval.apap import apap_stitch

    start = time.perf_counter()
    result = apap_stitch(reference, target)
    return MethodOutput(result.image, result.filled, result.ref_offset, time.perf_counter() - start)


METHODS = {
    "pis3r": stitch_pis3r,
    "opencv": _opencv(cv2.Stitcher_PANORAMA),
    "opencv-scans": _opencv(cv2.Stitcher_SCANS),
    "stitching": stitch_stitching,
    "apap": stitch_apap,
}


def run_method(name: str, reference: np.ndarray, target: np.ndarray, timeout: float = DEFAULT_TIMEOUT_S) -> MethodOutput:
    """Run method ``name`` on ``(H, W, 3)`` images in a child process with a ``timeout`` (s).

    Raises :class:`MethodFailure` for a crash, timeout or refusal."""
    if name not in METHODS:
        raise MethodFailure(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    with tempfile.TemporaryDirectory(prefix="pis3r-eval-") as tmp:
        inputs, output = Path(tmp) / "inputs.npz", Path(tmp) / "output.npz"
        np.savez(inputs, reference=reference, target=target)
        # One thread per method process: the evaluation already runs many in parallel.
        env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "pis3r.eval.baselines", name, str(inputs), str(output)],
                capture_output=True, text=True, timeout=timeout, env=env,
            )
        except subprocess.TimeoutExpired:
            raise MethodFailure(f"{name} timed out after {timeout:g} s") from None
        if proc.returncode != 0 or not output.is_file():
            lines = (proc.stderr or proc.stdout or "").strip().splitlines()
            raise MethodFailure(f"{name} failed (exit {proc.returncode}): {lines[-1] if lines else 'no message'}")
        with np.load(output) as data:
            offset = tuple(int(v) for v in data["ref_offset"]) if data["ref_offset"].size else None
            return MethodOutput(data["image"], data["filled"], offset, float(data["seconds"]))


def _child(name: str, inputs: str, output: str) -> int:
    """Entry point of the child process: run one method, write its output, exit 0; or print
    one line and exit 1."""
    with np.load(inputs) as data:
        reference, target = data["reference"], data["target"]
    try:
        result = METHODS[name](reference, target)
    except Exception as exc:  # any failure of a peer is a result here, reported in one line
        print(f"{exc.__class__.__name__}: {exc}".splitlines()[0], file=sys.stderr)
        return 1
    offset = np.array(result.ref_offset if result.ref_offset is not None else [], np.int64)
    np.savez(output, image=result.image.astype(np.float32), filled=result.filled, ref_offset=offset,
             seconds=result.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(_child(*sys.argv[1:4]))
