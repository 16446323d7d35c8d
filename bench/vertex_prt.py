"""The vertex-space baseline: Sloan-style per-vertex transfer (Sloan et al. 2002).

Transfer ray traced at the mesh vertices (area-weighted vertex normals,
:func:`prt.runtime.normals.vertex_normals`; open surfaces get a second set for their back
side), interpolated by the rasteriser (4 RGBA32F targets, ``shaders/vertex_prt.vert|frag``),
shaded like the rest; mesh scenes only.
"""

from __future__ import annotations

import time
from pathlib import Path

import moderngl
import numpy as np

from prt.bench.reference import cached_transfer
from prt.runtime.normals import vertex_normals
from prt.shaders import assemble

__all__ = ["VertexPRT", "vertex_transfer"]


class VertexPRT:
    """Per-vertex transfer (Sloan et al. 2002) interpolated across triangles by the rasteriser.

    Parameters
    ----------
    ctx : moderngl.Context
    geometry : prt.train.geometry.Geometry
        A mesh scene (not an SDF).
    front, back : (V, 16) float32
        Transfer at each vertex for its normal and for the reversed normal (used by open
        surfaces seen from behind).
    width, height : int

    Attributes
    ----------
    timings : dict
        ``raster`` and ``readback`` milliseconds of the last :meth:`render`.
    """

    def __init__(self, ctx, geometry, front, back, width: int, height: int):
        self.ctx, self.width, self.height = ctx, int(width), int(height)
        faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
        record = np.dtype([("p", "<f4", 3), ("f", "<f4", 16), ("b", "<f4", 16), ("s", "<i4")])
        corners = np.empty((len(faces), 3), dtype=record)  # unindexed: sidedness is per face
        corners["p"] = np.asarray(geometry.mesh.vertices, dtype=np.float32)[faces]
        corners["f"] = front[faces]
        corners["b"] = back[faces]
        corners["s"] = np.asarray(geometry.two_sided, dtype=np.int32)[:, None]
        self.program = ctx.program(vertex_shader=assemble("vertex_prt.vert"), fragment_shader=assemble("vertex_prt.frag"))
        self.vbo = ctx.buffer(corners.tobytes())
        names = ["in_position", *(f"in_f{k}" for k in range(4)), *(f"in_b{k}" for k in range(4)), "in_two_sided"]
        self.vao = ctx.vertex_array(self.program, [(self.vbo, "3f 4f 4f 4f 4f 4f 4f 4f 4f 1i", *names)])
        self.count = 3 * len(faces)
        self.textures = [ctx.texture((self.width, self.height), 4, dtype="f4") for _ in range(4)]
        for tex in self.textures:
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.depth = ctx.depth_texture((self.width, self.height))
        self.fbo = ctx.framebuffer(self.textures, self.depth)
        self._staging = np.empty((4, self.height, self.width, 4), dtype=np.float32)
        self.timings: dict[str, float] = {}

    def render(self, camera):
        """Rasterise the interpolated transfer seen by ``camera``.

        Returns
        -------
        transfer : (H, W, 16) float32, row 0 at the top
        drawn : (H, W) bool, pixels a triangle covers
        """
        t0 = time.perf_counter()
        self.program["u_view_projection"].write(camera.view_projection(self.width / self.height).T.astype(np.float32).tobytes())
        self.fbo.use()  # every pass of the renderer binds its own target, so none is restored
        self.ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.vao.render(moderngl.TRIANGLES, vertices=self.count)
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.ctx.finish()
        t1 = time.perf_counter()
        for k in range(4):
            self.fbo.read_into(self._staging[k], components=4, attachment=k, dtype="f4")
        transfer = np.ascontiguousarray(self._staging[:, ::-1].transpose(1, 2, 0, 3).reshape(self.height, self.width, 16))
        t2 = time.perf_counter()
        depth = np.frombuffer(self.fbo.read(attachment=-1, components=1, dtype="f4"), dtype=np.float32)
        self.timings = {"raster": 1e3 * (t1 - t0), "readback": 1e3 * (t2 - t1)}
        return transfer, depth.reshape(self.height, self.width)[::-1] < 1.0

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.program, self.fbo, self.depth, *self.textures):
            obj.release()


def vertex_transfer(geometry, tracer, rays: int, cache: Path, geometry_id: str):
    """Transfer at the mesh vertices: front (area-weighted normal) and back (reversed normal).

    Returns
    -------
    front, back : (V, 16) float32
        ``back`` equals ``front`` at vertices no open (two-sided) face uses.
    back_vertices : int
        Vertices that needed a second, back-side transfer vector.
    """
    vertices = np.asarray(geometry.mesh.vertices, dtype=np.float32)
    faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
    normals = vertex_normals(vertices, faces).astype(np.float32)
    front, _ = cached_transfer(cache, "vertices-front", geometry, tracer, vertices, normals, rays, 0, geometry_id)
    back = front.copy()
    open_vertices = np.unique(faces[np.asarray(geometry.two_sided, dtype=bool)])
    if len(open_vertices):
        back[open_vertices], _ = cached_transfer(
            cache, "vertices-back", geometry, tracer, vertices[open_vertices], -normals[open_vertices], rays, 0, geometry_id
        )
    return front, back, int(len(open_vertices))
