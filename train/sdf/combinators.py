"""SDF combinators: union, intersection and subtraction of child nodes, plain or blended.

numpy skips costly children at points where they provably cannot change the result
(:func:`~prt.train.sdf.nodes.fold`), so the culling is exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .glsl import glsl_float
from .nodes import Node, as_positive, box_union, fold

__all__ = ["Union", "SmoothUnion", "Intersection", "Subtraction", "SmoothSubtraction"]


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


def _check_children(children, what: str) -> tuple[Node, ...]:
    children = tuple(children)
    if not children or not all(isinstance(c, Node) for c in children):
        raise ValueError(f"{what} needs one or more Node children, got {children!r}")
    return children


def _hull_bound(children, extra_slack: float = 0.0) -> tuple[np.ndarray, float]:
    """Cull bound of a min over children: the hull of their boxes, their largest slack."""
    bounds = [c.cull_bound for c in children]
    boxes = [np.array(box) for box, _ in bounds]
    return box_union(boxes), max(slack for _, slack in bounds) + extra_slack


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
            d = fold(d, child, x, y, z, d, np.minimum)
        return d

    def emit_glsl(self, w, p):
        d = self.children[0].emit_glsl(w, p)
        for child in self.children[1:]:
            d = w.let("float", f"min({d}, {child.emit_glsl(w, p)})")
        return d

    def bounds(self, level=0.0):
        return box_union([c.bounds(level) for c in self.children])

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
        object.__setattr__(self, "k", as_positive(self.k, "SmoothUnion.k"))

    @property
    def cost(self) -> float:
        return sum(c.cost for c in self.children) + 0.8 * (len(self.children) - 1)

    def _eval(self, x, y, z):
        k = self.k
        d = self.children[0]._eval(x, y, z)
        for child in self.children[1:]:
            d = fold(d, child, x, y, z, d + k, lambda a, b: _smin(a, b, k))
        return d

    def emit_glsl(self, w, p):
        fn = w.helper("smin")
        d = self.children[0].emit_glsl(w, p)
        for child in self.children[1:]:
            d = w.let("float", f"{fn}({d}, {child.emit_glsl(w, p)}, {glsl_float(self.k)})")
        return d

    @property
    def _blend_slack(self) -> float:
        """How far the blend can dip below the plain union: k/4 per fold."""
        return (len(self.children) - 1) * self.k / 4.0

    def bounds(self, level=0.0):
        # {f <= level} lies in {min <= level + slack}.
        return box_union([c.bounds(level + self._blend_slack) for c in self.children])

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
        return fold(d, self.cutter, x, y, z, -d, lambda a, b: np.maximum(a, -b))

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
        object.__setattr__(self, "k", as_positive(self.k, "SmoothSubtraction.k"))

    @property
    def cost(self) -> float:
        return self.base.cost + self.cutter.cost + 0.8

    def _eval(self, x, y, z):
        k = self.k
        d = self.base._eval(x, y, z)
        # smax(base, -cutter) is base wherever -cutter <= base - k, i.e. cutter >= k - base.
        return fold(d, self.cutter, x, y, z, k - d, lambda a, b: _smax(a, -b, k))

    def emit_glsl(self, w, p):
        fn = w.helper("smax")
        a, b = self.base.emit_glsl(w, p), self.cutter.emit_glsl(w, p)
        return w.let("float", f"{fn}({a}, -{b}, {glsl_float(self.k)})")

    def bounds(self, level=0.0):
        # smax(a, -b) >= a, so the result lies inside base.
        return self.base.bounds(level)

    def _cull_bound(self):
        box, slack = self.base.cull_bound
        return np.array(box), slack
