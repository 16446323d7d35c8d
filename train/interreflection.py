"""Interreflected transfer (Sloan, Kautz and Snyder 2002, section 6): the bounce operator.

Direct transfer ``T_0(p)`` (16 SH coefficients, including the ``1/pi``: see docs/design.md)
gives the irradiance-weighted light a point receives straight from the environment.  Light that
reaches ``p`` after bouncing off another surface point ``q`` is, for a diffuse ``q`` with albedo
``a(q)``, ``a(q) dot(T_{b-1}(q), L)``; with the cosine-importance-sampled rays of
:mod:`prt.train.transfer` (pdf ``cos / pi``, which cancels the cosine and the ``1/pi``)

    T_b(p) = mean_j  hit_j * a(q_j) * T_{b-1}(q_j)          (RGB: a is a colour)

and the interreflected transfer is ``T_0 + T_1 + ... + T_N``.  Every term is linear in the
lighting ``L``, so relighting stays a dot product per channel; with coloured albedos the result
is RGB transfer, shape (S, n, 3).

Estimator of ``T_{b-1}(q)`` at a hit point: the ray-traced transfer of the precomputed sample
nearest to ``q`` in (position, NORMAL_WEIGHT * normal), the hit's normal turned towards the ray's
origin: so the sample is on the side of the surface the ray sees (open surfaces have samples
on both sides at the same places).
Chosen over the fitted direct networks because it needs nothing beyond the precompute (the
bounce stage runs before fitting, stays chunked and deterministic, and its error does not depend
on how well a network fitted), and because each bounce then costs a sparse product: the rays,
hit points and nearest samples are found once (:func:`trace_bounce_rays`) and every bounce is
``T_b[:, :, c] = W_c @ T_{b-1}[:, :, c]`` with ``W_c[p, q] = sum of a_c(hit) / M`` over p's
rays landing nearest to q.  Indirect light is smooth, so it takes fewer rays than the direct
term (:data:`BOUNCE_RAYS`).

Status: the operator and its tests; ``prt-train --bounces`` and RGB transfer in the networks,
runtime and benchmark reference are not wired yet (see the issue).
"""

from __future__ import annotations

import numpy as np

from .transfer import _unit, cosine_directions, orthonormal_frames

__all__ = ["BounceRays", "trace_bounce_rays", "interreflect", "bounce_matrices", "BOUNCE_RAYS", "NORMAL_WEIGHT"]

# Rays per sample of the bounce stage (the direct transfer keeps its own count).
BOUNCE_RAYS = 64
# Weight of the normal against the position in the nearest-sample search: the other side of
# a sheet is 2 * NORMAL_WEIGHT away, far beyond the sample spacing (~0.03 at 20k samples).
NORMAL_WEIGHT = 0.25


class BounceRays:
    """Which sample each ray of each sample lands nearest to, found once for all bounces.

    Attributes
    ----------
    nearest : (S, M) int64
        Sample index nearest to the ray's hit point on a surface facing the ray, -1 for a miss.
    hit_face : (S, M) int64
        Triangle hit (-1: miss).
    """

    def __init__(self, nearest: np.ndarray, hit_face: np.ndarray):
        self.nearest = nearest
        self.hit_face = hit_face


