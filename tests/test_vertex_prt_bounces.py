"""Per-vertex PRT with interreflection (issue 25): the build's bounce estimator on the vertices.

- The integrating sphere (as tests/test_bounce_reference.py): inside a bowl every point gets direct
  light f = (1 - h) / 2 and bounce k (a (1 - f))^k f; the bowl is open, so its inside is the
  vertices' back side.
- A white furnace: inside a closed box every bounce ray hits, so a constant T_0 gives T_b = a^b T_0
  exactly, the geometric series.
- A plain twin: a per-sample loop over the same rays against the sparse products, and the mapping
  from samples back to the vertices' front and back sides.
- bounces = 0 gives the direct-only transfer exactly, and 4 raster passes of "direct+rgb" with zero
  indirect give the 1-pass direct raster bit for bit.
- ``prt-bench`` on a tiny 1-bounce Cornell box: vertex rows direct and "1 bounce" beside each other,
  every record's ``transfer`` in the JSON and the Markdown table.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from prt.bench import cli
from prt.bench.bounce_reference import face_albedo
from prt.bench.vertex_prt import VertexPRT, vertex_bounce_transfer, vertex_indirect, vertex_samples, vertex_transfer
from prt.runtime.camera import Camera
from prt.runtime.normals import vertex_normals
from prt.train.inputs.geometry import Geometry
from prt.train.transport.interreflection import trace_bounce_rays
from prt.train.transport.transfer import make_tracer

DATA = Path(__file__).resolve().parent / "data"
H = 0.3
F_OPEN = (1 - H) / 2
ALBEDO = np.array([0.8, 0.5, 0.2])
DC = np.sqrt(4 * np.pi)  # SH coefficient of a constant radiance of 1


def _geometry(mesh, two_sided: bool, name: str = "thing") -> Geometry:
    n = len(mesh.faces)
    return Geometry(mesh=mesh, object_ids=np.zeros(n, np.int64), object_names=[name], two_sided=np.full(n, two_sided),
                    to_source=np.eye(4), source=name, sdf=None)  # fmt: skip


@pytest.fixture(scope="module")
def bowl(tmp_path_factory):
    """An open sphere (cap above y = H removed): vertex samples, direct transfer (cached) and tracer."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    mesh = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 1] < H], process=False)
    mesh.remove_unreferenced_vertices()
    geometry = _geometry(mesh, two_sided=True, name="bowl")
    cache = tmp_path_factory.mktemp("vertex_cache")
    front, back, back_vertices = vertex_transfer(geometry, make_tracer(geometry), 256, cache, "bowl")
    return geometry, front, back, back_vertices, cache


def test_vertex_samples_are_fronts_then_open_backs(bowl):
    geometry, _, _, back_vertices, _ = bowl
    points, normals, front_row, back_row = vertex_samples(geometry)
    n_vertices = len(geometry.mesh.vertices)
    assert back_vertices == n_vertices and len(points) == 2 * n_vertices  # every vertex of an open surface has two sides
    np.testing.assert_array_equal(points[front_row], points[back_row])
    np.testing.assert_allclose(normals[front_row], -normals[back_row])
    outward = geometry.mesh.vertices / np.linalg.norm(geometry.mesh.vertices, axis=1, keepdims=True)
    assert (np.einsum("vc,vc->v", normals[front_row], outward) > 0.9).all()


@pytest.mark.parametrize("bounces", [1, 2])
def test_the_inside_of_a_bowl_is_the_integrating_sphere(bowl, bounces):
    geometry, front, back, _, cache = bowl
    albedo = face_albedo({"bowl": ALBEDO}, geometry)
    front64, back64, _ = vertex_bounce_transfer(geometry, front, back, albedo, bounces, rays=256, seed=0, cache=cache, geometry_id="bowl")
    assert front64.shape == back64.shape == (len(front), 64)
    inside = back64[:, 16:].reshape(-1, 3, 16)[:, :, 0] * DC  # (V, RGB) indirect DC under a constant sky of 1
    r = ALBEDO * (1 - F_OPEN)
    exact = F_OPEN * sum(r**k for k in range(1, bounces + 1))
    np.testing.assert_allclose(inside.mean(axis=0), exact, rtol=0.03)
    assert np.std(inside[:, 0]) < 0.15 * exact[0]  # the same at every vertex, up to the rays' noise
    # The outside sees only the sky: no ray comes back from a convex surface.
    assert np.abs(front64[:, 16:]).max() < 1e-6 * np.abs(front64[:, :16]).max()
    np.testing.assert_array_equal(front64[:, :16], front)
    np.testing.assert_array_equal(back64[:, :16], back)


