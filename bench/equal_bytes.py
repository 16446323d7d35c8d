"""Per-vertex PRT at a build's bytes: the mesh decimated until its vertex transfer fits them (``prt-bench --equal-bytes``).

The paper's argument for networks is storage: per-vertex PRT (Sloan et al. 2002) stores 16
floats per vertex (64 with interreflection), so on a dense mesh it needs far more bytes than a
few networks, and at the networks' bytes it must make do with far fewer vertices.  This baseline
measures that directly:

1. **Decimate** the scene's mesh (quadric error metrics, ``fast_simplification``) to the vertex
   count whose transfer takes the build's weight bytes: ``bytes / (4 x width)`` vertices (open
   meshes: their back-side vertices counted in, :func:`vertex_budget`).
2. **Per-vertex PRT of the decimated mesh**, as ``prt-bench``'s vertex baseline computes it for any
   mesh (:mod:`prt.bench.vertex_prt`): direct transfer ray traced at its vertices against its own
   triangles, then the same N bounces with the build's estimator on its vertex samples.
3. **Resampled onto the full mesh's vertices** (:func:`resample`): every full-resolution vertex takes
   the barycentric interpolation of the decimated triangle nearest to it, so the full mesh is
   rasterised with the coarse transfer: the same pixels, silhouettes and G-buffer as every other
   configuration, and the transfer holds no more information than the decimated vertices carry.

Rows: backend ``vertex`` with ``"equal_bytes"`` in the record (the decimated vertex count, its bytes
and the build's); label ``vertex equal-bytes ...``.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from prt.bench.vertex_prt import vertex_bounce_transfer, vertex_transfer
from prt.runtime.files import atomic_save_npz
from prt.train.inputs.adaptive import closest_on_triangles
from prt.train.transport.transfer import EmbreeTracer

__all__ = ["vertex_budget", "decimate", "resample", "equal_bytes_vertex", "CANDIDATES"]

# Decimated triangles searched per full-resolution vertex (nearest by centroid).
CANDIDATES = 12


def vertex_budget(target_bytes: int, width: int, vertices: int, back_vertices: int) -> int:
    """Vertices whose per-vertex transfer (``width`` float32 each, back sides counted in the full
    mesh's proportion) takes at most ``target_bytes``."""
    per_vertex = 4 * int(width) * (1.0 + back_vertices / max(vertices, 1))
    return max(4, int(target_bytes // per_vertex))


def decimate(vertices: np.ndarray, faces: np.ndarray, target_vertices: int, tries: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The mesh decimated to at most ``target_vertices`` vertices (quadric error metrics).

    ``fast_simplification`` is asked for a share of the faces; the vertex count it reaches is
    checked, and the share lowered in proportion until it fits (at most ``tries`` times)."""
    import fast_simplification

    vertices, faces = np.asarray(vertices, np.float32), np.asarray(faces, np.int64)
    if target_vertices >= len(vertices):
        return vertices.astype(np.float64), faces
    keep = target_vertices / len(vertices)
    for _ in range(tries):
        v, f = fast_simplification.simplify(vertices, faces, target_reduction=float(min(max(1.0 - keep, 0.0), 0.999)))
        used = np.unique(f)
        if len(used) <= target_vertices:
            break
        keep *= 0.97 * target_vertices / len(used)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(v, np.float64)[used], remap[f]


def resample(coarse_vertices, coarse_faces, coarse_two_sided, front, back, points, normals) -> np.ndarray:
    """Transfer at ``points`` (P, 3) with ``normals`` (P, 3) read from the coarse mesh: the barycentric
    interpolation of the nearest coarse triangle's vertex rows, its back rows where the triangle is
    two-sided and faces away from the normal.  Returns (P, width) float32."""
    from scipy.spatial import cKDTree

    coarse_vertices = np.asarray(coarse_vertices, np.float64)
    corners = coarse_vertices[coarse_faces]  # (F, 3, 3)
    points = np.asarray(points, np.float64)
    k = int(min(CANDIDATES, len(coarse_faces)))
    _, near = cKDTree(corners.mean(axis=1)).query(points, k=k)
    near = np.asarray(near).reshape(len(points), k)
    tri = corners[near]  # (P, k, 3, 3)
    closest, weights = closest_on_triangles(points[:, None, :], tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    best = np.argmin(((closest - points[:, None, :]) ** 2).sum(axis=2), axis=1)
    rows = np.arange(len(points))
    face, weights = near[rows, best], weights[rows, best]
    c = corners[face]
    face_normal = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    behind = np.asarray(coarse_two_sided, bool)[face] & (np.einsum("pc,pc->p", face_normal, np.asarray(normals, np.float64)) < 0.0)
    out = np.zeros((len(points), front.shape[1]), dtype=np.float64)
    for j in range(3):
        idx = coarse_faces[face, j]
        out += weights[:, j : j + 1] * np.where(behind[:, None], back[idx], front[idx])
    return out.astype(np.float32)


def equal_bytes_vertex(geometry, target_bytes: int, *, width: int, bounces: int, face_albedo, rays: int, seed: int, cache: Path,
                       geometry_id: str, log=print) -> tuple[np.ndarray, np.ndarray, dict]:  # fmt: skip
    """Per-vertex PRT of ``geometry``'s mesh decimated to ``target_bytes``, resampled onto its vertices (module docstring).

    Parameters
    ----------
    geometry : a mesh scene (``mesh``, ``two_sided``)
    target_bytes : the build's weight bytes
    width : 16 (direct) or 64 ("direct+rgb", with ``bounces`` > 0)
    face_albedo : (F, 3) of the full mesh's faces (the decimated faces take their nearest full face's)
    rays : rays per vertex of the direct transfer and of the bounces (``--baseline-rays``)

    Returns
    -------
    front, back : (V, width) float32 on the full mesh's vertices (for :class:`prt.bench.vertex_prt.VertexPRT`)
    info : dict
        ``vertices``, ``faces`` (decimated), ``weight_bytes`` (its transfer's), ``target_bytes``, ``seconds``.
    """
    from prt.bench.vertex_prt import vertex_samples
    from prt.runtime.normals import vertex_normals
    from scipy.spatial import cKDTree
    import trimesh

    t0 = time.perf_counter()
    full_vertices = np.asarray(geometry.mesh.vertices, np.float64)
    full_faces = np.asarray(geometry.mesh.faces, np.int64)
    two_sided = np.asarray(geometry.two_sided, bool)
    _, _, _, back_rows = vertex_samples(geometry)
    budget = vertex_budget(target_bytes, width, len(full_vertices), int((back_rows >= 0).sum()))
    digest = hashlib.sha1(f"{geometry_id}|{budget}|{rays}|{seed}|{bounces}|{width}".encode())
    digest.update(np.ascontiguousarray(face_albedo, np.float64).tobytes())
    path = Path(cache) / f"equal-bytes-{budget}-{digest.hexdigest()[:12]}.npz"
    if path.is_file():
        with np.load(path) as data:
            info = {k: int(data[k]) for k in ("vertices", "faces", "weight_bytes")}
            return data["front"], data["back"], {**info, "target_bytes": int(target_bytes), "seconds": 0.0}
    v, f = decimate(full_vertices, full_faces, budget)
    # Each decimated face keeps its nearest full face's sidedness and albedo.
    _, nearest = cKDTree(full_vertices[full_faces].mean(axis=1)).query(v[f].mean(axis=1))
    coarse = SimpleNamespace(mesh=trimesh.Trimesh(v, f, process=False), two_sided=two_sided[nearest], kind="mesh")
    tracer = EmbreeTracer(coarse.mesh)
    coarse_id = f"{geometry_id}|decimated-{len(v)}"
    front, back, _ = vertex_transfer(coarse, tracer, rays, Path(cache), coarse_id)
    if bounces > 0:
        front, back, _ = vertex_bounce_transfer(coarse, front, back, np.asarray(face_albedo, np.float64)[nearest], bounces, rays=rays, seed=seed,
                                                cache=Path(cache), geometry_id=coarse_id)  # fmt: skip
    _, _, _, coarse_back = vertex_samples(coarse)
    weight_bytes = 4 * front.shape[1] * (len(v) + int((coarse_back >= 0).sum()))
    normals = vertex_normals(full_vertices.astype(np.float32), full_faces).astype(np.float64)
    full_front = resample(v, f, coarse.two_sided, front, back, full_vertices, normals)
    full_back = resample(v, f, coarse.two_sided, front, back, full_vertices, -normals)
    atomic_save_npz(path, front=full_front, back=full_back, vertices=len(v), faces=len(f), weight_bytes=weight_bytes)
    seconds = time.perf_counter() - t0
    log(f"  vertex baseline at equal bytes: {len(full_vertices):,} -> {len(v):,} vertices, {weight_bytes:,} bytes "
        f"(the build's {int(target_bytes):,}; {seconds:.1f} s)")  # fmt: skip
    return full_front, full_back, {"vertices": int(len(v)), "faces": int(len(f)), "weight_bytes": int(weight_bytes),
                                   "target_bytes": int(target_bytes), "seconds": round(seconds, 3)}  # fmt: skip
