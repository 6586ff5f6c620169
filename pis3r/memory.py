"""Handing freed memory back to the system between stages (issue 41).

A reconstruction allocates and frees thousands of arrays of a few megabytes (features,
matches, each pair's depth at working size) on several threads. glibc serves each thread from
its own arena and keeps what is freed there for later: after 17 photos of 8 MP the process
held 1.2 GB it no longer used, and a panorama's canvas (80 MP: 2 GB of raster and colours) was
then allocated on top. :func:`release_free_memory` asks glibc to return those pages
(``malloc_trim``); where the C library is not glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import cache


@cache
def _malloc_trim():
    """glibc's ``malloc_trim``, or ``None`` where the C library has none (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None


def release_free_memory() -> bool:
    """Return the C heap's free pages to the system; whether the C library could (glibc)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True
