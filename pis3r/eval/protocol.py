"""The evaluation protocol: cases with ground truth, placing a stitched canvas on the GT grid, scores.

A :class:`Case` is one stitching problem with a ground-truth wide view: the reference is a
crop of the GT (at ``crop_offset``), the target is another photo. Two ways to put a method's
stitched canvas on the GT grid:

- **exact** (:func:`score_exact`): for methods that export where the reference landed on
  their canvas (pis3r's ``ref_offset``) — a pure translation, no registration;
- **registered** (:func:`score_registered`, the paper's "pad, register, compute"): pad the
  reference to the GT size at its offset and register the stitched image to it with one
  feature-based homography (SIFT + MAGSAC), the same for every method. A method whose output
  cannot be registered (or that crashed) is a registration failure (RSR).

Scores (all on the GT grid; a method's "filled" pixels are those it produced anything for):

- ``valid_psnr/ssim/lpips``: every valid (filled) pixel, reference area included (paper
  Step 3);
- ``fill_psnr/ssim/lpips``: the extension (GT outside the reference crop) where the method
  filled it;
- ``coverage``: share of the extension the method filled — a method must not win by filling
  nothing;
- ``ext_psnr/ssim/lpips``: the whole extension with unfilled pixels black (strict: what a
  method leaves out counts as black);
- ``bar_psnr/ssim/lpips``: issue 2's bar — "extension region only, failures scored as an
  empty extension": ``fill_*`` for a result, ``ext_*`` of the empty result for a failure.

A failure is scored as an empty result: the padded reference alone, valid everywhere, so
its ``valid_*``, ``ext_*`` and ``bar_*`` scores count black wherever the GT extends the
reference.

Cases come from a folder (:func:`discover_cases`, :func:`load_case`): ``pis3r synth``
output, pair folders under the crop protocol, and the calibrated scenes of the development
set. Geometry (:func:`score_geometry`, :func:`pose_error`) needs their GT cameras.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pis3r.camera import Camera, fundamental_matrix
from pis3r.camera import relative_pose as camera_relative_pose
from pis3r.errors import InputError
from pis3r.eval import metrics
from pis3r.io import read_image, to_uint8

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
PARALLAX_CLASSES = ("rotation", "slight", "large")
UNKNOWN_CLASS = "unknown"

# Registration: Lowe's ratio, MAGSAC threshold (px), and what counts as a usable homography.
RATIO = 0.75
MAGSAC_THRESHOLD_PX = 3.0
MIN_INLIERS = 15
# A stitched canvas is (close to) the reference's own perspective: a homography that
# shrinks or grows areas by more than this is a wrong registration, not a result.
MAX_AREA_CHANGE = 4.0
# Geometry: matches between two canvases farther than this (px) from a fundamental matrix
# fitted to them are mismatches, not distortion.
GEOMETRY_OUTLIER_PX = 8.0
# Pixels whose bilinear warp mixes in more than this share of unfilled canvas are not valid.
VALID_WEIGHT = 0.999


@dataclass(frozen=True)
class Case:
    """One stitching problem with ground truth.

    ``reference`` ``(h, w, 3)``: the input the result must be a perspective image of; it is
    ``gt[y:y+h, x:x+w]`` for ``crop_offset = (x, y)`` (GT pixel of reference pixel (0, 0)).
    ``target`` ``(h2, w2, 3)``: the other input. ``gt`` ``(H, W, 3)``: the wide ground truth.
    All float32 RGB in [0, 1]. ``parallax_class``: ``rotation`` | ``slight`` | ``large`` |
    ``unknown``; ``parallax_level``: the dataset's own continuous level (synthetic: GT
    homography residual in % of the diagonal; calibrated scenes: baseline / depth; NaN
    when it has none). ``cameras``: GT cameras ``{"ref", "tgt", "gt": Camera}`` when the dataset is
    calibrated, else ``None``.
    """

    name: str
    dataset: str
    reference: np.ndarray
    target: np.ndarray
    gt: np.ndarray
    crop_offset: tuple[int, int]
    parallax_class: str = UNKNOWN_CLASS
    parallax_level: float = math.nan
    cameras: dict | None = None

    @property
    def reference_region(self) -> np.ndarray:
        """``(H, W)`` bool: GT pixels covered by the reference."""
        region = np.zeros(self.gt.shape[:2], bool)
        x, y = self.crop_offset
        h, w = self.reference.shape[:2]
        region[y : y + h, x : x + w] = True
        return region

    @property
    def padded_reference(self) -> np.ndarray:
        """``(H, W, 3)``: the reference at its offset on the GT grid, black elsewhere (Step 1)."""
        padded = np.zeros_like(self.gt)
        x, y = self.crop_offset
        h, w = self.reference.shape[:2]
        padded[y : y + h, x : x + w] = self.reference
        return padded


@dataclass(frozen=True)
class Placed:
    """A method's result on the GT grid: ``image`` ``(H, W, 3)`` (black where unfilled) and
    ``filled`` ``(H, W)`` bool."""

    image: np.ndarray
    filled: np.ndarray


@dataclass(frozen=True)
class Registration:
    """Outcome of registering a stitched canvas to the padded reference.

    ``homography`` ``(3, 3)`` maps canvas pixels to GT pixels, ``None`` on failure
    (``reason`` says why). ``matches`` / ``inliers``: SIFT matches and MAGSAC inliers.
    """

    homography: np.ndarray | None
    matches: int
    inliers: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.homography is not None


# --------------------------------------------------------------------------- cases


def find_image(folder: Path, stem: str) -> Path | None:
    """The file ``folder/stem.<image suffix>``, or ``None``."""
    for path in sorted(Path(folder).glob(f"{stem}.*")):
        if path.suffix.lower() in IMAGE_SUFFIXES:
            return path
    return None


def is_pair_dir(folder: Path) -> bool:
    """A pair folder holds ``ref.*`` and ``tgt.*`` images."""
    return find_image(folder, "ref") is not None and find_image(folder, "tgt") is not None


def centre_crop_box(width: int, height: int, crop: float) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` of the centred crop keeping ``crop`` of each side. The centre stays
    put so a crop of a photo is still a photo of the same camera (principal point centred)."""
    if not 0.0 < crop <= 1.0:
        raise InputError(f"--crop must be in (0, 1], got {crop}")
    w, h = max(1, round(width * crop)), max(1, round(height * crop))
    return (width - w) // 2, (height - h) // 2, w, h


