"""Interreflected transfer (Sloan, Kautz and Snyder 2002, section 6): the bounce operator.

Direct transfer ``T_0(p)`` (16 SH coefficients, including the ``1/pi``: see docs/design.md)
gives the irradiance-weighted light a point receives straight from the environment.  Light that
reaches ``p`` after bouncing off another surface point ``q`` is, for a diffuse ``q`` with albedo
``a(q)``, ``a(q) dot(T_{b-1}(q), L)``; with the cosine-importance-sampled rays of
:mod:`prt.train.transport.transfer` (pdf ``cos / pi``, which cancels the cosine and the ``1/pi``)

    T_b(p) = mean_j  hit_j * a(q_j) * T_{b-1}(q_j)          (RGB: a is a colour)

and the interreflected transfer is ``T_0 + T_1 + ... + T_N``.  Every term is linear in the
lighting ``L``, so relighting stays a dot product per channel; with coloured albedos the result
is RGB transfer, shape (S, n, 3).

Estimator of ``T_{b-1}(q)`` at a hit point: the ray-traced transfer of the precomputed sample
nearest to ``q`` in (position, NORMAL_WEIGHT * normal), the hit's normal turned towards the ray's
origin: so the sample is on the side of the surface the ray sees (open surfaces have samples
on both sides at the same places); of the :data:`PLANE_CANDIDATES` nearest, the one nearest the
hit's tangent plane wins ties between parallel sheets facing the same way (:func:`nearest_on_plane`:
the Cornell box's light quad below the ceiling, issue #13), and of those only one whose segment
from the hit crosses no surface (:func:`nearest_visible`: a wall between a room's floor and the
ground outside; :data:`CLEAR_LIFT`).  The search is bounded (:data:`SEARCH_RADIUS`); a hit with
no sample of its side that near takes the best of the samples nearest in position, and a hit
with no clear candidate carries no light.  In the bounce stage's first bounce, such a hit and one
whose clear sample lies far from it read the direct transfer traced at the hit itself instead
(:data:`TRACE_FAR`, :meth:`BounceJob.traced_chunk`).
A ray leaving its sample below the plane of the sample's own face enters the surface: the
sample's normal is the interpolated (smooth) one, so its cosine hemisphere reaches a sliver under
the flat face, and from an origin lifted along that normal such a ray hits the face itself from
above (or slips past its edge).  It carries no light (:func:`entering`): a path entering a
closed surface ends at its inside, as a path tracer spawning the ray from the face finds (Mitsuba
3, issue 38).  Without the rule the self-hits gathered the sample's own light again: 0.07-0.5 % of
the rays on the shared meshes, the reference's indirect light 3-4 % (0.1 % of the total) too
bright on Spot.  Samples with a face (the build's, which know theirs) take the rule; points
without one find theirs with :func:`surface_faces`.
Chosen over the fitted direct networks because it needs nothing beyond the precompute (the
bounce stage runs before fitting, stays chunked and deterministic, and its error does not depend
on how well a network fitted), and because each bounce then costs a sparse product: the rays,
hit points and nearest samples are found once (:func:`trace_bounce_rays`) and every bounce is
``T_b[:, :, c] = W_c @ T_{b-1}[:, :, c]`` with ``W_c[p, q] = sum of a_c(hit) / M`` over p's
rays landing nearest to q.  Indirect light is smooth, so it takes fewer rays than the direct
term (:data:`BOUNCE_RAYS`).

The training samples' indirect part is then averaged over their nearest samples on the same side
(:func:`prt.train.transport.smoothing.smooth_indirect`): the networks would otherwise fit part of the gather's noise.

``prt-train --bounces N`` runs :func:`bounce_stage` after the direct precompute and fits
networks of the "direct+rgb" layout (:mod:`prt.train.networks.network`) to ``[T_0, T_ind_R, T_ind_G,
T_ind_B]``; the albedos of the bouncing surfaces are the diffuse albedos (``Kd``) of the mesh's
own per-object materials, fixed at build time and recorded in the manifest's ``interreflection``.
Bounces are diffuse: a glossy surface bounces its diffuse albedo only.  ``--bounces auto``
(:mod:`prt.train.transport.bounce_depth`) measures the terms on the validation samples first and keeps the
smallest N whose truncation error is small; the rays are traced once for both.
"""

from __future__ import annotations

import numpy as np

from .transfer import _unit, cosine_directions, orthonormal_frames

__all__ = ["BounceRays", "BounceJob", "trace_bounce_rays", "bounce_chunk", "trace_stage", "bounce_terms", "bounce_stage", "interreflect", "bounce_matrices",
           "nearest_on_plane", "nearest_visible", "nearest_visible_reference", "clear_between", "first_clear", "face_normals", "surface_faces", "entering",
           "sample_spacing", "traced_term", "collect_rays", "BOUNCE_RAYS", "CLEAR_LIFT", "CLEAR_RULE", "NORMAL_WEIGHT", "RAY_RULE", "TRACE_FAR", "TRACED_RAYS",
           "TRACE_RULE"]

