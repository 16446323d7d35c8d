"""The deformable-scene benchmark (prt.bench.deform_bench, issue 24): the linear morphable model
against plain twins, the nearest-frame choice, the report's fields and the frame-time ratio, on a
tiny bending bar built in the test."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from prt.bench import deform_bench
from prt.bench.deform_bench import DeformBench, Settings, fit_lmm, nearest_training_frame, select_frames
from prt.runtime.renderer import Renderer, Scene, demo_scene_path

SIZE = 32
LIGHTS = ["scene", "studio"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A bar on a plate bent over 7 frames (4 train, 2 unseen, 1 extrapolated), one tiny network."""
    from prt.train.deform.deform_build import DeformSpec, run_deform_build
    from prt.train.deform.deform_sources import procedural

    bar = trimesh.creation.box((0.3, 2.0, 0.3)).subdivide().subdivide()
    plate = trimesh.creation.box((2.0, 0.1, 2.0))
    plate.apply_translation((0, -1.05, 0))
    vertices = np.concatenate([bar.vertices, plate.vertices])
    faces = np.concatenate([bar.faces, plate.faces + len(bar.vertices)])
    source = procedural("bend", np.linspace(0, 60, 7), mesh=(vertices, faces), path="tinybar")
    out = tmp_path_factory.mktemp("deform") / "scene"
    spec = DeformSpec(samples=400, validation=100, rays=16, steps=30, hidden=8, layers=1, segments=1, holdout_every=3, extrapolate=1, code_freqs=1,
                      residual="on")  # a residual network with a code: both backends add the unshadowed term back
    run_deform_build(source, out, spec, threads=1, progress=False, log=lambda *_: None)
    return out


@pytest.fixture(scope="module")
def bench_run(tiny, tmp_path_factory):
    """One run of the command on the tiny scene: (exit status, JSON report, Markdown, image folder)."""
    folder = tmp_path_factory.mktemp("bench")
    argv = [str(tiny), "--size", str(SIZE), "--ref-rays", "8", "--repeats", "3", "--warmup", "1", "--threads", "1",
            "--lights", *LIGHTS, "--json", str(folder / "r.json"), "--md", str(folder / "r.md"), "--images", str(folder / "img")]
    status = deform_bench.main(argv)
    return status, json.loads((folder / "r.json").read_text()), (folder / "r.md").read_text(), folder / "img"


# ------------------------------------------------------------------ the linear morphable model


def _plain_lmm(transfers, theta, k):
    """Plain twin: PCA by the eigenvectors of the frames' Gram matrix, coefficients by explicit dot
    products, the regression by the normal equations."""
    x = np.asarray(transfers, np.float64).reshape(len(transfers), -1)
    mean = np.array([x[:, j].sum() / len(x) for j in range(x.shape[1])])
    centred = x - mean
    gram = centred @ centred.T
    values, vectors = np.linalg.eigh(gram)
    order = np.argsort(values)[::-1][:k]
    basis = np.stack([centred.T @ vectors[:, i] / np.sqrt(values[i]) for i in order])
    coeffs = np.array([[float(np.dot(centred[f], basis[j])) for j in range(k)] for f in range(len(x))])
    design = np.concatenate([np.ones((len(theta), 1)), np.asarray(theta, np.float64)], axis=1)
    regression = np.linalg.solve(design.T @ design, design.T @ coeffs)
    return mean, basis, coeffs, regression


