"""Adaptive sampling: more training samples where transfer varies fastest (issue 12, item 2c).

Transfer is smooth almost everywhere and sharp at contact shadows, creases and concavities.  A
first pass of area-uniform samples (:func:`prt.train.inputs.sampling.sample_surface`) and their
ray-traced transfer tells where: :func:`transfer_variation` scores each sample by how far its
transfer is from that of its nearest neighbours on the surface.  :func:`adaptive_samples` then
draws a second set of points near samples chosen in proportion to that score (mixed with a
uniform share, so no region is left empty), each moved by a random tangent offset of the order
of the first pass's sample spacing and put back on the surface: the closest point on the mesh
(with the normal the G-buffer interpolates there) or the SDF's zero set.

The held-out validation set stays area-uniform, so a network's validation error still measures
the whole surface, not the regions the second pass favoured.

Plain twin: :func:`transfer_variation_reference` (a double loop over samples and their
neighbours found by brute force), tested against the k-d tree version.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ...runtime.normals import corner_normals, interpolated_normals
from .sampling import SurfaceSamples

__all__ = ["ADAPTIVE_STREAM", "NEIGHBOURS", "UNIFORM_SHARE", "transfer_variation", "transfer_variation_reference",
           "adaptive_samples"]  # fmt: skip

# Random stream of the second pass (the first pass and validation use 0 and 1).
ADAPTIVE_STREAM = 3
# Neighbours a sample is compared with.
NEIGHBOURS = 8
# Share of the second pass drawn around uniformly chosen samples (defensive mixture).
UNIFORM_SHARE = 0.25
# Normals weigh like this many scene units in the neighbour search: samples on the two sides of a
# thin sheet, or across a crease, are not neighbours.
NORMAL_WEIGHT = 0.05


def _keys(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(points, np.float64), NORMAL_WEIGHT * np.asarray(normals, np.float64)], axis=1)


def transfer_variation(points: np.ndarray, normals: np.ndarray, transfer: np.ndarray, *,
                       neighbours: int = NEIGHBOURS) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """How fast transfer varies around each sample.

    Parameters
    ----------
    points, normals : (N, 3)
    transfer : (N, n) SH transfer of the samples (direct, or any layout: all columns count)

    Returns
    -------
    score : (N,) float64
        Mean L1 distance between the sample's transfer and that of its ``neighbours`` nearest
        samples (position and normal, :data:`NORMAL_WEIGHT`), divided by the mean L1 norm of all
        transfer (so the score is scale-free).
    spacing : (N,) float64
        Mean distance (scene units) to those neighbours: the local sample spacing.
    """
    transfer = np.asarray(transfer, np.float64).reshape(len(transfer), -1)
    k = int(min(neighbours, len(points) - 1))
    if k < 1:
        return np.zeros(len(points)), np.zeros(len(points))
    distance, index = cKDTree(_keys(points, normals)).query(_keys(points, normals), k=k + 1)
    distance, index = distance[:, 1:], index[:, 1:]  # drop the sample itself
    scale = max(float(np.abs(transfer).sum(axis=1).mean()), 1e-12)
    score = np.zeros(len(points))
    for j in range(k):  # a loop over neighbours keeps memory at (N, n)
        score += np.abs(transfer - transfer[index[:, j]]).sum(axis=1)
    spacing = np.linalg.norm(np.asarray(points, np.float64)[index] - np.asarray(points, np.float64)[:, None], axis=2).mean(axis=1)
    return score / (k * scale), spacing


def transfer_variation_reference(points, normals, transfer, *, neighbours: int = NEIGHBOURS):
    """Plain twin of :func:`transfer_variation`: brute-force neighbours, one sample at a time."""
    keys = _keys(points, normals)
    transfer = np.asarray(transfer, np.float64).reshape(len(transfer), -1)
    points = np.asarray(points, np.float64)
    k = int(min(neighbours, len(points) - 1))
    scale = max(float(np.mean([np.sum(np.abs(t)) for t in transfer])), 1e-12)
    score, spacing = np.zeros(len(points)), np.zeros(len(points))
    for i in range(len(points)):
        d = np.sqrt(((keys - keys[i]) ** 2).sum(axis=1))
        d[i] = np.inf
        near = np.argsort(d, kind="stable")[:k]
        score[i] = sum(np.sum(np.abs(transfer[i] - transfer[j])) for j in near) / (k * scale)
        spacing[i] = np.mean([np.linalg.norm(points[j] - points[i]) for j in near])
    return score, spacing


def _tangent_offsets(normals: np.ndarray, radius: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Uniform points in the disc of ``radius`` in each normal's tangent plane."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(normals, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    r = radius * np.sqrt(rng.random(len(normals)))
    angle = 2.0 * np.pi * rng.random(len(normals))
    return (r * np.cos(angle))[:, None] * u + (r * np.sin(angle))[:, None] * v


def adaptive_samples(geometry, first: SurfaceSamples, transfer: np.ndarray, count: int, *, seed: int = 0,
                     uniform_share: float = UNIFORM_SHARE, neighbours: int = NEIGHBOURS) -> tuple[SurfaceSamples, dict]:  # fmt: skip
    """Draw ``count`` samples concentrated where the first pass's transfer varies fastest.

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry (mesh, SDF or mixed scene: a point goes back onto its seed
        sample's own object)
    first : the first pass's samples; ``transfer`` their (N, n) transfer
    count : samples to draw
    seed : with :data:`ADAPTIVE_STREAM`, the random stream (deterministic)
    uniform_share : share of the draws around uniformly chosen first-pass samples

    Returns
    -------
    samples : SurfaceSamples (``face_index``: the mesh triangle nearest to the point)
    stats : dict -- ``score_quantiles`` (50, 90, 99 %), ``favoured``: how many times more draws the
        top decile of scores got than a uniform draw would give it
    """
    count = int(count)
    if count <= 0:
        raise ValueError(f"adaptive sample count must be positive, got {count}")
    points = np.asarray(first.points, np.float64)
    normals = np.asarray(first.normals, np.float64)
    score, spacing = transfer_variation(points, normals, transfer, neighbours=neighbours)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), ADAPTIVE_STREAM]))
    n_uniform = int(round(count * float(uniform_share)))
    weights = score / score.sum() if score.sum() > 0 else np.full(len(score), 1.0 / len(score))
    chosen = np.concatenate([rng.integers(0, len(points), n_uniform), rng.choice(len(points), count - n_uniform, p=weights)])
    radius = spacing[chosen]
    moved = points[chosen] + _tangent_offsets(normals[chosen], radius, rng)
    if geometry.sdf is not None:
        new_points = geometry.sdf.project_to_surface(moved)
        new_normals = geometry.sdf.normals(new_points)
        faces = first.face_index[chosen]
        objects = first.object_ids[chosen]
    elif getattr(geometry, "kind", "mesh") == "mixed":  # each point back onto its seed sample's own object
        new_points, new_normals = moved.copy(), normals[chosen].copy()
        faces, objects = first.face_index[chosen].copy(), first.object_ids[chosen].copy()
        on_sdf = geometry.mixed.proxy_faces[faces]
        for k, sdf in geometry.mixed.sdfs.items():
            mine = np.flatnonzero(on_sdf & (objects == k))
            if mine.size:
                new_points[mine] = sdf.project_to_surface(moved[mine])
                new_normals[mine] = sdf.normals(new_points[mine])
        mesh = np.flatnonzero(~on_sdf)
        if mesh.size:
            on_mesh = _on_mesh(geometry, moved[mesh], normals[chosen][mesh], faces[mesh], ~geometry.mixed.proxy_faces)
            new_points[mesh], new_normals[mesh], faces[mesh] = on_mesh
            objects[mesh] = np.asarray(geometry.object_ids, np.int64)[faces[mesh]]
    else:
        new_points, new_normals, faces = _on_mesh(geometry, moved, normals[chosen], first.face_index[chosen])
        objects = np.asarray(geometry.object_ids, np.int64)[faces]
    length = np.linalg.norm(new_normals, axis=1, keepdims=True)
    bad = ~(length[:, 0] > 1e-12) | ~np.isfinite(new_points).all(axis=1)
    # A point that could not be put back on the surface keeps its seed sample's place.
    new_points = np.where(bad[:, None], points[chosen], new_points)
    new_normals = np.where(bad[:, None], normals[chosen], new_normals / np.where(length > 1e-12, length, 1.0))
    top = score >= np.quantile(score, 0.9)
    stats = {
        "score_quantiles": [float(q) for q in np.quantile(score, [0.5, 0.9, 0.99])],
        "favoured": float(np.mean(top[chosen]) / max(np.mean(top), 1e-12)),
        "unplaced": int(bad.sum()),
    }
    samples = SurfaceSamples(new_points.astype(np.float32), new_normals.astype(np.float32), faces.astype(np.int64), objects.astype(np.int64))
    return samples, stats


def closest_on_triangles(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point to each point on its triangle (a, b, c): (..., 3) arrays -> the point and its
    barycentric weights (Ericson, "Real-Time Collision Detection", 5.1.5, by Voronoi regions)."""
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = np.einsum("...i,...i", ab, ap), np.einsum("...i,...i", ac, ap)
    bp, cp = points - b, points - c
    d3, d4 = np.einsum("...i,...i", ab, bp), np.einsum("...i,...i", ac, bp)
    d5, d6 = np.einsum("...i,...i", ab, cp), np.einsum("...i,...i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = 1e-30
    # Face interior by default, then the edges and vertices override where their region holds.
    denom = np.where(np.abs(va + vb + vc) > tiny, va + vb + vc, tiny)
    v, w = vb / denom, vc / denom
    u = 1.0 - v - w
    weights = np.stack([u, v, w], axis=-1)

    def region(mask, wa, wb, wc):
        weights[mask] = np.stack([wa, wb, wc], axis=-1)[mask]

    t = d1 / np.where(np.abs(d1 - d3) > tiny, d1 - d3, tiny)
    region((vc <= 0) & (d1 >= 0) & (d3 <= 0), 1 - t, t, 0 * t)  # edge ab
    t = d2 / np.where(np.abs(d2 - d6) > tiny, d2 - d6, tiny)
    region((vb <= 0) & (d2 >= 0) & (d6 <= 0), 1 - t, 0 * t, t)  # edge ac
    t = (d4 - d3) / np.where(np.abs((d4 - d3) + (d5 - d6)) > tiny, (d4 - d3) + (d5 - d6), tiny)
    region((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 0 * t, 1 - t, t)  # edge bc
    one, zero = np.ones_like(d1), np.zeros_like(d1)
    region((d1 <= 0) & (d2 <= 0), one, zero, zero)  # vertex a
    region((d3 >= 0) & (d4 <= d3), zero, one, zero)  # vertex b
    region((d6 >= 0) & (d5 <= d6), zero, zero, one)  # vertex c
    closest = weights[..., :1] * a + weights[..., 1:2] * b + weights[..., 2:] * c
    return closest, weights


# Candidate triangles searched per point (nearest by centroid, plus the seed sample's own triangle).
CANDIDATES = 16


def _on_mesh(geometry, points: np.ndarray, seed_normals: np.ndarray, seed_faces: np.ndarray, allowed: np.ndarray | None = None):
    """Closest points on the mesh among nearby triangles (of ``allowed`` ones, default all), the
    G-buffer's interpolated normal there, turned to the side of the seed sample on two-sided faces."""
    mesh = geometry.mesh
    vertices, triangles = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    corners = vertices[triangles]  # (F, 3, 3)
    pool = np.arange(len(triangles)) if allowed is None else np.flatnonzero(allowed)
    k = int(min(CANDIDATES, len(pool)))
    _, near = cKDTree(corners[pool].mean(axis=1)).query(points, k=k)
    near = pool[near]
    candidates = np.concatenate([np.asarray(seed_faces).reshape(-1, 1), np.asarray(near).reshape(len(points), -1)], axis=1)
    tri = corners[candidates]  # (P, K + 1, 3, 3)
    closest, weights = closest_on_triangles(points[:, None, :], tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    best = np.argmin(((closest - points[:, None, :]) ** 2).sum(axis=2), axis=1)
    rows = np.arange(len(points))
    faces = candidates[rows, best].astype(np.int64)
    closest, weights = closest[rows, best], weights[rows, best]
    face_normal, corner = corner_normals(vertices, triangles)
    normals = interpolated_normals(corner, face_normal, faces, weights)
    two_sided = np.asarray(geometry.two_sided, bool)[faces]
    flip = two_sided & (np.einsum("ij,ij->i", normals, seed_normals) < 0.0)
    normals[flip] *= -1.0
    return closest, normals, faces