def load_crop_case(
    pair_dir: str | Path,
    crop: float = 0.6,
    parallax_class: str = UNKNOWN_CLASS,
    dataset: str | None = None,
    name: str | None = None,
) -> Case:
    """The paper's real-world construction for a pair folder (``ref.*`` = A, ``tgt.*`` = B):
    reference = centre crop of A keeping ``crop`` of each side, target = B, GT = A. A
    ``gt.txt`` next to them (ScanNet) gives the GT cameras."""
    pair_dir = Path(pair_dir)
    path_a, path_b = find_image(pair_dir, "ref"), find_image(pair_dir, "tgt")
    if path_a is None or path_b is None:
        raise InputError(f"{pair_dir}: not a pair folder (needs ref.* and tgt.* images)")
    images = [read_image(path_a).pixels, read_image(path_b).pixels]
    gt_txt = pair_dir / "gt.txt"
    cameras = scannet_cameras(gt_txt, images) if gt_txt.is_file() else None
    return crop_case(*images, crop, name or pair_dir.name, dataset or pair_dir.parent.name,
                     parallax_class, cameras=cameras)


def crop_case(
    image_a: np.ndarray,
    image_b: np.ndarray,
    crop: float,
    name: str,
    dataset: str,
    parallax_class: str = UNKNOWN_CLASS,
    parallax_level: float = math.nan,
    cameras: tuple[Camera, Camera] | None = None,
) -> Case:
    """Crop-protocol case from two ``(H, W, 3)`` photos; ``cameras`` = GT cameras of A and B
    (their images' full sizes), turned into ``{"ref", "tgt", "gt"}`` with the crop applied."""
    height, width = image_a.shape[:2]
    x, y, w, h = centre_crop_box(width, height, crop)
    gt_cameras = None
    if cameras is not None:
        cam_a, cam_b = cameras
        K_ref = cam_a.K.copy()
        K_ref[:2, 2] -= (x, y)
        gt_cameras = {"gt": cam_a, "tgt": cam_b, "ref": Camera(K_ref, cam_a.R, cam_a.t, w, h)}
    return Case(
        name=name,
        dataset=dataset,
        reference=np.ascontiguousarray(image_a[y : y + h, x : x + w]),
        target=image_b,
        gt=image_a,
        crop_offset=(x, y),
        parallax_class=parallax_class,
        parallax_level=parallax_level,
        cameras=gt_cameras,
    )


