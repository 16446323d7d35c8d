"""Surface samples: area-weighted uniform points on meshes (Turk 1990) and on SDF zero sets.

Every random draw comes from a generator keyed by ``(seed, stream)`` so the training set and
the held-out validation set are independent and reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...runtime.errors import GeometryError
from ...runtime.normals import corner_normals, interpolated_normals

__all__ = ["SurfaceSamples", "sample_surface", "TRAIN_STREAM", "VALIDATION_STREAM"]

TRAIN_STREAM = 0
VALIDATION_STREAM = 1


@dataclass
class SurfaceSamples:
    """Points on a surface with the normal of the side they belong to.

    points : (N, 3) float32, scene units
    normals : (N, 3) float32, unit length: on meshes the normal the runtime's G-buffer
        interpolates there (smooth vertex normals, the face normal at creases; see
        :func:`prt.runtime.normals.corner_normals`), on SDFs the gradient
    face_index : (N,) int64, triangle of ``geometry.mesh`` the sample was drawn from
    object_ids : (N,) int64, object of that triangle
    weights : (N, 3) float64 barycentric weights of the point in its triangle (meshes; None on SDFs):
        the same point on another pose of the mesh (deformable scenes, :mod:`prt.train.deform.deform_build`)
    """

    points: np.ndarray
    normals: np.ndarray
    face_index: np.ndarray
    object_ids: np.ndarray
    weights: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, index: np.ndarray) -> "SurfaceSamples":
        return SurfaceSamples(
            self.points[index], self.normals[index], self.face_index[index], self.object_ids[index],
            None if self.weights is None else self.weights[index],
        )


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(stream)]))


def sample_surface(geometry, count: int, *, seed: int = 0, stream: int = TRAIN_STREAM, sides=None) -> SurfaceSamples:
    """Draw ``count`` area-uniform samples on ``geometry``.

    Meshes: a face is chosen with probability proportional to its area, then a uniform
    point inside it (square-root barycentric warp), with the interpolated smooth normal the
    G-buffer gives that point.  Faces of open components
    (``geometry.two_sided``) are surfaces on both sides: each sample takes one side at random.
    SDF scenes: samples on the marching-cubes mesh are projected onto the zero level set
    along the gradient and take the normalised gradient as normal.  Mixed scenes
    (:mod:`prt.train.inputs.mixed`): samples on an SDF object's proxy faces so, onto that object's own
    zero set; samples on mesh objects as on meshes.

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
    count : int, number of samples (> 0)
    seed, stream : keys of the random generator (use another stream for validation)
    sides : (F, 2) bool or None
        Meshes: the sides of each face samples may stand for (side 0 along the face's winding,
        side 1 against it; :func:`prt.train.inputs.visibility.surface_sides`).  Faces with an
        allowed side are drawn by area (as without ``sides``), faces without one not at all, and
        each sample takes an allowed side (at random where both are).  None: the geometry's own sides (one-sided faces their
        front, two-sided ones either), drawn exactly as before.
    """
    if count <= 0:
        raise ValueError(f"sample count must be positive, got {count}")
    mesh = geometry.mesh
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    if sides is not None:
        sides = np.asarray(sides, dtype=bool)
        areas = areas * sides.any(axis=1)  # a face keeps its area's share; its samples split among its allowed sides
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise GeometryError(f"{geometry.source}: surface has no area to sample")
    rng = _rng(seed, stream)
    cdf = np.cumsum(areas)
    faces = np.searchsorted(cdf, rng.random(count) * cdf[-1], side="right")
    faces = np.minimum(faces, len(areas) - 1)
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    tri = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)[faces]]  # (N, 3, 3)
    points = (
        (1.0 - r1)[:, None] * tri[:, 0]
        + (r1 * (1.0 - r2))[:, None] * tri[:, 1]
        + (r1 * r2)[:, None] * tri[:, 2]
    )
    flip = rng.random(count) < 0.5  # drawn either way: SDF and mesh samples keep one random stream
    if geometry.sdf is not None:
        points = geometry.sdf.project_to_surface(points)
        normals = geometry.sdf.normals(points)
    elif geometry.kind == "mixed":
        normals = _mixed_samples(geometry, points, faces, r1, r2, flip)
    else:
        # The normals the runtime's G-buffer interpolates (smooth, face normals at creases), so
        # the networks learn transfer for the normals they will be asked about.
        face_normal, corner = corner_normals(np.asarray(mesh.vertices), np.asarray(mesh.faces))
        weights = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
        normals = interpolated_normals(corner, face_normal, faces, weights)
        if sides is None:
            two_sided = np.asarray(geometry.two_sided, dtype=bool)[faces]
            normals[two_sided & flip] *= -1.0
        else:
            allowed = sides[faces]
            back = np.where(allowed.all(axis=1), flip, allowed[:, 1])
            normals[back] *= -1.0  # corner normals lie within 40 degrees of the front (CREASE_COS)
    normals = _safe_normalise(normals)
    return SurfaceSamples(
        points.astype(np.float32),
        normals.astype(np.float32),
        faces.astype(np.int64),
        np.asarray(geometry.object_ids, dtype=np.int64)[faces],
        None if geometry.sdf is not None else np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1),
    )


def _mesh_normals(geometry, faces, r1, r2, flip) -> np.ndarray:
    """The G-buffer's interpolated normals at barycentric (r1, r2) samples of ``faces``."""
    mesh = geometry.mesh
    face_normal, corner = corner_normals(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    weights = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    normals = interpolated_normals(corner, face_normal, faces, weights)
    two_sided = np.asarray(geometry.two_sided, dtype=bool)[faces]
    normals[two_sided & flip] *= -1.0
    return normals


def _mixed_samples(geometry, points, faces, r1, r2, flip) -> np.ndarray:
    """Mixed scenes: project the SDF objects' samples (in place) onto their own zero sets; normals."""
    parts = geometry.mixed
    normals = np.zeros_like(points)
    on_mesh = ~parts.proxy_faces[faces]
    if on_mesh.any():
        # corner normals of the whole mesh: proxy faces share no vertex with mesh objects
        normals[on_mesh] = _mesh_normals(geometry, faces[on_mesh], r1[on_mesh], r2[on_mesh], flip[on_mesh])
    objects = np.asarray(geometry.object_ids, dtype=np.int64)[faces]
    for k, sdf in parts.sdfs.items():
        mine = np.flatnonzero(~on_mesh & (objects == k))
        if mine.size:
            points[mine] = sdf.project_to_surface(points[mine])
            normals[mine] = sdf.normals(points[mine])
    return normals


def _safe_normalise(v: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    bad = ~(length[:, 0] > 1e-12)
    out = v / np.where(length > 1e-12, length, 1.0)
    out[bad] = (0.0, 1.0, 0.0)  # degenerate normal: any unit vector keeps the tracer finite
    return out
