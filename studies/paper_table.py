"""The paper-style table, reproduced by one command.

usage: python studies/paper_table.py [--samples 1000000] [--views 30] [--size 512] [--ref-rays 1024]
                                   [--backends onnx glsl vertex texture] [--texture-size 512 1024] [--work /tmp/prt-paper]
                                   [--meshes bunny ...] [--sizes k64 k128 right-sized] [--build-only]
                                   [--warmup 3] [--config-budget SECONDS] [--packing-views N]
                                   [--precisions fp32 fp16 int8] [--fresh] [--bounces auto|N]
                                   [--ref-hit-rays N] [--ref-hit-transfer-rays N]
                                   [--out docs/benchmarks/paper] [--doc docs/paper_table.md]

Builds the shared meshes (bunny, teapot, spot, daffodil plant; from ../shared/data/meshes,
Spot falls back to the bundled copy), the bundled Cornell box and the built-in ``creature`` SDF
scene, with ``prt-train``'s default bounces (``--bounces 0``: the paper's direct transfer; the
vertex and texture baselines get the networks' bounces), at the paper's two sizes (k = 64 and k = 128, l = 4) and
at our right-sized setting (``prt-train --match 64x4``: per segment, the cheapest size on the
ladder whose validation error is within 5 % of the k = 64 network's), sharing one
precompute per mesh, then runs the backend benchmark (``prt-bench``) over all of
them and writes ``<out>.json``, ``<out>.md``, ``<out>.png`` and ``<out>_builds.json`` (each build's
command and wall time) plus ``docs/paper_table.md`` (or ``--doc``) with the date and command that made them.  Every stage is cached (builds under --work, references and
each finished scene's measurement in ``<out>_cache``), so an interrupted run resumes at the
scene it was on; --fresh measures every scene again.  The full setting takes hours on 2 cores; smaller --samples/--views/--size give a
quicker table (the settings are written next to the figures).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from prt.runtime.files import atomic_write_bytes

ROOT = Path(__file__).resolve().parents[1]  # the checkout
SHARED = ROOT.parent / "shared" / "data" / "meshes"
MESHES = {
    "bunny": SHARED / "stanford_bunny_hr.obj",
    "teapot": SHARED / "utah_teapot.obj",
    "spot": SHARED / "spot.obj",
    "daffodil": SHARED / "daffodil_plant.obj",
    "cornell": ROOT / "tests" / "data" / "CornellBox-Original.obj",  # bundled (public domain)
    "creature": "creature",  # a built-in SDF scene (no vertices: no vertex PRT)
}
SIZES = {
    "k64": ["--hidden", "64", "--layers", "4", "--no-analytic"],
    "k128": ["--hidden", "128", "--layers", "4", "--no-analytic"],
    # the cheapest ladder size as accurate as k = 64 (5 % MAE), per segment: the default build's rule
    "right-sized": ["--match", "64x4"],
}
K64_FLOPS = 35_257  # k = 64, l = 4 per fragment (prt.train.networks.network.Architecture)


TARGET_DIFFUSE = {"daffodil": 40.0}  # dB at k = 64; the others 45
FLOOR_DIFFUSE = {"daffodil": 40.0, "cornell": 40.0}  # issue 12: the default build's diffuse PSNR
TARGET_GLOSSY = 38.0


def _pick(records, scene, backend="onnx", precision="fp32", material="diffuse", texture_size=None):
    """The record of ``scene``'s configuration; a baseline (vertex, texture) with the networks' transfer
    (the same N bounces: a scene with bounces has direct-only baseline rows too)."""
    network = next((r for r in records if (r["scene"], r["backend"]) == (scene, "onnx")), None)
    transfer = None if network is None else network.get("transfer")
    for r in records:
        if (r["scene"], r["backend"], r["precision"], r["material"]) == (scene, backend, precision, material) and (
            texture_size is None or r.get("texture_size") == texture_size
        ) and (transfer is None or r.get("transfer", transfer) == transfer) and not r.get("interpolate"):
            return r
    return None


def _texture_sizes(records) -> list[int]:
    return sorted({r["texture_size"] for r in records if r["backend"] == "texture" and "texture_size" in r})


def _range(values, fmt="{:.2f}", unit=""):
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    lo, hi = min(values), max(values)
    return fmt.format(lo) + unit if lo == hi else f"{fmt.format(lo)} to {fmt.format(hi)}{unit}"


def summary(report: dict) -> str:
    """The table's headline figures per mesh and each target's verdict, as Markdown."""
    records = report["records"]
    meshes = [m for m in MESHES if any(r["scene"].startswith(f"{m}-") for r in records)]
    textures = _texture_sizes(records)  # texture-space PRT columns, when the run measured them
    sizes = [z for z in SIZES if any(r["scene"].endswith(f"-{z}") for r in records)]  # the builds this run made
    names = {"k64": "k = 64", "k128": "k = 128", "right-sized": "default (right-sized)"}
    head = ["mesh", "transfer", *(names[z] for z in sizes), "vertex PRT (Sloan)", *(f"texture {t}^2" for t in textures), "GLSL k = 64 FPS"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * (len(head) - 1) + "---:|"]
    verdict = {"accuracy": [], "right": [], "packing": [], "precision": [], "gemm": [], "gemm128": [], "vertex": [], "k128": [], "floor": []}
    for mesh in meshes:
        network = _pick(records, f"{mesh}-right-sized") or _pick(records, f"{mesh}-k64")
        cells = [network.get("transfer", "direct") if network else "-"]  # the baselines' rows carry the same
        for size in sizes:
            d, g = _pick(records, f"{mesh}-{size}"), _pick(records, f"{mesh}-{size}", material="glossy")
            if d is None or g is None:
                cells.append("-")
                continue
            cells.append(f"{d['psnr']:.1f} / {g['psnr']:.1f} ({d['flops_per_fragment'] / 1e3:.0f}k FLOPs, {d['weight_bytes'] / 1024:.0f} KiB)")
        vd, vg = _pick(records, f"{mesh}-k64", "vertex"), _pick(records, f"{mesh}-k64", "vertex", material="glossy")
        cells.append(f"{vd['psnr']:.1f} / {vg['psnr']:.1f} ({vd['weight_bytes'] / 1024:.0f} KiB)" if vd and vg else "-")
        for t in textures:
            td = _pick(records, f"{mesh}-k64", "texture", "fp16", texture_size=t)
            tg = _pick(records, f"{mesh}-k64", "texture", "fp16", "glossy", texture_size=t)
            cells.append(f"{td['psnr']:.1f} / {tg['psnr']:.1f} ({td['weight_bytes'] / 2**20:.1f} MiB)" if td and tg else "-")
        gl = _pick(records, f"{mesh}-k64", "glsl")
        cells.append(f"{gl['fps']:.2f}" if gl else "-")
        lines.append(f"| {mesh} | " + " | ".join(cells) + " |")
        k64d, k64g = _pick(records, f"{mesh}-k64"), _pick(records, f"{mesh}-k64", material="glossy")
        if k64d and k64g:
            need = TARGET_DIFFUSE.get(mesh, 45.0)
            verdict["accuracy"].append(f"{mesh} {k64d['psnr']:.1f}/{k64g['psnr']:.1f} dB ({'met' if k64d['psnr'] >= need and k64g['psnr'] >= TARGET_GLOSSY else 'missed'}; needs {need:.0f}/{TARGET_GLOSSY:.0f})")
            rs = _pick(records, f"{mesh}-right-sized")
            vd = _pick(records, f"{mesh}-k64", "vertex")
            if rs and vd:  # issue 12: the default beats per-vertex PRT by >= 3 dB with no more bytes
                gain = rs["psnr"] - vd["psnr"]
                ok = gain >= 3.0 and rs["weight_bytes"] <= vd["weight_bytes"]
                verdict["vertex"].append(f"{mesh} {gain:+.1f} dB with {rs['weight_bytes'] / vd['weight_bytes']:.2f}x the bytes ({'met' if ok else 'missed'})")
            big = _pick(records, f"{mesh}-k128")
            if rs and big:  # issue 12: k = 128's PSNR at no more FLOPs than k = 64
                ok = rs["psnr"] >= big["psnr"] and rs["flops_per_fragment"] <= K64_FLOPS
                verdict["k128"].append(f"{mesh} {rs['psnr'] - big['psnr']:+.1f} dB at {rs['flops_per_fragment'] / 1e3:.1f}k FLOPs ({'met' if ok else 'missed'})")
            if rs and mesh in FLOOR_DIFFUSE:
                need = FLOOR_DIFFUSE[mesh]
                verdict["floor"].append(f"{mesh} {rs['psnr']:.1f} dB ({'met' if rs['psnr'] >= need else 'missed'}; needs {need:.0f})")
            if rs:
                delta, ratio = rs["psnr"] - k64d["psnr"], rs["flops_per_fragment"] / max(k64d["flops_per_fragment"], 1)
                ok = delta >= -0.5 and ratio < 1.0
                verdict["right"].append(f"{mesh} {delta:+.2f} dB with {ratio:.2f}x the FLOPs ({'met' if ok else 'missed'})")
            # Both materials run the same networks on the same pixels: their network stages pool
            # into one ratio per mesh (a single configuration's 10-view median is noisy here).
            for precision in ("int8", "fp16", "fp16-mlp"):
                v, vg = _pick(records, f"{mesh}-k64", precision=precision), _pick(records, f"{mesh}-k64", precision=precision, material="glossy")
                if v and vg and v["network_ms"] > 0 and vg["network_ms"] > 0:
                    ratio = (k64d["network_ms"] + k64g["network_ms"]) / (v["network_ms"] + vg["network_ms"])
                    loss = min(v["psnr"] - k64d["psnr"], vg["psnr"] - k64g["psnr"])
                    verdict["precision"].append((precision, mesh, ratio, loss))
            verdict["gemm"].append((mesh, 0.5 * (k64d["machine_percent"] + k64g["machine_percent"])))
            big, bigg = _pick(records, f"{mesh}-k128"), _pick(records, f"{mesh}-k128", material="glossy")
            if big and bigg:
                verdict["gemm128"].append((mesh, 0.5 * (big["machine_percent"] + bigg["machine_percent"])))
        for scene in report["scenes"]:
            if scene["scene"] == f"{mesh}-k64":
                for p in scene["packing"]:
                    verdict["packing"].append((mesh, p["packing_speedup"], p["pixel_ratio"]))
    out = ["\n".join(lines), ""]
    resumed = sorted(r["scene"] for r in report.get("machine", {}).get("resumed", []))
    where = f"{', '.join(resumed)} from an earlier run's checkpoints, the rest measured in this run" if resumed else "measured in this run"
    out.append(f"Targets (k = 64 unless said; {where}):")
    out.append("- accuracy, diffuse/glossy PSNR over covered pixels: " + "; ".join(verdict["accuracy"]))
    if verdict["right"]:
        out.append("- right-sized vs k = 64, diffuse PSNR and FLOPs per fragment (target: the same PSNR, within 0.5 dB, "
                   "with fewer FLOPs): " + "; ".join(verdict["right"]))  # fmt: skip
    if verdict["vertex"]:
        out.append("- default (right-sized) against per-vertex PRT, diffuse (target: >= 3 dB better with no more bytes): " + "; ".join(verdict["vertex"]))
    if verdict["k128"]:
        out.append(f"- default (right-sized) against k = 128, diffuse (target: k = 128's PSNR at <= {K64_FLOPS:,} FLOPs per fragment): "
                   + "; ".join(verdict["k128"]))  # fmt: skip
    if verdict["floor"]:
        out.append("- default (right-sized), diffuse: " + "; ".join(verdict["floor"]))
    met = all(s >= r for _, s, r in verdict["packing"])
    out.append("- packing vs naive: " + "; ".join(f"{m} {s}x (pixel ratio {r}x)" for m, s, r in verdict["packing"]) + f" ({'met' if met else 'missed'})")
    for precision in ("int8", "fp16", "fp16-mlp"):
        got = [(m, sp, db) for pr, m, sp, db in verdict["precision"] if pr == precision]
        if got:
            middle = float(np.median([sp for _, sp, _ in got]))
            worst = min(db for _, _, db in got)
            ok = middle >= 1.5 and worst >= -0.5
            per = "; ".join(f"{m} {sp:.2f}x, {db:+.2f} dB" for m, sp, db in got)
            out.append(f"- {precision} network stage against fp32 (both materials pooled; worse material's PSNR change): {per}: "
                       f"median {middle:.2f}x ({'met' if ok else 'missed'}: needs >= 1.5x with <= 0.5 dB lost)")  # fmt: skip
    limits = sorted({r["machine_gflops"] for r in records if r.get("machine_gflops")})
    limit = _range(limits, fmt="{:.0f}", unit=" GFLOP/s")
    share = [v for _, v in verdict["gemm"]]
    if share:
        middle = float(np.median(share))
        out.append(f"- network stage's share of the machine's fp32 GEMM limit ({limit}), k = 64: "
                   + "; ".join(f"{m} {v:.0f} %" for m, v in verdict["gemm"])
                   + f": median {middle:.0f} % ({'met' if middle >= 60 else 'missed'}: needs >= 60 %)"
                   + ("; k = 128 for comparison: " + "; ".join(f"{m} {v:.0f} %" for m, v in verdict["gemm128"]) if verdict["gemm128"] else ""))  # fmt: skip
    return "\n".join(out)


def build_times(builds: dict) -> str:
    """Each build's wall time (``prt-train``, every stage, 2 cores), as a Markdown section."""
    if not builds:
        return ""
    lines = ["## Build times", "", "| build | minutes | shares the precompute of |", "|---|---:|---|"]
    lines += [f"| {name} | {b['seconds'] / 60:.1f} | {b['shares_precompute_of'] or '-'} |" for name, b in builds.items()]
    total = sum(b["seconds"] for b in builds.values()) / 3600
    lines += ["", f"All builds: {total:.2f} h (the first build of each mesh includes its ray-traced ground truth and bounces)."]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--rays", type=int, default=512)
    p.add_argument("--views", type=int, default=30)
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--ref-rays", type=int, default=1024)
    p.add_argument("--backends", nargs="*", default=["onnx", "glsl", "vertex", "texture"], help="passed to prt-bench")
    p.add_argument("--texture-size", nargs="*", type=int, default=[512, 1024], help="passed to prt-bench (texture-space PRT)")
    p.add_argument("--warmup", type=int, default=3, help="passed to prt-bench")
    p.add_argument("--precisions", nargs="*", default=None, help="passed to prt-bench (default: all)")
    p.add_argument("--packing-views", type=int, default=None, metavar="N", help="passed to prt-bench")
    p.add_argument("--config-budget", type=float, default=None, metavar="SECONDS",
                   help="passed to prt-bench: slow configurations (GLSL k = 128 on llvmpipe) measure fewer views")  # fmt: skip
    p.add_argument("--fresh", action="store_true", help="passed to prt-bench: measure every scene again (default: resume)")
    p.add_argument("--meshes", nargs="*", default=list(MESHES), choices=list(MESHES))
    p.add_argument("--sizes", nargs="*", default=list(SIZES), choices=list(SIZES), help="which builds to make (all: the table)")
    p.add_argument("--build-only", action="store_true", help="make the builds (cached under --work) and stop before the benchmark")
    p.add_argument("--bounces", default="auto", metavar="N|auto",
                   help="passed to prt-train (default auto, its default); the baselines get the same bounces (0: the paper's direct transfer)")
    p.add_argument("--ref-hit-rays", type=int, default=None, metavar="N", help="passed to prt-bench (scenes with bounces)")
    p.add_argument("--ref-hit-transfer-rays", type=int, default=None, metavar="N", help="passed to prt-bench (scenes with bounces)")
    p.add_argument("--train-args", default="", help="more prt-train options for every build, e.g. \"--steps 1000 --batch 4096\"")
    p.add_argument("--summary-only", action="store_true",
                   help="rewrite the summary of --doc from the recorded <out>.json (new verdicts on old figures); builds and measures nothing")
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-paper"))
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "paper")
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "paper_table.md", help="the Markdown page with the summary")
    args = p.parse_args(argv)
    if args.summary_only:
        return _rewrite_summary(args.doc, json.loads(args.out.with_suffix(".json").read_text()))

    scenes = []
    builds_path = args.out.parent / f"{args.out.name}_builds.json"  # each build's command and wall time
    builds = json.loads(builds_path.read_text()) if builds_path.is_file() else {}
    for name in args.meshes:
        mesh = MESHES[name]
        if isinstance(mesh, Path) and not mesh.is_file():
            if name == "spot":
                mesh = ROOT / "tests" / "data" / "spot.obj"
            else:
                print(f"note: {mesh} not found (no ../shared here); skipping {name}")
                continue
        # one ground truth per mesh: later sizes (and later runs) link to the first precompute made
        first = next((args.work / name / z for z in SIZES if (args.work / name / z / "precompute").is_dir()
                      and not (args.work / name / z / "precompute").is_symlink()), None)  # fmt: skip
        for size, flags in SIZES.items():
            if size not in args.sizes:
                continue
            out = args.work / name / size
            if first is not None and first != out and not (out / "precompute").exists():
                out.mkdir(parents=True, exist_ok=True)
                (out / "precompute").symlink_to((first / "precompute").resolve())
            cmd = [sys.executable, "-m", "prt.train.train_cli", str(mesh), "-o", str(out), "--name", f"{name}-{size}",
                   "--samples", str(args.samples), "--rays", str(args.rays), "--bounces", args.bounces, "--no-progress",
                   *shlex.split(args.train_args), *flags]  # fmt: skip
            print(f"== {name} {size}: {shlex.join(cmd[2:])}", flush=True)
            started = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            seconds = time.perf_counter() - started
            # the first (uncached) build's wall time is the one kept: a rerun only reloads its stages
            if f"{name}-{size}" not in builds or builds[f"{name}-{size}"]["command"] != shlex.join(cmd[2:]):
                builds[f"{name}-{size}"] = {"command": shlex.join(cmd[2:]), "seconds": round(seconds, 1),
                                            "shares_precompute_of": None if first is None or first == out else first.name}  # fmt: skip
                atomic_write_bytes(builds_path, json.dumps(builds, indent=1).encode())
            first = first or out
            scenes.append(out / "scene.json")

    if args.build_only:
        print(f"built {len(scenes)} scenes under {args.work}")
        return 0
    bench = [sys.executable, "-m", "prt.bench.cli", *map(str, scenes),
             "--views", str(args.views), "--size", str(args.size), "--ref-rays", str(args.ref_rays),
             "--json", str(args.out.with_suffix(".json")), "--md", str(args.out.with_suffix(".md")),
             "--plot", str(args.out.with_suffix(".png")), "--backends", *args.backends, "--warmup", str(args.warmup),
             *(["--texture-size", *map(str, args.texture_size)] if "texture" in args.backends else []),
             *(["--config-budget", str(args.config_budget)] if args.config_budget else []),
             *(["--packing-views", str(args.packing_views)] if args.packing_views else []),
             *(["--ref-hit-rays", str(args.ref_hit_rays)] if args.ref_hit_rays else []),
             *(["--ref-hit-transfer-rays", str(args.ref_hit_transfer_rays)] if args.ref_hit_transfer_rays else []),
             *(["--precisions", *args.precisions] if args.precisions else []), *(["--fresh"] if args.fresh else [])]  # fmt: skip
    print(f"== benchmark: {shlex.join(bench[1:])}", flush=True)
    subprocess.run(bench, check=True)

    command = "python studies/paper_table.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    table = args.out.with_suffix(".md").read_text()
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    doc = args.doc
    report = json.loads(args.out.with_suffix(".json").read_text())
    page = (
        "# Paper-style table\n\n"
        f"Made on {time.strftime('%Y-%m-%d')} by `{command.strip()}` "
        "on this project's 2-core machine (no GPU; OpenGL from Mesa llvmpipe).\n\n"
        f"Settings: `{json.dumps(settings)}`\n\n"
        "Error is against a reference render whose transfer is ray traced at every visible pixel, on\n"
        "tone-mapped images over the pixels the scene covers; FPS are medians over the views.\n\n"
        "## Summary\n\n"
        f"{summary(report)}\n\n"
        f"{build_times(builds)}\n\n"
        "## Every configuration\n\n"
        f"{table}\n\n![speed against error]({os.path.relpath(args.out.with_suffix('.png').resolve(), doc.parent.resolve())})\n"
    )
    atomic_write_bytes(doc, page.encode())
    print(f"wrote {doc}")
    return 0


def _rewrite_summary(doc: Path, report: dict) -> int:
    """Replace the "## Summary" section of ``doc`` with :func:`summary` of ``report`` (the rest kept)."""
    page = doc.read_text()
    head, sep, rest = page.partition("## Summary\n\n")
    _, sep2, tail = rest.partition("\n\n## Every configuration")
    if not (sep and sep2):
        raise SystemExit(f"{doc}: no '## Summary' ... '## Every configuration' sections to rewrite")
    note = "(Summary rewritten from the recorded figures by `python studies/paper_table.py --summary-only`.)\n\n"
    atomic_write_bytes(doc, (head + sep + note + summary(report) + sep2 + tail).encode())
    print(f"wrote {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
