"""The runtime end to end: the backends agree, relighting runs no network, no NaN, clear errors.

Every renderer draws in the session's GL context (``gl_ctx``), so the conftest's GL error check
covers it; backends come from the ``backend`` fixture, one run per registered backend.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.runtime import EnvmapError, InputError, SpecError
from prt.runtime.backends import BACKENDS, create_backend
from prt.runtime.backends.onnx import OnnxTransfer
from prt.runtime.orbit import render_orbit
from prt.runtime.renderer import Renderer, Scene, ShaderCompileError, demo_scene_path
from prt.runtime.viewer import ViewerOptions

SIZE = 96
REFERENCE = "onnx"  # the backend the others are compared with


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Linear-radiance PSNR with the reference's peak as signal."""
    mse = float(((a.astype(np.float64) - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(float(b.max()) ** 2 / mse)


@pytest.fixture(scope="module")
def sdf_scene(tmp_path_factory):
    """A small SDF scene with network and analytic segments, built by prt-train."""
    out = tmp_path_factory.mktemp("sdf")
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", "sphere_plane", "-o", str(out), "--samples", "6000",
         "--validation", "1500", "--rays", "64", "--epochs", "3", "--batch", "1024", "--segments", "4",
         "--hidden", "8", "--layers", "1", "--target", "0.02", "--no-progress"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out / "scene.json"


@pytest.fixture(params=BACKENDS)
def backend(request) -> str:
    return request.param


def scenes(sdf_scene):
    return {"demo": Scene.load(), "sdf": Scene.load(sdf_scene)}


def render(gl_ctx, scene, backend, material, size=SIZE):
    with Renderer(scene, size, size, backend=backend, ctx=gl_ctx) as r:
        if material == "glossy":
            r.set_material("glossy", albedo=(0.5, 0.5, 0.5), specular=(0.4, 0.4, 0.4), exponent=16)
        return r.render()


@pytest.mark.parametrize("material", ["diffuse", "glossy"])
@pytest.mark.parametrize("backend", [b for b in BACKENDS if b != REFERENCE])
def test_backends_render_the_same_image(gl_ctx, sdf_scene, backend, material):
    for name, scene in scenes(sdf_scene).items():
        reference = render(gl_ctx, scene, REFERENCE, material)
        assert reference.max() > 0.05, name  # something was lit
        assert psnr(render(gl_ctx, scene, backend, material), reference) >= 60.0, (name, backend, material)


def test_unknown_backend_is_an_input_error(gl_ctx):
    scene = Scene.load()
    with pytest.raises(InputError, match="backend must be one of"):
        Renderer(scene, 8, 8, backend="cuda", ctx=gl_ctx)
    with pytest.raises(InputError, match="backend must be one of"):
        create_backend("cuda", gl_ctx, scene.manifest)
    with Renderer(scene, 8, 8, ctx=gl_ctx) as r, pytest.raises(InputError, match="backend must be one of"):
        r.set_backend("cuda")


def test_relighting_reuses_the_transfer_without_running_a_network(gl_ctx, monkeypatch):
    with Renderer(Scene.load(), SIZE, SIZE, backend="onnx", ctx=gl_ctx) as r:
        first = r.render()
        calls = []
        original = OnnxTransfer.infer_sorted  # what the onnx backend runs its networks through
        monkeypatch.setattr(OnnxTransfer, "infer_sorted", lambda *a, **k: calls.append(1) or original(*a, **k))
        runs = r.stats["network_runs"]
        r.set_envmap("studio")
        studio = r.render()
        r.set_material("glossy", albedo=(0.5, 0.5, 0.5), specular=(0.3, 0.3, 0.3), exponent=8)
        r.render()
        r.set_lighting_sh(np.tile([[np.sqrt(4 * np.pi)]] + [[0.0]] * 15, (1, 3)))
        r.render()
        assert calls == [] and r.stats["network_runs"] == runs and r.stats["relight_frames"] == 3
        assert not np.allclose(first, studio)
        # the relit frame equals a full frame with the same light
        r.set_material("diffuse", albedo=(0.6, 0.6, 0.6))
        r.set_envmap("studio")
        relit = r.render()
        r.set_camera_object(r.camera)  # invalidates the transfer
        full = r.render()
        assert calls == [1]
        assert np.array_equal(relit, full)


@pytest.fixture(scope="module")
def ball_scene(tmp_path_factory):
    """An unshadowed sphere built by prt-train (its segments may be analytic)."""
    import trimesh

    tmp_path = tmp_path_factory.mktemp("ball")
    trimesh.creation.icosphere(subdivisions=4).export(tmp_path / "ball.ply")
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(tmp_path / "ball.ply"), "-o", str(tmp_path / "ball"),
         "--samples", "3000", "--validation", "1000", "--rays", "64", "--target", "0.01", "--no-progress"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return tmp_path / "ball"


def test_white_furnace_gives_the_albedo_on_unshadowed_surfaces(gl_ctx, ball_scene, backend):
    light = np.zeros((16, 3))
    light[0] = np.sqrt(4 * np.pi)
    with Renderer(Scene.load(ball_scene), SIZE, SIZE, backend=backend, ctx=gl_ctx) as r:
        r.set_lighting_sh(light)
        r.set_material("diffuse", albedo=(0.25, 0.5, 0.75))
        image = r.render()
        covered = r.gbuffer_image().covered
    assert covered.sum() > 1000
    assert np.allclose(image[covered], [0.25, 0.5, 0.75], atol=2e-4)
    assert (image[~covered] == 0).all()


def test_no_nan_reaches_a_pixel(gl_ctx, sdf_scene, backend):
    for scene in scenes(sdf_scene).values():
        with Renderer(scene, 64, 48, backend=backend, ctx=gl_ctx) as r:
            views = [
                dict(eye=(0, 0.6, 3.2)),
                dict(eye=(0, 0, 5), target=(0, 0, 10)),  # looking away: all background
                dict(eye=(0.0, 0.0, 0.05), target=(0, 0, -1)),  # inside the object
                dict(eye=(0, 5, 0.001), target=(0, 0, 0)),  # almost straight down
            ]
            for view in views:
                r.set_camera(**view)
                for kind in ("diffuse", "glossy"):
                    r.set_material(kind)
                    image = r.render()
                    assert np.isfinite(image).all() and (image >= 0).all()
            r.set_camera(eye=(0, 0, 5), target=(0, 0, 10))
            r.set_background(False)  # the demo draws its env map where no geometry is
            assert (r.render() == 0).all()


def copy_demo(tmp_path) -> Path:
    dst = tmp_path / "demo"
    shutil.copytree(demo_scene_path().parent, dst)
    return dst


def test_bad_models_shaders_and_envmaps_raise_specific_errors(gl_ctx, tmp_path):
    import onnx
    from onnx import TensorProto, helper

    scene_dir = copy_demo(tmp_path)
    # corrupt ONNX file
    (scene_dir / "segments" / "seg000.onnx").write_bytes(b"not a model")
    with Renderer(Scene.load(scene_dir), 32, 32, ctx=gl_ctx) as r, pytest.raises(InputError, match="seg000.onnx"):
        r.render()
    # a model with the wrong input shape
    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 5])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 5])],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, scene_dir / "segments" / "seg000.onnx")
    with Renderer(Scene.load(scene_dir), 32, 32, ctx=gl_ctx) as r, pytest.raises(InputError, match=r"\[N, 6\]"):
        r.render()
    # a generated shader that does not compile: the message names the shader and the driver's error
    scene_dir = copy_demo(tmp_path / "b")
    glsl = scene_dir / "segments" / "seg001.glsl"
    glsl.write_text(glsl.read_text() + "\nthis is not glsl;\n")
    with Renderer(Scene.load(scene_dir), 32, 32, backend="glsl", ctx=gl_ctx) as r, pytest.raises(ShaderCompileError) as err:
        r.render()
    assert "transfer pass" in str(err.value) and "error" in str(err.value).lower() and "\n" not in str(err.value)
    # env map not found / not readable
    with Renderer(Scene.load(), 32, 32, ctx=gl_ctx) as r:
        with pytest.raises(EnvmapError, match="nope.hdr"):
            r.set_envmap(tmp_path / "nope.hdr")
        with pytest.raises(EnvmapError):
            r.set_envmap("no_such_bundled_map")
    # a manifest path escaping its folder
    manifest = (scene_dir / "scene.json").read_text().replace('"segments/seg000.onnx"', '"../../outside.onnx"')
    (scene_dir / "scene.json").write_text(manifest)
    with pytest.raises(SpecError, match="escapes"):
        Scene.load(scene_dir)


