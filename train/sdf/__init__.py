"""Analytic signed distance field (SDF) scenes, each defined once for numpy and GLSL.

A scene is a small expression tree of node objects.  Every node evaluates itself with numpy
and emits the equivalent GLSL, so the precompute (numpy) and the renderer (GLSL sphere
tracing) agree by construction.

Conventions: scene space is the box ``[-1, 1]^3`` centred at the origin, +Y up; distances
are negative inside.  Every node is a distance *bound*: Lipschitz constant <= 1, so it
never overestimates the distance to the surface and sphere tracing never steps through it.

Modules
-------
nodes
    :class:`Node`, the protocol every node implements, and the exact culling of costly
    children that combinators use.
primitives
    :class:`Sphere`, :class:`Box`, :class:`Torus`, :class:`Capsule`, :class:`Polyline`.
combinators
    :class:`Union`, :class:`SmoothUnion`, :class:`Intersection`, :class:`Subtraction`,
    :class:`SmoothSubtraction`.
transforms
    :class:`Translate`, :class:`Rotate`, :class:`Scale`, :class:`MirrorX`.
glsl
    :class:`GLSLWriter`, which nodes append their GLSL to; the helper functions it declares
    are the templates ``prt/shaders/sdf_*.glsl.tmpl``.
field
    :class:`SDF`: a root node with evaluation, gradients, GLSL, meshing, projection onto
    the surface and batched sphere tracing (the one sphere tracer; the transfer's
    ``SDFTracer`` uses it).
library
    The named scenes, :data:`SDF_SCENES`; look them up with :func:`get_sdf`.
"""

from .combinators import Intersection, SmoothSubtraction, SmoothUnion, Subtraction, Union
from .field import SDF
from .glsl import GLSLWriter
from .library import SDF_SCENES, get_sdf, sdf_names, torus_knot_curve
from .nodes import Node
from .primitives import Box, Capsule, Polyline, Sphere, Torus
from .transforms import MirrorX, Rotate, Scale, Translate

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
