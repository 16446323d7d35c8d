"""The paper table's verdicts (studies/paper_table.py), on the committed full report and edits of it."""

import copy
import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
REPORT = ROOT / "docs" / "benchmarks" / "paper_2026-11-22_direct.json"  # the 1M-sample direct run (k = 64, 128, right-sized)


@pytest.fixture(scope="module")
def paper_table(bench_module):
    return bench_module("paper_table")


@pytest.fixture()
def report():
    return json.loads(REPORT.read_text())


def _record(report, scene, backend="onnx", precision="fp32", material="diffuse"):
    for r in report["records"]:
        if (r["scene"], r["backend"], r["precision"], r["material"]) == (scene, backend, precision, material):
            return r
    raise KeyError(scene)


def _line(text, start):
    return next(line for line in text.splitlines() if line.startswith(start))


def test_accuracy_verdict_follows_the_records(paper_table, report):
    text = paper_table.summary(report)
    line = _line(text, "- accuracy")
    for mesh in ("bunny", "teapot", "spot", "daffodil"):
        d, g = _record(report, f"{mesh}-k64"), _record(report, f"{mesh}-k64", material="glossy")
        need = 40.0 if mesh == "daffodil" else 45.0
        met = d["psnr"] >= need and g["psnr"] >= 38.0
        assert f"{mesh} {d['psnr']:.1f}/{g['psnr']:.1f} dB ({'met' if met else 'missed'}" in line
    # raising the teapot above 45 dB flips its verdict, and only its
    edited = copy.deepcopy(report)
    _record(edited, "teapot-k64")["psnr"] = 45.5
    _record(edited, "teapot-k64", material="glossy")["psnr"] = 45.5
    after = _line(paper_table.summary(edited), "- accuracy")
    assert "teapot 45.5/45.5 dB (met" in after
    for part in line.split("; "):
        if "teapot" not in part:
            assert part.split(": ")[-1] in after


def test_right_sized_needs_fewer_flops_and_the_same_psnr(paper_table, report):
    edited = copy.deepcopy(report)
    k64 = _record(edited, "bunny-k64")
    rs = _record(edited, "bunny-right-sized")
    rs["flops_per_fragment"] = k64["flops_per_fragment"]
    assert "with 1.00x the FLOPs (missed)" in _line(paper_table.summary(edited), "- right-sized")
    rs["flops_per_fragment"] = k64["flops_per_fragment"] // 2
    rs["psnr"] = k64["psnr"] - 0.6
    assert "bunny -0.60 dB with 0.50x the FLOPs (missed)" in _line(paper_table.summary(edited), "- right-sized")
    rs["psnr"] = k64["psnr"] - 0.4
    assert "bunny -0.40 dB with 0.50x the FLOPs (met)" in _line(paper_table.summary(edited), "- right-sized")


def test_precision_verdict_pools_materials_and_takes_the_median(paper_table, report):
    edited = copy.deepcopy(report)
    for mesh in ("bunny", "teapot", "spot", "daffodil"):
        for material in ("diffuse", "glossy"):
            fp32 = _record(edited, f"{mesh}-k64", material=material)
            int8 = _record(edited, f"{mesh}-k64", precision="int8", material=material)
            int8["network_ms"] = fp32["network_ms"] / 2
            int8["psnr"] = fp32["psnr"] - 0.2
    line = _line(paper_table.summary(edited), "- int8")
    assert "median 2.00x (met" in line
    _record(edited, "spot-k64", precision="int8", material="glossy")["psnr"] -= 1.0  # one mesh loses too much
    assert "median 2.00x (missed" in _line(paper_table.summary(edited), "- int8")


def test_says_which_scenes_came_from_checkpoints(paper_table, report):
    edited = copy.deepcopy(report)
    edited["machine"]["resumed"] = [{"scene": "spot-k64", "measured": "2026-01-01T00:00:00"}]
    assert "spot-k64 from an earlier run's checkpoints" in _line(paper_table.summary(edited), "Targets")
    edited["machine"]["resumed"] = []
    assert _line(paper_table.summary(edited), "Targets").endswith("measured in this run):")


def test_texture_columns_appear_when_the_run_measured_texture_prt(paper_table, report):
    edited = copy.deepcopy(report)
    edited["records"] = [r for r in edited["records"] if r["backend"] != "texture"]
    assert "texture" not in paper_table.summary(edited).splitlines()[0]  # a run without texture PRT has no column
    for mesh, psnr in (("bunny", 49.2), ("spot", 50.0)):
        for material, delta in (("diffuse", 0.0), ("glossy", 0.5)):
            record = dict(_record(edited, f"{mesh}-k64", "vertex", material=material))
            record.update(backend="texture", precision="fp16", texture_size=512, psnr=psnr + delta, weight_bytes=3 * 2**20)
            edited["records"].append(record)
    table = paper_table.summary(edited).splitlines()
    assert table[0].split(" | ")[6] == "texture 512^2"
    assert _line("\n".join(table), "| bunny").split(" | ")[6] == "49.2 / 49.7 (3.0 MiB)"
    assert _line("\n".join(table), "| teapot").split(" | ")[6] == "-"


