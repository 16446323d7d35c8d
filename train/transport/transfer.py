"""Ray-traced ground-truth transfer.

For a surface point ``p`` with normal ``n`` the shadowed diffuse transfer is

    T_i = (1/pi) * integral V(p, w) max(0, n.w) Y_i(w) dw

with ``V`` the visibility of the whole scene.  We importance-sample the cosine: directions
come from a cosine-weighted Hammersley set in the point's local frame (z = normal), which turns
the estimator into ``T_i = mean_j V_j Y_i(w_j)``.  Because the pdf cancels the cosine and the
``1/pi``, an unoccluded point gets exactly ``T_0 = Y_00`` (white furnace: ``dot(T, L) = 1``).

The integral is done in the local frame, with one shared direction set (so its SH values are
computed once), then rotated into the world frame per sample with SH rotation matrices.  Each
sample's frame is spun about its normal by a random angle so the shared set does not print a
pattern over the surface.

Visibility: Embree (embreex) for meshes, batched sphere tracing for SDF scenes, both for mixed
scenes (a ray is blocked if either blocks it).  Work is split
into deterministic chunks spread over a thread pool (Embree and numpy release the GIL) or the
tasks of a Ray cluster (:mod:`prt.train.executor`) and, when a cache folder is given, each
finished chunk is written atomically so an interrupted run resumes where it stopped with
bit-identical results.
"""

from __future__ import annotations

import hashlib
import os
from contextlib import closing
from pathlib import Path

import numpy as np

from ...runtime import sh
from ..cache import ChunkStore
from ..executor import LocalExecutor

__all__ = [
    "cosine_directions",
    "orthonormal_frames",
    "EmbreeTracer",
    "SDFTracer",
    "MixedTracer",
    "make_tracer",
    "sdf_trace_for",
    "SDF_TRACES",
    "SDF_TRACE_CHOICES",
    "TransferIntegrator",
    "compute_transfer",
    "TransferJob",
    "transfer_chunk",
    "DEFAULT_CHUNK",
]

DEFAULT_CHUNK = 2048
# Ray origins move this far along the normal (scene units; the scene spans [-1, 1]^3): far
# above float32 round-off at |x| ~ 1 (1e-7) yet below any real wall thickness we expect.
MESH_RAY_OFFSET = 1e-4
# Sphere tracing stops within ~1e-4 of a surface, so it needs a clearly larger start offset.
SDF_RAY_OFFSET = 2e-3
# How SDF scenes are traced (SDFTracer): the band tracer, or the plain sphere tracer (its twin).
SDF_TRACES = ("band", "sphere")
SDF_TRACE_CHOICES = ("auto",) + SDF_TRACES


def _radical_inverse_base2(i: np.ndarray) -> np.ndarray:
    i = i.astype(np.uint64)
    bits = np.zeros_like(i)
    for shift in range(32):
        bits |= ((i >> np.uint64(shift)) & np.uint64(1)) << np.uint64(31 - shift)
    return bits.astype(np.float64) / 2.0**32


def cosine_directions(rays: int) -> np.ndarray:
    """Cosine-weighted low-discrepancy directions about +z.

    A Hammersley point set ``((j + 0.5) / M, radical_inverse(j))`` mapped with Malley's
    method (uniform disc, lifted to the hemisphere), so each direction has pdf ``cos / pi``.

    Returns
    -------
    (rays, 3) float64 unit vectors with z > 0
    """
    if rays < 1:
        raise ValueError(f"ray count must be positive, got {rays}")
    j = np.arange(rays)
    u1 = (j + 0.5) / rays
    u2 = _radical_inverse_base2(j)
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)], axis=1)


def orthonormal_frames(normals: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
    """Rotation matrices whose third column is the normal.

    Branchless construction of Duff et al. (2017), then a spin by ``angles`` about the normal.

    Parameters
    ----------
    normals : (N, 3) unit vectors
    angles : (N,) radians, or None for no spin

    Returns
    -------
    (N, 3, 3) float64, columns (tangent, bitangent, normal): local -> world
    """
    n = np.asarray(normals, dtype=np.float64)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=1)
    bt = np.stack([b, sign + y * y * a, -y], axis=1)
    if angles is not None:
        c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
        t, bt = c * t + s * bt, -s * t + c * bt
    return np.stack([t, bt, n], axis=2)


