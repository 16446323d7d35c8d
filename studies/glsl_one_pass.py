"""The GLSL backend's one-pass 64-wide transfer against the code it replaced, measured in one run.

usage: python studies/glsl_one_pass.py --bounce SCENE --held-out-16 SCENE --held-out-64 SCENE
                                       [--old-commit 3313a73 | --old DIR] [--size 160] [--views 6]
                                       [--demo-frames 30] [--demo-rounds 3] [--json OUT] [--md OUT]

"Today" is the code at ``--old-commit`` (the branch point; extracted with ``git archive`` into a
temporary folder, or ``--old DIR`` already extracted) imported as a second package ``prt_old``
next to this checkout's ``prt``, so old and new render in one process, frame for frame:

- **GLSL frames** (llvmpipe here): per scene, for each of ``--views`` orbit views, a frame of the old
  renderer, of the new one (one draw where the context has OpenGL 4.3) and of the new one held to
  the 3.3 path (two draws), in turn; each timed around ``Renderer.render()`` (pixels read back, as
  the old code always did), medians.  The images are compared: new against old and against the
  new ONNX backend (PSNR over the image's peak).
- **Scenes**: ``--bounce``, a default build with bounces (64-wide transfer); ``--held-out-16`` and
  ``--held-out-64``, one mesh built twice with the same network size, without and with bounces:
  the ratio of their frames, old and new.
- **Demo** (``make demo``'s frames: the bundled scene, ONNX backend, 512x512, interpolation at its
  default): old and new alternating frame by frame on ``--demo-frames`` orbit views, ``--demo-rounds``
  rounds; medians of each one's frame and stages, and how far the ratio moved between rounds.

Writes the figures with provenance (CPU, its ISA extensions, the machine's other load) as JSON and a
Markdown table.
"""

from __future__ import annotations

import argparse
import importlib
import io
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import cpu_label, provenance
from prt.runtime.backends.glsl import GlslBackend
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.gl import context_info, create_context

ROOT = Path(__file__).resolve().parents[1]


def old_package(commit: str, folder: Path | None, tmp: Path):
    """The runtime of ``commit`` imported as ``prt_old`` (its renderer module)."""
    if folder is None:
        folder = tmp / "old"
        data = subprocess.run(["git", "archive", commit], cwd=ROOT, capture_output=True, check=True).stdout
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            tar.extractall(folder, filter="data")
    (tmp / "pkgs").mkdir(exist_ok=True)
    link = tmp / "pkgs" / "prt_old"
    link.symlink_to(Path(folder).resolve(), target_is_directory=True)
    sys.path.insert(0, str(tmp / "pkgs"))
    return importlib.import_module("prt_old.runtime.renderer")