def test_default_build_verdicts_against_vertex_prt_and_k128(paper_table, report):
    edited = copy.deepcopy(report)
    rs, vd, big = _record(edited, "spot-right-sized"), _record(edited, "spot-k64", "vertex"), _record(edited, "spot-k128")
    rs["psnr"], rs["weight_bytes"] = vd["psnr"] + 3.5, vd["weight_bytes"]
    assert "spot +3.5 dB with 1.00x the bytes (met)" in _line(paper_table.summary(edited), "- default (right-sized) against per-vertex")
    rs["weight_bytes"] = vd["weight_bytes"] + 1  # one byte more than per-vertex storage
    assert "spot +3.5 dB with 1.00x the bytes (missed)" in _line(paper_table.summary(edited), "- default (right-sized) against per-vertex")
    rs["psnr"], rs["flops_per_fragment"] = big["psnr"] + 0.1, 35_257
    assert "spot +0.1 dB at 35.3k FLOPs (met)" in _line(paper_table.summary(edited), "- default (right-sized) against k = 128")
    rs["flops_per_fragment"] = 35_258
    assert "spot +0.1 dB at 35.3k FLOPs (missed)" in _line(paper_table.summary(edited), "- default (right-sized) against k = 128")


def test_summary_only_rewrites_the_summary_and_keeps_the_rest(paper_table, report, tmp_path):
    doc = tmp_path / "table.md"
    doc.write_text("# T\n\nMade by `x`.\n\n## Summary\n\nold summary\n\n## Every configuration\n\n| a |\n")
    out = tmp_path / "paper.json"
    out.write_text(json.dumps(report))
    assert paper_table.main(["--summary-only", "--doc", str(doc), "--out", str(tmp_path / "paper")]) == 0
    text = doc.read_text()
    assert "old summary" not in text and text.startswith("# T\n\nMade by `x`.") and text.endswith("## Every configuration\n\n| a |\n")
    assert "- default (right-sized) against per-vertex PRT" in text


def test_table_names_each_mesh_transfer_and_shows_only_the_sizes_built(paper_table, report):
    edited = copy.deepcopy(report)
    for r in edited["records"]:
        if r["scene"].startswith("bunny-") and r["backend"] == "onnx":
            r["transfer"] = "2 bounces"
    rows = paper_table.summary(edited).splitlines()
    assert rows[0].split(" | ")[1] == "transfer"
    assert _line("\n".join(rows), "| bunny").split(" | ")[1] == "2 bounces"
    assert _line("\n".join(rows), "| spot").split(" | ")[1] == _record(report, "spot-k64").get("transfer", "direct")
    # a run without k = 128 builds has no k = 128 column (and no k = 128 verdict)
    edited["records"] = [r for r in edited["records"] if not r["scene"].endswith("-k128")]
    text = paper_table.summary(edited)
    assert "k = 128 |" not in text.splitlines()[0] and "k = 64 |" in text.splitlines()[0]
    assert not any(line.startswith("- default (right-sized) against k = 128") for line in text.splitlines())


def test_build_times_list_every_build_and_their_sum(paper_table):
    builds = {"bunny-k64": {"command": "a", "seconds": 600.0, "shares_precompute_of": None},
              "bunny-right-sized": {"command": "b", "seconds": 300.0, "shares_precompute_of": "k64"}}
    text = paper_table.build_times(builds)
    assert "| bunny-k64 | 10.0 | - |" in text and "| bunny-right-sized | 5.0 | k64 |" in text
    assert "All builds: 0.25 h" in text
    assert paper_table.build_times({}) == ""


def test_vertex_same_bounces_study_relights_a_copy_and_pairs_rows_by_transfer(bench_module, tmp_path):
    """studies/vertex_same_bounces.py: the relit copy keeps the networks and takes the map's SH;
    the summary pairs each network row with the vertex row of the same transfer only."""
    study = bench_module("vertex_same_bounces")
    from prt.runtime.envmap import load_envmap_sh
    from prt.runtime.renderer import Scene, demo_scene_path

    demo = demo_scene_path().parent
    envmap = demo / "envmap.hdr"
    out = study.relit_copy(demo, envmap, tmp_path)
    scene = Scene.load(out)  # a valid manifest
    assert scene.name == "spot-envmap" and scene.manifest.lighting.envmap is None
    np.testing.assert_allclose(np.asarray(json.loads((out / "scene.json").read_text())["lighting"]["sh"]), load_envmap_sh(envmap, 4), rtol=1e-12)
    assert sorted(p.name for p in (out / "segments").iterdir()) == sorted(p.name for p in (demo / "segments").iterdir())

    def rec(backend, transfer, psnr, nbytes):
        return {"scene": "s", "backend": backend, "precision": "fp32", "material": "diffuse", "transfer": transfer, "psnr": psnr,
                "weight_bytes": nbytes, "ref_noise_psnr": 50.0}  # fmt: skip

    report = {"records": [rec("onnx", "2 bounces", 48.0, 100), rec("vertex", "direct", 40.0, 50), rec("vertex", "2 bounces", 44.5, 400),
                          {**rec("onnx", "2 bounces", 30.0, 100), "material": "glossy"}]}  # fmt: skip
    rows = study.summary(report)
    assert len(rows) == 1 and rows[0]["vertex_db"] == 44.5 and rows[0]["gain_db"] == 3.5 and rows[0]["bytes_ratio"] == 0.25 and rows[0]["met"]
    assert rows[0]["vertex_rays"] is None
    report["scenes"] = [{"scene": "s", "vertex_baseline": {"rays": 512}}]  # --baseline-rays: the row says how many
    assert study.summary(report)[0]["vertex_rays"] == 512
    report["records"][2]["psnr"] = 45.5  # +2.5 dB: missed
    assert not study.summary(report)[0]["met"]
