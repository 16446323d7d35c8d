"""The narrow band of an SDF: two marching-cubes shells around its zero set, and local slopes.

:class:`~prt.train.sdf.band_trace.BandTracer` traces rays against an SDF with Embree on these
shells and evaluates the field only between them (see there).  This module builds them:

1. **Grid.**  The field on the build's grid (:meth:`SDF.grid`, 128 samples along the box: the
   grid the sampling mesh came from, evaluated once), refined ``refine`` times (fine step ``h_f``)
   in every coarse cell the band may pass through: whose corner values come within ``A`` of the
   zero level, ``A`` the larger of 1.5x (``delta`` + the coarse grid's largest interpolation
   error, measured at random points of the cells the surface crosses) and half a cell diagonal
   times the median slope at the surface.  The other fine samples take a corner's value of their
   coarse cell; every corner of such a cell lies beyond ``A``, so no shell crosses them.
2. **Shells.**  Marching cubes at ``-delta`` (the *inner* shell, inside the solid) and
   ``+delta`` (the *outer* shell, enclosing it), wound outwards.  ``delta`` is the larger of
   (a) ``0.5 * s_med * h_f`` (``s_med``: the median slope at the surface): a feature at least
   ``(sqrt(3) - 1) h_f`` thick, 0.006 scene units at the defaults, has a fine sample within
   ``delta`` of its field value, so the outer shell encloses it; and (b) 1.25x the fine grid's
   largest interpolation error (measured as above) plus the sphere tracer's hit threshold at
   ``t = 1`` (2e-4): the shells then lie where the field is clearly above (outer) or below
   (inner) that threshold.  The field at random points of each shell is recorded
   (``stats["shell_levels"]``).  Measured on the neural bunny (64x4): ``delta`` 1.09e-3 in field
   units (about 4e-3 scene units at its slope of 0.28), the outer shell's field 3.8e-4 to 1.6e-3.
3. **Local slopes.**  The tracer's steps between the shells are certified by a Lipschitz bound.
   Every SDF here is a distance *bound* (slope <= 1; a neural SDF is divided by its measured
   largest slope), but a neural SDF's slope near its surface is about 0.3, so steps bounded by 1
   are three times too short.  Per cell of :data:`LIPSCHITZ_CELL` fine steps:
   :data:`LIPSCHITZ_MARGIN` x the largest central-difference slope among the evaluated fine
   samples of the cell and its 26 neighbours, at most 1; 1 where none was evaluated.  Measured on
   the neural bunny: the exact slope (central differences of 1e-5) at 220k random points near the
   surface stays below 0.86x the table.

The band is deterministic in the SDF and the settings (:data:`BAND_RULE` names them for cache keys).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Band", "build_band", "BAND_RULE", "LIPSCHITZ_MARGIN", "LIPSCHITZ_CELL"]

BAND_RULE = "band-v1"
LIPSCHITZ_MARGIN = 1.5  # the slope table's factor over the finite-difference slopes it saw
LIPSCHITZ_CELL = 4  # fine steps per cell of the slope table
_ERROR_PROBES = 50_000  # random points measuring the interpolation error (and the shells' levels)
_HIT_THRESHOLD = 2e-4  # the sphere tracer's eps * (1 + t) at t = 1 (eps = 1e-4)


@dataclass
class Band:
    """Two shells bracketing an SDF's zero set and a table of local slope bounds.

    Attributes
    ----------
    inner, outer : tuple of (V, 3) float32 and (F, 3) int32 ndarrays
        Vertices and faces of the marching-cubes surfaces at ``-delta`` and ``+delta``, wound so
        their normals point out of the solid.
    delta : float
        The shells' field level (field units).
    slopes : (cx, cy, cz) float32 ndarray
        An upper bound of ``|grad f|`` within each cell of the table (<= 1).
    slopes_origin : (3,) float64 ndarray
        Scene position of the corner of cell ``(0, 0, 0)``.
    cell : float
        Cell size of the table (scene units).
    stats : dict
        What the build measured and cost (for logs and benchmarks).
    """

    inner: tuple
    outer: tuple
    delta: float
    slopes: np.ndarray
    slopes_origin: np.ndarray
    cell: float
    stats: dict = field(default_factory=dict)

    def slope_at(self, points: np.ndarray) -> np.ndarray:
        """Slope bound (N,) float32 at points (N, 3): the table's cell, 1 outside the table."""
        idx = np.floor((np.asarray(points, dtype=np.float64) - self.slopes_origin) / self.cell).astype(np.int64)
        shape = np.asarray(self.slopes.shape)
        inside = ((idx >= 0) & (idx < shape)).all(axis=1)
        out = np.ones(len(idx), dtype=np.float32)
        i = idx[inside]
        out[inside] = self.slopes[i[:, 0], i[:, 1], i[:, 2]]
        return out