def psnr(a: np.ndarray, b: np.ndarray) -> float | None:
    """PSNR of ``b`` against ``a`` over ``a``'s peak, in dB; None where the two are identical."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    peak = float(max(np.abs(a).max(), 1e-12))
    return None if mse == 0 else round(10 * np.log10(peak**2 / mse), 2)


def glsl_frames(path: Path, old, size: int, views: int, ctx) -> dict:
    """Old, new (one pass) and new held to two draws, frame for frame on the same views."""
    from prt.runtime.renderer import Renderer, Scene

    renderers = {
        "old": old.Renderer(old.Scene.load(path), size, size, backend="glsl", ctx=ctx),
        "new": Renderer(Scene.load(path), size, size, backend="glsl", ctx=ctx),
        "new_two_draws": Renderer(Scene.load(path), size, size, backend="glsl", ctx=ctx),
    }
    forced = renderers["new_two_draws"]
    forced._backends["glsl"] = GlslBackend(ctx, forced.scene.manifest, one_pass=False)
    for r in renderers.values():
        r.set_background(False)
    start = renderers["new"].camera
    times = {k: [] for k in renderers}
    network = {k: [] for k in renderers}
    images = {}
    for i in range(-2, views):  # two warm-up views (the JIT of the first draw), then the timed ones
        camera = start.orbit(2 * np.pi * i / views) if i >= 0 else start.orbit(-0.01 * (i + 3))
        for name, r in renderers.items():
            r.set_camera_object(r.camera.__class__(camera.eye, camera.target, camera.up, camera.fov_y, camera.near, camera.far)
                                if name == "old" else camera)  # fmt: skip
            t0 = time.perf_counter()
            image = r.render()
            if i >= 0:
                times[name].append(1e3 * (time.perf_counter() - t0))
                network[name].append(r.timings.get("network", 0.0))
            if i == 0:
                images[name] = image
        print(f"  {path.parent.name} view {i}: " + ", ".join(f"{k} {v[-1]:.0f} ms" for k, v in times.items() if v), flush=True)
    one_pass = renderers["new"]._backends["glsl"].one_pass
    with Renderer(Scene.load(path), size, size, backend="onnx", ctx=ctx) as onnx:
        onnx.set_background(False)
        onnx.set_camera_object(start.orbit(0.0))
        reference = onnx.render()
    for r in renderers.values():
        r.close()
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {
        "scene": str(path), "transfer_width": int(renderers["new"].scene.manifest.transfer_width), "one_pass": bool(one_pass),
        "frame_ms": {k: round(v, 2) for k, v in med.items()},
        "network_ms": {k: round(float(np.median(v)), 2) for k, v in network.items()},
        "frames_ms": {k: [round(t, 2) for t in v] for k, v in times.items()},
        "speedup_vs_old": round(med["old"] / med["new"], 3),
        "speedup_two_draws_vs_old": round(med["old"] / med["new_two_draws"], 3),
        # None: the images are identical, bit for bit
        "psnr_db": {"new_vs_old": psnr(images["old"], images["new"]), "new_two_draws_vs_old": psnr(images["old"], images["new_two_draws"]),
                    "new_vs_onnx": psnr(reference, images["new"])},
    }  # fmt: skip


def demo_frames(old_renderer, frames: int, rounds: int, ctx) -> dict:
    """``make demo``'s frames (the bundled scene, ONNX backend, 512x512, default interpolation), old and
    new alternating frame by frame on the same orbit views (the first of each pair swapped every view,
    so neither always follows the other); medians of each renderer's frame and stages."""
    from prt.runtime.interpolation import DEFAULT_TOLERANCE
    from prt.runtime.renderer import Renderer, Scene

    renderers = {"old": old_renderer.Renderer(old_renderer.Scene.load(), 512, 512, ctx=ctx, interpolate=DEFAULT_TOLERANCE),
                 "new": Renderer(Scene.load(), 512, 512, ctx=ctx, interpolate=DEFAULT_TOLERANCE)}  # fmt: skip
    start = renderers["new"].camera
    stages = {k: {} for k in renderers}
    for k in range(rounds):
        for i in range(-2, frames):  # two warm-up views per round
            camera = start.orbit(2 * np.pi * i / frames)
            for name in (("old", "new") if (i + k) % 2 == 0 else ("new", "old")):
                r = renderers[name]
                r.set_camera_object(camera if name == "new" else r.camera.__class__(camera.eye, camera.target, camera.up, camera.fov_y,
                                                                                       camera.near, camera.far))  # fmt: skip
                r.render()
                if i >= 0:
                    for stage, ms in r.timings.items():
                        stages[name].setdefault(stage, []).append(ms)
        print(f"  demo round {k + 1}: " + ", ".join(f"{n} {np.median(v['frame'][-frames:]):.1f}" for n, v in stages.items()) + " ms/frame", flush=True)
    for r in renderers.values():
        r.close()
    med = {n: {stage: round(float(np.median(v)), 3) for stage, v in st.items()} for n, st in stages.items()}
    per_round = {n: [float(np.median(st["frame"][j * frames : (j + 1) * frames])) for j in range(rounds)] for n, st in stages.items()}
    ratios = [a / b for a, b in zip(per_round["new"], per_round["old"])]
    return {"frame_ms": {n: m["frame"] for n, m in med.items()}, "stages_ms": med, "rounds_ms": per_round,
            "new_over_old": round(med["new"]["frame"] / med["old"]["frame"], 3),
            "round_ratio_spread": round(max(ratios) - min(ratios), 3)}  # fmt: skip


