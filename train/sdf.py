"""Analytic signed distance field (SDF) scenes, each defined once for numpy and GLSL.

A scene is a small expression tree of node objects: primitives (:class:`Sphere`,
:class:`Box`, :class:`Torus`, :class:`Capsule`, :class:`Polyline`), combinators
(:class:`Union`, :class:`SmoothUnion`, :class:`Intersection`, :class:`Subtraction`,
:class:`SmoothSubtraction`) and transforms (:class:`Translate`, :class:`Rotate`,
:class:`Scale`, :class:`MirrorX`).  Every node evaluates itself with numpy and emits the
equivalent GLSL, so the precompute (numpy) and the renderer (GLSL sphere tracing) agree
by construction.  :class:`SDF` wraps a root node with the operations the precompute needs:
evaluation, gradients, meshing, projection onto the surface and batched sphere tracing.

Conventions: scene space is the box ``[-1, 1]^3`` centred at the origin, +Y up; distances
are negative inside.  Every node is a distance *bound*: Lipschitz constant <= 1, so it
never overestimates the distance to the surface and sphere tracing never steps through it.

The library scenes live in :data:`SDF_SCENES`; look them up with :func:`get_sdf`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from string import Template

import numpy as np

from ..runtime.errors import GeometryError

__all__ = [
    "Node",
    "Sphere",
    "Box",
    "Torus",
    "Capsule",
    "Polyline",
    "Union",
    "SmoothUnion",
    "Intersection",
    "Subtraction",
    "SmoothSubtraction",
    "Translate",
    "Rotate",
    "Scale",
    "MirrorX",
    "GLSLWriter",
    "SDF",
    "SDF_SCENES",
    "get_sdf",
    "sdf_names",
    "torus_knot_curve",
]

# Elements per (segments, points) temporary when broadcasting points against segments.
_BLOCK_ELEMENTS = 1 << 18
# Points per batch of finite-difference taps in SDF.gradient.
_GRADIENT_CHUNK = 1 << 17


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------


def _vec3(value, what: str) -> tuple[float, float, float]:
    """Return ``value`` as a tuple of three finite floats, or raise ValueError naming it."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def _positive(value, what: str, allow_zero: bool = False) -> float:
    """Return ``value`` as a float that is > 0 (or >= 0), or raise ValueError naming it."""
    v = float(value)
    if not math.isfinite(v) or v < 0.0 or (v == 0.0 and not allow_zero):
        raise ValueError(f"{what} must be {'>= 0' if allow_zero else '> 0'}, got {value!r}")
    return v


def _glsl_float(x: float) -> str:
    """Format a float as a GLSL literal; ``repr`` round-trips, so numpy and GLSL agree."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot write non-finite constant {x!r} to GLSL")
    return repr(x)


def _glsl_vec3(v) -> str:
    """Format three floats as a GLSL ``vec3`` constructor."""
    return "vec3({}, {}, {})".format(*(_glsl_float(c) for c in v))


def _box_union(boxes: list[np.ndarray]) -> np.ndarray:
    """Smallest AABB ((2, 3) ndarray) containing every AABB in ``boxes``."""
    stacked = np.stack(boxes)
    return np.stack([stacked[:, 0].min(axis=0), stacked[:, 1].max(axis=0)])


def _as_points(points, what: str = "points") -> np.ndarray:
    """Return ``points`` as an (N, 3) float32 or float64 array (other dtypes -> float64)."""
    p = np.asarray(points)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what} must have shape (N, 3), got {p.shape}")
    return p


def _columns(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split (N, 3) points into three contiguous (N,) arrays (elementwise ops run faster)."""
    return tuple(np.ascontiguousarray(p[:, i]) for i in range(3))


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum; matches the GLSL helper ``*_smin`` term for term.

    Written as ``b (1 - h) + a h`` so that it returns exactly ``a`` once ``b >= a + k``.
    """
    h = np.clip(0.5 + (b - a) * (0.5 / k), 0.0, 1.0)
    return b * (1.0 - h) + a * h - k * h * (1.0 - h)


def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth maximum; matches the GLSL helper ``*_smax`` term for term.

    Returns exactly ``a`` once ``b <= a - k``.
    """
    h = np.clip(0.5 - (b - a) * (0.5 / k), 0.0, 1.0)
    return b * (1.0 - h) + a * h + k * h * (1.0 - h)


# GLSL helpers, instantiated with a prefixed name ($fn) so several scenes can share a shader.
_GLSL_HELPERS = {
    "box": (
        "float $fn(vec3 p, vec3 inner, float r) {\n"
        "    vec3 q = abs(p) - inner;\n"
        "    return length(max(q, 0.0)) + min(max(q.x, max(q.y, q.z)), 0.0) - r;\n"
        "}\n"
    ),
    "torus": (
        "float $fn(vec3 p, vec3 axis, float major, float minor) {\n"
        "    float h = dot(p, axis);\n"
        "    return length(vec2(length(p - h * axis) - major, h)) - minor;\n"
        "}\n"
    ),
    "capsule": (
        "float $fn(vec3 p, vec3 a, vec3 ba, float inv_baba, float r) {\n"
        "    vec3 pa = p - a;\n"
        "    float h = clamp(dot(pa, ba) * inv_baba, 0.0, 1.0);\n"
        "    return length(pa - ba * h) - r;\n"
        "}\n"
    ),
    "smin": (
        "float $fn(float a, float b, float k) {\n"
        "    float h = clamp(0.5 + (b - a) * (0.5 / k), 0.0, 1.0);\n"
        "    return b * (1.0 - h) + a * h - k * h * (1.0 - h);\n"
        "}\n"
    ),
    "smax": (
        "float $fn(float a, float b, float k) {\n"
        "    float h = clamp(0.5 - (b - a) * (0.5 / k), 0.0, 1.0);\n"
        "    return b * (1.0 - h) + a * h + k * h * (1.0 - h);\n"
        "}\n"
    ),
}