def test_a_white_furnace_closed_box_gives_the_geometric_series():
    """Inside a closed box (inward normals) every bounce ray hits: constant T_0 -> T_b = a^b T_0."""
    box = trimesh.creation.box(extents=(2.0, 1.5, 1.0)).subdivide().subdivide()
    inside_out = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)  # normals point in
    geometry = _geometry(inside_out, two_sided=False)
    points, normals, _, _ = vertex_samples(geometry)
    t0 = np.random.default_rng(0).normal(size=16)
    direct = np.tile(t0, (len(points), 1))
    albedo = np.tile([0.9, 0.6, 0.3], (len(inside_out.faces), 1))
    for bounces in (1, 3):
        indirect = vertex_indirect(geometry, points, normals, direct, albedo, bounces, rays=64, seed=4)
        series = sum(np.array([0.9, 0.6, 0.3]) ** b for b in range(1, bounces + 1))
        np.testing.assert_allclose(indirect, np.broadcast_to(t0[None, :, None] * series, indirect.shape), rtol=1e-5, atol=1e-6)


def _loop_twin(geometry, front, back, albedo, bounces: int, rays: int, seed: int):
    """The interreflected vertex transfer by plain loops: samples listed one vertex at a time, each
    bounce a per-sample, per-ray sum over the same rays, then copied back vertex by vertex."""
    vertices = np.asarray(geometry.mesh.vertices, dtype=np.float32)
    faces = np.asarray(geometry.mesh.faces)
    vertex_normal = vertex_normals(vertices, faces).astype(np.float32)
    normal_of = {v: vertex_normal[v] for v in range(len(vertices)) if np.linalg.norm(vertex_normal[v]) > 0}
    open_vertices = sorted({int(v) for f, face in enumerate(faces) if geometry.two_sided[f] for v in face})
    samples = [(v, +1) for v in range(len(vertices)) if v in normal_of] + [(v, -1) for v in open_vertices]
    points = np.array([vertices[v] for v, _ in samples])
    normals = np.array([side * normal_of[v] for v, side in samples])
    direct = [front[v] if side > 0 else back[v] for v, side in samples]
    found = trace_bounce_rays(geometry.mesh, points, normals, rays=rays, seed=seed, clear=False)  # the estimator's lookup
    previous = [np.repeat(t[:, None], 3, axis=1).astype(np.float64) for t in direct]
    indirect = [np.zeros((16, 3)) for _ in samples]
    for _ in range(bounces):
        current = []
        for s in range(len(samples)):
            total = np.zeros((16, 3))
            for j in range(rays):
                q = found.nearest[s, j]
                if q >= 0:
                    total += albedo[found.hit_face[s, j]][None, :] * previous[q]
            current.append(total / rays)
        indirect = [a + b for a, b in zip(indirect, current)]
        previous = current
    out_front = np.zeros((len(vertices), 64), np.float32)
    out_front[:, :16] = front
    out_back = out_front.copy()
    out_back[:, :16] = back
    for (v, side), ind in zip(samples, indirect):
        target = [out_front, out_back] if side > 0 else [out_back]
        for out in target:
            out[v, 16:] = ind.T.reshape(-1)
    return out_front, out_back