# Rays per sample of the bounce stage (the direct transfer keeps its own count).  32: on the
# Cornell box (105k samples, 512 direct rays) 64 bounce rays made the stage 3.5x the direct
# transfer's time (the nearest-sample searches dominate), over the 3x budget for the
# whole precompute; the training targets' indirect part is averaged over neighbours (smooth_indirect).
BOUNCE_RAYS = 32
# Weight of the normal against the position in the nearest-sample search: the other side of
# a sheet is 2 * NORMAL_WEIGHT away, far beyond the sample spacing (~0.03 at 20k samples).
NORMAL_WEIGHT = 0.25
# The search looks this far (in the weighted 6-d distance) and no farther: a hit with no sample of
# its side that near (e.g. the underside of a box standing on the floor, a few % of the hits in the
# Cornell box) makes an unbounded k-d search visit much of the tree (2-3x the time of all other
# hits together); those take the best of the FALLBACK_CANDIDATES samples nearest in position.
SEARCH_RADIUS = 0.15
FALLBACK_CANDIDATES = 8
# Parallel sheets facing the same way a few sample spacings apart (the Cornell box's light quad,
# 0.01 below the ceiling) are not told apart by the normal term: a hit on the light's underside
# took the ceiling sample above it (inside the light/ceiling gap, whose estimate is wrong) about
# as often as a light sample, and a hit on the light's top the ceiling's roof side (sky light).
# So the search takes the PLANE_CANDIDATES nearest samples and keeps the one minimising the 6-d
# distance squared plus (PLANE_WEIGHT * its distance from the hit's tangent plane) squared.
PLANE_CANDIDATES = 8
PLANE_WEIGHT = 4.0
# Names the rules for rays that enter the surface (:func:`entering`) and for the segment test
# (:func:`clear_between`) in the chunk stores of rays traced with them: rays traced before the
# first gathered self-hits, before the second light from the far side of walls.
CLEAR_RULE = "clear1"
RAY_RULE = "enter1-" + CLEAR_RULE
# How far above a point :func:`surface_faces` starts its probe (scene units; float32 positions of
# a surface point lie ~1e-7 off it, the ray origins 1e-4).
SURFACE_REACH = 1e-3
# A hit takes the best-ranked candidate sample whose segment from it is clear (:func:`clear_between`),
# both ends lifted off their surfaces by this share of their distance: two points of one floor are
# joined above it, two of a curved surface clear it while the chord is shorter than twice the
# curvature radius (the sagitta stays below the lift), and a wall between them blocks whatever its
# thickness.  A hit none of whose candidates is clear carries no light: it is a side no sample
# stands for (mostly a gap the sampling leaves out, :mod:`prt.train.inputs.visibility`: nearly dark).
# Measured on the Duplex house (``studies/bounce_lookup.py``: the first bounce of each rule against
# the direct transfer traced at the hits themselves, 64 rays per sample; the build's samples):
# - one sample per pixel of the four inside views (``docs/benchmarks/bounce_lookup_duplex_inside.md``):
#   without the test 4.5 % of the hits read a sample beyond a wall (outdoors, the next room) and the
#   rooms' first bounce was 3.8 % too bright, a tenth of the samples 23 % or more; with it -0.1 %
#   (90th percentile 1.09), the 3.1 % of hits without a clear sample carrying 1 % of the traced light;
# - 2,000 samples at random over the house (``bounce_lookup_duplex.md``): in its voids (dark
#   samples) 2.8x -> 1.13x, dim +3 % -> +1.6 %, but open surfaces 15 % low -> 12 % low: there the
#   13 % of the hits without a clear sample carry 10 % of the traced light (small lit parts whose
#   nearest samples lie down a step).  Tracing the direct transfer at such hits would leave them 6 %
#   high (the study's "clear + traced"): the clear hits' nearest samples, when far from the hit, are
#   brighter than it.  Tracing also the hits whose clear sample is farther than twice the median such
#   distance ("clear + traced far": 29 % of the hits over the house, 19 % at the inside views' pixels)
#   puts every group within 2.6 % (open +1.6 %, per-sample 90th percentile 1.08; inside +0.1 %): the
#   next step for the bounce stage, taken: :data:`TRACE_FAR`.
CLEAR_LIFT = 0.25
# The bounce stage's first bounce reads the direct transfer traced at the hit itself (TRACED_RAYS
# cosine rays, :class:`prt.train.transport.transfer.TransferIntegrator`) where the hit has no clear
# candidate, or where its clear sample lies farther from it than TRACE_FAR times the training samples'
# median spacing (:func:`sample_spacing`: the distance to the nearest other sample on its side).
# Higher bounces still read the clear sample's previous bounce (nothing where there is none).  2.5
# spacings is twice the median distance from a hit to its clear sample on the Duplex house (spacing
# 0.0043, that median 0.0054): the threshold of the study's "clear + traced far" row (0.0108 there),
# which put the first bounce within 2.6 % of the traced one in every group (see CLEAR_LIFT).
TRACE_FAR = 2.5
TRACED_RAYS = 32
TRACE_RULE = f"far{TRACE_FAR:g}t{TRACED_RAYS}"  # names the bounce stage's chunk stores and is in the fits' cache key


def face_normals(tracer) -> np.ndarray:
    """(F, 3) float64 unit normals of the tracer's triangles (their winding; zero for degenerate ones), kept on the tracer."""
    cached = getattr(tracer, "_face_normals", None)
    if cached is None:
        tri = np.asarray(tracer._triangles, dtype=np.float64)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(cross, axis=1, keepdims=True)
        cached = np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)
        tracer._face_normals = cached
    return cached


def surface_faces(tracer, points, normals, reach: float = SURFACE_REACH) -> np.ndarray:
    """(P,) the face each surface point lies on (-1 where none within ``reach``): a ray from ``reach``
    above it (along its normal) back down to it, for points that do not know their face (pixels, texels)."""
    points = np.asarray(points, dtype=np.float64)
    normals = _unit(np.asarray(normals, dtype=np.float64))
    origins = (points + reach * normals).astype(np.float32)
    result = tracer._scene.run(origins, (-normals).astype(np.float32), output=1)
    faces = result["primID"].astype(np.int64)
    return np.where((faces >= 0) & (result["tfar"] <= 2.0 * reach), faces, -1)


