"""Neural SDFs: the fitted network is a distance bound, numpy/ONNX/GLSL agree, tracing is safe, scenes render."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("torch")

from prt.runtime.gl import run_fragment_program  # noqa: E402
from prt.train.sdf.neural import fit_neural_sdf, geometric_error, load_neural_sdf, parse_sdf_size  # noqa: E402

RADIUS = 0.6
_EVAL_MAIN = "void main() { f_out = vec4(scene_sdf(prt_input().xyz)); }\n"


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """A 16x2 network fitted to an icosphere of radius 0.6 (a few seconds)."""
    path = tmp_path_factory.mktemp("neural_sdf") / "ball.sdf.onnx"
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    info = fit_neural_sdf(mesh, path, size=(16, 2), samples=20_000, steps=600, batch=2048, lr=1e-2, log=lambda *a: None)
    return load_neural_sdf(path), info, mesh


def _analytic(p):
    return np.linalg.norm(p, axis=1) - RADIUS


def test_fitted_sphere_is_close_to_the_analytic_distance(sphere):
    sdf, info, mesh = sphere
    p = np.random.default_rng(0).uniform(-0.95, 0.95, (5000, 3))
    f = sdf.evaluate(p) * info["distance_divided_by"]  # undo the Lipschitz scaling
    near = np.abs(_analytic(p)) < 0.2
    assert np.abs(f - _analytic(p))[near].mean() < 0.03
    error = geometric_error(sdf, mesh, points=5000, resolution=48)
    assert error["chamfer"] < 0.03 and error["mean_abs_sdf"] < 0.02, error


def test_sign_is_right_inside_and_outside(sphere):
    sdf, _, _ = sphere
    p = np.random.default_rng(1).uniform(-0.95, 0.95, (5000, 3))
    d = _analytic(p)
    clear = np.abs(d) > 0.05
    assert np.array_equal(np.sign(sdf.evaluate(p))[clear], np.sign(d)[clear])


def test_exported_network_is_a_distance_bound(sphere):
    sdf, info, _ = sphere
    assert info["distance_divided_by"] >= 1.0 and info["lipschitz_weight_bound"] >= info["lipschitz_measured"]
    rng = np.random.default_rng(2)
    p = rng.uniform(-1.0, 1.0, (4000, 3))
    g = sdf.gradient(p)
    assert np.linalg.norm(g, axis=1).max() <= 1.0  # the measured max |grad| was divided out, with a margin


def test_onnx_runtime_numpy_and_glsl_agree(sphere, gl_ctx):
    ort = pytest.importorskip("onnxruntime")
    sdf, _, _ = sphere
    p = np.random.default_rng(3).uniform(-1.2, 1.2, (3000, 3)).astype(np.float32)
    session = ort.InferenceSession(str(sdf.root.path), providers=["CPUExecutionProvider"])
    x = np.concatenate([p, np.zeros_like(p)], axis=1)
    onnx = session.run(None, {"x": x})[0][:, 0]
    numpy = sdf.evaluate(p)
    glsl = run_fragment_program(gl_ctx, sdf.glsl() + _EVAL_MAIN, p, components=1)[:, 0]
    np.testing.assert_allclose(numpy, onnx, atol=1e-5)
    np.testing.assert_allclose(glsl, onnx, atol=1e-4)


def test_glsl_with_position_frequencies_and_odd_width_agrees(tmp_path, gl_ctx):
    """The loop-free writer's other paths: sin/cos features and a width that is not a multiple of 4."""
    ort = pytest.importorskip("onnxruntime")
    path = tmp_path / "freq.sdf.onnx"
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=RADIUS)
    fit_neural_sdf(mesh, path, size=(10, 3), pos_freqs=2, samples=5000, steps=50, batch=512, log=lambda *a: None)
    sdf = load_neural_sdf(path)
    p = np.random.default_rng(5).uniform(-1.5, 1.5, (2000, 3)).astype(np.float32)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    onnx = session.run(None, {"x": np.concatenate([p, np.zeros_like(p)], axis=1)})[0][:, 0]
    glsl = run_fragment_program(gl_ctx, sdf.glsl() + _EVAL_MAIN, p, components=1)[:, 0]
    np.testing.assert_allclose(sdf.evaluate(p), onnx, atol=1e-5)
    np.testing.assert_allclose(glsl, onnx, atol=1e-5)


