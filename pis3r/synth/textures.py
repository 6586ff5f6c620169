"""Textures for synthetic scenes: real photographs plus procedural patterns.

Every texture is a square ``(S, S, 3)`` uint8 image. Photos come from the images
scikit-image ships inside its wheel (no network) and from any folder the user
names; procedural ones (noise, checker, bricks, sky, near-flat paint) are drawn
from a random generator so each scene gets its own.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from pis3r.errors import InputError
from pis3r.io import read_image, to_uint8

TEXTURE_SIZE = 512

# Photos inside scikit-image's wheel (skimage/data/), read as files: importing
# skimage.data costs a second, and its other images (brain, kidney, eagle, ...) are
# downloaded on first use, which must never happen here.
SKIMAGE_PHOTOS = (
    "astronaut.png", "camera.png", "chelsea.png", "coffee.png", "rocket.jpg", "coins.png", "moon.png",
    "page.png", "hubble_deep_field.jpg", "ihc.png", "motorcycle_left.png",
)
# Grey photos of real materials: tinted per surface so one photo gives many materials.
SKIMAGE_MATERIALS = ("brick.png", "grass.png", "gravel.png")

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}


@dataclass(frozen=True)
class Texture:
    """One texture layer: ``pixels (S, S, 3)`` uint8; ``kind`` is ``photo`` (real,
    colour or grey), ``material`` (grey real surface to tint), ``pattern``
    (procedural, textured), ``flat`` (almost uniform: low texture), ``sky`` or
    ``landscape`` (far hills under a sky, for the backdrop)."""

    name: str
    pixels: np.ndarray
    kind: str


def square(image: np.ndarray, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Centre square crop of an RGB image ``(H, W, 3)`` (uint8, or float in [0, 1]) resized
    to ``(size, size, 3)`` uint8 (area filter when shrinking)."""
    rgb = image if image.dtype == np.uint8 else to_uint8(image)
    h, w = rgb.shape[:2]
    side = min(h, w)
    y0, x0 = (h - side) // 2, (w - side) // 2
    crop = np.ascontiguousarray(rgb[y0 : y0 + side, x0 : x0 + side])
    interpolation = cv2.INTER_AREA if side >= size else cv2.INTER_CUBIC
    return cv2.resize(crop, (size, size), interpolation=interpolation)


@functools.lru_cache(maxsize=1)
def skimage_textures() -> tuple[Texture, ...]:
    """The bundled scikit-image photos and materials as textures (loaded once); a file a
    future scikit-image no longer bundles is skipped."""
    import skimage

    folder = Path(skimage.__file__).parent / "data"

    def load(file: str, kind: str) -> Texture:
        with Image.open(folder / file) as image:  # PIL: quiet about page.png's odd ICC profile
            return Texture(Path(file).stem, square(np.asarray(image.convert("RGB"))), kind)

    files = [(f, "photo") for f in SKIMAGE_PHOTOS] + [(f, "material") for f in SKIMAGE_MATERIALS]
    return tuple(load(f, kind) for f, kind in files if (folder / f).is_file())


def folder_textures(folder: str | Path) -> tuple[Texture, ...]:
    """Every readable image in ``folder`` (not recursive) as a ``photo`` texture, sorted by name.

    Raises :class:`InputError` when the folder is missing or holds no readable image.
    """
    path = Path(folder)
    if not path.is_dir():
        raise InputError(f"--textures {path}: not a directory")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    textures = []
    for file in files:
        try:
            textures.append(Texture(file.name, square(read_image(file).pixels), "photo"))
        except InputError:
            continue  # one broken file in a texture folder should not stop a dataset
    if not textures:
        raise InputError(f"--textures {path}: no readable images ({', '.join(sorted(IMAGE_SUFFIXES))})")
    return tuple(textures)


@functools.lru_cache(maxsize=16)
def _amplitude(size: int, slope: float, lowest: float) -> np.ndarray:
    """``f**-slope`` on the ``rfft2`` grid of a ``size``-square texture, 0 below ``lowest``."""
    fy = np.fft.fftfreq(size)[:, None] * size
    fx = np.fft.rfftfreq(size)[None, :] * size
    freq = np.hypot(fx, fy)
    return np.where(freq >= lowest, np.maximum(freq, 1.0) ** -slope, 0.0).astype(np.float32)


def periodic_noise(rng: np.random.Generator, size: int, slope: float = 1.5, lowest: float = 2.0) -> np.ndarray:
    """Tileable fractal noise ``(size, size)`` float32 in [0, 1], made in the Fourier domain:
    random complex coefficients with amplitude ``f**-slope`` for ``f >= lowest`` cycles per
    texture (larger ``slope``: smoother; larger ``lowest``: smaller blobs)."""
    amplitude = _amplitude(size, slope, lowest)
    real, imag = rng.standard_normal((2, *amplitude.shape), dtype=np.float32)
    noise = np.fft.irfft2(amplitude * (real + 1j * imag), s=(size, size)).astype(np.float32)
    noise -= noise.min()
    return noise / max(float(noise.max()), 1e-12)


