"""Builds by preset, timed, then measured against per-vertex PRT with the same bounces and at equal bytes.

usage: python studies/builds_vs_vertex.py MESH [MESH ...] --quality draft [standard high] --json OUT.json [--md OUT.md]
           [--work DIR] [--lights venice_sunset_1k] [--threads 1] [--views 2] [--size 192] [--ref-rays 1024]
           [--ref-hit-rays 256] [--ref-hit-transfer-rays 32] [--extra FLAG ...]

For every mesh and quality: ``prt-train MESH -o WORK/NAME-QUALITY --quality Q`` runs under ``nice``
(wall seconds, the build's CPU seconds, the machine's load and the share of the cores other
processes took meanwhile, ``prt.bench.machine.other_cpu_share``), then ``prt-bench`` measures
the scene under its own light and relit copies under ``--lights`` (``studies/vertex_same_bounces.py``'s
``relit_copy``): the ONNX networks, per-vertex PRT with the same bounces at the build's rays per
vertex (``--baseline-rays``), and per-vertex PRT on the mesh decimated to the networks' bytes
(``--equal-bytes``), against a reference of ``--ref-rays`` (raised up to 4x where it is not 6 dB
above the best PSNR) and ``--ref-hit-rays`` x ``--ref-hit-transfer-rays`` for its bounces.

Each row: build time and CPU time, the build's own held-out estimate (``build.json``'s ``sizing``),
and per light the diffuse PSNR of networks, vertex PRT and vertex PRT at equal bytes, the gains,
the bytes, the reference's noise, and whether issue 38's targets hold: >= +1 dB at <= vertex PRT's
bytes, >= +6 dB at equal bytes, the reference >= 6 dB quieter than both.  Resumable: a build
whose timing was recorded is not rebuilt, and ``prt-bench`` keeps its checkpoints in WORK.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from prt.bench.machine import busy_seconds, cpu_name
from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes, atomic_write_json

sys.path.insert(0, str(Path(__file__).resolve().parent))
from vertex_same_bounces import relit_copy, resolve_envmap  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def others_share(start, children_cpu: float, wall: float):
    """Share of the cores' time other processes took during a build: all busy time less this
    process's and the build's own (``prt.bench.machine.other_cpu_share`` counts a child as other)."""
    end = busy_seconds()
    if start is None or end is None or wall <= 0:
        return None
    others = (end[0] - start[0]) - (end[1] - start[1]) - children_cpu
    return round(max(others, 0.0) / (wall * (os.cpu_count() or 1)), 3)


def timed_build(mesh: Path, quality: str, out: Path, threads: int, extra: list[str]) -> dict:
    """Run (or read back) one build; its timing record (``out/timing.json``)."""
    record_path = out / "timing.json"
    if record_path.is_file() and (out / "scene.json").is_file():
        return json.loads(record_path.read_text())
    command = ["nice", "-n", "10", sys.executable, "-m", "prt.train.train_cli", str(mesh), "-o", str(out), "--quality", quality,
               "--threads", str(threads), "--no-progress", *extra]  # fmt: skip
    print("==", " ".join(command[3:]), flush=True)
    load, busy, cpu, t0 = os.getloadavg()[0], busy_seconds(), _children_cpu(), time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if out.is_dir():
        (out / "train.log").write_text(proc.stdout + proc.stderr)  # the whole log (its warnings among it)
    if proc.returncode != 0:
        raise SystemExit(f"prt-train failed on {mesh} ({quality}): {proc.stderr.strip()[-500:]}")
    report = json.loads((out / "build.json").read_text())
    cpu = _children_cpu() - cpu
    record = {"mesh": str(mesh), "quality": quality, "command": "prt-train " + " ".join(command[6:]), "wall_s": round(wall, 1),
              "cpu_s": round(cpu, 1), "threads": threads, "load_average": round(load, 2),
              "other_cpu_share": others_share(busy, cpu, wall), "stage_s": {k: round(v, 1) for k, v in report["timings"].items() if k.endswith("_s")},
              "vertices": report["memory"]["vertices"], "weight_bytes": report["memory"]["weight_bytes"],
              "sizing": report.get("sizing"), "summary": proc.stdout.strip().splitlines()[-16:]}  # fmt: skip
    atomic_write_json(record_path, record)
    print("\n".join(record["summary"]), flush=True)
    return record


def bench(build: Path, lights: list[str], args) -> dict:
    """prt-bench on the build and its relit copies; the report."""
    scenes = [build] + [relit_copy(build, resolve_envmap(name), build.parent / "relit") for name in lights]
    report = build / "bench.json"
    rays = json.loads((build / "build.json").read_text())["spec"]["rays"]
    command = [sys.executable, "-m", "prt.bench.cli", *[str(s / "scene.json") for s in scenes], "--views", str(args.views), "--size",
               str(args.size), "--ref-rays", str(args.ref_rays), "--ref-rays-max", str(4 * args.ref_rays), "--ref-hit-rays",
               str(args.ref_hit_rays), "--ref-hit-transfer-rays", str(args.ref_hit_transfer_rays), "--baseline-rays", str(rays),
               "--backends", "onnx", "vertex", "--precisions", "fp32", "--equal-bytes", "--warmup", "1", "--packing-views", "1",
               "--gemm-size", "1024", "--cache", str(build.parent / "bench_cache"), "--json", str(report)]  # fmt: skip
    print("==", " ".join(["prt-bench", *command[3:]]), flush=True)
    subprocess.run(["nice", "-n", "10", *command], check=True, stdout=subprocess.DEVNULL)
    out = json.loads(report.read_text())
    out["command"] = " ".join(["prt-bench", *command[3:]])
    return out


def rows_of(report: dict, timing: dict) -> list[dict]:
    """One row per scene (light) of a bench report: networks against both vertex baselines."""
    rows = []
    recs = [r for r in report["records"] if r["material"] == "diffuse" and r["precision"] == "fp32"]
    noise = {e["scene"]: e["reference"]["noise_psnr"] for e in report["scenes"]}
    for scene in dict.fromkeys(r["scene"] for r in recs):
        net = next(r for r in recs if r["scene"] == scene and r["backend"] == "onnx")
        same = next(r for r in recs if r["scene"] == scene and r["backend"] == "vertex" and r["transfer"] == net["transfer"]
                    and not r.get("equal_bytes"))  # fmt: skip
        equal = next((r for r in recs if r["scene"] == scene and r.get("equal_bytes")), None)
        ref_noise = next(iter(noise[scene].values()))["diffuse"]
        row = {"scene": scene, "mesh": Path(timing["mesh"]).name, "quality": timing["quality"], "transfer": net["transfer"],
               "resolution": net["resolution"], "psnr_db": net["psnr"], "vertex_psnr_db": same["psnr"],
               "gain_db": round(net["psnr"] - same["psnr"], 2), "weight_bytes": net["weight_bytes"], "vertex_bytes": same["weight_bytes"],
               "ref_noise_db": ref_noise, "ref_rays": net["ref_rays"],
               "met_1db_at_bytes": bool(net["psnr"] - same["psnr"] >= 1.0 and net["weight_bytes"] <= same["weight_bytes"]),
               "ref_quiet_6db": bool(ref_noise >= max(net["psnr"], same["psnr"]) + 6.0)}  # fmt: skip
        if equal is not None:
            row.update({"equal_bytes_psnr_db": equal["psnr"], "equal_bytes_vertices": equal["equal_bytes"]["vertices"],
                        "equal_bytes_bytes": equal["weight_bytes"], "gain_equal_bytes_db": round(net["psnr"] - equal["psnr"], 2),
                        "met_6db_equal_bytes": bool(net["psnr"] - equal["psnr"] >= 6.0)})  # fmt: skip
        rows.append(row)
    return rows


def markdown(result: dict) -> str:
    prov = result.get("provenance", {})
    lines = [f"Made by `{prov.get('command', 'python studies/builds_vs_vertex.py')}` ({prov.get('date', '?')}, {result.get('cpu', '?')}, "
             f"{result.get('cores', '?')} cores; from `{Path(str(result.get('json', 'presets.json'))).name}`).", "",
             f"Build s: wall-clock seconds of `prt-train` under `nice` with `--threads {result['builds'][0]['timing']['threads'] if result['builds'] else '?'}`; CPU s: the build's own CPU time (on an idle "
             "machine a one-thread build's wall time is about its CPU time); others' CPU share: the share of the cores other "
             "processes took during the build (`prt.bench.machine`).  Estimate: `build.json`'s held-out sizing summary (dB over the "
             "per-vertex PRT estimate, worst bundled light; where sizing ended).  Then `prt-bench`'s diffuse PSNR of view images "
             "(networks, per-vertex PRT with the same bounces at the build's rays per vertex, per-vertex PRT on the mesh decimated to "
             "the networks' bytes), and the reference's own noise.", "",
             "| mesh | vertices | quality | build s (CPU s) | others' CPU share | estimate: gain dB (ended) | light | networks dB | vertex dB | gain | "
             "bytes / vertex bytes | equal-bytes vertex dB (vertices) | gain at equal bytes | reference noise dB |",
             "|---|---:|---|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for b in result["builds"]:
        t, z = b["timing"], b["timing"].get("sizing") or {}
        estimate = f"{z['gain_db']:+.2f} ({z['ended']})" if z else "-"
        for r in b.get("rows", [{}]):
            light = r.get("scene", "-").removeprefix(b["scene"]).lstrip("-") or "own (potsdamer)"
            eq = (f"{r['equal_bytes_psnr_db']:.2f} ({r['equal_bytes_vertices']:,})", f"{r['gain_equal_bytes_db']:+.2f}") if "equal_bytes_psnr_db" in r else ("-", "-")
            lines.append(f"| {Path(t['mesh']).name} | {t['vertices']:,} | {t['quality']} | {t['wall_s']:.0f} ({t['cpu_s']:.0f}) | {t['other_cpu_share']} | "
                         f"{estimate} | {light} | {r.get('psnr_db', '-')} | {r.get('vertex_psnr_db', '-')} | {r.get('gain_db', '-')} | "
                         f"{r.get('weight_bytes', 0) / max(r.get('vertex_bytes', 1), 1):.2f} | {eq[0]} | {eq[1]} | {r.get('ref_noise_db', '-')} |")
    notes = [f"- {Path(b['timing']['mesh']).name} {b['timing']['quality']}: {b['note']}" for b in result["builds"] if b.get("note")]
    return "\n".join(lines + ([""] + notes if notes else [])) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("meshes", nargs="+", type=Path)
    p.add_argument("--quality", nargs="+", default=["standard"], choices=("draft", "standard", "high"))
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--md", type=Path, default=None)
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-builds-vs-vertex"))
    p.add_argument("--lights", nargs="*", default=["venice_sunset_1k"])
    p.add_argument("--threads", type=int, default=1, help="prt-train --threads (1: on a shared machine, oversubscribed threads are slower)")
    p.add_argument("--views", type=int, default=2)
    p.add_argument("--size", type=int, default=192)
    p.add_argument("--ref-rays", type=int, default=1024)
    p.add_argument("--ref-hit-rays", type=int, default=256)
    p.add_argument("--ref-hit-transfer-rays", type=int, default=32)
    p.add_argument("--no-bench", action="store_true", help="time the builds only")
    p.add_argument("--md-only", action="store_true", help="write --md from --json's records, measure nothing")
    p.add_argument("--extra", nargs="*", default=[], help="more prt-train flags, the same for every build")
    args = p.parse_args(argv)
    result = {"provenance": provenance(), "cpu": cpu_name(), "cores": os.cpu_count(), "json": str(args.json), "builds": []}
    if args.json.is_file():  # resume: keep what was measured
        kept = json.loads(args.json.read_text())
        result["builds"] = kept.get("builds", [])
        if args.md_only:
            if args.md:
                atomic_write_bytes(args.md, markdown({**kept, "json": str(args.json)}).encode())
            return 0
    done = {(b["timing"]["mesh"], b["timing"]["quality"]) for b in result["builds"] if "rows" in b or args.no_bench}
    for mesh in args.meshes:
        for quality in args.quality:
            if (str(mesh), quality) in done:
                continue
            out = args.work / f"{mesh.stem}-{quality}"
            timing = timed_build(mesh, quality, out, args.threads, args.extra)
            entry = {"scene": json.loads((out / "scene.json").read_text())["name"], "timing": timing}
            if not args.no_bench:
                report = bench(out, args.lights, args)
                entry.update(rows=rows_of(report, timing), bench_command=report["command"],
                             bench_machine={k: report["machine"].get(k) for k in ("cpu", "load_average", "other_cpu_share")})  # fmt: skip
            result["builds"] = [b for b in result["builds"] if (b["timing"]["mesh"], b["timing"]["quality"]) != (str(mesh), quality)]
            result["builds"].append(entry)
            result["provenance"] = provenance()
            atomic_write_json(args.json, result)
            if args.md:
                atomic_write_bytes(args.md, markdown(result).encode())
            print(markdown(result), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