def test_sparse_products_match_a_per_sample_loop(tmp_path):
    """A floor (open: both sides) under a closed box, coloured apart: the fast path against the loop twin."""
    floor = trimesh.creation.box(extents=(2.0, 0.02, 2.0))
    floor = trimesh.Trimesh(floor.vertices * [1, 0, 1], floor.faces[floor.face_normals[:, 1] > 0.5], process=False)
    floor = floor.subdivide().subdivide()
    floor.remove_unreferenced_vertices()
    cube = trimesh.creation.box(extents=(0.6, 0.6, 0.6)).subdivide()
    cube.apply_translation([0.0, 0.35, 0.0])
    mesh = trimesh.util.concatenate([floor, cube])
    n_floor = len(floor.faces)
    geometry = Geometry(mesh=mesh, object_ids=np.r_[np.zeros(n_floor, np.int64), np.ones(len(cube.faces), np.int64)],
                        object_names=["floor", "cube"], two_sided=np.r_[np.ones(n_floor, bool), np.zeros(len(cube.faces), bool)],
                        to_source=np.eye(4), source="scene", sdf=None)  # fmt: skip
    front, back, back_vertices = vertex_transfer(geometry, make_tracer(geometry), 64, tmp_path, "scene")
    assert back_vertices == len(floor.vertices)
    albedo = face_albedo({"floor": [0.9, 0.2, 0.1], "cube": [0.1, 0.7, 0.8]}, geometry)
    fast_front, fast_back, seconds = vertex_bounce_transfer(geometry, front, back, albedo, 2, rays=16, seed=3, cache=tmp_path,
                                                            geometry_id="scene")  # fmt: skip
    twin_front, twin_back = _loop_twin(geometry, front, back, albedo, 2, rays=16, seed=3)
    np.testing.assert_allclose(fast_front, twin_front, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(fast_back, twin_back, rtol=1e-5, atol=1e-7)
    assert np.abs(fast_front[:, 16:]).max() > 1e-3  # light did bounce (the floor lights the cube's sides)
    assert seconds > 0
    again = vertex_bounce_transfer(geometry, front, back, albedo, 2, rays=16, seed=3, cache=tmp_path, geometry_id="scene")
    np.testing.assert_array_equal(again[0], fast_front)
    assert again[2] == 0.0  # read from the cache
    other = vertex_bounce_transfer(geometry, front, back, albedo, 1, rays=16, seed=3, cache=tmp_path, geometry_id="scene")
    assert other[2] > 0 and not np.array_equal(other[0], fast_front)  # the bounce count is part of the key


def test_no_bounce_is_the_direct_transfer_exactly(bowl):
    geometry, front, back, _, cache = bowl
    albedo = face_albedo({"bowl": ALBEDO}, geometry)
    front64, back64, _ = vertex_bounce_transfer(geometry, front, back, albedo, 0, rays=64, seed=0, cache=cache, geometry_id="bowl")
    np.testing.assert_array_equal(front64[:, :16], front)
    np.testing.assert_array_equal(back64[:, :16], back)
    assert not front64[:, 16:].any() and not back64[:, 16:].any()


@pytest.mark.gl
def test_four_raster_passes_reproduce_the_direct_raster(bowl, gl_ctx):
    """"direct+rgb" is drawn 16 values a pass: with zero indirect its direct part is the 1-pass image bit for bit,
    and each pass carries its own columns."""
    geometry, front, back, _, _ = bowl
    camera = Camera(eye=(0.4, 2.2, 2.0), target=(0.0, 0.0, 0.0))
    direct = VertexPRT(gl_ctx, geometry, front, back, 48, 40)
    try:
        image16, drawn16 = direct.render(camera)
    finally:
        direct.release()
    rng = np.random.default_rng(2)
    extra_front, extra_back = rng.normal(size=(len(front), 48)), rng.normal(size=(len(front), 48))
    wide = VertexPRT(gl_ctx, geometry, np.c_[front, np.zeros_like(extra_front)], np.c_[back, np.zeros_like(extra_back)], 48, 40)
    coloured = VertexPRT(gl_ctx, geometry, np.c_[front, extra_front], np.c_[back, extra_back], 48, 40)
    try:
        image64, drawn64 = wide.render(camera)
        image_c, _ = coloured.render(camera)
    finally:
        wide.release()
        coloured.release()
    assert drawn16.any() and image64.shape == (40, 48, 64)
    np.testing.assert_array_equal(drawn64, drawn16)
    np.testing.assert_array_equal(image64[..., :16], image16)
    assert not image64[..., 16:].any()
    np.testing.assert_array_equal(image_c[..., :16], image16)  # the passes do not mix
    assert np.abs(image_c[drawn16][:, 16:]).mean() > 0.1
    with pytest.raises(ValueError, match="16 k"):
        VertexPRT(gl_ctx, geometry, front[:, :12], back[:, :12], 8, 8)


@pytest.fixture(scope="module")
def cornell_report(tmp_path_factory):
    """A tiny 1-bounce Cornell box build measured by prt-bench (onnx fp32 and vertex)."""
    out = tmp_path_factory.mktemp("cornell_bounce_bench")
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(DATA / "CornellBox-Original.obj"), "-o", str(out / "scene"), "--samples", "2500",
         "--validation", "600", "--rays", "32", "--segments", "1", "--hidden", "16", "--layers", "2", "--steps", "100", "--bounces", "1",
         "--no-analytic", "--no-progress", "--threads", "1"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    paths = {"json": out / "r.json", "md": out / "r.md"}
    argv = [str(out / "scene" / "scene.json"), "--size", "32", "--views", "2", "--ref-rays", "32", "--ref-rays-max", "32", "--ref-hit-rays-max", "64",
            "--warmup", "0", "--backends", "onnx", "vertex", "--precisions", "fp32", "--gemm-size", "64", "--json", str(paths["json"]),
            "--md", str(paths["md"])]  # fmt: skip
    assert cli.main(argv) == 0
    return json.loads(paths["json"].read_text()), paths["md"].read_text()


@pytest.mark.gl
def test_bench_reports_vertex_rows_with_the_scenes_bounces_beside_direct(cornell_report):
    data, md = cornell_report
    records = data["records"]
    assert all(r["transfer"] in ("direct", "1 bounce") for r in records)
    assert {r["transfer"] for r in records if r["backend"] == "onnx"} == {"1 bounce"}
    vertex = {(r["transfer"], r["material"]): r for r in records if r["backend"] == "vertex"}
    assert set(vertex) == {(t, m) for t in ("direct", "1 bounce") for m in ("diffuse", "glossy")}
    assert vertex[("direct", "diffuse")]["label"] == "vertex diffuse"
    assert vertex[("1 bounce", "diffuse")]["label"] == "vertex 1 bounce diffuse"
    baseline = data["scenes"][0]["vertex_baseline"]
    assert baseline["bounces"]["bounces"] == 1 and baseline["bounces"]["rays"] == 32
    assert vertex[("1 bounce", "diffuse")]["weight_bytes"] == 4 * vertex[("direct", "diffuse")]["weight_bytes"] == baseline["bounces"]["weight_bytes"]
    # Two transfers, two images (their accuracy on the box's 40 vertices says little: the estimator is tested above).
    assert vertex[("1 bounce", "diffuse")]["mae"] != vertex[("direct", "diffuse")]["mae"]
    header = next(line for line in md.splitlines() if line.startswith("| scene |"))
    cells = [c.strip() for c in header.strip("|").split("|")]
    column = cells.index("transfer")
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in md.splitlines() if line.startswith(f"| {records[0]['scene']} |")]
    assert len(rows) == len(records)
    assert sorted(row[column] for row in rows) == sorted(r["transfer"] for r in records)
    assert "vertex baseline with 1 bounce" in md


