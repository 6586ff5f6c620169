"""How the classical path spends a process's CPU: its one-off costs, paid on a thread while
the first stage runs, and its BLAS threads (issue 12).

The classical backend's first stage, finding features, spends about half a second on a 1 MP
pair inside OpenCV with the GIL released. Meanwhile a thread builds OpenCV's CIE Lab tables
(0.1 s at a process's first Lab conversion, which the depth fill's edge weights make),
imports the scipy modules the later stages call (its sparse solvers) and creates the
headless OpenGL context the renderer draws with (EGL on Mesa: 0.1-0.3 s). A stage that needs
one of them before the thread is done waits for it (OpenCV's own lock, Python's import lock,
:mod:`pis3r.gl`'s lock): results do not change, only when the cost is paid.

OpenBLAS runs one thread during a classical stitch (:func:`single_threaded_blas`): its calls
there are small (descriptor products, the conjugate-gradient dot products of the depth fill)
while pis3r's own threads keep both cores busy, and after each call OpenBLAS's helper thread
spins for a while, taking a core from them: 1.3-1.9 of the 5-7 CPU seconds of a 0.67 MP pair.
"""

from __future__ import annotations

import importlib
import threading

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from pis3r import gl

# What the classical backend's stages import on first use: the depth fill's solvers. (Its pose
# and rotation fits are pis3r.reconstruct.robust_lsq: scipy.optimize is never imported.) ASIFT's
# match refinement imports scipy.spatial (0.12 s of CPU) when it first runs: the pairs SIFT
# matches, most of them, do not pay for it.
CLASSICAL_MODULES = ("scipy.sparse.linalg",)

_started = threading.Lock()


def warm_up_in_background(modules: tuple[str, ...] = CLASSICAL_MODULES) -> threading.Thread | None:
    """Start the warm-up (module docstring), importing ``modules``, on a thread and return it;
    None when a warm-up has started in this process already. A failure is left to the stage
    that needs the module or the context, which reports it."""
    if not _started.acquire(blocking=False):
        return None

    def warm_up() -> None:
        cv2.cvtColor(np.zeros((1, 1, 3), np.float32), cv2.COLOR_RGB2LAB)
        for name in modules:
            try:
                importlib.import_module(name)
            except ImportError:
                break
        gl.shared_context()

    # Not a daemon: a process that ends meanwhile waits for it rather than stopping it inside
    # an import or an EGL call.
    thread = threading.Thread(target=warm_up, name="pis3r-warm-up")
    thread.start()
    return thread


def single_threaded_blas() -> threadpool_limits:
    """A context manager: one OpenBLAS thread in every BLAS library loaded when the block starts
    (numpy's and OpenCV's; scipy's once a stitch in this process has imported it), restored
    after it."""
    return threadpool_limits(1, user_api="blas")
