"""The engines' baseline: an L2 SH irradiance probe grid (``prt-bench --backends probes``).

What Unity's Adaptive Probe Volumes, Godot's LightmapGI and three.js's light-probe grids serve
for scenes, reduced to its core:

- **Probes** on a regular grid over the mesh's bounds (:func:`grid_layout`: at the centres of
  cubic cells tiling the bounds, at least 2 probes per axis; none on the bounds' own faces).  Two densities are measured: at the
  networks' fp32 bytes (``equal bytes``: as many probes as 27 float32 each, plus a validity
  bit, fit in them) and at a density engines use (``engine``: :data:`ENGINE_SPACING_M` = 1 m
  between probes in the source file's units, glTF's metres; Unity APV's default minimum probe
  spacing), translated into the normalised scene by ``to_source``'s scale and kept within
  :data:`MIN_PER_AXIS`..:data:`MAX_PER_AXIS` probes per axis and :data:`MAX_PROBES` in all.
- **Baking** (:func:`bake_probes`): from each probe :data:`PROBE_RAYS` directions uniform over the whole
  sphere (a Fibonacci set turned at random per probe) are traced with the project's Embree
  tracer.  A ray that leaves the scene sees the scene's SH light ``L(w)`` (what the reference's
  transfer integrates); a ray that hits a surface sees that point's outgoing diffuse radiance
  with the same number of bounces as the build: ``a(q) [T_0 + ... + T_{N-1}](q) . L`` read from
  the nearest of a set of independent ray-traced surface samples (the bounce operator's
  tangent-plane-aware rule on the hit's side of walls, :func:`prt.train.transport.interreflection.nearest_visible`), so a
  probe lit through N bounces matches the reference's N-bounce pixel (with ``--bounces 0``
  surfaces send nothing, as in the reference).  The incident radiance is projected on 9 real SH
  (bands 0-2) per RGB channel: 27 numbers per probe.
- **Lookup** (:meth:`ProbeGrid.lookup`): trilinear between the 8 probes around the point, the
  irradiance the L2 SH gives for the pixel's normal (cosine lobe: ``A_l / pi`` = 1, 2/3, 1/4;
  the lobe has no band 3, so an unoccluded probe reproduces the 16-coefficient light's diffuse
  shading exactly), shaded ``albedo * D`` like the renderer's diffuse material.
- **Leak mitigation** (what engines ship): *probe validity*: a probe whose rays hit back faces
  of one-sided triangles in more than :data:`VALIDITY_THRESHOLD` of its directions stands inside
  geometry; it is invalid and its trilinear weight is dropped (the other corners renormalised;
  where all 8 are invalid the plain weights are kept), as APV's validity and Godot's probe
  invalidation do; and a *normal bias*: the lookup point moves :data:`NORMAL_BIAS` probe spacings
  along the pixel's normal, off the surface towards the side the pixel faces.  Neither stops a
  probe outside a thin wall from lighting the room behind it: the leak the benchmark's figure
  (:mod:`prt.bench.leak`) measures.

Mesh scenes only; the diffuse material only (probes store irradiance, no glossy lobe).
:func:`lookup_reference` is the plain twin of the vectorised trilinear lookup.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from prt.runtime import sh

__all__ = ["ENGINE_SPACING_M", "VALIDITY_THRESHOLD", "NORMAL_BIAS", "PROBE_BYTES", "MIN_PER_AXIS", "MAX_PER_AXIS", "ProbeGrid",
           "grid_layout", "equal_bytes_spacing", "engine_spacing", "sphere_directions", "bake_probes", "lookup_reference",
           "IRRADIANCE_BANDS", "MAX_PROBES", "PROBE_RAYS"]  # fmt: skip

ENGINE_SPACING_M = 1.0  # Unity APV's default minimum probe spacing (metres; the source file's units)
VALIDITY_THRESHOLD = 0.5  # invalid above this share of back-face hits ("most of its rays")
NORMAL_BIAS = 0.25  # lookup offset along the normal, in probe spacings
PROBE_BYTES = 27 * 4  # 9 SH coefficients x RGB, float32 (the validity bit is counted apart)
MIN_PER_AXIS, MAX_PER_AXIS = 2, 64
MAX_PROBES = 32_768  # the engine density's cap (its bake traces PROBE_RAYS per probe)
PROBE_RAYS = 512  # directions per probe
IRRADIANCE_BANDS = np.array([1.0, 2.0 / 3.0, 2.0 / 3.0, 2.0 / 3.0, 0.25, 0.25, 0.25, 0.25, 0.25])  # A_l / pi per coefficient


def grid_layout(lo, hi, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), dims (3,) int) of the probes at the centres of about ``extent / spacing`` cells per axis
    tiling ``[lo, hi]`` (at least :data:`MIN_PER_AXIS`), ``spacing`` apart, centred on it: no probe sits on the
    bounds' faces (the outer walls of a building), each is a quarter to three quarters of a spacing inside."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    extent = np.maximum(hi - lo, 0.0)
    dims = np.maximum(MIN_PER_AXIS, np.round(extent / spacing).astype(np.int64))
    origin = 0.5 * (lo + hi) - 0.5 * (dims - 1) * spacing
    return origin, dims


def equal_bytes_spacing(lo, hi, budget_bytes: int) -> float:
    """The smallest spacing whose grid fits ``budget_bytes`` (27 float32 and a validity bit per probe);
    the coarsest grid (2 per axis) when even it does not."""
    def cost(s: float) -> float:
        n = int(np.prod(grid_layout(lo, hi, s)[1]))
        return n * PROBE_BYTES + math.ceil(n / 8)

    big = float(np.max(np.asarray(hi) - np.asarray(lo))) or 1.0
    small = big / (4 * MAX_PER_AXIS)
    if cost(small) <= budget_bytes:
        return small
    for _ in range(60):  # bisection on a log scale: cost falls as the spacing grows
        mid = math.sqrt(small * big)
        small, big = (small, mid) if cost(mid) <= budget_bytes else (mid, big)
    return big


def engine_spacing(lo, hi, to_source) -> tuple[float, bool]:
    """(spacing in scene units, clamped) of :data:`ENGINE_SPACING_M` in the source's units, kept within
    :data:`MIN_PER_AXIS`..:data:`MAX_PER_AXIS` probes per axis (``clamped``: it had to be)."""
    scale = abs(float(np.linalg.det(np.asarray(to_source, dtype=np.float64)[:3, :3]))) ** (1.0 / 3.0) or 1.0
    spacing = ENGINE_SPACING_M / scale
    extent = float(np.max(np.asarray(hi) - np.asarray(lo))) or 1.0
    fine, coarse = extent / (MAX_PER_AXIS - 1), extent / (MIN_PER_AXIS - 1)
    clamped = float(min(max(spacing, fine), coarse))
    while np.prod(grid_layout(lo, hi, clamped)[1]) > MAX_PROBES:
        clamped *= 1.05
    return clamped, not math.isclose(clamped, spacing)


def sphere_directions(count: int) -> np.ndarray:
    """(count, 3) unit directions spread evenly over the sphere (Fibonacci lattice), float64."""
    i = np.arange(count, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _random_rotations(rng, n: int) -> np.ndarray:
    """(n, 3, 3) uniformly random rotations (from unit quaternions)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)  # fmt: skip