class GLSLWriter:
    """Collects the statements and helper functions of one generated GLSL SDF function.

    Nodes call :meth:`let` to append ``type name = expr;`` statements to the function body
    and :meth:`helper` / :meth:`add_helper` to declare helper functions (emitted once each,
    named ``<prefix>_<key>`` so they do not clash with other code in the shader).

    Parameters
    ----------
    prefix : str
        Prefix of every helper name (the scene function's name).
    """

    def __init__(self, prefix: str):
        self.prefix = prefix
        self.helpers: dict[str, str] = {}
        self.body: list[str] = []
        self._count = 0

    def let(self, glsl_type: str, expr: str, stem: str = "d") -> str:
        """Append ``glsl_type <new name> = expr;`` to the body and return the new name."""
        self._count += 1
        name = f"{stem}{self._count}"
        self.body.append(f"    {glsl_type} {name} = {expr};")
        return name

    def helper(self, key: str) -> str:
        """Declare the standard helper ``key`` (box, torus, capsule, smin, smax); return its name."""
        return self.add_helper(key, _GLSL_HELPERS[key])

    def add_helper(self, key: str, template: str) -> str:
        """Declare a helper from a template whose ``$fn`` is its name; return that name."""
        name = f"{self.prefix}_{key}"
        if key not in self.helpers:
            self.helpers[key] = Template(template).substitute(fn=name)
        return name

    def unique_key(self, stem: str) -> str:
        """A helper key not used yet, for helpers specific to one node (e.g. a polyline)."""
        i = 0
        while f"{stem}{i}" in self.helpers:
            i += 1
        return f"{stem}{i}"


# --------------------------------------------------------------------------------------
# Nodes
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
        p = _as_points(p)
        return self._eval(*_columns(p))

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


_CULL_MIN_COST = 3.0


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


def _fold(d: np.ndarray, child: Node, x, y, z, limit, combine) -> np.ndarray:
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


# ----- primitives (exact Euclidean distances) ---------------------------------------


@dataclass(frozen=True, eq=False)
class Sphere(Node):
    """Sphere of ``radius`` around ``center``."""

    center: tuple[float, float, float]
    radius: float
    cost = 1.0

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "Sphere.center"))
        object.__setattr__(self, "radius", _positive(self.radius, "Sphere.radius"))

    def _eval(self, x, y, z):
        cx, cy, cz = self.center
        dx, dy, dz = x - cx, y - cy, z - cz
        return np.sqrt(dx * dx + dy * dy + dz * dz) - self.radius

    def emit_glsl(self, w, p):
        return w.let("float", f"length({p} - {_glsl_vec3(self.center)}) - {_glsl_float(self.radius)}")

    def bounds(self, level=0.0):
        c, r = np.array(self.center), self.radius + level
        return np.stack([c - r, c + r])

    def _cull_bound(self):
        c = np.array(self.center)
        return np.stack([c, c]), self.radius


@dataclass(frozen=True, eq=False)
class Box(Node):
    """Axis-aligned box with rounded edges.

    ``half_size`` includes the rounding: the box spans ``center +- half_size`` and its edges
    are rounded with radius ``rounding`` (0 gives sharp edges).
    """

    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    rounding: float = 0.0
    cost = 2.0

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "Box.center"))
        half = _vec3(self.half_size, "Box.half_size")
        if min(half) <= 0.0:
            raise ValueError(f"Box.half_size must be > 0, got {half}")
        rounding = _positive(self.rounding, "Box.rounding", allow_zero=True)
        if rounding > min(half):
            raise ValueError(f"Box.rounding {rounding} exceeds the smallest half size {min(half)}")
        object.__setattr__(self, "half_size", half)
        object.__setattr__(self, "rounding", rounding)

    @property
    def _inner(self) -> tuple[float, float, float]:
        """Half size of the core box that the rounding inflates."""
        return tuple(h - self.rounding for h in self.half_size)

    def _eval(self, x, y, z):
        cx, cy, cz = self.center
        ix, iy, iz = self._inner
        qx, qy, qz = np.abs(x - cx) - ix, np.abs(y - cy) - iy, np.abs(z - cz) - iz
        ox, oy, oz = np.maximum(qx, 0.0), np.maximum(qy, 0.0), np.maximum(qz, 0.0)
        outside = np.sqrt(ox * ox + oy * oy + oz * oz)
        inside = np.minimum(np.maximum(qx, np.maximum(qy, qz)), 0.0)
        return outside + inside - self.rounding

    def emit_glsl(self, w, p):
        fn = w.helper("box")
        args = f"{p} - {_glsl_vec3(self.center)}, {_glsl_vec3(self._inner)}, {_glsl_float(self.rounding)}"
        return w.let("float", f"{fn}({args})")

    def bounds(self, level=0.0):
        c, h = np.array(self.center), np.array(self.half_size) + level
        return np.stack([c - h, c + h])

    def _cull_bound(self):
        # Outside, f >= distance to the box; inside, f >= -(smallest half size).
        return self.bounds(0.0), min(self.half_size)


@dataclass(frozen=True, eq=False)
class Torus(Node):
    """Torus around ``center``: a tube of radius ``minor`` around a circle of radius ``major``.

    ``axis`` is the normal of the circle's plane (normalised here); (0, 1, 0) lays it flat.
    """

    center: tuple[float, float, float]
    major: float
    minor: float
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    cost = 2.0

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "Torus.center"))
        object.__setattr__(self, "major", _positive(self.major, "Torus.major"))
        object.__setattr__(self, "minor", _positive(self.minor, "Torus.minor"))
        axis = np.array(_vec3(self.axis, "Torus.axis"))
        if np.linalg.norm(axis) == 0.0:
            raise ValueError("Torus.axis must be non-zero")
        object.__setattr__(self, "axis", tuple(float(a) for a in axis / np.linalg.norm(axis)))

    def _eval(self, x, y, z):
        cx, cy, cz = self.center
        ax, ay, az = self.axis
        dx, dy, dz = x - cx, y - cy, z - cz
        h = dx * ax + dy * ay + dz * az
        rx, ry, rz = dx - h * ax, dy - h * ay, dz - h * az
        ring = np.sqrt(rx * rx + ry * ry + rz * rz) - self.major
        return np.sqrt(ring * ring + h * h) - self.minor

    def emit_glsl(self, w, p):
        fn = w.helper("torus")
        args = (
            f"{p} - {_glsl_vec3(self.center)}, {_glsl_vec3(self.axis)}, "
            f"{_glsl_float(self.major)}, {_glsl_float(self.minor)}"
        )
        return w.let("float", f"{fn}({args})")

    def bounds(self, level=0.0):
        return self._ring_box(self.minor + level)

    def _ring_box(self, pad: float) -> np.ndarray:
        # A circle with unit normal a extends major * sqrt(1 - a_i^2) along axis i.
        a = np.array(self.axis)
        half = self.major * np.sqrt(np.clip(1.0 - a * a, 0.0, 1.0)) + pad
        c = np.array(self.center)
        return np.stack([c - half, c + half])

    def _cull_bound(self):
        # f is the distance to the core circle minus the minor radius.
        return self._ring_box(0.0), self.minor


