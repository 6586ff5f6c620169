"""The one headless OpenGL context of a pis3r process (moderngl on EGL: Mesa's llvmpipe on a
CPU, the GPU's driver where there is one).

Everything that draws (the renderer, the synthetic-scene generator) uses this context, made
current in the calling thread under one lock for the duration of a draw: two contexts in one
process break each other's calls when the wrong one is current, and releasing an EGL context
terminates the display that every context of the process shares, so it is never released.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager

from pis3r.errors import Pis3rError

_lock = threading.RLock()
_state: dict = {}


def shared_context():
    """The process's ``moderngl.Context``, or ``None`` when none can be created (no libEGL,
    no driver, no moderngl; :func:`unavailable_reason` says why)."""
    with _lock:
        if "context" not in _state:
            try:
                import moderngl

                context = moderngl.create_standalone_context(backend="egl")
                # A new context is current in the thread that made it, and an EGL context can be
                # current in one thread only: release it here, so that any thread (the web
                # server's workers, a warm-up thread) can make it current for a draw.
                context.__exit__(None, None, None)
                _state["context"], _state["error"] = context, ""
            except Exception as exc:  # moderngl raises bare Exceptions for a missing EGL or driver
                _state["context"], _state["error"] = None, str(exc).strip() or exc.__class__.__name__
    return _state["context"]


def unavailable_reason() -> str:
    """Why :func:`shared_context` is ``None`` (empty when it is not)."""
    shared_context()
    return _state["error"]


def required_context():
    """The shared context; a one-line :class:`Pis3rError` saying why when there is none."""
    context = shared_context()
    if context is None:
        raise Pis3rError(
            f"cannot create a headless OpenGL context (moderngl + EGL): {unavailable_reason()}; "
            "install Mesa's EGL (Debian/Ubuntu: libegl1 libgl1-mesa-dri)"
        )
    return context


@contextmanager
def current_context():
    """The shared context, current in this thread for the ``with`` block."""
    context = required_context()
    with _lock, context:
        yield context
