"""The library of named SDF scenes; look them up with :func:`get_sdf`."""

from __future__ import annotations

import numpy as np

from ...runtime.errors import GeometryError
from .combinators import SmoothSubtraction, SmoothUnion, Union
from .field import SDF
from .primitives import Box, Capsule, Polyline, Sphere
from .transforms import MirrorX

__all__ = ["SDF_SCENES", "get_sdf", "sdf_names", "torus_knot_curve"]


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