def trace_bounce_rays(mesh, points, normals, sample_faces=None, *, rays: int = BOUNCE_RAYS, seed: int = 0, chunk: int = 4096,
                      workers: int = -1, targets=None) -> BounceRays:
    """Trace ``rays`` cosine-distributed rays per sample and find, at every hit, the nearest sample.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The scene (scene units).
    points, normals : (S, 3) float
        The precomputed samples.
    sample_faces : (S,) int, optional
        Unused (kept for callers that have it); the normal term of the search finds the side.
    rays : int
    seed : int
        Ray frames are spun by angles drawn from (seed, chunk index): deterministic.
    targets : (points, normals), optional
        The samples searched at the hit points; default: ``points, normals`` themselves (the
        bounce stage).  Other query points (the benchmark's pixels) pass the precomputed samples.
    """
    from scipy.spatial import cKDTree

    from .transfer import EmbreeTracer

    tracer = EmbreeTracer(mesh)
    points = np.asarray(points, dtype=np.float64)
    normals = _unit(np.asarray(normals, dtype=np.float64))
    local = cosine_directions(rays).astype(np.float32)
    if targets is None:
        targets = (points, normals)
    target_points = np.asarray(targets[0], dtype=np.float64)
    target_normals = _unit(np.asarray(targets[1], dtype=np.float64))
    tree = cKDTree(np.concatenate([target_points, NORMAL_WEIGHT * target_normals], axis=1))
    nearest = np.full((len(points), rays), -1, dtype=np.int64)
    hit_face = np.full((len(points), rays), -1, dtype=np.int64)
    for c, start in enumerate(range(0, len(points), chunk)):
        rows = slice(start, start + chunk)
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0xB0B, c]))
        frames = orthonormal_frames(normals[rows], rng.uniform(0.0, 2.0 * np.pi, len(points[rows]))).astype(np.float32)
        dirs = np.matmul(local[None], frames.transpose(0, 2, 1)).reshape(-1, 3)
        origins = np.repeat((points[rows] + tracer.offset * normals[rows]).astype(np.float32), rays, axis=0)
        result = tracer._scene.run(origins, dirs, output=1)
        faces = result["primID"].astype(np.int64)
        hit = faces >= 0
        w = dirs[hit].astype(np.float64)
        q = origins[hit] + result["tfar"][hit, None] * dirs[hit]
        ng = _unit(result["Ng"][hit].astype(np.float64))
        ng *= -np.sign(np.einsum("qc,qc->q", ng, w))[:, None]  # the side facing the ray's origin
        _, chosen = tree.query(np.concatenate([q, NORMAL_WEIGHT * ng], axis=1), k=1, workers=workers)
        flat_nearest = np.full(len(origins), -1, dtype=np.int64)
        flat_nearest[hit] = chosen
        nearest[rows] = flat_nearest.reshape(-1, rays)
        hit_face[rows] = faces.reshape(-1, rays)
    del sample_faces
    return BounceRays(nearest, hit_face)


def interreflect(direct, bounce_rays: BounceRays, face_albedo, bounces: int, transfer_at=None, chunk: int = 1024) -> np.ndarray:
    """Interreflected transfer ``T_0 + ... + T_N`` (see the module docstring).

    Parameters
    ----------
    direct : (S, n) float
        Direct transfer of the samples.
    bounce_rays : BounceRays
    face_albedo : (F, 3) float
        Albedo of every triangle (fixed at build time).
    bounces : int
        N >= 0; 0 returns the direct transfer (as RGB).
    transfer_at : callable, optional
        ``transfer_at(sample_indices, previous)`` -> transfer of the previous bounce at the hit
        points; default: ``previous[sample_indices]`` (the nearest sample's).

    Returns
    -------
    (S, n, 3) float64
    """
    direct = np.asarray(direct, dtype=np.float64)
    albedo = np.asarray(face_albedo, dtype=np.float64)
    total = np.repeat(direct[:, :, None], 3, axis=2)
    previous = total.copy()
    hit = bounce_rays.nearest >= 0
    rays = bounce_rays.nearest.shape[1]
    if transfer_at is not None:  # a general estimator: gather its values chunk by chunk
        index = np.where(hit, bounce_rays.nearest, 0)
        for _ in range(int(bounces)):
            current = np.empty_like(previous)
            for start in range(0, len(direct), chunk):  # (chunk, M, n, 3) at a time
                rows = slice(start, start + chunk)
                weight = np.where(hit[rows, :, None], albedo[np.where(hit[rows], bounce_rays.hit_face[rows], 0)], 0.0)
                current[rows] = np.einsum("smc,smnc->snc", weight, transfer_at(index[rows], previous)) / rays
            total += current
            previous = current
        return total
    matrices = bounce_matrices(bounce_rays, albedo)
    for _ in range(int(bounces)):
        previous = np.stack([matrices[c] @ previous[:, :, c] for c in range(3)], axis=2)
        total += previous
    return total


def bounce_matrices(bounce_rays: BounceRays, face_albedo) -> list:
    """``W_c`` (S, S) sparse, per channel: ``W_c[p, q]`` = sum over p's rays landing nearest to q of
    ``a_c(hit face) / M``."""
    from scipy.sparse import csr_matrix

    nearest = bounce_rays.nearest
    count, rays = nearest.shape
    rows, cols = np.nonzero(nearest >= 0)
    targets = nearest[rows, cols]
    albedo = np.asarray(face_albedo, dtype=np.float64)[bounce_rays.hit_face[rows, cols]] / rays
    return [csr_matrix((albedo[:, c], (rows, targets)), shape=(count, count)) for c in range(3)]