def _nearest_fill(values: np.ndarray, factor: int) -> np.ndarray:
    """A grid ``factor`` times finer whose every sample holds the value of a corner of its coarse cell:
    exact at the coarse samples, and beyond any level that the coarse corners all lie beyond."""
    fine = values
    for axis in range(3):
        fine = np.repeat(fine, factor, axis=axis)
    n = values.shape
    return np.ascontiguousarray(fine[: factor * (n[0] - 1) + 1, : factor * (n[1] - 1) + 1, : factor * (n[2] - 1) + 1])


def _cell_points(cells: np.ndarray, factor: int) -> np.ndarray:
    """Fine-grid mask of the samples in or on the marked coarse cells (separable: one axis at a time)."""
    mask = cells
    for axis in range(3):
        up = np.repeat(mask, factor, axis=axis)  # fine cell -> its coarse cell
        shape = list(up.shape)
        shape[axis] += 1
        points = np.zeros(shape, dtype=bool)
        lead = [slice(None)] * 3
        lead[axis] = slice(0, -1)
        points[tuple(lead)] |= up  # a fine sample belongs to the fine cells on both sides of it
        lead[axis] = slice(1, None)
        points[tuple(lead)] |= up
        mask = points
    return mask


def _slope_magnitude(values: np.ndarray, h: float) -> np.ndarray:
    """Finite-difference slope ``|grad f|`` of a grid (central inside, one-sided at the border)."""
    g = np.gradient(values, h)
    return np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).astype(np.float32)


