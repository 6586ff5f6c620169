"""Ground-truth stitching cases: a reference view, a target view and the wide truth.

A case is drawn from a scene and a seed:

- **reference camera**: near the scene's viewpoint, looking roughly down ``+z``.
- **GT camera**: the reference camera on a canvas ``canvas_scale`` times larger in
  width and height, principal point shifted by ``crop_offset`` (the GT pixel of the
  reference pixel (0, 0)); ``gt.png`` is what a perfect stitcher produces and
  ``ref.png`` is exactly its centre crop.
- **target camera**, by parallax class (equal shares in datasets):
  ``rotation``: same centre (``t = 0`` exactly); ``slight``: baseline 0.5-2 % of the
  reference view's near depth (its 25th depth percentile: the median would often be the
  far backdrop, which says little about parallax); ``large``: 25-80 % of it,
  i.e. comparable to the scene depth. Baselines are sideways or forward/backward
  (half each); the rotation is any up to 45 deg. The pose is redrawn until the target
  sees 30-80 % of the reference's pixels, shows at least 10 % of its own pixels in
  the GT canvas outside the reference, and keeps 1 m from every surface.

Everything is expressed in the reference camera frame (reference ``R = I, t = 0``).

Parallax level (``ParallaxLevel``), measured on the full-resolution ground truth over
the co-visible reference pixels (those whose scene point the target sees, unoccluded):

- ``baseline_over_depth``: ``|c_tgt - c_ref|`` / near depth of those points (25th
  percentile of their z in the reference);
- ``max_parallax_px``: largest distance, in target pixels, between where those points
  land and where the pure-rotation homography ``K_tgt R K_ref^-1`` would put them
  (0 for a rotating camera);
- ``homography_residual_pct``: 90th percentile transfer residual of the least-squares
  homography fitted to those correspondences, in % of the image diagonal (what
  :mod:`pis3r.parallax` estimates from feature matches).
"""

from __future__ import annotations

import io as _io
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from pis3r.camera import Camera, intrinsics, rotation_angle_deg, rotation_from_angles, transfer
from pis3r.errors import Pis3rError
from pis3r.io import write_bytes, write_json, write_png
from pis3r.synth.render import NEAR, render, render_depth
from pis3r.synth.scenes import Seed, SynthScene, demo_scene, make_scene

CLASSES = ("rotation", "slight", "large")
BASELINE_RATIO = {"rotation": (0.0, 0.0), "slight": (0.005, 0.02), "large": (0.25, 0.8)}
OVERLAP_RANGE = (0.3, 0.8)
MIN_EXTENSION = 0.1
CLEARANCE_M = 1.0
MAX_ROTATION_DEG = 45.0
NEAR_PERCENTILE = 25  # "near depth" of a view: this percentile of its depths
PROBE_WIDTH = 128  # low-resolution renders used while searching for a valid pose


@dataclass(frozen=True)
class CaseCameras:
    """Cameras of a case in the reference frame; ``crop_offset = (x, y)``: the GT pixel of
    the reference pixel (0, 0) (the reference is ``gt[y:y+H, x:x+W]``)."""

    ref: Camera
    gt: Camera
    tgt: Camera
    crop_offset: tuple[int, int]

    def to_dict(self) -> dict:
        return {
            "frame": "reference camera (OpenCV: x right, y down, z forward; metres)",
            "ref": self.ref.to_dict(),
            "gt": self.gt.to_dict(),
            "tgt": self.tgt.to_dict(),
            "crop_offset": list(self.crop_offset),
        }


@dataclass(frozen=True)
class ParallaxLevel:
    """Class and measured parallax of a pair (definitions in the module docstring).
    ``overlap``: fraction of reference pixels co-visible in the target; ``extension``:
    fraction of target pixels whose point falls outside the reference image."""

    parallax_class: str
    motion: str
    baseline_m: float
    rotation_deg: float
    baseline_over_depth: float
    max_parallax_px: float
    homography_residual_pct: float
    overlap: float
    extension: float


