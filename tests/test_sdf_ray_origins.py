"""Ray origins on fields that grow slowly (a neural SDF divided by its Lipschitz bound).

A fixed 2e-3 offset along the normal leaves the origin below the sphere tracer's hit threshold
where the field's slope is ~0.05: every ray "hits" at once and a lit surface is traced black
(the neural-SDF bunny's ear tip).  :meth:`prt.train.sdf.SDF.start_points` lifts such origins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prt.runtime import sh
from prt.train.sdf import SDF, Sphere
from prt.train.sdf.glsl import glsl_float
from prt.train.transport.transfer import SDF_RAY_OFFSET, EmbreeTracer, SDFTracer, TransferIntegrator

SLOPE = 0.04  # about the smallest slope measured on the neural bunny's surface samples (0.03 to 0.4)


@dataclass(frozen=True, eq=False)
class SlowSphere(Sphere):
    """A sphere whose distance is scaled by SLOPE: still a bound (Lipschitz SLOPE), as a neural SDF is."""

    def _eval(self, x, y, z):
        return super()._eval(x, y, z) * x.dtype.type(SLOPE)

    def emit_glsl(self, w, p):
        return w.let("float", f"{super().emit_glsl(w, p)} * {glsl_float(SLOPE)}")


def _sphere_points(count: int, radius: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return (radius * n).astype(np.float32), n.astype(np.float32)


def test_a_fixed_offset_starts_inside_the_hit_threshold_of_a_slow_field():
    sdf = SDF("slow", SlowSphere((0.0, 0.0, 0.0), 0.5))
    points, normals = _sphere_points(200, 0.5)
    # the hazard the rule removes: a ray straight out of a convex surface reported as blocked
    assert sdf.sphere_trace(points + SDF_RAY_OFFSET * normals, normals).all()
    origins = SDFTracer(sdf).origins(points, normals)
    assert not sdf.sphere_trace(origins, normals).any()
    assert (sdf.evaluate(origins.astype(np.float64)) >= 3.9e-4).all()
    lifted = np.linalg.norm(origins - points, axis=1)
    assert (lifted > SDF_RAY_OFFSET).all() and (lifted <= 0.02 + SDF_RAY_OFFSET + 1e-6).all()


class FixedOffsetTracer(SDFTracer):
    """The rule before: every origin 2e-3 along the normal."""

    def origins(self, points, normals):
        return np.asarray(points, np.float32) + np.float32(self.offset) * np.asarray(normals, np.float32)


def test_an_unoccluded_slow_sphere_gets_the_unshadowed_transfer():
    """Analytic case: nothing occludes a convex sphere, so the DC term is exact where no ray is blocked.

    On a field this slow, a grazing ray can exhaust the tracer's step budget (256) before it leaves
    the scene, and is then counted as blocked: at most one of the 64 here."""
    points, normals = _sphere_points(64, 0.5, seed=1)
    slow = SDF("slow", SlowSphere((0.0, 0.0, 0.0), 0.5))
    lifted = TransferIntegrator(SDFTracer(slow), rays=64).chunk(points, normals, 0)
    fixed = TransferIntegrator(FixedOffsetTracer(slow), rays=64).chunk(points, normals, 0)
    exact = TransferIntegrator(SDFTracer(SDF("unit", Sphere((0.0, 0.0, 0.0), 0.5))), rays=64).chunk(points, normals, 0)
    dc = sh.unshadowed_transfer(normals)[:, 0]
    np.testing.assert_allclose(exact[:, 0], dc, atol=1e-5)  # an exact distance: every ray free
    assert (lifted[:, 0] >= dc * (1 - 1.01 / 64)).all()
    assert np.median(np.abs(lifted - exact).max(axis=1)) < 1e-6  # most samples: the same rays, all free
    assert (np.abs(fixed[:, 0]) < 0.05 * dc).all()  # before: (nearly) every ray blocked at its origin


def test_an_exact_distance_keeps_the_fixed_offset():
    sdf = SDF("unit", Sphere((0.0, 0.0, 0.0), 0.5))
    points, normals = _sphere_points(100, 0.5, seed=2)
    origins = SDFTracer(sdf).origins(points, normals)
    np.testing.assert_allclose(origins, points + SDF_RAY_OFFSET * normals, atol=1e-6)


def test_a_nearby_occluder_bounds_the_lift():
    """Two concentric slow spheres 0.01 apart (the outer one's inside faces the inner one's
    surface): the lift stops at its cap instead of walking through the occluder."""
    from prt.train.sdf import Subtraction, Union

    inner = SlowSphere((0.0, 0.0, 0.0), 0.5)
    shell = Subtraction(SlowSphere((0.0, 0.0, 0.0), 0.6), SlowSphere((0.0, 0.0, 0.0), 0.51))
    sdf = SDF("shell", Union((inner, shell)))
    points, normals = _sphere_points(50, 0.5, seed=3)
    origins = SDFTracer(sdf).origins(points, normals)
    lifted = np.linalg.norm(origins - points, axis=1)
    assert (lifted <= 0.02 + SDF_RAY_OFFSET + 1e-6).all()
    assert (np.linalg.norm(origins, axis=1) < 0.51).all()  # still in the gap, not through the shell


def test_mesh_origins_are_unchanged(tmp_path):
    import trimesh

    tracer = EmbreeTracer(trimesh.creation.icosphere(subdivisions=2, radius=0.5))
    points, normals = _sphere_points(20, 0.5, seed=4)
    assert tracer.origin_rule == ""
    np.testing.assert_array_equal(tracer.origins(points, normals), points + np.float32(tracer.offset) * normals)