def parallax_classes_from_sources(sources_md: str | Path) -> dict[str, str]:
    """``{folder: class}`` from the "parallax class" column of every table in a SOURCES.md.

    Cells are free text ("slight-to-moderate (...)"); their leading words decide:
    "pure rotation..." -> ``rotation``, "slight..." -> ``slight``, "very large..." -> ``large``.
    """
    classes: dict[str, str] = {}
    column = None
    for line in Path(sources_md).read_text(encoding="utf-8").splitlines():
        if not line.startswith("|"):
            column = None
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if column is None:
            column = cells.index("parallax class") if "parallax class" in cells else -1
            continue
        if column < 0 or column >= len(cells) or set(cells[0]) <= {"-", ":"}:
            continue
        classes[cells[0]] = class_from_text(cells[column])
    return classes


def class_from_text(text: str) -> str:
    """``rotation`` | ``slight`` | ``large`` | ``unknown`` from a free-text description."""
    text = text.lower()
    for prefix, cls in (("pure rotation", "rotation"), ("slight", "slight"), ("very large", "large")):
        if text.startswith(prefix):
            return cls
    return UNKNOWN_CLASS


# Calibrated scenes of shared/data/real (SOURCES.md): view pairs (A, B) and their GT
# baseline / median depth. Up to this level a stitched pair counts as slight parallax.
CALIBRATED_PAIRS = {
    "strecha-fountain-P11": ((4, 5, 0.20), (3, 6, 0.55), (2, 8, 1.15), (0, 10, 1.62)),
    "strecha-Herz-Jesus-P8": ((3, 4, 0.16), (2, 5, 0.34), (0, 7, 0.72)),
    "middlebury-templeRing": ((13, 14, 0.13), (13, 16, 0.40), (13, 19, 0.77), (13, 25, 1.43)),
}
SLIGHT_MAX_BASELINE_OVER_DEPTH = 0.2


@dataclass(frozen=True)
class CaseSpec:
    """Where a case comes from, small enough to ship to a worker: ``kind`` is ``synth``
    (a ``pis3r synth`` pair folder with ``gt.png``), ``pair`` (a pair folder, crop
    protocol) or ``calibrated`` (views ``view_a``, ``view_b`` of a calibrated scene)."""

    name: str
    dataset: str
    kind: str
    folder: str
    parallax_class: str = UNKNOWN_CLASS
    parallax_level: float = math.nan
    view_a: int = -1
    view_b: int = -1


