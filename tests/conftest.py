import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("PIS3R_DEBUG", "")

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REAL = SHARED / "data" / "real"
PANORAMA = SHARED / "data" / "panorama"


def real_pairs() -> list[Path]:
    """Pair folders (ref.*, tgt.*) of the development set, or [] without ../shared."""
    if not REAL.is_dir():
        return []
    return sorted(p for p in REAL.iterdir() if p.is_dir() and list(p.glob("ref.*")) and list(p.glob("tgt.*")))


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` imported as module ``benchmarks_<name>`` (benchmarks/ is no
    package), registered in ``sys.modules``: a benchmark's dataclasses look their module up by name."""
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", Path(__file__).resolve().parents[1]
                                                  / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


needs_real_data = pytest.mark.skipif(
    not REAL.is_dir(), reason=f"real image pairs not found at {REAL} (../shared is absent)"
)
needs_panorama_data = pytest.mark.skipif(
    not PANORAMA.is_dir(), reason=f"panorama sets not found at {PANORAMA} (../shared is absent)"
)


@pytest.fixture(scope="session")
def small_pair():
    """Two overlapping 190x160 crops of one photo, uint8 RGB (reference first)."""
    from skimage import data

    photo = data.astronaut()[::2, ::2]
    return photo[20:180, 0:190].copy(), photo[30:190, 60:250].copy()


@pytest.fixture(scope="session")
def small_result(small_pair):
    """``pis3r.stitch`` of ``small_pair`` (classical backend), computed once per session."""
    import pis3r

    return pis3r.stitch(list(small_pair), backend="classical")
