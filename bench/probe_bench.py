"""The probe-grid baseline inside a scene's benchmark (:mod:`prt.bench.probe_grid`; ``--backends probes``).

:func:`scene_grids` bakes the two grids of a mesh scene once (equal bytes with the networks'
fp32 weights, and the engine density) under the scene's light; :func:`probe_frame` is one frame
(the renderer's G-buffer, the trilinear lookup on the CPU, diffuse shading); the records are
made by :meth:`prt.bench.scene_bench.SceneBench._probe_records`.  The scene's entry gets
``probe_grid``: ``grids`` (per density: ``dims``, ``probes``, ``spacing`` in scene units,
``invalid`` probes, ``rays`` per probe, ``weight_bytes``, ``seconds``), ``engine_spacing_m``,
``engine_clamped``, ``validity_threshold``, ``normal_bias``, ``mitigation``, ``radiance``
(what a probe ray sees at a hit), ``samples`` (surface samples carrying the hit radiance), or
``note`` when skipped.
"""

from __future__ import annotations

import time

import numpy as np

from prt.bench.bounce_reference import HIGHER_SAMPLES, REFERENCE_CANDIDATES, REFERENCE_PLANE_WEIGHT, SEED_STREAM
from prt.bench.probe_grid import (
    ENGINE_SPACING_M, MAX_PER_AXIS, MAX_PROBES, MIN_PER_AXIS, NORMAL_BIAS, PROBE_RAYS, VALIDITY_THRESHOLD, build_grid, engine_spacing,
    equal_bytes_spacing,
)  # fmt: skip
from prt.bench.reference import cached_transfer

__all__ = ["DENSITIES", "MITIGATION", "scene_grids", "probe_frame", "hit_radiance_source"]

DENSITIES = ("equal-bytes", "engine")
MITIGATION = (f"probe validity (a probe with more than {VALIDITY_THRESHOLD:g} of its rays on back faces of one-sided triangles is "
              f"dropped from the trilinear weights, the rest renormalised) and a normal bias of {NORMAL_BIAS:g} probe spacings")  # fmt: skip


def hit_radiance_source(sb, light_sh):
    """``hit_radiance(points, normals, faces) -> (K, 3)`` for :func:`prt.bench.probe_grid.bake_probes`, and how many
    samples carry it: the outgoing diffuse radiance ``a(q) [T_0 + H](q) . L`` of the nearest independent surface sample on the hit's side of walls
    (the reference's higher-bounce samples and rule, :mod:`prt.bench.bounce_reference`); (None, 0) without bounces."""
    if sb.bounces <= 0:
        return None, 0
    from scipy.spatial import cKDTree

    from prt.train.inputs.sampling import sample_surface
    from prt.train.transport.interreflection import NORMAL_WEIGHT, nearest_visible

    settings = sb.settings
    if sb.higher is not None:  # bounces >= 2: the reference's independent samples, with T_1 + ... + T_{N-1}
        points, normals, higher = sb.higher
    else:
        samples = sample_surface(sb.geometry, HIGHER_SAMPLES, seed=settings.seed, stream=SEED_STREAM)
        points, normals, higher = samples.points, samples.normals, None
    direct, _ = cached_transfer(sb.transfer_cache, "probe-samples", sb.geometry, sb.tracer, points, normals, settings.rays_of_baselines,
                                settings.seed + SEED_STREAM, sb.geometry_id, executor=sb.executor)  # fmt: skip
    total = np.repeat(direct[:, :, None].astype(np.float64), 3, axis=2)
    if higher is not None:
        total += higher
    outgoing = np.einsum("skc,kc->sc", total, np.asarray(light_sh, dtype=np.float64))  # (S, 3): D at the sample, before albedo
    tree = cKDTree(np.concatenate([points, NORMAL_WEIGHT * normals], axis=1))
    albedo = np.asarray(sb.bounce_albedo, dtype=np.float64)

    def hit_radiance(q, n, faces):
        nearest = nearest_visible(tree, np.concatenate([q, NORMAL_WEIGHT * n], axis=1), sb.tracer, candidates=REFERENCE_CANDIDATES,
                                  plane_weight=REFERENCE_PLANE_WEIGHT, bound=np.inf)  # fmt: skip
        return albedo[faces] * outgoing[np.maximum(nearest, 0)] * (nearest >= 0)[:, None]

    return hit_radiance, len(points)


