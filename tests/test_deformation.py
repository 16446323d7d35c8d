"""Deformable objects: the shape-conditioned network and its twins, the shape code, a small real
build rendered by both backends, the runtime API and the commands' errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh

from prt.export.onnx_model import build_model
from prt.runtime.deformation import Deformation, code_bias, code_features, code_frequencies
from prt.runtime.errors import InputError, SpecError
from prt.train.networks.network import Architecture, TransferMLP, evaluate_numpy


def _network(code_dim=3, code_freqs=2, seed=0):
    arch = Architecture(hidden=16, layers=2, pos_freqs=3, normal_freqs=1, code_dim=code_dim, code_freqs=code_freqs)
    torch.manual_seed(seed)
    model = TransferMLP(arch, np.array([[-1.0, -1, -1], [1, 1, 1]]), np.full(16, 0.5, np.float32), np.zeros(16, np.float32))
    for p in model.parameters():
        torch.nn.init.normal_(p, std=0.4)
    return arch, model


@pytest.mark.parametrize("code_freqs", [0, 2])
def test_code_enters_as_a_per_frame_bias_in_every_twin(code_freqs):
    """torch (concatenated inputs) = numpy (concatenated features) = ONNX (code input) = the static
    network with the per-frame bias of prt.runtime.deformation.code_bias (what the GLSL backend uploads)."""
    import onnxruntime as ort

    arch, model = _network(code_freqs=code_freqs)
    rng = np.random.default_rng(1)
    p, n = rng.uniform(-1, 1, (300, 3)).astype(np.float32), rng.normal(size=(300, 3)).astype(np.float32)
    theta = np.array([0.4, -1.3, 0.9], np.float32)
    codes = np.tile(theta, (300, 1))
    with torch.no_grad():
        ref = model(torch.from_numpy(np.concatenate([p, n, codes], 1))).numpy()
    arrays = model.arrays()
    assert arrays["layer0_weight"].shape == (arch.input_dim, 16) and arrays["code_weight"].shape == (arch.code_features, 16)
    np.testing.assert_allclose(evaluate_numpy(arrays, p, n, codes), ref, atol=2e-5)
    session = ort.InferenceSession(build_model(arrays, {**arch.as_dict(), "bands": 4}).SerializeToString())
    np.testing.assert_allclose(session.run(None, {"x": np.concatenate([p, n], 1), "code": theta[None]})[0], ref, atol=2e-5)
    static = {k: v for k, v in arrays.items() if k not in ("code_weight", "enc_code_freq")}
    static["layer0_bias"] = code_bias(arrays, theta)
    np.testing.assert_allclose(evaluate_numpy(static, p, n), ref, atol=2e-5)
    # and the code matters: another code gives another output
    assert np.abs(evaluate_numpy(arrays, p, n, np.tile(-theta, (300, 1))) - ref).max() > 1e-3


def test_code_features_and_cost():
    b = code_frequencies(2, 2)
    g = code_features(np.array([0.5, -1.0]), b)
    expected = [0.5, -1.0, *np.sin([0.5 * np.pi / 2, -np.pi / 2, 0.5 * np.pi, -np.pi]), *np.cos([0.5 * np.pi / 2, -np.pi / 2, 0.5 * np.pi, -np.pi])]
    np.testing.assert_allclose(g, expected, atol=1e-6)
    static = Architecture(hidden=16, layers=2, pos_freqs=3, normal_freqs=1)
    coded = Architecture(hidden=16, layers=2, pos_freqs=3, normal_freqs=1, code_dim=3, code_freqs=2)
    assert coded.flops_per_fragment() == static.flops_per_fragment()  # the code is folded in once per frame
    assert coded.weight_count() == static.weight_count() + 15 * 16
    assert "code_dim" not in static.as_dict() and coded.as_dict()["code_dim"] == 3


def test_shape_code_spans_the_training_frames():
    from prt.train.deform.deform_build import shape_code, split_frames

    rng = np.random.default_rng(0)
    rest = rng.normal(size=(50, 3))
    modes = rng.normal(size=(2, 50, 3))
    weights = np.stack([np.sin(np.linspace(0, 3, 12)), np.linspace(-1, 2, 12)], 1)
    frames = rest + np.einsum("km,mvc->kvc", weights, modes)
    roles = split_frames(12, 4, 2)
    assert roles["extrapolated"] == [10, 11] and roles["unseen"] == [2, 6] and 0 in roles["train"]
    extreme = split_frames(12, 4, 2, extremeness=np.abs(np.arange(12) - 5.0))
    assert extreme["extrapolated"] == [0, 11] and extreme["unseen"] == [3, 7] and sorted(sum(extreme.values(), [])) == list(range(12))
    for scale in ("common", "component"):
        code = shape_code(rest, frames, roles["train"], scale=scale)
        assert code["dim"] == 2 and code["explained"] > 0.999999 and code["scale"] == scale
        spans = np.abs(code["theta"][roles["train"]]).max(axis=0)
        assert spans[0] == pytest.approx(1.0, abs=1e-6)  # the first component spans [-1, 1] either way
        rebuilt = rest + code["mean"] + np.einsum("kd,dvc->kvc", code["theta"], code["basis"])
        np.testing.assert_allclose(rebuilt, frames, atol=1e-5)  # every frame, also the held-out ones: the modes span them
        if scale == "component":
            np.testing.assert_allclose(spans, 1.0, atol=1e-6)
        else:  # one scale: distances between codes are distances between shapes (the offsets), over every pair of frames
            s0 = float(np.linalg.norm(code["basis"][0]))
            np.testing.assert_allclose(np.linalg.norm(code["basis"].reshape(2, -1), axis=1), s0, rtol=1e-5)
            offsets = (frames - rest).reshape(12, -1)
            shapes = np.linalg.norm(offsets[:, None] - offsets[None], axis=-1)
            codes = s0 * np.linalg.norm(code["theta"][:, None].astype(np.float64) - code["theta"][None], axis=-1)
            np.testing.assert_allclose(codes, shapes, atol=1e-4 * shapes.max())
            assert spans[1] < 1.0  # the second mode moves the mesh less: a smaller range, not stretched to [-1, 1]
    with pytest.raises(SpecError, match="give more frames"):
        split_frames(3, 2, 2)
    from prt.train.deform.deform_build import DeformSpec

    with pytest.raises(SpecError, match="extrapolate_from"):
        DeformSpec(extrapolate_from="middle").check()
    with pytest.raises(SpecError, match="code_dim"):
        DeformSpec(code_dim=99).check()
    with pytest.raises(SpecError, match="code_scale"):
        DeformSpec(code_scale="unit").check()
    with pytest.raises(SpecError, match="residual"):
        DeformSpec(residual="maybe").check()
    with pytest.raises(SpecError, match="code scale"):
        shape_code(rest, frames, roles["train"], scale="unit")


def _box_arm():
    plate = trimesh.creation.box((2.0, 0.1, 2.0))
    plate.apply_translation((0, -0.05, 0))
    arm = trimesh.creation.box((0.25, 1.2, 0.25)).subdivide().subdivide()
    arm.apply_translation((0, 0.6, 0))
    vertices = np.concatenate([plate.vertices, arm.vertices])
    faces = np.concatenate([plate.faces, arm.faces + len(plate.vertices)])
    return vertices, faces


@pytest.fixture(scope="module")
def bent_scene(tmp_path_factory):
    """A small real build: a bar bending over a plate (procedural bend), few samples and steps."""
    from prt.train.deform.deform_build import DeformSpec, run_deform_build
    from prt.train.deform.deform_sources import procedural

    out = tmp_path_factory.mktemp("deform") / "bar"
    source = procedural("bend", np.linspace(0, 60, 7), mesh=_box_arm(), axis="z", path="bar")
    spec = DeformSpec(samples=1500, validation=200, rays=32, steps=80, hidden=16, layers=2, segments=2, pos_freqs=3)
    report = run_deform_build(source, out, spec, threads=2, progress=False, log=lambda *a: None)
    return out, report


def test_build_records_the_deformation(bent_scene):
    out, report = bent_scene
    data = json.loads((out / "scene.json").read_text())
    assert data["version"] == 3 and data["deformation"]["code"]["kind"] == "pca"
    frames = data["deformation"]["frames"]
    assert frames["count"] == 7 and frames["extrapolated"] in ([0], [6]) and set(frames["unseen"]).isdisjoint(frames["train"])  # an end of the range
    assert data["deformation"]["source"]["deformer"] == "bend"
    for seg in data["segments"]:
        assert seg["architecture"]["code_dim"] == data["deformation"]["code"]["dim"] and (out / seg["code"]).is_file()
    assert set(report["frame_errors"]["mean"]) == {"train", "unseen", "extrapolated"}
    # resumable: a second run reuses every frame and fit
    from prt.train.deform.deform_build import DeformSpec, run_deform_build
    from prt.train.deform.deform_sources import procedural

    lines = []
    source = procedural("bend", np.linspace(0, 60, 7), mesh=_box_arm(), axis="z", path="bar")
    spec = DeformSpec(samples=1500, validation=200, rays=32, steps=80, hidden=16, layers=2, segments=2, pos_freqs=3)
    run_deform_build(source, out, spec, threads=2, progress=False, log=lines.append)
    assert not any("traced" in line for line in lines) and sum("cached" in line for line in lines) == len(data["segments"])


def test_both_backends_agree_and_follow_the_pose(bent_scene):
    from prt.bench.metrics import psnr_from_mse
    from prt.runtime import Renderer, Scene
    from prt.runtime.envmaps import bundled_envmap_path

    scene = Scene.load(bent_scene[0])
    assert isinstance(scene.deformation, Deformation) and scene.deformation.frame_count == 7
    images = {}
    for backend in ("onnx", "glsl"):
        with Renderer(scene, 96, 96, backend=backend) as r:
            r.set_camera(eye=(2.0, 1.4, 2.4), target=(0, 0, 0))
            for key in (0, 6):
                r.set_deformation(frame=key)
                images[backend, key] = r.render()
            r.set_deformation(theta=np.full(scene.deformation.dim, 0.3))
            images[backend, "theta"] = r.render()
            relit = r.stats["network_runs"]
            r.set_envmap(bundled_envmap_path("studio"))
            r.render()
            assert r.stats["network_runs"] == relit  # relighting a pose runs no network
    for key in (0, 6, "theta"):
        a, b = images["onnx", key], images["glsl", key]
        assert psnr_from_mse(float(np.mean((a - b) ** 2))) > 60
    assert np.abs(images["onnx", 0] - images["onnx", 6]).mean() > 1e-3  # the pose changed the frame


def test_a_new_pose_behind_a_still_camera_redraws_the_background(bent_scene):
    """The background layer where the bar was and is no more: the env map, not what the layer held before."""
    from prt.runtime import Renderer, Scene
    from prt.runtime.envmaps import bundled_envmap_path

    scene = Scene.load(bent_scene[0])
    with Renderer(scene, 64, 64) as r:
        r.set_envmap(bundled_envmap_path("studio"))
        r.set_background(True)
        r.set_camera(eye=(2.0, 1.4, 2.4), target=(0, 0, 0))
        covered = {}
        for key in (0, 6):
            r.set_deformation(frame=key)
            image = r.render()
            covered[key] = r.covered_mask()
        uncovered = covered[0] & ~covered[6]
        assert uncovered.sum() > 20  # the bend moved the bar off these pixels
        full = r._background.image(r.camera, r._envmap_rotation)  # the map at every pixel, drawn afresh
        assert np.array_equal(image[uncovered], full[uncovered])


def test_gbuffer_carries_the_rest_position(bent_scene):
    from prt.runtime import Renderer, Scene

    scene = Scene.load(bent_scene[0])
    with Renderer(scene, 64, 64) as r:
        r.set_camera(eye=(2.0, 1.4, 2.4), target=(0, 0, 0))
        r.set_deformation(frame=6)
        r.render()
        packed = r.gbuffer.read_packed()
        world = r.gbuffer.read_world()
    covered = packed[:, 3] > 0.5
    rest_points, posed = packed[covered, :3], world[covered]
    d = scene.deformation
    # every rest position lies on the rest mesh's bounding box; the posed ones of the bent bar do not
    lo, hi = d.rest.min(0) - 1e-4, d.rest.max(0) + 1e-4
    assert ((rest_points >= lo) & (rest_points <= hi)).all()
    assert np.abs(rest_points - posed).max() > 0.05


def test_set_deformation_errors(bent_scene):
    from prt.runtime import Renderer, Scene

    scene = Scene.load(bent_scene[0])
    with Renderer(scene, 32, 32) as r:
        with pytest.raises(InputError, match="out of range"):
            r.set_deformation(frame=7)
        with pytest.raises(InputError, match=f"{scene.deformation.dim} finite numbers"):
            r.set_deformation(theta=[np.nan] * scene.deformation.dim)
        with pytest.raises(InputError, match="exactly one"):
            r.set_deformation()
    with Renderer(Scene.load(), 32, 32) as r:  # the demo is static
        with pytest.raises(InputError, match="not deformable"):
            r.set_deformation(frame=0)


def test_runtime_animates_headless(bent_scene, tmp_path):
    out = tmp_path / "frames"
    run = subprocess.run([sys.executable, "-m", "prt.runtime.cli", str(bent_scene[0]), "--headless", "--animate", "--frames", "3",
                          "--size", "48", "--out", str(out)], capture_output=True, text=True)  # fmt: skip
    assert run.returncode == 0, run.stderr
    images = sorted(out.glob("*.png"))
    assert len(images) == 3
    import imageio.v3 as iio

    assert not np.array_equal(iio.imread(images[0]), iio.imread(images[-1]))
    bad = subprocess.run([sys.executable, "-m", "prt.runtime.cli", "--headless", "--animate", "--frames", "2", "--size", "32",
                          "--out", str(tmp_path / "x")], capture_output=True, text=True)  # fmt: skip
    assert bad.returncode == 2 and "needs a deformable scene" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_train_refuses_bad_deform_input_with_one_line(tmp_path):
    from prt.train.train_cli import main

    glb = "tests/data/character/minetest_character.glb"
    out = tmp_path / "never"
    code = main([glb, "--deform", "gltf:animation=dance", "-o", str(out), "--no-progress"])
    assert code == 2 and not out.exists()


def test_static_bench_sends_deformable_scenes_to_the_deform_bench(bent_scene, tmp_path, capsys):
    from prt.bench.cli import main

    code = main([str(bent_scene[0]), "--views", "1", "--size", "32", "--json", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert code == 2 and "prt-bench deform" in err and not (tmp_path / "r.json").exists()


def test_glossy_shading_takes_the_posed_position(bent_scene):
    """Glossy shading needs the view direction at the posed point (the G-buffer's second target):
    the CPU shading (onnx) and the shade pass (glsl) agree at a bent pose."""
    from prt.bench.metrics import psnr_from_mse
    from prt.runtime import Renderer, Scene

    scene = Scene.load(bent_scene[0])
    images = []
    for backend in ("onnx", "glsl"):
        with Renderer(scene, 64, 64, backend=backend) as r:
            r.set_camera(eye=(2.0, 1.4, 2.4), target=(0, 0, 0))
            r.set_material("glossy", albedo=(0.5, 0.5, 0.5), specular=(0.5, 0.5, 0.5), exponent=32)
            r.set_deformation(frame=6)
            images.append(r.render())
    assert psnr_from_mse(float(np.mean((images[0] - images[1]) ** 2))) > 60
