"""Headless OpenGL rendering (moderngl + EGL, Mesa on the CPU) of exact OpenCV pinhole cameras.

The projection is built from ``K`` so that a world point lands exactly on the pixel
``K x_cam / z`` predicts: OpenCV pixel ``u`` is OpenGL window coordinate ``u + 0.5``
(GL samples pixel centres at half-integers), and image row ``v`` is GL window row
``v`` (not flipped: ``glReadPixels`` returns the bottom GL row first, which is then
image row 0). Depth is the camera-frame ``z`` written to a float32 colour attachment,
exact per pixel centre, ``inf`` where no surface is hit.

Colour is supersampled (render ``s`` times larger, average ``s x s`` blocks, the same
as integrating each pixel's footprint) from trilinear-mipmapped textures and slightly
blurred like a lens would, so images look like photographs rather than aliased renders.
Anisotropic filtering is left off: on llvmpipe it costs 4-5x the render time, and
supersampling already sharpens surfaces seen at grazing angles.

One GL context per process (create it after any fork); the last scene's geometry and
textures stay uploaded.
"""

from __future__ import annotations

import functools
import weakref
from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.camera import Camera
from pis3r.gl import current_context, required_context
from pis3r.synth.scenes import SynthScene

NEAR, FAR = 0.05, 5000.0  # metres; the backdrop is at most ~400 m from any camera
# Real lenses do not resolve up to the pixel Nyquist limit; this slight blur makes the
# renders look like photos and band-limits them, so reprojected GT matches closely.
LENS_BLUR_PX = 0.5

_VERTEX_SHADER = """
#version 330
uniform mat4 clip_from_world;
in vec3 in_position;
in vec2 in_uv;
in float in_layer;
in vec3 in_color;
out vec2 v_uv;
flat out float v_layer;
out vec3 v_color;
out float v_z;
void main() {
    gl_Position = clip_from_world * vec4(in_position, 1.0);
    v_z = gl_Position.w;  // w_clip is the camera-frame z by construction of the projection
    v_uv = in_uv;
    v_layer = in_layer;
    v_color = in_color;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform sampler2DArray textures;
uniform bool textured;  // false: a depth pass, colour is not needed
in vec2 v_uv;
flat in float v_layer;
in vec3 v_color;
in float v_z;
layout(location = 0) out vec4 out_color;
layout(location = 1) out float out_depth;
void main() {
    // Mirrored repeat (no seams between copies of a photo); the gradients of the
    // unfolded coordinates keep mip level and anisotropy right across the folds.
    vec3 texel = vec3(1.0);
    if (textured) {
        vec2 folded = 1.0 - abs(1.0 - mod(v_uv, 2.0));
        texel = textureGrad(textures, vec3(folded, v_layer), dFdx(v_uv), dFdy(v_uv)).rgb;
    }
    out_color = vec4(clamp(texel * v_color, 0.0, 1.0), 1.0);
    out_depth = v_z;
}
"""


@dataclass(frozen=True)
class Rendering:
    """``image (H, W, 3)`` float32 RGB in [0, 1]; ``depth (H, W)`` float32 camera-frame z,
    ``inf`` where nothing was hit."""

    image: np.ndarray
    depth: np.ndarray


def gl_projection(camera: Camera, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """``(4, 4)`` matrix taking camera-frame points (OpenCV axes) to GL clip space such that
    window ``x = u + 0.5``, window ``y = v + 0.5`` for ``(u, v) = K x / z``, and ``w = z``."""
    K, w, h = camera.K, camera.width, camera.height
    return np.array(
        [
            [2 * K[0, 0] / w, 2 * K[0, 1] / w, 2 * (K[0, 2] + 0.5) / w - 1, 0],
            [0, 2 * K[1, 1] / h, 2 * (K[1, 2] + 0.5) / h - 1, 0],
            [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)],
            [0, 0, 1, 0],
        ]
    )


def clip_from_world(camera: Camera) -> np.ndarray:
    """``(4, 4)`` world-to-clip matrix ``P [R | t]`` of ``camera``."""
    extrinsics = np.eye(4)
    extrinsics[:3, :3], extrinsics[:3, 3] = camera.R, camera.t
    return gl_projection(camera) @ extrinsics


@functools.lru_cache(maxsize=1)
def _program():
    return required_context().program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)