@pytest.mark.gl
def test_lmm_reproduces_training_frames_of_the_scene(tiny, tmp_path):
    """K = Kt - 1: every training frame's vertex transfer back from its PCA coefficients, and the
    regression equals the normal equations' (same fitted codes up to the components' signs)."""
    bench = DeformBench(tiny, Settings(size=SIZE, ref_rays=8, cache=tmp_path, lights=("scene",)), log=lambda *_: None)
    vertex, _ = bench.vertex_frames()
    train = bench.roles["train"]
    transfers = np.stack([vertex[f] for f in train])
    theta = bench.deformation.theta[train]
    lmm = fit_lmm(transfers, theta, components=len(train) - 1)
    assert lmm.components == len(train) - 1
    scale = np.abs(transfers).max()
    for i in range(len(train)):
        assert np.abs(lmm.reconstruct(lmm.coeffs[i]) - transfers[i]).max() < 1e-9 * scale
    mean, basis, coeffs, regression = _plain_lmm(transfers, theta, lmm.components)
    signs = np.sign(np.sum(basis * lmm.basis, axis=1))
    assert np.allclose(lmm.mean, mean)
    assert np.allclose(lmm.basis, basis * signs[:, None], atol=1e-8)
    assert np.allclose(lmm.coeffs, coeffs * signs, atol=1e-8 * scale)
    fitted = np.concatenate([np.ones((len(train), 1)), theta], axis=1) @ lmm.regression
    assert np.allclose(fitted, (np.concatenate([np.ones((len(train), 1)), theta], axis=1) @ regression) * signs, atol=1e-6 * scale)
    if theta.shape[1] + 1 < len(train):  # fewer code dimensions than frames: the linear fit cannot be exact
        assert not np.allclose(fitted, lmm.coeffs, atol=1e-6 * scale)


def test_lmm_predicts_training_frames_exactly_when_codes_span_them():
    """Kt - 1 components and a (Kt - 1)-d code: the regression interpolates, predict(theta_i) = frame i."""
    rng = np.random.default_rng(3)
    transfers, theta = rng.normal(size=(5, 20, 16)), rng.normal(size=(5, 4))
    lmm = fit_lmm(transfers, theta, components=4)
    for i in range(5):
        assert np.allclose(lmm.predict(theta[i]), transfers[i], atol=1e-9)
    plain = lmm.mean.reshape(20, 16) + sum(c * b.reshape(20, 16) for c, b in zip(np.concatenate([[1.0], theta[2]]) @ lmm.regression, lmm.basis))
    assert np.allclose(lmm.predict(theta[2]), plain)


def test_lmm_size_by_variance_and_bytes():
    """A rank-1 family needs one component at 99.9 %; a rank-3 one three; bytes count mean, basis, regression."""
    rng = np.random.default_rng(0)
    theta = rng.normal(size=(6, 2))
    direction = rng.normal(size=(10, 16))
    rank1 = 1.0 + theta[:, :1, None] * direction[None]
    assert fit_lmm(rank1, theta).components == 1
    rank3 = rank1 + rng.normal(size=(6, 1, 1)) * rng.normal(size=(10, 16)) + rng.normal(size=(6, 1, 1)) * rng.normal(size=(10, 16))
    lmm = fit_lmm(rank3, theta)
    assert lmm.components == 3
    assert lmm.stored_bytes(10) == 4 * (10 * 16 * 4 + 3 * 3)


def test_nearest_training_frame_matches_brute_force():
    rng = np.random.default_rng(1)
    codes = rng.uniform(-1, 1, size=(12, 3))
    train = [0, 2, 3, 5, 7, 8, 11]
    for f in range(12):
        best = min(train, key=lambda t: (sum((codes[t][i] - codes[f][i]) ** 2 for i in range(3)), train.index(t)))
        assert nearest_training_frame(codes[f], codes, train) == best
        if f in train:
            assert nearest_training_frame(codes[f], codes, train) == f
    twins = np.zeros((3, 2))
    assert nearest_training_frame(np.zeros(2), twins, [2, 0, 1]) == 2  # ties: the first listed


def test_select_frames():
    roles = {"train": [0, 1, 2, 4, 5, 6, 8], "unseen": [3, 7], "extrapolated": [9]}
    picked = select_frames(roles, 3)
    assert picked == {"train": [0, 4, 8], "unseen": [3, 7], "extrapolated": [9]}
    assert select_frames(roles, 0)["train"] == [] and select_frames(roles, 50)["train"] == roles["train"]


