"""prt-bench (prt.bench) on a tiny scene: report keys, errors, baselines, precision variants, plot."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.bench import cli, machine, metrics, scene_bench
from prt.bench import report as report_format
from prt.export.precision import PRECISIONS, model_weight_bytes, variant_manifest
from prt.runtime.normals import CREASE_COS, corner_normals, vertex_normals

ROOT = Path(__file__).resolve().parents[1]
SIZE = 40
VIEWS = 2
# Largest |transfer - fp32 transfer| allowed per precision (coefficients are ~0.1-0.5).  Full
# fp16 rounds the encoding's arguments (up to 2^5 pi |x|) to 11 bits: a few 1e-2 at worst.
TOLERANCE = {"fp16": 5e-2, "fp16-mlp": 2e-3, "int8": 5e-2}

# The tool renders with both backends and rasterises the vertex baseline.
pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """Spot with two tiny networks, built by prt-train in a few seconds."""
    out = tmp_path_factory.mktemp("scene")
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(ROOT / "tests" / "data" / "spot.obj"), "-o", str(out),
         "--samples", "20000", "--rays", "64", "--epochs", "5", "--hidden", "16", "--layers", "2",
         "--segments", "2", "--no-progress"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out / "scene.json"


@pytest.fixture(scope="module")
def report(tiny_scene, tmp_path_factory):
    """The tool run end to end through main(); returns the parsed JSON and the output paths."""
    out = tmp_path_factory.mktemp("bench")
    paths = {"json": out / "r.json", "md": out / "r.md", "plot": out / "r.png"}
    argv = [str(tiny_scene), "--size", str(SIZE), "--views", str(VIEWS), "--ref-rays", "64", "--warmup", "1",
            "--gemm-size", "256", "--json", str(paths["json"]), "--md", str(paths["md"]), "--plot", str(paths["plot"]),
            "--images", str(out / "images"), "--interpolate", "0.1"]  # fmt: skip
    assert cli.main(argv) == 0
    return json.loads(paths["json"].read_text()), paths


def test_report_has_every_documented_key(report):
    data, _ = report
    documented = set(re.findall(r"``(\w+)``", report_format.__doc__))
    for keys in (report_format.REPORT_KEYS, report_format.MACHINE_KEYS, report_format.SCENE_KEYS, report_format.PACKING_KEYS, report_format.RECORD_KEYS):
        assert set(keys) <= documented, set(keys) - documented
    assert set(report_format.REPORT_KEYS) <= set(data)
    assert set(report_format.MACHINE_KEYS) <= set(data["machine"])
    machine = data["machine"]
    assert machine["gemm_numpy_gflops"] > 0 and machine["gemm_onnxruntime_gflops"] > 0
    # the limit is the faster library, so no network stage is measured against a slow BLAS
    assert machine["machine_gflops"] == max(machine["gemm_numpy_gflops"], machine["gemm_onnxruntime_gflops"])
    for scene in data["scenes"]:
        assert set(report_format.SCENE_KEYS) <= set(scene)
        for packing in scene["packing"]:
            assert set(report_format.PACKING_KEYS) <= set(packing)
    configs = {(r["backend"], r["precision"], r["material"]) for r in data["records"]}
    expected = {("onnx", p, m) for p in PRECISIONS for m in scene_bench.MATERIALS}
    expected |= {(b, "fp32", m) for b in ("glsl", "vertex") for m in scene_bench.MATERIALS}
    assert configs == expected
    for record in data["records"]:
        missing = set(report_format.RECORD_KEYS) - set(record)
        assert not missing, (record["label"], missing)
        assert record["resolution"] == f"{SIZE}x{SIZE}" and record["views"] == VIEWS
        assert record["fps"] > 0 and record["stages_ms"]


def test_an_interrupted_run_resumes_from_its_scene_checkpoints(report, tiny_scene, tmp_path, capsys):
    """A second run with the same scene and settings takes the finished scene from its checkpoint."""
    data, paths = report
    out = paths["json"].parent
    argv = [str(tiny_scene), "--size", str(SIZE), "--views", str(VIEWS), "--ref-rays", "64", "--warmup", "1",
            "--gemm-size", "256", "--cache", str(out / "r_cache"), "--json", str(tmp_path / "again.json"),
            "--images", str(out / "images"), "--interpolate", "0.1"]  # fmt: skip
    capsys.readouterr()
    assert cli.main(argv) == 0
    assert "kept in" in capsys.readouterr().out
    again = json.loads((tmp_path / "again.json").read_text())
    assert again["scenes"] == data["scenes"] and again["records"] == data["records"]  # not measured again
    checkpoint = Path(data["scenes"][0]["checkpoint"])
    assert checkpoint.is_file() and not list(checkpoint.parent.glob(".*.tmp"))
    # --fresh measures again (its FPS differ from the first run's at the timer's resolution).
    assert cli.main([*argv, "--fresh"]) == 0
    assert "kept in" not in capsys.readouterr().out
    fresh = json.loads((tmp_path / "again.json").read_text())
    assert [r["frame_ms"] for r in fresh["records"]] != [r["frame_ms"] for r in data["records"]]
    # Other settings, or changed scene files, key another checkpoint.
    settings = scene_bench.Settings(views=VIEWS, sizes=(SIZE,), ref_rays=64, warmup=1, gemm_size=256, cache=out / "r_cache",
                           images=out / "images", interpolate=(0.1,))  # fmt: skip
    assert report_format.scene_checkpoint(tiny_scene, settings) == checkpoint
    assert report_format.scene_checkpoint(tiny_scene, dataclasses.replace(settings, warmup=2)) != checkpoint
    assert report_format.scene_checkpoint(tiny_scene, dataclasses.replace(settings, interpolate=(0.2,))) != checkpoint
    assert report_format.scene_checkpoint(tiny_scene, dataclasses.replace(settings, ref_hit_rays=512)) != checkpoint  # the bounce reference
    assert report_format.scene_checkpoint(tiny_scene, dataclasses.replace(settings, ref_hit_transfer_rays=16)) != checkpoint
    assert report_format.scene_checkpoint(tiny_scene, dataclasses.replace(settings, cache=tmp_path)).name == checkpoint.name
    copy = tmp_path / "scene"
    shutil.copytree(tiny_scene.parent, copy)
    assert report_format.scene_checkpoint(copy / "scene.json", settings) == checkpoint  # same files, same key
    model = next(copy.rglob("*.onnx"))
    model.write_bytes(model.read_bytes() + b"\0")
    assert report_format.scene_checkpoint(copy / "scene.json", settings) != checkpoint


def test_error_maps_show_reference_and_every_configuration(report):
    """One figure per scene and size: a row per material, the reference then each configuration."""
    from PIL import Image

    data, _ = report
    (path,) = data["scenes"][0]["error_images"]
    image = np.asarray(Image.open(path).convert("RGB"))
    configs = len(data["records"]) // len(scene_bench.MATERIALS)
    # (1 + configs) panels of ~2.6 in at 100 dpi across, two rows down
    assert image.shape[1] > 200 * (1 + configs) and image.shape[0] > 2 * 200
    assert image.std() > 10  # not blank


def test_errors_are_finite_and_plausible(report):
    data, _ = report
    for record in data["records"]:
        for key in ("psnr", "psnr_whole", "mae", "ssim"):
            assert math.isfinite(record[key]), (record["label"], key)
        assert record["psnr"] > 10.0, record["label"]
        assert record["psnr_whole"] >= record["psnr"]  # the black background matches exactly
        assert 0.0 <= record["ssim"] <= 1.0
    vertex = [r for r in data["records"] if r["backend"] == "vertex"]
    assert vertex and all(math.isfinite(r["mae"]) for r in vertex)
    baseline = data["scenes"][0]["vertex_baseline"]
    assert baseline["weight_bytes"] == 16 * 4 * (baseline["vertices"] + baseline["back_vertices"])
    assert baseline["coverage_agreement"][f"{SIZE}x{SIZE}"] > 0.99  # the same pixels as the G-buffer


def test_reference_noise_is_reported(report):
    # ray-traced transfer lives in one content-keyed folder that scenes of one mesh share
    cache = Path(report[0]["scenes"][0]["reference"]["cache"])
    assert cache.name == "transfer" and any(cache.glob("view000-*.npz")) and any(cache.glob("vertices-front-*.npz"))
    data, _ = report
    noise = data["scenes"][0]["reference"]["noise_psnr"][f"{SIZE}x{SIZE}"]
    assert set(noise) == set(scene_bench.MATERIALS)
    assert all(math.isfinite(v) and v > 20.0 for v in noise.values())
    assert data["scenes"][0]["reference"]["rays"] == 64
    # issue 12: rays raised (within --ref-rays-max) where the noise is not 6 dB above a pilot; verdict recorded
    ref = data["scenes"][0]["reference"]
    verdict = ref["convergence"][f"{SIZE}x{SIZE}"]
    assert 64 <= ref["rays_by_size"][f"{SIZE}x{SIZE}"] == verdict["rays"] <= 4096 and set(verdict["margin_db"]) == set(scene_bench.MATERIALS)
    assert verdict["floor"] == any(g < 6.0 for g in verdict["margin_db"].values())
    assert all(r["ref_rays"] == verdict["rays"] for r in data["records"])


def test_naive_path_runs_every_pixel_through_every_network(report):
    data, _ = report
    (packing,) = data["scenes"][0]["packing"]
    assert packing["all_pixels"] == SIZE * SIZE
    assert packing["network_segments"] >= 1
    assert all(rows == SIZE * SIZE for rows in packing["naive_rows_per_segment"].values())
    assert packing["naive_total_rows"] == packing["network_segments"] * SIZE * SIZE
    assert 0 < packing["covered_pixels"] < SIZE * SIZE
    assert packing["naive_max_abs_diff"] < 1e-4  # same networks, same answers on covered pixels
    assert packing["naive_inference_ms"] > 0 and packing["packed_inference_ms"] > 0


def test_pareto_front_of_hand_made_points():
    points = [(1.0, 10.0), (2.0, 9.0), (3.0, 3.0), (1.5, 8.0), (2.0, 9.0), (0.5, 11.0), (3.0, 2.0), (0.4, 11.0)]
    # (1.5, 8) loses to (2, 9); (3, 2) to (3, 3); (0.4, 11) to (0.5, 11); the duplicates both stay.
    assert metrics.pareto_front(points) == [5, 0, 1, 4, 2]
    assert metrics.pareto_front([(1.0, 1.0)]) == [0]
    assert metrics.pareto_front([]) == []


def test_pareto_front_in_report_and_plot(report):
    data, paths = report
    assert data["pareto"] and all(data["pareto"].values())
    for group, labels in data["pareto"].items():
        members = [r for r in data["records"] if metrics.group_key(r) == group]
        front = {r["label"] for r in members if r["pareto"]}
        assert front == set(labels)
        for r in members:  # nothing on the front is beaten in both FPS and PSNR
            if r["pareto"]:
                assert not any(o["fps"] > r["fps"] and o["psnr"] > r["psnr"] for o in members)
    assert paths["plot"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = paths["md"].read_text()
    assert table.count(f"| {SIZE}x{SIZE} |") == len(data["records"])
    assert f"reference noise vs best PSNR {SIZE}x{SIZE}: diffuse " in table  # issue 12: the reference's margin


def test_precision_variants_stay_close_to_fp32(tiny_scene, tmp_path):
    import onnxruntime as ort

    from prt.runtime.manifest import load_manifest

    manifest = load_manifest(tiny_scene)
    rng = np.random.default_rng(1)
    normals = rng.standard_normal((4096, 3))
    x = np.concatenate([rng.uniform(-0.9, 0.9, (4096, 3)), normals / np.linalg.norm(normals, axis=1, keepdims=True)], axis=1)
    x = x.astype(np.float32)

    def run(path):
        return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]

    for precision, limit in TOLERANCE.items():
        variant = variant_manifest(manifest, precision, tmp_path)
        for seg, original in zip(variant.segments, manifest.segments):
            if seg.kind != "network":
                continue
            assert seg.model != original.model and seg.model.is_file()
            got, want = run(seg.model), run(original.model)
            assert got.dtype == np.float32 and got.shape == want.shape
            assert np.abs(got - want).max() < limit, (precision, seg.id, float(np.abs(got - want).max()))
        assert model_weight_bytes(variant) < model_weight_bytes(manifest)


def test_variant_records_match_fp32_transfer(report):
    data, _ = report
    for r in data["records"]:
        if r["backend"] == "onnx" and r.get("interpolate"):
            continue  # interpolated pixels differ: test_interpolated_rows_are_labelled_and_close
        if r["backend"] == "onnx":
            assert r["transfer_max_abs_diff"] < TOLERANCE.get(r["precision"], 1e-6), r["label"]
        elif r["backend"] == "glsl":
            assert r["transfer_max_abs_diff"] < 1e-4  # the same networks in the fragment shader


def test_interpolated_rows_are_labelled_and_close(report):
    """--interpolate adds fp32 ONNX rows that ran fewer networks, within 1 dB of every pixel's PSNR."""
    data, paths = report
    rows = {(r["material"], r.get("interpolate")): r for r in data["records"] if r["backend"] == "onnx" and r["precision"] == "fp32"}
    for material in ("diffuse", "glossy"):
        exact, interp = rows[(material, None)], rows[(material, 0.1)]
        assert exact["network_fraction"] == 1.0
        assert 0 < interp["network_fraction"] <= 1.0  # at 40x40 most pixels lie next to an edge (256x256: tests/test_interpolation.py)
        assert interp["label"] == f"onnx fp32 interpolate 0.1 {material}"
        assert abs(interp["psnr"] - exact["psnr"]) < 1.0, (interp["psnr"], exact["psnr"])
        assert interp["transfer_max_abs_diff"] < 0.5
    assert "interpolate 0.1" in paths["md"].read_text()


