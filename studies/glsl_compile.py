"""Compile + first-frame time of a whole scene's GLSL on llvmpipe: per-segment GLSL against the compact form.

usage: python studies/glsl_compile.py NAME=SCENE.json [...] [--work DIR] [--size 256]
           [--timeout 300] [--forms per-segment compact] [--json OUT.json] [--md OUT.md]

Per scene and form, the scene folder is copied to ``WORK/NAME-FORM`` and its segment GLSL rewritten
from the ONNX files (:func:`prt.export.glsl_compact.rewrite_scene_glsl`): ``per-segment`` is what
the export wrote before the compact form (a function per segment: const ``mat4``s up to 1536
blocks, else a weight texture; a grid's :func:`prt.export.grid_onnx.glsl_function`), ``compact``
one function per architecture reading every segment's texels from one texture.  A fresh process
(Mesa's shader cache off: ``MESA_SHADER_CACHE_DISABLE=true``) then times, with the ``glsl``
backend at SIZE x SIZE:

- ``build_s``: ``Renderer(...)`` (G-buffer programs and the transfer program: compile + link);
- ``first_frame_s``: the first ``render()`` (llvmpipe generates the machine code at the first
  draw, then the pass runs);
- ``next_frame_s``: a ``render()`` after the camera moved (the transfer pass again, compiled);
- ``psnr_vs_onnx``: the glsl frame against the onnx backend's (same view);
- the program's size (``source_chars``), its network functions, the 1-minute load average.

A measurement still running after ``--timeout`` seconds is stopped and reported as ``> T s``.

``--ladder`` adds a synthetic scene with one segment of every architecture the build's right-sizing
may pick (the 7 frequency sizes of ``BuildSpec().architectures()``; with ``--ladder-grid`` also the 4
grid sizes), random weights, in the compact form: the program then holds one function per
architecture, the case where the compact form's size is largest.  Timed as above, but on SIZE x SIZE
random points of the box (segment = pixel index mod segments, so every function runs) through the
backend's program directly (``build_s``: the backend, ``first_frame_s``: the first draw,
``next_frame_s``: a second one).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path


def measure(scene_path: str, size: int) -> dict:
    """One scene in this process (the child): the timings described above."""
    import numpy as np

    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(scene_path)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    with Renderer(scene, size, size, backend="glsl") as r:
        t1 = time.perf_counter()
        image = r.render()
        t2 = time.perf_counter()
        backend = r._backend()
        r.set_camera(eye=(2.2, 1.2, 2.0))
        t3 = time.perf_counter()
        r.render()
        t4 = time.perf_counter()
        chars, compile_s = getattr(backend, "source_chars", None), getattr(backend, "compile_s", None)
        functions = len(backend.functions)
    with Renderer(scene, size, size, backend="onnx") as r:
        reference = r.render()
    mse = float(((image.astype(np.float64) - reference) ** 2).mean())
    psnr = float("inf") if mse == 0 else 10 * np.log10(float(reference.max()) ** 2 / mse)
    return {
        "build_s": t1 - t0, "compile_s": compile_s, "first_frame_s": t2 - t1, "build_and_first_frame_s": t2 - t0,
        "next_frame_s": t4 - t3, "psnr_vs_onnx": psnr, "source_chars": chars, "functions": functions,
        "load_1min": load, "segments": len(scene.manifest.segments),
    }  # fmt: skip


def ladder_files(folder: Path, grid: bool) -> list[dict]:
    """One random-weight segment per architecture of the right-sizing ladder: compact files."""
    from types import SimpleNamespace

    import numpy as np
    import torch

    from prt.export.glsl_compact import write_segment_glsl
    from prt.export.onnx_model import build_model, save_model
    from prt.train.build import BuildSpec, spec_from_dict
    from prt.train.networks.grid_encoding import GridTransfer
    from prt.train.networks.network import TransferMLP

    folder.mkdir(parents=True, exist_ok=True)
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    segments = []
    archs = list(BuildSpec(geometry="x", bounces=0).architectures()) + (list(spec_from_dict({"geometry": "x", "encoding": "grid", "bounces": 0}).architectures()) if grid else [])
    for i, arch in enumerate(archs):
        scale, shift = rng.uniform(0.1, 0.5, 16).astype(np.float32), rng.uniform(-0.1, 0.1, 16).astype(np.float32)
        info = SimpleNamespace(id=i, model=folder / f"seg{i:03d}.onnx", architecture=None, glsl=None, glsl_weights=None)
        if type(arch).__name__ == "GridArchitecture":
            m = GridTransfer(arch, box, scale, shift)
            with torch.no_grad():
                m.table.normal_()
            write_segment_glsl(info, "auto", grid_arrays=m.eval().arrays())
        else:
            save_model(build_model(TransferMLP(arch, box, scale, shift).arrays(), arch.as_dict()), info.model)
            write_segment_glsl(info, "auto")
        segments.append({"id": i, "glsl": str(info.glsl), "weights": str(info.glsl_weights), "label": arch.label() if hasattr(arch, "label") else str(arch)})
    (folder / "ladder.json").write_text(json.dumps(segments, indent=1))
    return segments


def measure_ladder(folder: str, size: int) -> dict:
    """The ladder's program: build, first and second draw over random points (see the docstring)."""
    from types import SimpleNamespace

    import numpy as np

    from prt.runtime.backends.glsl import GlslBackend
    from prt.runtime.gl import create_context, run_fragment_program

    items = json.loads((Path(folder) / "ladder.json").read_text())
    segments = [SimpleNamespace(id=s["id"], kind="network", glsl=Path(s["glsl"]), glsl_weights=Path(s["weights"]), encoding=None) for s in items]
    manifest = SimpleNamespace(path=Path(folder) / "scene.json", segments=segments, transfer_width=16)
    ctx = create_context()
    rng = np.random.default_rng(1)
    n = size * size
    position = np.concatenate([rng.uniform(-1, 1, (n, 3)), np.ones((n, 1))], axis=1).astype(np.float32)
    normal = np.concatenate([rng.normal(size=(n, 3)), (np.arange(n) % len(segments))[:, None]], axis=1).astype(np.float32)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    backend = GlslBackend(ctx, manifest)
    t1 = time.perf_counter()
    textures = {"prt_weights": backend._textures[0][0]}
    draw = lambda: run_fragment_program(ctx, backend.program, {"u_position": position, "u_normal": normal}, 16, attachments=4, textures=textures)  # noqa: E731
    out = draw()
    t2 = time.perf_counter()
    draw()
    t3 = time.perf_counter()
    return {"build_s": t1 - t0, "compile_s": backend.compile_s, "first_frame_s": t2 - t1, "build_and_first_frame_s": t2 - t0,
            "next_frame_s": t3 - t2, "finite": bool(np.isfinite(out).all()), "source_chars": backend.source_chars,
            "functions": len(backend.functions), "load_1min": load, "segments": len(segments)}  # fmt: skip