# ------------------------------------------------------------------ the command


@pytest.mark.gl
def test_report_fields(bench_run, tiny):
    status, report, text, images = bench_run
    assert status == 0 and not report["failed"]
    (entry,) = report["scenes"]
    manifest = Scene.load(tiny).manifest
    roles = manifest.deformation.frames
    measured = [f["frame"] for f in entry["frames"]]
    assert set(roles["unseen"]) | set(roles["extrapolated"]) <= set(measured)
    assert entry["lights"] == LIGHTS
    for f in entry["frames"]:
        for light in LIGHTS:
            for method in deform_bench.METHODS:
                m = f["metrics"][light][method]
                assert 0 < m["psnr"] <= 100 and -1 <= m["ssim"] <= 1
            assert f["glsl_max_abs_diff"][light] < 1e-3  # the GLSL backend agrees with ONNX
        if f["role"] == "train":
            assert f["nearest_train_frame"] == f["frame"]
        else:
            assert f["nearest_train_frame"] in roles["train"]
    noise = entry["frames"][0]["reference_noise"]
    assert set(noise) == set(LIGHTS) and all(0 < v["psnr"] < 100 for v in noise.values())  # two seeds differ
    assert all("reference_noise" not in f for f in entry["frames"][1:])
    assert entry["summary"]["reference_noise"]["lights"] == noise
    assert entry["bytes"]["ours"] == sum(s.weight_bytes for s in manifest.segments)
    assert entry["baseline_vertices"] == entry["vertices"]  # no --vertex-subdivide
    rows = entry["vertices"] + entry["back_vertices"]
    assert entry["bytes"]["nearest_vertex_per_frame"] == 64 * rows
    assert entry["bytes"]["nearest_vertex_all_frames"] == 64 * rows * len(roles["train"])
    assert 1 <= entry["lmm"]["components"] <= len(roles["train"]) - 1
    summary = entry["summary"]
    for light in LIGHTS:
        assert set(summary["targets"][light]) == {"unseen_gap_db", "unseen_ssim", "extrapolated_ours_minus_lmm_db", "train_ours_minus_nearest_db"}
        lead = summary["means"][light]["ours"]["train"]["psnr"] - summary["means"][light]["nearest_vertex"]["train"]["psnr"]
        assert summary["targets"][light]["train_ours_minus_nearest_db"]["value"] == pytest.approx(lead, abs=2e-3)
        ours = [f["metrics"][light]["ours"]["psnr"] for f in entry["frames"] if f["role"] == "unseen"]
        assert summary["means"][light]["ours"]["unseen"]["psnr"] == pytest.approx(np.mean(ours), abs=1e-3)
    assert "| onnx |" in text and "| glsl |" in text and "extrapolated" in text
    assert report["provenance"]["commit"] is None or isinstance(report["provenance"]["commit"], str)
    assert {"date", "command", "machine"} <= set(report["provenance"])
    png = trimesh.util.wrap_as_stream((images / "deform_tinybar.png").read_bytes())
    import imageio.v3 as iio

    strip = iio.imread(png)
    assert strip.shape[1] == 5 * SIZE and strip.shape[0] == SIZE * len({f["role"] for f in entry["frames"]})


@pytest.mark.gl
def test_frame_time_ratio_is_measured(bench_run):
    """Both backends: medians of both kinds of frames and their ratio."""
    _, report, _, _ = bench_run
    timing = report["scenes"][0]["frame_time"]
    assert set(timing) == {"onnx", "glsl"}
    for t in timing.values():
        assert t["static_ms"] > 0 and t["pose_ms"] > 0 and t["repeats"] == 3
        assert t["ratio"] == pytest.approx(t["pose_ms"] / t["static_ms"], rel=1e-3)
    assert report["scenes"][0]["summary"]["pose_ratio"]["onnx"]["value"] == timing["onnx"]["ratio"]