@pytest.mark.gl
def test_baseline_rays_set_the_vertex_baselines_rays_and_leave_the_reference(cornell_report, tmp_path):
    """``--baseline-rays``: the vertex baseline (direct and bounces) traces its own ray count; the
    reference, and so the networks' PSNR, stays the ``--ref-rays`` one."""
    data, _ = cornell_report
    out = tmp_path / "r.json"
    argv = [data["scenes"][0]["path"], "--size", "32", "--views", "2", "--ref-rays", "32", "--ref-rays-max", "32", "--ref-hit-rays-max", "64",
            "--warmup", "0", "--backends", "onnx", "vertex", "--precisions", "fp32", "--gemm-size", "64", "--baseline-rays", "8", "--json", str(out)]  # fmt: skip
    assert cli.main([*argv, "--md", str(tmp_path / "r.md")]) == 0
    assert "x 16 float32" in (md := (tmp_path / "r.md").read_text()) and "8 rays per vertex" in md
    fewer = json.loads(out.read_text())
    baseline = fewer["scenes"][0]["vertex_baseline"]
    assert baseline["rays"] == 8 and baseline["bounces"]["rays"] == 8
    assert fewer["scenes"][0]["reference"]["rays"] == 32
    def psnr(report, backend, transfer):
        return next(r["psnr"] for r in report["records"] if (r["backend"], r["transfer"], r["material"]) == (backend, transfer, "diffuse"))
    assert psnr(fewer, "onnx", "1 bounce") == pytest.approx(psnr(data, "onnx", "1 bounce"), abs=1e-6)
    for transfer in ("direct", "1 bounce"):  # 8 rays per vertex against 32: another, noisier baseline
        assert psnr(fewer, "vertex", transfer) != pytest.approx(psnr(data, "vertex", transfer), abs=1e-3)
    with pytest.raises(SystemExit):
        cli.main([*argv[:-4], "--baseline-rays", "0", "--json", str(out)])