def discover_cases(root: str | Path) -> list[CaseSpec]:
    """Every case under ``root``, sorted by name: ``pis3r synth`` pair folders (any depth),
    pair folders (``ref.*`` + ``tgt.*``) and the calibrated scenes of ``CALIBRATED_PAIRS``.
    Parallax classes of pair folders come from a ``SOURCES.md`` in ``root`` if present."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: no such dataset folder")
    sources = root / "SOURCES.md"
    classes = parallax_classes_from_sources(sources) if sources.is_file() else {}
    specs = []
    for folder in sorted(p for p in root.rglob("*") if p.is_dir()):
        name = folder.relative_to(root).as_posix()
        if folder.name in CALIBRATED_PAIRS:
            for a, b, level in CALIBRATED_PAIRS[folder.name]:
                cls = "slight" if level <= SLIGHT_MAX_BASELINE_OVER_DEPTH else "large"
                specs.append(CaseSpec(f"{name}/{a}-{b}", root.name, "calibrated", str(folder), cls, level, a, b))
        elif is_pair_dir(folder) and find_image(folder, "gt") is not None:
            info = json.loads((folder / "case.json").read_text())
            specs.append(CaseSpec(name, root.name, "synth", str(folder), info["parallax_class"],
                                  float(info["homography_residual_pct"])))
        elif is_pair_dir(folder):
            # ScanNet pairs (gt.txt) are calibrated; SOURCES.md gives their class in prose.
            cls = classes.get(folder.name, "large" if (folder / "gt.txt").is_file() else UNKNOWN_CLASS)
            specs.append(CaseSpec(name, root.name, "pair", str(folder), cls))
    if not specs:
        raise InputError(f"{root}: no cases (pair folders with ref.* and tgt.*, or `pis3r synth` output)")
    return specs


def load_case(spec: CaseSpec, crop: float = 0.6) -> Case:
    """Read the images (and GT cameras where known) of a case. ``crop`` applies to pair
    folders and calibrated scenes; ``pis3r synth`` cases bring their own ground truth."""
    folder = Path(spec.folder)
    if spec.kind == "synth":
        cameras = json.loads((folder / "cameras.json").read_text())
        return Case(
            name=spec.name,
            dataset=spec.dataset,
            reference=read_image(find_image(folder, "ref")).pixels,
            target=read_image(find_image(folder, "tgt")).pixels,
            gt=read_image(find_image(folder, "gt")).pixels,
            crop_offset=tuple(int(v) for v in cameras["crop_offset"]),
            parallax_class=spec.parallax_class,
            parallax_level=spec.parallax_level,
            cameras={key: Camera.from_dict(cameras[key]) for key in ("ref", "gt", "tgt")},
        )
    if spec.kind == "pair":
        return load_crop_case(folder, crop, spec.parallax_class, spec.dataset, spec.name)
    images, cameras = calibrated_views(folder, (spec.view_a, spec.view_b))
    return crop_case(*images, crop, spec.name, spec.dataset, spec.parallax_class, spec.parallax_level, cameras)


def calibrated_views(folder: Path, views: tuple[int, int]) -> tuple[list[np.ndarray], tuple[Camera, Camera]]:
    """Images and GT cameras of two views of a Strecha or Middlebury scene (formats in
    shared/data/real/SOURCES.md)."""
    if folder.name.startswith("strecha"):
        paths = [folder / "images" / f"{v:04d}.jpg" for v in views]
        images = [read_image(p).pixels for p in paths]
        scale = dict(line.split(maxsplit=1) for line in (folder / "scale.txt").read_text().splitlines() if line.strip())
        sx, sy = float(scale["sx"]), float(scale["sy"])
        cameras = tuple(
            strecha_camera(folder / "cameras" / f"{p.name}.camera", sx, sy, image.shape[1], image.shape[0])
            for p, image in zip(paths, images)
        )
        return images, cameras
    rows = {}
    for line in (folder / "templeR_par.txt").read_text().splitlines()[1:]:
        fields = line.split()
        if len(fields) == 22:
            rows[fields[0]] = np.array(fields[1:], np.float64)
    names = [f"templeR{v:04d}.png" for v in views]
    images = [read_image(folder / "images" / name).pixels for name in names]
    cameras = tuple(
        Camera(rows[name][:9], rows[name][9:18], rows[name][18:], image.shape[1], image.shape[0])
        for name, image in zip(names, images)
    )
    return images, cameras


def strecha_camera(path: Path, sx: float, sy: float, width: int, height: int) -> Camera:
    """A Strecha ``.camera`` file (K, distortion, camera-to-world R, centre C, size; full
    resolution) as a world-to-camera :class:`Camera` of an image downscaled by ``sx, sy``."""
    values = np.array(path.read_text().split(), np.float64)
    K = values[:9].reshape(3, 3) * np.array([[sx], [sy], [1.0]])
    R_cam_to_world, centre = values[12:21].reshape(3, 3), values[21:24]
    R = R_cam_to_world.T
    return Camera(K, R, -R @ centre, width, height)


def scannet_cameras(gt_txt: Path, images: list[np.ndarray]) -> tuple[Camera, Camera]:
    """GT cameras of a ScanNet pair (``name0 name1 rot0 rot1 K0 K1 T_0to1``, SuperGlue's
    format): camera 0 at the origin, ``x_cam1 = R x_cam0 + t``."""
    values = np.array(gt_txt.read_text().split()[4:], np.float64)
    K0, K1, T = values[:9], values[9:18], values[18:34].reshape(4, 4)
    (h0, w0), (h1, w1) = images[0].shape[:2], images[1].shape[:2]
    return Camera(K0, np.eye(3), np.zeros(3), w0, h0), Camera(K1, T[:3, :3], T[:3, 3], w1, h1)


# --------------------------------------------------------------------------- placing


def place(image: np.ndarray, filled: np.ndarray, homography: np.ndarray, case: Case) -> Placed:
    """Warp a canvas ``(h, w, 3)`` with its ``filled`` ``(h, w)`` bool onto the GT grid through
    ``homography`` (canvas px -> GT px). Bilinear; a GT pixel is filled only when (almost) all
    of its interpolation weight comes from filled canvas pixels."""
    height, width = case.gt.shape[:2]
    flags = cv2.INTER_LINEAR
    warped = cv2.warpPerspective(
        np.where(filled[..., None], image, 0).astype(np.float32), homography, (width, height), flags=flags
    )
    weight = cv2.warpPerspective(filled.astype(np.float32), homography, (width, height), flags=flags)
    valid = weight >= VALID_WEIGHT
    return Placed(np.where(valid[..., None], np.clip(warped, 0.0, 1.0), 0.0).astype(np.float32), valid)


def translation(dx: float, dy: float) -> np.ndarray:
    """``(3, 3)`` homography of a shift by ``(dx, dy)`` px."""
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def exact_homography(ref_offset: tuple[int, int], case: Case) -> np.ndarray:
    """Canvas -> GT shift that puts the canvas's reference (at ``ref_offset``) on the crop."""
    return translation(case.crop_offset[0] - ref_offset[0], case.crop_offset[1] - ref_offset[1])


