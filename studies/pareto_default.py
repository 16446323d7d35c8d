"""Many small networks on a finer spatial split, measured: the Pareto study behind the default build.

usage: python studies/pareto_default.py [--scenes spot daffodil spot-nomerge] [--configs paper seg32-k32l3 ...]
           [--work /tmp/prt-many] [--common-args "..."] [--bench-args "..."] [--glsl-size 128 | --no-glsl]
           [--speed-rounds 5] [--speed-frames 8] [--build-only] [--out docs/benchmarks/many_networks]

For each scene and each named configuration (``CONFIGS``: a name and the extra ``prt-train``
arguments), builds ``prt-train SCENE -o WORK/<scene>/<config> --name <scene>-<config> <common args>
<config args>`` (skipped when that folder's ``scene.json`` exists), then runs ``prt-bench`` on it
(its JSON cached as ``WORK/<scene>/bench/<config>-<tag of the bench args>.json``; one ``--cache`` per scene, so each scene's
ray-traced reference is traced once) and, unless ``--no-glsl``, times the ``glsl`` backend's build +
first frame in a fresh process (``studies/glsl_compile.py``'s measurement, Mesa's shader cache
off, at ``--glsl-size``; cached as ``WORK/<scene>/bench/<config>.glsl<size>.json``).  Writes ``<out>.json``
(every row) and ``<out>.md`` (a table per scene, with the commands; what follows its notes marker
line, ``NOTES``, is kept).

Columns: segments (networks), PSNR diffuse / glossy (ONNX fp32, covered pixels), FLOPs per
fragment (pixel-weighted), weight bytes (fp32), ONNX FPS at the bench size, the GLSL build + first
frame, the build's seconds (``build.json`` timings) and two Pareto flags per material: on the front
of PSNR against FLOPs per fragment, and of PSNR against weight bytes (fewer is better).

Scenes: ``spot`` (the bundled cow), ``daffodil`` (``../shared/data/meshes/daffodil_plant.obj``; skipped,
saying so, when ``../shared`` is absent) and ``spot-nomerge`` (Spot through a build spec with the
segments' merge off, so every k-d leaf keeps its own network; the spec is written to
``WORK/specs/``).  After a scene's rows, a speed pass alternates its configs' ONNX renderers in one
process (``--speed-rounds``), the FPS comparison to trust on a shared machine.

``--segment-errors BUILD OTHER`` instead says where BUILD loses to OTHER: the ONNX transfer's squared error
against a ray-traced reference per segment of BUILD (4 views at 256^2, 256 rays).

A new configuration is one line of ``CONFIGS``.  Every stage is cached, so an interrupted run
resumes; delete a build folder (or its bench JSON) to measure it again.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from prt.bench.metrics import pareto_front
from prt.runtime.files import atomic_write_bytes, atomic_write_json

ROOT = Path(__file__).resolve().parents[1]  # the checkout
SCENES = {
    "spot": ROOT / "tests" / "data" / "spot.obj",
    "daffodil": ROOT.parent / "shared" / "data" / "meshes" / "daffodil_plant.obj",
    # a build spec (written to WORK/specs/<name>.json): every k-d leaf keeps its own network (no merge)
    "spot-nomerge": {"geometry": str(ROOT / "tests" / "data" / "spot.obj"), "merge": False},
}
# name -> extra prt-train arguments (after the common ones)
CONFIGS = {
    "paper": ["--hidden", "64", "--layers", "4", "--segments", "8"],
    "seg32-k32l3": ["--segments", "32", "--hidden", "32", "--layers", "3"],
    "seg64-k32l2": ["--segments", "64", "--hidden", "32", "--layers", "2"],
    "seg64-k16l2": ["--segments", "64", "--hidden", "16", "--layers", "2"],
    "seg32-k64l2": ["--segments", "32", "--hidden", "64", "--layers", "2"],
    # the same with every segment a network (no analytic segments; the fixed sizes' analytic test is --target's)
    "paper-na": ["--hidden", "64", "--layers", "4", "--segments", "8", "--no-analytic"],
    "seg32-k32l3-na": ["--segments", "32", "--hidden", "32", "--layers", "3", "--no-analytic"],
    "seg64-k32l2-na": ["--segments", "64", "--hidden", "32", "--layers", "2", "--no-analytic"],
    "seg32-k64l2-na": ["--segments", "32", "--hidden", "64", "--layers", "2", "--no-analytic"],
    # prt-train's own sizing rule (no size flags: right-sized per segment, see `prt-train --help`)
    "default": ["--segments", "8"],
    "seg32-default": ["--segments", "32"],
}
DEFAULT_CONFIGS = ["paper", "seg32-k32l3", "seg64-k32l2", "seg64-k16l2", "seg32-k64l2"]  # the five
COMMON_ARGS = "--samples 100000 --rays 256 --steps 1000 --batch 4096 --threads 1 --bounces 0 --no-progress"
BENCH_ARGS = "--views 4 --size 256 --ref-rays 256 --backends onnx --precisions fp32 --packing-views 1"
MATERIALS = ("diffuse", "glossy")
NOTES = "<!-- notes: written by hand, kept when the script rewrites the tables above -->"


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def _run(cmd: list[str], log: Path) -> float:
    """Run ``cmd`` with its output in ``log``; its wall seconds.  A failure is one line naming the log."""
    log.parent.mkdir(parents=True, exist_ok=True)
    _log("$ " + shlex.join(cmd) + f"  (log: {log})")
    start = time.perf_counter()
    with open(log, "w") as f:
        done = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT)
    if done.returncode != 0:
        tail = (log.read_text().strip().splitlines() or ["?"])[-1]
        raise SystemExit(f"error: {cmd[2] if len(cmd) > 2 else cmd[0]} failed ({done.returncode}), see {log}: {tail}")
    return time.perf_counter() - start


def build(scene: str, mesh: Path, config: str, args) -> Path:
    out = args.work / scene / config
    cmd = [sys.executable, "-m", "prt.train.train_cli", str(mesh), "-o", str(out), "--name", f"{scene}-{config}",
           *shlex.split(args.common_args), *CONFIGS[config]]  # fmt: skip
    if not (out / "scene.json").is_file():
        _run(cmd, args.work / scene / "logs" / f"{config}.train.log")
    return out


def _key(text: str) -> str:
    """A short tag of the settings a cached result depends on (other settings: another file)."""
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def bench(scene: str, config: str, folder: Path, args) -> dict:
    path = args.work / scene / "bench" / f"{config}-{_key(args.bench_args)}.json"
    if not path.is_file() or path.stat().st_mtime < (folder / "scene.json").stat().st_mtime:
        cmd = [sys.executable, "-m", "prt.bench.cli", str(folder / "scene.json"), "--json", str(path),
               "--cache", str(args.work / scene / "bench_cache"), *shlex.split(args.bench_args)]  # fmt: skip
        _run(cmd, path.with_suffix(".log"))
    return json.loads(path.read_text())


def glsl_timing(scene: str, config: str, folder: Path, args) -> dict | None:
    if args.no_glsl:
        return None
    path = args.work / scene / "bench" / f"{config}.glsl{args.glsl_size}.json"
    if path.is_file() and path.stat().st_mtime >= (folder / "scene.json").stat().st_mtime:
        return json.loads(path.read_text())
    import glsl_compile  # the sibling study (this script's folder is first on sys.path)

    _log(f"glsl backend build + first frame: {folder / 'scene.json'} at {args.glsl_size}^2")
    result = {**glsl_compile.run_one(folder / "scene.json", args.glsl_size, args.glsl_timeout), "size": args.glsl_size}
    atomic_write_json(path, result)
    return result


def speed_pass(scene: str, folders: dict[str, Path], args) -> dict[str, dict]:
    """The ONNX backend's frame and inference stage per config, interleaved in one process (config by config,
    ``--speed-rounds`` rounds, each ``--speed-frames`` frames over the orbit's views after 2 warm-up frames), so
    the configs' speeds compare as ratios within one run on a shared machine.  Diffuse material."""
    import numpy as np

    from prt.runtime.camera import Camera, orbit_views
    from prt.runtime.renderer import Renderer, Scene

    size = args.speed_size
    samples = {c: {"frame": [], "inference": []} for c in folders}
    loads = []
    for _ in range(args.speed_rounds):
        loads.append(os.getloadavg()[0])
        for config, folder in folders.items():
            loaded = Scene.load(folder / "scene.json")
            cameras = orbit_views(Camera.from_manifest(loaded.manifest.camera), args.speed_frames)
            with Renderer(loaded, size, size, backend="onnx", threads=args.speed_threads) as r:
                for i in range(2 + args.speed_frames):
                    r.set_camera_object(cameras[i % len(cameras)] if i >= 2 else cameras[-1 - i])
                    r.render()
                    if i >= 2:
                        samples[config]["frame"].append(r.timings["frame"])
                        samples[config]["inference"].append(r.timings.get("inference", 0.0))
    out = {}
    for config, t in samples.items():
        frame, inference = float(np.median(t["frame"])), float(np.median(t["inference"]))
        out[config] = {"size": size, "frames": len(t["frame"]), "frame_ms": round(frame, 3), "fps": round(1e3 / frame, 2),
                       "inference_ms": round(inference, 3), "threads": args.speed_threads,
                       "load_1min": [round(v, 2) for v in loads]}  # fmt: skip
    _log(f"{scene} speed pass: " + "; ".join(f"{c} {v['fps']} FPS (inference {v['inference_ms']} ms)" for c, v in out.items()))
    return out