@dataclass
class SynthCase:
    """One stitching case. Images ``(h, w, 3)`` float32 in [0, 1]; depths ``(h, w)``
    float32 camera z. ``gt``/``gt_depth`` are on the GT canvas, ``ref``/``gt_depth_ref``
    its centre crop, ``tgt``/``gt_depth_tgt`` the target's view. ``ref_in_scene``: the
    reference camera in the scene's frame (:func:`in_scene_frame` takes any camera of the
    case there, to render more views). ``seed`` reproduces the case (with the same
    scene); ``None`` when a generator was passed."""

    ref: np.ndarray
    tgt: np.ndarray
    gt: np.ndarray
    gt_depth: np.ndarray
    gt_depth_ref: np.ndarray
    gt_depth_tgt: np.ndarray
    cameras: CaseCameras
    parallax: ParallaxLevel
    ref_in_scene: Camera
    seed: int | list[int] | None


def in_scene_frame(camera: Camera, ref_in_scene: Camera) -> Camera:
    """A camera given in the reference frame, re-expressed in the scene frame."""
    R = camera.R @ ref_in_scene.R
    return Camera(camera.K, R, camera.R @ ref_in_scene.t + camera.t, camera.width, camera.height)


def _reference_pose(rng: np.random.Generator, scene: SynthScene, K: np.ndarray, size: tuple[int, int]) -> Camera:
    """The reference camera in the scene frame: within 1 m of ``scene.home``, yawed up to
    25 deg, pitched -5..8 deg (mostly a little down, as people hold cameras), rolled up to 3 deg."""
    orientation = rotation_from_angles(rng.uniform(-25, 25), rng.uniform(-5, 8), rng.uniform(-3, 3))
    centre = scene.home + np.array([rng.uniform(-1, 1), rng.uniform(-0.3, 0.5), rng.uniform(-1, 1)])
    R = orientation.T
    return Camera(K, R, -R @ centre, *size)


def _target_pose(rng: np.random.Generator, parallax: str, near_depth: float,
                 ref: Camera) -> tuple[Camera, str]:
    """A target camera in the reference frame for a parallax class, and its motion kind."""
    while True:
        orientation = rotation_from_angles(rng.uniform(-45, 45), rng.uniform(-15, 15), rng.uniform(-10, 10))
        if rotation_angle_deg(orientation) <= MAX_ROTATION_DEG:
            break
    R = orientation.T
    if parallax == "rotation":
        return Camera(ref.K, R, np.zeros(3), ref.width, ref.height), "none"
    if rng.random() < 0.5:
        motion = "sideways"
        direction = np.array([rng.choice([-1.0, 1.0]), rng.uniform(-0.2, 0.2), rng.uniform(-0.3, 0.3)])
    else:
        motion = "forward"
        direction = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1), 1.0 if rng.random() < 0.75 else -1.0])
    centre = direction / np.linalg.norm(direction) * rng.uniform(*BASELINE_RATIO[parallax]) * near_depth
    return Camera(ref.K, R, -R @ centre, ref.width, ref.height), motion


def _probe(scene: SynthScene, camera: Camera) -> tuple[Camera, np.ndarray]:
    """A low-resolution depth render of ``camera``: its scaled camera and depth map."""
    small = camera.scaled(PROBE_WIDTH / camera.width)
    return small, render_depth(scene, small)


def gt_canvas(ref: Camera, canvas_scale: float) -> tuple[Camera, tuple[int, int]]:
    """The GT camera: ``ref`` centred on a canvas ``canvas_scale`` times larger (integer
    margins, equal on both sides), and the crop offset of the reference in it."""
    mx = round((canvas_scale - 1.0) / 2.0 * ref.width)
    my = round((canvas_scale - 1.0) / 2.0 * ref.height)
    return ref.shifted(mx, my, ref.width + 2 * mx, ref.height + 2 * my), (mx, my)


