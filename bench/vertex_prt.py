"""The vertex-space baseline: Sloan-style per-vertex transfer (Sloan et al. 2002), direct or interreflected.

Transfer ray traced at the mesh vertices (area-weighted vertex normals,
:func:`prt.runtime.normals.vertex_normals`; open surfaces get a second set for their back
side), interpolated by the rasteriser (4 RGBA32F targets per pass of 16 values,
``shaders/vertex_prt.vert|frag``), shaded like the rest; mesh scenes only.

Interreflected transfer (scenes built with ``--bounces N``, Sloan et al. 2002 section 6) uses
the build's bounce-stage estimator (:mod:`prt.train.transport.interreflection`) with the vertices as its
samples, so the baseline carries no information beyond its own vertices: the sample set is the
front of every used vertex plus the back of the vertices of open faces (reversed normal); each
shoots cosine rays (:func:`prt.train.transport.interreflection.trace_bounce_rays`), every hit takes the
previous bounce of the vertex sample nearest to it in (position, normal), tangent-plane aware
(:func:`prt.train.transport.interreflection.nearest_on_plane`; unchecked for walls between, unlike the build's:
see :func:`prt.train.transport.vertex_estimate.vertex_indirect`), and the bounces are the sparse products of
:func:`prt.train.transport.interreflection.interreflect`: ``T_b = W @ T_{b-1}`` over the vertex samples,
starting from their ray-traced direct transfer.  (Not the benchmark reference's estimator,
:mod:`prt.bench.bounce_reference`, which traces the direct transfer afresh at every hit and
reads higher bounces from independent samples.)  The result has the networks' "direct+rgb"
layout (direct, indirect R, G, B: 64 values per vertex and side), drawn in 4 raster passes.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import moderngl
import numpy as np

from prt.bench.bounce_reference import direct_rgb
from prt.bench.reference import cached_transfer
from prt.runtime.files import atomic_save_npz
from prt.runtime.gl import bind_framebuffer
from prt.runtime.normals import vertex_normals
from prt.shaders import assemble
from prt.train.transport.vertex_estimate import vertex_indirect, vertex_samples  # the build's estimate computes them alike

__all__ = ["VertexPRT", "vertex_transfer", "vertex_samples", "vertex_indirect", "cached_vertex_indirect", "vertex_bounce_transfer",
           "ESTIMATOR_VERSION"]

# Part of the cache key of the interreflected vertex transfer: raise it when the estimator changes.
ESTIMATOR_VERSION = "vertex-bounces-v1"
_PASS = 16  # transfer values one raster pass writes (4 RGBA32F targets)


class VertexPRT:
    """Per-vertex transfer (Sloan et al. 2002) interpolated across triangles by the rasteriser.

    Parameters
    ----------
    ctx : moderngl.Context
    geometry : prt.train.inputs.geometry.Geometry
        A mesh scene (not an SDF).
    front, back : (V, n) float32
        Transfer at each vertex for its normal and for the reversed normal (used by open
        surfaces seen from behind); ``n`` = 16 (direct) or 64 ("direct+rgb"), one raster pass
        per 16 values.
    width, height : int

    Attributes
    ----------
    timings : dict
        ``raster`` and ``readback`` milliseconds of the last :meth:`render` (all passes).
    """

    def __init__(self, ctx, geometry, front, back, width: int, height: int):
        self.ctx, self.width, self.height = ctx, int(width), int(height)
        front, back = np.asarray(front, dtype=np.float32), np.asarray(back, dtype=np.float32)
        if front.shape != back.shape or front.ndim != 2 or front.shape[1] % _PASS:
            raise ValueError(f"VertexPRT: front and back must both be (V, 16 k), got {front.shape} and {back.shape}")
        faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
        record = np.dtype([("p", "<f4", 3), ("f", "<f4", _PASS), ("b", "<f4", _PASS), ("s", "<i4")])
        positions = np.asarray(geometry.mesh.vertices, dtype=np.float32)[faces]
        two_sided = np.asarray(geometry.two_sided, dtype=np.int32)[:, None]
        self.program = ctx.program(vertex_shader=assemble("vertex_prt.vert"), fragment_shader=assemble("vertex_prt.frag"))
        names = ["in_position", *(f"in_f{k}" for k in range(4)), *(f"in_b{k}" for k in range(4)), "in_two_sided"]
        self.vbos, self.vaos = [], []
        for start in range(0, front.shape[1], _PASS):  # one vertex buffer per pass of 16 values
            corners = np.empty((len(faces), 3), dtype=record)  # unindexed: sidedness is per face
            corners["p"], corners["s"] = positions, two_sided
            corners["f"] = front[:, start : start + _PASS][faces]
            corners["b"] = back[:, start : start + _PASS][faces]
            self.vbos.append(ctx.buffer(corners.tobytes()))
            self.vaos.append(ctx.vertex_array(self.program, [(self.vbos[-1], "3f 4f 4f 4f 4f 4f 4f 4f 4f 1i", *names)]))
        self.count = 3 * len(faces)
        self.textures = [ctx.texture((self.width, self.height), 4, dtype="f4") for _ in range(4)]
        for tex in self.textures:
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.depth = ctx.depth_texture((self.width, self.height))
        self.fbo = ctx.framebuffer(self.textures, self.depth)
        self._staging = np.empty((len(self.vaos), 4, self.height, self.width, 4), dtype=np.float32)
        self.timings: dict[str, float] = {}

    def render(self, camera):
        """Rasterise the interpolated transfer seen by ``camera``.

        Returns
        -------
        transfer : (H, W, n) float32, row 0 at the top
        drawn : (H, W) bool, pixels a triangle covers
        """
        raster = readback = 0.0
        self.program["u_view_projection"].write(camera.view_projection(self.width / self.height).T.astype(np.float32).tobytes())
        for p, vao in enumerate(self.vaos):
            t0 = time.perf_counter()
            self.fbo.use()  # every pass of the renderer binds its own target, so none is restored
            self.ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
            self.ctx.enable(moderngl.DEPTH_TEST)
            self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            vao.render(moderngl.TRIANGLES, vertices=self.count)
            self.ctx.disable(moderngl.DEPTH_TEST)
            self.ctx.finish()
            t1 = time.perf_counter()
            for k in range(4):
                self.fbo.read_into(self._staging[p, k], components=4, attachment=k, dtype="f4")
            raster, readback = raster + (t1 - t0), readback + (time.perf_counter() - t1)
        # (pass, target, H, W, 4) -> (H, W, pass * 16): pass-major, as the vertex arrays' columns
        transfer = np.ascontiguousarray(self._staging[:, :, ::-1].transpose(2, 3, 0, 1, 4).reshape(self.height, self.width, -1))
        depth = np.frombuffer(self.fbo.read(attachment=-1, components=1, dtype="f4"), dtype=np.float32)
        self.timings = {"raster": 1e3 * raster, "readback": 1e3 * readback}
        return transfer, depth.reshape(self.height, self.width)[::-1] < 1.0

    def release(self) -> None:
        """Free the GL objects; the default framebuffer is bound first (moderngl re-binds the bound one
        when it creates a framebuffer, and a released one there makes that fail)."""
        bind_framebuffer(self.ctx, None)
        for obj in (*self.vaos, *self.vbos, self.program, self.fbo, self.depth, *self.textures):
            obj.release()


def cached_vertex_indirect(cache: Path, geometry, points, normals, direct, face_albedo, bounces: int, *, rays: int, seed: int,
                           geometry_id: str) -> tuple[np.ndarray, float]:  # fmt: skip
    """:func:`vertex_indirect`, read from ``cache`` when computed before; (indirect, seconds computed).

    Keyed by the samples, their direct transfer, the albedos, ``bounces``, ``rays``, ``seed``, the
    geometry and :data:`ESTIMATOR_VERSION`.
    """
    digest = hashlib.sha1()
    for part in (points, normals, direct, face_albedo):
        digest.update(np.ascontiguousarray(part).tobytes())
    digest.update(f"|{bounces}|{rays}|{seed}|{geometry_id}|{ESTIMATOR_VERSION}".encode())
    path = Path(cache) / f"vertices-indirect-b{bounces}-m{rays}-s{seed}-{digest.hexdigest()[:12]}.npz"
    if path.is_file():
        with np.load(path) as data:
            return data["indirect"], 0.0
    t0 = time.perf_counter()
    indirect = vertex_indirect(geometry, points, normals, direct, face_albedo, bounces, rays=rays, seed=seed)
    seconds = time.perf_counter() - t0
    atomic_save_npz(path, indirect=indirect)
    return indirect, seconds


def vertex_transfer(geometry, tracer, rays: int, cache: Path, geometry_id: str):
    """Direct transfer at the mesh vertices: front (area-weighted normal) and back (reversed normal).

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