def empty_result(case: Case) -> Placed:
    """What a failed method leaves: the padded reference, nothing else filled."""
    return Placed(case.padded_reference, case.reference_region)


# --------------------------------------------------------------------------- registration


def _sift(image: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoints ``(N, 2)`` and descriptors of ``(H, W, 3)`` ``image`` inside ``mask``
    ``(H, W)`` bool, eroded so that no keypoint sits on the edge of the content."""
    mask_u8 = cv2.erode(mask.astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    gray = cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2GRAY)
    keypoints, descriptors = cv2.SIFT_create(nfeatures=8000).detectAndCompute(gray, mask_u8)
    return np.array([kp.pt for kp in keypoints], np.float32).reshape(-1, 2), descriptors


def match_images(image_a: np.ndarray, mask_a: np.ndarray, image_b: np.ndarray, mask_b: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches (Lowe's ratio ``RATIO``) between two images, each inside its mask:
    ``(N, 2)``, ``(N, 2)`` float32 pixels of a and of b."""
    pts_a, desc_a = _sift(image_a, mask_a)
    pts_b, desc_b = _sift(image_b, mask_b)
    if desc_a is None or desc_b is None or len(pts_a) < 2 or len(pts_b) < 2:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    return pts_a[[m.queryIdx for m in good]].reshape(-1, 2), pts_b[[m.trainIdx for m in good]].reshape(-1, 2)


def register(image: np.ndarray, filled: np.ndarray, case: Case) -> Registration:
    """Register a stitched canvas ``(h, w, 3)`` (``filled`` ``(h, w)`` bool) to the padded
    reference: SIFT inside the filled area and inside the reference crop, Lowe's ratio test,
    MAGSAC homography. Fails (``homography=None``) with too few inliers or a homography that
    changes areas by more than ``MAX_AREA_CHANGE``."""
    src, dst = match_images(image, filled, case.padded_reference, case.reference_region)
    if len(src) < MIN_INLIERS:
        return Registration(None, len(src), 0, f"{len(src)} matches")
    homography, inlier_mask = cv2.findHomography(
        src, dst, cv2.USAC_MAGSAC, MAGSAC_THRESHOLD_PX, maxIters=10000, confidence=0.999
    )
    inliers = int(inlier_mask.sum()) if inlier_mask is not None else 0
    if homography is None or inliers < MIN_INLIERS:
        return Registration(None, len(src), inliers, f"{inliers} inliers")
    area_change = abs(np.linalg.det(homography[:2, :2] / homography[2, 2]))
    if not 1.0 / MAX_AREA_CHANGE <= area_change <= MAX_AREA_CHANGE:
        return Registration(None, len(src), inliers, f"degenerate homography (area x{area_change:.2g})")
    return Registration(homography, len(src), inliers)


# --------------------------------------------------------------------------- scores


def score_placed(placed: Placed, case: Case, failed: bool = False, lpips_device: str = "cpu") -> dict:
    """Scores of a result on the GT grid (see the module docstring for each key).

    ``failed``: the result stands for a failure, so ``valid_*`` are taken over the whole GT
    frame (black where nothing was filled) instead of over the filled pixels.
    Returns ``{valid_*, fill_*, ext_*, bar_*, coverage}`` with ``* = psnr, ssim, lpips``
    (NaN where a region is empty)."""
    extension = ~case.reference_region
    regions = {
        "valid": np.ones_like(placed.filled) if failed else placed.filled,
        "fill": extension & placed.filled,
        "ext": extension,
    }
    # Unfilled pixels are black in placed.image, so one LPIPS map serves every region.
    distance = lpips_map(placed.image, case.gt, lpips_device)
    scores = {}
    for prefix, mask in regions.items():
        scores.update(_quality(placed.image, case.gt, mask, distance, prefix))
    bar = "ext" if failed else "fill"
    scores.update({f"bar_{metric}": scores[f"{bar}_{metric}"] for metric in ("psnr", "ssim", "lpips")})
    scores["coverage"] = float(metrics.coverage(placed.filled, extension)) if extension.any() else math.nan
    return scores


def lpips_map(image: np.ndarray, gt: np.ndarray, device: str = "cpu") -> np.ndarray:
    """``(H, W)`` LPIPS-Alex distance map of two ``(H, W, 3)`` images: the map whose mean
    over a mask is ``metrics.lpips(image, gt, mask)``, computed once for several masks."""
    import torch

    from pis3r.eval.lpips import lpips_model

    def to_tensor(array: np.ndarray) -> torch.Tensor:
        pixels = torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1), dtype=np.float32))
        return (pixels[None] * 2 - 1).to(device)

    with torch.no_grad():
        return lpips_model(str(device)).distance_map(to_tensor(image), to_tensor(gt))[0, 0].cpu().numpy()


