"""Synthetic stitching cases with exact ground truth (``pis3r synth``).

Scenes (:mod:`.scenes`) are textured meshes with strong depth variation; they are
rendered headless with moderngl + EGL as exact OpenCV pinhole cameras (:mod:`.render`);
:mod:`.cases` draws reference / target / wide ground-truth views per parallax class.
"""

from pis3r.synth.cases import CLASSES, CaseCameras, ParallaxLevel, SynthCase, demo_pair, make_case, write_case
from pis3r.synth.scenes import SynthScene, make_scene

__all__ = [
    "CLASSES", "CaseCameras", "ParallaxLevel", "SynthCase", "SynthScene", "demo_pair", "make_case", "make_scene",
    "write_case",
]
