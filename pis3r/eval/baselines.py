"""The stitchers under evaluation, each behind one contract and run in its own process.

Every method is a function ``(reference, target, geometry) -> MethodOutput`` on
``(H, W, 3)`` float32 RGB images. :func:`run_method` runs one in a child process with a time
limit, so a crash (even a segfault in native code), a hang or a refusal of a peer becomes a
:class:`MethodFailure` — a registration failure in the tables, as in the paper — and never
takes the evaluation down.

Methods: ``pis3r`` (classical backend), ``opencv`` (``cv2.Stitcher`` PANORAMA),
``opencv-scans`` (``cv2.Stitcher`` SCANS), ``stitching`` (the PyPI package), ``apap``
(:mod:`pis3r.eval.apap`).
"""

from __future__ import annotations

import atexit
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from pis3r.errors import Pis3rError
from pis3r.io import to_uint8
from pis3r.projection import DEFAULT_PROJECTION
from pis3r.reconstruct.options import DEFAULT_MATCHER

DEFAULT_TIMEOUT_S = 300.0


class MethodFailure(Pis3rError):
    """A method crashed, timed out or refused the pair; the message says which."""


@dataclass(frozen=True)
class MethodCanvas:
    """A peer's stitched canvas: ``image`` ``(h, w, 3)`` float32 RGB in [0, 1]; ``filled`` ``(h, w)``
    bool (pixels the method produced); ``offset`` ``(x, y)``: canvas pixel of the pixel
    (0, 0) of the camera it is seen from, when the method knows it exactly, else ``None``."""

    image: np.ndarray
    filled: np.ndarray
    offset: tuple[int, int] | None


@dataclass(frozen=True)
class MethodOutput:
    """What one method made of a pair: ``canvas`` in the reference's view; with geometry
    asked for and supported, ``target_canvas`` in the target's view and ``relative_pose``
    ``(3, 4)`` ``[R | t]`` (reference camera -> target camera) as the method reconstructed
    it (``None`` otherwise). ``seconds``: wall time of the method itself."""

    canvas: MethodCanvas
    seconds: float
    target_canvas: MethodCanvas | None = None
    relative_pose: np.ndarray | None = None


def _bgr(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2BGR)


