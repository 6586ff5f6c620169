"""Training pairs for the refiner, synthesised offline from single photos (spec §10 b).

One pair = (degraded canvas, true image of the canvas camera, validity mask), made
by the same code that stitches at inference:

1. **Ground truth.** A crop of a photo bundled with scikit-image (or a procedural
   texture), colour-jittered, with 0-3 foreground objects cut from other sources
   pasted on top, and a synthetic depth: a random plane or smooth field for the
   backdrop, nearer blobs for the objects. This is the ``size x size`` true image
   of the canvas camera.
2. **Reference view.** A window of that frame (30-65 % per side, anywhere):
   its pixels are copied verbatim into the canvas, exactly as stitching does.
3. **Source view.** A second camera from one of the parallax classes (pure
   rotation, slight, very large baseline; focal 0.5-1.25x the frame's, so its
   points land up to 2x apart on the canvas) sees the 2.5D world; its image is
   forward-splatted at 2x supersampling with a z-buffer. Its photo then gets its
   own exposure / white balance / vignetting, sensor noise, JPEG, blur and
   sometimes motion blur (seams, and the GoPro stage's blur).
4. **Estimated geometry.** The source's depth is perturbed (low-frequency scale
   and shift error, Gaussian noise, edges fattened across discontinuities so that
   mixed-depth flying pixels appear, 0.1-2 % outliers, random point dropout for
   cracks) and its pose too (0.1-1 deg rotation, 0.5-2 % translation of the scene
   depth, 0.5-2 % focal).
5. **Our pipeline.** :func:`pis3r.stitch.render.render_to_canvas` (surfaces, one
   z-buffer, colour sampled from the source) then :func:`pis3r.stitch.holes.fill_holes`
   (closing + Telea + background), and the canvas is cut back to the true frame.
   (The shipped weights were trained on the earlier point-splatting canvases.)
6. **Mask / target.** ``mask`` = 255 rendered, 128 inpainted, 0 background.
   Outside the closed region the target equals the input (residual 0): the model
   learns to leave legitimate voids alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from pis3r.camera import Camera, intrinsics
from pis3r.scene import Scene, View
from pis3r.stitch.holes import fill_holes
from pis3r.stitch.mask import MaskValue, stitch_mask
from pis3r.stitch.render import render_to_canvas

# Photos that ship inside scikit-image (no download). Never the evaluation set.
PHOTO_NAMES = (
    "astronaut", "camera", "chelsea", "coffee", "rocket", "coins", "hubble_deep_field",
    "immunohistochemistry", "moon", "page", "text", "colorwheel", "logo", "grass",
    "gravel", "brick", "cell", "clock", "retina", "stereo_motorcycle",
)  # fmt: skip


@dataclass
class TrainingPair:
    """``degraded``, ``target``: ``(H, W, 3)`` float32 in [0, 1]; ``mask``: ``(H, W)`` uint8
    (255 projected, 128 inpainted, 0 background); ``raw``: the canvas before hole filling
    (the "no hole filling" baseline); ``parallax``: the source camera's class."""

    degraded: np.ndarray
    target: np.ndarray
    mask: np.ndarray
    raw: np.ndarray
    parallax: str


@lru_cache(maxsize=None)
def _photos() -> tuple[np.ndarray, ...]:
    """The bundled photos as float32 RGB ``(H, W, 3)``; ones this install lacks are skipped."""
    import skimage.data

    photos = []
    for name in PHOTO_NAMES:
        try:
            image = getattr(skimage.data, name)()
        except Exception:  # a data file missing from this scikit-image build
            continue
        for array in image if isinstance(image, tuple) else (image,):
            array = np.asarray(array)
            if array.dtype != np.uint8:  # stereo_motorcycle also returns its disparity map
                continue
            if array.ndim == 2:
                array = np.repeat(array[..., None], 3, axis=2)
            photos.append(array[..., :3].astype(np.float32) / 255.0)
    return tuple(photos)


def smooth_field(rng: np.random.Generator, size: int, scale: float) -> np.ndarray:
    """``(size, size)`` float32 noise in about [-1, 1] with features ``scale`` pixels wide."""
    cells = max(2, int(round(size / max(scale, 1.0))) + 1)
    coarse = rng.standard_normal((cells, cells)).astype(np.float32)
    field = cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC)
    return field / (np.abs(field).max() + 1e-6)


