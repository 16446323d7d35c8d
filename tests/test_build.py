"""prt-train end to end on small scenes: stages, caching, manifest, analytic segments, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import trimesh

from prt.runtime.camera import DEFAULT_CAMERA
from prt.runtime.manifest import load_manifest
from prt.runtime.errors import SpecError
from prt.train.build import PRECOMPUTE_FIELDS, BuildSpec, spec_from_dict
from prt.train.presets import DEFAULT_QUALITY, PRESETS
from prt.train.networks.fit import DEFAULT_STEPS, FitSettings
from prt.train.transport.precompute import PrecomputeSettings
from prt.train.train_cli import main as prt_train_main

DATA = Path(__file__).parent / "data"
QUICK = ["--samples", 4000, "--validation", 1500, "--rays", 64, "--epochs", 4, "--batch", 512, "--bounces", 0, "--no-progress"]


def prt_train(*args):
    return subprocess.run([sys.executable, "-m", "prt.train.train_cli", *map(str, args)], capture_output=True, text=True)


@pytest.fixture(scope="module")
def spot_build(tmp_path_factory):
    out = tmp_path_factory.mktemp("spot")
    proc = prt_train(DATA / "spot.obj", "-o", out, *QUICK, "--segments", 3, "--hidden", 16, "--layers", 2, "--no-analytic")
    assert proc.returncode == 0, proc.stderr
    return out, proc


def test_build_writes_a_loadable_scene(spot_build):
    out, proc = spot_build
    manifest = load_manifest(out / "scene.json")
    assert manifest.sh_bands == 4 and manifest.geometry.type == "mesh"
    assert len(manifest.segments) >= 1
    rng = np.random.default_rng(0)
    for seg in manifest.segments:
        assert seg.kind == "network" and seg.model.is_file() and seg.glsl.is_file()
        assert seg.architecture["hidden"] == 16 and seg.architecture["layers"] == 2
        sess = ort.InferenceSession(str(seg.model), providers=["CPUExecutionProvider"])
        y = sess.run(None, {"x": rng.normal(size=(7, 6)).astype(np.float32)})[0]
        assert y.shape == (7, 16) and np.isfinite(y).all()
    with np.load(out / "geometry.npz") as g:
        assert g["faces"].shape[1] == 3 and np.abs(g["vertices"]).max() <= 1.0 + 1e-6
    report = json.loads((out / "build.json").read_text())
    assert report["memory"]["weight_bytes"] > 0
    assert report["memory"]["vertex_storage_bytes"] == report["memory"]["vertices"] * 64
    # the table names every segment and the memory comparison
    assert "k16-l2" in proc.stdout and "per-vertex" in proc.stdout


def test_a_new_build_shows_its_environment_as_background(spot_build):
    """The build records the map its light was projected from (a copy in the folder, background on):
    the background draws it where no geometry is, and the shading's light is the stored SH."""
    from prt.runtime import Renderer, Scene
    from prt.runtime.envmap import load_envmap_sh
    from prt.runtime.envmaps import bundled_envmap_path
    from prt.train.networks.rightsize import SCENE_LIGHT

    out, _ = spot_build
    manifest = load_manifest(out / "scene.json")
    lighting = manifest.lighting
    assert lighting.background and lighting.envmap == (out / "envmap.hdr").resolve()
    assert lighting.envmap.read_bytes() == bundled_envmap_path(SCENE_LIGHT).read_bytes()
    assert json.loads((out / "scene.json").read_text())["lighting"]["envmap"] == "envmap.hdr"  # inside the folder: it travels with it
    np.testing.assert_allclose(load_envmap_sh(lighting.envmap, 4), lighting.sh, rtol=1e-6, atol=1e-7)
    with Renderer(Scene.load(out), 48, 48) as r:
        image, covered = r.render(), r.covered_mask()
        assert r.background and covered.any() and not covered.all()
        assert (image[~covered].max(axis=-1) > 0).all()  # the sky, not black
        r.set_background(False)
        assert r.render()[~covered].max() == 0


def test_rerun_reuses_every_stage(spot_build):
    out, _ = spot_build
    before = {p: p.stat().st_mtime_ns for p in (out / "train").glob("*.npz")}
    again = prt_train(DATA / "spot.obj", "-o", out, *QUICK, "--segments", 3, "--hidden", 16, "--layers", 2, "--no-analytic")
    assert again.returncode == 0, again.stderr
    assert "up to date" in again.stdout and "cached" in again.stdout
    assert before == {p: p.stat().st_mtime_ns for p in (out / "train").glob("*.npz")}