def entering(dirs, normals, faces, table) -> np.ndarray:
    """(S, M) bool: the rays ``dirs`` (S, M, 3) of samples with ``normals`` (S, 3) on ``faces`` (S,) that
    leave below the plane of their own face (``table``: :func:`face_normals`), turned to the sample's side."""
    faces = np.asarray(faces, dtype=np.int64)
    own = np.asarray(table, dtype=np.float64)[np.maximum(faces, 0)]
    own *= np.where(np.einsum("sc,sc->s", own, normals) < 0.0, -1.0, 1.0)[:, None]  # two-sided: the sample's side
    return (np.einsum("smc,sc->sm", dirs, own) <= 0.0) & (faces >= 0)[:, None]


class BounceRays:
    """Which sample each ray of each sample lands nearest to, found once for all bounces.

    Attributes
    ----------
    nearest : (S, M) int64
        Sample index nearest to the ray's hit point on a surface facing the ray, -1 for a miss.
    hit_face : (S, M) int64
        Triangle hit (-1: miss).
    traced : (S, M) int64 or None
        Row of ``traced_transfer`` the ray's first bounce reads (-1: its nearest sample's), where the
        rays were traced with :data:`TRACE_FAR` (the bounce stage's); None: every hit reads its sample.
    traced_transfer : (H, n) float32 or None
        The direct transfer traced at those hits.
    """

    def __init__(self, nearest: np.ndarray, hit_face: np.ndarray, traced: np.ndarray | None = None, traced_transfer: np.ndarray | None = None):
        self.nearest = nearest
        self.hit_face = hit_face
        self.traced = traced
        self.traced_transfer = traced_transfer


def trace_bounce_rays(mesh, points, normals, sample_faces=None, *, rays: int = BOUNCE_RAYS, seed: int = 0, chunk: int = 4096,
                      workers: int = -1, targets=None, candidates: int | None = None, plane_weight: float | None = None,
                      clear: bool = True, trace_far: float | None = None, bands: int = 4) -> BounceRays:  # fmt: skip
    """Trace ``rays`` cosine-distributed rays per sample and find, at every hit, the nearest sample.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The scene (scene units).
    points, normals : (S, 3) float
        The precomputed samples.
    sample_faces : (S,) int, optional
        The samples' faces: rays entering the surface carry nothing (:func:`entering`); None:
        the rule is not applied (points without a face: :func:`surface_faces` finds them).
    rays : int
    seed : int
        Ray frames are spun by angles drawn from (seed, chunk index): deterministic.
    targets : (points, normals), optional
        The samples searched at the hit points; default: ``points, normals`` themselves (the
        bounce stage).  Other query points (the benchmark's pixels) pass the precomputed samples.
    candidates, plane_weight : optional
        Of :func:`nearest_on_plane` (defaults :data:`PLANE_CANDIDATES`, :data:`PLANE_WEIGHT`).
    clear : bool
        Keep to candidates whose segment from the hit is clear (:func:`nearest_visible`, the default);
        False: the best-ranked candidate whatever lies between (the vertex estimator: see
        :mod:`prt.train.transport.vertex_estimate`).
    trace_far, bands : optional
        As :class:`BounceJob`'s: the bounce stage's rays (:func:`trace_stage` passes :data:`TRACE_FAR`
        times the samples' spacing); None: every hit reads its sample.
    """
    from .transfer import EmbreeTracer

    points = np.asarray(points, dtype=np.float64)
    normals = _unit(np.asarray(normals, dtype=np.float64))
    if targets is None:
        targets = (points, normals)
    job = BounceJob(EmbreeTracer(mesh), targets[0], targets[1], rays=rays, seed=seed, workers=workers, candidates=candidates,
                    plane_weight=plane_weight, clear=clear, trace_far=trace_far, bands=bands)  # fmt: skip
    out = np.full((len(points), 2 if trace_far is None else 3, rays), -1, dtype=np.int32)
    traced = {}
    for c, start in enumerate(range(0, len(points), chunk)):
        value = bounce_chunk(job, (c, points[start : start + chunk], normals[start : start + chunk])
                             + (() if sample_faces is None else (sample_faces[start : start + chunk],)))  # fmt: skip
        if isinstance(value, tuple):
            value, traced[c] = value
        out[start : start + chunk] = value
    if trace_far is None:
        return BounceRays(out[:, 0].astype(np.int64), out[:, 1].astype(np.int64))
    return collect_rays(out, traced, chunk, bands)


