"""Hostile and careless input to the runtime, the API and prt-bench (issue 16): one test per class.

The scenes are the hostile corpus's tiny quad scene (tests/hostile/cases_runtime.py) with one
thing broken; renderers draw 8x8 pixels in the session's GL context unless a test needs its own.
"""

from __future__ import annotations

import errno
import gc
import json
import re
import sys
import threading
import tomllib
from pathlib import Path

import moderngl
import numpy as np
import pytest
from onnx import TensorProto, helper, numpy_helper

from prt.runtime import cli
from prt.runtime.camera import Camera
from prt.runtime.errors import ArgumentTypeError, FrameError, InputError, PRTError, RendererStateError, SpecError
from prt.runtime.gl import ShaderCompileError, compile_program
from prt.runtime.onnxfile import external_data_tensors, read_model
from prt.runtime.orbit import render_orbit
from prt.runtime.renderer import Renderer, Scene
from prt.shaders import Source, assemble

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "hostile"))
import cases_runtime as corpus  # noqa: E402

pytestmark = pytest.mark.gl


def write_scene(folder: Path, manifest=None, **files) -> Path:
    """The corpus's quad scene in ``folder`` with ``manifest`` / ``files`` (``seg000__onnx=...``) replaced."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, content in corpus._scene(manifest, **files).items():
        (folder / name).write_bytes(content if isinstance(content, bytes) else content.encode())
    return folder / "scene.json"


@pytest.fixture
def quad(tmp_path) -> Scene:
    return Scene.load(write_scene(tmp_path / "quad"))


def nan_network(tmp_path) -> Scene:
    return Scene.load(write_scene(tmp_path / "nan", seg000__onnx=corpus._model(bias=np.full(16, np.nan, np.float32)),
                                  seg000__glsl=corpus.GLSL.replace("vec4(0.6, 0.05, 0.05, 0.05)", "vec4(sqrt(-1.0 - abs(position.x)))")))  # fmt: skip


# ----------------------------------------------------------------------------- 2: NaN and Inf


@pytest.mark.parametrize("backend", ["onnx", "glsl"])
def test_a_network_giving_nan_is_a_frame_error_in_both_backends(gl_ctx, tmp_path, backend):
    scene = nan_network(tmp_path)
    with Renderer(scene, 8, 8, backend=backend, ctx=gl_ctx) as r:
        with pytest.raises(FrameError, match=r"the transfer is NaN or Inf at \d+ pixels"):
            r.render()
        with pytest.raises(FrameError):  # relighting the same view does not hand out the broken transfer
            r.render()
        with pytest.raises(FrameError):
            r.render_transfer()
        r.set_camera_object(r.camera.orbit(0.1))
        with pytest.raises(FrameError, match=r"the transfer is NaN or Inf at \d+ pixels"):
            r.draw()  # a frame left on the GPU is checked too, without reading it back (an occlusion query)


def test_inputs_are_checked_in_float32(gl_ctx, quad):
    with Renderer(quad, 8, 8, ctx=gl_ctx) as r:
        with pytest.raises(InputError, match=r"Lighting\.sh: .*float32"):
            r.set_lighting_sh(np.full((16, 3), 1e39))
        with pytest.raises(InputError, match=r"Material\.albedo: .*float32"):
            r.set_material("diffuse", albedo=(1e39, 0, 0))
        with pytest.raises(InputError, match=r"Material\.exponent: .*float32"):
            r.set_material("glossy", exponent=1e300)
        with pytest.raises(InputError, match=r"Camera: eye: .*float32"):
            r.set_camera(eye=(0, 0, 1e308))
        with pytest.raises(InputError, match="NaN or Inf"):
            r.set_camera(eye=(0, float("nan"), 3))
        # Finite inputs whose product overflows float32: the frame is refused, not black.
        r.set_lighting_sh(np.full((16, 3), 1e37))
        r.set_material("diffuse", albedo=(100.0, 100.0, 100.0))
        with pytest.raises(FrameError, match="NaN or Inf values after shading"):
            r.render()


def test_manifest_numbers_beyond_float32_are_spec_errors(tmp_path):
    for field, value in [("material.albedo.0", 1e39), ("lighting.sh.0.0", -1e39), ("camera.eye.2", 1e308)]:
        path = write_scene(tmp_path / field, corpus._set(field, value))
        with pytest.raises(SpecError, match="is not finite in float32"):
            Scene.load(path)


def test_a_nan_frame_exits_2_without_a_png(tmp_path, capsys):
    scene = nan_network(tmp_path).path
    out = tmp_path / "frames"
    assert cli.main([str(scene), "--headless", "--size", "8", "--frames", "2", "--out", str(out)]) == 2
    assert "the transfer is NaN or Inf" in capsys.readouterr().err
    assert not out.exists()


# ----------------------------------------------------------------------------- 3: external data


def _external(tensor, location="../../etc/passwd"):
    tensor.ClearField("raw_data")
    tensor.data_location = TensorProto.EXTERNAL
    tensor.external_data.add(key="location", value=location)
    return tensor


def test_models_with_external_data_anywhere_are_refused(tmp_path):
    def w():
        return numpy_helper.from_array(np.zeros((6, 16), np.float32), "W")

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 6])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 16])

    def model(nodes, inits=(), sparse=()):
        graph = helper.make_graph(nodes, "g", [x], [y], list(inits), sparse_initializer=list(sparse))
        return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()

    matmul = helper.make_node("MatMul", ["x", "W"], ["y"])
    sub = helper.make_graph([helper.make_node("Constant", [], ["c"], value=_external(numpy_helper.from_array(np.ones(1, np.float32), "c")))],
                            "sub", [], [helper.make_tensor_value_info("c", TensorProto.FLOAT, [1])])  # fmt: skip
    sparse_values = _external(numpy_helper.from_array(np.ones(1, np.float32), "S"))
    sparse = helper.make_sparse_tensor(sparse_values, numpy_helper.from_array(np.zeros(1, np.int64), "Si"), [6, 16])
    models = {
        "initializer": model([matmul], [_external(w())]),
        "constant attribute": model([helper.make_node("Constant", [], ["W"], value=_external(w())), matmul]),
        "subgraph": model([helper.make_node("If", ["x"], ["y"], then_branch=sub, else_branch=sub)], [w()]),
        "sparse initializer": model([matmul], sparse=[sparse]),
    }
    location_only = w()
    location_only.external_data.add(key="location", value="/etc/hostname")  # data_location left DEFAULT
    models["location only"] = model([matmul], [location_only])
    for where, data in models.items():
        assert external_data_tensors(data) == (2 if where == "subgraph" else 1), where
        (tmp_path / "m.onnx").write_bytes(data)
        with pytest.raises(InputError, match=r"m\.onnx: \d tensor\(s\) keep their data in external files"):
            read_model(tmp_path / "m.onnx")
    assert external_data_tensors(corpus._model()) == 0
    for bad in (b"", b"\xff" * 10, corpus._model()[:-3]):
        with pytest.raises(ValueError):
            external_data_tensors(bad)


def test_the_onnxruntime_floor_confines_external_data_itself():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    floor = next(d for d in project["dependencies"] if d.startswith("onnxruntime"))
    version = tuple(int(v) for v in re.search(r">=([\d.]+)", floor).group(1).split("."))
    assert version >= (1, 24, 3)  # models loaded from bytes: external paths checked (onnxruntime PR 27430)


# ----------------------------------------------------------------------------- 4: threads


def test_a_renderer_refuses_calls_from_another_thread(gl_ctx, quad):
    with Renderer(quad, 8, 8, ctx=gl_ctx) as r:
        errors = []

        def other():
            for call in (r.render, lambda: r.set_camera(eye=(0, 0, 2)), r.close):
                try:
                    call()
                except RendererStateError as exc:
                    errors.append(str(exc))

        thread = threading.Thread(target=other, name="worker")
        thread.start()
        thread.join()
        assert len(errors) == 3 and "belongs to the thread that created it" in errors[0]
        assert r.render().shape == (8, 8, 3)  # still usable, and still its own camera, in its own thread


# ----------------------------------------------------------------------------- 9: lifetime


def test_render_after_close_and_release_on_collection(gl_ctx, quad):
    closed = Renderer(quad, 8, 8, ctx=gl_ctx)
    closed.render()
    closed.close()
    closed.close()  # harmless
    for call in (closed.render, closed.render_transfer, lambda: closed.set_backend("glsl"), lambda: closed.set_lighting_sh(np.zeros((16, 3)))):
        with pytest.raises(RendererStateError, match="used after close"):
            call()
    r = Renderer(quad, 8, 8, ctx=gl_ctx)
    r.render()
    texture, program = r._out_texture, r._shade_program
    del r
    gc.collect()
    assert isinstance(texture.mglo, moderngl.InvalidObject) and isinstance(program.mglo, moderngl.InvalidObject)
    own = Renderer(quad, 8, 8)  # its own context, released too
    ctx = own.ctx
    del own
    gc.collect()
    assert isinstance(ctx.mglo, moderngl.InvalidObject)


# ----------------------------------------------------------------------------- 10: no empty folders


def test_orbit_output_folder_only_when_there_is_something_to_write(gl_ctx, tmp_path, quad):
    with Renderer(nan_network(tmp_path), 8, 8, ctx=gl_ctx) as r, pytest.raises(FrameError):
        render_orbit(r, 2, tmp_path / "a" / "b")
    assert not (tmp_path / "a").exists()
    with Renderer(quad, 8, 8, ctx=gl_ctx) as r:
        calls = {"n": 0}
        render = r.render

        def fails_on_the_third_frame():
            calls["n"] += 1
            if calls["n"] == 5:  # 2 warm-up frames, then views 0, 1 written, view 2 fails
                raise FrameError("broken")
            return render()

        r.render = fails_on_the_third_frame
        with pytest.raises(FrameError):
            render_orbit(r, 4, tmp_path / "c" / "d")
        assert not (tmp_path / "c").exists()  # the frames written and the folders made are gone
        r.render = render
        summary = render_orbit(r, 2, tmp_path / "e")
        assert sorted(p.name for p in summary.out.iterdir()) == ["frame_000.png", "frame_001.png"]


def test_a_full_disk_is_one_line_and_leaves_no_frames(tmp_path, monkeypatch, capsys):
    import prt.runtime.files as files

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full)
    scene = write_scene(tmp_path / "quad")
    out = tmp_path / "frames"
    assert cli.main([str(scene), "--headless", "--size", "8", "--frames", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "No space left on device" in err and "frame_000.png" in err
    assert not out.exists()


# ----------------------------------------------------------------------------- 11: GLSL errors


def test_a_glsl_compile_error_names_the_users_file_and_its_own_line(gl_ctx, tmp_path):
    broken = corpus.GLSL.replace("    t[3] = vec4(0.05);", "    t[3] = vec4(0.05)\n    t[3] = vec4(0.05);")
    scene = Scene.load(write_scene(tmp_path / "s", seg000__glsl=broken))
    with Renderer(scene, 8, 8, backend="glsl", ctx=gl_ctx) as r:
        with pytest.raises(ShaderCompileError) as info:
            r.render()
    assert re.match(rf"{re.escape(str(tmp_path / 's' / 'seg000.glsl'))}:7: GLSL compile failed \(.*\): error", str(info.value))


def test_assembled_sources_map_every_line_to_its_file():
    fill = Source.from_file("float f() {\n    return 1.0;\n}", "/scene/seg.glsl")
    text = assemble("sh_basis.glsl", "transfer_pass.frag", defines={"A": 1}, fills={"networks": fill, "dispatch": "case 0:\nbreak;"})
    lines = text.split("\n")
    assert text.where(1) == ("#version", 1) and text.where(2) == ("#define", 1)
    assert text.where(lines.index("    return 1.0;") + 1) == ("/scene/seg.glsl", 2)
    assert text.where(lines.index("break;") + 1) == ("${dispatch}", 2)
    frag = lines.index("uniform sampler2D u_position;  // xyz, covered") + 1
    own = (ROOT / "shaders" / "transfer_pass.frag").read_text().split("\n").index("uniform sampler2D u_position;  // xyz, covered") + 1
    assert text.where(frag) == ("transfer_pass.frag", own)


def test_bundled_shader_errors_name_the_bundled_file(gl_ctx):
    source = assemble("sh_basis.glsl", "packed_eval.frag", fills={"body": Source.from_file("void main() {\n  f_out = nope;\n}", "body.glsl")})
    with pytest.raises(ShaderCompileError, match=r"^body\.glsl:2: GLSL compile failed \(test\): error: .*nope"):
        compile_program(gl_ctx, source, "test")


# ----------------------------------------------------------------------------- 5, 12: one-line errors


def test_wrong_python_types_in_the_api_are_project_errors(gl_ctx, quad):
    with pytest.raises(ArgumentTypeError, match="width must be an integer, got '64'"):
        Renderer(quad, "64", 64, ctx=gl_ctx)
    with pytest.raises(ArgumentTypeError, match="scene must be a Scene"):
        Renderer("scene.json", 8, 8, ctx=gl_ctx)
    with pytest.raises(ArgumentTypeError, match=r"Scene: expected a Manifest, got str; open a file with Scene.load\('scene.json'\)"):
        Scene("scene.json")
    with pytest.raises(ArgumentTypeError, match="expected a Manifest, got NoneType$"):
        Scene(None)
    with pytest.raises(ArgumentTypeError):
        Renderer(quad, 8, 8, backend=["onnx"], ctx=gl_ctx)
    with pytest.raises(InputError, match="threads .* must be >= 1, got -1"):
        Renderer(quad, 8, 8, threads=-1, ctx=gl_ctx)
    with pytest.raises(InputError, match="this OpenGL driver allows at most"):
        Renderer(quad, 100000, 8, ctx=gl_ctx)
    with Renderer(quad, 8, 8, ctx=gl_ctx) as r:
        for call, error in [
            (lambda: r.set_camera(eye="abc"), ArgumentTypeError),
            (lambda: r.set_camera(eye=None), ArgumentTypeError),
            (lambda: r.set_camera(fov="wide"), ArgumentTypeError),
            (lambda: r.set_camera_object("camera"), ArgumentTypeError),
            (lambda: r.set_envmap(42), ArgumentTypeError),
            (lambda: r.set_lighting_sh("bright"), ArgumentTypeError),
            (lambda: r.set_lighting_sh(np.ones((9, 3))), InputError),  # 3 bands for a 4-band scene
            (lambda: r.set_material("glossy", albedo="red"), ArgumentTypeError),
            (lambda: r.set_material(7), InputError),
        ]:
            with pytest.raises(error) as info:
                call()
            assert isinstance(info.value, PRTError) and "\n" not in str(info.value)
    with pytest.raises(ArgumentTypeError):
        Scene.load(42)
    with pytest.raises(ArgumentTypeError):
        Camera(eye=[0, 0, "x"], target=[0, 0, 0])


def test_onnx_input_name_and_type(gl_ctx, tmp_path):
    named = Scene.load(write_scene(tmp_path / "named", seg000__onnx=corpus._model(input_name="points")))
    with Renderer(named, 8, 8, ctx=gl_ctx) as r:
        assert r.render().max() > 0  # fed by its own name
    wrong = Scene.load(write_scene(tmp_path / "f64", seg000__onnx=corpus._model(
        weight=np.zeros((6, 16), np.float64), bias=np.zeros(16, np.float64), input_type=TensorProto.DOUBLE)))  # fmt: skip
    with Renderer(wrong, 8, 8, ctx=gl_ctx) as r, pytest.raises(InputError, match="model input must be one float32 tensor"):
        r.render()


def test_nul_bytes_and_non_utf8_glsl(gl_ctx, tmp_path):
    with pytest.raises(SpecError, match="holds a control character"):
        Scene.load(write_scene(tmp_path / "nul", corpus._set("geometry.file", "geometry\x00.npz")))
    with pytest.raises(SpecError):
        Scene.load(str(tmp_path / "nul\x00" / "scene.json"))
    scene = Scene.load(write_scene(tmp_path / "latin", seg000__glsl="// Gr\u00fc\u00dfe\n".encode("latin-1")))
    with Renderer(scene, 8, 8, backend="glsl", ctx=gl_ctx) as r, pytest.raises(InputError, match=r"seg000\.glsl: GLSL is not UTF-8 text \(byte 5\)"):
        r.render()


@pytest.mark.parametrize("flag", [["--threads", "-1"], ["--threads", "0"], ["--frames", "-3"], ["--exposure", "nan"], ["--size", "100000"]])
def test_cli_flags_are_checked_before_anything_is_written(tmp_path, capsys, flag):
    scene = write_scene(tmp_path / "quad")
    out = tmp_path / "frames"
    assert cli.main([str(scene), "--headless", "--size", "8", "--frames", "1", *flag, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and flag[0] in err or "image size" in err
    assert not out.exists()


# ----------------------------------------------------------------------------- 6: prt-bench


def test_bench_skips_a_broken_scene_and_reports_the_rest(tmp_path, capsys):
    from prt.bench import cli as bench

    good = write_scene(tmp_path / "good")
    bad = write_scene(tmp_path / "bad", seg000__onnx=corpus._model(bias=np.full(16, np.nan, np.float32)))
    missing = tmp_path / "missing" / "scene.json"
    report = tmp_path / "report.json"
    argv = [str(bad), str(good), str(missing), *[a.replace("{run}", str(tmp_path)) for a in corpus.BENCH_FAST], "--cache", str(tmp_path / "cache")]
    assert bench.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "seg000.onnx: the network gives NaN" in err[0] and "manifest not found" in err[1]
    data = json.loads(report.read_text())
    assert [s["path"] for s in data["scenes"]] == [str(good.resolve())]
    assert [f["scene"] for f in data["failed"]] == [str(bad), str(missing)]
    assert data["records"] and all(r["scene"] == "quad" for r in data["records"])