@dataclass(frozen=True, eq=False)
class Capsule(Node):
    """Segment from ``a`` to ``b`` inflated by ``radius`` (a sphere when a == b)."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float
    cost = 2.0

    def __post_init__(self):
        object.__setattr__(self, "a", _vec3(self.a, "Capsule.a"))
        object.__setattr__(self, "b", _vec3(self.b, "Capsule.b"))
        object.__setattr__(self, "radius", _positive(self.radius, "Capsule.radius"))

    @property
    def _segment(self) -> tuple[tuple[float, float, float], float]:
        """``b - a`` and ``1 / |b - a|^2`` (0 for a degenerate segment, giving a sphere)."""
        ba = tuple(bi - ai for ai, bi in zip(self.a, self.b))
        baba = sum(c * c for c in ba)
        return ba, (1.0 / baba if baba > 0.0 else 0.0)

    def _eval(self, x, y, z):
        (bax, bay, baz), inv_baba = self._segment
        pax, pay, paz = x - self.a[0], y - self.a[1], z - self.a[2]
        h = np.clip((pax * bax + pay * bay + paz * baz) * inv_baba, 0.0, 1.0)
        ex, ey, ez = pax - bax * h, pay - bay * h, paz - baz * h
        return np.sqrt(ex * ex + ey * ey + ez * ez) - self.radius

    def emit_glsl(self, w, p):
        fn = w.helper("capsule")
        ba, inv_baba = self._segment
        args = (
            f"{p}, {_glsl_vec3(self.a)}, {_glsl_vec3(ba)}, "
            f"{_glsl_float(inv_baba)}, {_glsl_float(self.radius)}"
        )
        return w.let("float", f"{fn}({args})")

    def bounds(self, level=0.0):
        ends = np.array([self.a, self.b])
        r = self.radius + level
        return np.stack([ends.min(axis=0) - r, ends.max(axis=0) + r])

    def _cull_bound(self):
        ends = np.array([self.a, self.b])
        return np.stack([ends.min(axis=0), ends.max(axis=0)]), self.radius


def _segments_d2(x, y, z, a, ba, inv_baba) -> np.ndarray:
    """Squared distance from points to the nearest of M segments.

    Parameters
    ----------
    x, y, z : (N,) ndarray
        Point coordinates.
    a, ba : (M, 3) ndarray
        Segment starts and ``end - start``, in the points' dtype.
    inv_baba : (M,) ndarray
        ``1 / |end - start|^2``.

    Returns
    -------
    (N,) ndarray
    """
    out = np.empty_like(x)
    # (M, n) temporaries: long contiguous rows are ~3x faster than (n, M) with small M.
    ax, ay, az = (a[:, i, None] for i in range(3))
    bx, by, bz = (ba[:, i, None] for i in range(3))
    inv = inv_baba[:, None]
    block = max(1, _BLOCK_ELEMENTS // len(a))
    for s in range(0, len(x), block):
        sl = slice(s, s + block)
        pax = x[sl] - ax
        pay = y[sl] - ay
        paz = z[sl] - az
        h = pax * bx
        h += pay * by
        h += paz * bz
        h *= inv
        np.clip(h, 0.0, 1.0, out=h)
        # In place: these temporaries dominate the cost.
        pax -= bx * h
        pay -= by * h
        paz -= bz * h
        pax *= pax
        pay *= pay
        paz *= paz
        pax += pay
        pax += paz
        pax.min(axis=0, out=out[sl])
    return out


@dataclass(frozen=True, eq=False)
class Polyline(Node):
    """Tube of constant ``radius`` along a polyline: the union of its segments' capsules.

    numpy broadcasts points against segments and takes one square root per point; long
    polylines are split into clusters of consecutive segments, and a cluster is skipped
    at points where it provably cannot hold the nearest segment (exact, not approximate).
    GLSL loops over a constant array of all segments.

    Parameters
    ----------
    points : (M, 3) array_like
        Polyline vertices (M >= 2).
    radius : float
        Tube radius.
    closed : bool
        Also join the last vertex to the first.
    """

    points: tuple[tuple[float, float, float], ...]
    radius: float
    closed: bool = False
    _a: np.ndarray = field(init=False, repr=False)
    _ba: np.ndarray = field(init=False, repr=False)
    _inv_baba: np.ndarray = field(init=False, repr=False)

    #: Segments per cluster; polylines shorter than three clusters are not split.
    CLUSTER = 8

    def __post_init__(self):
        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.all(np.isfinite(pts)):
            raise ValueError(f"Polyline.points must be (M >= 2, 3) finite numbers, got shape {pts.shape}")
        object.__setattr__(self, "points", tuple(tuple(float(c) for c in row) for row in pts))
        object.__setattr__(self, "radius", _positive(self.radius, "Polyline.radius"))
        a = pts if self.closed else pts[:-1]
        ba = (np.roll(pts, -1, axis=0) if self.closed else pts[1:]) - a
        baba = np.einsum("ij,ij->i", ba, ba)
        keep = baba > 0.0  # zero-length segments add nothing and would divide by zero
        object.__setattr__(self, "_a", a[keep])
        object.__setattr__(self, "_ba", ba[keep])
        object.__setattr__(self, "_inv_baba", 1.0 / baba[keep])

    @cached_property
    def _clusters(self) -> tuple[list[slice], np.ndarray, np.ndarray] | None:
        """``(segment slices, anchors (J, 3), reach (J,))`` or None when not worth it.

        Every point of cluster j lies within ``reach[j]`` of its ``anchors[j]``, a vertex
        of the cluster, so the cluster is at least ``|p - anchor| - reach`` away while the
        centreline is at most ``|p - anchor|`` away.
        """
        m = len(self._a)
        if m < 3 * self.CLUSTER:
            return None
        slices = [slice(s, min(s + self.CLUSTER, m)) for s in range(0, m, self.CLUSTER)]
        anchors, reach = [], []
        for sl in slices:
            verts = np.concatenate([self._a[sl], self._a[sl] + self._ba[sl]])
            anchor = verts[np.argmin(np.linalg.norm(verts - verts.mean(axis=0), axis=1))]
            anchors.append(anchor)
            # Padded so float32 rounding can never drop the nearest cluster.
            reach.append(np.linalg.norm(verts - anchor, axis=1).max() * (1.0 + 1e-5) + 1e-5)
        return slices, np.array(anchors), np.array(reach)

    @property
    def cost(self) -> float:
        m = len(self._a)
        return 1.5 * (m if self._clusters is None else 3 * self.CLUSTER + len(self._clusters[0]))

    def _eval(self, x, y, z):
        dt = x.dtype
        a, ba, inv_baba = self._a.astype(dt), self._ba.astype(dt), self._inv_baba.astype(dt)
        if self._clusters is None:
            d2 = _segments_d2(x, y, z, a, ba, inv_baba)
        else:
            d2 = self._clustered_d2(x, y, z, a, ba, inv_baba)
        return np.sqrt(d2) - self.radius

    def _clustered_d2(self, x, y, z, a, ba, inv_baba) -> np.ndarray:
        """:func:`_segments_d2` visiting, per point, only clusters that may hold the nearest."""
        slices, anchors, reach = self._clusters
        anchors, reach = anchors.astype(x.dtype), reach.astype(x.dtype)
        out = np.empty_like(x)
        block = max(1, _BLOCK_ELEMENTS // len(slices))
        for s in range(0, len(x), block):
            bx, by, bz = x[s : s + block], y[s : s + block], z[s : s + block]
            ex = anchors[:, 0, None] - bx
            ey = anchors[:, 1, None] - by
            ez = anchors[:, 2, None] - bz
            dist = np.sqrt(ex * ex + ey * ey + ez * ez)  # (J, n)
            need = dist - reach[:, None] <= dist.min(axis=0)
            best = np.full(len(bx), np.inf, dtype=x.dtype)
            for sl, rows in zip(slices, need):
                idx = np.flatnonzero(rows)
                if idx.size:
                    d2 = _segments_d2(bx[idx], by[idx], bz[idx], a[sl], ba[sl], inv_baba[sl])
                    best[idx] = np.minimum(best[idx], d2)
            out[s : s + block] = best
        return out

    def emit_glsl(self, w, p):
        key = w.unique_key("polyline")
        n = len(self._a)

        def array(name: str, glsl_type: str, rows) -> str:
            items = ",\n    ".join(rows)
            return f"const {glsl_type} ${{fn}}_{name}[{n}] = {glsl_type}[{n}](\n    {items});\n"

        template = (
            array("a", "vec3", [_glsl_vec3(v) for v in self._a])
            + array("ba", "vec3", [_glsl_vec3(v) for v in self._ba])
            + array("inv_baba", "float", [_glsl_float(v) for v in self._inv_baba])
            + "float $fn(vec3 p) {\n"
            "    float d2 = 3.0e38;\n"
            f"    for (int i = 0; i < {n}; ++i) {{\n"
            "        vec3 pa = p - ${fn}_a[i];\n"
            "        float h = clamp(dot(pa, ${fn}_ba[i]) * ${fn}_inv_baba[i], 0.0, 1.0);\n"
            "        vec3 e = pa - ${fn}_ba[i] * h;\n"
            "        d2 = min(d2, dot(e, e));\n"
            "    }\n"
            f"    return sqrt(d2) - {_glsl_float(self.radius)};\n"
            "}\n"
        )
        fn = w.add_helper(key, template)
        return w.let("float", f"{fn}({p})")

    def bounds(self, level=0.0):
        pts = np.asarray(self.points)
        r = self.radius + level
        return np.stack([pts.min(axis=0) - r, pts.max(axis=0) + r])

    def _cull_bound(self):
        pts = np.asarray(self.points)
        return np.stack([pts.min(axis=0), pts.max(axis=0)]), self.radius


# ----- combinators ---------------------------------------------------------------------


def _check_children(children, what: str) -> tuple[Node, ...]:
    children = tuple(children)
    if not children or not all(isinstance(c, Node) for c in children):
        raise ValueError(f"{what} needs one or more Node children, got {children!r}")
    return children


def _hull_bound(children, extra_slack: float = 0.0) -> tuple[np.ndarray, float]:
    """Cull bound of a min over children: the hull of their boxes, their largest slack."""
    bounds = [c.cull_bound for c in children]
    boxes = [np.array(box) for box, _ in bounds]
    return _box_union(boxes), max(slack for _, slack in bounds) + extra_slack


@dataclass(frozen=True, eq=False)
class Union(Node):
    """Union of ``children``: ``min`` of their distances (exact outside).

    numpy evaluates the cheapest children first (``min`` is exactly order-independent) so
    that costly ones are skipped wherever they cannot be the minimum.
    """

    children: tuple[Node, ...]

    def __post_init__(self):
        object.__setattr__(self, "children", _check_children(self.children, "Union"))

    @property
    def cost(self) -> float:
        return sum(c.cost for c in self.children)

    @cached_property
    def _cheapest_first(self) -> tuple[Node, ...]:
        return tuple(sorted(self.children, key=lambda c: c.cost))

    def _eval(self, x, y, z):
        first, *rest = self._cheapest_first
        d = first._eval(x, y, z)
        for child in rest:
            d = _fold(d, child, x, y, z, d, np.minimum)
        return d

    def emit_glsl(self, w, p):
        d = self.children[0].emit_glsl(w, p)
        for child in self.children[1:]:
            d = w.let("float", f"min({d}, {child.emit_glsl(w, p)})")
        return d

    def bounds(self, level=0.0):
        return _box_union([c.bounds(level) for c in self.children])

    def _cull_bound(self):
        return _hull_bound(self.children)


@dataclass(frozen=True, eq=False)
class SmoothUnion(Node):
    """Union of ``children`` blended over a width ``k`` (polynomial smooth minimum, folded left).

    The blend is Lipschitz 1 (its gradient is a convex combination of the children's) and
    lies at most ``k / 4`` below the plain union per fold; a child at least ``k`` above
    the running result leaves it unchanged, which lets numpy skip it there.
    """

    children: tuple[Node, ...]
    k: float

    def __post_init__(self):
        object.__setattr__(self, "children", _check_children(self.children, "SmoothUnion"))
        object.__setattr__(self, "k", _positive(self.k, "SmoothUnion.k"))

    @property
    def cost(self) -> float:
        return sum(c.cost for c in self.children) + 0.8 * (len(self.children) - 1)

    def _eval(self, x, y, z):
        k = self.k
        d = self.children[0]._eval(x, y, z)
        for child in self.children[1:]:
            d = _fold(d, child, x, y, z, d + k, lambda a, b: _smin(a, b, k))
        return d

    def emit_glsl(self, w, p):
        fn = w.helper("smin")
        d = self.children[0].emit_glsl(w, p)
        for child in self.children[1:]:
            d = w.let("float", f"{fn}({d}, {child.emit_glsl(w, p)}, {_glsl_float(self.k)})")
        return d

    @property
    def _blend_slack(self) -> float:
        """How far the blend can dip below the plain union: k/4 per fold."""
        return (len(self.children) - 1) * self.k / 4.0

    def bounds(self, level=0.0):
        # {f <= level} lies in {min <= level + slack}.
        return _box_union([c.bounds(level + self._blend_slack) for c in self.children])

    def _cull_bound(self):
        return _hull_bound(self.children, self._blend_slack)


@dataclass(frozen=True, eq=False)
class Intersection(Node):
    """Intersection of ``children``: ``max`` of their distances (a bound)."""

    children: tuple[Node, ...]

    def __post_init__(self):
        object.__setattr__(self, "children", _check_children(self.children, "Intersection"))

    @property
    def cost(self) -> float:
        return sum(c.cost for c in self.children)

    def _eval(self, x, y, z):
        d = self.children[0]._eval(x, y, z)
        for child in self.children[1:]:
            d = np.maximum(d, child._eval(x, y, z))
        return d

    def emit_glsl(self, w, p):
        d = self.children[0].emit_glsl(w, p)
        for child in self.children[1:]:
            d = w.let("float", f"max({d}, {child.emit_glsl(w, p)})")
        return d

    def bounds(self, level=0.0):
        boxes = np.stack([c.bounds(level) for c in self.children])
        lo, hi = boxes[:, 0].max(axis=0), boxes[:, 1].min(axis=0)
        return np.stack([lo, np.maximum(hi, lo)])

    def _cull_bound(self):
        # max >= any one child; the first is as good a witness as any.
        box, slack = self.children[0].cull_bound
        return np.array(box), slack


@dataclass(frozen=True, eq=False)
class Subtraction(Node):
    """``base`` with ``cutter`` carved out: ``max(base, -cutter)`` (a bound)."""

    base: Node
    cutter: Node

    @property
    def cost(self) -> float:
        return self.base.cost + self.cutter.cost

    def _eval(self, x, y, z):
        d = self.base._eval(x, y, z)
        # The cutter only matters where -cutter > base, i.e. cutter < -base.
        return _fold(d, self.cutter, x, y, z, -d, lambda a, b: np.maximum(a, -b))

    def emit_glsl(self, w, p):
        a, b = self.base.emit_glsl(w, p), self.cutter.emit_glsl(w, p)
        return w.let("float", f"max({a}, -{b})")

    def bounds(self, level=0.0):
        return self.base.bounds(level)

    def _cull_bound(self):
        box, slack = self.base.cull_bound
        return np.array(box), slack


@dataclass(frozen=True, eq=False)
class SmoothSubtraction(Node):
    """``base`` with ``cutter`` carved out, the cut edge blended over width ``k``."""

    base: Node
    cutter: Node
    k: float

    def __post_init__(self):
        object.__setattr__(self, "k", _positive(self.k, "SmoothSubtraction.k"))

    @property
    def cost(self) -> float:
        return self.base.cost + self.cutter.cost + 0.8

    def _eval(self, x, y, z):
        k = self.k
        d = self.base._eval(x, y, z)
        # smax(base, -cutter) is base wherever -cutter <= base - k, i.e. cutter >= k - base.
        return _fold(d, self.cutter, x, y, z, k - d, lambda a, b: _smax(a, -b, k))

    def emit_glsl(self, w, p):
        fn = w.helper("smax")
        a, b = self.base.emit_glsl(w, p), self.cutter.emit_glsl(w, p)
        return w.let("float", f"{fn}({a}, -{b}, {_glsl_float(self.k)})")

    def bounds(self, level=0.0):
        # smax(a, -b) >= a, so the result lies inside base.
        return self.base.bounds(level)

    def _cull_bound(self):
        box, slack = self.base.cull_bound
        return np.array(box), slack


# ----- transforms ----------------------------------------------------------------------


def _rotated_box(box: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """AABB (2, 3) of the AABB ``box`` (2, 3) rotated by ``matrix`` (3, 3)."""
    lo, hi = box
    corners = np.array([[(lo, hi)[(i >> k) & 1][k] for k in range(3)] for i in range(8)])
    moved = corners @ matrix.T
    return np.stack([moved.min(axis=0), moved.max(axis=0)])


@dataclass(frozen=True, eq=False)
class Translate(Node):
    """``child`` moved by ``offset``."""

    offset: tuple[float, float, float]
    child: Node

    def __post_init__(self):
        object.__setattr__(self, "offset", _vec3(self.offset, "Translate.offset"))

    @property
    def cost(self) -> float:
        return self.child.cost + 0.3

    def _eval(self, x, y, z):
        tx, ty, tz = self.offset
        return self.child._eval(x - tx, y - ty, z - tz)

    def emit_glsl(self, w, p):
        q = w.let("vec3", f"{p} - {_glsl_vec3(self.offset)}", stem="p")
        return self.child.emit_glsl(w, q)

    def bounds(self, level=0.0):
        return self.child.bounds(level) + np.array(self.offset)

    def _cull_bound(self):
        box, slack = self.child.cull_bound
        return np.array(box) + np.array(self.offset), slack


@dataclass(frozen=True, eq=False)
class Rotate(Node):
    """``child`` rotated about the origin by the orthonormal 3x3 ``matrix`` R.

    The distance is ``child(R^T p)``: a point of the child at q appears at R q.
    """

    matrix: tuple[tuple[float, float, float], ...]
    child: Node

    def __post_init__(self):
        m = np.asarray(self.matrix, dtype=np.float64)
        if m.shape != (3, 3) or not np.allclose(m @ m.T, np.eye(3), atol=1e-9):
            raise ValueError(f"Rotate.matrix must be an orthonormal 3x3 matrix, got {self.matrix!r}")
        object.__setattr__(self, "matrix", tuple(tuple(float(c) for c in row) for row in m))

    @classmethod
    def about_y(cls, angle: float, child: Node) -> "Rotate":
        """Rotate ``child`` by ``angle`` radians about +Y (right-handed: +Z towards +X)."""
        c, s = math.cos(angle), math.sin(angle)
        return cls(((c, 0.0, s), (0.0, 1.0, 0.0), (-s, 0.0, c)), child)

    @property
    def cost(self) -> float:
        return self.child.cost + 1.0

    def _eval(self, x, y, z):
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self.matrix
        # Rows of R^T are the columns of R.
        return self.child._eval(
            r00 * x + r10 * y + r20 * z,
            r01 * x + r11 * y + r21 * z,
            r02 * x + r12 * y + r22 * z,
        )

    def emit_glsl(self, w, p):
        cols = np.asarray(self.matrix).T
        rows = ", ".join(f"dot({_glsl_vec3(c)}, {p})" for c in cols)
        q = w.let("vec3", f"vec3({rows})", stem="p")
        return self.child.emit_glsl(w, q)

    def bounds(self, level=0.0):
        return _rotated_box(self.child.bounds(level), np.asarray(self.matrix))

    def _cull_bound(self):
        box, slack = self.child.cull_bound
        return _rotated_box(np.array(box), np.asarray(self.matrix)), slack


@dataclass(frozen=True, eq=False)
class Scale(Node):
    """``child`` scaled uniformly by ``factor`` about the origin (stays a distance bound)."""

    factor: float
    child: Node

    def __post_init__(self):
        object.__setattr__(self, "factor", _positive(self.factor, "Scale.factor"))

    @property
    def cost(self) -> float:
        return self.child.cost + 0.5

    def _eval(self, x, y, z):
        inv = 1.0 / self.factor
        return self.child._eval(x * inv, y * inv, z * inv) * self.factor

    def emit_glsl(self, w, p):
        q = w.let("vec3", f"{p} * {_glsl_float(1.0 / self.factor)}", stem="p")
        d = self.child.emit_glsl(w, q)
        return w.let("float", f"{d} * {_glsl_float(self.factor)}")

    def bounds(self, level=0.0):
        return self.child.bounds(level / self.factor) * self.factor

    def _cull_bound(self):
        box, slack = self.child.cull_bound
        return np.array(box) * self.factor, slack * self.factor


@dataclass(frozen=True, eq=False)
class MirrorX(Node):
    """``child`` reflected into x < 0 too: ``child(|x|, y, z)`` (for bilateral symmetry)."""

    child: Node

    @property
    def cost(self) -> float:
        return self.child.cost + 0.1

    def _eval(self, x, y, z):
        return self.child._eval(np.abs(x), y, z)

    def emit_glsl(self, w, p):
        q = w.let("vec3", f"vec3(abs({p}.x), {p}.yz)", stem="p")
        return self.child.emit_glsl(w, q)

    def bounds(self, level=0.0):
        # Only the child's x >= 0 part is kept, together with its mirror image.
        lo, hi = self.child.bounds(level)
        reach = max(float(hi[0]), 0.0)
        return np.stack([[-reach, lo[1], lo[2]], [reach, hi[1], hi[2]]])

    def _cull_bound(self):
        # (|x|, y, z) is as far from an x-symmetric box as (x, y, z) is.
        (lo, hi), slack = self.child.cull_bound
        reach = max(abs(lo[0]), abs(hi[0]))
        return np.array([[-reach, lo[1], lo[2]], [reach, hi[1], hi[2]]]), slack


# --------------------------------------------------------------------------------------
# The scene wrapper
# --------------------------------------------------------------------------------------


def _ray_box(o, d, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ray parameters of the AABB [lo, hi] for (n,) component lists o, d."""
    t_in = np.full(o[0].shape, -np.inf, dtype=o[0].dtype)
    t_out = np.full(o[0].shape, np.inf, dtype=o[0].dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            inv = 1.0 / d[i]
            t1, t2 = (lo[i] - o[i]) * inv, (hi[i] - o[i]) * inv
            # fmin/fmax skip the NaN of 0 * inf (origin on a slab, direction parallel to it).
            t_in = np.fmax(t_in, np.fmin(t1, t2))
            t_out = np.fmin(t_out, np.fmax(t1, t2))
    return t_in, t_out


@dataclass(frozen=True, eq=False)
class SDF:
    """A named SDF scene: a node tree plus what the precompute and the renderer need.

    Parameters
    ----------
    name : str
        Scene name (the :data:`SDF_SCENES` key).
    root : Node
        The distance expression.
    description : str
        One line for listings.
    """

    name: str
    root: Node
    description: str = ""

    def __post_init__(self):
        if not isinstance(self.root, Node):
            raise ValueError(f"SDF {self.name!r}: root must be a Node, got {type(self.root).__name__}")

    # ----- evaluation -----------------------------------------------------------------

    def evaluate(self, points) -> np.ndarray:
        """Signed distance at points.

        Parameters
        ----------
        points : (N, 3) array_like
            Query points; float32 is evaluated in float32, anything else in float64.

        Returns
        -------
        (N,) ndarray, float32 for float32 input, else float64
            Distance bound, negative inside.
        """
        return self.root.eval_np(_as_points(points))

    __call__ = evaluate

    def gradient(self, points, eps: float = 1e-4) -> np.ndarray:
        """Gradient of the distance by central differences (6 evaluations per point).

        Parameters
        ----------
        points : (N, 3) array_like
            Query points.
        eps : float
            Half the difference step.

        Returns
        -------
        (N, 3) ndarray, float32 for float32 input, else float64
            Computed in float64 either way (float32 differences would be noise).
        """
        p = _as_points(points)
        offsets = np.concatenate([np.eye(3), -np.eye(3)]) * eps
        grad = np.empty(p.shape, dtype=np.float64)
        for s in range(0, len(p), _GRADIENT_CHUNK):  # bounds the 6x tap array
            chunk = p[s : s + _GRADIENT_CHUNK].astype(np.float64)
            taps = (chunk[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
            f = self.root.eval_np(taps).reshape(6, len(chunk))
            grad[s : s + len(chunk)] = (f[:3] - f[3:]).T / (2.0 * eps)
        return grad.astype(p.dtype, copy=False)

    def normals(self, points, eps: float = 1e-4) -> np.ndarray:
        """Unit outward normals: the normalised :meth:`gradient`, (N, 3) in the input's dtype."""
        g = self.gradient(points, eps)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        return g / np.maximum(norm, np.finfo(g.dtype).tiny)

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 AABB ``[min, max]`` that contains the surface and the interior (read-only)."""
        box = self.root.bounds(0.0)
        box.flags.writeable = False
        return box

    # ----- GLSL ----------------------------------------------------------------------

    def glsl(self, function_name: str = "scene_sdf") -> str:
        """Self-contained GLSL 330 source defining ``float <function_name>(vec3 p)``.

        Helper functions and constants are prefixed with ``<function_name>_``; every
        constant is written with ``repr`` so numpy and GLSL use the same float32 values.
        """
        reserved = "__" in function_name or function_name.startswith("gl_")
        if reserved or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", function_name):
            raise ValueError(f"function_name must be a GLSL identifier, got {function_name!r}")
        w = GLSLWriter(function_name)
        result = self.root.emit_glsl(w, "p")
        lines = [f"// SDF scene '{self.name}', generated by prt.train.sdf; do not edit.\n"]
        lines += list(w.helpers.values())
        body = "\n".join(w.body)
        lines.append(f"float {function_name}(vec3 p) {{\n{body}\n    return {result};\n}}\n")
        return "\n".join(lines)

    # ----- meshing and projection ----------------------------------------------------

    def to_mesh(self, resolution: int = 128):
        """Triangle mesh of the zero level set by marching cubes over :attr:`bounds`.

        Parameters
        ----------
        resolution : int
            Grid samples along the longest side of the bounds (cubic voxels).

        Returns
        -------
        trimesh.Trimesh
            Merged vertices, outward-facing consistent winding, no degenerate faces.
        """
        import trimesh
        from skimage.measure import marching_cubes

        if int(resolution) < 8:
            raise ValueError(f"resolution must be >= 8, got {resolution}")
        lo, hi = self.bounds
        h = float((hi - lo).max()) / (int(resolution) - 1)
        lo = lo - 2.0 * h  # two voxels of margin: the grid boundary is strictly outside
        counts = np.ceil((hi + 2.0 * h - lo) / h).astype(int) + 1
        axes = [lo[i] + h * np.arange(counts[i]) for i in range(3)]
        volume = np.empty(tuple(counts), dtype=np.float32)
        yz = np.stack(np.meshgrid(axes[1], axes[2], indexing="ij"), axis=-1).reshape(-1, 2)
        for i, x in enumerate(axes[0]):  # one x-slab at a time bounds memory
            slab = np.column_stack([np.full(len(yz), x), yz]).astype(np.float32)
            volume[i] = self.evaluate(slab).reshape(counts[1], counts[2])
        verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=(h, h, h))
        mesh = trimesh.Trimesh(vertices=verts + lo, faces=faces, process=True)
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
        # The level set is closed (the grid boundary is outside), so a negative signed
        # volume means inward winding; checking beats relying on skimage's convention.
        if mesh.volume < 0.0:
            mesh.invert()
        return mesh

    def project_to_surface(self, points, iterations: int = 8, tol: float = 1e-7) -> np.ndarray:
        """Move points onto the zero level set by Newton steps ``p -= f * g / |g|^2``.

        Parameters
        ----------
        points : (N, 3) array_like
            Points near the surface (e.g. marching-cubes samples).
        iterations : int
            Maximum Newton steps; stops early once every ``|f| <= tol``.
        tol : float
            Convergence threshold on ``|f|``.

        Returns
        -------
        (N, 3) ndarray, float32 for float32 input, else float64
            Projected points (computed in float64).  In smooth regions ``|f| < 1e-5``
            afterwards; on creases (min/max without blending) convergence may be slower.
        """
        p_in = _as_points(points)
        p = p_in.astype(np.float64, copy=True)
        todo = np.arange(len(p))
        for _ in range(int(iterations)):
            f = self.root.eval_np(p[todo])
            moving = np.abs(f) > tol
            todo, f = todo[moving], f[moving]
            if todo.size == 0:
                break
            g = self.gradient(p[todo])
            g2 = np.maximum(np.einsum("ij,ij->i", g, g), 1e-12)
            p[todo] -= (f / g2)[:, None] * g
        return p.astype(p_in.dtype, copy=False)

    # ----- visibility ----------------------------------------------------------------

    def sphere_trace(
        self,
        origins,
        dirs,
        t_max,
        eps: float = 1e-4,
        max_steps: int = 256,
        *,
        chunk_size: int = 1 << 18,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Occlusion test of many rays at once by batched float32 sphere tracing.

        A ray hits when the distance at ``origin + t * dir`` drops below ``eps * (1 + t)``
        and misses once ``t > t_max`` or it leaves :attr:`bounds` (nothing lies outside).
        Each step evaluates only the still-active rays (compaction).  A ray that exhausts
        ``max_steps`` is reported as a HIT: that happens to grazing rays creeping along a
        surface, where calling them occluded is the conservative choice.

        Parameters
        ----------
        origins : (N, 3) array_like
            Ray origins, outside the surface (offset surface points along the normal by
            more than ``eps``, e.g. 1e-3, or they hit immediately).
        dirs : (N, 3) array_like
            Ray directions (normalised here).
        t_max : float or (N,) array_like
            Maximum ray parameter.
        eps : float
            Hit threshold at t = 0, growing linearly with t.
        max_steps : int
            Step budget per ray.
        chunk_size : int
            Rays traced together; bounds temporary memory (about 100 bytes per ray).
        out : (N,) bool ndarray, optional
            Written with the result and returned.

        Returns
        -------
        (N,) bool ndarray
            True where the ray is occluded.
        """
        o = np.asarray(origins, dtype=np.float32)
        d = np.asarray(dirs, dtype=np.float32)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise ValueError(f"origins and dirs must both be (N, 3), got {o.shape} and {d.shape}")
        n = len(o)
        t_max = np.broadcast_to(np.asarray(t_max, dtype=np.float32), (n,))
        if out is None:
            out = np.empty(n, dtype=bool)
        elif out.shape != (n,) or out.dtype != bool:
            raise ValueError(f"out must be a ({n},) bool array, got {out.shape} {out.dtype}")
        for s in range(0, n, int(chunk_size)):
            sl = slice(s, s + int(chunk_size))
            out[sl] = self._trace_chunk(o[sl], d[sl], t_max[sl], np.float32(eps), int(max_steps))
        return out

    @cached_property
    def _trace_box(self) -> np.ndarray:
        """Bounds padded past the hit threshold, as float32 (2, 3)."""
        return self.root.bounds(0.01).astype(np.float32)

    def _trace_chunk(self, o, d, t_max, eps, max_steps) -> np.ndarray:
        """Trace one chunk of rays; see :meth:`sphere_trace`."""
        n = len(o)
        hit = np.zeros(n, dtype=bool)
        ox, oy, oz = _columns(o)
        dx, dy, dz = _columns(d)
        inv_len = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx * inv_len, dy * inv_len, dz * inv_len
        lo, hi = self._trace_box
        t_in, t_out = _ray_box((ox, oy, oz), (dx, dy, dz), lo, hi)
        t = np.maximum(t_in, np.float32(0.0))  # jump to the box: nothing to hit before it
        t_end = np.minimum(t_max, t_out)
        live = np.flatnonzero(t <= t_end)
        ox, oy, oz, dx, dy, dz, t, t_end = (a[live] for a in (ox, oy, oz, dx, dy, dz, t, t_end))
        one = np.float32(1.0)
        for _ in range(max_steps):
            if live.size == 0:
                break
            f = self.root._eval(ox + t * dx, oy + t * dy, oz + t * dz)
            close = f < eps * (one + t)
            t += f
            done = close | (t > t_end)
            hit[live[close]] = True
            if done.any():
                keep = np.flatnonzero(~done)
                live, ox, oy, oz, dx, dy, dz, t, t_end = (
                    a[keep] for a in (live, ox, oy, oz, dx, dy, dz, t, t_end)
                )
        hit[live] = True  # steps exhausted: conservatively occluded
        return hit


# --------------------------------------------------------------------------------------
# The scene library
# --------------------------------------------------------------------------------------


def torus_knot_curve(p: int, q: int, major: float, minor: float, segments: int) -> np.ndarray:
    """Vertices of a (p, q) torus knot lying around the +Y axis.

    Parameters
    ----------
    p, q : int
        Windings around the axis and through the hole.
    major, minor : float
        Radii of the torus the knot winds on.
    segments : int
        Number of vertices (the curve is closed: join the last to the first).

    Returns
    -------
    (segments, 3) float64 ndarray
    """
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    r = major + minor * np.cos(q * phi)
    return np.column_stack([r * np.cos(p * phi), minor * np.sin(q * phi), r * np.sin(p * phi)])


def _sphere_plane() -> SDF:
    ground = Box(center=(0.0, -0.55, 0.0), half_size=(0.9, 0.05, 0.9), rounding=0.02)
    # Resting 0.01 above the slab (top at y = -0.5): a tight gap for a soft contact shadow.
    ball = Sphere(center=(0.0, -0.04, 0.0), radius=0.45)
    return SDF("sphere_plane", Union((ball, ground)), "sphere resting just above a ground slab")


def _torus_knot() -> SDF:
    curve = torus_knot_curve(2, 3, major=0.55, minor=0.24, segments=96)
    tube = Polyline(curve, radius=0.11, closed=True)
    return SDF("torus_knot", tube, "(2, 3) torus knot tube, strong self-shadowing")


def _creature() -> SDF:
    """A four-legged horned blob with a tail, tentacle arms, eyes and a mouth, on a slab."""
    ground = Box(center=(0.0, -0.8, 0.0), half_size=(0.9, 0.06, 0.9), rounding=0.03)  # top y = -0.74
    trunk = SmoothUnion(
        (
            Sphere((0.0, -0.2, 0.0), 0.34),  # torso
            Sphere((0.0, -0.33, 0.1), 0.26),  # belly
            Sphere((0.0, 0.2, 0.16), 0.24),  # head
            Sphere((0.0, 0.13, 0.34), 0.13),  # snout
        ),
        k=0.12,
    )
    legs = MirrorX(
        SmoothUnion(
            (
                Capsule((0.18, -0.36, 0.14), (0.29, -0.67, 0.26), 0.075),  # front leg
                Sphere((0.3, -0.665, 0.29), 0.08),  # front foot, sinks 5 mm into the slab
                Capsule((0.18, -0.38, -0.14), (0.29, -0.67, -0.24), 0.075),  # hind leg
                Sphere((0.3, -0.665, -0.26), 0.08),  # hind foot
            ),
            k=0.05,
        )
    )
    arms = MirrorX(
        Polyline(
            (
                (0.25, -0.12, 0.12),
                (0.42, -0.08, 0.24),
                (0.55, 0.02, 0.22),
                (0.6, 0.14, 0.1),
                (0.55, 0.24, 0.02),
            ),
            radius=0.045,  # a tentacle arm curling up and back
        )
    )
    horns = MirrorX(
        SmoothUnion(
            (Capsule((0.1, 0.36, 0.1), (0.22, 0.6, 0.0), 0.035), Sphere((0.23, 0.62, -0.01), 0.05)),
            k=0.03,
        )
    )
    tail = Polyline(
        ((0.0, -0.3, -0.3), (0.0, -0.42, -0.52), (0.0, -0.36, -0.7), (0.0, -0.2, -0.78)), radius=0.05
    )
    spike_roots = ((0.08, -0.2), (-0.04, -0.3), (-0.17, -0.34))  # (y, z) along the back
    spikes = Union(tuple(Capsule((0.0, y, z), (0.0, y + 0.12, z - 0.1), 0.03) for y, z in spike_roots))
    body = SmoothUnion((trunk, legs, arms, horns, tail, spikes), k=0.06)
    eye_sockets = MirrorX(Sphere((0.09, 0.3, 0.33), 0.075))
    mouth = Capsule((-0.09, 0.08, 0.45), (0.09, 0.08, 0.45), 0.025)
    face = SmoothSubtraction(SmoothSubtraction(body, eye_sockets, k=0.03), mouth, k=0.02)
    eyes = MirrorX(Sphere((0.09, 0.3, 0.325), 0.06))
    return SDF("creature", Union((face, eyes, ground)), "horned four-legged creature on a ground slab")


SDF_SCENES: dict[str, SDF] = {s.name: s for s in (_sphere_plane(), _torus_knot(), _creature())}
"""The library scenes by name; every one fits inside [-0.95, 0.95]^3."""


def sdf_names() -> list[str]:
    """Names of the library scenes, sorted."""
    return sorted(SDF_SCENES)


def get_sdf(name: str) -> SDF:
    """Look up a library scene.

    Raises
    ------
    GeometryError
        If ``name`` is not a library scene (one line listing the known names).
    """
    try:
        return SDF_SCENES[name]
    except (KeyError, TypeError):
        raise GeometryError(f"unknown SDF scene {name!r} (known: {', '.join(sdf_names())})") from None
