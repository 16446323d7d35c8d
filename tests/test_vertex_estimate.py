"""The build's per-vertex PRT estimate and the "vertex" sizing rule it sets the bar of."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from prt.runtime.sh import unshadowed_transfer
from prt.train.networks.rightsize import ENDINGS, PSNR_CAP, pooled_psnr, shaded_psnr
from prt.train.transport.vertex_estimate import VertexEstimate, estimate_vertex_prt, vertex_samples

DATA = Path(__file__).parent / "data"


def _loop_predict(est: VertexEstimate, points, normals, faces):
    """Plain twin of VertexEstimate.predict: per sample, weights from a 3x3 solve, the side by the face normal."""
    out = []
    for p, n, f in zip(points, normals, faces):
        a, b, c = est.vertices[est.faces[f]]
        m = np.stack([b - a, c - a, np.cross(b - a, c - a)], axis=1)
        v, w, _ = np.linalg.solve(m, p - a)
        weights = (1 - v - w, v, w)
        behind = est.two_sided[f] and np.dot(np.cross(b - a, c - a), n) < 0
        table = est.back if behind else est.front
        out.append(sum(wk * table[vk] for wk, vk in zip(weights, est.faces[f])))
    return np.asarray(out)


def test_predict_interpolates_its_triangles_vertex_rows_on_the_side_of_the_sample():
    rng = np.random.default_rng(3)
    mesh = trimesh.creation.icosphere(subdivisions=1)
    faces = np.asarray(mesh.faces)
    est = VertexEstimate(front=rng.normal(size=(len(mesh.vertices), 64)).astype(np.float32),
                         back=rng.normal(size=(len(mesh.vertices), 64)).astype(np.float32), vertices=np.asarray(mesh.vertices, np.float64),
                         faces=faces, two_sided=rng.random(len(faces)) < 0.5, weight_bytes=0, rays=1)  # fmt: skip
    face = rng.integers(0, len(faces), 400)
    bary = rng.dirichlet([1, 1, 1], 400)
    points = np.einsum("mk,mkc->mc", bary, est.vertices[faces[face]])
    normals = np.asarray(mesh.face_normals)[face] * np.where(rng.random(400) < 0.5, 1.0, -1.0)[:, None]
    np.testing.assert_allclose(est.predict(points, normals, face), _loop_predict(est, points, normals, face), atol=2e-5)
    # at a vertex, seen from the front: its own front row
    corner = est.vertices[faces[face[:5], 0]]
    np.testing.assert_allclose(est.predict(corner, np.asarray(mesh.face_normals)[face[:5]], face[:5]), est.front[faces[face[:5], 0]], atol=1e-5)


def test_vertex_samples_give_open_faces_a_back_side():
    quad = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    geometry = SimpleNamespace(mesh=quad, two_sided=np.array([True, True]))
    points, normals, front, back = vertex_samples(geometry)
    assert len(points) == 8 and (front >= 0).all() and (back >= 0).all()
    np.testing.assert_allclose(normals[back], -normals[front])


def test_the_estimate_of_a_convex_mesh_is_its_unshadowed_transfer_and_takes_the_baselines_bytes(tmp_path):
    from prt.train.inputs.geometry import load_geometry

    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.ply")
    geometry = load_geometry(str(tmp_path / "ball.ply"))
    n = len(geometry.mesh.vertices)
    est = estimate_vertex_prt(geometry, tmp_path / "cache", rays=256, bands=4, seed=0, chunk_size=256, threads=1, log=lambda s: None)
    assert est.front.shape == (n, 16) and est.weight_bytes == 4 * 16 * n
    _, normals, front, _ = vertex_samples(geometry)
    expect = unshadowed_transfer(normals[front], 4)
    assert np.abs(est.front[:, 0] - expect[:, 0]).max() < 1e-3  # DC: cosine-importance sampling is exact unoccluded
    assert np.abs(est.front - expect).max() < 0.05
    # with bounces: "direct+rgb"; no bounce ray of a convex mesh hits it, so no indirect light
    albedo = np.full((len(geometry.mesh.faces), 3), 0.8)
    est = estimate_vertex_prt(geometry, tmp_path / "cache", rays=64, bands=4, seed=0, chunk_size=256, bounces=2, face_albedo=albedo,
                              threads=1, log=lambda s: None)  # fmt: skip
    assert est.front.shape == (n, 64) and est.weight_bytes == 4 * 64 * n
    assert np.all(est.front[:, 16:] == 0.0) and len(list((tmp_path / "cache").glob("indirect-*.npz"))) == 1


def test_the_estimates_indirect_part_is_the_vertex_baselines(tmp_path):
    """The build's estimate and prt-bench's vertex baseline with the same bounces compute the indirect part alike."""
    from prt.bench.vertex_prt import vertex_indirect as bench_indirect
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.vertex_estimate import vertex_indirect

    geometry = load_geometry(str(DATA / "CornellBox-Original.obj"))
    points, normals, _, _ = vertex_samples(geometry)
    direct = unshadowed_transfer(normals, 4).astype(np.float32)
    albedo = np.full((len(geometry.mesh.faces), 3), 0.5)
    ours = vertex_indirect(geometry, points, normals, direct, albedo, 2, rays=16, seed=0)
    assert bench_indirect is vertex_indirect and np.abs(ours).max() > 0.0  # the box's walls light each other


def test_pooled_psnr_is_the_psnr_of_all_samples_together():
    rng = np.random.default_rng(0)
    light = {"l": rng.normal(size=(16, 3)) * 0.3 + np.r_[[[1.0, 1.0, 1.0]], np.zeros((15, 3))]}
    truth = [rng.normal(size=(n, 16)) * 0.1 + 0.3 for n in (50, 200, 7)]
    pred = [t + rng.normal(size=t.shape) * s for t, s in zip(truth, (0.01, 0.003, 0.05))]
    parts = [(len(t), shaded_psnr(p, t, light, 16)["l"]) for p, t in zip(pred, truth)]
    whole = shaded_psnr(np.concatenate(pred), np.concatenate(truth), light, 16)["l"]
    assert pooled_psnr(parts) == pytest.approx(whole, abs=1e-9)
    assert pooled_psnr([]) == PSNR_CAP


def test_a_default_build_sizes_each_segment_against_vertex_prt_and_says_where_it_ended(tmp_path):
    out = tmp_path / "spot"
    proc = subprocess.run([sys.executable, "-m", "prt.train.train_cli", str(DATA / "spot.obj"), "-o", str(out), "--quality", "draft",
                           "--samples", "4000", "--validation", "1500", "--rays", "32", "--segments", "2", "--steps", "40", "--batch", "1024",
                           "--bounces", "1", "--bounce-rays", "4", "--no-progress", "--threads", "1"], capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "build.json").read_text())
    z = report["sizing"]
    assert z["rule"] == "vertex" and z["ended"] in ENDINGS and z["margin_db"] == 1.0
    assert z["vertex_bytes"] == 4 * 64 * report["memory"]["vertices"]  # spot is closed: no back sides
    rows = [r for r in report["segments"] if "vertex" in r]
    assert rows and all(r["sizing"]["rule"] == "vertex" and r["vertex"]["ended"] in ENDINGS for r in rows)
    for light, value in z["network_psnr_db"].items():
        assert value == pytest.approx(pooled_psnr([(r["validation_samples"], r["sizing"]["psnr_db"][light]) for r in rows]), abs=1e-3)
    for r in rows:  # the gain is the worst light's, and a network within its byte share (or the smallest size)
        gain = min(r["sizing"]["psnr_db"][k] - r["vertex"]["psnr_db"][k] for k in r["vertex"]["psnr_db"])
        assert r["vertex"]["gain_db"] == pytest.approx(gain, abs=2e-3)
        assert r["vertex"]["ended"] != "error" or gain >= 1.0
        if r["kind"] == "network" and r["vertex"]["ended"] != "bytes":
            assert r["weight_bytes"] <= r["vertex"]["byte_budget"]
    manifest = json.loads((out / "scene.json").read_text())
    assert all(s["sizing"]["rule"] == "vertex" and s["sizing"]["ended"] in ENDINGS for s in manifest["segments"])
    assert "vs vertex" in proc.stdout and "sizing: networks" in proc.stdout and "ended:" in proc.stdout
    assert "preset: draft (set by hand:" in proc.stdout
    assert report["preset"]["quality"] == "draft" and report["preset"]["differs"]["samples"] == [100_000, 4000]


def test_sdf_scenes_fall_back_to_the_match_rule(tmp_path):
    from prt.train.build import BuildSpec, run_build, spec_from_dict

    data = {**BuildSpec(geometry="sphere_plane").to_dict(), "samples": 1500, "validation": 600, "rays": 16, "segments": 1, "steps": 5,
            "batch": 256, "ladder": [{"hidden": 8, "layers": 1}], "bounces": 0}  # fmt: skip
    del data["ladder"]
    spec = spec_from_dict({k: v for k, v in data.items() if v is not None and k not in ("target", "match", "vertex_margin")})
    assert spec.vertex_margin is not None
    lines = []
    report = run_build(spec, tmp_path / "out", threads=1, progress=False, log=lines.append)
    assert any("needs a triangle mesh" in line for line in lines)
    assert "sizing" not in report and all(s["sizing"]["rule"] in ("match", "fixed") for s in report["segments"] if "sizing" in s)