class _Uploaded:
    """A scene's vertex buffer and texture array on the GL context."""

    def __init__(self, scene: SynthScene) -> None:
        import moderngl

        ctx = required_context()
        self.program = _program()
        mesh = scene.mesh
        per_vertex = np.repeat(np.arange(mesh.triangles), 3)
        vertices = np.hstack(
            [mesh.positions, mesh.uv, mesh.texture_id[per_vertex, None].astype(np.float32), mesh.color[per_vertex]]
        ).astype(np.float32)
        self.buffer = ctx.buffer(np.ascontiguousarray(vertices).tobytes())
        self.vao = ctx.vertex_array(
            self.program, [(self.buffer, "3f 2f 1f 3f", "in_position", "in_uv", "in_layer", "in_color")]
        )
        layers, size = scene.textures.shape[0], scene.textures.shape[1]
        self.textures = ctx.texture_array((size, size, layers), 3, np.ascontiguousarray(scene.textures).tobytes())
        self.textures.build_mipmaps()
        self.textures.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.textures.repeat_x = self.textures.repeat_y = False  # the shader mirrors

    def release(self) -> None:
        for resource in (self.vao, self.buffer, self.textures):
            resource.release()


_upload: tuple[weakref.ref, _Uploaded] | None = None  # the last scene rendered, kept on the GPU
_targets: dict[tuple[int, int], object] = {}


def _uploaded(scene: SynthScene) -> _Uploaded:
    """The GL resources of ``scene``, uploading it (and dropping the previous one) if needed."""
    global _upload
    if _upload is None or _upload[0]() is not scene:
        if _upload is not None:
            _upload[1].release()
        _upload = (weakref.ref(scene), _Uploaded(scene))
    return _upload[1]


def _target(width: int, height: int):
    """A framebuffer (float RGBA colour, float z, depth buffer) of this size, kept for reuse."""
    if (width, height) not in _targets:
        if len(_targets) >= 8:  # sizes come in a handful per dataset; do not hoard memory
            for fbo in _targets.values():
                fbo.release()
            _targets.clear()
        ctx = required_context()
        colour = ctx.texture((width, height), 4, dtype="f4")
        depth = ctx.texture((width, height), 1, dtype="f4")
        _targets[(width, height)] = ctx.framebuffer([colour, depth], ctx.depth_renderbuffer((width, height)))
    return _targets[(width, height)]


def _draw(scene: SynthScene, camera: Camera, textured: bool):
    """Rasterise ``scene`` for ``camera`` (one sample per pixel centre); the framebuffer.
    Call with the shared context current."""
    import moderngl

    required_context().enable(moderngl.DEPTH_TEST)
    uploaded = _uploaded(scene)
    fbo = _target(camera.width, camera.height)
    fbo.use()
    fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
    uploaded.program["clip_from_world"].write(clip_from_world(camera).T.astype(np.float32).tobytes())
    uploaded.program["textured"].value = textured
    if textured:
        uploaded.textures.use(0)
        uploaded.program["textures"].value = 0
    uploaded.vao.render()
    return fbo


def render_depth(scene: SynthScene, camera: Camera) -> np.ndarray:
    """Camera-frame z ``(H, W)`` float32 at each pixel centre, ``inf`` where nothing is hit."""
    with current_context():
        fbo = _draw(scene, camera, textured=False)
        depth = np.frombuffer(fbo.read(components=1, attachment=1, dtype="f4"), np.float32)
    return np.where(depth > 0, depth, np.inf).astype(np.float32).reshape(camera.height, camera.width)


def render_colour(scene: SynthScene, camera: Camera) -> np.ndarray:
    """RGB ``(H, W, 3)`` float32 in [0, 1], one sample at each pixel centre (aliased)."""
    with current_context():
        fbo = _draw(scene, camera, textured=True)
        colour = np.frombuffer(fbo.read(components=3, attachment=0, dtype="f4"), np.float32)
    return colour.reshape(camera.height, camera.width, 3)


def area_downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor x factor`` blocks: ``(H*f, W*f, C)`` to ``(H, W, C)``."""
    size = (image.shape[1] // factor, image.shape[0] // factor)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)  # exact block mean for integer factors


def render(scene: SynthScene, camera: Camera, supersample: int = 2, blur: float = LENS_BLUR_PX) -> Rendering:
    """Photo-like colour and exact per-pixel-centre z of ``scene`` seen by ``camera``.

    Colour: ``supersample**2`` samples per pixel, box-filtered (the sensor pixel), then a
    Gaussian of ``blur`` pixels (the lens), computed on a margin so that border pixels see
    the scene and not a padding rule.
    """
    pad = int(np.ceil(4 * blur))  # OpenCV's Gaussian kernel radius for float images
    padded = camera.shifted(pad, pad, camera.width + 2 * pad, camera.height + 2 * pad)
    colour = area_downsample(render_colour(scene, padded.scaled(supersample)), supersample)
    if blur > 0:
        colour = cv2.GaussianBlur(colour, (0, 0), blur)
    colour = colour[pad : pad + camera.height, pad : pad + camera.width]
    return Rendering(np.ascontiguousarray(colour), render_depth(scene, camera))