class BounceJob:
    """What the chunks of one set of bounce rays share (picklable: the tracer sends its triangles,
    the k-d tree of the target samples travels as it is)."""

    def __init__(self, tracer, target_points, target_normals, *, rays: int = BOUNCE_RAYS, seed: int = 0, stream: int = 0,
                 workers: int = -1, candidates: int | None = None, plane_weight: float | None = None, clear: bool = True,
                 trace_far: float | None = None, bands: int = 4):  # fmt: skip
        """``trace_far``: hits with no clear sample, or whose clear sample lies farther than this (scene
        units), read the direct transfer traced at themselves (``bands`` SH bands; :meth:`traced_chunk`,
        :data:`TRACE_FAR`); None: every hit reads its sample's."""
        from scipy.spatial import cKDTree

        target_points = np.asarray(target_points, dtype=np.float64)
        target_normals = _unit(np.asarray(target_normals, dtype=np.float64))
        self.tracer, self.rays, self.seed, self.stream, self.workers = tracer, int(rays), int(seed), int(stream), workers
        self.tree = cKDTree(np.concatenate([target_points, NORMAL_WEIGHT * target_normals], axis=1))
        self.positions = cKDTree(target_points)
        self.local = cosine_directions(self.rays).astype(np.float32)
        self.candidates, self.plane_weight, self.clear = candidates, plane_weight, bool(clear)
        self.trace_far, self.bands = (None if trace_far is None else float(trace_far)), int(bands)
        self.face_normal = face_normals(tracer)

    def chunk(self, points, normals, c: int, faces=None) -> tuple[np.ndarray, np.ndarray]:
        """(nearest, hit_face), each (S, rays) int64, of the rays of chunk ``c`` (deterministic in seed, stream, c).

        With the samples' ``faces`` (S,), rays entering the surface count as misses (:func:`entering`)."""
        faces, q, ng = self.hits(points, normals, c, faces)
        hit = faces >= 0
        flat_nearest = np.full(faces.size, -1, dtype=np.int64)
        flat_nearest[hit.reshape(-1)] = self.choose(q, ng)
        return flat_nearest.reshape(faces.shape), faces

    def traced_chunk(self, points, normals, c: int, faces=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(nearest, hit_face, traced) (S, rays) int64 and the traced transfer (H, n) float32 of chunk ``c``
        (:class:`BounceRays`' attributes, ``traced`` counting rows from 0 in this chunk)."""
        from .transfer import TransferIntegrator

        faces, q, ng = self.hits(points, normals, c, faces)
        hit = faces.reshape(-1) >= 0
        chosen = self.choose(q, ng)
        gap = np.full(len(q), np.inf)
        found = chosen >= 0
        gap[found] = np.linalg.norm(self.tree.data[chosen[found], :3] - q[found], axis=1)
        pick = np.flatnonzero(gap > (np.inf if self.trace_far is None else self.trace_far))
        integrator = TransferIntegrator(self.tracer, rays=TRACED_RAYS, bands=self.bands, seed=self.seed)
        # Its own seed stream apart from the precompute's ((stream + 1) << 32 | c); the hit lies on its
        # face (float32 ray arithmetic), the integrator lifts it by the tracer's offset.
        transfer = integrator.chunk(q[pick], ng[pick], ((self.stream + 1) << 32) | int(c)) if len(pick) else np.zeros((0, self.bands**2), np.float32)
        flat = np.full(faces.size, -1, dtype=np.int64)
        flat[hit] = chosen
        rows = np.full(len(q), -1, dtype=np.int64)
        rows[pick] = np.arange(len(pick))
        traced = np.full(faces.size, -1, dtype=np.int64)
        traced[hit] = rows
        return flat.reshape(faces.shape), faces, traced.reshape(faces.shape), transfer

    def hits(self, points, normals, c: int, faces=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rays of chunk ``c``: hit faces (S, rays) int64 (-1: miss or entering), and of the hits
        (row-major) their points and normals turned towards the ray's origin, (H, 3) float64 each."""
        points = np.asarray(points, dtype=np.float64)
        normals = _unit(np.asarray(normals, dtype=np.float64))
        rays, tracer = self.rays, self.tracer
        # Stream 0 keeps the seeding trace_bounce_rays always had; other streams (validation) add theirs.
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0xB0B, int(c)] + ([self.stream] if self.stream else [])))
        frames = orthonormal_frames(normals, rng.uniform(0.0, 2.0 * np.pi, len(points))).astype(np.float32)
        dirs = np.matmul(self.local[None], frames.transpose(0, 2, 1)).reshape(-1, 3)
        origins = np.repeat((points + tracer.offset * normals).astype(np.float32), rays, axis=0)
        result = tracer._scene.run(origins, dirs, output=1)
        hit_faces = result["primID"].astype(np.int64)
        if faces is not None:
            hit_faces[entering(dirs.reshape(len(points), rays, 3), normals, faces, self.face_normal).reshape(-1)] = -1
        faces = hit_faces
        hit = faces >= 0
        w = dirs[hit].astype(np.float64)
        q = origins[hit] + result["tfar"][hit, None] * dirs[hit]
        ng = _unit(result["Ng"][hit].astype(np.float64))
        ng *= -np.sign(np.einsum("qc,qc->q", ng, w))[:, None]  # the side facing the ray's origin
        return faces.reshape(-1, rays), q.astype(np.float64), ng

    def choose(self, q, ng) -> np.ndarray:
        """(H,) int64: the target sample each hit (point ``q``, normal ``ng`` facing the ray) reads; -1: none."""
        key = np.concatenate([np.asarray(q, np.float64), NORMAL_WEIGHT * np.asarray(ng, np.float64)], axis=1)
        index, score = _ranked(self.tree, key, candidates=self.candidates, plane_weight=self.plane_weight, workers=self.workers)
        far = np.flatnonzero(~np.isfinite(score[:, 0]))
        if len(far):  # the same 6-d distance, over the samples nearest in position
            k = min(FALLBACK_CANDIDATES, self.tree.n)
            _, near = self.positions.query(q[far], k=k, workers=self.workers)
            near = near.reshape(len(far), k)
            d2 = ((self.tree.data[near] - key[far, None, :]) ** 2).sum(axis=2)
            order = np.argsort(d2, axis=1, kind="stable")
            fallback = np.full((len(far), index.shape[1]), np.inf)
            fallback[:, :k] = np.take_along_axis(d2, order, axis=1)[:, : index.shape[1]]
            index[far, :k] = np.take_along_axis(near, order, axis=1)[:, : index.shape[1]]
            score[far] = fallback
        if self.clear:
            return first_clear(self.tracer, self.tree.data, key, index, score)
        return np.where(np.isfinite(score[:, 0]), index[:, 0], -1).astype(np.int64)


