"""Evaluation cases with ground truth: discovery under a folder and the dataset parsers.

An :class:`EvalCase` is one stitching problem with a ground-truth wide view: the reference
is a crop of the GT (at ``crop_offset``), the target is another photo. Cases come from a
folder (:func:`discover_cases` lists them as small :class:`CaseSpec` records, :func:`load_case`
reads one): ``pis3r synth`` output, pair folders under the crop protocol (``ref.*`` = A,
``tgt.*`` = B, reference = centre crop of A, GT = A; a ScanNet ``gt.txt`` adds GT cameras),
and the calibrated Strecha / Middlebury templeRing scenes of the development set.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pis3r.camera import Camera
from pis3r.errors import InputError
from pis3r.io import read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
PARALLAX_CLASSES = ("rotation", "slight", "large")
UNKNOWN_CLASS = "unknown"


@dataclass(frozen=True)
class EvalCase:
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
) -> EvalCase:
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
) -> EvalCase:
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
    return EvalCase(
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
    return {folder: class_from_text(text) for folder, text in parallax_labels_from_sources(sources_md).items()}


def parallax_labels_from_sources(sources_md: str | Path) -> dict[str, str]:
    """``{folder: text}``: the "parallax class" cell of each row of every table in a SOURCES.md
    that has that column (tables without it, such as calibrated scenes', are skipped)."""
    labels: dict[str, str] = {}
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
        labels[cells[0]] = cells[column]
    return labels


def class_from_text(text: str) -> str:
    """``rotation`` | ``slight`` | ``large`` | ``unknown`` from a free-text description."""
    text = text.lower()
    for prefix, parallax_class in (("pure rotation", "rotation"), ("slight", "slight"), ("very large", "large")):
        if text.startswith(prefix):
            return parallax_class
    return UNKNOWN_CLASS


# Calibrated scenes of shared/data/real (SOURCES.md): view pairs (A, B) and their GT
# baseline / median depth. Up to this level a stitched pair counts as slight parallax.
CALIBRATED_PAIRS = {
    "strecha-fountain-P11": ((4, 5, 0.20), (3, 6, 0.55), (2, 8, 1.15), (0, 10, 1.62)),
    "strecha-Herz-Jesus-P8": ((3, 4, 0.16), (2, 5, 0.34), (0, 7, 0.72)),
    "middlebury-templeRing": ((13, 14, 0.13), (13, 16, 0.40), (13, 19, 0.77), (13, 25, 1.43)),
}
SLIGHT_MAX_BASELINE_OVER_DEPTH = 0.2
# ``--pose-only`` judges the cameras on more pairs of each calibrated scene than the crop
# protocol renders: every view with its next one (neighbours) and with the one this many
# further on (distant), besides CALIBRATED_PAIRS.
DISTANT_VIEW_STEP = 3


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


def discover_cases(root: str | Path, every_view_pair: bool = False) -> list[CaseSpec]:
    """Every case under ``root``, sorted by name: ``pis3r synth`` pair folders (any depth),
    pair folders (``ref.*`` + ``tgt.*``) and the calibrated scenes of ``CALIBRATED_PAIRS``
    (with ``every_view_pair``, also :func:`view_pairs`: for judging cameras, not pictures).
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
                parallax_class = "slight" if level <= SLIGHT_MAX_BASELINE_OVER_DEPTH else "large"
                specs.append(CaseSpec(f"{name}/{a}-{b}", root.name, "calibrated", str(folder), parallax_class,
                                      level, a, b))
            if every_view_pair:
                listed = {(a, b) for a, b, _ in CALIBRATED_PAIRS[folder.name]}
                specs += [CaseSpec(f"{name}/{a}-{b}", root.name, "calibrated", str(folder), UNKNOWN_CLASS,
                                   math.nan, a, b) for a, b in view_pairs(folder) if (a, b) not in listed]
        elif is_pair_dir(folder) and find_image(folder, "gt") is not None:
            info = json.loads((folder / "case.json").read_text())
            specs.append(CaseSpec(name, root.name, "synth", str(folder), info["parallax_class"],
                                  float(info["homography_residual_pct"])))
        elif is_pair_dir(folder):
            # ScanNet pairs (gt.txt) are calibrated; SOURCES.md gives their class in prose.
            parallax_class = classes.get(folder.name, "large" if (folder / "gt.txt").is_file() else UNKNOWN_CLASS)
            specs.append(CaseSpec(name, root.name, "pair", str(folder), parallax_class))
    if not specs:
        raise InputError(f"{root}: no cases (pair folders with ref.* and tgt.*, or `pis3r synth` output)")
    return specs


def view_pairs(folder: Path) -> list[tuple[int, int]]:
    """The neighbouring and the distant (``DISTANT_VIEW_STEP`` apart) view pairs of a
    calibrated scene, by the view numbers of its images."""
    views = sorted(int("".join(filter(str.isdigit, path.stem))) for path in (Path(folder) / "images").iterdir()
                   if path.suffix.lower() in IMAGE_SUFFIXES)
    return [(views[i], views[i + step]) for step in (1, DISTANT_VIEW_STEP) for i in range(len(views) - step)]


def load_case(spec: CaseSpec, crop: float = 0.6) -> EvalCase:
    """Read the images (and GT cameras where known) of a case. ``crop`` applies to pair
    folders and calibrated scenes; ``pis3r synth`` cases bring their own ground truth."""
    folder = Path(spec.folder)
    if spec.kind == "synth":
        cameras = json.loads((folder / "cameras.json").read_text())
        return EvalCase(
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


def calibrated_paths(folder: Path, views: tuple[int, ...]) -> list[Path]:
    """The image files of ``views`` of a Strecha (``images/NNNN.jpg``) or Middlebury
    (``images/templeRNNNN.png``) scene."""
    if Path(folder).name.startswith("strecha"):
        return [Path(folder) / "images" / f"{v:04d}.jpg" for v in views]
    return [Path(folder) / "images" / f"templeR{v:04d}.png" for v in views]


def calibrated_views(folder: Path, views: tuple[int, int]) -> tuple[list[np.ndarray], tuple[Camera, Camera]]:
    """Images and GT cameras of two views of a Strecha or Middlebury scene (formats in
    shared/data/real/SOURCES.md)."""
    paths = calibrated_paths(folder, views)
    if folder.name.startswith("strecha"):
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
    images = [read_image(path).pixels for path in paths]
    cameras = tuple(
        Camera(rows[path.name][:9], rows[path.name][9:18], rows[path.name][18:], image.shape[1], image.shape[0])
        for path, image in zip(paths, images)
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

