"""Mesh normals shared by the G-buffer and the training samples (numpy only)."""

from __future__ import annotations

import numpy as np

__all__ = ["CREASE_COS", "vertex_normals", "corner_normals", "interpolated_normals"]

# Corners whose smooth normal is further than this from the face normal keep the face normal,
# so creases (box edges, the Cornell walls) stay sharp while curved surfaces shade smoothly.
CREASE_COS = float(np.cos(np.radians(40.0)))


def _face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) float64 cross product of each face's edges: 2 x area x unit normal."""
    corners = np.asarray(vertices)[faces].astype(np.float64)  # (F, 3, 3)
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def _unit_vertex_sum(weighted: np.ndarray, faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V, 3) unit sum of ``weighted`` (F, 3) over the faces at each vertex; zero where it vanishes."""
    vertex_normal = np.zeros((n_vertices, 3))
    for k in range(3):
        np.add.at(vertex_normal, faces[:, k], weighted)
    vlen = np.linalg.norm(vertex_normal, axis=1, keepdims=True)
    return np.divide(vertex_normal, vlen, out=np.zeros_like(vertex_normal), where=vlen > 0.0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float64 area-weighted vertex normals: unit, zero for unused or degenerate vertices.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    """
    faces = np.asarray(faces).astype(np.int64)
    return _unit_vertex_sum(_face_cross(vertices, faces), faces, len(vertices))


def corner_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normals the G-buffer interpolates: ``(face (F, 3), corner (F, 3, 3))``, float64.

    Corner normals are area-weighted vertex normals (:func:`vertex_normals`; vertices are shared
    within an object only, see prt.train.inputs.geometry), except at creases: a corner further than 40
    degrees from its face's normal keeps the face normal.  Degenerate faces get zero normals.
    Training samples take their normals from here too (barycentric mix, normalised), so the
    networks learn transfer for the normals the runtime asks about.
    """
    faces = np.asarray(faces).astype(np.int64)
    weighted = _face_cross(vertices, faces)  # 2 x area x normal
    length = np.linalg.norm(weighted, axis=1, keepdims=True)
    normal = np.divide(weighted, length, out=np.zeros_like(weighted), where=length > 0.0)
    smooth = _unit_vertex_sum(weighted, faces, len(vertices))[faces]  # (F, 3, 3)
    crease = np.einsum("fkc,fc->fk", smooth, normal) < CREASE_COS
    smooth[crease] = np.broadcast_to(normal[:, None, :], smooth.shape)[crease]
    return normal, smooth


def interpolated_normals(corner: np.ndarray, face: np.ndarray, faces_index: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Unit normals at points given by face index and barycentric ``weights`` (N, 3), as the
    rasteriser interpolates ``corner`` normals; the face normal where the mix vanishes."""
    mixed = np.einsum("nk,nkc->nc", weights, corner[faces_index])
    length = np.linalg.norm(mixed, axis=1, keepdims=True)
    out = np.divide(mixed, length, out=np.zeros_like(mixed), where=length > 1e-12)
    bad = ~(length[:, 0] > 1e-12)
    out[bad] = face[faces_index[bad]]
    return out
