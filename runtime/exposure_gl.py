"""Auto exposure of a renderer's frame: on the GPU where the frame stays there, else numpy.

:func:`frame_exposure` is what :meth:`prt.runtime.renderer.Renderer.frame_exposure` returns: the
auto exposure (:func:`prt.runtime.exposure.auto_exposure`) of the frame drawn last, over the
pixels the scene covers.  A frame shaded on the CPU (the ONNX backend) is reduced in numpy from
the covered rows; a frame shaded on the GPU (``glsl``, ``texture``) is reduced there by
:class:`LogLuminanceReduction` (``shaders/log_luminance.frag``: per 16 x 16 tile, the sum of
``log(EPS + L)`` and the count of covered pixels), and only the tiles are read back (1/256 of
the frame), so a window keeps its no-read-back frame.  ``tests/test_exposure.py`` holds the GPU
sums to the numpy twin on the same frame.
"""

from __future__ import annotations

import moderngl
import numpy as np

from ..shaders import assemble
from .exposure import BLOCK, auto_exposure, exposure_defines, exposure_from_log_mean
from .errors import RendererStateError
from .gl import bind_framebuffer, compile_program

__all__ = ["LogLuminanceReduction", "frame_exposure", "covered_mask"]


class LogLuminanceReduction:
    """The log-luminance sum and covered count of a frame texture, per tile on the GPU."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, block: int = BLOCK) -> None:
        self.ctx, self.width, self.height, self.block = ctx, width, height, block
        self.program = compile_program(ctx, assemble("log_luminance.frag", defines=exposure_defines(block)), "log_luminance.frag")
        self.vao = ctx.vertex_array(self.program, [])
        self.tiles = (-(-width // block), -(-height // block))
        self.target = ctx.texture(self.tiles, 2, dtype="f4")
        self.fbo = ctx.framebuffer([self.target])
        self._out = np.zeros((self.tiles[1], self.tiles[0], 2), dtype=np.float32)

    def sums(self, frame: moderngl.Texture, depth: moderngl.Texture) -> tuple[float, int]:
        """(sum of log(EPS + L) over the covered pixels, their count)."""
        previous = self.ctx.fbo
        compare = depth.compare_func
        try:
            depth.compare_func = ""  # read the depth values, not a comparison
            frame.use(0)
            depth.use(1)
            p = self.program
            p["u_frame"].value, p["u_depth"].value = 0, 1
            p["u_size"].value = (self.width, self.height)
            self.fbo.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            self.vao.render(moderngl.TRIANGLES, vertices=3)
            self.fbo.read_into(self._out, components=2, dtype="f4")
        finally:
            depth.compare_func = compare
            bind_framebuffer(self.ctx, previous)
        total = self._out.astype(np.float64).sum(axis=(0, 1))
        return float(total[0]), int(round(total[1]))

    def log_mean(self, frame: moderngl.Texture, depth: moderngl.Texture) -> float | None:
        s, n = self.sums(frame, depth)
        return None if n == 0 else s / n

    def release(self) -> None:
        for obj in (self.fbo, self.target, self.vao, self.program):
            obj.release()


def covered_mask(r) -> np.ndarray:
    """(H, W) bool, row 0 at the top: the pixels the last frame of renderer ``r`` covers."""
    r._check_usable()
    if not r.stats["frames"]:
        raise RendererStateError("Renderer.covered_mask: no frame drawn yet; call draw() or render()")
    if r._transfer_on_cpu:
        mask = np.zeros(r.height * r.width, dtype=bool)
        mask[r._covered] = True
        return mask.reshape(r.height, r.width)
    depth = np.frombuffer(r.gbuffer.depth_texture.read(), dtype=np.float32).reshape(r.height, r.width)
    return np.ascontiguousarray(depth[::-1] < 1.0)


def frame_exposure(r, image: np.ndarray | None = None) -> float:
    """The auto exposure of the last frame of renderer ``r`` (``image``: that frame, read back)."""
    r._check_usable()
    if not r.stats["frames"]:
        raise RendererStateError("Renderer.frame_exposure: no frame drawn yet; call draw() or render()")
    if r._transfer_on_cpu or (image is not None and r.frame_texture is None):
        frame = r._cpu_image if image is None else image
        return auto_exposure(frame.reshape(-1, 3)[r._covered])  # the covered rows: no full-frame mask
    reduction = getattr(r, "_exposure_reduction", None)
    if reduction is None:
        reduction = r._resources.keep(LogLuminanceReduction(r.ctx, r.width, r.height))
        r._exposure_reduction = reduction
    return exposure_from_log_mean(reduction.log_mean(r.frame_texture, r.gbuffer.depth_texture))