class EmbreeTracer:
    """Occlusion queries against a triangle mesh with Embree (both faces of a triangle block)."""

    offset = MESH_RAY_OFFSET
    origin_rule = ""  # part of cache keys where it is not empty: how origins leave the surface

    def __init__(self, mesh):
        triangles = np.ascontiguousarray(
            np.asarray(mesh.vertices, dtype=np.float32)[np.asarray(mesh.faces)]
        )
        self._build(triangles, "embree:" + hashlib.sha1(triangles.tobytes()).hexdigest())

    def _build(self, triangles: np.ndarray, identity: str) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self._triangles = triangles  # (F, 3, 3) float32: what a pickle carries
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self._scene, triangles)
        self.identity = identity

    def __reduce__(self):
        # An Embree scene cannot be pickled: send the triangles, rebuild once per process.
        return _embree_tracer, (self._triangles, self.identity)

    def origins(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Ray origins (S, 3) float32 of surface points with unit normals: ``offset`` along the normal."""
        return np.asarray(points, dtype=np.float32) + self.offset * np.asarray(normals, dtype=np.float32)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, t_max=None) -> np.ndarray:
        """origins, dirs : (K, 3) float32 -> (K,) bool, True where the ray hits anything (within ``t_max`` (K,) when given)."""
        if t_max is None:
            return self._scene.run(origins, dirs, query="OCCLUDED") != -1
        return self._scene.run(origins, dirs, query="OCCLUDED", dists=np.ascontiguousarray(t_max, dtype=np.float32)) != -1


# Tracers unpickled in this process (a cluster worker), by geometry identity: a worker builds
# a scene's Embree BVH once, not once per task.  A few entries: one build sees one geometry.
_TRACERS: dict[str, EmbreeTracer] = {}
_TRACERS_KEPT = 4


def _embree_tracer(triangles: np.ndarray, identity: str) -> EmbreeTracer:
    tracer = _TRACERS.get(identity)
    if tracer is None:
        tracer = EmbreeTracer.__new__(EmbreeTracer)
        tracer._build(np.ascontiguousarray(triangles), identity)
        while len(_TRACERS) >= _TRACERS_KEPT:
            _TRACERS.pop(next(iter(_TRACERS)))
        _TRACERS[identity] = tracer
    return tracer


class SDFTracer:
    """Occlusion queries against an SDF scene: its band tracer, or its plain sphere tracer.

    ``trace="band"``: :class:`prt.train.sdf.band_trace.BandTracer` (Embree on the band's shells,
    the field evaluated only between them); ``"sphere"``: :meth:`prt.train.sdf.SDF.sphere_trace`,
    the plain tracer and the band tracer's reference twin.  Both keep the origin rule
    (:meth:`origins`) and the hit rule; the tracing rule is part of :attr:`identity` (and of
    :attr:`trace_rule`, which precompute and bench cache keys add where it is not empty).
    """

    offset = SDF_RAY_OFFSET
    origin_rule = "lift-v1"  # :meth:`prt.train.sdf.SDF.start_points`

    def __init__(self, sdf, trace: str = "sphere", threads: int | None = None):
        if trace not in SDF_TRACES:
            raise ValueError(f"trace must be one of {', '.join(SDF_TRACES)}, got {trace!r}")
        self._sdf = sdf
        self.trace = trace
        self._band = None
        self.trace_rule = ""
        if trace == "band":
            from ..sdf.band_trace import TRACE_RULE, BandTracer

            self._band = BandTracer(sdf, threads=threads)
            self.trace_rule = TRACE_RULE
        # the origin rule is part of the identity: builds cached before it trace again
        rule = f"{self.origin_rule}:{self.trace_rule}:" if self.trace_rule else f"{self.origin_rule}:"
        self.identity = f"sdf:{rule}" + hashlib.sha1(sdf.glsl().encode()).hexdigest()

    def origins(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Ray origins (S, 3) float32: ``offset`` along the normal, further where the field is still
        below the hit threshold there (:meth:`prt.train.sdf.SDF.start_points`)."""
        return self._sdf.start_points(points, normals, self.offset)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """origins, dirs : (K, 3) float32 -> (K,) bool, True where the ray hits the scene."""
        if self._band is not None:
            return self._band.occluded(origins, dirs)
        return self._sdf.sphere_trace(origins, dirs)  # t_max: across the whole scene


class MixedTracer:
    """Occlusion against every object: Embree for the mesh objects OR the SDF tracer for the SDFs
    (``sdf_trace``: :class:`SDFTracer`'s ``trace``, for the union of the SDF objects)."""

    def __init__(self, geometry, sdf_trace: str = "sphere", threads: int | None = None):
        parts = geometry.mixed
        keep = ~parts.proxy_faces
        self.offset = SDF_RAY_OFFSET  # the sphere tracer's start offset; ample for Embree too
        self.origin_rule = ""
        self.mesh = None
        if keep.any():
            import trimesh

            faces = np.asarray(geometry.mesh.faces)[keep]
            self.mesh = EmbreeTracer(trimesh.Trimesh(np.asarray(geometry.mesh.vertices), faces, process=False))
        union = parts.union()
        self.sdf = SDFTracer(union, sdf_trace, threads) if union is not None else None
        self.trace_rule = ""
        if self.sdf is not None:
            self.origin_rule = self.sdf.origin_rule
            self.trace_rule = self.sdf.trace_rule
        ids = [t.identity for t in (self.mesh, self.sdf) if t is not None]
        self.identity = "mixed:" + hashlib.sha1("|".join(ids).encode()).hexdigest()

    def origins(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Ray origins (S, 3) float32: the SDF objects' rule (:meth:`SDFTracer.origins`) when the scene has any."""
        if self.sdf is None:
            return np.asarray(points, dtype=np.float32) + self.offset * np.asarray(normals, dtype=np.float32)
        return self.sdf.origins(points, normals)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """origins, dirs : (K, 3) float32 -> (K,) bool, True where a mesh or an SDF object blocks the ray."""
        hit = np.zeros(len(origins), dtype=bool)
        if self.mesh is not None:
            hit |= self.mesh.occluded(origins, dirs)
        if self.sdf is not None:
            todo = np.flatnonzero(~hit)  # rays a mesh blocked need no sphere tracing
            if todo.size:
                hit[todo] = self.sdf.occluded(origins[todo], dirs[todo])
        return hit


def sdf_trace_for(geometry, sdf_trace: str = "auto") -> str | None:
    """How a geometry's SDFs are traced: ``"band"`` or ``"sphere"`` (None: no SDF in it).

    ``"auto"`` (the default): the band tracer wherever the scene holds a neural SDF, whose
    network makes every sphere-tracing step costly; analytic SDFs keep the plain sphere tracer
    (measured: their cheap exact distances leave it the faster; ``docs/guides/sdf-and-mixed.md``).
    """
    if sdf_trace not in SDF_TRACE_CHOICES:
        raise ValueError(f"sdf_trace must be one of {', '.join(SDF_TRACE_CHOICES)}, got {sdf_trace!r}")
    kind = getattr(geometry, "kind", None)
    if kind == "mixed":
        fields = list(geometry.mixed.sdfs.values())
    elif geometry.sdf is not None:
        fields = [geometry.sdf]
    else:
        return None
    if sdf_trace != "auto":
        return sdf_trace
    return "band" if any(_has_network(f.root) for f in fields) else "sphere"


def _has_network(node) -> bool:
    """Whether an SDF node tree holds a network (:class:`prt.train.sdf.neural.NeuralNode`)."""
    from ..sdf import Node
    from ..sdf.neural import NeuralNode

    if isinstance(node, NeuralNode):
        return True
    for value in vars(node).values():  # children, child, base, cutter...
        for child in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(child, Node) and _has_network(child):
                return True
    return False


def make_tracer(geometry, sdf_trace: str = "auto", threads: int | None = None):
    """The visibility tracer for a geometry: Embree for meshes, the SDF tracer for SDFs
    (``sdf_trace``: :func:`sdf_trace_for`), both for mixed scenes (:class:`MixedTracer`)."""
    trace = sdf_trace_for(geometry, sdf_trace)
    if getattr(geometry, "kind", None) == "mixed":
        return MixedTracer(geometry, trace, threads)
    if geometry.sdf is not None:
        return SDFTracer(geometry.sdf, trace, threads)
    return EmbreeTracer(geometry.mesh)


class TransferIntegrator:
    """Transfer of one chunk of samples at a time, deterministic in (seed, chunk index)."""

    def __init__(self, tracer, rays: int = 512, bands: int = 4, seed: int = 0):
        self.tracer = tracer
        self.rays = int(rays)
        self.bands = int(bands)
        self.seed = int(seed)
        self.local_dirs = cosine_directions(self.rays)  # (M, 3)
        self._local_dirs32 = self.local_dirs.astype(np.float32)
        # Cosine pdf cancels cos/pi: T_local = V @ Y(d) / M.
        self._basis_over_m = sh.basis(self.local_dirs, self.bands) / self.rays  # (M, n)

    def chunk_rays(self, points: np.ndarray, normals: np.ndarray, chunk_index: int):
        """The rays of one chunk: origins and directions (S*M, 3) float32, frames (S, 3, 3)."""
        count = len(points)
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x7E4, int(chunk_index)]))
        frames = orthonormal_frames(_unit(normals), rng.uniform(0.0, 2.0 * np.pi, count))
        frames32 = frames.astype(np.float32)
        # world direction of local ray j at sample s: frames[s] @ d[j]  -> (S, M, 3)
        dirs = np.matmul(self._local_dirs32[None], frames32.transpose(0, 2, 1))
        origins = self.tracer.origins(points, frames32[:, :, 2])
        return np.repeat(origins, self.rays, axis=0), dirs.reshape(-1, 3), frames

    def integrate(self, hit: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Transfer from the hit flags (S*M,) of a chunk's rays -> (S, bands**2) float32."""
        visible = (~hit).reshape(len(frames), self.rays).astype(np.float64)
        local = visible @ self._basis_over_m  # (S, n)
        rot = sh.rotation_matrices(frames, self.bands)  # (S, n, n)
        return np.einsum("sij,sj->si", rot, local).astype(np.float32)

    def chunk(self, points: np.ndarray, normals: np.ndarray, chunk_index: int) -> np.ndarray:
        """Transfer at ``points`` (S, 3) with ``normals`` (S, 3) -> (S, bands**2) float32."""
        origins, dirs, frames = self.chunk_rays(points, normals, chunk_index)
        return self.integrate(self.tracer.occluded(origins, dirs), frames)


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return np.where(length > 1e-12, v / np.where(length > 1e-12, length, 1.0), (0.0, 1.0, 0.0))


def _fingerprint(*parts) -> str:
    h = hashlib.sha1()
    for part in parts:
        h.update(part.tobytes() if isinstance(part, np.ndarray) else repr(part).encode())
        h.update(b"|")
    return h.hexdigest()[:16]


def compute_transfer(
    geometry,
    points: np.ndarray,
    normals: np.ndarray,
    rays: int = 512,
    bands: int = 4,
    *,
    seed: int = 0,
    chunk_size: int = DEFAULT_CHUNK,
    threads: int | None = None,
    cache_dir: str | os.PathLike | None = None,
    progress=False,
    tracer=None,
    executor=None,
    progress_stage: str = "precompute",
) -> np.ndarray:
    """Ground-truth transfer at arbitrary surface points.

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry, the whole scene that casts shadows
    points : (N, 3) scene-unit positions on the surface
    normals : (N, 3) normals of the side being lit (normalised here)
    rays : directions per point (cosine-weighted, low discrepancy)
    bands : SH bands; the result has ``bands**2`` coefficients
    seed : spin of the per-sample frames; the result is a pure function of the arguments
    chunk_size : samples per work unit (part of the cache key)
    threads : worker threads (default: all cores)
    cache_dir : folder for finished chunks; a rerun with the same arguments resumes there
    progress : show a progress bar (rays per second, ETA); a :class:`prt.train.progress.BuildProgress`:
        count the rays into the build's one display, as ``progress_stage``
    tracer : an existing tracer for ``geometry`` (saves rebuilding the Embree scene)
    executor : where chunks run (:mod:`prt.train.executor`; default: ``threads`` threads here)

    Returns
    -------
    (N, bands**2) float32
    """
    points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
    normals = np.ascontiguousarray(normals, dtype=np.float32).reshape(-1, 3)
    if len(points) != len(normals):
        raise ValueError(f"points ({len(points)}) and normals ({len(normals)}) differ in length")
    if not (np.isfinite(points).all() and np.isfinite(normals).all()):
        raise ValueError("points or normals contain NaN or Inf")
    tracer = tracer if tracer is not None else make_tracer(geometry)
    n_chunks = (len(points) + chunk_size - 1) // chunk_size
    store = None
    if cache_dir is not None:
        key = _fingerprint(points, normals, rays, bands, seed, chunk_size, tracer.identity, "v1")
        store = ChunkStore(Path(cache_dir) / f"transfer-{key}", n_chunks)
    result = np.empty((len(points), bands * bands), dtype=np.float32)
    todo = []
    for k in range(n_chunks):
        shape = (_chunk_len(k, chunk_size, len(points)), bands * bands)
        cached = store.load(k, shape) if store is not None and store.has(k) else None  # damaged: recomputed
        if cached is not None:
            result[k * chunk_size : (k + 1) * chunk_size] = cached
        else:
            todo.append(k)

    from ..progress import RAY, progress_bar

    bar = progress_bar(progress, progress_stage, "transfer", len(points) * rays, unit="ray", unit_cost=RAY,
                       initial=(len(points) - sum(_chunk_len(k, chunk_size, len(points)) for k in todo)) * rays,
                       unit_scale=True, mininterval=0.5, smoothing=0.1)  # fmt: skip
    job = TransferJob(tracer, rays, bands, seed)
    chunks = [(k, points[k * chunk_size : (k + 1) * chunk_size], normals[k * chunk_size : (k + 1) * chunk_size]) for k in todo]
    executor = executor if executor is not None else LocalExecutor(threads)
    try:
        with closing(executor.map(transfer_chunk, job, chunks, task_threads=1)) as finished:
            for done, ((k, _, _), value) in enumerate(finished, start=n_chunks - len(todo) + 1):
                if store is not None:  # the driver alone writes the cache
                    store.save(k, value)
                result[k * chunk_size : (k + 1) * chunk_size] = value
                if bar is not None:
                    bar.set_postfix_str(f"chunk {done}/{n_chunks}", refresh=False)
                    bar.update(len(value) * rays)
    finally:
        if bar is not None:
            bar.close()
    return result


class TransferJob:
    """What every chunk of one :func:`compute_transfer` call shares (picklable: sent once to a cluster)."""

    def __init__(self, tracer, rays: int, bands: int, seed: int):
        self.tracer, self.rays, self.bands, self.seed = tracer, int(rays), int(bands), int(seed)
        self._integrator = None

    def integrator(self) -> TransferIntegrator:
        if self._integrator is None:
            self._integrator = TransferIntegrator(self.tracer, rays=self.rays, bands=self.bands, seed=self.seed)
        return self._integrator

    def __getstate__(self):
        return {**self.__dict__, "_integrator": None}  # rebuilt where it lands (about 1 ms)


def transfer_chunk(job: TransferJob, chunk) -> np.ndarray:
    """One chunk ``(k, points (S, 3), normals (S, 3))`` -> transfer (S, bands**2) float32: a task."""
    k, points, normals = chunk
    return job.integrator().chunk(points, normals, k)


def _chunk_len(k: int, chunk_size: int, total: int) -> int:
    return min(chunk_size, total - k * chunk_size)