def _search_pose(rng: np.random.Generator, scene: SynthScene, K: np.ndarray, size: tuple[int, int],
                 parallax: str, canvas_scale: float) -> tuple[Camera, Camera, str]:
    """Draw reference (scene frame) and target (reference frame) cameras until the pair
    meets the overlap, extension and clearance rules of the module docstring."""
    ref = Camera.identity(K, *size)
    gt, (mx, my) = gt_canvas(ref, canvas_scale)
    for _ in range(40):
        ref_scene = _reference_pose(rng, scene, K, size)
        ref_probe, ref_depth = _probe(scene, ref_scene)
        if ref_depth.min() < CLEARANCE_M:
            continue
        for _ in range(25):
            tgt, motion = _target_pose(rng, parallax, float(np.percentile(ref_depth, NEAR_PERCENTILE)), ref)
            tgt_scene = in_scene_frame(tgt, ref_scene)
            if -tgt_scene.center[1] < CLEARANCE_M / 2:  # stay above the ground plane y = 0
                continue
            tgt_probe, tgt_depth = _probe(scene, tgt_scene)
            if tgt_depth.min() < CLEARANCE_M:
                continue
            overlap = transfer(ref_depth, ref_probe, tgt_probe, tgt_depth, near=NEAR).visible.mean()
            if not OVERLAP_RANGE[0] <= overlap <= OVERLAP_RANGE[1]:
                continue
            landing = transfer(tgt_depth, tgt_probe, in_scene_frame(gt, ref_scene), near=NEAR)
            u, v = landing.uv[..., 0], landing.uv[..., 1]
            inside_ref = (u >= mx) & (u <= mx + size[0] - 1) & (v >= my) & (v <= my + size[1] - 1)
            if (landing.visible & ~inside_ref).mean() >= MIN_EXTENSION:
                return ref_scene, tgt, motion
    raise Pis3rError(f"could not place a {parallax}-parallax camera pair in this scene")


def measure_parallax(parallax: str, motion: str, ref: Camera, tgt: Camera, depth_ref: np.ndarray,
                     depth_tgt: np.ndarray) -> ParallaxLevel:
    """The parallax level of a pair from its exact depths (definitions: module docstring)."""
    seen = transfer(depth_ref, ref, tgt, depth_tgt, near=NEAR)
    co_visible = seen.visible
    baseline = float(np.linalg.norm(tgt.center - ref.center))
    R = tgt.R @ ref.R.T
    v, u = np.nonzero(co_visible)
    pixels = np.stack([u, v], axis=1).astype(np.float64)
    landed = seen.uv[co_visible]
    infinite = np.hstack([pixels, np.ones((len(pixels), 1))]) @ (tgt.K @ R @ np.linalg.inv(ref.K)).T
    drift = np.linalg.norm(landed - infinite[:, :2] / infinite[:, 2:], axis=1)
    sample = np.linspace(0, len(pixels) - 1, min(len(pixels), 4000)).astype(int)
    H, _ = cv2.findHomography(pixels[sample], landed[sample], 0)
    fitted = cv2.perspectiveTransform(pixels[sample, None], H)[:, 0]
    residual = np.linalg.norm(fitted - landed[sample], axis=1)
    outside = ~transfer(depth_tgt, tgt, ref, near=NEAR).visible
    return ParallaxLevel(
        parallax_class=parallax,
        motion=motion,
        baseline_m=baseline,
        rotation_deg=rotation_angle_deg(R),
        baseline_over_depth=baseline / float(np.percentile(depth_ref[co_visible], NEAR_PERCENTILE)),
        max_parallax_px=float(drift.max()),
        homography_residual_pct=float(np.percentile(residual, 90) / np.hypot(ref.width, ref.height) * 100),
        overlap=float(co_visible.mean()),
        extension=float((outside & np.isfinite(depth_tgt)).mean()),
    )