def test_orbit_renders_the_views_and_restores_the_camera(gl_ctx, tmp_path, backend):
    options = ViewerOptions(width=24, height=16, backend=backend, envmap="studio", material="glossy", exponent=8.0)
    with options.renderer(Scene.load(), ctx=gl_ctx) as r:
        start = r.camera
        assert r.material.kind == "glossy" and r.material.exponent == 8.0
        summary = render_orbit(r, 2, tmp_path / "frames", warmup=1)
        assert r.camera is start
        frames = r.stats["frames"]
    assert frames == 3 and summary.frames == 2 and summary.backend == backend and summary.fps > 0
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_000.png", "frame_001.png"]
    assert "FPS" in str(summary) and "frame" in summary.median_ms


def test_viewer_cli_headless_frames_and_errors(tmp_path):
    out = tmp_path / "frames"
    proc = subprocess.run(
        [sys.executable, "-m", "prt.runtime.cli", "--headless", "--frames", "3", "--size", "48x32", "--out", str(out)],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "FPS" in proc.stdout and "inference" in proc.stdout
    import imageio.v3 as iio

    frames = sorted(out.glob("frame_*.png"))
    assert len(frames) == 3 and iio.imread(frames[0]).shape == (32, 48, 3)
    for args in (["nope.json", "--headless"], ["--headless", "--size", "0"], ["--headless", "--envmap", "missing.hdr"]):
        proc = subprocess.run([sys.executable, "-m", "prt.runtime.cli", *args, "--out", str(tmp_path / "x")], capture_output=True, text=True)
        assert proc.returncode == 2, (args, proc.stderr)
        assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr


def test_readme_embedding_example_runs():
    """The example in README.md, executed as written (with the bundled demo scene for the tour's build)."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    code = readme.split("```python\nfrom prt.runtime import Scene, Renderer", 1)[1].split("```", 1)[0]
    code = "from prt.runtime import Scene, Renderer" + code
    assert 'Scene.load("my_scene")' in code
    code = code.replace('Scene.load("my_scene")', "Scene.load()")
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    image = namespace["image"]
    assert image.ndim == 3 and image.shape[2] == 3 and np.isfinite(image).all() and image.max() > 0


@pytest.mark.parametrize("backend", ["onnx", "glsl"])
def test_two_renderers_in_one_thread_each_draw_their_own_scene(sdf_scene, backend):
    """Each renderer owns an EGL context; its calls make it current (found by the many-networks
    study: the first renderer's frame ran in the second's context and failed or drew wrongly)."""
    demo, sdf_scene = Scene.load(), Scene.load(sdf_scene)
    alone = {}
    for name, scene, size in (("demo", demo, 48), ("sdf", sdf_scene, 40)):
        with Renderer(scene, size, size, backend=backend) as r:
            alone[name] = r.render().copy()
    with Renderer(demo, 48, 48, backend=backend) as a, Renderer(sdf_scene, 40, 40, backend=backend) as b:
        for name, r in (("demo", a), ("sdf", b), ("demo", a), ("sdf", b)):
            np.testing.assert_array_equal(r.render(), alone[name], err_msg=name)
        a.set_material("glossy")  # state changes go to the right context too
        assert a.render().shape == (48, 48, 3) and np.isfinite(a.render()).all()
    with Renderer(demo, 48, 48, backend=backend) as a:  # closing one leaves the other working
        b = Renderer(sdf_scene, 40, 40, backend=backend)
        b.close()
        np.testing.assert_array_equal(a.render(), alone["demo"])