def vertex_bounce_transfer(geometry, front, back, face_albedo, bounces: int, *, rays: int, seed: int, cache: Path,
                           geometry_id: str) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """The interreflected vertex transfer in the "direct+rgb" layout, from :func:`vertex_transfer`'s direct one.

    Returns
    -------
    front, back : (V, 64) float32
        Direct (16), then indirect R, G, B (16 each); unused vertices get zero indirect, and
        ``back`` equals ``front`` where no open face uses the vertex.
    seconds : float
        Time spent computing (0 when cached).
    """
    points, normals, front_row, back_row = vertex_samples(geometry)
    direct = np.zeros((len(points), front.shape[1]), dtype=np.float32)
    has_front, has_back = front_row >= 0, back_row >= 0
    direct[front_row[has_front]] = front[has_front]
    direct[back_row[has_back]] = back[has_back]
    indirect, seconds = cached_vertex_indirect(cache, geometry, points, normals, direct, face_albedo, bounces, rays=rays, seed=seed,
                                               geometry_id=geometry_id)  # fmt: skip
    front_indirect = np.zeros((len(front),) + indirect.shape[1:], dtype=np.float32)
    front_indirect[has_front] = indirect[front_row[has_front]]
    back_indirect = front_indirect.copy()
    back_indirect[has_back] = indirect[back_row[has_back]]
    return direct_rgb(front, front_indirect), direct_rgb(back, back_indirect), seconds