def make_case(seed: Seed, size: tuple[int, int] = (640, 480), parallax: str | None = None,
              scene: SynthScene | None = None, canvas_scale: float = 1.6, supersample: int = 2) -> SynthCase:
    """Render one ground-truth stitching case.

    ``seed``: an int, a sequence of ints or a numpy Generator (drives scene, cameras,
    class when ``parallax`` is None); ``size``: ``(W, H)`` of reference and target;
    ``parallax``: ``rotation`` | ``slight`` | ``large``; ``scene``: reuse a scene (a
    random :func:`make_scene` otherwise); ``canvas_scale``: GT canvas size over ``size``;
    ``supersample``: samples per pixel side for colour.
    """
    rng = np.random.default_rng(seed)
    parallax = parallax or CLASSES[int(rng.integers(len(CLASSES)))]
    if parallax not in CLASSES:
        raise ValueError(f"parallax must be one of {CLASSES}, got {parallax!r}")
    scene = scene if scene is not None else make_scene(rng)
    width, height = size
    focal = width / 2.0 / np.tan(np.radians(rng.uniform(50.0, 75.0)) / 2.0)  # horizontal FOV 50-75 deg
    K = intrinsics(focal, width, height)
    ref_scene, tgt, motion = _search_pose(rng, scene, K, (width, height), parallax, canvas_scale)
    ref = Camera.identity(K, width, height)
    gt, (mx, my) = gt_canvas(ref, canvas_scale)
    wide = render(scene, in_scene_frame(gt, ref_scene), supersample)
    target = render(scene, in_scene_frame(tgt, ref_scene), supersample)
    crop = (slice(my, my + height), slice(mx, mx + width))
    return SynthCase(
        ref=wide.image[crop].copy(),
        tgt=target.image,
        gt=wide.image,
        gt_depth=wide.depth,
        gt_depth_ref=wide.depth[crop].copy(),
        gt_depth_tgt=target.depth,
        cameras=CaseCameras(ref, gt, tgt, (mx, my)),
        parallax=measure_parallax(parallax, motion, ref, tgt, wide.depth[crop], target.depth),
        ref_in_scene=ref_scene,
        seed=_seed_record(seed),
    )


def _seed_record(seed: Seed) -> int | list[int] | None:
    """The seed as JSON can hold it; a Generator cannot be recorded."""
    if isinstance(seed, np.random.Generator):
        return None
    return int(seed) if np.ndim(seed) == 0 else [int(s) for s in seed]


def demo_pair(size: tuple[int, int] = (480, 360), seed: int = 0) -> SynthCase:
    """A small very-large-parallax case: photo panels at ~3, 7 and 16 m and two boxes
    in front of a far backdrop (see :func:`pis3r.synth.scenes.demo_scene`)."""
    return make_case(seed, size, "large", scene=demo_scene(seed))


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = _io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array, dtype=np.float32))
    return buffer.getvalue()


def write_case(case: SynthCase, directory: str | Path) -> None:
    """Write ``ref.png, tgt.png, gt.png, cameras.json, gt_depth_ref.npy, gt_depth_tgt.npy,
    case.json`` into ``directory`` (each file atomically)."""
    out = Path(directory)
    write_png(out / "ref.png", case.ref)
    write_png(out / "tgt.png", case.tgt)
    write_png(out / "gt.png", case.gt)
    write_bytes(out / "gt_depth_ref.npy", _npy_bytes(case.gt_depth_ref))
    write_bytes(out / "gt_depth_tgt.npy", _npy_bytes(case.gt_depth_tgt))
    write_json(out / "cameras.json", case.cameras.to_dict())
    write_json(out / "case.json", {**asdict(case.parallax), "seed": case.seed,
                                   "size": [case.ref.shape[1], case.ref.shape[0]]})
