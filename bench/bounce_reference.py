"""The interreflected part of the benchmark's reference (scenes built with ``--bounces N``).

The renderer's interreflected transfer is ``T_0 + T_1 + ... + T_N`` (Sloan et al. 2002; see
:mod:`prt.train.transport.interreflection`).  At every covered pixel ``p`` the reference computes

    T(p) = T_0(p) + mean_j  a(q_j) * [ T_0(q_j) + H(q_j) ]          (RGB: a is a colour)

over ``hit_rays`` cosine-distributed rays from ``p`` hitting ``q_j``:

- ``T_0(p)``: the ray-traced direct transfer of the pixel (the reference's usual
  :func:`prt.bench.reference.cached_transfer`);
- ``T_0(q_j)``: the direct transfer ray traced afresh *at the exact hit point* (``rays`` rays,
  the hit's geometric normal turned towards ``p``), so the first bounce, which carries almost
  all of the indirect light, involves no interpolation at all (the interpolated normal there
  instead, as a path tracer shades the hit, measured the same against Mitsuba 3 on Spot: +0.12 %
  against +0.09 %, so the geometric one stays);
- rays leaving ``p`` below the plane of its own face (found by
  :func:`prt.train.transport.interreflection.surface_faces`) enter the surface and carry nothing,
  the build's rule (:func:`prt.train.transport.interreflection.entering`);
- ``H(q_j) = T_1 + ... + T_{N-1}`` (``N >= 2`` only): the higher bounces, from the nearest of
  an independent set of surface samples (own seed and count, not the build's) on which the
  bounce operator of :mod:`prt.train.transport.interreflection` ran with the same albedos (its
  tangent-plane-aware nearest-sample rule on the hit's side of walls, stricter: :data:`REFERENCE_CANDIDATES`,
  :data:`REFERENCE_PLANE_WEIGHT`; a hit with no clear candidate carries no higher bounces).

So the reference shares nothing with the build but the scene, the albedos recorded in the
manifest and the SH-projected light: only the transfer representation differs.  Cached by
content like the direct reference.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from prt.runtime.errors import InputError
from prt.runtime.files import atomic_save_npz
from prt.train import compute_transfer
from prt.train.transport.interreflection import NORMAL_WEIGHT, RAY_RULE, entering, face_normals, interreflect, nearest_visible, surface_faces, trace_bounce_rays
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.transfer import cosine_directions, orthonormal_frames

__all__ = ["face_albedo", "higher_bounce_samples", "indirect_transfer", "cached_indirect", "direct_rgb", "HIT_RAYS", "HIT_TRANSFER_RAYS", "HIGHER_SAMPLES"]

HIT_RAYS = 64  # bounce rays per pixel
HIT_TRANSFER_RAYS = 128  # rays of the direct transfer at each hit point (averaged again over HIT_RAYS hits)
HIGHER_SAMPLES = 40_000  # independent samples carrying the bounces >= 2
SEED_STREAM = 0x5EF  # keeps the reference's random streams apart from the build's
# The nearest-sample searches of the higher bounces (prt.train.transport.interreflection.nearest_on_plane)
# compare more samples with the hit's tangent plane, and weigh the distance from it more, than
# the build's (8, 4.0): the independent samples are sparser, and at 40k on the Cornell box the
# build's values left the light/ceiling gap's samples with leaked sky light (mean shaded T_1
# 0.045 under potsdamer; 0.0001 with these).
REFERENCE_CANDIDATES = 16
REFERENCE_PLANE_WEIGHT = 16.0


def face_albedo(albedos: dict, geometry) -> np.ndarray:
    """(F, 3) albedo of every triangle from ``{object name: [r, g, b]}`` (the manifest's record).

    An object the record does not name is an error: the reference would silently differ from the
    build otherwise.
    """
    names = list(geometry.object_names)
    missing = [n for n in names if n not in albedos]
    if missing:
        raise InputError(f"interreflection.albedos has no albedo for object(s) {', '.join(missing)}")
    table = np.array([np.asarray(albedos[n], dtype=np.float64) for n in names]).reshape(len(names), 3)
    return table[np.asarray(geometry.object_ids)]


def _digest(*parts) -> str:
    h = hashlib.sha1()
    for part in parts:
        h.update(np.ascontiguousarray(part).tobytes() if isinstance(part, np.ndarray) else repr(part).encode())
    return h.hexdigest()[:12]


def higher_bounce_samples(geometry, tracer, albedo, bounces: int, *, rays: int, count: int = HIGHER_SAMPLES, seed: int = 0,
                          cache: Path | None = None, geometry_id: str = "", log=print):
    """Independent surface samples with ``H = T_1 + ... + T_{bounces-1}`` (None when ``bounces < 2``).

    Returns
    -------
    (points (S, 3), normals (S, 3), higher (S, 16, 3) float32) or None
    """
    if bounces < 2:
        return None
    path = None
    if cache is not None:
        path = Path(cache) / f"higher-b{bounces}-n{count}-r{rays}-s{seed}-{_digest(geometry_id, albedo, 'v3', RAY_RULE)}.npz"
        if path.is_file():
            with np.load(path) as data:
                return data["points"], data["normals"], data["higher"]
    t0 = time.perf_counter()
    samples = sample_surface(geometry, count, seed=seed, stream=SEED_STREAM)
    points, normals = samples.points, samples.normals
    direct = compute_transfer(geometry, points, normals, rays=rays, seed=seed + SEED_STREAM, tracer=tracer)
    found = trace_bounce_rays(geometry.mesh, points, normals, samples.face_index, rays=HIT_RAYS, seed=seed + SEED_STREAM,
                              candidates=REFERENCE_CANDIDATES, plane_weight=REFERENCE_PLANE_WEIGHT)  # fmt: skip
    higher = (interreflect(direct, found, albedo, bounces - 1) - direct[:, :, None].astype(np.float64)).astype(np.float32)
    log(f"  reference bounces >= 2: {count:,} samples x {rays} rays, {bounces - 1} bounce(s) in {time.perf_counter() - t0:.1f} s")
    if path is not None:
        atomic_save_npz(path, points=points, normals=normals, higher=higher)
    return points, normals, higher


def _hits(tracer, points, normals, rays: int, seed: int, faces=None):
    """Cosine-distributed rays from every point: hit points (P, M, 3), normals facing the ray, faces (-1: miss).

    With the points' own ``faces``, rays entering the surface count as misses
    (:func:`prt.train.transport.interreflection.entering`)."""
    local = cosine_directions(rays).astype(np.float32)
    rng = np.random.default_rng(np.random.SeedSequence([seed, SEED_STREAM, len(points)]))
    frames = orthonormal_frames(normals.astype(np.float64), rng.uniform(0.0, 2.0 * np.pi, len(points))).astype(np.float32)
    dirs = np.matmul(local[None], frames.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat((points + tracer.offset * normals).astype(np.float32), rays, axis=0)
    result = tracer._scene.run(origins, dirs, output=1)
    hit_faces = result["primID"].astype(np.int64)
    if faces is not None:
        hit_faces[entering(dirs.reshape(len(points), rays, 3), normals.astype(np.float64), faces, face_normals(tracer)).reshape(-1)] = -1
    faces = hit_faces
    hit_points = origins + result["tfar"][:, None].astype(np.float32) * dirs
    ng = result["Ng"].astype(np.float64)
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-30)
    ng *= -np.sign(np.einsum("qc,qc->q", ng, dirs))[:, None]  # the side the ray sees
    return hit_points, ng.astype(np.float32), faces


def indirect_transfer(geometry, tracer, points, normals, albedo, bounces: int, *, hit_rays: int = HIT_RAYS,
                      rays: int = HIT_TRANSFER_RAYS, higher=None, seed: int = 0, chunk: int = 2048, entering_rule: bool = True) -> np.ndarray:
    """``mean_j a(q_j) [T_0(q_j) + H(q_j)]`` at ``points``: (P, 16, 3) float32 (zeros when ``bounces == 0``).

    Parameters
    ----------
    geometry, tracer :
        The scene and its Embree tracer (:func:`prt.train.transport.transfer.make_tracer`).
    points, normals : (P, 3)
        Pixels' positions and normals (facing the camera).
    albedo : (F, 3)
        Per-triangle albedo (:func:`face_albedo`).
    higher : the result of :func:`higher_bounce_samples` (needed when ``bounces >= 2``).
    entering_rule : bool
        Rays entering the surface carry nothing (the default); False: the estimator before issue 38
        (``studies/mitsuba_bias.py`` measures both).
    """
    points = np.ascontiguousarray(points, dtype=np.float32)
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    out = np.zeros((len(points), 16, 3), dtype=np.float32)
    if bounces <= 0 or len(points) == 0:
        return out
    if bounces >= 2 and higher is None:
        raise InputError("indirect_transfer: bounces >= 2 needs the higher-bounce samples")
    albedo = np.asarray(albedo, dtype=np.float64)
    tree = None
    if bounces >= 2:  # the nearest-sample rule of the bounce stage (tangent-plane aware), on the independent samples
        s_points, s_normals, _ = higher
        tree = cKDTree(np.concatenate([s_points, NORMAL_WEIGHT * s_normals], axis=1))
    own = surface_faces(tracer, points, normals) if entering_rule else None  # the pixels' faces: rays entering the surface carry nothing
    for c, start in enumerate(range(0, len(points), chunk)):
        rows = slice(start, start + chunk)
        q, nq, faces = _hits(tracer, points[rows], normals[rows], hit_rays, seed + c, None if own is None else own[rows])
        hit = faces >= 0
        t = np.zeros((len(q), 16, 3), dtype=np.float64)
        if hit.any():
            t0 = compute_transfer(geometry, q[hit], nq[hit], rays=rays, seed=seed + c, tracer=tracer).astype(np.float64)
            t[hit] = t0[:, :, None]
            if tree is not None:
                nearest = nearest_visible(tree, np.concatenate([q[hit], NORMAL_WEIGHT * nq[hit]], axis=1), tracer, candidates=REFERENCE_CANDIDATES,
                                          plane_weight=REFERENCE_PLANE_WEIGHT, bound=np.inf)  # fmt: skip
                t[hit] += np.where((nearest >= 0)[:, None, None], higher[2][np.maximum(nearest, 0)], 0.0)
        weight = np.where(hit[:, None], albedo[np.where(hit, faces, 0)], 0.0)  # (P*M, 3)
        n = len(points[rows])
        out[rows] = np.einsum("pmc,pmkc->pkc", weight.reshape(n, hit_rays, 3), t.reshape(n, hit_rays, 16, 3)) / hit_rays
    return out


def cached_indirect(cache: Path, tag: str, geometry, tracer, points, normals, albedo, bounces: int, *, higher=None, seed: int = 0,
                    geometry_id: str = "", hit_rays: int = HIT_RAYS, rays: int = HIT_TRANSFER_RAYS, cost: dict | None = None):
    """:func:`indirect_transfer`, read from ``cache`` when computed before; (indirect, seconds computed).

    ``cost`` (a dict) receives ``seconds``: what computing it took, then or when it was cached
    (None for a file cached before its time was kept)."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    key = _digest(points, normals, albedo, bounces, hit_rays, rays, seed, geometry_id, None if higher is None else higher[2], "v3", RAY_RULE)
    path = Path(cache) / f"{tag}-indirect-b{bounces}-s{seed}-{key}.npz"
    if path.is_file():
        with np.load(path) as data:
            if cost is not None:
                cost["seconds"] = float(data["seconds"]) if "seconds" in data else None
            return data["indirect"], 0.0
    t0 = time.perf_counter()
    indirect = indirect_transfer(geometry, tracer, points, normals, albedo, bounces, hit_rays=hit_rays, rays=rays, higher=higher, seed=seed)
    seconds = time.perf_counter() - t0
    atomic_save_npz(path, indirect=indirect, seconds=np.float64(seconds))
    if cost is not None:
        cost["seconds"] = seconds
    return indirect, seconds


def direct_rgb(direct, indirect) -> np.ndarray:
    """The networks' ``direct+rgb`` layout: (P, 64) = direct (16), then indirect R, G, B (16 each)."""
    indirect = np.asarray(indirect, dtype=np.float32)
    return np.concatenate([np.asarray(direct, dtype=np.float32)] + [indirect[:, :, c] for c in range(3)], axis=1)