def _ranked(tree, key, *, candidates: int | None = None, plane_weight: float | None = None, bound: float = SEARCH_RADIUS,
            workers: int = -1) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(index, score), each (Q, k): every hit's ``candidates`` nearest samples within ``bound``, best
    first by :func:`nearest_on_plane`'s score (inf, index 0: no such candidate)."""
    key = np.asarray(key, dtype=np.float64)
    k = min(int(PLANE_CANDIDATES if candidates is None else candidates), tree.n)
    distance, index = tree.query(key, k=k, distance_upper_bound=bound, workers=workers)
    distance, index = distance.reshape(len(key), k), index.reshape(len(key), k)
    found = np.isfinite(distance)
    safe = np.where(found, index, 0)
    normal = key[:, 3:] / NORMAL_WEIGHT
    off = np.einsum("qkc,qc->qk", tree.data[safe, :3] - key[:, None, :3], normal)
    weight = PLANE_WEIGHT if plane_weight is None else float(plane_weight)
    score = np.where(found, distance**2 + (weight * off) ** 2, np.inf)
    order = np.argsort(score, axis=1, kind="stable")
    return np.take_along_axis(safe, order, axis=1).astype(np.int64), np.take_along_axis(score, order, axis=1)


def nearest_on_plane(tree, key, *, candidates: int | None = None, plane_weight: float | None = None, bound: float = SEARCH_RADIUS, workers: int = -1) -> np.ndarray:
    """Index of the sample for each hit ``key`` (Q, 6) = (position, NORMAL_WEIGHT * normal) in ``tree``
    (built on the same key): of the ``candidates`` (default :data:`PLANE_CANDIDATES`) nearest within ``bound``, the one minimising the
    6-d distance squared plus ``(plane_weight * (sample - hit) . normal)**2`` (default
    :data:`PLANE_WEIGHT`); -1 where none is
    within ``bound``.  See :data:`PLANE_WEIGHT`; :func:`nearest_on_plane_reference` is its plain twin."""
    index, score = _ranked(tree, key, candidates=candidates, plane_weight=plane_weight, bound=bound, workers=workers)
    return np.where(np.isfinite(score[:, 0]), index[:, 0], -1).astype(np.int64)


def _plain_ranked(data, row, candidates, plane_weight, bound) -> list:
    """The candidates of one hit ``row`` (6,) among ``data`` (T, 6), best first (brute force)."""
    d = np.sqrt(((data - row) ** 2).sum(axis=1))
    k = min(int(PLANE_CANDIDATES if candidates is None else candidates), len(data))
    order = [i for i in np.argsort(d, kind="stable")[:k] if d[i] <= bound]
    normal = row[3:] / NORMAL_WEIGHT
    weight = PLANE_WEIGHT if plane_weight is None else float(plane_weight)
    scores = [d[i] ** 2 + (weight * float((data[i, :3] - row[:3]) @ normal)) ** 2 for i in order]
    return [order[j] for j in np.argsort(scores, kind="stable")]


def nearest_on_plane_reference(data, key, *, candidates: int | None = None, plane_weight: float | None = None, bound: float = SEARCH_RADIUS) -> np.ndarray:
    """Plain twin of :func:`nearest_on_plane` (brute force over ``data`` (T, 6), one hit at a time)."""
    data = np.asarray(data, dtype=np.float64)
    out = []
    for row in np.asarray(key, dtype=np.float64):
        ranked = _plain_ranked(data, row, candidates, plane_weight, bound)
        out.append(ranked[0] if ranked else -1)
    return np.asarray(out, dtype=np.int64)


def clear_between(tracer, points, normals, others, other_normals) -> np.ndarray:
    """(Q,) bool: no surface crosses the segment from each surface point to its ``other``, both ends
    lifted off their surfaces along their normals by :data:`CLEAR_LIFT` of their distance (at least
    the tracer's ray offset): the other point stands for light on this side of any wall between them."""
    points, others = np.asarray(points, dtype=np.float64), np.asarray(others, dtype=np.float64)
    lift = np.maximum(tracer.offset, CLEAR_LIFT * np.linalg.norm(others - points, axis=1))[:, None]
    start = points + lift * _unit(np.asarray(normals, dtype=np.float64))
    step = others + lift * _unit(np.asarray(other_normals, dtype=np.float64)) - start
    length = np.linalg.norm(step, axis=1)
    apart = length > 1e-9
    clear = np.ones(len(points), dtype=bool)
    if apart.any():
        clear[apart] = ~tracer.occluded(start[apart].astype(np.float32), (step[apart] / length[apart, None]).astype(np.float32), t_max=length[apart])
    return clear


def first_clear(tracer, data, key, index, score) -> np.ndarray:
    """(Q,) int64: for each hit ``key`` (Q, 6), the first of its ranked candidates (``index``, ``score``
    (Q, k): :func:`_ranked`) in ``data`` (T, 6) whose segment from the hit is clear
    (:func:`clear_between`); -1 where none is (the hit carries no light: see :data:`CLEAR_LIFT`)."""
    key, data = np.asarray(key, dtype=np.float64), np.asarray(data, dtype=np.float64)
    chosen = np.full(len(key), -1, dtype=np.int64)
    todo = np.arange(len(key))
    for j in range(index.shape[1]):
        todo = todo[np.isfinite(score[todo, j])]
        if not len(todo):
            break
        candidate = index[todo, j]
        ok = clear_between(tracer, key[todo, :3], key[todo, 3:], data[candidate, :3], data[candidate, 3:])
        chosen[todo[ok]] = candidate[ok]
        todo = todo[~ok]
    return chosen


