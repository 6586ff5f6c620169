"""Reprojection of every view's points into the reference camera with a z-buffer.

Paper eqs. 2–5: points go into the reference camera frame, are projected and
rounded to the nearest pixel; at each pixel the nearest point wins. The canvas is
the reference camera with a larger image: its principal point is shifted by
``ref_offset`` (the canvas pixel of the reference's pixel (0, 0)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pis3r.camera import Camera
from pis3r.scene import Scene

# Points closer than this (relative to the median scene depth) are numerically on
# the camera plane: their projection explodes, so they are dropped.
MIN_RELATIVE_DEPTH = 1e-3
# Relative depth added to a point's footprint pixels, so that exact hits of the
# same surface win over them while nearer surfaces still occlude farther ones.
FOOTPRINT_DEPTH_BIAS = 1e-3
# Points sampled to estimate each view's exposure gain.
GAIN_SAMPLES = 200_000
# The canvas is at most this many times the reference's width and height.
DEFAULT_MAX_CANVAS_SCALE = 3.0


@dataclass
class Canvas:
    """The z-buffered reprojection of a scene onto the reference camera.

    ``image``: ``(H, W, 3)`` float32; ``depth``: ``(H, W)`` float32 z in the reference
    frame (``inf`` where empty); ``source``: ``(H, W)`` int16 index of the view whose
    point won (``-1`` where empty); ``camera``: the canvas camera; ``ref_offset``:
    ``(x, y)`` canvas pixel of the reference's pixel ``(0, 0)``;
    ``dropped_points``: points that fell outside the capped canvas;
    ``under_reference``: ``(h, w, 3)`` what the other views put where the reference
    (``h x w``) is pasted, and ``under_valid`` ``(h, w)`` bool where they put anything
    (the overlap that blending across the reference border works from).
    """

    image: np.ndarray
    depth: np.ndarray
    source: np.ndarray
    camera: Camera
    ref_offset: tuple[int, int]
    dropped_points: int
    under_reference: np.ndarray | None = None
    under_valid: np.ndarray | None = None

    @property
    def occupied(self) -> np.ndarray:
        """``(H, W)`` bool: pixels that received a point (or the reference itself)."""
        return self.source >= 0


def _scene_points(scene: Scene, ref_index: int, device: torch.device, min_confidence: float):
    """Stack the valid points of every view but the reference (whose pixels are copied
    verbatim): reference-frame xyz ``(N, 3)``, rgb ``(N, 3)``, view ``(N,)``, and
    ``spread (N,)``: depth in the point's own view times the focal ratio, so that
    ``spread / z_ref`` is how much the reprojection magnifies that view there."""
    ref = scene.views[ref_index].camera
    xyz, rgb, owner, spread = [], [], [], []
    for index, view in enumerate(scene.views):
        if index == ref_index:
            continue
        keep = torch.from_numpy(view.valid & (view.confidence >= min_confidence)).to(device)
        if not bool(keep.any()):
            continue
        cam = view.camera
        # view camera -> reference camera: x_ref = R_rel (x_view - t_view) + t_ref with R_rel = R_ref R_view^T
        R_rel = torch.as_tensor(ref.R @ cam.R.T, dtype=torch.float32, device=device)
        t_rel = torch.as_tensor(ref.t - ref.R @ cam.R.T @ cam.t, dtype=torch.float32, device=device)
        K_inv = torch.as_tensor(np.linalg.inv(cam.K), dtype=torch.float32, device=device)
        v, u = torch.nonzero(keep, as_tuple=True)
        depth = torch.from_numpy(view.depth).to(device)[v, u]
        pix = torch.stack([u.float(), v.float(), torch.ones_like(depth)], dim=1)
        xyz.append((pix @ K_inv.T) * depth[:, None] @ R_rel.T + t_rel)
        rgb.append(torch.from_numpy(view.image).to(device)[v, u])
        owner.append(torch.full((len(depth),), index, dtype=torch.int16, device=device))
        spread.append(depth * float(ref.focal / cam.focal))
    if not xyz:
        empty = torch.zeros((0, 3), device=device)
        return empty, empty, torch.zeros((0,), dtype=torch.int16, device=device), torch.zeros(0, device=device)
    return torch.cat(xyz), torch.cat(rgb), torch.cat(owner), torch.cat(spread)


def _footprint(px, py, z, rgb, owner, step_x, step_y, magnification):
    """Splat each point onto the pixel centres it covers once magnified: the 2x2 block
    around its exact position, or the 3x3 block where the view is magnified more than
    twice. Copies sit a little behind the point, so exact hits of the same surface win
    while nearer surfaces still occlude. All inputs ``(N,)`` (``rgb (N, 3)``)."""
    behind = z * (1.0 + FOOTPRINT_DEPTH_BIAS)
    big = magnification > 2.0
    offsets = [(step_x, 0, None), (0, step_y, None), (step_x, step_y, None)] + [
        (dx * step_x, dy * step_y, big) for dx, dy in ((-1, 0), (0, -1), (-1, -1), (1, -1), (-1, 1))
    ]
    xs, ys, zs, colours, owners = [px], [py], [z], [rgb], [owner]
    for dx, dy, only in offsets:
        sel = slice(None) if only is None else only
        xs.append((px + dx)[sel] if isinstance(dx, torch.Tensor) else px[sel] + dx)
        ys.append((py + dy)[sel] if isinstance(dy, torch.Tensor) else py[sel] + dy)
        zs.append(behind[sel])
        colours.append(rgb[sel])
        owners.append(owner[sel])
    return torch.cat(xs), torch.cat(ys), torch.cat(zs), torch.cat(colours), torch.cat(owners)


def _window(coords: torch.Tensor, ref_size: int, limit: int) -> tuple[int, int]:
    """Choose ``[lo, hi)`` along one axis: covers ``[0, ref_size)`` and as many
    projected coordinates as possible within ``limit`` pixels."""
    if coords.numel() == 0:
        return 0, ref_size
    lo = int(min(0, torch.floor(coords.min()).item()))
    hi = int(max(ref_size, torch.ceil(coords.max()).item() + 1))
    if hi - lo <= limit:
        return lo, hi
    # Slide a window of `limit` pixels that always contains the reference and
    # keep the start that holds the most points (a 1-D histogram prefix sum).
    hist = torch.bincount((coords.round().long() - lo).clamp(0, hi - lo - 1), minlength=hi - lo)
    prefix = torch.cat([hist.new_zeros(1), torch.cumsum(hist, 0)]).cpu().numpy()
    starts = np.arange(max(lo, ref_size - limit), 1)
    counts = prefix[np.minimum(starts - lo + limit, hi - lo)] - prefix[starts - lo]
    start = int(starts[int(np.argmax(counts))])
    return start, start + limit


def _match_gains(rgb, owner, ref_x, ref_y, ref_image: np.ndarray) -> torch.Tensor:
    """Scale each view's colours ``(N, 3)`` by the robust per-channel gain that maps
    them onto the reference image at the pixels ``(ref_x, ref_y)`` where they land."""
    h, w = ref_image.shape[:2]
    # A robust median needs far fewer samples than a canvas has points.
    step = max(1, rgb.shape[0] // GAIN_SAMPLES)
    sample = torch.arange(0, rgb.shape[0], step, device=rgb.device)
    x, y, ours, views = ref_x[sample], ref_y[sample], rgb[sample], owner[sample]
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    x, y, ours, views = x[inside], y[inside], ours[inside], views[inside]
    theirs = torch.from_numpy(ref_image).to(rgb.device)[y, x]
    # Saturated or black pixels carry no information about the gain.
    usable = ((ours > 0.02) & (ours < 0.98) & (theirs > 0.02) & (theirs < 0.98)).all(dim=1)
    gains = torch.ones((int(owner.max()) + 1 if owner.numel() else 1, 3), device=rgb.device)
    for view in torch.unique(views[usable]).tolist():
        chosen = usable & (views == view)
        if int(chosen.sum()) >= 100:
            gains[view] = (theirs[chosen] / ours[chosen]).median(dim=0).values.clamp(0.5, 2.0)
    return (rgb * gains[owner.long()]).clamp(0.0, 1.0)


def reproject_to_canvas(
    scene: Scene,
    ref_index: int = 0,
    max_canvas_scale: float = DEFAULT_MAX_CANVAS_SCALE,
    device: str | torch.device = "cpu",
    min_confidence: float = 0.0,
    match_exposure: bool = True,
    footprint: bool = True,
) -> Canvas:
    """Z-buffer all points of ``scene`` into camera ``ref_index`` on a canvas that grows
    to hold them (capped at ``max_canvas_scale`` times the reference's size).

    The reference's own pixels are copied verbatim into the canvas. With
    ``match_exposure``, every other view's colours are scaled per channel by the gain
    that matches them to the reference where they land inside it, so a different
    exposure does not show as a frame around the reference. With ``footprint``,
    each point covers the 2x2 (or, where its view is magnified more than twice, 3x3)
    pixel centres around it, exact hits first: this closes the cracks of views that
    the reprojection magnifies.
    """
    device = torch.device(device)
    ref_view = scene.views[ref_index]
    ref = ref_view.camera
    xyz, rgb, owner, spread = _scene_points(scene, ref_index, device, min_confidence)

    z = xyz[:, 2]
    positive = z[z > 0]
    min_z = MIN_RELATIVE_DEPTH * float(positive.median()) if positive.numel() else 0.0
    front = z > max(min_z, 1e-9)
    xyz, rgb, owner, spread, z = xyz[front], rgb[front], owner[front], spread[front], z[front]
    K = torch.as_tensor(ref.K, dtype=torch.float32, device=device)
    u = K[0, 0] * xyz[:, 0] / z + K[0, 2]
    v = K[1, 1] * xyz[:, 1] / z + K[1, 2]

    x0, x1 = _window(u, ref.width, int(round(max_canvas_scale * ref.width)))
    y0, y1 = _window(v, ref.height, int(round(max_canvas_scale * ref.height)))
    width, height = x1 - x0, y1 - y0
    px = torch.round(u).long() - x0
    py = torch.round(v).long() - y0
    inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
    dropped = int((~inside).sum())
    px, py, z, rgb, owner = px[inside], py[inside], z[inside], rgb[inside], owner[inside]
    step_x = torch.where(u[inside] - x0 >= px, 1, -1)
    step_y = torch.where(v[inside] - y0 >= py, 1, -1)
    magnification = spread[inside] / z

    ox, oy = -x0, -y0
    if match_exposure:
        rgb = _match_gains(rgb, owner, px - ox, py - oy, ref_view.image)

    if footprint:
        px, py, z, rgb, owner = _footprint(px, py, z, rgb, owner, step_x, step_y, magnification)
        keep = (px >= 0) & (px < width) & (py >= 0) & (py < height)
        px, py, z, rgb, owner = px[keep], py[keep], z[keep], rgb[keep], owner[keep]

    flat = py * width + px
    zbuf = torch.full((height * width,), float("inf"), device=device)
    zbuf.scatter_reduce_(0, flat, z, reduce="amin")
    # Ties at equal depth are broken by the highest point index, so the result
    # does not depend on scatter order.
    is_nearest = z == zbuf[flat]
    winner = torch.full((height * width,), -1, dtype=torch.long, device=device)
    candidates = torch.arange(z.numel(), device=device)
    winner.scatter_reduce_(0, flat[is_nearest], candidates[is_nearest], reduce="amax")

    filled = winner >= 0
    image = torch.zeros((height * width, 3), device=device)
    source = torch.full((height * width,), -1, dtype=torch.int16, device=device)
    image[filled] = rgb[winner[filled]]
    source[filled] = owner[winner[filled]]

    image = image.reshape(height, width, 3).cpu().numpy()
    depth = zbuf.reshape(height, width).cpu().numpy()
    source = source.reshape(height, width).cpu().numpy()

    window = (slice(oy, oy + ref.height), slice(ox, ox + ref.width))
    under_reference, under_valid = image[window].copy(), source[window] >= 0
    image[window] = ref_view.image
    source[window] = ref_index
    ref_depth = np.where(ref_view.valid, ref_view.depth, np.inf).astype(np.float32)
    depth[window] = ref_depth
    return Canvas(
        image=image,
        depth=depth,
        source=source,
        camera=ref.shifted(ox, oy, width, height),
        ref_offset=(ox, oy),
        dropped_points=dropped,
        under_reference=under_reference,
        under_valid=under_valid,
    )
