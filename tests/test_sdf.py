"""The SDF scene library: one definition, numpy and GLSL in agreement, safe to sphere trace."""

import numpy as np
import pytest

from prt.runtime.errors import GeometryError
from prt.runtime.gl import run_fragment_program
from prt.train.sdf import SDF, Capsule, Polyline, Sphere, Union, get_sdf, sdf_names

SCENES = sdf_names()

# Evaluates the scene's GLSL at each packed input point.
_EVAL_MAIN = "void main() { f_out = vec4(scene_sdf(prt_input().xyz)); }\n"


@pytest.fixture(scope="module")
def meshes():
    """Coarse marching-cubes mesh of every library scene, by name."""
    return {name: get_sdf(name).to_mesh(resolution=64) for name in SCENES}


def _test_points(sdf: SDF, mesh, rng) -> np.ndarray:
    """(N, 3) float64: 10^4 points uniform in [-1, 1]^3 plus 4000 within ~0.01 of the surface."""
    box = rng.uniform(-1.0, 1.0, (10_000, 3))
    near = mesh.vertices[rng.integers(0, len(mesh.vertices), 4000)] + rng.normal(0.0, 0.01, (4000, 3))
    return np.concatenate([box, near])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_library_scenes():
    assert {"sphere_plane", "torus_knot", "creature"} <= set(SCENES)
    for name in SCENES:
        assert get_sdf(name).name == name


def test_unknown_scene_raises_one_line():
    with pytest.raises(GeometryError) as info:
        get_sdf("teapot")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("unknown SDF scene 'teapot' (known: ")
    assert all(name in message for name in SCENES)


@pytest.mark.parametrize("name", SCENES)
def test_evaluate_keeps_float_dtype(name):
    sdf = get_sdf(name)
    p = np.random.default_rng(0).uniform(-1.0, 1.0, (100, 3))
    f64, f32 = sdf.evaluate(p), sdf.evaluate(p.astype(np.float32))
    assert f64.dtype == np.float64 and f64.shape == (100,)
    assert f32.dtype == np.float32 and f32.shape == (100,)
    assert np.abs(f32 - f64).max() < 1e-5


@pytest.mark.gl
@pytest.mark.parametrize("name", SCENES)
def test_numpy_matches_glsl(gl_ctx, meshes, name):
    sdf = get_sdf(name)
    p = _test_points(sdf, meshes[name], np.random.default_rng(1))
    glsl = run_fragment_program(gl_ctx, sdf.glsl() + _EVAL_MAIN, p, components=1)[:, 0]
    # GLSL sees the float32-rounded points, as does the float32 numpy path.
    p32 = p.astype(np.float32)
    worst64 = np.abs(glsl - sdf.evaluate(p32.astype(np.float64))).max()
    worst32 = np.abs(glsl - sdf.evaluate(p32)).max()
    report = f"{name}: worst |numpy - GLSL| {worst64:.3g} (float64), {worst32:.3g} (float32)"
    assert worst64 <= 1e-4 and worst32 <= 1e-4, report


@pytest.mark.gl
def test_glsl_snippets_coexist_in_one_shader(gl_ctx):
    a, b = get_sdf("creature"), get_sdf("torus_knot")
    source = (
        a.glsl("sdf_a") + b.glsl("sdf_b") + "void main() { vec3 p = prt_input().xyz;"
        " f_out = vec4(sdf_a(p), sdf_b(p), 0.0, 0.0); }\n"
    )
    p = np.random.default_rng(2).uniform(-1.0, 1.0, (3000, 3)).astype(np.float32)
    out = run_fragment_program(gl_ctx, source, p, components=2)
    assert out.shape == (3000, 2) and out.dtype == np.float32
    assert np.abs(out[:, 0] - a.evaluate(p)).max() <= 1e-4
    assert np.abs(out[:, 1] - b.evaluate(p)).max() <= 1e-4


@pytest.mark.gl
def test_run_fragment_program_keeps_row_order(gl_ctx):
    # 2500 rows span three texture rows, the last one partly padded.
    p = np.random.default_rng(3).normal(size=(2500, 3)).astype(np.float32)
    out = run_fragment_program(gl_ctx, "void main() { f_out = prt_input(); }\n", p, components=3)
    np.testing.assert_array_equal(out, p)


@pytest.mark.parametrize("name", SCENES)
def test_scene_fits_in_unit_box(meshes, name):
    sdf = get_sdf(name)
    lo, hi = sdf.bounds
    assert np.all(lo >= -0.95) and np.all(hi <= 0.95), f"{name}: bounds {sdf.bounds.tolist()}"
    assert np.all(meshes[name].vertices >= lo - 1e-6) and np.all(meshes[name].vertices <= hi + 1e-6)
    # Points on the faces of [-1, 1]^3 are all outside.
    rng = np.random.default_rng(4)
    face = rng.uniform(-1.0, 1.0, (6, 2000, 3))
    for i in range(3):
        face[2 * i, :, i], face[2 * i + 1, :, i] = -1.0, 1.0
    assert sdf.evaluate(face.reshape(-1, 3)).min() > 0.0


@pytest.mark.parametrize("name", SCENES)
def test_distance_never_overestimates(meshes, name):
    """Lipschitz <= 1: |f(p) - f(q)| <= |p - q| on random pairs, near and far apart."""
    sdf = get_sdf(name)
    rng = np.random.default_rng(5)
    p = _test_points(sdf, meshes[name], rng)
    step = _unit(rng.normal(size=p.shape)) * np.exp(rng.uniform(np.log(1e-3), np.log(1.0), (len(p), 1)))
    q = p + step
    ratio = np.abs(sdf.evaluate(q) - sdf.evaluate(p)) / np.linalg.norm(step, axis=1)
    assert ratio.max() <= 1.0 + 1e-3, f"{name}: Lipschitz ratio {ratio.max():.6f}"