def test_sphere_tracing_misses_and_grazing_rays_stay_finite(sphere):
    sdf, _, _ = sphere
    origins = np.array([[0, 0, 3], [0, 0, 3], [RADIUS, 0, 3], [3, 3, 3], [0, 2, 0], [0, 0, -2.5], [2.5, 0, 0]], dtype=np.float32)
    dirs = np.array([[0, 0, -1], [0, 1, 0], [0, 0, -1], [1, 1, 1], [0, 0, 1], [0, 0, 1], [-1, 0, 0]], dtype=np.float32)
    with np.errstate(over="raise", invalid="raise"):
        hit = sdf.sphere_trace(origins, dirs)
    # at it, past it, grazing (either answer), away, parallel outside the box, at it from within t_max (default)
    assert hit.tolist()[:2] == [True, False] and hit[3] == False and hit[4] == False and hit[5] and hit[6]  # noqa: E712


def test_thin_slab_is_not_tunnelled(tmp_path):
    slab = trimesh.creation.box(extents=(1.4, 1.4, 0.08))
    path = tmp_path / "slab.sdf.onnx"
    fit_neural_sdf(slab, path, size=(16, 2), samples=20_000, steps=600, batch=2048, lr=1e-2, log=lambda *a: None)
    sdf = load_neural_sdf(path)
    xy = np.random.default_rng(4).uniform(-0.5, 0.5, (500, 2))
    # rays through points inside the network's own slab: tracing must stop there, not step over
    xy = xy[sdf.evaluate(np.column_stack([xy, np.zeros(500)])) < 0.0]
    assert len(xy) > 400
    origins = np.column_stack([xy, np.full(len(xy), 0.9)]).astype(np.float32)
    dirs = np.tile(np.array([0.0, 0.0, -1.0], dtype=np.float32), (len(xy), 1))
    assert sdf.sphere_trace(origins, dirs).all()
    assert not sdf.sphere_trace(origins, -dirs).any()


def test_network_glsl_has_no_loop(sphere):
    """llvmpipe ends every loop of an invocation after 65535 iterations in total; a network with
    layer loops inside the sphere tracer's loop ran out of them (18 % of the bunny's pixels)."""
    sdf, _, _ = sphere
    source = re.sub(r"//[^\n]*", "", sdf.glsl())  # code only
    assert not re.search(r"\b(for|while|do)\b", source), "the SDF network's GLSL must be loop-free"


def test_gbuffer_sphere_traces_one_call_site_and_few_loop_iterations():
    from prt.shaders import source

    text = re.sub(r"//[^\n]*", "", source("gbuffer_sdf.frag"))  # code only
    assert text.count("scene_sdf(") == 1  # one call site: the network is inlined once
    assert len(re.findall(r"\bfor\b", text)) == 1 and "PRT_MAX_STEPS + 4" in text