def test_unshadowed_segments_need_no_network(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=4)
    sphere.export(tmp_path / "ball.ply")
    out = tmp_path / "ball"
    proc = prt_train(tmp_path / "ball.ply", "-o", out, *QUICK, "--segments", 2, "--target", 0.01)
    assert proc.returncode == 0, proc.stderr
    manifest = load_manifest(out / "scene.json")
    assert all(seg.kind == "analytic" and seg.model is None for seg in manifest.segments)
    assert manifest.memory.weight_bytes == 0
    assert "analytic" in proc.stdout


def test_match_right_sizes_against_a_reference_size(tmp_path):
    fixed = tmp_path / "fixed"
    # plain networks (--residual off): one fit per size, so each reference is read from the cache once
    proc = prt_train(DATA / "spot.obj", "-o", fixed, *QUICK, "--segments", 2, "--hidden", 32, "--layers", 2, "--no-analytic", "--residual", "off")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "match"
    out.mkdir()
    (out / "precompute").symlink_to(fixed / "precompute")  # one ground truth, as the paper table shares it
    proc = prt_train(DATA / "spot.obj", "-o", out, *QUICK, "--segments", 2, "--match", "32x2", "--match-tolerance", 0.5, "--residual", "off")
    assert proc.returncode == 0, proc.stderr
    # the references are the fixed build's networks, read from the fit cache in the shared precompute
    fixed_report = json.loads((fixed / "build.json").read_text())
    assert proc.stdout.count("k32-l2-f6: fitted before on this precompute (cached)") == len(fixed_report["segments"])
    report = json.loads((out / "build.json").read_text())
    ref_flops = None
    for seg in report["segments"]:
        tried = seg["tried"]
        assert tried[0]["arch"].startswith("k32-l2") and tried[0]["reference"]
        fixed_seg = next(f for f in fixed_report["segments"] if f["id"] == seg["id"])
        assert tried[0]["val_mae"] == fixed_seg["val_mae"]
        ref_flops = tried[0]["flops"]
        assert seg["bar"] == pytest.approx(tried[0]["val_mae"] * 1.5)
        if seg["kind"] == "network":
            assert seg["flops_per_fragment"] <= ref_flops and seg["val_mae"] <= seg["bar"] + 1e-12
            assert seg["met_target"]
        # every smaller rung tried but the last cleared the bar (the walk stops at the first miss)
        assert all(t["val_mae"] <= seg["bar"] for t in tried[1:-1])
    assert ref_flops is not None


def test_spec_file_and_its_errors(tmp_path, capsys):
    spec = {"geometry": "sphere_plane", "samples": 3000, "validation": 1000, "rays": 32, "epochs": 2,
            "batch": 512, "segments": 2, "fixed": {"hidden": 8, "layers": 1, "pos_freqs": 2}, "glsl_layout": "texture"}
    (tmp_path / "ok.json").write_text(json.dumps(spec))
    proc = prt_train(tmp_path / "ok.json", "-o", tmp_path / "ok", "--no-progress", "--no-analytic")
    assert proc.returncode == 0, proc.stderr
    m = load_manifest(tmp_path / "ok" / "scene.json")
    assert m.geometry.type == "sdf" and (tmp_path / "ok" / "scene_sdf.glsl").is_file()
    assert {s.architecture["hidden"] for s in m.segments} == {8}
    for seg in m.segments:  # texture layout: the weights travel as a texture file
        texture = np.load(seg.glsl_weights)
        assert texture.ndim == 3 and texture.shape[2] == 4 and np.isfinite(texture).all()
        assert "_weights" in seg.glsl.read_text()

    bad = {
        "typo.json": ({**spec, "sampels": 10}, "sampels"),
        "type.json": ({**spec, "rays": "many"}, "rays"),
        "ladder.json": ({**spec, "fixed": {"hidden": 8, "depth": 2}}, "fixed.depth"),
        "match.json": ({**spec, "fixed": None, "match": {"hidden": 0, "layers": 2}}, "match.hidden"),
        "both.json": ({**spec, "match": {"hidden": 64, "layers": 4}}, "match"),
        "tolerance.json": ({**spec, "fixed": None, "match_tolerance": 3}, "match_tolerance"),
        "json.json": (None, "line 1"),
    }
    for name, (content, field) in bad.items():
        (tmp_path / name).write_text(json.dumps(content) if content is not None else "{oops")
        assert prt_train_main([str(tmp_path / name), "-o", str(tmp_path / "x")]) == 2
        line = capsys.readouterr().err.strip()
        assert "\n" not in line and field in line and name in line, line


