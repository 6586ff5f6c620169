"""Random 3D scenes with strong depth variation, as textured triangle meshes.

Frame: the scene's world frame has the OpenCV orientation of an upright camera:
x right, **y down**, z forward. The ground is the plane ``y = 0``; "up" is ``-y``;
heights are therefore negative y. Objects stand in front of (``+z``) a nominal
viewpoint ``SynthScene.home`` above the origin, inside a far cylindrical backdrop with a
sky cap, so every viewing ray hits something (no empty pixels) and the depth range
is far beyond 10x (objects from ~3 m, backdrop at 120-300 m).

Shading is Lambertian from one sun direction and baked into per-triangle colours,
so a surface point has the same colour from every viewpoint (what makes the
ground truth of a stitching case exact).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np

from pis3r.synth.textures import (
    PATTERNS,
    Texture,
    flat_texture,
    landscape_texture,
    skimage_textures,
    sky_texture,
)

AMBIENT = 0.45
UP = np.array([0.0, -1.0, 0.0])

Seed = Union[int, Sequence[int], np.random.Generator]


@dataclass(frozen=True)
class Mesh:
    """A triangle soup: three consecutive vertices per triangle.

    ``positions (3T, 3)`` float32 world points; ``uv (3T, 2)`` float32 texture
    coordinates, 1.0 = one texture width, repeated mirrored beyond [0, 1];
    ``texture_id (T,)`` int32 layer of ``SynthScene.textures``; ``color (T, 3)`` float32
    RGB multiplier (tint times shading).
    """

    positions: np.ndarray
    uv: np.ndarray
    texture_id: np.ndarray
    color: np.ndarray

    @property
    def triangles(self) -> int:
        return len(self.texture_id)

    @staticmethod
    def concat(parts: list["Mesh"]) -> "Mesh":
        return Mesh(
            np.concatenate([p.positions for p in parts]).astype(np.float32),
            np.concatenate([p.uv for p in parts]).astype(np.float32),
            np.concatenate([p.texture_id for p in parts]).astype(np.int32),
            np.concatenate([p.color for p in parts]).astype(np.float32),
        )

    def normals(self) -> np.ndarray:
        """Unit face normals ``(T, 3)`` (orientation arbitrary)."""
        p = self.positions.reshape(-1, 3, 3).astype(np.float64)
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def lit(self, sun: np.ndarray) -> "Mesh":
        """This mesh with two-sided Lambert shading from unit direction ``sun (3,)`` baked in."""
        shade = AMBIENT + (1.0 - AMBIENT) * np.abs(self.normals() @ sun)
        return Mesh(self.positions, self.uv, self.texture_id, self.color * shade[:, None].astype(np.float32))


@dataclass(eq=False)
class SynthScene:
    """A renderable scene. ``mesh``: all geometry; ``textures (L, S, S, 3)`` uint8 layers
    with their ``texture_names``; ``home (3,)``: nominal camera centre (scene frame)
    looking down ``+z``, around which the case generator places reference cameras."""

    mesh: Mesh
    textures: np.ndarray
    texture_names: tuple[str, ...]
    home: np.ndarray


def quad(corners: np.ndarray, tile: tuple[float, float], texture: int, tint: np.ndarray, u0: float = 0.0) -> Mesh:
    """Planar quad ``corners (4, 3)`` in order top-left, top-right, bottom-right,
    bottom-left (as seen from the front); the texture repeats every ``tile`` metres
    along (top edge, left edge), starting at ``u0`` at the left; its row 0 is at the top."""
    c = np.asarray(corners, dtype=np.float64)
    u1 = u0 + np.linalg.norm(c[1] - c[0]) / tile[0]
    height = np.linalg.norm(c[3] - c[0]) / tile[1]
    uv = np.array([[u0, 0], [u1, 0], [u1, height], [u0, height]], dtype=np.float64)
    order = [0, 1, 2, 0, 2, 3]
    return Mesh(c[order], uv[order], np.full(2, texture), np.tile(tint, (2, 1)))


def _upright_quad(bottom_centre: np.ndarray, normal: np.ndarray, width: float, height: float,
                  tile: tuple[float, float], texture: int, tint: np.ndarray) -> Mesh:
    """Vertical quad standing on ``bottom_centre``, facing horizontal ``normal``; upright texture."""
    right = np.cross(-UP, -normal)  # camera "right" of a viewer looking at the face: down x forward
    half = right * width / 2.0
    top = UP * height
    b = np.asarray(bottom_centre, dtype=np.float64)
    return quad(np.array([b - half + top, b + half + top, b + half, b - half]), tile, texture, tint)


def _yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about the vertical axis by ``yaw`` radians (x towards z)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def box(centre_xz: tuple[float, float], size: tuple[float, float, float], yaw: float, texture: int,
        tint: np.ndarray, tile: float, base: float = 0.0) -> Mesh:
    """Box of ``size`` (width x, height, depth z) standing at height ``base`` (metres above
    the ground) on ``centre_xz``, turned by ``yaw``; four sides and the top (the bottom is
    never seen from above the ground)."""
    w, h, d = size
    rot = _yaw_matrix(yaw)
    centre = np.array([centre_xz[0], -base, centre_xz[1]])
    faces = []
    for normal, width, offset in (((0, 0, -1), w, d), ((0, 0, 1), w, d), ((-1, 0, 0), d, w), ((1, 0, 0), d, w)):
        n = rot @ np.array(normal, dtype=np.float64)
        faces.append(_upright_quad(centre + n * offset / 2.0, n, width, h, (tile, tile), texture, tint))
    x, z = rot @ np.array([w / 2, 0, 0]), rot @ np.array([0, 0, d / 2])
    top = centre + UP * h
    faces.append(quad(np.array([top - x + z, top + x + z, top + x - z, top - x - z]), (tile, tile), texture, tint))
    return Mesh.concat(faces)


def cylinder(centre_xz: tuple[float, float], radius: float, height: float, segments: int, texture: int,
             tint: np.ndarray, tile: tuple[float, float], cap_texture: int | None = None,
             cap_tile: float = 1.0) -> Mesh:
    """Upright open cylinder (``segments`` flat sides) on the ground, with an optional top
    cap (a fan of triangles, planar texture every ``cap_tile`` metres)."""
    angles = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    centre = np.array([centre_xz[0], 0.0, centre_xz[1]])
    rim = centre + radius * np.stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)], axis=1)
    side = 2.0 * radius * np.sin(np.pi / segments)
    parts = [quad(np.array([a + UP * height, b + UP * height, b, a]), tile, texture, tint, u0=k * side / tile[0])
             for k, (a, b) in enumerate(zip(rim[:-1], rim[1:]))]  # u runs on around the cylinder
    if cap_texture is not None:
        top = rim + UP * height
        apex = centre + UP * height
        fan = np.stack([np.repeat(apex[None], segments, 0), top[:-1], top[1:]], axis=1).reshape(-1, 3)
        parts.append(Mesh(fan, fan[:, [0, 2]] / cap_tile, np.full(segments, cap_texture),
                          np.tile(tint, (segments, 1))))
    return Mesh.concat(parts)


class _Palette:
    """The texture layers of one scene and how surfaces draw from them."""

    def __init__(self, rng: np.random.Generator, extra: tuple[Texture, ...]) -> None:
        library = skimage_textures() + tuple(extra)
        photos = [t for t in library if t.kind == "photo"]
        chosen = sorted(rng.choice(len(photos), size=min(6, len(photos)), replace=False))
        self.layers = [photos[i] for i in chosen] + [t for t in library if t.kind == "material"]
        self.layers += [Texture(make.__name__, make(rng), "pattern") for make in PATTERNS]
        self.layers += [Texture("flat", flat_texture(rng), "flat") for _ in range(2)]
        self.layers += [Texture("sky", sky_texture(rng), "sky")]
        self.layers += [Texture("landscape", landscape_texture(rng), "landscape")]
        self.rng = rng
        self.used: set[int] = set()

    def pick(self, *kinds: str) -> tuple[int, np.ndarray]:
        """A random layer of one of ``kinds`` (one not used yet while there is one, for
        variety) and the tint to use it with."""
        options = [i for i, t in enumerate(self.layers) if t.kind in kinds]
        options = [i for i in options if i not in self.used] or options
        layer = int(options[self.rng.integers(len(options))])
        self.used.add(layer)
        kind = self.layers[layer].kind
        if kind == "material":  # grey photos of brick/grass/gravel: colour them
            tint = self.rng.uniform(0.45, 1.0, 3)
        elif kind == "photo":
            tint = self.rng.uniform(0.85, 1.0, 3)
        else:  # procedural layers carry their own colours
            tint = np.ones(3)
        return layer, tint

    def scene(self, parts: list[Mesh], unlit: list[Mesh], home: np.ndarray) -> SynthScene:
        """Assemble: ``parts`` get the sun's shading, ``unlit`` (backdrop, sky) keep their colour."""
        elevation, azimuth = np.radians(self.rng.uniform(25, 70)), self.rng.uniform(0, 2 * np.pi)
        sun = np.array([np.cos(elevation) * np.cos(azimuth), -np.sin(elevation), np.cos(elevation) * np.sin(azimuth)])
        mesh = Mesh.concat([Mesh.concat(parts).lit(sun)] + unlit)
        textures = np.stack([t.pixels for t in self.layers])
        return SynthScene(mesh, textures, tuple(t.name for t in self.layers), home)