def test_network_profile_splits_the_run_into_ops(report):
    data, paths = report
    prof = data["scenes"][0]["packing"][0]["network_profile"]
    assert prof["rows"] > 0 and prof["run_us"] > 0
    assert {"FusedGemm", "Sin", "Cos", "Concat"} <= set(prof["op_us"])  # ORT fuses Gemm + LeakyRelu
    assert 0.0 < prof["gemm_share"] < 1.0
    assert sum(prof["op_us"].values()) <= 1.2 * prof["run_us"]  # ops sum to about one run, not many
    assert "network profile" in paths["md"].read_text()


def test_budget_keeps_view_zero_and_spreads_the_rest():
    views = list(range(30))
    assert scene_bench.budget_views(views, None, 0.5) == views  # no budget: every view
    assert scene_bench.budget_views(views, 60.0, None) == views  # nothing timed yet
    assert scene_bench.budget_views(views, 60.0, 1.0) == views  # 60 frames fit
    few = scene_bench.budget_views(views, 10.0, 1.0)
    assert len(few) == 10 and few[0] == 0 and few[-1] == 29 and few == sorted(set(few))
    assert len(scene_bench.budget_views(views, 1.0, 16.0)) == 4  # a 16 s frame still gets the minimum
    assert scene_bench.spread(views, None) == views and scene_bench.spread(views, 1) == [0] and scene_bench.spread(views, 3) == [0, 14, 29]


