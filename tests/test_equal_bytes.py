"""prt-bench --equal-bytes: per-vertex PRT on the mesh decimated to a build's bytes, resampled onto the full mesh."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

import numpy as np
import trimesh

from prt.bench.equal_bytes import decimate, equal_bytes_vertex, resample, vertex_budget
from prt.runtime.normals import vertex_normals
from prt.runtime.sh import unshadowed_transfer


def test_the_vertex_budget_counts_back_sides_in_the_full_meshes_proportion():
    assert vertex_budget(64_000, 16, 1000, 0) == 1000
    assert vertex_budget(256_000, 64, 1000, 0) == 1000
    assert vertex_budget(64_000, 16, 1000, 1000) == 500  # every vertex with a back side: half as many
    assert vertex_budget(10, 16, 1000, 0) == 4  # a triangle's worth at least


def test_decimation_reaches_the_vertex_budget():
    mesh = trimesh.creation.icosphere(subdivisions=5)
    v, f = decimate(mesh.vertices, mesh.faces, 500)
    assert 250 < len(v) <= 500 and f.min() == 0 and f.max() == len(v) - 1
    radius = np.linalg.norm(v, axis=1)
    assert np.abs(radius - 1.0).max() < 0.05  # on the sphere still
    same_v, same_f = decimate(mesh.vertices, mesh.faces, 10**6)
    assert len(same_v) == len(mesh.vertices)


def test_resampling_is_exact_at_coarse_vertices_and_for_linear_fields():
    coarse = trimesh.creation.box().subdivide()
    v, f = np.asarray(coarse.vertices), np.asarray(coarse.faces)
    rng = np.random.default_rng(1)
    gradient = rng.normal(size=(3, 16))
    front = (v @ gradient).astype(np.float32)  # linear in position: barycentric interpolation is exact
    back = -front
    two_sided = np.zeros(len(f), bool)
    normals = vertex_normals(v.astype(np.float32), f).astype(np.float64)
    np.testing.assert_allclose(resample(v, f, two_sided, front, back, v, normals), front, atol=1e-5)
    face = rng.integers(0, len(f), 300)
    points = np.einsum("mk,mkc->mc", rng.dirichlet([1, 1, 1], 300), v[f[face]])
    np.testing.assert_allclose(resample(v, f, two_sided, front, back, points, np.asarray(coarse.face_normals)[face]), points @ gradient,
                               atol=1e-4)  # fmt: skip
    # a two-sided face seen from behind reads the back rows
    np.testing.assert_allclose(resample(v, f, np.ones(len(f), bool), front, back, points, -np.asarray(coarse.face_normals)[face]),
                               -(points @ gradient), atol=1e-4)  # fmt: skip


def test_the_equal_bytes_baseline_of_a_convex_mesh_fits_the_bytes_and_is_its_unshadowed_transfer(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=4)  # 2,562 vertices
    geometry = SimpleNamespace(mesh=mesh, two_sided=np.zeros(len(mesh.faces), bool), kind="mesh")
    target = 16 * 4 * 300  # the bytes of 300 vertices' direct transfer
    logs = []
    front, back, info = equal_bytes_vertex(geometry, target, width=16, bounces=0, face_albedo=np.zeros((len(mesh.faces), 3)), rays=256,
                                           seed=0, cache=tmp_path, geometry_id="ball", log=logs.append)  # fmt: skip
    assert front.shape == (len(mesh.vertices), 16) and info["vertices"] <= 300 and info["weight_bytes"] <= target
    normals = vertex_normals(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces)).astype(np.float64)
    # unoccluded everywhere: the coarse vertices' transfer is U(n) of their normals, interpolated
    assert np.abs(front[:, 0] - unshadowed_transfer(normals, 4)[:, 0]).max() < 5e-3
    again = equal_bytes_vertex(geometry, target, width=16, bounces=0, face_albedo=np.zeros((len(mesh.faces), 3)), rays=256, seed=0,
                               cache=tmp_path, geometry_id="ball", log=logs.append)  # fmt: skip
    np.testing.assert_array_equal(again[0], front)
    assert again[2]["seconds"] == 0.0 and len(logs) == 1  # read from the cache


@pytest.mark.gl
def test_prt_bench_measures_the_equal_bytes_baseline_beside_the_others(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    from prt.bench import cli

    out = tmp_path / "scene"
    proc = subprocess.run([sys.executable, "-m", "prt.train.train_cli", str(Path(__file__).parent / "data" / "spot.obj"), "-o", str(out),
                           "--samples", "3000", "--rays", "16", "--steps", "10", "--batch", "512", "--hidden", "8", "--layers", "1",
                           "--segments", "1", "--bounces", "1", "--bounce-rays", "4", "--no-progress", "--threads", "1"],
                          capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    report = tmp_path / "r.json"
    argv = [str(out / "scene.json"), "--size", "32", "--views", "1", "--ref-rays", "16", "--ref-rays-max", "16", "--ref-hit-rays", "4",
            "--ref-hit-transfer-rays", "4", "--warmup", "0", "--gemm-size", "64", "--backends", "onnx", "vertex", "--precisions", "fp32",
            "--baseline-rays", "16", "--equal-bytes", "--json", str(report), "--md", str(tmp_path / "r.md")]  # fmt: skip
    assert cli.main(argv) == 0
    data = json.loads(report.read_text())
    equal = [r for r in data["records"] if r.get("equal_bytes")]
    net = next(r for r in data["records"] if r["backend"] == "onnx")
    assert {r["material"] for r in equal} == {"diffuse", "glossy"}
    for r in equal:
        assert r["backend"] == "vertex" and r["transfer"] == net["transfer"] == "1 bounce" and r["label"].startswith("vertex equal-bytes")
        assert r["weight_bytes"] <= net["weight_bytes"] and r["equal_bytes"]["target_bytes"] == net["weight_bytes"]
        assert 0 < r["psnr"] < 100
    assert data["scenes"][0]["vertex_baseline"]["equal_bytes"]["vertices"] == equal[0]["equal_bytes"]["vertices"]
    assert "vertex at equal bytes" in (tmp_path / "r.md").read_text()
