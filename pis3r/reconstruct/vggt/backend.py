"""The ``vggt`` reconstruction backend: photos -> Scene with VGGT cameras and depth.

Contract details (see :class:`pis3r.scene.View`):

- world frame = the first photo's camera, exactly (``R = I, t = 0``): VGGT's own world
  is close to it but predicted, so every pose is re-expressed relative to camera 0;
- cameras, depth, confidence and colours are on each photo's **original** pixel grid;
- depth is the depth branch (the official demos' default), z in each camera's frame,
  in VGGT's normalised scene scale; 0 where unknown;
- confidence maps VGGT's ``depth_conf = 1 + exp(c) > 1`` monotonically to [0, 1) by
  ``1 - 1/depth_conf``; pixels below ``ReconstructOptions.conf_threshold`` on that scale
  get depth 0 (the default 0 keeps every point, as the paper does).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from pis3r.camera import Camera
from pis3r.errors import InputError, ReconstructionError, WeightsError
from pis3r.io import Photo
from pis3r.device import resolve_device
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.vggt.preprocess import Placement, preprocess_images
from pis3r.reconstruct.vggt.weights import FETCH_HINT, WEIGHTS_ENV, find_weights, load_vggt
from pis3r.scene import Scene, View

# The last loaded model, kept for the next call (a server stitches many times; loading
# 5 GB each time would dominate). Key: (resolved path, file mtime, device).
_loaded: dict[tuple, object] = {}


def _model_for(path: Path, device: str):
    key = (str(path.resolve()), path.stat().st_mtime_ns if path.is_file() else None, device)
    if key not in _loaded:
        _loaded.clear()
        model = load_vggt(path, device)
        # One forward per stitch: capturing a CUDA graph (two warm-up runs, then a
        # private memory pool held for good) would cost more than it saves.
        model.cuda_graphs = False
        _loaded[key] = model
    return _loaded[key]


def inference_context(device: str):
    """Autocast for the aggregator: bf16 on CUDA GPUs of compute capability >= 8, fp16
    on older ones, none on the CPU (fp32). The model itself keeps its heads in fp32."""
    import torch

    if not device.startswith("cuda"):
        return contextlib.nullcontext()
    major, _ = torch.cuda.get_device_capability(torch.device(device))
    return torch.autocast("cuda", dtype=torch.bfloat16 if major >= 8 else torch.float16)


def run_vggt(model, images: np.ndarray, device: str) -> dict[str, np.ndarray]:
    """Model input ``(S, 3, H, W)`` -> ``pose_enc (S, 9)``, ``depth (S, H, W)``, ``depth_conf (S, H, W)``."""
    import torch

    with torch.no_grad(), inference_context(device):
        out = model(torch.from_numpy(images).to(device))
    return {
        "pose_enc": out["pose_enc"][0].double().cpu().numpy(),
        "depth": out["depth"][0, ..., 0].float().cpu().numpy(),
        "depth_conf": out["depth_conf"][0].float().cpu().numpy(),
    }


def cameras_from_pose_encoding(pose_enc: np.ndarray, image_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(S, 9)`` encodings -> camera-from-world ``(S, 3, 4)`` relative to camera 0 and
    intrinsics ``(S, 3, 3)`` in model-input pixels (float64)."""
    import torch

    from pis3r.reconstruct.vggt.geometry import relative_to_first
    from pis3r.reconstruct.vggt.pose_encoding import pose_encoding_to_extri_intri

    extrinsics, intrinsics = pose_encoding_to_extri_intri(torch.from_numpy(pose_enc)[None], image_hw)
    return relative_to_first(extrinsics[0]).numpy(), intrinsics[0].numpy()


def confidence_to_unit(depth_conf: np.ndarray) -> np.ndarray:
    """VGGT confidence ``1 + exp(c)`` (> 1) -> ``1 - 1/conf`` in [0, 1), monotonic."""
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = 1.0 - 1.0 / depth_conf.astype(np.float64)
    return np.clip(np.nan_to_num(unit, nan=0.0), 0.0, 1.0).astype(np.float32)