def _surroundings(palette: _Palette, rng: np.random.Generator) -> tuple[Mesh, list[Mesh]]:
    """Ground square and the far world: a cylindrical backdrop of radius 120-300 m (far
    hills, or a photo mural in one scene of four) up to 45 deg elevation, closed by a sky
    cap. Returns (ground, [backdrop])."""
    r = rng.uniform(120.0, 300.0)
    layer, tint = palette.pick("material", "pattern")
    tile = rng.uniform(2.5, 6.0)
    ground = quad(np.array([[-r, 0, r], [r, 0, r], [r, 0, -r], [-r, 0, -r]]), (tile, tile), layer, tint)
    wall_layer, wall_tint = palette.pick("photo" if rng.random() < 0.25 else "landscape")
    sky_layer, _ = palette.pick("sky")
    backdrop = cylinder((0.0, 0.0), r, r, 64, wall_layer, wall_tint, (r, r), cap_texture=sky_layer, cap_tile=r)
    return ground, [backdrop]


def _placement(rng: np.random.Generator, near: float, far: float, extent: float,
               spread_deg: float = 90.0) -> tuple[tuple[float, float], float]:
    """Ground position (x, z) at a random azimuth within +-``spread_deg`` of +z and a
    log-uniform distance in [near, far], pushed out so an object of half-size ``extent``
    keeps 2 m from the origin (where cameras stand); and a yaw roughly facing the origin."""
    azimuth = np.radians(rng.uniform(-spread_deg, spread_deg))
    distance = max(np.exp(rng.uniform(np.log(near), np.log(far))), extent + 2.0)
    yaw = azimuth + np.radians(rng.uniform(-35, 35))
    return (distance * np.sin(azimuth), distance * np.cos(azimuth)), yaw