def test_spec_is_flat_outside_and_composed_inside():
    """Spec files and build.json name the precompute settings flat; the spec holds a PrecomputeSettings."""
    spec = BuildSpec()
    assert spec.precompute == PrecomputeSettings() and spec.camera == json.loads(json.dumps(DEFAULT_CAMERA))
    flat = spec.to_dict()
    assert "precompute" not in flat and "chunk_size" not in flat and set(PRECOMPUTE_FIELDS) < set(flat)
    assert list(flat)[:2] == ["geometry", "name"]
    again = spec_from_dict({**flat, "geometry": "x", "samples": 123, "merge": False, "epochs": 3})
    assert again.precompute == PrecomputeSettings(samples=123, merge=False)
    assert (again.epochs, again.bands, again.seed) == (3, 4, 0)
    assert spec_from_dict(again.to_dict()) == again


def test_old_specs_with_epochs_load_and_steps_reach_the_fit_settings():
    """Issue 12: training is by steps; an old build.json (epochs, no steps) still loads and trains by epochs as it did."""
    old = {k: v for k, v in BuildSpec(geometry="x").to_dict().items() if k not in ("steps", "time_budget")}
    spec = spec_from_dict({**old, "epochs": 100})
    assert (spec.steps, spec.epochs, spec.time_budget) == (None, 100, None)
    assert spec.fit_settings().plan(80_000)[1:3] == (1000, 10)  # 100 epochs of 10 batches, validated per epoch
    assert spec_from_dict(old).fit_settings().plan(80_000)[1] == PRESETS[DEFAULT_QUALITY]["steps"]  # no steps field: the preset's
    assert spec_from_dict({**old, "steps": None}).fit_settings().plan(80_000)[1] == DEFAULT_STEPS  # "steps": null, as build.json writes it
    settings = spec_from_dict({**old, "steps": 77, "time_budget": 9.5}).fit_settings()
    assert (settings.steps, settings.epochs, settings.max_seconds) == (77, None, 9.5)
    for field, value in (("steps", 0), ("time_budget", 0), ("time_budget", "1"), ("epochs", 1.5)):
        with pytest.raises(SpecError, match=field):
            spec_from_dict({**old, field: value})


def test_fit_cache_keys_change_with_the_training_settings(tmp_path):
    """Changed training settings must not reuse stale fits (the fit cache is keyed by them)."""
    from prt.train.build import _FitCache
    from prt.train.networks.network import Architecture

    arch = Architecture(hidden=8, layers=1)
    paths = {_FitCache(tmp_path, "key", 0, FitSettings(**kw))._paths(arch)[0].name
             for kw in ({}, {"steps": 10}, {"steps": 11}, {"epochs": 5}, {"max_seconds": 3.0}, {"batch": 64})}  # fmt: skip
    assert len(paths) == 6


def test_bad_inputs_fail_in_one_line(tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    cases = [
        ["no_such_sdf", "-o", tmp_path / "a"],
        [DATA / "spot.obj", "-o", tmp_path / "file" / "out"],
        [DATA / "spot.obj", "-o", tmp_path / "b", "--hidden", 16],
        [DATA / "spot.obj", "-o", tmp_path / "c", "--match", "64"],
    ]
    for args in cases:
        assert prt_train_main([*map(str, args), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_static_int8_study_runs_on_a_build(spot_build, tmp_path):
    """studies/int8_static.py: three versions per segment, each timed and each about as accurate."""
    out, _ = spot_build
    report = tmp_path / "int8.json"
    script = Path(__file__).resolve().parents[1] / "studies" / "int8_static.py"
    proc = subprocess.run([sys.executable, str(script), str(out / "scene.json"), "--rows", "256", "--repeats", "2",
                           "--calibration", "256", "--json", str(report)], capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    data = json.loads(report.read_text())
    assert data["segments"]
    for row in data["segments"]:
        assert set(row["ms"]) == {"fp32", "int8-dynamic", "int8-static"} and all(v > 0 for v in row["ms"].values())
        # quantisation moves the error, it must not wreck it (8 bits of a tanh output ~ 0.004)
        assert row["mae"]["int8-static"] < row["mae"]["fp32"] + 0.01
        assert row["mae"]["int8-dynamic"] < row["mae"]["fp32"] + 0.01


def test_graph_fold_study_runs_on_a_build(spot_build, tmp_path):
    """studies/onnx_graph_fold.py: both graphs timed per segment, and they agree on held-out samples."""
    out, _ = spot_build
    report = tmp_path / "fold.json"
    script = Path(__file__).resolve().parents[1] / "studies" / "onnx_graph_fold.py"
    proc = subprocess.run([sys.executable, str(script), str(out / "scene.json"), "--rows", "256", "--repeats", "2",
                           "--json", str(report)], capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    data = json.loads(report.read_text())
    assert data["segments"]
    for row in data["segments"]:
        assert set(row["ms"]) == {"exported", "folded"} and all(v > 0 for v in row["ms"].values())
        assert row["max_abs_diff"] < 1e-5
    bad = subprocess.run([sys.executable, str(script), str(tmp_path / "missing.json")], capture_output=True, text=True)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "Traceback" not in bad.stderr