def nearest_visible(tree, key, tracer, *, candidates: int | None = None, plane_weight: float | None = None, bound: float = SEARCH_RADIUS,
                    workers: int = -1) -> np.ndarray:  # fmt: skip
    """:func:`nearest_on_plane`'s ranking, keeping the best candidate whose segment from the hit is clear
    (:func:`first_clear`); -1 where none is.  :func:`nearest_visible_reference` is its plain twin."""
    index, score = _ranked(tree, key, candidates=candidates, plane_weight=plane_weight, bound=bound, workers=workers)
    return first_clear(tracer, tree.data, key, index, score)


def nearest_visible_reference(data, key, tracer, *, candidates: int | None = None, plane_weight: float | None = None,
                              bound: float = SEARCH_RADIUS) -> np.ndarray:  # fmt: skip
    """Plain twin of :func:`nearest_visible`: one hit and one candidate at a time."""
    data = np.asarray(data, dtype=np.float64)
    out = []
    for row in np.asarray(key, dtype=np.float64):
        pick = -1
        for i in _plain_ranked(data, row, candidates, plane_weight, bound):
            if clear_between(tracer, row[None, :3], row[None, 3:], data[None, i, :3], data[None, i, 3:])[0]:
                pick = i
                break
        out.append(pick)
    return np.asarray(out, dtype=np.int64)


def bounce_chunk(job: BounceJob, item):
    """One chunk ``(c, points, normals[, faces])`` of bounce rays -> (S, 2, rays) int32 [nearest, hit_face]: a task.

    A job with ``trace_far``: ((S, 3, rays) int32 [nearest, hit_face, traced], (H, n) float32 traced transfer)."""
    c, points, normals, *faces = item
    if job.trace_far is not None:
        *index, transfer = job.traced_chunk(points, normals, c, faces[0] if faces else None)
        return np.stack(index, axis=1).astype(np.int32), transfer
    nearest, faces = job.chunk(points, normals, c, faces[0] if faces else None)
    return np.stack([nearest, faces], axis=1).astype(np.int32)  # sample and face counts are far below 2^31