def test_gemm_rate_counts_the_flops_of_a_product(monkeypatch):
    """2 n^3 FLOPs over the median time of the timed calls (the warm-up call is not timed).

    A formula that forgot a power of n, or timed the warm-up, would be off by n or more. The
    clock is a fake one advanced by the product itself, so the check does not depend on load.
    """
    clock = {"t": 0.0}
    durations = iter([100.0, 2.0, 5.0, 3.0])  # warm-up, then three timed calls: median 3 s

    def product():
        clock["t"] += next(durations)

    monkeypatch.setattr(machine.time, "perf_counter", lambda: clock["t"])
    assert machine._gemm_rate(product, 1000, repeats=3) == pytest.approx(2.0 * 1000**3 / 3.0 / 1e9)


def test_image_metrics_of_identical_images():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (32, 32, 3))
    covered = np.zeros((32, 32), dtype=bool)
    covered[8:24, 8:24] = True
    same = metrics.image_metrics(image, image, covered)
    assert same == {"mae": 0.0, "psnr": metrics.PSNR_CAP, "ssim": pytest.approx(1.0), "psnr_whole": metrics.PSNR_CAP}
    darker = metrics.image_metrics(image * 0.9, image, covered)
    assert 0 < darker["mae"] and darker["psnr"] < metrics.PSNR_CAP and darker["ssim"] < 1.0


