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
- their **indirect transfer** (builds with bounces) is the mean of the :data:`NEIGHBOURS`
  training samples nearest in (position, normal) (:data:`~prt.train.transport.interreflection.NORMAL_WEIGHT`
  as in the bounce lookup): indirect light is smooth, and so the estimate does not trace bounce
  rays of its own (``prt-bench`` does, on the vertices, with the build's bounce estimator);
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

__all__ = ["NEIGHBOURS", "vertex_samples", "VertexEstimate", "estimate_vertex_prt", "barycentric"]

# Training samples whose indirect transfer a vertex sample averages (about 8 x 32 bounce rays).
NEIGHBOURS = 8


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


def estimate_vertex_prt(geometry, samples: dict, folder, *, rays: int, bands: int, seed: int, chunk_size: int, executor=None,
                        threads: int | None = None, progress=False, tracer=None, log=print) -> VertexEstimate:  # fmt: skip
    """Per-vertex transfer of ``geometry`` (a mesh scene) for the build's sizing rule (module docstring).

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
    samples : dict
        The build's training samples: ``points``, ``normals`` (S, 3) and ``transfer`` (S, n) or, after
        the bounce stage, (S, 4 n) ("direct+rgb": its indirect part is averaged onto the vertices).
    folder : path
        Chunk cache of the vertices' direct transfer (``compute_transfer``'s ``cache_dir``).
    rays, bands, seed, chunk_size : of the build's precompute (rays per vertex sample).
    progress : bool or a :class:`prt.train.progress.BuildProgress`
    """
    from scipy.spatial import cKDTree

    from .interreflection import NORMAL_WEIGHT
    from .transfer import compute_transfer

    points, normals, front_row, back_row = vertex_samples(geometry)
    n = bands * bands
    direct = compute_transfer(geometry, points, normals, rays=rays, bands=bands, seed=seed, chunk_size=chunk_size, threads=threads,
                              cache_dir=Path(folder), progress=progress, tracer=tracer, executor=executor, progress_stage="vertices")  # fmt: skip
    transfer = np.asarray(samples["transfer"], dtype=np.float32)
    values = direct
    if transfer.shape[1] > n:  # "direct+rgb": the indirect part from the nearest training samples
        key = np.concatenate([samples["points"], NORMAL_WEIGHT * _unit(samples["normals"])], axis=1)
        k = min(NEIGHBOURS, len(key))
        _, near = cKDTree(key).query(np.concatenate([points, NORMAL_WEIGHT * _unit(normals)], axis=1), k=k, workers=threads or -1)
        near = np.asarray(near).reshape(len(points), k)
        values = np.concatenate([direct, transfer[near, n:].mean(axis=1)], axis=1)
    width = values.shape[1]
    count = len(geometry.mesh.vertices)
    front = np.zeros((count, width), dtype=np.float32)
    has_front = front_row >= 0
    front[has_front] = values[front_row[has_front]]
    back = front.copy()
    has_back = back_row >= 0
    back[has_back] = values[back_row[has_back]]
    weight_bytes = 4 * width * (count + int(has_back.sum()))
    log(f"vertex PRT estimate: {len(points):,} vertex samples x {rays} rays, {weight_bytes:,} bytes")
    return VertexEstimate(front=front, back=back, vertices=np.asarray(geometry.mesh.vertices, dtype=np.float64),
                          faces=np.asarray(geometry.mesh.faces, dtype=np.int64), two_sided=np.asarray(geometry.two_sided, dtype=bool),
                          weight_bytes=weight_bytes, rays=int(rays))  # fmt: skip


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