def markdown(figures: dict) -> str:
    m = figures["machine"]
    lines = [
        f"# GLSL one-pass transfer against the branch point ({figures['old_commit']}), one run",
        "",
        f"{m['renderer']}; {m['cpu']}; other processes' share of the cores during the run: {m['other_cpu_share']}. "
        f"GLSL frames at {figures['size']}x{figures['size']}, {figures['views']} orbit views each, medians of `Renderer.render()` "
        "(pixels read back), old / new / new held to two draws in turn.",
        "",
        "| scene | width | old ms | new ms (one pass) | new, two draws ms | old / new | new vs old dB | new vs ONNX dB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, row in figures["scenes"].items():
        f, p = row["frame_ms"], {k: "identical" if v is None else v for k, v in row["psnr_db"].items()}
        lines.append(f"| {key} | {row['transfer_width']} | {f['old']:.1f} | {f['new']:.1f} | {f['new_two_draws']:.1f} | "
                     f"{row['speedup_vs_old']:.2f}x | {p['new_vs_old']} | {p['new_vs_onnx']} |")  # fmt: skip
    t = figures["targets"]
    lines += ["", "| target | measured | met |", "|---|---|---|"]
    for name, row in t.items():
        lines.append(f"| {name} | {row['measured']} | {'yes' if row['met'] else 'no'} |")
    d = figures.get("demo")
    if d:
        stages = lambda n: ", ".join(f"{k} {v:.2f}" for k, v in d["stages_ms"][n].items() if k != "frame")  # noqa: E731
        lines += ["", f"Demo (`make demo`'s frames: ONNX backend, 512x512, interpolation on), old and new alternating frame by frame, "
                  f"{figures['demo_frames']} views x {figures['demo_rounds']} rounds: old {d['frame_ms']['old']:.2f} ms/frame "
                  f"({stages('old')}), new {d['frame_ms']['new']:.2f} ms/frame ({stages('new')}); new / old {d['new_over_old']:.3f}."]  # fmt: skip
    lines += ["", f"Command: `{figures['provenance']['command']}`; commit {figures['provenance']['commit']}, "
              f"{figures['provenance']['date']}."]  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bounce", type=Path, required=True, help="a default build with bounces (scene.json)")
    p.add_argument("--held-out-16", type=Path, required=True, help="the held-out mesh built without bounces")
    p.add_argument("--held-out-64", type=Path, required=True, help="the same mesh, same network size, with bounces")
    p.add_argument("--old-commit", default="3313a73", help="the code measured as 'today' (default: the branch point)")
    p.add_argument("--old", type=Path, default=None, help="that code already extracted (instead of git archive)")
    p.add_argument("--size", type=int, default=160)
    p.add_argument("--views", type=int, default=6)
    p.add_argument("--demo-frames", type=int, default=30)
    p.add_argument("--demo-rounds", type=int, default=3)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    busy, t0 = busy_seconds(), time.perf_counter()
    ctx = create_context()
    with tempfile.TemporaryDirectory() as tmp:
        old_renderer = old_package(args.old_commit, args.old, Path(tmp))
        scenes = {}
        for key, path in (("bounce", args.bounce), ("held_out_16", args.held_out_16), ("held_out_64", args.held_out_64)):
            scenes[key] = glsl_frames(path, old_renderer, args.size, args.views, ctx)
        demo = demo_frames(old_renderer, args.demo_frames, args.demo_rounds, ctx) if args.demo_rounds else None
    held = {k: scenes["held_out_64"]["frame_ms"][k] / scenes["held_out_16"]["frame_ms"][k] for k in ("old", "new")}
    targets = {
        "bounce build: old / new >= 1.8": {"measured": scenes["bounce"]["speedup_vs_old"], "met": bool(scenes["bounce"]["speedup_vs_old"] >= 1.8)},
        "bounce build: new vs ONNX >= 60 dB": {"measured": scenes["bounce"]["psnr_db"]["new_vs_onnx"],
                                                "met": bool((scenes["bounce"]["psnr_db"]["new_vs_onnx"] or np.inf) >= 60)},
        "held-out: 64-wide / 16-wide <= 1.4 (new)": {"measured": round(held["new"], 3), "met": bool(held["new"] <= 1.4)},
        "held-out: 64-wide / 16-wide (old, for reference)": {"measured": round(held["old"], 3), "met": None},
    }  # fmt: skip
    if demo:
        noise = demo["round_ratio_spread"]  # how much the ratio moved between rounds: what a difference must exceed
        targets[f"demo frame: new / old <= 1 within the rounds' spread of the ratio ({noise:.3f})"] = {
            "measured": demo["new_over_old"], "met": bool(demo["new_over_old"] <= 1 + noise)}
    machine = {"renderer": context_info(ctx)["renderer"], "cpu": cpu_label(), "other_cpu_share": other_cpu_share(busy, time.perf_counter() - t0)}
    ctx.release()
    figures = {
        "provenance": provenance(), "renderer": machine["renderer"], "machine": machine, "old_commit": args.old_commit,
        "size": args.size, "views": args.views, "demo_frames": args.demo_frames, "demo_rounds": args.demo_rounds,
        "scenes": scenes, "held_out_ratio": {k: round(v, 3) for k, v in held.items()}, "demo": demo, "targets": targets,
    }  # fmt: skip
    text = markdown(figures)
    print(text)
    if args.json:
        atomic_write_json(args.json, figures)
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