@pytest.mark.parametrize(("backend", "transfer", "label"), [
    ("texture", "2 bounces", "texture 1024 2 bounces diffuse"), ("texture", "direct", "texture 1024 diffuse"),
    ("vertex", "1 bounce", "vertex 1 bounce diffuse"), ("glsl", "2 bounces", "glsl diffuse"),
])  # fmt: skip
def test_baseline_labels_name_a_transfer_other_than_direct(backend, transfer, label):
    from prt.bench.report import transfer_label
    from prt.bench.scene_bench import _record

    common = {"scene": "s", "resolution": "8x8", "machine_gflops": 1.0}
    summary = {"mae": 0.1, "ssim": 0.9, "psnr": 30.0, "psnr_whole": 31.0, "fps": 10.0, "frame_ms": 100.0, "network_ms": 1.0,
               "transfer": transfer, **({"texture_size": 1024} if backend == "texture" else {})}  # fmt: skip
    record = _record(common, backend, "fp32", "diffuse", summary, 100, {}, lambda *_: None)
    assert record["label"] == label and record["transfer"] == transfer
    assert [transfer_label(n) for n in (0, 1, 3)] == ["direct", "1 bounce", "3 bounces"]


@pytest.mark.gl
def test_bench_against_mitsuba_sets_every_configuration_beside_our_reference(cornell_report, tmp_path):
    """``prt-bench --reference mitsuba`` (issue 38) on the tiny 1-bounce box: our reference, the networks
    and both vertex baselines against Mitsuba 3 in the JSON, the Markdown and a side-by-side figure;
    the quiet reference's verdict says why it stopped (here: the ray caps)."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'prt-runtime[mitsuba]')")
    data, _ = cornell_report
    out = tmp_path / "r.json"
    argv = [data["scenes"][0]["path"], "--size", "24", "--views", "2", "--ref-rays", "32", "--ref-rays-max", "32", "--ref-hit-rays", "16",
            "--ref-hit-rays-max", "16", "--warmup", "0", "--backends", "onnx", "vertex", "--precisions", "fp32", "--gemm-size", "64",
            "--reference", "mitsuba", "--mitsuba-views", "1", "--mitsuba-spp", "64", "--images", str(tmp_path / "images"),
            "--json", str(out), "--md", str(tmp_path / "r.md")]  # fmt: skip
    assert cli.main(argv) == 0
    report = json.loads(out.read_text())
    mi = report["scenes"][0]["mitsuba"]
    assert mi["variant"] in ("llvm_ad_rgb", "scalar_rgb") and mi["max_depth"] == 3 and mi["views"] == [0] and mi["spp"] >= 64
    assert set(mi["albedos"]) == {"floor", "ceiling", "backWall", "rightWall", "leftWall", "shortBox", "tallBox", "light"}
    size = mi["sizes"]["24x24"]
    labels = [r["label"] for r in size["rows"]]
    assert labels == ["our reference", "onnx fp32", "vertex direct", "vertex 1 bounce"]
    ours = size["rows"][0]
    assert size["pixels"] > 200 and ours["mse_ratio"] > 0 and 0 < ours["bias_se"] < 0.1
    # (the box's 40 vertices say little about the vertex baselines: their values are only checked for being measured)
    assert abs(ours["bias"]) < 0.1 and all(math.isfinite(r["psnr_vs_ours"]) and math.isfinite(r["bias"]) for r in size["rows"][1:])
    by_label = {r["label"]: r for r in size["rows"]}
    assert by_label["vertex direct"]["transfer"] == "direct" and by_label["onnx fp32"]["transfer"] == "1 bounce"
    assert Path(size["figure"]).is_file()
    md = (tmp_path / "r.md").read_text()
    assert "against Mitsuba 3" in md and "| our reference | 1 bounce |" in md and "joint noise" in md
    verdict = report["scenes"][0]["reference"]["convergence"]["24x24"]
    assert verdict["hit_rays"] == 16
    # the verdict says why it stopped: the ray caps, or the views' mean PSNR beat view 0's pilot (which depends on the build)
    from prt.bench.report import _FLOOR_REASONS

    assert ("the reference is the floor" in md and f"({_FLOOR_REASONS[verdict['reason']]}" in md) if verdict["floor"] else "quiet enough" in md
    assert not verdict["floor"] or verdict["reason"] in ("caps", "pilot")