def _dense_march(sdf: SDF, o: np.ndarray, d: np.ndarray, t_max: float, step: float = 1e-3) -> np.ndarray:
    """(N,) smallest distance sampled every ``step`` along each ray, brute force."""
    t = np.arange(0.0, t_max + step, step)
    samples = o[:, None, :] + t[None, :, None] * d[:, None, :]
    return sdf.evaluate(samples.reshape(-1, 3)).reshape(len(o), len(t)).min(axis=1)


@pytest.mark.parametrize("name", SCENES)
def test_sphere_trace_matches_dense_march(name):
    sdf = get_sdf(name)
    rng = np.random.default_rng(6)
    o = rng.uniform(-0.95, 0.95, (2000, 3))
    o = o[sdf.evaluate(o) > 0.02][:300]
    d = _unit(rng.normal(size=o.shape))
    t_max = 1.5
    traced = sdf.sphere_trace(o, d, t_max)
    closest = _dense_march(sdf, o, d, t_max)
    # Grazing rays, within a few march steps of the surface, are too close to call.
    clear = np.abs(closest) > 3e-3
    assert clear.mean() > 0.9
    np.testing.assert_array_equal(traced[clear], closest[clear] < 0.0)
    assert 0 < traced[clear].sum() < clear.sum()  # both outcomes were exercised


def test_sphere_trace_towards_and_away_from_a_sphere():
    ball = SDF("ball", Sphere((0.1, 0.2, -0.1), 0.5))
    rng = np.random.default_rng(7)
    n = _unit(rng.normal(size=(500, 3)))
    surface = np.array(ball.root.center) + 0.5 * n
    away = ball.sphere_trace(surface + 1e-3 * n, n, t_max=10.0)
    assert not away.any()
    # From 0.9 out, aim within the cone that still meets the sphere (half-angle asin(0.5/0.9)).
    start = np.array(ball.root.center) + 0.9 * n
    aim = _unit(-n + 0.5 * np.tan(np.arcsin(0.5 / 0.9)) * _unit(np.cross(n, rng.normal(size=(500, 3)))))
    towards = ball.sphere_trace(start, aim, t_max=10.0)
    assert towards.all()
    # t_max shorter than the gap (0.4): nothing reached yet.
    assert not ball.sphere_trace(start, -n, t_max=0.3).any()
    # Out of steps before leaving the scene counts as occluded (conservative).
    assert ball.sphere_trace(surface + 1e-3 * n, n, t_max=10.0, max_steps=2).all()


def test_sphere_trace_chunks_and_out():
    sdf = get_sdf("creature")
    rng = np.random.default_rng(8)
    o = rng.uniform(-0.9, 0.9, (3000, 3)).astype(np.float32)
    d = _unit(rng.normal(size=o.shape)).astype(np.float32)
    whole = sdf.sphere_trace(o, d, 2.0)
    out = np.zeros(len(o), dtype=bool)
    chunked = sdf.sphere_trace(o, d, 2.0, chunk_size=256, out=out)
    assert chunked is out
    np.testing.assert_array_equal(chunked, whole)


@pytest.mark.parametrize("name", SCENES)
def test_mesh_projects_onto_surface_with_outward_normals(meshes, name):
    sdf, mesh = get_sdf(name), meshes[name]
    assert mesh.is_watertight and mesh.volume > 0.0
    assert mesh.nondegenerate_faces().all()
    on = sdf.project_to_surface(mesh.sample(3000, seed=9))
    f = np.abs(sdf.evaluate(on))
    assert np.quantile(f, 0.99) < 1e-5 and f.max() < 1e-4, f"{name}: |f| after projection up to {f.max():.3g}"
    # The winding's normals point outward: f increases along them, as along the SDF normals.
    v, vn = mesh.vertices, mesh.vertex_normals
    assert (sdf.evaluate(v + 2e-3 * vn) > sdf.evaluate(v - 2e-3 * vn)).mean() > 0.99
    n = sdf.normals(on)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert (sdf.evaluate(on + 1e-3 * n) > 0.0).all() and (sdf.evaluate(on - 1e-3 * n) < 0.0).mean() > 0.99


def test_culling_is_exact():
    """Bounding-box culling (unions, subtractions) and polyline clusters change no value."""
    rng = np.random.default_rng(10)
    loop = rng.uniform(-0.6, 0.6, (40, 3))
    capsules = [Capsule(a, b, 0.03) for a, b in zip(loop, np.roll(loop, -1, axis=0))]
    p = rng.uniform(-1.0, 1.0, (5000, 3))
    brute = np.minimum.reduce([c.eval_np(p) for c in capsules])
    np.testing.assert_array_equal(Union(tuple(capsules)).eval_np(p), brute)
    np.testing.assert_allclose(Polyline(loop, 0.03, closed=True).eval_np(p), brute, rtol=0.0, atol=1e-12)
    # The creature's smooth unions and subtractions against an uncullable copy of its tree.
    sdf = get_sdf("creature")
    q = np.concatenate([p, rng.normal(0.0, 0.3, (5000, 3))])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("prt.train.sdf.nodes._CULL_MIN_COST", float("inf"))
        unculled = sdf.evaluate(q)
    np.testing.assert_allclose(sdf.evaluate(q), unculled, rtol=0.0, atol=1e-12)