def _shell(values: np.ndarray, level: float, origin: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface of ``values == level``: vertices (V, 3) float32 and faces (F, 3) int32,
    wound so the face normals point to larger values (out of the solid)."""
    from skimage.measure import marching_cubes

    if not (values.min() < level < values.max()):
        return np.zeros((0, 3), dtype=np.float32), np.zeros((0, 3), dtype=np.int32)
    verts, faces, _, _ = marching_cubes(values, level=level, spacing=(h, h, h))
    verts = (verts + origin).astype(np.float32)
    tri = verts[faces].astype(np.float64)
    # outward: skimage's winding is checked, not assumed (the signed volume of the closed surface decides)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if np.einsum("ij,ij->", cross, tri[:, 0]) < 0.0:
        faces = faces[:, ::-1]
    return verts, np.ascontiguousarray(faces, dtype=np.int32)


def build_band(sdf, *, resolution: int = 128, refine: int = 2, threads: int | None = None, seed: int = 0) -> Band:
    """The :class:`Band` of an SDF (see the module docstring for each step).

    Parameters
    ----------
    sdf : prt.train.sdf.SDF
    resolution : int
        The coarse grid (:meth:`SDF.grid`).
    refine : int
        Fine steps per coarse step in the cells near the surface.
    threads : int, optional
        Worker threads of the field evaluations (default: all cores).
    seed : int
        The interpolation-error probes' random points.

    Returns
    -------
    Band
    """
    t0 = time.perf_counter()
    coarse = sdf.grid(resolution, threads)
    seconds = {"grid_s": time.perf_counter() - t0}
    values, origin, h = coarse.values, np.asarray(coarse.origin, dtype=np.float64), float(coarse.spacing)
    hf = h / refine
    slope = _slope_magnitude(values, h)[np.abs(values) < h]
    if slope.size == 0:  # no surface the grid can see: empty shells, every slope the global bound
        empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
        return Band(empty, empty, 0.0,
                    np.ones((1, 1, 1), np.float32), origin, 1.0, {"rule": BAND_RULE, "empty": True})  # fmt: skip
    s_med = float(np.median(slope))
    delta_thin = 0.5 * s_med * hf

    # 1. the cells the band may cross: where the coarse corners come within 1.5x (delta + the coarse
    # grid's own interpolation error, measured) of 0, or half a cell diagonal at the median slope
    rng = np.random.default_rng(seed)
    surface = np.argwhere(_cells_within(values, 0.0))
    coarse_error = _interpolation_error(sdf, values, origin, h, surface, 1, rng, threads)
    reach = max(1.5 * (delta_thin + coarse_error), s_med * h * np.sqrt(3.0) / 2.0)
    active = _cells_within(values, reach)
    box = np.argwhere(active)
    lo_c, hi_c = box.min(axis=0), box.max(axis=0) + 2  # coarse samples of the active cells' box
    crop = tuple(slice(a, b) for a, b in zip(lo_c, hi_c))
    active = active[tuple(slice(a, b - 1) for a, b in zip(lo_c, hi_c))]
    sub_origin = origin + h * lo_c
    fine = _nearest_fill(values[crop], refine)
    evaluated = _cell_points(active, refine)
    todo = evaluated.copy()
    todo[::refine, ::refine, ::refine] = False  # the coarse samples are exact already
    index = np.argwhere(todo)
    fine[todo] = _evaluate(sdf, (sub_origin + hf * index).astype(np.float32), threads)
    del todo
    seconds["refine_s"] = time.perf_counter() - t0 - seconds["grid_s"]

    # 2. the fine grid's interpolation error, at random points of the coarse cells the surface crosses
    error = _interpolation_error(sdf, fine, sub_origin, hf, surface - lo_c, refine, rng, threads)
    delta = max(delta_thin, 1.25 * error + _HIT_THRESHOLD)

    # 3. the shells, and the field at random points of each
    inner = _shell(fine, -delta, sub_origin, hf)
    outer = _shell(fine, delta, sub_origin, hf)
    levels = {}
    for name, (verts, faces) in (("inner", inner), ("outer", outer)):
        tri = verts[faces]
        if len(tri):
            w = rng.dirichlet((1.0, 1.0, 1.0), min(_ERROR_PROBES, len(tri)))
            at = np.einsum("fk,fkj->fj", w, tri[rng.integers(0, len(tri), len(w))])
            f = _evaluate(sdf, at.astype(np.float32), threads)
            levels[name] = [float(f.min()), float(f.max())]
    seconds["shells_s"] = time.perf_counter() - t0 - seconds["grid_s"] - seconds["refine_s"]

    # 4. local slope bounds from the evaluated fine samples
    slopes, cell = _slope_table(fine, evaluated, hf)
    stats = {
        "rule": BAND_RULE,
        "resolution": int(resolution),
        "refine": int(refine),
        "fine_step": hf,
        "active_cells": int(active.sum()),
        "evaluated_points": int(len(index)),
        "slope_median": s_med,
        "slope_max": float(slope.max()),
        "coarse_interpolation_error": coarse_error,
        "interpolation_error": error,
        "delta": delta,
        "inner_faces": int(len(inner[1])),
        "outer_faces": int(len(outer[1])),
        "shell_levels": levels,  # the field at random points of each shell: [min, max]
        "slope_table_median": float(np.median(slopes[slopes < 1.0])) if (slopes < 1.0).any() else 1.0,
        **{k: round(v, 3) for k, v in seconds.items()},
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return Band(inner, outer, float(delta), slopes, sub_origin, cell, stats)


def _cells_within(values: np.ndarray, reach: float) -> np.ndarray:
    """Cells (nx-1, ny-1, nz-1) bool whose corner values come within ``reach`` of 0 (or straddle it)."""
    n = values.shape
    low = np.full((n[0] - 1, n[1] - 1, n[2] - 1), np.inf, dtype=np.float32)
    high = np.full_like(low, -np.inf)
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                corner = values[i : i + n[0] - 1, j : j + n[1] - 1, k : k + n[2] - 1]
                np.minimum(low, corner, out=low)
                np.maximum(high, corner, out=high)
    return (low <= reach) & (high >= -reach)


def _interpolation_error(sdf, values, origin, h, cells, factor, rng, threads) -> float:
    """Largest |f - trilinear interpolation of ``values``| at random points of the given coarse
    ``cells`` (N, 3) int; ``values`` is ``factor`` times finer than they are."""
    if len(cells) == 0:
        return 0.0
    pick = cells[rng.integers(0, len(cells), min(_ERROR_PROBES, len(cells)))]
    at = factor * (pick + rng.random((len(pick), 3)))  # in fine steps
    fine_cell = np.minimum(np.floor(at).astype(np.int64), np.asarray(values.shape) - 2)
    exact = _evaluate(sdf, (origin + h * at).astype(np.float32), threads)
    return float(np.abs(exact - _trilinear(values, fine_cell, at - fine_cell)).max())


def _trilinear(values: np.ndarray, cells: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of a grid at ``cells + frac`` (cells (N, 3) int, frac (N, 3) in [0, 1))."""
    out = np.zeros(len(cells))
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                w = (frac[:, 0] if i else 1 - frac[:, 0]) * (frac[:, 1] if j else 1 - frac[:, 1]) * (frac[:, 2] if k else 1 - frac[:, 2])
                out += w * values[cells[:, 0] + i, cells[:, 1] + j, cells[:, 2] + k]
    return out


def _slope_table(values: np.ndarray, evaluated: np.ndarray, h: float):
    """Per cell of LIPSCHITZ_CELL steps: LIPSCHITZ_MARGIN x the largest central-difference slope
    among the evaluated samples of the cell and its 26 neighbours (a sample counts where its six
    neighbours were evaluated too), at most 1; 1 where no such sample is near."""
    from scipy.ndimage import maximum_filter

    c = LIPSCHITZ_CELL
    inner = evaluated[1:-1, 1:-1, 1:-1].copy()
    for axis in range(3):  # central differences read both neighbours along every axis
        for shift in (0, 2):
            index = [slice(1, -1)] * 3
            index[axis] = slice(shift, shift + evaluated.shape[axis] - 2)
            inner &= evaluated[tuple(index)]
    idx = np.argwhere(inner) + 1
    g2 = np.zeros(len(idx))
    for axis in range(3):
        up, down = idx.copy(), idx.copy()
        up[:, axis] += 1
        down[:, axis] -= 1
        d = (values[up[:, 0], up[:, 1], up[:, 2]].astype(np.float64) - values[down[:, 0], down[:, 1], down[:, 2]]) / (2.0 * h)
        g2 += d * d
    shape = tuple((n - 1) // c + 1 for n in values.shape)
    cell_max = np.zeros(shape, dtype=np.float32)
    cells = idx // c
    np.maximum.at(cell_max, (cells[:, 0], cells[:, 1], cells[:, 2]), np.sqrt(g2).astype(np.float32))
    seen = np.zeros(shape, dtype=bool)
    seen[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    bound = np.minimum(LIPSCHITZ_MARGIN * maximum_filter(cell_max, size=3, mode="nearest"), 1.0)
    near = maximum_filter(seen, size=3, mode="constant", cval=False)
    return np.where(near, bound, 1.0).astype(np.float32), c * h


def _evaluate(sdf, points: np.ndarray, threads: int | None) -> np.ndarray:
    """The field at (N, 3) float32 points, in chunks over worker threads."""
    from ..executor import LocalExecutor

    chunk = 1 << 16
    out = np.empty(len(points), dtype=np.float32)
    parts = [(s, points[s : s + chunk]) for s in range(0, len(points), chunk)]
    for (s, _), f in LocalExecutor(threads).map(_evaluate_part, sdf, parts):
        out[s : s + len(f)] = f
    return out


def _evaluate_part(sdf, part) -> np.ndarray:
    return sdf.evaluate(part[1])
