"""Neural-SDF table in the spirit of the paper's Table 3: two SDF sizes x two transfer sizes.

usage: python studies/neural_sdf_table.py [--mesh MESH] [--sdf-sizes 64x4 32x4] [--transfer-sizes 32x3 64x3]
                                        [--sdf-samples 150000] [--sdf-steps 1500] [--samples 8000] [--rays 128]
                                        [--steps 1000] [--segments 2] [--size 128] [--views 2] [--ref-rays 256]
                                        [--gbuffer-frames 5] [--threads 2] [--work /tmp/prt-neural-sdf-table]
                                        [--out docs/benchmarks/neural_sdf_table] [--build-only] [--note TEXT]

For every SDF size (``--sdf-size KxL`` of ``prt-train --neural-sdf``) and transfer size
(``--hidden H --layers L`` of the transfer networks) it builds the mesh (default the shared
bunny) as a neural-SDF scene, then measures diffuse and glossy FPS and PSNR against the
ray-traced reference with ``prt-bench`` (ONNX and GLSL backends, fp32), and the G-buffer
cost per frame of each SDF scene beside that of the mesh itself rasterised (a mesh scene of
the same mesh with throwaway transfer networks: the G-buffer does not depend on them).

Resumable: builds live under ``--work`` (``sdf<K>x<L>/t<H>x<L>``); a build whose
``scene.json`` exists and whose recorded command is the same is reused.  One SDF fit per SDF
size (later transfer sizes copy its ``.sdf.onnx`` and ``neural_sdf.json``, which
``prt-train`` reuses) and one precompute (linked).  ``prt-bench`` keeps its reference and
each finished scene in ``<work>/bench_cache``, so an interrupted run resumes.  Writes
``<out>.json`` and ``<out>.md`` with the settings and the command.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import default_mesh  # noqa: E402

from prt.runtime.files import atomic_write_bytes, atomic_write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]  # the checkout
MARK = "study_build.json"


def _size(text: str) -> tuple[int, int]:
    try:
        k, l = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected KxL (e.g. 64x4), got {text!r}") from None
    if k < 1 or l < 1:
        raise argparse.ArgumentTypeError(f"expected positive KxL, got {text!r}")
    return k, l


def _label(size) -> str:
    return f"{size[0]}x{size[1]}"


def _run_build(cmd: list[str], out: Path, log) -> bool:
    """Run ``prt-train`` unless ``out`` holds a finished build of the same command; True if it ran."""
    mark = out / MARK
    if (out / "scene.json").is_file() and mark.is_file() and json.loads(mark.read_text()).get("cmd") == cmd[1:]:
        log(f"   reusing {out}")
        return False
    log(f"   {shlex.join(cmd[1:])}")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    (out.parent / f"{out.name}.log").write_text(proc.stdout)
    if proc.returncode != 0:
        raise SystemExit(f"build failed ({out}); its log: {out.parent / (out.name + '.log')}\n" + proc.stdout[-2000:])
    atomic_write_json(mark, {"cmd": cmd[1:], "seconds": round(time.perf_counter() - t0, 1)})
    return True


def gbuffer_ms(scene_path: Path, size: int, frames: int, ctx) -> dict:
    """Median G-buffer time per frame (ms) of a scene at ``size``^2, default camera, after one warm-up."""
    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(scene_path)
    with Renderer(scene, size, size, backend="onnx", ctx=ctx) as r:
        r.gbuffer.render(r.camera)
        ctx.finish()
        times = []
        for _ in range(frames):
            t0 = time.perf_counter()
            r.gbuffer.render(r.camera)
            ctx.finish()
            times.append(time.perf_counter() - t0)
        covered = int(r.gbuffer_image().covered.sum())
    return {"ms": round(1e3 * float(np.median(times)), 2), "frames": frames, "covered_pixels": covered,
            "kind": scene.manifest.geometry.type}  # fmt: skip


def _pick(records, scene, backend, material):
    for r in records:
        if (r["scene"], r["backend"], r["precision"], r["material"]) == (scene, backend, "fp32", material):
            return r
    return None


def table(report: dict) -> str:
    """The Markdown table of ``report``."""
    head = ["SDF", "SDF error (mean abs / Chamfer)", "transfer", "weights", "diffuse PSNR", "glossy PSNR",
            "diffuse FPS (onnx / glsl)", "glossy FPS (onnx / glsl)", "SDF G-buffer ms", "mesh G-buffer ms", "ref noise (d / g)"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|---|---|---|" + "---:|" * (len(head) - 3)]
    mesh_ms = report["mesh_gbuffer"]["ms"] if report.get("mesh_gbuffer") else None
    for row in report["rows"]:
        def cell(key, fmt="{:.2f}"):
            v = row.get(key)
            return "-" if v is None else fmt.format(v)

        err = row["sdf_error"]
        lines.append(
            f"| {row['sdf_size']} | {err['mean_abs_sdf']:.2e} / {err['chamfer']:.2e} | {row['transfer_size']} | "
            f"{cell('weight_bytes', '{:,}')} | {cell('psnr_diffuse')} | {cell('psnr_glossy')} | "
            f"{cell('fps_diffuse_onnx')} / {cell('fps_diffuse_glsl')} | {cell('fps_glossy_onnx')} / {cell('fps_glossy_glsl')} | "
            f"{cell('gbuffer_ms', '{:.1f}')} | {'-' if mesh_ms is None else f'{mesh_ms:.1f}'} | "
            f"{cell('ref_noise_diffuse', '{:.1f}')} / {cell('ref_noise_glossy', '{:.1f}')} |"
        )  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", type=Path, default=None, help="watertight mesh (default: the shared bunny)")
    p.add_argument("--sdf-sizes", type=_size, nargs="+", default=[(64, 4), (32, 4)], metavar="KxL")
    p.add_argument("--transfer-sizes", type=_size, nargs="+", default=[(32, 3), (64, 3)], metavar="HxL",
                   help="transfer networks' --hidden x --layers")  # fmt: skip
    p.add_argument("--sdf-samples", type=int, default=150_000)
    p.add_argument("--sdf-steps", type=int, default=1500)
    p.add_argument("--samples", type=int, default=8000)
    p.add_argument("--rays", type=int, default=128)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--segments", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--size", type=int, default=128, help="image side of the benchmark and the G-buffer timing")
    p.add_argument("--views", type=int, default=2)
    p.add_argument("--ref-rays", type=int, default=256)
    p.add_argument("--gbuffer-frames", type=int, default=5)
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-neural-sdf-table"))
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "neural_sdf_table")
    p.add_argument("--build-only", action="store_true")
    p.add_argument("--note", default="", help="a sentence written under the title (e.g. why the settings are small)")
    args = p.parse_args(argv)
    log = lambda line: print(line, flush=True)  # noqa: E731

    mesh = default_mesh(args.mesh)
    stem = mesh.name.split(".")[0]
    args.work.mkdir(parents=True, exist_ok=True)
    common = ["--samples", str(args.samples), "--rays", str(args.rays), "--steps", str(args.steps),
              "--segments", str(args.segments), "--threads", str(args.threads), "--no-progress"]  # fmt: skip
    builds = []
    for sdf_size in args.sdf_sizes:
        first = None
        for transfer in args.transfer_sizes:
            out = args.work / f"sdf{_label(sdf_size)}" / f"t{_label(transfer)}"
            name = f"{stem}-sdf{_label(sdf_size)}-t{_label(transfer)}"
            log(f"== {name}")
            out.mkdir(parents=True, exist_ok=True)
            if first is not None:  # the same SDF network and ground truth as the first transfer size
                for f in (f"{stem}.sdf.onnx", "neural_sdf.json", ".prt-build"):
                    if (first / f).is_file() and not (out / f).exists():
                        shutil.copy2(first / f, out / f)
                if not (out / "precompute").exists():
                    (out / "precompute").symlink_to((first / "precompute").resolve())
            cmd = [sys.executable, "-m", "prt.train.train_cli", str(mesh), "-o", str(out), "--name", name, "--neural-sdf",
                   "--sdf-size", _label(sdf_size), "--sdf-samples", str(args.sdf_samples), "--sdf-steps", str(args.sdf_steps),
                   "--hidden", str(transfer[0]), "--layers", str(transfer[1]), *common]  # fmt: skip
            _run_build(cmd, out, log)
            first = first or out
            builds.append((sdf_size, transfer, name, out))
    mesh_out = args.work / "mesh-gbuffer"
    log("== mesh G-buffer scene (throwaway transfer networks)")
    _run_build([sys.executable, "-m", "prt.train.train_cli", str(mesh), "-o", str(mesh_out), "--name", f"{stem}-mesh",
                "--samples", "2000", "--validation", "1000", "--rays", "16", "--steps", "50", "--segments", "1",
                "--hidden", "8", "--layers", "1", "--bounces", "0", "--threads", str(args.threads), "--no-progress"], mesh_out, log)  # fmt: skip
    if args.build_only:
        log(f"built {len(builds)} neural-SDF scenes and the mesh scene under {args.work}")
        return 0

    from prt.runtime.gl import create_context

    ctx = create_context()
    mesh_gb = gbuffer_ms(mesh_out / "scene.json", args.size, args.gbuffer_frames, ctx)
    log(f"mesh G-buffer {args.size}^2: {mesh_gb['ms']:.1f} ms")
    sdf_gb = {}
    for _, _, name, out in builds:
        sdf_gb[name] = gbuffer_ms(out / "scene.json", args.size, args.gbuffer_frames, ctx)
        log(f"{name} G-buffer {args.size}^2: {sdf_gb[name]['ms']:.1f} ms")
    ctx.release()

    bench_json = args.work / "bench.json"
    bench = [sys.executable, "-m", "prt.bench.cli", *(str(out / "scene.json") for *_, out in builds),
             "--views", str(args.views), "--size", str(args.size), "--ref-rays", str(args.ref_rays),
             "--backends", "onnx", "glsl", "--precisions", "fp32", "--json", str(bench_json),
             "--md", str(args.work / "bench.md"), "--cache", str(args.work / "bench_cache")]  # fmt: skip
    log(f"== benchmark: {shlex.join(bench[1:])}")
    subprocess.run(bench, check=True)
    records = json.loads(bench_json.read_text())["records"]

    rows = []
    for sdf_size, transfer, name, out in builds:
        info = json.loads((out / "neural_sdf.json").read_text())
        row = {"scene": name, "sdf_size": _label(sdf_size), "transfer_size": _label(transfer),
               "sdf_error": info["geometric_error"], "sdf_fit_s": info.get("seconds"),
               "gbuffer_ms": sdf_gb[name]["ms"], "gbuffer_covered_pixels": sdf_gb[name]["covered_pixels"]}  # fmt: skip
        for material in ("diffuse", "glossy"):
            for backend in ("onnx", "glsl"):
                r = _pick(records, name, backend, material)
                if r is None:
                    continue
                row[f"fps_{material}_{backend}"] = r["fps"]
                row[f"bench_gbuffer_ms_{material}_{backend}"] = r["stages_ms"].get("gbuffer")
                if backend == "onnx":
                    row[f"psnr_{material}"] = r["psnr"]
                    row[f"ref_noise_{material}"] = r.get("ref_noise_psnr")  # the reference's own noise (dB)
                    row["weight_bytes"] = r["weight_bytes"]
                    row["flops_per_fragment"] = r["flops_per_fragment"]
        rows.append(row)
    command = "python studies/neural_sdf_table.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    settings = {k: ([_label(s) for s in v] if k.endswith("sizes") else str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    report = {"command": command.strip(), "settings": settings, "mesh": str(mesh), "mesh_gbuffer": mesh_gb, "rows": rows,
              "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out.with_suffix(".json"), report)
    note = f"{args.note}\n\n" if args.note else ""
    page = (
        "# Neural-SDF table (Table 3 style)\n\n"
        f"Made by `{report['command']}` on this project's 2-core machine (no GPU; OpenGL from Mesa llvmpipe).\n\n"
        f"{note}"
        f"Settings: `{json.dumps(settings)}`\n\n"
        "PSNR over covered pixels (ONNX backend, fp32; the GLSL backend agrees) against a reference whose transfer is\n"
        "sphere traced at every visible pixel through the same SDF network; FPS are medians over the views.\n"
        f"G-buffer ms: median of {args.gbuffer_frames} frames at {args.size}x{args.size}, default camera; the mesh column is\n"
        "the same mesh rasterised.  SDF error in scene units (scene box side 2).\n\n"
        f"{table(report)}\n"
    )
    atomic_write_bytes(args.out.with_suffix(".md"), page.encode())
    log(f"wrote {args.out.with_suffix('.json')} and {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