def _quality(image: np.ndarray, gt: np.ndarray, mask: np.ndarray, distance: np.ndarray, prefix: str) -> dict:
    """PSNR, SSIM and LPIPS (mean of the ``distance`` map) over ``mask``, keys ``prefix_*``."""
    if not mask.any():
        return {f"{prefix}_psnr": math.nan, f"{prefix}_ssim": math.nan, f"{prefix}_lpips": math.nan}
    try:
        ssim = float(metrics.ssim(image, gt, mask=mask))
    except InputError:  # the region lies entirely in the 5-px border SSIM does not score
        ssim = math.nan
    return {
        f"{prefix}_psnr": float(metrics.psnr(image, gt, mask=mask)),
        f"{prefix}_ssim": ssim,
        f"{prefix}_lpips": float(distance[mask].mean()),
    }


def _image_and_filled(stitched, filled: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(image, filled)`` from a :class:`pis3r.api.StitchResult`-like object (``.image``,
    ``.mask`` with 0 = background) or an ``(h, w, 3)`` image (all filled unless told)."""
    if hasattr(stitched, "image"):
        image = stitched.image
        filled = stitched.mask > 0 if filled is None else filled
    else:
        image = stitched
    if filled is None:
        filled = np.ones(image.shape[:2], bool)
    return np.asarray(image, np.float32), np.asarray(filled, bool)


def score_exact(stitched, ref_offset: tuple[int, int], case: Case, filled: np.ndarray | None = None,
                lpips_device: str = "cpu") -> dict:
    """Score a canvas placed with its exported reference offset, no registration.

    ``stitched``: a ``StitchResult`` (its ``mask`` gives the filled pixels) or an
    ``(h, w, 3)`` image with ``filled`` ``(h, w)`` bool. ``ref_offset``: ``(x, y)`` canvas
    pixel of the reference's pixel (0, 0). Returns :func:`score_placed`'s dict."""
    image, filled = _image_and_filled(stitched, filled)
    placed = place(image, filled, exact_homography(ref_offset, case), case)
    return score_placed(placed, case, lpips_device=lpips_device)


def score_registered(stitched, case: Case, filled: np.ndarray | None = None, lpips_device: str = "cpu") -> dict:
    """The paper's protocol: register the canvas to the padded reference, then score.

    Returns :func:`score_placed`'s dict plus ``registered`` (bool), ``reg_inliers`` and
    ``reg_reason``; a failed registration is scored as :func:`empty_result`."""
    image, filled = _image_and_filled(stitched, filled)
    return register_and_score(image, filled, case, lpips_device)[0]


def register_and_score(image: np.ndarray, filled: np.ndarray, case: Case, lpips_device: str = "cpu"
                       ) -> tuple[dict, Placed | None]:
    """:func:`score_registered` of a canvas ``(h, w, 3)`` with ``filled`` ``(h, w)``, and the
    registered result on the GT grid (``None`` when registration failed)."""
    registration = register(image, filled, case)
    placed = place(image, filled, registration.homography, case) if registration.ok else None
    if placed is not None:
        scores = score_placed(placed, case, lpips_device=lpips_device)
    else:
        scores = score_failure(case, lpips_device)
    return {**scores, "registered": registration.ok, "reg_inliers": registration.inliers,
            "reg_reason": registration.reason}, placed


def score_failure(case: Case, lpips_device: str = "cpu") -> dict:
    """Scores of a method that produced nothing usable (crash, timeout, refusal, unregistrable)."""
    return score_placed(empty_result(case), case, failed=True, lpips_device=lpips_device)


# --------------------------------------------------------------------------- geometry


def score_geometry(canvas_ref: tuple[np.ndarray, np.ndarray, tuple[int, int]],
                   canvas_tgt: tuple[np.ndarray, np.ndarray, tuple[int, int]], case: Case) -> dict:
    """Sampson epipolar error (paper eq. 11) between the two canvases of a pair, one in the
    reference camera's view and one in the target's, against the GT fundamental matrix of
    the two canvas cameras (GT cameras with the principal point moved by each canvas's offset).

    Each canvas is ``(image (h, w, 3), filled (h, w) bool, offset (x, y))`` where ``offset``
    is the canvas pixel of its own camera's pixel (0, 0). SIFT matches between the canvases
    are cleaned of gross mismatches by a loose MAGSAC fundamental matrix fitted to the
    matches themselves (``GEOMETRY_OUTLIER_PX``): that keeps any consistent distortion of the
    stitched images, which is what the GT matrix measures. Returns ``{sampson_mean,
    sampson_median (px²), sampson_matches}``."""
    (image_a, filled_a, offset_a), (image_b, filled_b, offset_b) = canvas_ref, canvas_tgt
    camera_a = case.cameras["ref"].shifted(*offset_a, image_a.shape[1], image_a.shape[0])
    camera_b = case.cameras["tgt"].shifted(*offset_b, image_b.shape[1], image_b.shape[0])
    pts_a, pts_b = match_images(image_a, filled_a, image_b, filled_b)
    if len(pts_a) >= 8:
        _, inliers = cv2.findFundamentalMat(pts_a, pts_b, cv2.USAC_MAGSAC, GEOMETRY_OUTLIER_PX, 0.999, 10000)
        if inliers is not None:
            pts_a, pts_b = pts_a[inliers.ravel() > 0], pts_b[inliers.ravel() > 0]
    errors = metrics.sampson_error(fundamental_matrix(camera_a, camera_b), pts_a, pts_b) if len(pts_a) >= 8 else []
    # A rotating pair has no epipolar geometry (F = 0): every error is NaN.
    errors = np.asarray(errors)[np.isfinite(errors)]
    if not len(errors):
        return {"sampson_mean": math.nan, "sampson_median": math.nan, "sampson_matches": len(pts_a)}
    return {"sampson_mean": float(errors.mean()), "sampson_median": float(np.median(errors)),
            "sampson_matches": len(pts_a)}


def pose_error(relative_pose: np.ndarray, case: Case) -> dict:
    """Error of a reconstructed relative pose ``(3, 4)`` ``[R | t]`` (reference camera ->
    target camera, ``x_tgt = R x_ref + t``) against the GT cameras: ``rotation_error_deg``
    (angle of ``R_est R_gt^T``) and ``translation_error_deg`` (angle between the translation
    directions; NaN when either has none, e.g. a rotating camera)."""
    R_gt, t_gt = camera_relative_pose(case.cameras["ref"], case.cameras["tgt"])
    R, t = relative_pose[:, :3], relative_pose[:, 3]
    cos_rotation = np.clip((np.trace(R @ R_gt.T) - 1.0) / 2.0, -1.0, 1.0)
    norms = np.linalg.norm(t) * np.linalg.norm(t_gt)
    translation = math.degrees(math.acos(np.clip(t @ t_gt / norms, -1.0, 1.0))) if norms > 1e-12 else math.nan
    return {"rotation_error_deg": math.degrees(math.acos(cos_rotation)), "translation_error_deg": translation}