def make_scene(seed: Seed, extra_textures: tuple[Texture, ...] = ()) -> SynthScene:
    """A random outdoor-like scene: textured ground, 2-4 walls, 5-10 boxes, 3-8 poles,
    0-2 stairs, 1-3 billboards from 3 to about 50 m, some surfaces almost textureless,
    inside a far backdrop and sky (see module docstring for the frame). ``seed``: int,
    sequence of ints or numpy Generator; ``extra_textures``: more photos to draw from."""
    rng = np.random.default_rng(seed)
    palette = _Palette(rng, extra_textures)
    ground, unlit = _surroundings(palette, rng)
    parts = [ground]
    for _ in range(rng.integers(2, 5)):  # walls
        length, height = rng.uniform(6, 20), rng.uniform(2, 5)
        where, yaw = _placement(rng, 8, 40, length / 2, spread_deg=80)
        layer, tint = palette.pick("material", "pattern", "photo", "flat")
        tile = length if palette.layers[layer].kind == "photo" else rng.uniform(1, 3)
        parts.append(box(where, (length, height, 0.3), yaw, layer, tint, tile))
    for _ in range(rng.integers(5, 11)):  # boxes
        size = rng.uniform(0.5, 3.0, 3)
        where, yaw = _placement(rng, 3, 30, size.max())
        layer, tint = palette.pick("photo", "material", "pattern", "flat")
        tile = size.max() if palette.layers[layer].kind == "photo" else rng.uniform(0.5, 2)
        parts.append(box(where, tuple(size), yaw, layer, tint, tile))
    for _ in range(rng.integers(3, 9)):  # poles
        radius, height = rng.uniform(0.08, 0.3), rng.uniform(3, 8)
        where, _ = _placement(rng, 3, 25, radius)
        layer, tint = palette.pick("flat", "material")
        parts.append(cylinder(where, radius, height, 10, layer, tint, (1.0, 1.0)))
    for _ in range(rng.integers(0, 3)):  # stairs: adjacent boxes of growing height
        steps, rise = int(rng.integers(4, 9)), rng.uniform(0.15, 0.3)
        run, width = rng.uniform(0.25, 0.45), rng.uniform(1.5, 4)
        where, yaw = _placement(rng, 5, 20, max(width, steps * run))
        layer, tint = palette.pick("material", "pattern", "flat")
        forward = _yaw_matrix(yaw) @ np.array([0.0, 0.0, 1.0])
        for i in range(steps):
            offset = (i - steps / 2 + 0.5) * run
            parts.append(box((where[0] + forward[0] * offset, where[1] + forward[2] * offset),
                             (width, (i + 1) * rise, run), yaw, layer, tint, 1.0))
    for _ in range(rng.integers(1, 4)):  # billboards: a photo panel on two legs
        width, panel, legs = rng.uniform(1.5, 4), rng.uniform(1, 2.5), rng.uniform(0.5, 2)
        where, yaw = _placement(rng, 4, 25, width / 2)
        layer, tint = palette.pick("photo")
        parts.append(box(where, (width, panel, 0.12), yaw, layer, tint, max(width, panel), base=legs))
        side = _yaw_matrix(yaw) @ np.array([width / 2 - 0.1, 0.0, 0.0])
        leg_layer, leg_tint = palette.pick("flat")
        for sign in (-1, 1):
            parts.append(cylinder((where[0] + sign * side[0], where[1] + sign * side[2]), 0.05,
                                  legs + panel / 2, 8, leg_layer, leg_tint, (1.0, 1.0)))
    return palette.scene(parts, unlit, home=np.array([0.0, -1.6, 0.0]))


def demo_scene(seed: Seed) -> SynthScene:
    """A small scene for demos and analytic tests: three photo panels facing the viewpoint
    at about 3, 7 and 16 m, two boxes, textured ground, far backdrop and sky."""
    rng = np.random.default_rng(seed)
    palette = _Palette(rng, ())
    ground, unlit = _surroundings(palette, rng)
    parts = [ground]
    for distance, x, width in ((3.0, -0.8, 1.6), (7.0, 1.5, 3.5), (16.0, -2.0, 8.0)):
        layer, tint = palette.pick("photo")
        parts.append(box((x, distance), (width, 0.75 * width, 0.1), rng.uniform(-0.3, 0.3), layer, tint, width))
    for x, z in ((2.2, 4.5), (-3.0, 10.0)):
        layer, tint = palette.pick("material", "pattern")
        parts.append(box((x, z), tuple(rng.uniform(0.8, 1.6, 3)), rng.uniform(0, np.pi), layer, tint, 1.0))
    return palette.scene(parts, unlit, home=np.array([0.0, -1.4, 0.0]))