def scene_grids(sb, lighting) -> tuple[dict, dict]:
    """({density: ProbeGrid}, the scene's ``probe_grid`` entry) of a mesh scene (``sb``: its SceneBench)."""
    if sb.geometry.kind != "mesh":
        return {}, {"note": f"skipped: {sb.geometry.kind} scene (the probes are traced on meshes)"}
    vertices = np.asarray(sb.geometry.mesh.vertices, dtype=np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    light_sh = np.asarray(lighting.sh, dtype=np.float64)
    t0 = time.perf_counter()
    hit_radiance, samples = hit_radiance_source(sb, light_sh)
    engine, clamped = engine_spacing(lo, hi, sb.manifest.geometry.to_source)
    spacings = {"equal-bytes": equal_bytes_spacing(lo, hi, sb.weights["fp32"]), "engine": engine}
    rays = PROBE_RAYS
    grids = {}
    for density, spacing in spacings.items():
        grids[density] = build_grid(sb.tracer, sb.geometry.two_sided, lo, hi, spacing, light_sh, rays=rays, seed=sb.settings.seed,
                                    hit_radiance=hit_radiance, density=density)  # fmt: skip
        info = grids[density].info
        sb.log(f"  probe grid {density}: {'x'.join(map(str, info['dims']))} = {info['probes']} probes ({info['invalid']} invalid), "
               f"spacing {info['spacing']:.4g}, {info['weight_bytes']:,} bytes, {rays} rays each ({info['seconds']:.1f} s)")  # fmt: skip
    entry = {
        "grids": {d: g.info for d, g in grids.items()}, "engine_spacing_m": ENGINE_SPACING_M, "engine_clamped": clamped,
        "engine_limits": {"per_axis": [MIN_PER_AXIS, MAX_PER_AXIS], "probes": MAX_PROBES},
        "validity_threshold": VALIDITY_THRESHOLD, "normal_bias": NORMAL_BIAS, "mitigation": MITIGATION,
        "radiance": ("rays leaving the scene see the SH light; hits see the nearest independent sample on their side of walls: its outgoing diffuse "
                     f"radiance with {sb.bounces - 1} further bounce(s)") if sb.bounces > 0 else "rays leaving the scene see the SH light; surfaces send nothing (no bounces)",
        "samples": samples, "seconds": round(time.perf_counter() - t0, 3),
    }  # fmt: skip
    return grids, entry


def probe_frame(grid, gbuffer_pass, camera, albedo, width: int, height: int) -> tuple[np.ndarray, dict]:
    """One frame of the probe grid: G-buffer pass, trilinear lookup, diffuse shading; (linear (H, W, 3), timings)."""
    t0 = time.perf_counter()
    gbuffer_pass.render(camera)
    packed = gbuffer_pass.read_packed()
    t1 = time.perf_counter()
    covered = np.flatnonzero(packed[:, 3] > 0.5)
    rows = packed[covered]
    irradiance = grid.irradiance(rows[:, 0:3], rows[:, 4:7])
    t2 = time.perf_counter()
    image = np.zeros((len(packed), 3), dtype=np.float32)
    image[covered] = np.maximum(irradiance * np.asarray(albedo, dtype=np.float64), 0.0)
    t3 = time.perf_counter()
    timings = {"gbuffer": 1e3 * (t1 - t0), "probes": 1e3 * (t2 - t1), "shade": 1e3 * (t3 - t2), "frame": 1e3 * (t3 - t0)}
    return image.reshape(height, width, 3), timings