def call_costs(folder: Path, covered: float, calls: int = 200) -> dict:
    """One network segment's ONNX session alone: median microseconds of a call on 1 row (the fixed
    cost per network and frame) and on the rows a segment gets on average (covered pixels / networks)."""
    import numpy as np
    import onnxruntime as ort

    segments = json.loads((folder / "scene.json").read_text())["segments"]
    nets = [s for s in segments if s["kind"] == "network"]
    sess = ort.InferenceSession(str(folder / nets[0]["model"]), providers=["CPUExecutionProvider"])
    inp = sess.get_inputs()[0]
    rows = max(1, int(covered) // len(nets))
    out = {"rows": rows}
    for n, key in ((1, "one_row_us"), (rows, "rows_us")):
        x = np.random.default_rng(0).uniform(-1, 1, (n, inp.shape[1])).astype(np.float32)
        times = []
        for i in range(20 + calls):
            t0 = time.perf_counter()
            sess.run(None, {inp.name: x})
            if i >= 20:
                times.append(time.perf_counter() - t0)
        out[key] = round(1e6 * float(np.median(times)), 1)
    out["us_per_row"] = round(out["rows_us"] / rows, 3)
    return out


def segment_errors(first: Path, second: Path, size: int = 256, views: int = 4, rays: int = 256) -> list[dict]:
    """Where build ``first`` loses to ``second`` (two builds of one mesh): the ONNX transfer's squared
    error against a ray-traced reference (``rays`` per pixel, seed 0) on ``views`` orbit views, summed per
    segment of ``first``, largest excess first.  Both renderers share one GL context."""
    import numpy as np

    from prt.bench.reference import cached_transfer, load_scene_geometry
    from prt.runtime.camera import Camera, orbit_views
    from prt.runtime.gl import create_context
    from prt.runtime.renderer import Renderer, Scene
    from prt.train.transport.transfer import make_tracer

    a, b = Scene.load(first / "scene.json"), Scene.load(second / "scene.json")
    geometry, info = load_scene_geometry(a.manifest)
    tracer = make_tracer(geometry)
    per = {}  # segment of first -> [pixels, squared error first, squared error second]
    ctx = create_context()
    with Renderer(a, size, size, backend="onnx", ctx=ctx) as ra, Renderer(b, size, size, backend="onnx", ctx=ctx) as rb:
        for v, camera in enumerate(orbit_views(Camera.from_manifest(a.manifest.camera), views)):
            ra.set_camera_object(camera)
            rb.set_camera_object(camera)
            g = ra.gbuffer_image()
            cov = g.covered
            ref, _ = cached_transfer(first.parent.parent / "segment_errors_cache", f"view{v:03d}-{size}", geometry, tracer,
                                     g.position[cov], g.normal[cov], rays, 0, info["checksum"])  # fmt: skip
            ta, tb, seg = ra.render_transfer()[cov], rb.render_transfer()[cov], g.segment[cov]
            for k in np.unique(seg):
                m = seg == k
                row_ = per.setdefault(int(k), [0, 0.0, 0.0])
                row_[0] += int(m.sum())
                row_[1] += float(((ta[m] - ref[m]) ** 2).sum())
                row_[2] += float(((tb[m] - ref[m]) ** 2).sum())
    excess = sum(e1 - e2 for _, e1, e2 in per.values())
    leaf_segment = np.asarray(a.manifest.segmentation["leaf_segment"])
    out = [{"segment": k, "kind": a.manifest.segments[k].kind, "leaves": int((leaf_segment == k).sum()), "pixels": n,
            "mse": e1 / n, "mse_other": e2 / n, "share_of_excess": (e1 - e2) / excess if excess else 0.0}
           for k, (n, e1, e2) in per.items()]  # fmt: skip
    total = [sum(v[i] for v in per.values()) for i in range(3)]
    _log(f"{first} vs {second}: transfer MSE {total[1] / total[0]:.3e} vs {total[2] / total[0]:.3e} over {total[0]} pixels")
    for r in sorted(out, key=lambda r: -r["share_of_excess"])[:8]:
        _log(f"  segment {r['segment']} ({r['kind']}, {r['leaves']} leaves): {r['pixels']} px, MSE {r['mse']:.2e} vs "
             f"{r['mse_other']:.2e}, {r['share_of_excess']:.2f} of the excess squared error")  # fmt: skip
    return out


def row(scene: str, config: str, folder: Path, report: dict, glsl: dict | None) -> dict:
    """One table row from the build's ``build.json``, ``scene.json`` and the bench report."""
    build_json = json.loads((folder / "build.json").read_text())
    manifest = json.loads((folder / "scene.json").read_text())
    segments = manifest["segments"]
    records = {r["material"]: r for r in report["records"] if (r["backend"], r["precision"]) == ("onnx", "fp32")}
    if not all(m in records for m in MATERIALS):
        raise SystemExit(f"error: {scene}/{config}: the bench report has no onnx fp32 record per material")
    d = records["diffuse"]
    archs = sorted({s["arch_label"] for s in build_json["segments"] if s.get("kind") == "network" and s.get("arch_label")})
    return {
        "scene": scene, "config": config, "args": CONFIGS[config],
        "leaf_budget": build_json["spec"].get("segments"),
        "segments": len(segments), "networks": sum(s.get("kind", "network") == "network" for s in segments),
        "architectures": archs,
        "psnr": {m: records[m]["psnr"] for m in MATERIALS},
        "flops_per_fragment": d["flops_per_fragment"], "weight_bytes": d["weight_bytes"],
        "onnx_fps": {m: records[m]["fps"] for m in MATERIALS},
        "onnx_inference_ms": {m: records[m]["stages_ms"].get("inference") for m in MATERIALS},
        "resolution": d["resolution"], "views": d["views"], "covered_pixels": d["covered_pixels"],
        "ref_rays": d.get("ref_rays"),
        "ref_noise_psnr": {m: records[m]["ref_noise_psnr"] for m in MATERIALS},
        "build_s": build_json["timings"], "load_1min": report.get("machine", {}).get("load_average"),
        "glsl": glsl, "speed": None,
    }  # fmt: skip


def mark_fronts(rows: list[dict]) -> None:
    """Per scene and material: on the front of PSNR vs FLOPs per fragment, and of PSNR vs bytes (both fewer)."""
    for scene in {r["scene"] for r in rows}:
        mine = [r for r in rows if r["scene"] == scene]
        for r in mine:
            r["front_flops"], r["front_bytes"] = [], []
        for m in MATERIALS:
            for key, cost in (("front_flops", "flops_per_fragment"), ("front_bytes", "weight_bytes")):
                for i in pareto_front([(-r[cost], r["psnr"][m]) for r in mine]):
                    mine[i][key].append(m)


def _flag(materials: list[str]) -> str:
    return "/".join(m[0].upper() for m in materials) or "-"


def _speed_cell(v: dict | None) -> str:
    return f"{v['fps']:.1f} ({v['inference_ms']:.1f})" if v else "-"


def _call_cell(v: dict | None) -> str:
    return f"{v['call']['one_row_us']:.0f} / {v['call']['us_per_row']:.2f}" if v else "-"


def _glsl_cell(g: dict | None) -> str:
    if not g:
        return "-"
    if g.get("timed_out"):
        return f"> {g['timeout_s']:.0f} s"
    if "error" in g:
        return "error"
    return f"{g['build_and_first_frame_s']:.1f} s ({g['psnr_vs_onnx']:.0f} dB)"


def markdown(rows: list[dict], args, argv: list[str], machine: str) -> str:
    out = ["# Many small networks on a finer split: measured", "",
           "Made by `python studies/pareto_default.py " + shlex.join(argv) + "` "
           f"({time.strftime('%Y-%m-%d')}).", "",
           f"- build: `prt-train SCENE -o WORK/<scene>/<config> --name <scene>-<config> {args.common_args} <config args>`",
           f"- bench: `prt-bench WORK/<scene>/<config>/scene.json --cache WORK/<scene>/bench_cache {args.bench_args}`",
           "- PSNR: ONNX fp32 against the ray-traced reference over covered pixels, diffuse / glossy; FLOPs per "
           "fragment pixel-weighted; bytes: fp32 weights; FPS: ONNX backend, the bench's median frame "
           "(diffuse / glossy); fits s (total): `build.json` timings, the networks' fits (and precompute + fits + "
           "export; a precompute already cached counts 0); GLSL: the `glsl` backend's build + first frame in a "
           f"fresh process at {args.glsl_size}^2 on llvmpipe (its PSNR against the ONNX frame)",
           "- interleaved: the ONNX backend's median frame (FPS) and inference stage, diffuse, configs alternated "
           f"in one process ({args.speed_rounds} rounds x {args.speed_frames} frames at {args.speed_size}^2): the "
           "speed comparison to trust on a shared machine; call us: one network's ONNX session alone, the median "
           "microseconds of a call on 1 row (fixed cost per network and frame) and per row at the rows a segment "
           "gets on average (covered pixels / networks)",
           f"- machine: {machine}",
           "- front: on the Pareto front of PSNR vs FLOPs per fragment / vs weight bytes, for D(iffuse) and G(lossy)", ""]  # fmt: skip
    for scene in dict.fromkeys(r["scene"] for r in rows):
        mine = [r for r in rows if r["scene"] == scene]
        out += [f"## {scene}", "",
                "| config | leaf budget | segments (networks) | sizes | PSNR D / G (dB) | FLOPs/frag | weight bytes | "
                "ONNX FPS D / G | ONNX FPS, interleaved (inference ms) | call us: 1 row / per row | GLSL 1st frame | "
                "fits s (total) | front FLOPs | front bytes |",
                "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]  # fmt: skip
        for r in mine:
            out.append(
                f"| {r['config']} | {r['leaf_budget']} | {r['segments']} ({r['networks']}) | {' '.join(r['architectures'])} | "
                f"{r['psnr']['diffuse']:.2f} / {r['psnr']['glossy']:.2f} | {r['flops_per_fragment']:,.0f} | "
                f"{r['weight_bytes']:,} | {r['onnx_fps']['diffuse']:.1f} / {r['onnx_fps']['glossy']:.1f} | "
                f"{_speed_cell(r['speed'])} | {_call_cell(r['speed'])} | {_glsl_cell(r['glsl'])} | "
                f"{r['build_s']['train_s']:.0f} ({r['build_s']['total_s']:.0f}) | {_flag(r['front_flops'])} | {_flag(r['front_bytes'])} |"
            )  # fmt: skip
        noise = mine[0]["ref_noise_psnr"]
        loads = [v for r in mine if r["speed"] for v in r["speed"]["load_1min"]][: args.speed_rounds]
        speed_load = f"; at the speed pass's rounds: {min(loads)} to {max(loads)}" if loads else ""
        out += ["", f"Reference noise PSNR (two seeds, view 0): {noise['diffuse']:.1f} / {noise['glossy']:.1f} dB; "
                f"reference rays per pixel (prt-bench raises them where its noise is not 6 dB above a pilot's PSNR): "
                f"{', '.join(str(r['ref_rays']) for r in mine)}; "
                f"1-minute load at the bench: {', '.join(str(r['load_1min']) for r in mine)}{speed_load}.", ""]  # fmt: skip
    return "\n".join(out)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["spot", "daffodil"], choices=list(SCENES))
    p.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS, choices=list(CONFIGS),
                   help=f"names of CONFIGS [{' '.join(DEFAULT_CONFIGS)}]")  # fmt: skip
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-many"))
    p.add_argument("--common-args", default=COMMON_ARGS, help=f"prt-train arguments of every build [{COMMON_ARGS}]")
    p.add_argument("--bench-args", default=BENCH_ARGS, help=f"prt-bench arguments [{BENCH_ARGS}]")
    p.add_argument("--glsl-size", type=int, default=128, help="image size of the GLSL first-frame timing")
    p.add_argument("--glsl-timeout", type=float, default=300.0)
    p.add_argument("--no-glsl", action="store_true", help="skip the GLSL first-frame timing")
    p.add_argument("--speed-rounds", type=int, default=5, help="rounds of the interleaved ONNX speed pass (0: none)")
    p.add_argument("--speed-frames", type=int, default=8, help="timed frames per config and round (orbit views)")
    p.add_argument("--speed-size", type=int, default=256, help="image size of the speed pass")
    p.add_argument("--speed-threads", type=int, default=None, help="ONNX Runtime threads of the speed pass (default: its own)")
    p.add_argument("--build-only", action="store_true", help="make the builds and stop")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "many_networks",
                   help="writes OUT.json and OUT.md")  # fmt: skip
    p.add_argument("--segment-errors", nargs=2, type=Path, metavar=("BUILD", "OTHER"),
                   help="only this: per segment of BUILD, its transfer error against OTHER's (two builds of one mesh)")
    args = p.parse_args(argv)
    if args.segment_errors:
        segment_errors(*args.segment_errors)
        return 0

    rows, machine = [], "?"
    for scene in args.scenes:
        mesh = SCENES[scene]
        if isinstance(mesh, dict):  # a build spec: prt-train's input, the flags override its fields
            if not Path(mesh["geometry"]).is_file():
                _log(f"note: {mesh['geometry']} not found; skipping {scene}")
                continue
            spec, mesh = mesh, args.work / "specs" / f"{scene}.json"
            atomic_write_json(mesh, spec)
        elif not mesh.is_file():
            _log(f"note: {mesh} not found (no ../shared here); skipping {scene}")
            continue
        folders = {}
        for config in args.configs:
            folder = folders[config] = build(scene, mesh, config, args)
            if args.build_only:
                continue
            report = bench(scene, config, folder, args)
            m = report.get("machine", {})
            machine = (f"{m.get('cpu', '?')}, {m.get('cores', '?')} cores, {m.get('gl_renderer', '?')}; onnxruntime "
                       f"{m.get('onnxruntime', '?')}; fp32 GEMM limit {m.get('machine_gflops', '?')} GFLOP/s")  # fmt: skip
            rows.append(row(scene, config, folder, report, glsl_timing(scene, config, folder, args)))
        if folders and not args.build_only and args.speed_rounds > 0:
            speed = speed_pass(scene, folders, args)
            for r in rows:
                if r["scene"] == scene:
                    r["speed"] = {**speed[r["config"]], "call": call_costs(folders[r["config"]], r["covered_pixels"])}
    if args.build_only or not rows:
        return 0
    mark_fronts(rows)
    atomic_write_json(args.out.with_suffix(".json"), {"argv": argv, "common_args": args.common_args,
                                                      "bench_args": args.bench_args, "rows": rows})  # fmt: skip
    md = args.out.with_suffix(".md")
    notes = md.read_text().partition(NOTES)[2] if md.is_file() and NOTES in md.read_text() else "\n"
    atomic_write_bytes(md, (markdown(rows, args, argv, machine) + "\n" + NOTES + notes).encode())
    _log(f"wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