def _surface_rays(sdf, count, rays, seed=0):
    """Cosine rays from projected surface points, offset along the normal as the precompute does."""
    from prt.train.transport.transfer import SDF_RAY_OFFSET, cosine_directions, orthonormal_frames

    rng = np.random.default_rng(seed)
    m = sdf.to_mesh(resolution=48)
    p = sdf.project_to_surface(m.vertices[rng.integers(0, len(m.vertices), count)])
    n = sdf.normals(p)
    frames = orthonormal_frames(n, rng.uniform(0.0, 2.0 * np.pi, count))
    dirs = np.matmul(cosine_directions(rays)[None], frames.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(p + SDF_RAY_OFFSET * n, rays, axis=0)
    return origins.astype(np.float32), dirs.astype(np.float32), p, n


def test_self_occlusion_of_a_fitted_sphere_is_rare(sphere):
    """A convex shape does not shadow itself: shadow rays from its fitted surface see the sky.

    The fitted field is piecewise linear (ReLU), so a few grazing rays may clip a neighbouring
    facet; a point whose rays start inside the solid would lose half its sky or more."""
    sdf, _, _ = sphere
    origins, dirs, p, n = _surface_rays(sdf, 400, 64)
    assert (sdf.evaluate(origins[::64]) > 0).all()  # every origin outside the solid
    with np.errstate(over="raise", invalid="raise"):
        hit = sdf.sphere_trace(origins, dirs).reshape(400, 64)
    assert hit.mean() < 0.005, hit.mean()  # rays (measured: 0.0)
    assert hit.mean(axis=1).max() < 0.2  # no point loses a fifth of its sky


def test_gbuffer_points_of_a_neural_sdf_lie_on_it_with_its_normals(gl_ctx, neural_scene):
    """The G-buffer's sphere tracer agrees with numpy: hits on the zero set, normals = gradient,
    and shadow rays from its points start outside the solid (the reference traces from there)."""
    from prt.runtime.renderer import Renderer, Scene
    from prt.train.transport.transfer import SDF_RAY_OFFSET

    scene = Scene.load(neural_scene / "scene.json")
    sdf = load_neural_sdf(neural_scene / "ball.sdf.onnx")
    with Renderer(scene, 64, 64, backend="onnx", ctx=gl_ctx) as r:
        g = r.gbuffer_image()
    p, n = g.position[g.covered], g.normal[g.covered]
    assert len(p) > 500 and np.isfinite(p).all() and np.isfinite(n).all()
    f = np.abs(sdf.evaluate(p))
    # within the hit threshold (1e-4 * t), but for grazing rays out of steps within the pixel's cone
    assert np.mean(f < 1e-3) > 0.98 and f.max() < 0.04, np.percentile(f, [50, 99, 100])
    cos = np.einsum("ij,ij->i", n, sdf.normals(p.astype(np.float64)))
    assert np.mean(cos > 0.99) > 0.97 and cos.min() > 0.0
    assert np.mean(sdf.evaluate(p + SDF_RAY_OFFSET * n) < 0) < 0.002


def test_sdf_size_parsing():
    assert parse_sdf_size("64x4") == (64, 4) and parse_sdf_size("32X4") == (32, 4)
    for bad in ("64", "x4", "0x4", "64x9", "axb"):
        with pytest.raises(ValueError, match="--sdf-size"):
            parse_sdf_size(bad)


# ----- end to end ------------------------------------------------------------------------


def _psnr(a, b):
    mse = float(((a.astype(np.float64) - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(float(b.max()) ** 2 / mse)


@pytest.fixture(scope="module")
def neural_scene(tmp_path_factory):
    base = tmp_path_factory.mktemp("neural_scene")
    mesh_path = base / "ball.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=1.0).export(mesh_path)
    out = base / "scene"
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(mesh_path), "-o", str(out), "--neural-sdf", "--sdf-size", "16x2",
         "--sdf-samples", "10000", "--sdf-steps", "250", "--samples", "2000", "--validation", "1000", "--rays", "32",
         "--steps", "150", "--batch", "512", "--segments", "1", "--hidden", "8", "--layers", "1", "--threads", "2",
         "--no-progress"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "neural SDF geometric error" in proc.stdout
    return out


def test_neural_sdf_scene_renders_alike_in_both_backends(gl_ctx, neural_scene):
    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(neural_scene / "scene.json")
    assert scene.manifest.geometry.type == "sdf" and (neural_scene / "ball.sdf.onnx").is_file()
    images = {}
    for backend in ("onnx", "glsl"):
        with Renderer(scene, 64, 64, backend=backend, ctx=gl_ctx) as r:
            images[backend] = r.render()
    assert np.isfinite(images["glsl"]).all() and images["onnx"].max() > 0.05
    assert _psnr(images["glsl"], images["onnx"]) >= 60.0


def test_neural_sdf_rerun_reuses_the_network(neural_scene):
    before = (neural_scene / "ball.sdf.onnx").stat().st_mtime_ns
    from prt.train.sdf.neural_fit import prepare_neural_sdf

    import json

    settings = json.loads((neural_scene / "neural_sdf.json").read_text())["settings"]
    path = prepare_neural_sdf(settings["source"], neural_scene, size=(16, 2), samples=10000, steps=250, seed=settings["seed"], log=lambda *a: None)
    assert path.stat().st_mtime_ns == before


def test_neural_sdf_needs_a_watertight_mesh(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.update_faces(np.arange(len(mesh.faces) - 4))
    path = tmp_path / "open.obj"
    mesh.export(path)
    proc = subprocess.run([sys.executable, "-m", "prt.train.train_cli", str(path), "-o", str(tmp_path / "o"), "--neural-sdf"],
                          capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 2 and "watertight" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_missing_torch_is_one_line_naming_the_extra(monkeypatch):
    from prt.runtime.errors import InputError
    from prt.train.sdf.neural_fit import require_torch

    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now fails as if not installed
    with pytest.raises(InputError, match=r"--neural-sdf needs torch: pip install 'prt-runtime\[train\]'"):
        require_torch()


def _looped_scene_glsl(onnx_path) -> str:
    """The scene GLSL a neural-SDF build wrote before the loop-free writer: the network from the
    transfer networks' generator (layer loops), called once by ``scene_sdf``."""
    from prt.export.glsl import generate_glsl

    network = generate_glsl(onnx_path, "scene_sdf_net0", layout="const")
    wrapper = ("float scene_sdf(vec3 p) {\n    vec4 net0_t[1];\n    scene_sdf_net0(p, vec3(0.0), net0_t);\n"
               "    float d1 = net0_t[0].x;\n    return d1;\n}\n")  # fmt: skip
    return "// SDF scene 'ball.sdf.onnx', generated by prt.train.sdf; do not edit.\n\n" + network + "\n" + wrapper


def test_scene_with_the_old_looped_network_glsl_is_refused(gl_ctx, neural_scene, tmp_path):
    """A neural-SDF scene built before the fix keeps the looped network GLSL, which llvmpipe cuts
    short mid-march: loading it is one line saying to rebuild, not a wrong image."""
    import shutil

    from prt.runtime.errors import GeometryError
    from prt.runtime.renderer import Renderer, Scene

    old = tmp_path / "old"
    shutil.copytree(neural_scene, old)
    glsl = _looped_scene_glsl(old / "ball.sdf.onnx")
    assert re.search(r"\bfor\s*\(", glsl)  # the old generator's layer loops
    (old / "scene_sdf.glsl").write_text(glsl)
    scene = Scene.load(old / "scene.json")
    for backend in ("onnx", "glsl"):
        with pytest.raises(GeometryError, match=r"rebuild the scene with prt-train") as info:
            Renderer(scene, 16, 16, backend=backend, ctx=gl_ctx).close()
        assert "\n" not in str(info.value) and str(old / "scene_sdf.glsl") in str(info.value)


def test_loop_guard_passes_current_network_and_analytic_loops(sphere):
    """The guard looks at network layer functions only: the loop-free network and an analytic
    SDF's own loops (a polyline) pass."""
    from prt.runtime.gbuffer import _refuse_looped_network
    from prt.train.sdf.library import get_sdf

    sdf, _, _ = sphere
    _refuse_looped_network(sdf.glsl(), "ball")
    knot = get_sdf("torus_knot").glsl()
    assert re.search(r"\bfor\s*\(", knot)
    _refuse_looped_network(knot, "torus_knot")