def _from_bgr_canvas(canvas: np.ndarray) -> MethodCanvas:
    """OpenCV stitchers paint the background black and export no mask: filled = non-black."""
    image = cv2.cvtColor(canvas, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    return MethodCanvas(image, canvas.max(axis=2) > 0, None)


def stitch_pis3r(reference: np.ndarray, target: np.ndarray, geometry: bool,
                 matcher: str = DEFAULT_MATCHER, projection: str = DEFAULT_PROJECTION) -> MethodOutput:
    """pis3r with its default :class:`~pis3r.options.StitchOptions`, except the weight-free
    classical backend on CPU (what every user has) and the ``matcher`` and ``projection`` given;
    with ``geometry`` one canvas per camera from one reconstruction (``ref="all"``)."""
    from pis3r.api import stitch
    from pis3r.options import StitchOptions

    options = StitchOptions(backend="classical", device="cpu", ref="all" if geometry else 0, matcher=matcher,
                            projection=projection)
    start = time.perf_counter()
    result = stitch([reference, target], options)
    seconds = time.perf_counter() - start
    results = result if geometry else [result]
    canvases = [MethodCanvas(r.image, r.mask > 0, tuple(int(v) for v in r.ref_offset)) for r in results]
    if not geometry:
        return MethodOutput(canvases[0], seconds)
    camera = results[0].scene.views[1].camera
    return MethodOutput(canvases[0], seconds, canvases[1], np.hstack([camera.R, camera.t[:, None]]))


def _opencv(mode: int):
    def stitch_opencv(reference: np.ndarray, target: np.ndarray, geometry: bool) -> MethodOutput:
        start = time.perf_counter()
        status, canvas = cv2.Stitcher_create(mode).stitch([_bgr(reference), _bgr(target)])
        seconds = time.perf_counter() - start
        if status != cv2.Stitcher_OK or canvas is None:
            raise MethodFailure(f"cv2.Stitcher refused the pair (status {status})")
        return MethodOutput(_from_bgr_canvas(canvas), seconds)

    return stitch_opencv


def stitch_stitching(reference: np.ndarray, target: np.ndarray, geometry: bool) -> MethodOutput:
    """The ``stitching`` package with the canvas left uncropped (its default crops to the
    largest interior rectangle, which throws the extension away) and SIFT features."""
    from stitching import Stitcher
    from stitching.stitching_error import StitchingError

    start = time.perf_counter()
    try:
        canvas = Stitcher(detector="sift", crop=False).stitch([_bgr(reference), _bgr(target)])
    except StitchingError as exc:
        raise MethodFailure(f"stitching refused the pair: {exc}") from None
    return MethodOutput(_from_bgr_canvas(canvas), time.perf_counter() - start)


def stitch_apap(reference: np.ndarray, target: np.ndarray, geometry: bool) -> MethodOutput:
    """APAP onto the reference's frame; with ``geometry`` also onto the target's."""
    from pis3r.eval.apap import apap_stitch

    start = time.perf_counter()
    views = [apap_stitch(reference, target)] + ([apap_stitch(target, reference)] if geometry else [])
    canvases = [MethodCanvas(v.image, v.filled, v.ref_offset) for v in views]
    return MethodOutput(canvases[0], time.perf_counter() - start, canvases[1] if geometry else None)


METHODS = {
    "pis3r": stitch_pis3r,
    "opencv": _opencv(cv2.Stitcher_PANORAMA),
    "opencv-scans": _opencv(cv2.Stitcher_SCANS),
    "stitching": stitch_stitching,
    "apap": stitch_apap,
}
# Methods whose canvas is a perspective image of a known camera at an offset they export:
# the exact-offset score and geometry apply to them.
CAMERA_METHODS = ("pis3r", "apap")


def run_method(name: str, reference: np.ndarray, target: np.ndarray, timeout: float = DEFAULT_TIMEOUT_S,
               threads: int = 1, geometry: bool = False, matcher: str = DEFAULT_MATCHER,
               projection: str = DEFAULT_PROJECTION) -> MethodOutput:
    """Run method ``name`` on ``(H, W, 3)`` images in a child process with a ``timeout`` (s),
    using at most ``threads`` CPU threads (OpenCV and torch). ``geometry``: also ask for the
    target-view canvas and relative pose (methods in ``CAMERA_METHODS``); ``matcher`` and
    ``projection``: pis3r's (the peers have their own).

    Raises :class:`MethodFailure` for a crash, timeout or refusal."""
    if name not in METHODS:
        raise MethodFailure(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    with tempfile.TemporaryDirectory(prefix="pis3r-eval-") as tmp:
        inputs, output, error = (Path(tmp) / f for f in ("inputs.npz", "output.npz", "error.txt"))
        np.savez(inputs, reference=reference, target=target)
        args = [name, str(threads), str(int(geometry)), matcher, projection, str(inputs), str(output), str(error)]
        exit_code = _server().run(args, timeout)
        if exit_code is None:
            raise MethodFailure(f"{name} timed out after {timeout:g} s")
        if exit_code != 0 or not output.is_file():
            message = error.read_text().strip() if error.is_file() else f"crashed (exit code {exit_code})"
            raise MethodFailure(f"{name} failed: {message}")
        with np.load(output) as data:
            return _unpack(dict(data))


class _ForkServer:
    """A long-lived ``python -m pis3r.eval.baselines --serve`` that forks one child per run.

    A fresh interpreter spends seconds importing torch; the server imports pis3r once and
    never computes anything itself, so forking it is cheap and safe (no threads, no
    OpenMP state to inherit). Unlike multiprocessing's forkserver it does not re-import the
    caller's ``__main__``, and it works inside daemonic processes (dask workers).
    Protocol on its stdin / stdout, one line each: the child's arguments as JSON in; the
    child's pid, then its exit code out."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "pis3r.eval.baselines", "--serve"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0,
        )
        self.pending = b""
        self.lock = threading.Lock()

    def alive(self) -> bool:
        return self.process.poll() is None

    def run(self, args: list[str], timeout: float) -> int | None:
        """Run :func:`_child` with ``args`` in a forked child: its exit code, or ``None``
        after ``timeout`` seconds (the child is killed)."""
        with self.lock:
            self.process.stdin.write((json.dumps(args) + "\n").encode())
            pid = int(self._read_line(None))
            line = self._read_line(timeout)
            if line is None:
                os.kill(pid, signal.SIGKILL)
                self._read_line(None)  # the server reports the killed child's status
                return None
            return int(line)

    def _read_line(self, timeout: float | None) -> str | None:
        """The next line from the server; ``None`` if none came within ``timeout`` s."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while b"\n" not in self.pending:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([self.process.stdout], [], [], wait)[0]:
                return None
            chunk = os.read(self.process.stdout.fileno(), 4096)
            if not chunk:
                raise MethodFailure("the method server died")
            self.pending += chunk
        line, self.pending = self.pending.split(b"\n", 1)
        return line.decode()

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


_SERVERS: list[_ForkServer] = []


def _server() -> _ForkServer:
    """This process's fork server, started on first use (and again if it died)."""
    if _SERVERS and not _SERVERS[0].alive():
        _SERVERS.pop()
    if not _SERVERS:
        _SERVERS.append(_ForkServer())
        atexit.register(_SERVERS[0].close)
    return _SERVERS[0]


def _serve() -> int:
    """The fork server's loop (see :class:`_ForkServer`)."""
    for line in sys.stdin.buffer:
        pid = os.fork()
        if pid == 0:
            # The child must not write into the protocol pipe (peers print).
            devnull = os.open(os.devnull, os.O_RDWR)
            for fd in (0, 1, 2):
                os.dup2(devnull, fd)
            code = 1
            try:
                code = _child(*json.loads(line))
            finally:
                os._exit(code)
        sys.stdout.write(f"{pid}\n")
        sys.stdout.flush()
        _, status = os.waitpid(pid, 0)
        sys.stdout.write(f"{os.waitstatus_to_exitcode(status)}\n")
        sys.stdout.flush()
    return 0


def _pack(output: MethodOutput) -> dict:
    """``MethodOutput`` as a flat dict of arrays (an ``.npz``); absent parts are left out."""
    arrays = {"seconds": np.float64(output.seconds)}
    for prefix, canvas in (("canvas", output.canvas), ("target_canvas", output.target_canvas)):
        if canvas is not None:
            arrays[f"{prefix}_image"] = canvas.image.astype(np.float32)
            arrays[f"{prefix}_filled"] = canvas.filled.astype(bool)
            arrays[f"{prefix}_offset"] = np.array(canvas.offset if canvas.offset is not None else [], np.int64)
    if output.relative_pose is not None:
        arrays["relative_pose"] = output.relative_pose
    return arrays


def _unpack(arrays: dict) -> MethodOutput:
    def canvas(prefix: str) -> MethodCanvas | None:
        if f"{prefix}_image" not in arrays:
            return None
        offset = arrays[f"{prefix}_offset"]
        return MethodCanvas(arrays[f"{prefix}_image"], arrays[f"{prefix}_filled"],
                      tuple(int(v) for v in offset) if offset.size else None)

    return MethodOutput(canvas("canvas"), float(arrays["seconds"]), canvas("target_canvas"),
                        arrays.get("relative_pose"))


def _child(name: str, threads: str, geometry: str, matcher: str, projection: str, inputs: str, output: str,
           error: str) -> int:
    """Run one method in the child process: write its output and return 0, or write one line
    saying why it failed to ``error`` and return 1."""
    import torch

    # The evaluation runs several methods side by side: each gets its share of the cores.
    cv2.setNumThreads(int(threads))
    torch.set_num_threads(int(threads))
    with np.load(inputs) as data:
        reference, target = data["reference"], data["target"]
    try:
        method = partial(stitch_pis3r, matcher=matcher, projection=projection) if name == "pis3r" else METHODS[name]
        result = method(reference, target, bool(int(geometry)))
    except Exception as exc:  # any failure of a peer is a result here, reported in one line
        Path(error).write_text(f"{exc.__class__.__name__}: {exc}".splitlines()[0])
        return 1
    np.savez(output, **_pack(result))
    return 0


if __name__ == "__main__":
    sys.exit(_serve())
