"""SDF primitives: exact Euclidean distances to spheres, boxes, tori, capsules and tubes."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .glsl import glsl_float, glsl_vec3, helper_template
from .nodes import Node, as_positive, as_vec3

__all__ = ["Sphere", "Box", "Torus", "Capsule", "Polyline"]

# Elements per (segments, points) temporary when broadcasting points against segments.
_BLOCK_ELEMENTS = 1 << 18


@dataclass(frozen=True, eq=False)
class Sphere(Node):
    """Sphere of ``radius`` around ``center``."""

    center: tuple[float, float, float]
    radius: float
    cost = 1.0

    def __post_init__(self):
        object.__setattr__(self, "center", as_vec3(self.center, "Sphere.center"))
        object.__setattr__(self, "radius", as_positive(self.radius, "Sphere.radius"))

    def _eval(self, x, y, z):
        cx, cy, cz = self.center
        dx, dy, dz = x - cx, y - cy, z - cz
        return np.sqrt(dx * dx + dy * dy + dz * dz) - self.radius

    def emit_glsl(self, w, p):
        return w.let("float", f"length({p} - {glsl_vec3(self.center)}) - {glsl_float(self.radius)}")

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
        object.__setattr__(self, "center", as_vec3(self.center, "Box.center"))
        half = as_vec3(self.half_size, "Box.half_size")
        if min(half) <= 0.0:
            raise ValueError(f"Box.half_size must be > 0, got {half}")
        rounding = as_positive(self.rounding, "Box.rounding", allow_zero=True)
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
        args = f"{p} - {glsl_vec3(self.center)}, {glsl_vec3(self._inner)}, {glsl_float(self.rounding)}"
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
        object.__setattr__(self, "center", as_vec3(self.center, "Torus.center"))
        object.__setattr__(self, "major", as_positive(self.major, "Torus.major"))
        object.__setattr__(self, "minor", as_positive(self.minor, "Torus.minor"))
        axis = np.array(as_vec3(self.axis, "Torus.axis"))
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
            f"{p} - {glsl_vec3(self.center)}, {glsl_vec3(self.axis)}, "
            f"{glsl_float(self.major)}, {glsl_float(self.minor)}"
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
        object.__setattr__(self, "a", as_vec3(self.a, "Capsule.a"))
        object.__setattr__(self, "b", as_vec3(self.b, "Capsule.b"))
        object.__setattr__(self, "radius", as_positive(self.radius, "Capsule.radius"))

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
            f"{p}, {glsl_vec3(self.a)}, {glsl_vec3(ba)}, "
            f"{glsl_float(inv_baba)}, {glsl_float(self.radius)}"
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
        object.__setattr__(self, "radius", as_positive(self.radius, "Polyline.radius"))
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
        rows = ",\n    ".join  # one constant per line
        fn = w.add_helper(
            w.unique_key("polyline"),
            helper_template("polyline"),
            n=str(len(self._a)),
            a=rows(glsl_vec3(v) for v in self._a),
            ba=rows(glsl_vec3(v) for v in self._ba),
            inv_baba=rows(glsl_float(v) for v in self._inv_baba),
            radius=glsl_float(self.radius),
        )
        return w.let("float", f"{fn}({p})")

    def bounds(self, level=0.0):
        pts = np.asarray(self.points)
        r = self.radius + level
        return np.stack([pts.min(axis=0) - r, pts.max(axis=0) + r])

    def _cull_bound(self):
        pts = np.asarray(self.points)
        return np.stack([pts.min(axis=0), pts.max(axis=0)]), self.radius
