"""Per-vertex PRT (Sloan et al. 2002) estimated during a build, on its held-out samples.

The default sizing rule (:mod:`prt.train.networks.rightsize`, rule ``"vertex"``) grows each
segment's network until its held-out error is a margin below what per-vertex transfer of the
same mesh would reach, or until it holds the segment's share of per-vertex transfer's bytes.
That needs per-vertex PRT's error without a benchmark; this module estimates it from the build's
own data:

- the **vertex samples** are the front of every used vertex (its area-weighted normal, as the
  G-buffer's) and the back of the vertices of open faces (the reversed normal), as
  ``prt-bench``'s vertex baseline stores them (:func:`vertex_samples`);
- their **direct transfer** is ray traced at the build's rays per sample and seed (chunked and
  cached beside the precompute, :func:`prt.train.transport.transfer.compute_transfer`);
- their **indirect transfer** (builds with bounces) is the build's bounce estimator run on the
  vertex samples alone, as ``prt-bench``'s baseline with the same bounces computes it: each
  vertex sample shoots the build's rays per sample as bounce rays, every hit takes the previous
  bounce of the vertex sample nearest to it, N sparse products (:func:`vertex_indirect`; so the
  estimate carries no information beyond the vertices, as per-vertex PRT does not).  A first
  version took the indirect part from the nearest training samples instead: more accurate than
  per-vertex PRT's own, it set the bar too high (``docs/benchmarks/presets.md``);
- a held-out sample's vertex PRT value is the **barycentric interpolation** of its triangle's
  three vertex rows (the back rows where the sample is on an open face's back side), which is
  what the rasteriser does (:meth:`VertexEstimate.predict`; a per-sample loop is its twin in the
  tests).

The estimate's bytes are those of ``prt-bench``'s baseline: 4 bytes x (16 or 64 values) x
(vertices + back-side vertices).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...runtime.normals import vertex_normals

__all__ = ["vertex_samples", "vertex_indirect", "VertexEstimate", "estimate_vertex_prt", "barycentric"]


def vertex_samples(geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-vertex PRT's own samples: the front of every used vertex, then the back of the open faces' vertices.

    Returns
    -------
    points, normals : (S, 3) float32
        Position and (front or reversed) area-weighted vertex normal of each sample.
    front, back : (V,) int64
        Row of each vertex's front / back sample in ``points``, -1 where it has none (an unused
        vertex; a back side only where an open face uses the vertex).
    """
    vertices = np.asarray(geometry.mesh.vertices, dtype=np.float32)
    faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
    normals = vertex_normals(vertices, faces).astype(np.float32)
    used = np.flatnonzero(np.linalg.norm(normals, axis=1) > 0.0)
    open_vertices = np.unique(faces[np.asarray(geometry.two_sided, dtype=bool)])
    front, back = np.full(len(vertices), -1, np.int64), np.full(len(vertices), -1, np.int64)
    front[used] = np.arange(len(used))
    back[open_vertices] = len(used) + np.arange(len(open_vertices))
    points = np.concatenate([vertices[used], vertices[open_vertices]])
    return points, np.concatenate([normals[used], -normals[open_vertices]]), front, back


def vertex_indirect(geometry, points, normals, direct, face_albedo, bounces: int, *, rays: int, seed: int = 0) -> np.ndarray:
    """Indirect transfer ``T_1 + ... + T_N`` of the vertex samples by the build's bounce estimator on them alone.

    Parameters
    ----------
    geometry : a mesh scene
    points, normals : (S, 3)
        The samples (:func:`vertex_samples`); their rays gather each other's previous bounce.
    direct : (S, n)
        Their direct transfer.
    face_albedo : (F, 3)
    bounces : N >= 0
    rays : bounce rays per sample

    Returns
    -------
    (S, n, 3) float32
    """
    from .interreflection import interreflect, trace_bounce_rays

    direct = np.asarray(direct, dtype=np.float64)
    if int(bounces) <= 0 or len(points) == 0:
        return np.zeros(direct.shape + (3,), dtype=np.float32)
    # Unchecked lookups (clear=False): a vertex sample sits on a mesh's corner, often metres from the hit,
    # and the segment to it usually crosses the geometry round that corner (on the Duplex house 54 %
    # of the hits found no clear vertex, scratch: 512 of its vertex samples x 512 rays, and the clear rule left them dark: vertex PRT inside from
    # 9.3 to 6.3 dB, prt-bench on a scratch build).  The baseline keeps the lookup it always had, leaks through walls included.
    found = trace_bounce_rays(geometry.mesh, points, normals, rays=int(rays), seed=int(seed), clear=False)
    return (interreflect(direct, found, face_albedo, int(bounces)) - direct[:, :, None]).astype(np.float32)


def barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(M, 3) barycentric weights of ``points`` in the triangles (a, b, c), each (M, 3): of the
    point's projection onto the triangle's plane, clamped into the triangle (a sample lies on it)."""
    from ..inputs.adaptive import closest_on_triangles

    _, weights = closest_on_triangles(np.asarray(points, np.float64), np.asarray(a, np.float64), np.asarray(b, np.float64),
                                      np.asarray(c, np.float64))  # fmt: skip
    return weights


@dataclass
class VertexEstimate:
    """Per-vertex transfer of a mesh, as per-vertex PRT stores it, and its bytes.

    Attributes
    ----------
    front, back : (V, width) float32
        Transfer at each vertex for its normal and for the reversed one (``back`` equals
        ``front`` where no open face uses the vertex); width 16 (direct) or 64 ("direct+rgb").
    vertices, faces : (V, 3) float64, (F, 3) int64
    two_sided : (F,) bool
    weight_bytes : int
        4 x width x (V + back-side vertices), as ``prt-bench``'s vertex baseline counts them.
    rays : int
        Rays per vertex sample of the direct transfer.
    """

    front: np.ndarray
    back: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    two_sided: np.ndarray
    weight_bytes: int
    rays: int

    def predict(self, points, normals, face_index) -> np.ndarray:
        """Per-vertex PRT at surface samples: (M, width) float32, the barycentric interpolation of each
        sample's triangle's vertex rows (back rows on an open face's back side).

        ``points``, ``normals``: (M, 3); ``face_index``: (M,) triangle of each sample."""
        face_index = np.asarray(face_index, dtype=np.int64)
        corners = self.faces[face_index]  # (M, 3)
        tri = self.vertices[corners]  # (M, 3, 3)
        weights = barycentric(points, tri[:, 0], tri[:, 1], tri[:, 2])
        face_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        behind = self.two_sided[face_index] & (np.einsum("mc,mc->m", face_normal, np.asarray(normals, np.float64)) < 0.0)
        out = np.zeros((len(face_index), self.front.shape[1]), dtype=np.float64)
        for k in range(3):
            rows = np.where(behind[:, None], self.back[corners[:, k]], self.front[corners[:, k]])
            out += weights[:, k : k + 1] * rows
        return out.astype(np.float32)


def estimate_vertex_prt(geometry, folder, *, rays: int, bands: int, seed: int, chunk_size: int, bounces: int = 0, face_albedo=None,
                        executor=None, threads: int | None = None, progress=False, tracer=None, log=print) -> VertexEstimate:  # fmt: skip
    """Per-vertex transfer of ``geometry`` (a mesh scene) for the build's sizing rule (module docstring).

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
    folder : path
        Chunk cache of the vertices' direct transfer (``compute_transfer``'s ``cache_dir``) and their
        indirect transfer (one file, keyed by its inputs).
    rays, bands, seed, chunk_size : of the build's precompute (rays per vertex sample, direct and bounce rays).
    bounces, face_albedo : N > 0 and (F, 3): the "direct+rgb" layout with N bounces (:func:`vertex_indirect`).
    progress : bool or a :class:`prt.train.progress.BuildProgress`
    """
    import hashlib

    from ...runtime.files import atomic_save_npz
    from .transfer import compute_transfer

    points, normals, front_row, back_row = vertex_samples(geometry)
    n = bands * bands
    direct = compute_transfer(geometry, points, normals, rays=rays, bands=bands, seed=seed, chunk_size=chunk_size, threads=threads,
                              cache_dir=Path(folder), progress=progress, tracer=tracer, executor=executor, progress_stage="vertices")  # fmt: skip
    values = direct
    if bounces > 0:  # "direct+rgb": [direct, indirect R, G, B], cached (its rays are not chunked)
        digest = hashlib.sha1(np.ascontiguousarray(direct).tobytes())
        digest.update(np.ascontiguousarray(face_albedo, np.float64).tobytes())
        digest.update(f"|{bounces}|{rays}|{seed}|{len(points)}".encode())
        path = Path(folder) / f"indirect-{digest.hexdigest()[:16]}.npz"
        try:
            with np.load(path) as data:
                indirect = data["indirect"]
        except (OSError, ValueError, KeyError, EOFError):  # missing or damaged: computed again
            indirect = vertex_indirect(geometry, points, normals, direct, face_albedo, bounces, rays=rays, seed=seed)
            atomic_save_npz(path, indirect=indirect)
        values = np.concatenate([direct, indirect.transpose(0, 2, 1).reshape(len(points), -1)], axis=1)
    width = values.shape[1]
    count = len(geometry.mesh.vertices)
    front = np.zeros((count, width), dtype=np.float32)
    has_front = front_row >= 0
    front[has_front] = values[front_row[has_front]]
    back = front.copy()
    has_back = back_row >= 0
    back[has_back] = values[back_row[has_back]]
    weight_bytes = 4 * width * (count + int(has_back.sum()))
    log(f"vertex PRT estimate: {len(points):,} vertex samples x {rays} rays{f', {bounces} bounce(s)' if bounces else ''}, {weight_bytes:,} bytes")
    return VertexEstimate(front=front, back=back, vertices=np.asarray(geometry.mesh.vertices, dtype=np.float64),
                          faces=np.asarray(geometry.mesh.faces, dtype=np.int64), two_sided=np.asarray(geometry.two_sided, dtype=bool),
                          weight_bytes=weight_bytes, rays=int(rays))  # fmt: skip