def _procedural_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """``(size, size, 3)`` float32: fractal noise, stripes, checkers or random shapes and glyphs."""
    kind = rng.integers(4)
    colours = rng.uniform(0, 1, (2, 3)).astype(np.float32)
    if kind == 0:
        octaves = sum(smooth_field(rng, size, size / 2**k) / 2**k for k in range(1, 6))
        weight = (octaves - octaves.min()) / (np.ptp(octaves) + 1e-6)
    elif kind == 1:
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        angle, period = rng.uniform(0, np.pi), rng.uniform(4, 24)
        weight = 0.5 + 0.5 * np.sin(2 * np.pi * (xx * np.cos(angle) + yy * np.sin(angle)) / period)
    elif kind == 2:
        cell = int(rng.integers(4, 24))
        yy, xx = np.mgrid[0:size, 0:size]
        weight = ((yy // cell + xx // cell) % 2).astype(np.float32)
    else:
        canvas = np.zeros((size, size), np.uint8)  # OpenCV draws text on 8-bit images only
        for _ in range(int(rng.integers(5, 25))):
            value = int(rng.integers(0, 256))
            x, y = (int(v) for v in rng.integers(0, size, 2))
            shape = rng.integers(3)
            if shape == 0:
                cv2.circle(canvas, (x, y), int(rng.integers(2, size // 4)), value, -1)
            elif shape == 1:
                w, h = (int(v) for v in rng.integers(2, size // 3, 2))
                cv2.rectangle(canvas, (x, y), (x + w, y + h), value, -1)
            else:
                text = "".join(chr(int(c)) for c in rng.integers(65, 91, int(rng.integers(2, 7))))
                cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, rng.uniform(0.3, 1.5), value, 1 + int(rng.integers(3)))
        weight = canvas.astype(np.float32) / 255.0
    return colours[0] + (colours[1] - colours[0]) * weight[..., None]


def random_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """``(size, size, 3)`` float32 in [0, 1]: a jittered photo crop (75 %) or a procedural texture."""
    if rng.uniform() < 0.25:
        image = _procedural_texture(rng, size)
    else:
        photos = _photos()
        photo = photos[int(rng.integers(len(photos)))]
        h, w = photo.shape[:2]
        side = int(rng.uniform(0.25, 1.0) * min(h, w))
        y, x = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        image = cv2.resize(photo[y : y + side, x : x + side], (size, size), interpolation=cv2.INTER_AREA)
        if rng.uniform() < 0.5:
            image = image[:, ::-1]
    gain = rng.uniform(0.8, 1.2, 3).astype(np.float32)
    grey = image.mean(axis=2, keepdims=True)
    image = grey + rng.uniform(0.6, 1.3) * (image - grey)
    return np.clip(image * gain, 0, 1) ** rng.uniform(0.8, 1.25)


def _scene_frame(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray]:
    """True image ``(size, size, 3)`` and z-depth ``(size, size)`` of the canvas camera."""
    image = random_texture(rng, size).astype(np.float32)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size - 0.5
    base = rng.uniform(3.0, 8.0)
    if rng.uniform() < 0.5:
        tilt = rng.uniform(-0.6, 0.6, 2)
        depth = base * (1.0 + tilt[0] * xx + tilt[1] * yy)
    else:
        depth = base * (1.0 + 0.3 * smooth_field(rng, size, rng.uniform(0.3, 1.0) * size))
    for _ in range(int(rng.integers(0, 4))):
        blob = smooth_field(rng, size, rng.uniform(0.15, 0.5) * size)
        cx, cy, radius = rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(0.08, 0.3)
        inside = (np.hypot(xx - cx, yy - cy) / radius + 0.35 * blob) < 1.0
        near = rng.uniform(0.35, 0.8) * depth.min() * (1.0 + 0.05 * blob)
        image[inside] = random_texture(rng, size)[inside]
        depth = np.where(inside, near, depth)
    return image, depth.astype(np.float32)


def _rotation(rng: np.random.Generator, degrees: tuple[float, float, float]) -> np.ndarray:
    """``(3, 3)`` rotation with random yaw, pitch, roll up to ``degrees``."""
    angles = np.deg2rad(rng.uniform(-1, 1, 3) * np.asarray(degrees))
    return cv2.Rodrigues(np.array([angles[1], angles[0], angles[2]], dtype=np.float64))[0]


def _source_camera(rng: np.random.Generator, frame: Camera, median_depth: float) -> tuple[Camera, str]:
    """A second camera of one parallax class looking roughly at the frame."""
    parallax = str(rng.choice(["rotation", "slight", "large"], p=[0.25, 0.35, 0.4]))
    R = _rotation(rng, (20.0, 12.0, 4.0))
    baseline = {"rotation": 0.0, "slight": rng.uniform(0.01, 0.04), "large": rng.uniform(0.06, 0.2)}[parallax]
    direction = np.array([rng.uniform(-1, 1), rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3)])
    centre = baseline * median_depth * direction / np.linalg.norm(direction)
    K = frame.K.copy()
    # Down to half the frame's focal: the source's points then land up to 2x apart on
    # the canvas, the dense lattice of cracks a zoomed or distant second photo leaves.
    K[:2, :2] *= rng.uniform(0.5, 1.25)
    return Camera(K, R, -R @ centre, frame.width, frame.height), parallax


def _splat(points: np.ndarray, colours: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-point z-buffer of world ``points (N, 3)`` with ``colours (N, 3)`` into ``camera``:
    image ``(H, W, 3)`` and depth ``(H, W)`` (0 where nothing landed)."""
    uv, z = camera.project(points)
    px, py = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
    keep = (z > 0) & (px >= 0) & (px < camera.width) & (py >= 0) & (py < camera.height)
    flat, z, colours = py[keep] * camera.width + px[keep], z[keep], colours[keep]
    zbuf = np.full(camera.width * camera.height, np.inf)
    np.minimum.at(zbuf, flat, z)
    nearest = z == zbuf[flat]
    image = np.zeros((camera.width * camera.height, 3), np.float32)
    image[flat[nearest]] = colours[nearest]
    depth = np.where(np.isfinite(zbuf), zbuf, 0.0).astype(np.float32)
    return image.reshape(camera.height, camera.width, 3), depth.reshape(camera.height, camera.width)


def _render_source(image: np.ndarray, depth: np.ndarray, frame: Camera, source: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The source camera's view of the 2.5D world ``(image, depth)`` seen by ``frame``.

    The frame is supersampled 2x so the splat leaves no cracks of its own; source
    pixels that see nothing of the frame (disoccluded or outside) get depth 0.
    """
    fine = frame.scaled(2.0)
    fine_image = cv2.resize(image, (fine.width, fine.height), interpolation=cv2.INTER_LINEAR)
    fine_depth = cv2.resize(depth, (fine.width, fine.height), interpolation=cv2.INTER_NEAREST)
    points = fine.unproject(fine_depth).reshape(-1, 3)
    return _splat(points, fine_image.reshape(-1, 3), source)


def _degrade_photo(rng: np.random.Generator, image: np.ndarray) -> np.ndarray:
    """Another camera's rendition: exposure, white balance, vignetting, noise, blur, JPEG."""
    h, w = image.shape[:2]
    out = image * rng.uniform(0.8, 1.2) * rng.uniform(0.9, 1.1, 3).astype(np.float32)
    if rng.uniform() < 0.5:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (0.25 * (w * w + h * h))
        out = out * (1.0 - rng.uniform(0.1, 0.4) * r2)[..., None]
    if rng.uniform() < 0.3:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.2))
    if rng.uniform() < 0.2:
        length = int(rng.integers(3, 9))
        kernel = np.zeros((length, length), np.float32)
        kernel[length // 2] = 1.0 / length
        centre = (length / 2 - 0.5, length / 2 - 0.5)
        kernel = cv2.warpAffine(kernel, cv2.getRotationMatrix2D(centre, rng.uniform(0, 180), 1.0), (length, length))
        out = cv2.filter2D(out, -1, kernel / max(kernel.sum(), 1e-6))
    out = out + rng.normal(0, rng.uniform(0, 0.02), out.shape).astype(np.float32)
    out = np.clip(out, 0, 1)
    if rng.uniform() < 0.5:
        ok, buf = cv2.imencode(".jpg", (out * 255).round().astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(60, 96))])
        out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32) / 255.0
    return out.astype(np.float32)


def _estimated_depth(rng: np.random.Generator, depth: np.ndarray) -> np.ndarray:
    """A reconstruction's depth ``(H, W)``: scale/shift drift, noise, fattened edges,
    outliers and dropped points (0 = no point)."""
    h = depth.shape[0]
    valid = depth > 0
    drift = 1.0 + rng.uniform(-0.04, 0.04) + rng.uniform(0, 0.03) * smooth_field(rng, h, h)
    out = depth * drift + rng.uniform(-0.02, 0.02) * np.median(depth[valid]) if valid.any() else depth
    out = out * (1.0 + rng.normal(0, rng.uniform(0.002, 0.015), depth.shape))
    # Networks smooth depth across occlusion edges: points there land between the
    # two surfaces and become flying pixels.
    radius = int(rng.integers(0, 3))
    if radius:
        blurred = cv2.blur(out.astype(np.float32), (2 * radius + 1, 2 * radius + 1))
        edges = cv2.dilate((cv2.morphologyEx(out.astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3))) > 0.05 * out).astype(np.uint8), np.ones((3, 3)))
        out = np.where(edges > 0, blurred, out)
    outliers = rng.uniform(size=depth.shape) < rng.uniform(0.001, 0.02)
    out = np.where(outliers, out * rng.uniform(0.3, 2.0, depth.shape), out)
    dropped = rng.uniform(size=depth.shape) < (rng.uniform(0, 0.3) if rng.uniform() < 0.5 else 0.0)
    return np.where(valid & ~dropped, out, 0.0).astype(np.float32)