def _mix(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Blend colours ``a, b (3,)`` by ``weight (S, S)`` into ``(S, S, 3)``."""
    return a * (1.0 - weight[..., None]) + b * weight[..., None]


def _two_shades(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random colour and a darker, slightly shifted shade of it (natural-looking pairs)."""
    light = rng.uniform(0.25, 0.95, 3)
    return light, np.clip(light * rng.uniform(0.35, 0.75) + rng.uniform(-0.08, 0.08, 3), 0.0, 1.0)


def noise_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Two shades blended by fractal noise (a stucco / terrain look)."""
    return to_uint8(_mix(*_two_shades(rng), periodic_noise(rng, size)))


def checker_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A checkerboard of 4..16 squares per side in two shades (tiles), with faint grain."""
    cells = int(rng.choice([4, 8, 16]))
    idx = np.arange(size) * cells // size
    board = ((idx[:, None] + idx[None, :]) % 2).astype(np.float32)
    grain = 0.08 * (periodic_noise(rng, size, slope=0.5, lowest=32) - 0.5)
    return to_uint8(_mix(*_two_shades(rng), board) + grain[..., None])


def bricks_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Running-bond bricks with light mortar, per-brick colour jitter and noise."""
    rows = int(rng.integers(6, 14))
    cols = max(2, rows // 2)
    brick_h, brick_w = size / rows, size / cols
    y, x = np.mgrid[0:size, 0:size].astype(float)
    row = np.floor(y / brick_h).astype(int)
    shifted = x + (row % 2) * brick_w / 2.0
    col = np.floor(shifted / brick_w).astype(int) % cols
    mortar_px = max(2.0, 0.08 * brick_h)
    mortar = (y - row * brick_h < mortar_px) | (shifted % brick_w < mortar_px)
    base = np.array([0.55, 0.25, 0.18]) * rng.uniform(0.6, 1.3, 3)
    jitter = rng.uniform(0.8, 1.2, (rows, cols))[row, col]
    grain = periodic_noise(rng, size, slope=1.0, lowest=8)
    image = base * jitter[..., None] * (0.75 + 0.5 * grain[..., None])
    image[mortar] = rng.uniform(0.6, 0.85) * (0.85 + 0.3 * grain[mortar, None])
    return to_uint8(image)


def flat_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Almost uniform paint (a low-texture surface): one colour, +-2 grey levels of noise."""
    colour = rng.uniform(0.2, 0.9, 3)
    return to_uint8(colour + (4.0 / 255.0) * (periodic_noise(rng, size) - 0.5)[..., None])


def _sky(rng: np.random.Generator, size: int, blue: np.ndarray) -> np.ndarray:
    """``blue (3,)`` with white clouds where smooth noise is high, ``(size, size, 3)`` float."""
    clouds = np.clip((periodic_noise(rng, size, slope=2.0, lowest=1) - 0.5) * 2.5, 0.0, 1.0)
    return _mix(blue, np.array([0.95, 0.95, 0.97]), clouds)


def sky_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """Blue sky with soft clouds: smooth, little texture (as a real sky)."""
    return to_uint8(_sky(rng, size, np.array([0.35, 0.55, 0.9]) * rng.uniform(0.8, 1.1)))


def landscape_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> np.ndarray:
    """A far landscape for the backdrop wall (row 0 = top): two ranges of fractal hills
    (the farther one hazier) over the bottom 10-45 %, hazy sky with clouds above."""
    image = _sky(rng, size, np.array([0.5, 0.65, 0.9]) * rng.uniform(0.85, 1.1))
    rows = np.arange(size)[:, None]
    for haze, (low, high) in ((0.45, (0.25, 0.45)), (0.0, (0.1, 0.3))):  # far range first
        profile = periodic_noise(rng, size, slope=1.5, lowest=1)[0]  # one row: a 1-D fractal
        profile = (profile - profile.min()) / max(float(np.ptp(profile)), 1e-12)
        ridge = size * (1.0 - low - (high - low) * profile)
        terrain = _mix(np.array([0.25, 0.4, 0.15]) * rng.uniform(0.7, 1.2, 3),
                       np.array([0.45, 0.38, 0.28]) * rng.uniform(0.7, 1.2, 3), periodic_noise(rng, size, slope=1.2))
        terrain = terrain * (1.0 - haze) + haze * np.array([0.6, 0.68, 0.8])
        image = np.where((rows >= ridge[None, :])[..., None], terrain, image)
    return to_uint8(image)


PATTERNS = (noise_texture, checker_texture, bricks_texture)
