"""The SDF expression tree's base class, its argument checks and the exact culling it uses.

Every node evaluates itself with numpy and emits the equivalent GLSL (see
:class:`~prt.train.sdf.glsl.GLSLWriter`), so the precompute and the renderer agree by
construction.  Every node is a distance *bound*: Lipschitz constant <= 1, so it never
overestimates the distance to the surface and sphere tracing never steps through it.
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np

from .glsl import GLSLWriter

__all__ = ["Node", "as_points", "as_positive", "as_vec3", "box_union", "columns", "fold"]

# Children cheaper than this (in spheres per point) are evaluated everywhere, not culled.
_CULL_MIN_COST = 3.0


# --------------------------------------------------------------------------------------
# Argument checks and array helpers shared by the node modules
# --------------------------------------------------------------------------------------


def as_vec3(value, what: str) -> tuple[float, float, float]:
    """Return ``value`` as a tuple of three finite floats, or raise ValueError naming it."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def as_positive(value, what: str, allow_zero: bool = False) -> float:
    """Return ``value`` as a float that is > 0 (or >= 0), or raise ValueError naming it."""
    v = float(value)
    if not math.isfinite(v) or v < 0.0 or (v == 0.0 and not allow_zero):
        raise ValueError(f"{what} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return v


def as_points(points, what: str = "points") -> np.ndarray:
    """Return ``points`` as an (N, 3) float32 or float64 array (other dtypes -> float64)."""
    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what} must have shape (N, 3), got {p.shape}")
    return p


def columns(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split (N, 3) points into three contiguous (N,) arrays (elementwise ops run faster)."""
    return tuple(np.ascontiguousarray(p[:, i]) for i in range(3))


def box_union(boxes: list[np.ndarray]) -> np.ndarray:
    """Smallest AABB ((2, 3) ndarray) containing every AABB in ``boxes``."""
    stacked = np.stack(boxes)
    return np.stack([stacked[:, 0].min(axis=0), stacked[:, 1].max(axis=0)])


# --------------------------------------------------------------------------------------
# The node protocol
# --------------------------------------------------------------------------------------


class Node:
    """Base class of the SDF expression tree.

    Subclasses implement these, which must agree with each other:

    - ``_eval(x, y, z)``: numpy distances from three (N,) coordinate arrays of one float
      dtype, returning a new (N,) array of that dtype (constants are Python floats or
      arrays cast to it, so float32 stays float32).
    - ``emit_glsl(writer, p)``: append GLSL statements computing the distance at the
      ``vec3`` variable named ``p`` and return the name of the ``float`` holding it.
    - ``bounds(level)``: a (2, 3) AABB ``[min, max]`` containing ``{p : f(p) <= level}``.
    - ``_cull_bound()``: ``(box, slack)``, a (2, 3) AABB and a float such that
      ``f(p) >= dist(p, box) - slack`` everywhere (slack covers the interior, where f < 0).
      Combinators use it to skip costly children at points where they cannot matter.
    - ``cost``: rough numpy work per point in units of one sphere; only children costing
      at least ``_CULL_MIN_COST`` are worth the culling test.
    """

    cost: float = 1.0

    def eval_np(self, p: np.ndarray) -> np.ndarray:
        """Evaluate the distance at points.

        Parameters
        ----------
        p : (N, 3) float32 or float64 ndarray
            Query points.

        Returns
        -------
        (N,) ndarray of ``p.dtype``
            Signed distance bounds (negative inside).
        """
        p = as_points(p)
        return self._eval(*columns(p))

    def _eval(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def emit_glsl(self, w: GLSLWriter, p: str) -> str:
        """Emit GLSL for the distance at ``vec3 p``; return the result variable's name."""
        raise NotImplementedError

    def bounds(self, level: float = 0.0) -> np.ndarray:
        """(2, 3) AABB containing every point where the distance is <= ``level`` (>= 0)."""
        raise NotImplementedError

    def _cull_bound(self) -> tuple[np.ndarray, float]:
        raise NotImplementedError

    @cached_property
    def cull_bound(self) -> tuple[tuple[tuple[float, ...], tuple[float, ...]], float]:
        """Cached :meth:`_cull_bound` as Python floats (so float32 math stays float32)."""
        box, slack = self._cull_bound()
        return (tuple(map(float, box[0])), tuple(map(float, box[1]))), float(slack)


# --------------------------------------------------------------------------------------
# Exact culling of costly children
# --------------------------------------------------------------------------------------


def _candidates(node: Node, x, y, z, limit) -> np.ndarray | None:
    """Indices of points where ``node`` may be below ``limit`` ((N,) per point).

    Returns None when culling does not pay for ``node`` (every point is a candidate).
    Skipped points provably have ``f >= dist(p, box) - slack >= limit``.
    """
    if node.cost < _CULL_MIN_COST:
        return None
    (lo, hi), slack = node.cull_bound
    gap2 = None
    for c, l, h in zip((x, y, z), lo, hi):
        g = np.maximum(l - c, c - h)
        np.maximum(g, 0.0, out=g)
        g *= g
        gap2 = g if gap2 is None else np.add(gap2, g, out=gap2)
    reach = limit + slack
    return np.flatnonzero((reach > 0.0) & (gap2 < reach * reach))


def fold(d: np.ndarray, child: Node, x, y, z, limit, combine) -> np.ndarray:
    """``combine(d, child)`` where the child may be below ``limit``; ``d`` elsewhere.

    ``combine`` must return its first argument unchanged wherever the child is >= limit,
    which makes the culling exact.  ``d`` may be updated in place.
    """
    idx = _candidates(child, x, y, z, limit)
    if idx is None or idx.size == len(d):
        return combine(d, child._eval(x, y, z))
    if idx.size:
        d[idx] = combine(d[idx], child._eval(x[idx], y[idx], z[idx]))
    return d