def _perturbed_camera(rng: np.random.Generator, camera: Camera, median_depth: float) -> Camera:
    """``camera`` with a reconstruction's pose and focal error."""
    axis = rng.standard_normal(3)
    delta = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.deg2rad(rng.uniform(0.1, 1.0)))[0]
    shift = rng.standard_normal(3)
    shift *= rng.uniform(0.005, 0.02) * median_depth / np.linalg.norm(shift)
    K = camera.K.copy()
    K[:2, :2] *= 1.0 + rng.choice([-1, 1]) * rng.uniform(0.005, 0.02)
    return Camera(K, delta @ camera.R, camera.t + shift, camera.width, camera.height)


def make_pair(seed: int, size: int = 128) -> TrainingPair:
    """One deterministic training pair of ``size x size`` pixels (see the module docstring)."""
    rng = np.random.default_rng(seed)
    image, depth = _scene_frame(rng, size)
    focal = size * rng.uniform(0.7, 1.4)
    frame = Camera.identity(intrinsics(focal, size, size), size, size)
    median_depth = float(np.median(depth))

    ww, wh = (int(rng.uniform(0.3, 0.65) * size) for _ in range(2))
    wx, wy = int(rng.integers(0, size - ww + 1)), int(rng.integers(0, size - wh + 1))
    ref_camera = frame.shifted(-wx, -wy, ww, wh)
    ref = View(image[wy : wy + wh, wx : wx + ww].copy(), ref_camera, depth[wy : wy + wh, wx : wx + ww].copy(),
               np.ones((wh, ww), np.float32), "ref")  # fmt: skip

    source_camera, parallax = _source_camera(rng, frame, median_depth)
    source_image, source_depth = _render_source(image, depth, frame, source_camera)
    estimated = _estimated_depth(rng, source_depth)
    source = View(_degrade_photo(rng, source_image), _perturbed_camera(rng, source_camera, median_depth),
                  estimated, (estimated > 0).astype(np.float32), "source")  # fmt: skip

    canvas = render_to_canvas(Scene([ref, source]), ref_index=0, max_canvas_scale=size / min(ww, wh) + 1)
    filled = fill_holes(canvas.image, canvas.occupied)
    mask = stitch_mask(canvas.occupied, filled.hole)

    # Canvas pixel (x, y) is frame pixel (x - ox + wx, y - oy + wy).
    ox, oy = canvas.ref_offset
    dx, dy = wx - ox, wy - oy
    degraded = np.zeros_like(image)
    raw = np.zeros_like(image)
    frame_mask = np.full((size, size), MaskValue.BACKGROUND, np.uint8)
    ch, cw = mask.shape
    x0, y0, x1, y1 = max(0, dx), max(0, dy), min(size, cw + dx), min(size, ch + dy)
    window = (slice(y0, y1), slice(x0, x1))
    canvas_window = (slice(y0 - dy, y1 - dy), slice(x0 - dx, x1 - dx))
    degraded[window] = filled.image[canvas_window]
    raw[window] = np.where(canvas.occupied[canvas_window][..., None], canvas.image[canvas_window], 0.0)
    frame_mask[window] = mask[canvas_window]
    target = np.where((frame_mask == MaskValue.BACKGROUND)[..., None], degraded, image)
    return TrainingPair(degraded=degraded, target=target.astype(np.float32), mask=frame_mask, raw=raw, parallax=parallax)