def sample_spacing(points, normals) -> float:
    """Median distance (position) from each sample to the nearest other sample on its side, in
    (position, :data:`NORMAL_WEIGHT` * normal); inf for fewer than two samples."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    if len(points) < 2:
        return float("inf")
    key = np.concatenate([points, NORMAL_WEIGHT * _unit(np.asarray(normals, dtype=np.float64))], axis=1)
    _, near = cKDTree(key).query(key, k=2, workers=-1)
    return float(np.median(np.linalg.norm(points[near[:, 1]] - points, axis=1)))


class _IndexStore:
    """A :class:`prt.train.cache.ChunkStore` of int32 chunks (its ``load`` takes float chunks only); with
    ``traced``, each chunk's traced transfer beside it (``traced/``: :func:`bounce_chunk`'s pairs)."""

    def __init__(self, folder, n_chunks: int, traced: bool = False):
        from pathlib import Path

        from ..cache import ChunkStore

        self.store = ChunkStore(folder, n_chunks)
        self.transfer = ChunkStore(Path(folder) / "traced", n_chunks) if traced else None
        self.traced: dict[int, np.ndarray] = {}  # chunk -> traced transfer, of the chunks load_into found

    def has(self, k: int) -> bool:
        return self.store.has(k) and (self.transfer is None or self.transfer.has(k))

    def save(self, k: int, value) -> None:
        if self.transfer is not None:  # the transfer first: a chunk counts as done once its indices are there
            self.transfer.save(k, value[1])
            value = value[0]
        self.store.save(k, value)

    def load(self, k: int, shape: tuple) -> np.ndarray | None:
        """Chunk ``k``; None (trace it again) if damaged, foreign or not int32 of ``shape``."""
        try:
            value = np.load(self.store.path(k), allow_pickle=False)
        except (OSError, ValueError, EOFError):
            return None
        return value if value.shape == tuple(shape) and value.dtype == np.int32 else None

    def load_into(self, out: np.ndarray, chunk_size: int) -> list[int]:
        """Copy every sound cached chunk into its rows of ``out`` (count, ...); the chunks still to trace."""
        todo = []
        for k in range(self.store.n_chunks):
            rows = slice(k * chunk_size, (k + 1) * chunk_size)
            cached = self.load(k, out[rows].shape) if self.has(k) else None  # damaged: traced again
            if cached is not None and self.transfer is not None:
                count = int((cached[:, 2] >= 0).sum())
                transfer = self.transfer.load(k)
                if transfer is None or transfer.ndim != 2 or len(transfer) != count or transfer.dtype != np.float32:
                    cached = None
                else:
                    self.traced[k] = transfer
            if cached is None:
                todo.append(k)
            else:
                out[rows] = cached
        return todo


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
        if bounce_rays.traced is not None:
            raise ValueError("interreflect: transfer_at takes rays without traced hits (trace_far=None)")
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
    for _, step in zip(range(int(bounces)), _steps(bounce_rays, albedo)):
        previous = step(previous)
        total += previous
    return total


def _steps(bounce_rays: BounceRays, albedo, targets: int | None = None):
    """Yield, bounce after bounce, ``step(T_{b-1} of the targets)`` -> ``T_b`` of the rays' samples (S, n, 3):
    ``W @ T_{b-1}`` per channel, the first bounce reading the traced transfer where the rays have it
    (:func:`traced_term`)."""
    matrices = bounce_matrices(bounce_rays, albedo, targets)
    if bounce_rays.traced is not None:
        first, extra = bounce_matrices(bounce_rays, albedo, targets, first=True), traced_term(bounce_rays, albedo)
        yield lambda previous: np.stack([first[c] @ previous[:, :, c] for c in range(3)], axis=2) + extra
    while True:
        yield lambda previous: np.stack([matrices[c] @ previous[:, :, c] for c in range(3)], axis=2)


def bounce_matrices(bounce_rays: BounceRays, face_albedo, targets: int | None = None, *, first: bool = False) -> list:
    """``W_c`` (S, T) sparse, per channel: ``W_c[p, q]`` = sum over p's rays landing nearest to q of
    ``a_c(hit face) / M``; ``targets`` T: the samples searched (default: S, the rays' own samples).
    ``first``: the first bounce's, leaving out the rays that read a traced transfer (:func:`traced_term`)."""
    from scipy.sparse import csr_matrix

    nearest = bounce_rays.nearest
    count, rays = nearest.shape
    reads = nearest >= 0
    if first and bounce_rays.traced is not None:
        reads &= bounce_rays.traced < 0
    rows, cols = np.nonzero(reads)
    landed = nearest[rows, cols]
    albedo = np.asarray(face_albedo, dtype=np.float64)[bounce_rays.hit_face[rows, cols]] / rays
    shape = (count, count if targets is None else int(targets))
    return [csr_matrix((albedo[:, c], (rows, landed)), shape=shape) for c in range(3)]


def traced_term(bounce_rays: BounceRays, face_albedo) -> np.ndarray:
    """(S, n, 3): the first bounce's part from the hits that read the direct transfer traced there,
    ``sum over p's such rays of a(hit face) T_0(hit) / M``."""
    from scipy.sparse import csr_matrix

    traced = bounce_rays.traced
    count, rays = traced.shape
    rows, cols = np.nonzero(traced >= 0)
    albedo = np.asarray(face_albedo, dtype=np.float64)[bounce_rays.hit_face[rows, cols]] / rays
    transfer = np.asarray(bounce_rays.traced_transfer, dtype=np.float64)
    shape = (count, len(transfer))
    return np.stack([csr_matrix((albedo[:, c], (rows, traced[rows, cols])), shape=shape) @ transfer for c in range(3)], axis=2)


def run_ray_chunks(executor, job, items, out: np.ndarray, chunk_size: int, rays: int, *, store=None, bar=None, traced: dict | None = None) -> None:
    """Trace the chunks ``items`` (``(k, points, normals)``) of bounce rays through ``executor``
    (:func:`bounce_chunk`): each chunk's rows into ``out[k * chunk_size ...]`` (a job with ``trace_far``:
    its traced transfer into ``traced[k]``) and, when given, into ``store`` (the driver alone writes the
    cache); ``bar`` advances by rays and is closed at the end."""
    from contextlib import closing

    try:
        with closing(executor.map(bounce_chunk, job, items, task_threads=1)) as finished:
            for (k, chunk_points, *_), value in finished:
                if store is not None:
                    store.save(k, value)
                if isinstance(value, tuple):
                    value, traced[k] = value
                out[k * chunk_size : (k + 1) * chunk_size] = value
                if bar is not None:
                    bar.update(len(chunk_points) * rays)
    finally:
        if bar is not None:
            bar.close()


def trace_stage(mesh, folder, train: dict, valid: dict, *, rays: int = BOUNCE_RAYS, seed: int = 0, chunk_size: int = 2048, key: str = "",
                executor=None, threads: int | None = None, progress: bool = True, log=print) -> dict:  # fmt: skip
    """The rays of the bounce stage, traced in chunks (cached in ``folder``): {"train", "validation"} -> :class:`BounceRays`.

    The hit points and nearest training samples do not depend on the albedos or the bounce count
    (see :func:`bounce_stage`); validation samples shoot their own rays (another seed stream).
    Samples with a ``face_index`` (the precompute's) apply the rule for rays entering the surface
    (:func:`entering`; their chunk stores are named with :data:`RAY_RULE`).  Hits with no clear sample,
    or whose clear sample lies farther than :data:`TRACE_FAR` times the training samples' spacing, get
    the direct transfer traced at themselves (``bands`` from the training transfer; :data:`TRACE_RULE`).
    """
    from pathlib import Path

    from ..executor import LocalExecutor
    from .transfer import EmbreeTracer

    import time

    executor = executor if executor is not None else LocalExecutor(threads)
    tracer = EmbreeTracer(mesh)
    found = {}
    t0 = time.perf_counter()
    far = TRACE_FAR * sample_spacing(train["points"], train["normals"])
    bands = int(round(np.sqrt(np.shape(train["transfer"])[1]))) if "transfer" in train else 4
    for stream, (name, data) in enumerate((("train", train), ("validation", valid))):
        points = np.ascontiguousarray(data["points"], dtype=np.float64)
        normals = np.ascontiguousarray(data["normals"], dtype=np.float64)
        count = len(points)
        n_chunks = (count + chunk_size - 1) // chunk_size
        faces = data.get("face_index")
        faces = None if faces is None or len(faces) != count else np.asarray(faces, dtype=np.int64)
        store = _IndexStore(Path(folder) / f"bounce-{name}-{key}-{CLEAR_RULE if faces is None else RAY_RULE}-{TRACE_RULE}", n_chunks, traced=True)
        out = np.empty((count, 3, rays), dtype=np.int32)
        todo = store.load_into(out, chunk_size)
        traced = store.traced
        job = BounceJob(tracer, train["points"], train["normals"], rays=rays, seed=seed, stream=stream, workers=1, trace_far=far, bands=bands)
        from ..progress import BOUNCE_RAY, progress_bar

        bar = progress_bar(progress, "bounces", f"bounce rays ({name})", count * rays, unit="ray", unit_cost=BOUNCE_RAY,
                           initial=(count - sum(min(chunk_size, count - k * chunk_size) for k in todo)) * rays, unit_scale=True,
                           mininterval=0.5)  # fmt: skip
        items = [(k, points[k * chunk_size : (k + 1) * chunk_size], normals[k * chunk_size : (k + 1) * chunk_size])
                 + (() if faces is None else (faces[k * chunk_size : (k + 1) * chunk_size],)) for k in todo]  # fmt: skip
        run_ray_chunks(executor, job, items, out, chunk_size, rays, store=store, bar=bar, traced=traced)
        found[name] = collect_rays(out, traced, chunk_size, bands)
    hits = sum(int((f.hit_face >= 0).sum()) for f in found.values())
    log(f"bounce rays: {sum(len(f.nearest) for f in found.values()):,} samples x {rays} rays in {time.perf_counter() - t0:.1f} s; "
        f"{sum(len(f.traced_transfer) for f in found.values()) / max(hits, 1):.1%} of the hits traced there "
        f"(no clear sample, or none within {far:.3g})")  # fmt: skip
    return found


def collect_rays(out: np.ndarray, traced: dict, chunk_size: int, bands: int) -> BounceRays:
    """:class:`BounceRays` of chunks traced with ``trace_far``: ``out`` (count, 3, rays) int32 [nearest,
    hit_face, traced row within its chunk] and ``traced`` {chunk: (H_k, n) its traced transfer}."""
    n_chunks = (len(out) + chunk_size - 1) // chunk_size
    rows, start = out[:, 2].astype(np.int64), 0
    for k in range(n_chunks):  # chunk-local rows of the traced transfer -> rows of their concatenation
        part = rows[k * chunk_size : (k + 1) * chunk_size]
        part[part >= 0] += start
        start += len(traced[k])
    transfer = np.concatenate([traced[k] for k in range(n_chunks)]) if n_chunks else np.zeros((0, bands * bands), np.float32)
    return BounceRays(out[:, 0].astype(np.int64), out[:, 1].astype(np.int64), rows, transfer)


def bounce_terms(found: dict, face_albedo, direct, bounces: int):
    """Yield ``(b, T_b of the training samples, T_b of the validation samples)`` for b = 1 .. ``bounces``.

    ``found``: :func:`trace_stage`'s rays; ``direct`` (S, n): the training samples' direct
    transfer.  Training: ``T_b = W @ T_{b-1}`` (:func:`bounce_matrices`, per channel);
    validation: its own rays gather the training samples' ``T_{b-1}`` (the same estimator).
    Each term is (count, n, 3) float64; only the previous training term is kept.
    """
    albedo = np.asarray(face_albedo, dtype=np.float64)
    steps, valid_steps = _steps(found["train"], albedo), _steps(found["validation"], albedo, targets=len(direct))
    previous = np.repeat(np.asarray(direct, dtype=np.float64)[:, :, None], 3, axis=2)
    for b, step, valid_step in zip(range(1, int(bounces) + 1), steps, valid_steps):
        valid_term = valid_step(previous)
        previous = step(previous)
        yield b, previous, valid_term


def bounce_stage(mesh, folder, train: dict, valid: dict, face_albedo, bounces: int, *, rays: int = BOUNCE_RAYS, seed: int = 0,
                 chunk_size: int = 2048, key: str = "", executor=None, threads: int | None = None, progress: bool = True,
                 log=print) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The build's bounce stage: indirect transfer ``T_1 + ... + T_N`` of the training and validation samples.

    Runs after the direct precompute and before fitting.  The rays (hit points and nearest
    training samples, which do not depend on the albedos) are traced in deterministic chunks
    through ``executor`` and stored in ``folder`` (:class:`prt.train.cache.ChunkStore`, keyed by
    ``key``: the precompute's key, rays, seed, chunk size; int32 indices), so an interrupted stage resumes and a
    change of albedo or bounce count retraces nothing (:func:`trace_stage`).  The bounces are
    sparse products (:func:`bounce_terms`).  Validation samples shoot their own rays (another
    seed stream) and gather the training samples' transfer of the previous bounce: the same estimator.

    Parameters
    ----------
    mesh : trimesh.Trimesh
    folder : path of the chunk stores
    train, valid : dicts with ``points``, ``normals``, ``transfer`` (direct, (S, n))
    face_albedo : (F, 3) diffuse albedo of every triangle
    bounces : N >= 1

    Returns
    -------
    (S, n, 3), (V, n, 3) float32: the indirect RGB transfer (without the direct term)
    """
    import time

    found = trace_stage(mesh, folder, train, valid, rays=rays, seed=seed, chunk_size=chunk_size, key=key, executor=executor,
                        threads=threads, progress=progress, log=log)  # fmt: skip
    t0 = time.perf_counter()
    direct = np.asarray(train["transfer"], dtype=np.float64)
    indirect = np.zeros(direct.shape + (3,))
    valid_indirect = np.zeros((len(found["validation"].nearest),) + direct.shape[1:] + (3,))
    for b, term, valid_term in bounce_terms(found, face_albedo, direct, bounces):
        indirect += term
        valid_indirect += valid_term
        log(f"bounce {b}/{bounces}: mean |T_{b}_0| {float(np.abs(term[:, 0]).mean()):.5f} (direct {float(np.abs(direct[:, 0]).mean()):.5f})")
    log(f"bounces: {bounces} in {time.perf_counter() - t0:.1f} s")
    return indirect.astype(np.float32), valid_indirect.astype(np.float32)
