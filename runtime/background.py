"""The environment map as the background: drawn where no geometry is, in linear radiance.

The renderer composites it into a frame's uncovered pixels when the background is on
(:meth:`prt.runtime.renderer.Renderer.set_background`; a manifest's ``lighting.background``),
before tone mapping, so both backends and every display path tone-map it the same way.  The
map follows the light: the same file and the same rotation as the lighting.  One full-screen
pass (``shaders/background.frag``) draws it; it is redrawn only when the camera, the map, its
rotation or the G-buffer (its ``generation``) changes.  A frame shaded on the CPU draws it right
after the G-buffer's pass (:meth:`EnvmapBackground.draw_layer`), so one wait on the GL finishes
both, and reads it back when the frame is assembled (:meth:`EnvmapBackground.image`).

Given the G-buffer's depth target, the pass shades only the pixels no geometry covers: its
triangle lies on the far plane and a depth test ``<=`` against that target (1 where nothing was
drawn; this pass writes no depth) lets only those through.  The pixels under geometry are left
as they are (not even cleared): the renderer fills them with the shaded frame.  Without a depth
target every pixel is drawn (the reference twin; the two agree exactly where nothing is covered).
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..shaders import assemble
from .envmap import read_envmap
from .gl import bind_framebuffer, compile_program, draw_fullscreen

__all__ = ["EnvmapBackground"]


class EnvmapBackground:
    """The background layer of one renderer (its context and size)."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int) -> None:
        self.ctx, self.width, self.height = ctx, width, height
        vertex = assemble("fullscreen.vert", defines={"PRT_FULLSCREEN_Z": 1.0})  # on the far plane
        self.program = compile_program(ctx, assemble("background.frag"), "background.frag", vertex=vertex)
        self.vao = ctx.vertex_array(self.program, [])
        self.target = ctx.texture((width, height), 3, dtype="f4")
        self.fbo = ctx.framebuffer([self.target])
        self._depth_fbo = None  # the target with a G-buffer's depth (built for the depth texture given)
        self._depth = None
        self._envmap_key = None
        self._envmap: moderngl.Texture | None = None
        self._drawn_key = None  # the layer drawn and read back into _image
        self._pending_key = None  # the layer drawn into the target, not read back yet
        self._image = np.zeros((height, width, 3), dtype=np.float32)  # as GL reads it: row 0 at the bottom

    def set_envmap(self, path, key: str) -> None:
        """Use the equirectangular map at ``path`` (``key``: its identity; read once per key)."""
        if key == self._envmap_key:
            return
        image = np.asarray(read_envmap(path), dtype=np.float32)  # (H, W, 3), row 0 = +Y
        # RGBA: llvmpipe filters four-channel float texels faster than three, to the same values.
        texels = np.ones(image.shape[:2] + (4,), dtype=np.float32)
        texels[..., :3] = image
        texture = self.ctx.texture((image.shape[1], image.shape[0]), 4, texels.tobytes(), dtype="f4")
        texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        texture.repeat_x, texture.repeat_y = True, False
        if self._envmap is not None:
            self._envmap.release()
        self._envmap, self._envmap_key, self._drawn_key, self._pending_key = texture, key, None, None

    @property
    def has_envmap(self) -> bool:
        return self._envmap is not None

    def draw_layer(self, camera, rotation, depth: moderngl.Texture | None = None, generation: int = 0) -> None:
        """Draw the layer :meth:`image` returns for the same arguments into this object's target now,
        without reading it back (nothing is drawn when it is drawn already).  ``generation``: the
        G-buffer's, so a new G-buffer behind the same camera (a deformed pose) is drawn again."""
        key = self._key(camera, rotation, depth, generation)
        if key in (self._drawn_key, self._pending_key):
            return
        self._set_view(camera, self._rotation(rotation))
        if depth is None:
            draw_fullscreen(self.ctx, self.fbo, self.vao, [(self._envmap, 0)])
        else:
            self._draw_behind(self._fbo_with(self.target, depth))
        self._pending_key = key
        self._camera = camera  # keeps id(camera) from being reused while the key holds it

    def image(self, camera, rotation, depth: moderngl.Texture | None = None, generation: int = 0) -> np.ndarray:
        """(H, W, 3) float32 radiance of the map seen by ``camera``, row 0 at the top.

        ``depth``: the G-buffer's depth texture for this camera (same size); only the pixels
        where it is 1 (nothing drawn) are drawn, the others keep whatever an earlier call left
        there (the caller overwrites them: no clear).  None: every pixel.  ``generation``: see
        :meth:`draw_layer` (a layer it drew is read back, not drawn again).  The array is a view
        of this object's buffer (rows flipped), overwritten by the next call that redraws.
        """
        key = self._key(camera, rotation, depth, generation)
        if key != self._drawn_key:
            self.draw_layer(camera, rotation, depth, generation)
            self.fbo.read_into(self._image, components=3, dtype="f4")
            self._drawn_key, self._pending_key = key, None
        return self._image[::-1]

    def _key(self, camera, rotation, depth, generation: int) -> tuple:
        return (id(camera), self._envmap_key, self._rotation(rotation).tobytes(), None if depth is None else id(depth), generation)

    @staticmethod
    def _rotation(rotation) -> np.ndarray:
        return np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)

    def draw_into(self, target: moderngl.Texture, camera, rotation, depth: moderngl.Texture) -> None:
        """Draw the map into ``target`` (a frame shaded on the GPU, the size of this layer) where
        ``depth`` is 1, as :meth:`image` draws it into its own layer; nothing is read back, the
        pixels under geometry keep the frame."""
        self._set_view(camera, self._rotation(rotation))
        self._draw_behind(self._fbo_with(target, depth))

    def _set_view(self, camera, rotation: np.ndarray) -> None:
        half_y = math.tan(math.radians(camera.fov_y) / 2.0)
        p = self.program
        # The light's rotation moved what was at w to rotation @ w: look the map up at rotation^T d.
        p["u_to_map"].write(np.ascontiguousarray(rotation, dtype="f4").tobytes())  # row-major R = GLSL's R^T
        for name, value in (("u_forward", camera.forward), ("u_right", camera.right), ("u_up", camera.true_up)):
            p[name].value = tuple(float(v) for v in value)
        p["u_half"].value = (half_y * self.width / self.height, half_y)
        p["u_size"].value = (float(self.width), float(self.height))
        p["u_envmap"].value = 0

    def _draw_behind(self, fbo) -> None:
        """One draw into ``fbo`` (a colour target and a G-buffer's depth): the far-plane triangle
        passes the ``<=`` depth test where nothing was drawn."""
        previous = self.ctx.fbo
        try:
            self._envmap.use(0)
            fbo.use()
            self.ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
            self.ctx.enable(moderngl.DEPTH_TEST)
            self.ctx.depth_func = "<="
            self.vao.render(moderngl.TRIANGLES, vertices=3)
        finally:
            self.ctx.disable(moderngl.DEPTH_TEST)
            bind_framebuffer(self.ctx, previous)

    def _fbo_with(self, target: moderngl.Texture, depth: moderngl.Texture):
        """``target`` with ``depth`` attached, read-only (depth writes off); one kept per pair."""
        key = (id(target), id(depth))
        if self._depth != key:
            if self._depth_fbo is not None:
                self._depth_fbo.release()
            self._depth_fbo = None  # a failed creation leaves none behind
            self._depth_fbo = self.ctx.framebuffer([target], depth)
            self._depth_fbo.depth_mask = False
            self._depth = key
            self._attached = (target, depth)  # keeps the ids from being reused while the key holds them
        return self._depth_fbo

    def release(self) -> None:
        for obj in (self._envmap, self._depth_fbo, self.fbo, self.target, self.vao, self.program):
            if obj is not None:
                obj.release()
        self._envmap = self._depth_fbo = self._depth = None