@pytest.mark.gl
def test_both_kinds_of_frame_run_the_networks(tiny):
    """The static frame of the timing is not a free relight: each round runs the networks twice."""
    with Renderer(Scene.load(tiny), SIZE, SIZE, threads=1) as r:
        r.render()
        before = r.stats["network_runs"]
        deform_bench.frame_times(r, [1, 2], repeats=2, warmup=1)
        assert r.stats["network_runs"] - before == 2 * 3
        assert r.stats["relight_frames"] == 0


@pytest.mark.gl
def test_reference_points_lie_on_the_posed_mesh(tiny, tmp_path):
    """The reference is traced at the posed positions (read_world), not the rest positions the networks read."""
    bench = DeformBench(tiny, Settings(size=SIZE, ref_rays=8, cache=tmp_path, lights=("scene",)), log=lambda *_: None)
    frame = _farthest_frame(bench)
    with Renderer(bench.scene, SIZE, SIZE, threads=1) as r:
        r.set_deformation(frame=frame)
        r.render()
        gb = r.gbuffer.read()
        world = r.gbuffer.read_world().reshape(SIZE, SIZE, 3)[gb.covered]
    posed, rest = bench.pose(frame)[0].mesh, bench.geometry.mesh
    assert _distance_to_mesh(world, posed).max() < 1e-3
    assert _distance_to_mesh(world, rest).max() > 1e-2


def _farthest_frame(bench) -> int:
    """The frame farthest from the rest pose."""
    d = bench.deformation
    return int(np.argmax(np.abs(d.frames - d.rest[None]).max(axis=(1, 2))))


def _distance_to_mesh(points, mesh) -> np.ndarray:
    """Each point's distance to the nearest triangle (every pair tried)."""
    from prt.train.inputs.adaptive import closest_on_triangles

    corners = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]  # (F, 3, 3)
    p = np.asarray(points, np.float64)[:, None, :]
    closest, _ = closest_on_triangles(p, corners[None, :, 0], corners[None, :, 1], corners[None, :, 2])
    return np.linalg.norm(closest - p, axis=2).min(axis=1)


def test_subdivided_poses_stay_on_the_posed_surface(tiny, tmp_path):
    """Subdividing each pose: one topology for every frame, the old vertices first, every new vertex the
    midpoint of an old edge of that pose (a loop over the faces), sidedness repeated per child face."""
    bench = DeformBench(tiny, Settings(size=SIZE, ref_rays=8, cache=tmp_path, lights=("scene",), vertex_subdivide=1), log=lambda *_: None)
    coarse = bench.pose(0)[0]
    far = _farthest_frame(bench)
    fine = [bench.vertex_pose(f)[0] for f in (0, far)]
    assert np.array_equal(fine[0].mesh.faces, fine[1].mesh.faces)
    assert len(fine[0].mesh.faces) == 4 * len(coarse.mesh.faces)
    assert np.array_equal(fine[0].two_sided, np.repeat(coarse.two_sided, 4))
    for f, geometry in zip((0, far), fine):
        posed = bench.deformation.frames[f].astype(np.float64)
        v = np.asarray(geometry.mesh.vertices)
        assert np.allclose(v[: len(posed)], posed)
        midpoints = {tuple(np.round((posed[a] + posed[b]) / 2, 6)) for tri in coarse.mesh.faces for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))}
        assert {tuple(p) for p in np.round(v[len(posed):], 6)} == midpoints


def test_bad_input_is_one_line(tiny, capsys):
    assert deform_bench.main([str(tiny), "--lights", "no_such_map"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no_such_map" in err[0]


@pytest.mark.gl
def test_static_scene_is_refused(tmp_path, capsys):
    assert deform_bench.main([str(demo_scene_path()), "--size", "16", "--json", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    assert "not a deformable scene" in err and "Traceback" not in err
    assert not (tmp_path / "r.json").exists()
