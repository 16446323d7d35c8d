"""SDF transforms: a child node moved, rotated, scaled or mirrored (each stays a distance bound)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .glsl import glsl_float, glsl_vec3
from .nodes import Node, as_positive, as_vec3

__all__ = ["Translate", "Rotate", "Scale", "MirrorX"]


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
        object.__setattr__(self, "offset", as_vec3(self.offset, "Translate.offset"))

    @property
    def cost(self) -> float:
        return self.child.cost + 0.3

    def _eval(self, x, y, z):
        tx, ty, tz = self.offset
        return self.child._eval(x - tx, y - ty, z - tz)

    def emit_glsl(self, w, p):
        q = w.let("vec3", f"{p} - {glsl_vec3(self.offset)}", stem="p")
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
        rows = ", ".join(f"dot({glsl_vec3(c)}, {p})" for c in cols)
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
        object.__setattr__(self, "factor", as_positive(self.factor, "Scale.factor"))

    @property
    def cost(self) -> float:
        return self.child.cost + 0.5

    def _eval(self, x, y, z):
        inv = 1.0 / self.factor
        return self.child._eval(x * inv, y * inv, z * inv) * self.factor

    def emit_glsl(self, w, p):
        q = w.let("vec3", f"{p} * {glsl_float(1.0 / self.factor)}", stem="p")
        d = self.child.emit_glsl(w, q)
        return w.let("float", f"{d} * {glsl_float(self.factor)}")

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
