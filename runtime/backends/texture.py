"""The ``"texture"`` backend: transfer fetched from a baked transfer texture (texture-space PRT).

The scene's ``transfer_texture`` (:mod:`prt.runtime.transfer_texture`, baked by
:func:`prt.train.transport.transfer_texture.bake_transfer_texture`) is uploaded once as an RGBA16F
texture array (layer ``B * atlas + k`` holds coefficients ``4k .. 4k+3``, B = 4 blocks per texel),
filtered bilinearly and clamped to the edge.  Per frame, a full-screen pass
(``shaders/texture_transfer.frag``) reads each pixel's UV from the G-buffer (attachment 2, drawn
only for scenes that have a transfer texture) and writes the fetched transfer to the renderer's
four RGBA32F targets; the renderer shades it with the same pass as every other GPU backend.  Its
plain reference twin is :func:`bilinear_lookup` (numpy).  Mesh scenes only.

Interreflection (a scene built with ``--bounces N``, its texture baked in the "direct+rgb"
layout): B = 16 blocks per texel (direct, indirect R, G, B), and the renderer's target is a pair
of framebuffers of 8 RGBA32F targets each (OpenGL 3.3 guarantees 8 draw buffers), so the pass
draws twice (``u_part`` 0: blocks 0..7, 1: blocks 8..15), as the GLSL backend does; the shade
pass reads the indirect blocks as it does for the networks.  GL guarantees 256 array layers:
16 atlases of 64-value transfer; :func:`check_texture_limits` refuses more than the context
allows, in one line, before the upload.
"""

from __future__ import annotations

import time

import moderngl
import numpy as np

from ...shaders import assemble
from ..errors import InputError
from ..gbuffer import load_mesh
from ..gl import compile_program
from ..transfer_texture import load_transfer_texture
from .base import TransferBackend, draw_transfer

__all__ = ["TextureBackend", "bilinear_lookup", "check_texture_limits", "texture_layers"]


def check_texture_limits(ctx, manifest, size: int, layers: int) -> None:
    """Refuse, in one line naming the scene, a transfer texture this GL cannot hold: more array
    layers than ``GL_MAX_ARRAY_TEXTURE_LAYERS`` (at least 256 in GL 3.3: 64 atlases of 16 values,
    16 of 64) or texels per side beyond ``GL_MAX_TEXTURE_SIZE``.  A driver would otherwise fail
    the upload with a bare GL error, or some drivers silently sample garbage."""
    info = ctx.info
    max_layers = int(info.get("GL_MAX_ARRAY_TEXTURE_LAYERS") or 256)
    max_size = int(info.get("GL_MAX_TEXTURE_SIZE") or 1024)
    if layers > max_layers:
        raise InputError(
            f"{manifest.path}: transfer_texture needs {layers} texture-array layers "
            f"(atlases x {manifest.transfer_width // 4} blocks) but this OpenGL allows {max_layers}: rebake with fewer atlases "
            f"(prt-train --texture-layout shared) or render with the onnx/glsl backends"
        )
    if size > max_size:
        raise InputError(f"{manifest.path}: transfer_texture.size {size} exceeds this OpenGL's GL_MAX_TEXTURE_SIZE {max_size}")


def texture_layers(transfer: np.ndarray) -> np.ndarray:
    """(A, S, S, n) transfer as (nA/4, S, S, 4) texture-array layers: layer ``(n/4) a + k`` holds
    coefficients ``4k .. 4k+3`` of atlas ``a``."""
    atlases, height, width, n = transfer.shape
    return np.ascontiguousarray(transfer.reshape(atlases, height, width, n // 4, 4).transpose(0, 3, 1, 2, 4)).reshape(-1, height, width, 4)


def bilinear_lookup(transfer: np.ndarray, uv: np.ndarray, atlas: np.ndarray) -> np.ndarray:
    """GL's bilinear fetch (clamp to edge) of ``transfer`` at ``uv``: the texture backend's numpy twin.

    Parameters
    ----------
    transfer : (A, S, S, n) float
        Row 0 at ``v`` near 0.
    uv : (N, 2) float
    atlas : (N,) int

    Returns
    -------
    (N, n) float32
    """
    _, height, width, _ = transfer.shape
    x = np.asarray(uv[:, 0], np.float64) * width - 0.5
    y = np.asarray(uv[:, 1], np.float64) * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xs = np.clip([x0, x0 + 1], 0, width - 1)
    ys = np.clip([y0, y0 + 1], 0, height - 1)
    t = np.asarray(transfer, np.float32)

    def at(j, i):
        return t[atlas, ys[j], xs[i]]

    return ((1 - fy) * ((1 - fx) * at(0, 0) + fx * at(0, 1)) + fy * ((1 - fx) * at(1, 0) + fx * at(1, 1))).astype(np.float32)


class TextureBackend(TransferBackend):
    """Bilinear fetches from the scene's transfer texture in one full-screen pass.

    Timings: ``texture`` (the fetch pass, finished).  ``upload_s`` is the texture upload time.

    Raises
    ------
    InputError
        If the scene has no transfer texture (or is an SDF scene).
    GeometryError
        If the texture file is malformed.
    """

    name = "texture"
    requires = "transfer_texture"  # not in BACKENDS (which render every scene), only ALL_BACKENDS

    def __init__(self, ctx, manifest, *, providers=None, threads: int | None = None, interpolate: float | None = None):
        super().__init__(ctx, manifest)
        info = manifest.transfer_texture
        if info is None or manifest.geometry.type != "mesh":
            raise InputError(f"{manifest.path}: the texture backend needs a mesh scene with a transfer_texture (prt-train --transfer-texture SIZE)")
        n_faces = len(load_mesh(manifest.geometry.path)["faces"])
        t0 = time.perf_counter()
        width = manifest.transfer_width  # 16, or 64 with interreflection
        check_texture_limits(ctx, manifest, info.size, info.atlases * (width // 4))
        arrays = load_transfer_texture(info, n_faces, width)
        layers = texture_layers(arrays["transfer"])
        self.blocks = width // 4
        self.texture = ctx.texture_array((info.size, info.size, len(layers)), 4, data=layers.tobytes(), dtype="f2")
        self.texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.texture.repeat_x = self.texture.repeat_y = False  # clamp to edge
        self.upload_s = time.perf_counter() - t0
        defines = {"PRT_TRANSFER_BLOCKS": self.blocks} if self.blocks != 4 else None
        self.program = compile_program(ctx, assemble("texture_transfer.frag", defines=defines), "texture_transfer.frag")
        self.program["u_uv"].value = 0
        self.program["u_transfer"].value = 1
        self.vao = ctx.vertex_array(self.program, [])

    def run(self, gbuffer, target) -> None:
        if gbuffer.uv_texture is None:
            raise InputError(f"{self.manifest.path}: the G-buffer has no UV target (built for a scene without a transfer texture)")
        t0 = time.perf_counter()
        textures = ((gbuffer.uv_texture, 0), (self.texture, 1))
        draw_transfer(self.ctx, self.program, self.vao, target, textures)
        self.ctx.finish()
        self.timings = {"texture": 1e3 * (time.perf_counter() - t0)}
        return None

    def release(self) -> None:
        for obj in (self.vao, self.program, self.texture):
            obj.release()