def run_one(scene: Path, size: int, timeout: float, ladder: bool = False) -> dict:
    env = dict(os.environ, MESA_SHADER_CACHE_DISABLE="true")
    load = os.getloadavg()[0]
    cmd = [sys.executable, __file__, "--measure-ladder" if ladder else "--measure", str(scene), "--size", str(size)]
    start = time.perf_counter()
    try:
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"timed_out": True, "timeout_s": timeout, "load_1min": load, "wall_s": time.perf_counter() - start}
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["?"])[-1], "load_1min": load}
    return json.loads(done.stdout.strip().splitlines()[-1])


def prepare(scene: Path, work: Path, name: str, form: str) -> Path:
    from prt.export.glsl_compact import rewrite_scene_glsl

    folder = work / f"{name}-{form}"
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(scene.parent, folder)
    rewrite_scene_glsl(folder / scene.name, form)
    return folder / scene.name


def _seconds(r: dict, key: str) -> str:
    if r.get("timed_out"):
        return f"> {r['timeout_s']:.0f} s"
    return "error" if "error" in r else f"{r[key]:.1f} s"


def markdown(results: list[dict]) -> str:
    lines = ["| scene | form | build + first frame | first frame | next frame | program chars | functions | PSNR vs ONNX | load |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in results:
        m = r["result"]
        psnr = f"{m['psnr_vs_onnx']:.1f} dB" if "psnr_vs_onnx" in m else ("- (finite)" if m.get("finite") else "-")
        chars = f"{m['source_chars']:,}" if m.get("source_chars") else "-"
        lines.append(f"| {r['scene']} | {r['form']} | {_seconds(m, 'build_and_first_frame_s')} | {_seconds(m, 'first_frame_s')} | "
                     f"{_seconds(m, 'next_frame_s')} | {chars} | {m.get('functions', '-')} | {psnr} | {m['load_1min']:.1f} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def _write(path, args, results) -> None:
    if path:
        path.write_text(json.dumps({"size": args.size, "timeout_s": args.timeout, "results": results}, indent=1) + "\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scenes", nargs="*", help="NAME=path/to/scene.json")
    p.add_argument("--work", type=Path, default=Path("/tmp/glsl_compile"))
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--timeout", type=float, default=300.0)
    p.add_argument("--forms", nargs="+", default=["per-segment", "compact"])
    p.add_argument("--json", type=Path)
    p.add_argument("--md", type=Path)
    p.add_argument("--ladder", action="store_true", help="add the synthetic scene of every right-sizing architecture")
    p.add_argument("--ladder-grid", action="store_true", help="with --ladder: the grid ladder's 4 sizes too")
    p.add_argument("--measure", help=argparse.SUPPRESS)
    p.add_argument("--measure-ladder", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.measure or args.measure_ladder:
        print(json.dumps(measure(args.measure, args.size) if args.measure else measure_ladder(args.measure_ladder, args.size)))
        return 0
    results = []
    if args.ladder:
        name = "ladder+grid" if args.ladder_grid else "ladder"
        folder = args.work / name
        segments = ladder_files(folder, args.ladder_grid)
        result = run_one(folder, args.size, args.timeout, ladder=True)
        results.append({"scene": name, "form": "compact", "source": [s["label"] for s in segments], "result": result})
        print(f"{name} compact: {json.dumps(result)}", flush=True)
        _write(args.json, args, results)
    for item in args.scenes:
        name, _, path = item.partition("=")
        for form in args.forms:
            scene = prepare(Path(path), args.work, name, form)
            result = run_one(scene, args.size, args.timeout)
            results.append({"scene": name, "form": form, "source": path, "result": result})
            print(f"{name} {form}: {json.dumps(result)}", flush=True)
            _write(args.json, args, results)
    table = markdown(results)
    print(table)
    if args.md:
        args.md.write_text(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
