import ctypes.util
import platform

from pis3r import memory


def test_freed_memory_is_handed_back_where_the_c_library_is_glibc():
    assert memory.release_free_memory() is (platform.libc_ver()[0] == "glibc")


def test_without_a_c_library_nothing_is_released(monkeypatch):
    memory._malloc_trim.cache_clear()
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    try:
        assert memory.release_free_memory() is False
    finally:
        memory._malloc_trim.cache_clear()
