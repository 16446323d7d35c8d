"""The environment map as the background: drawn where no geometry is, in linear radiance.

The renderer composites it into a frame's uncovered pixels when the background is on
(:meth:`prt.runtime.renderer.Renderer.set_background`; a manifest's ``lighting.background``),
before tone mapping, so both backends and every display path tone-map it the same way.  The
map follows the light: the same file and the same rotation as the lighting.  One full-screen
pass (``shaders/background.frag``) draws it; it is redrawn only when the camera, the map or its
rotation changes.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..shaders import assemble
from .envmap import read_envmap
from .gl import compile_program, draw_fullscreen

__all__ = ["EnvmapBackground"]


class EnvmapBackground:
    """The background layer of one renderer (its context and size)."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int) -> None:
        self.ctx, self.width, self.height = ctx, width, height
        self.program = compile_program(ctx, assemble("background.frag"), "background.frag")
        self.vao = ctx.vertex_array(self.program, [])
        self.target = ctx.texture((width, height), 3, dtype="f4")
        self.fbo = ctx.framebuffer([self.target])
        self._envmap_key = None
        self._envmap: moderngl.Texture | None = None
        self._drawn_key = None
        self._image = np.zeros((height, width, 3), dtype=np.float32)  # row 0 at the top

    def set_envmap(self, path, key: str) -> None:
        """Use the equirectangular map at ``path`` (``key``: its identity; read once per key)."""
        if key == self._envmap_key:
            return
        image = np.ascontiguousarray(read_envmap(path), dtype=np.float32)  # (H, W, 3), row 0 = +Y
        texture = self.ctx.texture((image.shape[1], image.shape[0]), 3, image.tobytes(), dtype="f4")
        texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        texture.repeat_x, texture.repeat_y = True, False
        if self._envmap is not None:
            self._envmap.release()
        self._envmap, self._envmap_key, self._drawn_key = texture, key, None

    @property
    def has_envmap(self) -> bool:
        return self._envmap is not None

    def image(self, camera, rotation) -> np.ndarray:
        """(H, W, 3) float32 radiance of the map seen by ``camera``, row 0 at the top."""
        rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        key = (id(camera), self._envmap_key, rotation.tobytes())
        if key != self._drawn_key:
            half_y = math.tan(math.radians(camera.fov_y) / 2.0)
            p = self.program
            # The light's rotation moved what was at w to rotation @ w: look the map up at rotation^T d.
            p["u_to_map"].write(np.ascontiguousarray(rotation, dtype="f4").tobytes())  # row-major R = GLSL's R^T
            for name, value in (("u_forward", camera.forward), ("u_right", camera.right), ("u_up", camera.true_up)):
                p[name].value = tuple(float(v) for v in value)
            p["u_half"].value = (half_y * self.width / self.height, half_y)
            p["u_size"].value = (float(self.width), float(self.height))
            p["u_envmap"].value = 0
            draw_fullscreen(self.ctx, self.fbo, self.vao, [(self._envmap, 0)])
            self.fbo.read_into(self._image, components=3, dtype="f4")
            self._drawn_key = key
            self._camera = camera  # keeps id(camera) from being reused while the key holds it
        return self._image

    def release(self) -> None:
        for obj in (self._envmap, self.fbo, self.target, self.vao, self.program):
            if obj is not None:
                obj.release()
        self._envmap = None
