"""Which k-d leaf to cut next: equal areas (``--split samples``) against unexplained transfer (``--split residual``).

usage: python studies/split_rule.py [--scenes daffodil spot bunny teapot] [--work DIR]
                                          [--samples 100000] [--rays 256] [--segments 8] [--rules samples residual]
                                          [--train-args "..."] [--bench-args "..."] [--json OUT] [--md OUT]

For each scene, two ``prt-train`` builds that differ only in ``--split``; the second starts from
a copy (hard links) of the first's ray-traced transfer cache, so both fit the same samples and
only the segments differ.  Then ``prt-bench`` measures both against one reference (shared
``--cache``): ONNX fp32, diffuse and glossy PSNR over the covered pixels, and the per-segment
held-out errors from each build's report.  Builds and benches are cached under ``--work``; a
rerun only measures what is missing.  ``--rules samples`` alone builds one side (e.g. the real
default, 8 leaves, beside a ``--split residual`` run with more leaves); its row then shows "-".
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

from prt.runtime.files import atomic_write_bytes

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT.parent / "shared" / "data" / "meshes"
SCENES = {
    "daffodil": MESHES / "daffodil_plant.obj",
    "spot": ROOT / "tests" / "data" / "spot.obj",
    "bunny": MESHES / "stanford_bunny_hr.obj",
    "teapot": MESHES / "utah_teapot.obj",
    "cornell": ROOT / "tests" / "data" / "CornellBox-Original.obj",
}
RULES = ("samples", "residual")
BENCH = ["--views", "4", "--size", "256", "--backends", "onnx", "--precisions", "fp32", "--warmup", "1", "--packing-views", "1"]


def build(scene: str, rule: str, args) -> Path:
    out = args.work / scene / f"{rule}-s{args.segments}"
    if (out / "scene.json").is_file():
        return out
    first = next((f for f in sorted((args.work / scene).glob("*-s*")) if (f / "precompute" / "cache").is_dir()
                  and f.name != out.name and (f / "build.json").is_file()), None)  # fmt: skip
    same = first is not None and json.loads((first / "build.json").read_text())["spec"].get("samples") == args.samples
    if same and not out.exists():
        (out / "precompute").mkdir(parents=True)  # the same ray-traced transfer: only the segments differ
        subprocess.run(["cp", "-al", str(first / "precompute" / "cache"), str(out / "precompute")], check=True)
    cmd = [sys.executable, "-m", "prt.train.train_cli", str(SCENES[scene]), "-o", str(out), "--force", "--name", f"{scene}-{rule}",
           "--samples", str(args.samples), "--rays", str(args.rays), "--segments", str(args.segments), "--split", rule,
           "--no-progress", *shlex.split(args.train_args)]  # fmt: skip
    print(f"== {scene} {rule}: {shlex.join(cmd[2:])}", flush=True)
    started = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.parent / f"{out.name}.log", "w") as log:
        subprocess.run(cmd, check=True, stdout=log, stderr=subprocess.STDOUT)
    (out / "study_build_seconds.txt").write_text(f"{time.perf_counter() - started:.1f}\n")
    return out


def bench(scene: str, out: Path, args) -> dict:
    report = out.parent / f"{out.name}_bench.json"
    if not report.is_file():
        cmd = [sys.executable, "-m", "prt.bench.cli", str(out / "scene.json"), "--ref-rays", str(args.ref_rays),
               "--cache", str(args.work / scene / "bench_cache"), "--json", str(report), *BENCH, *shlex.split(args.bench_args)]  # fmt: skip
        print(f"== bench {out.name}: {shlex.join(cmd[2:])}", flush=True)
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    rows = json.loads(report.read_text())["records"]
    psnr = {r["material"]: r["psnr"] for r in rows if r["backend"] == "onnx" and r["precision"] == "fp32"}
    built = json.loads((out / "build.json").read_text())
    segs = built["segments"]
    return {
        "diffuse_db": psnr["diffuse"], "glossy_db": psnr["glossy"],
        "segments": len(segs),
        "segment_samples": [s.get("samples") for s in segs],
        "segment_shaded_err_pct": [round(max(s["shaded"].values()) * 100, 2) if s.get("shaded") else None for s in segs],
        "weight_bytes": sum(int(s.get("weight_bytes", 0)) for s in segs),
        "ref_noise_db": min(r["ref_noise_psnr"] for r in rows),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="*", default=["daffodil", "spot"], choices=list(SCENES))
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-split"))
    p.add_argument("--samples", type=int, default=100_000)
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--ref-rays", type=int, default=256)
    p.add_argument("--segments", type=int, default=8)
    p.add_argument("--rules", nargs="*", default=list(RULES), choices=list(RULES), help="which sides to build [both]")
    p.add_argument("--train-args", default="--hidden 64 --layers 4 --steps 1000 --batch 4096 --bounces 0",
                   help="more prt-train options for both builds [%(default)s]")
    p.add_argument("--bench-args", default="", help="more prt-bench options, e.g. \"--ref-hit-rays 512 --ref-hit-transfer-rays 16\"")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    command = "python studies/split_rule.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    rows = []
    for scene in args.scenes:
        if not SCENES[scene].is_file():
            print(f"note: {SCENES[scene]} not found (no ../shared here); skipping {scene}")
            continue
        got = {rule: bench(scene, build(scene, rule, args), args) for rule in args.rules}
        both = all(rule in got for rule in RULES)
        rows.append({"scene": scene, **{rule: got.get(rule) for rule in RULES},
                     "gain_db": [round(got["residual"][m] - got["samples"][m], 2) for m in ("diffuse_db", "glossy_db")] if both else None})  # fmt: skip
    report = {"command": command, "date": time.strftime("%Y-%m-%d"), "settings": {k: str(v) for k, v in vars(args).items()}, "rows": rows}
    if args.json:
        atomic_write_bytes(args.json, json.dumps(report, indent=1).encode())
    lines = [f"Made by `{command}` on {report['date']}.", "",
             "| scene | leaf budget | `--split samples` D / G dB | `--split residual` D / G dB | gain D / G dB | worst segment's held-out shaded error %: samples -> residual |",
             "|---|---:|---|---|---|---|"]  # fmt: skip

    def side(got: dict | None) -> tuple[str, str]:
        if got is None:
            return "-", "-"
        worst = max((e for e in got["segment_shaded_err_pct"] if e is not None), default=float("nan"))  # nan: all analytic
        return f"{got['diffuse_db']:.2f} / {got['glossy_db']:.2f}", f"{worst:.1f}"

    for r in rows:
        (a, wa), (b, wb) = side(r["samples"]), side(r["residual"])
        gain = f"{r['gain_db'][0]:+.2f} / {r['gain_db'][1]:+.2f}" if r["gain_db"] else "-"
        lines.append(f"| {r['scene']} | {args.segments} | {a} | {b} | {gain} | {wa} -> {wb} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
