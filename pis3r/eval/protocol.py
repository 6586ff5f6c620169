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
- ``ext_psnr/ssim/lpips``: the whole extension with unfilled pixels black ("failures scored
  as an empty extension").

A failure is scored as an empty result: the padded reference alone, valid everywhere, so
its ``valid_*`` and ``ext_*`` scores count black wherever the GT extends the reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pis3r.camera import Camera
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
# Pixels whose bilinear warp mixes in more than this share of unfilled canvas are not valid.
VALID_WEIGHT = 0.999


@dataclass(frozen=True)
class Case:
    """One stitching problem with ground truth.

    ``reference`` ``(h, w, 3)``: the input the result must be a perspective image of; it is
    ``gt[y:y+h, x:x+w]`` for ``crop_offset = (x, y)`` (GT pixel of reference pixel (0, 0)).
    ``target`` ``(h2, w2, 3)``: the other input. ``gt`` ``(H, W, 3)``: the wide ground truth.
    All float32 RGB in [0, 1]. ``parallax_class``: ``rotation`` | ``slight`` | ``large`` |
    ``unknown``; ``parallax_level``: the dataset's own continuous level (NaN when it has
    none). ``cameras``: GT cameras ``{"ref", "tgt", "gt": Camera}`` when the dataset is
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
) -> Case:
    """The paper's real-world construction for a pair folder (``ref.*`` = A, ``tgt.*`` = B):
    reference = centre crop of A keeping ``crop`` of each side, target = B, GT = A."""
    pair_dir = Path(pair_dir)
    path_a, path_b = find_image(pair_dir, "ref"), find_image(pair_dir, "tgt")
    if path_a is None or path_b is None:
        raise InputError(f"{pair_dir}: not a pair folder (needs ref.* and tgt.* images)")
    return crop_case(
        read_image(path_a).pixels,
        read_image(path_b).pixels,
        crop,
        name=pair_dir.name,
        dataset=dataset or pair_dir.parent.name,
        parallax_class=parallax_class,
    )


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


def load_pair_cases(root: str | Path, crop: float = 0.6) -> list[Case]:
    """Crop-protocol cases for every pair folder directly under ``root`` (sorted by name),
    classed from ``root/SOURCES.md`` when there is one."""
    root = Path(root)
    sources = root / "SOURCES.md"
    classes = parallax_classes_from_sources(sources) if sources.is_file() else {}
    return [
        load_crop_case(folder, crop, classes.get(folder.name, UNKNOWN_CLASS), dataset=root.name)
        for folder in sorted(root.iterdir())
        if folder.is_dir() and is_pair_dir(folder)
    ]


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


def _sift(image_u8: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    sift = cv2.SIFT_create(nfeatures=8000)
    keypoints, descriptors = sift.detectAndCompute(cv2.cvtColor(image_u8, cv2.COLOR_RGB2GRAY), mask)
    return np.array([kp.pt for kp in keypoints], np.float32).reshape(-1, 2), descriptors


def register(image: np.ndarray, filled: np.ndarray, case: Case) -> Registration:
    """Register a stitched canvas ``(h, w, 3)`` (``filled`` ``(h, w)`` bool) to the padded
    reference: SIFT inside the filled area and inside the reference crop, Lowe ratio test,
    MAGSAC homography. Fails (``homography=None``) with too few inliers or a homography that
    changes areas by more than ``MAX_AREA_CHANGE``."""
    # Erode so that SIFT does not fire on the border between content and empty canvas.
    canvas_mask = cv2.erode(filled.astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    pts_canvas, desc_canvas = _sift(to_uint8(image), canvas_mask)
    pts_ref, desc_ref = _sift(to_uint8(case.padded_reference), case.reference_region.astype(np.uint8) * 255)
    if desc_canvas is None or desc_ref is None or len(pts_canvas) < 2 or len(pts_ref) < 2:
        return Registration(None, 0, 0, "no features")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_canvas, desc_ref, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    if len(good) < MIN_INLIERS:
        return Registration(None, len(good), 0, f"{len(good)} matches")
    src = pts_canvas[[m.queryIdx for m in good]]
    dst = pts_ref[[m.trainIdx for m in good]]
    homography, inlier_mask = cv2.findHomography(
        src, dst, cv2.USAC_MAGSAC, MAGSAC_THRESHOLD_PX, maxIters=10000, confidence=0.999
    )
    inliers = int(inlier_mask.sum()) if inlier_mask is not None else 0
    if homography is None or inliers < MIN_INLIERS:
        return Registration(None, len(good), inliers, f"{inliers} inliers")
    area_change = abs(np.linalg.det(homography[:2, :2] / homography[2, 2]))
    if not 1.0 / MAX_AREA_CHANGE <= area_change <= MAX_AREA_CHANGE:
        return Registration(None, len(good), inliers, f"degenerate homography (area x{area_change:.2g})")
    return Registration(homography, len(good), inliers)


# --------------------------------------------------------------------------- scores


def score_placed(placed: Placed, case: Case, failed: bool = False, lpips_device: str = "cpu") -> dict:
    """Scores of a result on the GT grid (see the module docstring for each key).

    ``failed``: the result stands for a failure, so ``valid_*`` are taken over the whole GT
    frame (black where nothing was filled) instead of over the filled pixels.
    Returns ``{valid_psnr, valid_ssim, valid_lpips, fill_psnr, fill_ssim, fill_lpips,
    coverage, ext_psnr, ext_ssim, ext_lpips}`` (NaN where a region is empty)."""
    extension = ~case.reference_region
    valid = np.ones_like(placed.filled) if failed else placed.filled
    scores = {
        **_quality(placed.image, case.gt, valid, "valid", lpips_device),
        **_quality(placed.image, case.gt, extension & placed.filled, "fill", lpips_device),
        **_quality(placed.image, case.gt, extension, "ext", lpips_device),
    }
    scores["coverage"] = float(metrics.coverage(placed.filled, extension)) if extension.any() else math.nan
    return scores


def _quality(image: np.ndarray, gt: np.ndarray, mask: np.ndarray, prefix: str, lpips_device: str) -> dict:
    if not mask.any():
        return {f"{prefix}_psnr": math.nan, f"{prefix}_ssim": math.nan, f"{prefix}_lpips": math.nan}
    return {
        f"{prefix}_psnr": float(metrics.psnr(image, gt, mask=mask)),
        f"{prefix}_ssim": float(metrics.ssim(image, gt, mask=mask)),
        f"{prefix}_lpips": float(metrics.lpips(image, gt, mask=mask, device=lpips_device)),
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
    registration = register(image, filled, case)
    if registration.ok:
        scores = score_placed(place(image, filled, registration.homography, case), case, lpips_device=lpips_device)
    else:
        scores = score_failure(case, lpips_device)
    return {**scores, "registered": registration.ok, "reg_inliers": registration.inliers,
            "reg_reason": registration.reason}


def score_failure(case: Case, lpips_device: str = "cpu") -> dict:
    """Scores of a method that produced nothing usable (crash, timeout, refusal, unregistrable)."""
    return score_placed(empty_result(case), case, failed=True, lpips_device=lpips_device)
