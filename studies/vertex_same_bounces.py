"""A build against per-vertex PRT with the same bounces, under its own env map and under others.

usage: python studies/vertex_same_bounces.py BUILD [BUILD ...] [--envmaps venice_sunset_1k]
                                        [--work DIR] [--views 8] [--size 256] [--ref-rays 512]
                                        [--ref-hit-rays 512] [--ref-hit-transfer-rays 16]
                                        [--baseline-rays N]
                                        [--json OUT] [--md OUT]

For each build (a ``prt-train`` output folder or its ``scene.json``) and each extra env map
(a file, or a name under ``../shared/data/envmaps``, ``.hdr`` optional), a copy of the scene
folder whose manifest's lighting is that map's SH projection (``load_envmap_sh``) goes under
``--work``; then ``prt-bench`` measures all of them once, ONNX fp32 and the vertex baseline
(direct and with the build's bounces), against the bounce reference with ``--ref-hit-rays`` x
``--ref-hit-transfer-rays`` (512 x 16: as many rays as the default 64 x 128, about 10 dB less
noisy).  The summary: per scene and light, the network's diffuse PSNR minus the vertex
baseline's with the same transfer, and their bytes (issue 25's target: >= +3 dB at <= the
vertex baseline's bytes).  The vertex baseline traces ``--ref-rays`` per vertex unless
``--baseline-rays`` says otherwise (e.g. the build's own ``--rays``, so that a quieter reference
does not also give the baseline more rays than the networks' training samples had).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from prt.runtime.envmap import load_envmap_sh
from prt.runtime.files import atomic_write_bytes

ROOT = Path(__file__).resolve().parents[1]
ENVMAPS = ROOT.parent / "shared" / "data" / "envmaps"


def resolve_envmap(name: str) -> Path:
    for p in (Path(name), ENVMAPS / name, ENVMAPS / f"{name}.hdr"):
        if p.is_file():
            return p
    raise SystemExit(f"env map {name!r}: no such file (nor under {ENVMAPS})")


def relit_copy(build: Path, envmap: Path, work: Path) -> Path:
    """A copy of ``build``'s scene folder lit by ``envmap``'s SH (no background map)."""
    manifest = json.loads((build / "scene.json").read_text())
    out = work / f"{manifest['name']}-{envmap.stem}"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for item in ("build.json", "geometry.npz", "segments"):
        src = build / item
        if src.is_dir():
            shutil.copytree(src, out / item)
        elif src.is_file():
            shutil.copy2(src, out / item)
    sh = load_envmap_sh(envmap, int(manifest["sh_bands"]))
    manifest["name"] = f"{manifest['name']}-{envmap.stem}"
    manifest["lighting"] = {"envmap": None, "sh": [[float(v) for v in row] for row in sh]}
    atomic_write_bytes(out / "scene.json", json.dumps(manifest, indent=1).encode())
    return out


def summary(report: dict) -> list[dict]:
    rows = []
    vertex_rays = {e["scene"]: e["vertex_baseline"].get("rays") for e in report.get("scenes", [])}
    recs = [r for r in report["records"] if r["material"] == "diffuse" and r["precision"] == "fp32"]
    for scene in dict.fromkeys(r["scene"] for r in recs):
        net = [r for r in recs if r["scene"] == scene and r["backend"] == "onnx"]
        for r in net:
            same = [v for v in recs if v["scene"] == scene and v["backend"] == "vertex" and v["transfer"] == r["transfer"]]
            if not same:
                continue
            v = same[0]
            rows.append({"scene": scene, "transfer": r["transfer"], "network_db": r["psnr"], "vertex_db": v["psnr"],
                         "gain_db": round(r["psnr"] - v["psnr"], 2), "network_bytes": r["weight_bytes"], "vertex_bytes": v["weight_bytes"],
                         "bytes_ratio": round(r["weight_bytes"] / v["weight_bytes"], 3), "ref_noise_db": r.get("ref_noise_psnr"),
                         "vertex_rays": vertex_rays.get(scene),
                         "met": bool(r["psnr"] - v["psnr"] >= 3.0 and r["weight_bytes"] <= v["weight_bytes"])})  # fmt: skip
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("builds", nargs="+", type=Path)
    p.add_argument("--envmaps", nargs="*", default=["venice_sunset_1k"])
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-vertex-same-bounces"))
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--ref-rays", type=int, default=512)
    p.add_argument("--ref-hit-rays", type=int, default=512)
    p.add_argument("--ref-hit-transfer-rays", type=int, default=16)
    p.add_argument("--baseline-rays", type=int, default=None, help="rays per vertex of the vertex baseline (default: --ref-rays)")
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    builds = [b.parent if b.suffix == ".json" else b for b in args.builds]
    scenes = list(builds)
    for b in builds:
        for name in args.envmaps:
            scenes.append(relit_copy(b, resolve_envmap(name), args.work))
    bench = [sys.executable, "-m", "prt.bench.cli", *[str(s / "scene.json") for s in scenes], "--views", str(args.views),
             "--size", str(args.size), "--ref-rays", str(args.ref_rays), "--ref-rays-max", str(2 * args.ref_rays),
             "--ref-hit-rays", str(args.ref_hit_rays), "--ref-hit-transfer-rays", str(args.ref_hit_transfer_rays),
             "--backends", "onnx", "vertex", "--precisions", "fp32", "--warmup", "2", "--config-budget", "8", "--packing-views", "1",
             "--cache", str(args.work / "bench_cache"), "--json", str(args.json)]  # fmt: skip
    if args.baseline_rays is not None:
        bench += ["--baseline-rays", str(args.baseline_rays)]
    print("==", " ".join(bench[1:]), flush=True)
    subprocess.run(bench, check=True)
    report = json.loads(args.json.read_text())
    rows = summary(report)
    report["vertex_same_bounces"] = {"command": "python studies/vertex_same_bounces.py " + " ".join(sys.argv[1:] if argv is None else argv),
                                     "rows": rows}  # fmt: skip
    atomic_write_bytes(args.json, json.dumps(report, indent=1).encode())
    lines = ["| scene | transfer | network dB | vertex dB (rays per vertex) | gain | bytes ratio | reference noise dB | target |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['scene']} | {r['transfer']} | {r['network_db']:.2f} | {r['vertex_db']:.2f} ({r['vertex_rays']}) | {r['gain_db']:+.2f} | {r['bytes_ratio']:.2f}x | "
              f"{r['ref_noise_db'] if r['ref_noise_db'] is not None else '-'} | {'met' if r['met'] else 'missed'} |" for r in rows]  # fmt: skip
    text = "\n".join(lines)
    print(text)
    if args.md:
        atomic_write_bytes(args.md, (text + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