def bake_probes(tracer, two_sided, positions, light_sh, *, rays: int, seed: int = 0, hit_radiance=None, chunk_rays: int = 1 << 18):
    """Incident radiance SH (bands 0-2, RGB) at every probe; the module docstring's rule.

    Parameters
    ----------
    tracer : the scene's Embree tracer (:func:`prt.train.transport.transfer.make_tracer`).
    two_sided : (F,) bool
        Triangles that are surfaces on both sides (their back is no inside).
    positions : (P, 3)
    light_sh : (16, 3) or (n, 3)
        The scene's SH light (what a ray leaving the scene sees).
    rays : int
        Directions per probe.
    hit_radiance : callable or None
        ``hit_radiance(points (K, 3), normals facing the ray (K, 3), faces (K,)) -> (K, 3)``: the
        outgoing radiance of front (or two-sided) hits; None: surfaces send nothing (no bounces).

    Returns
    -------
    coefficients : (P, 9, 3) float32
    back_fraction : (P,) float64, the share of directions that hit a one-sided triangle's back.
    """
    positions = np.asarray(positions, dtype=np.float64)
    light_sh = np.asarray(light_sh, dtype=np.float64)
    bands = math.isqrt(light_sh.shape[0])
    table = _face_normals(tracer)
    two_sided = np.asarray(two_sided, dtype=bool)
    base = sphere_directions(rays)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x9B0E, len(positions)]))
    rotations = _random_rotations(rng, len(positions))
    out = np.zeros((len(positions), 9, 3), dtype=np.float32)
    back_fraction = np.zeros(len(positions))
    per = max(1, chunk_rays // rays)
    for start in range(0, len(positions), per):
        rows = slice(start, start + per)
        n = len(positions[rows])
        dirs = np.einsum("pij,mj->pmi", rotations[rows], base).reshape(-1, 3)
        origins = np.repeat(positions[rows], rays, axis=0)
        result = tracer._scene.run(origins.astype(np.float32), dirs.astype(np.float32), output=1)
        faces = result["primID"].astype(np.int64)
        hit = faces >= 0
        along = np.einsum("qc,qc->q", table[np.maximum(faces, 0)], dirs)
        back = hit & (along > 0.0) & ~two_sided[np.maximum(faces, 0)]
        radiance = np.zeros((len(dirs), 3))
        miss = ~hit
        radiance[miss] = sh.basis(dirs[miss], bands) @ light_sh
        lit = hit & ~back
        if hit_radiance is not None and lit.any():
            q = origins[lit] + result["tfar"][lit, None].astype(np.float64) * dirs[lit]
            normals = table[faces[lit]] * -np.sign(along[lit])[:, None]  # the side the ray sees
            radiance[lit] = hit_radiance(q, normals, faces[lit])
        y9 = sh.basis(dirs, 3)
        coefficients = np.einsum("qk,qc->qkc", y9, radiance).reshape(n, rays, 9, 3).mean(axis=1) * (4.0 * math.pi)
        out[rows] = coefficients
        back_fraction[rows] = back.reshape(n, rays).mean(axis=1)
    return out, back_fraction


def _face_normals(tracer) -> np.ndarray:
    from prt.train.transport.interreflection import face_normals

    return face_normals(tracer)


@dataclass
class ProbeGrid:
    """A baked grid: ``coefficients`` (nx, ny, nz, 9, 3) at ``origin + spacing * (i, j, k)``, ``valid`` (nx, ny, nz)."""

    origin: np.ndarray
    spacing: float
    coefficients: np.ndarray
    valid: np.ndarray
    normal_bias: float = NORMAL_BIAS
    info: dict = field(default_factory=dict)

    @property
    def dims(self) -> tuple:
        return tuple(int(d) for d in self.valid.shape)

    @property
    def count(self) -> int:
        return int(self.valid.size)

    @property
    def weight_bytes(self) -> int:
        """27 float32 per probe and one validity bit."""
        return self.count * PROBE_BYTES + math.ceil(self.count / 8)

    def corners(self, points, normals) -> tuple[np.ndarray, np.ndarray]:
        """(flat indices (N, 8), weights (N, 8)) of the trilinear lookup with the validity rule (module docstring)."""
        points = np.asarray(points, dtype=np.float64)
        normals = np.asarray(normals, dtype=np.float64)
        dims = np.asarray(self.dims)
        u = (points + self.normal_bias * self.spacing * normals - self.origin) / self.spacing
        u = np.clip(u, 0.0, dims - 1)
        i0 = np.minimum(np.floor(u).astype(np.int64), dims - 2)
        f = u - i0
        index = np.empty((len(points), 8), dtype=np.int64)
        weight = np.empty((len(points), 8))
        for c in range(8):
            bits = np.array([(c >> 2) & 1, (c >> 1) & 1, c & 1])
            ijk = i0 + bits
            index[:, c] = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
            weight[:, c] = np.prod(np.where(bits == 1, f, 1.0 - f), axis=1)
        masked = weight * self.valid.reshape(-1)[index]
        total = masked.sum(axis=1, keepdims=True)
        use = total[:, 0] > 1e-8  # all 8 invalid: the plain weights
        weight[use] = masked[use] / total[use]
        return index, weight

    def lookup(self, points, normals) -> np.ndarray:
        """(N, 9, 3) interpolated SH at the pixels (positions, unit normals facing the eye)."""
        index, weight = self.corners(points, normals)
        flat = self.coefficients.reshape(-1, 9, 3)
        return np.einsum("nc,nckr->nkr", weight, flat[index].astype(np.float64))

    def irradiance(self, points, normals) -> np.ndarray:
        """(N, 3): ``D = E / pi`` for each normal (the renderer's diffuse term: radiance = albedo * D)."""
        normals = np.asarray(normals, dtype=np.float64)
        coefficients = self.lookup(points, normals)
        y = sh.basis(normals, 3) * IRRADIANCE_BANDS
        return np.einsum("nk,nkr->nr", y, coefficients)


def lookup_reference(grid: ProbeGrid, points, normals) -> np.ndarray:
    """Plain twin of :meth:`ProbeGrid.lookup`: one point and one corner at a time."""
    nx, ny, nz = grid.dims
    out = np.zeros((len(points), 9, 3))
    for p in range(len(points)):
        u = [(float(points[p][a]) + grid.normal_bias * grid.spacing * float(normals[p][a]) - float(grid.origin[a])) / grid.spacing
             for a in range(3)]  # fmt: skip
        cell, frac = [], []
        for a, n in enumerate((nx, ny, nz)):
            x = min(max(u[a], 0.0), n - 1)
            i = min(int(math.floor(x)), n - 2)
            cell.append(i)
            frac.append(x - i)
        corners = []
        for di in (0, 1):
            for dj in (0, 1):
                for dk in (0, 1):
                    w = (frac[0] if di else 1 - frac[0]) * (frac[1] if dj else 1 - frac[1]) * (frac[2] if dk else 1 - frac[2])
                    corners.append(((cell[0] + di, cell[1] + dj, cell[2] + dk), w))
        valid_total = sum(w for ijk, w in corners if grid.valid[ijk])
        for ijk, w in corners:
            if valid_total > 1e-8:
                w = w / valid_total if grid.valid[ijk] else 0.0
            out[p] += w * grid.coefficients[ijk].astype(np.float64)
    return out


def build_grid(tracer, two_sided, lo, hi, spacing: float, light_sh, *, rays: int, seed: int, hit_radiance=None, density: str = "") -> ProbeGrid:
    """Lay out, bake and validate one grid (:func:`grid_layout`, :func:`bake_probes`); ``info`` says what it is."""
    t0 = time.perf_counter()
    origin, dims = grid_layout(lo, hi, spacing)
    axes = [origin[a] + spacing * np.arange(dims[a]) for a in range(3)]
    positions = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    coefficients, back = bake_probes(tracer, two_sided, positions, light_sh, rays=rays, seed=seed, hit_radiance=hit_radiance)
    valid = (back <= VALIDITY_THRESHOLD).reshape(tuple(dims))
    grid = ProbeGrid(origin, float(spacing), coefficients.reshape(tuple(dims) + (9, 3)), valid)
    grid.info = {"density": density, "dims": [int(d) for d in dims], "probes": grid.count, "spacing": round(float(spacing), 6),
                 "invalid": int((~valid).sum()), "rays": int(rays), "weight_bytes": grid.weight_bytes,
                 "seconds": round(time.perf_counter() - t0, 3)}  # fmt: skip
    return grid