def test_vertex_baseline_normals_are_the_g_buffers_smooth_normals():
    """The vertex baseline traces transfer at the normals the G-buffer interpolates (away from creases)."""
    with np.load(ROOT / "runtime" / "data" / "demo" / "geometry.npz") as data:
        vertices, faces = data["vertices"], data["faces"].astype(np.int64)
    per_vertex = vertex_normals(vertices, faces)
    face, corner = corner_normals(vertices, faces)
    smooth = np.einsum("fkc,fc->fk", per_vertex[faces], face) >= CREASE_COS
    assert smooth.mean() > 0.5
    np.testing.assert_array_equal(corner[smooth], per_vertex[faces][smooth])
    used = np.unique(faces)
    np.testing.assert_allclose(np.linalg.norm(per_vertex[used], axis=1), 1.0, atol=1e-12)


def test_the_mitsuba_lines_say_how_the_skys_negative_part_was_handled():
    """A sky that is negative in places: subtracted (the negative part rendered apart) or, in older records, clamped."""
    row = {"label": "our reference", "transfer": "5 bounces", "psnr": 30.0, "bias": -0.01, "bias_se": 0.001, "psnr_vs_ours": None,
           "ours_noise_psnr": 31.0, "joint_noise_psnr": 29.0, "mse_ratio": 1.1, "within_noise": True, "bias_within": False}
    size = {"pixels": 100, "mitsuba_noise_psnr": 30.0, "rows": [row]}

    def lines(envmap):
        mi = {"mitsuba": "3.9.1", "variant": "llvm_ad_rgb", "spp": 64, "max_depth": 7, "views": [0], "envmap": envmap, "sizes": {"8x8": size}}
        return "\n".join(report_format._mitsuba_lines({"scene": "s", "mitsuba": mi}))

    share = {"clamped": True, "clamp_share": [0.005, 0.011, 0.014]}
    assert "0.50, 1.10, 1.40 % of the energy, R, G, B): that part rendered apart and subtracted" in lines({**share, "negative_part": True})
    assert "clamping its negative radiance removed 0.50, 1.10, 1.40 %" in lines({**share, "negative_part": False})
    assert "non-negative, nothing clamped" in lines({"clamped": False, "clamp_share": [0.0, 0.0, 0.0], "negative_part": False})