def view_from_prediction(
    photo: Photo, placement: Placement, extrinsic: np.ndarray, K_model: np.ndarray,
    depth: np.ndarray, depth_conf: np.ndarray, conf_threshold: float,
) -> View:
    """One photo's :class:`View` at its original resolution from model-input maps ``(H, W)``."""
    fx, fy = K_model[0, 0], K_model[1, 1]
    if not (np.all(np.isfinite(K_model)) and fx > 0 and fy > 0):
        raise ReconstructionError(f"{photo.name}: VGGT predicted a degenerate camera (focal {fx:g}, {fy:g} px)")
    K = placement.intrinsics_to_photo(K_model)
    usable = np.isfinite(depth) & (depth > 0)
    depth_photo, seen = placement.to_photo(np.where(usable, depth, 0.0))
    usable_photo, _ = placement.to_photo(usable.astype(np.float32))
    conf_photo, _ = placement.to_photo(confidence_to_unit(depth_conf))
    # Bilinear samples that touch an unusable model pixel are unusable too.
    valid = seen & (usable_photo > 0.999) & (conf_photo >= conf_threshold)
    camera = Camera(K, extrinsic[:, :3], extrinsic[:, 3], photo.width, photo.height)
    return View(
        image=photo.pixels,
        camera=camera,
        depth=np.where(valid, depth_photo, 0.0).astype(np.float32),
        confidence=np.where(valid, conf_photo, 0.0).astype(np.float32),
        name=photo.name,
    )


class VGGTBackend:
    """VGGT-1B reconstruction; ``photos[0]`` is the reference and defines the world frame.

    ``mode``: preprocessing, ``"crop"`` (official default: width 518, taller photos lose
    their top and bottom rows, which then have no depth) or ``"pad"`` (whole photo,
    longest side 518).
    """

    name = "vggt"

    def __init__(self, options: ReconstructOptions, mode: str = "crop") -> None:
        self.options = options
        self.mode = mode
        self.device = resolve_device(options.device)
        weights = find_weights(options.weights)
        if weights is None:
            raise WeightsError(f"no VGGT weights found: pass --weights PATH, set {WEIGHTS_ENV}, or {FETCH_HINT}")
        self.weights = weights

    def reconstruct(self, photos: list[Photo]) -> Scene:
        if not photos:
            raise InputError("VGGT needs at least one photo")
        model = _model_for(self.weights, self.device)
        images, placements = preprocess_images([p.pixels for p in photos], self.mode)
        prediction = run_vggt(model, images, self.device)
        extrinsics, intrinsics = cameras_from_pose_encoding(prediction["pose_enc"], images.shape[-2:])
        views = [
            view_from_prediction(
                photo, placement, extrinsics[i], intrinsics[i],
                prediction["depth"][i], prediction["depth_conf"][i], self.options.conf_threshold,
            )
            for i, (photo, placement) in enumerate(zip(photos, placements))
        ]
        return Scene(
            views, model="3d", model_reason="VGGT predicts every camera and depth map",
            focal=float(views[0].camera.K[0, 0]), focal_source="vggt",
            warnings=self._warnings(photos, placements, images.shape[-2:]),
            info={"backend": "vggt", "weights": str(self.weights), "device": self.device,
                  "input_size": [int(images.shape[-1]), int(images.shape[-2])], "preprocess": self.mode},
        )

    def _warnings(self, photos: list[Photo], placements: list[Placement], input_hw) -> tuple[str, ...]:
        warnings = []
        if self.options.focal is not None:
            warnings.append("--focal is not used by the vggt backend: VGGT predicts every camera's intrinsics")
        for photo, p in zip(photos, placements):
            top, bottom = p.to_model(np.zeros(1), np.array([0.0, photo.height - 1.0]))[1]
            if top < -0.5 or bottom > input_hw[0] - 0.5:
                warnings.append(
                    f"{photo.name}: rows outside VGGT's central {input_hw[0]}-row crop have no depth"
                )
        return tuple(warnings)
