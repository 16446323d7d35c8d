"""``make demo``'s frame rate as its command renders it: the orbit's frames written after rendering
(held in memory, :data:`prt.runtime.orbit.HOLD_BYTES`) against each written between two renders,
with interpolation (the default tolerance) and every pixel, as ratios in one run.

usage: python studies/demo_fps.py [--scene scene.json] [--size 512] [--frames 30] [--rounds 3]
                                        [--json OUT] [--md OUT]

Six configurations take turns, round after round, each a whole :func:`render_orbit` of
``--frames`` PNG frames into a temporary folder (``make demo``'s call): tolerance 0.1 or 0 (every
covered pixel runs its network), frames held or written one by one (``HOLD_BYTES`` = 1, what
``prt-runtime --headless`` did before), the default with the G-buffer's reference twin (every
fragment descends the k-d tree, :attr:`GBufferPass.known_segments` off: the pass before issue 44),
and the default with the background's pass drawn when the frame is assembled
(``Renderer.background_with_gbuffer`` off: the frame before its pass joined the G-buffer's).
Reported per configuration: the median over rounds of
the orbit's median frame time, FPS, stage times, the share of the frame outside the network
(everything but ``inference``) and seconds spent writing.  Then the PNG
encoding of one frame at zlib levels 1 (``PNG_LEVEL``) and 6 (Pillow's default): milliseconds
(median of 5) and bytes.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

import prt.runtime.orbit as orbit
from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes
from prt.runtime.gl import create_context
from prt.runtime.interpolation import DEFAULT_TOLERANCE
from prt.runtime.renderer import Renderer, Scene


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=None, help="scene.json (default: the bundled demo)")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    scene = Scene.load(args.scene)
    ctx = create_context()
    load_start, wall_start = busy_seconds(), time.perf_counter()
    configs = [(tol, hold, True, True) for tol in (DEFAULT_TOLERANCE, None) for hold in ("held", "each")]
    configs.append((DEFAULT_TOLERANCE, "held", False, True))  # the G-buffer's reference twin
    configs.append((DEFAULT_TOLERANCE, "held", True, False))  # the background's pass when the frame is assembled
    renderers = {tol: Renderer(scene, args.size, args.size, ctx=ctx, interpolate=tol) for tol in (DEFAULT_TOLERANCE, None)}
    runs: dict[str, list[dict]] = {}
    default_hold = orbit.HOLD_BYTES
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rounds):
            for tol, hold, known, early in configs:
                name = (f"interpolate {tol or 0} / {hold}" + ("" if known else " / G-buffer twin (per-fragment segments)")
                        + ("" if early else " / background drawn at assembly"))  # fmt: skip
                orbit.HOLD_BYTES = default_hold if hold == "held" else 1
                gbuffer = renderers[tol].gbuffer
                before = gbuffer.known_segments
                gbuffer.known_segments = known and before
                renderers[tol].background_with_gbuffer = early
                try:
                    s = orbit.render_orbit(renderers[tol], args.frames, Path(tmp) / f"{k}-{tol}-{hold}-{known}-{early}")
                finally:
                    orbit.HOLD_BYTES = default_hold
                    gbuffer.known_segments = before
                    renderers[tol].background_with_gbuffer = True
                runs.setdefault(name, []).append({"median_ms": s.median_ms, "write_s": s.write_s})
                print(f"round {k + 1}: {name}: {s.fps:.1f} FPS, wrote in {s.write_s:.2f} s", flush=True)
    png = {}
    image = renderers[DEFAULT_TOLERANCE].render_srgb()
    for level in (1, 6):
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            data = iio.imwrite("<bytes>", image, extension=".png", compress_level=level)
            times.append(1e3 * (time.perf_counter() - t0))
        png[level] = {"ms": float(np.median(times)), "bytes": len(data)}
    for r in renderers.values():
        r.close()
    rows = {}
    for name, rs in runs.items():
        stages = {st: float(np.median([r["median_ms"][st] for r in rs])) for st in rs[0]["median_ms"]}
        outside = float(np.median([1.0 - r["median_ms"].get("inference", 0.0) / r["median_ms"]["frame"] for r in rs]))
        rows[name] = {"frame_ms": stages["frame"], "fps": 1000.0 / stages["frame"], "stages_ms": stages, "outside_share": outside,
                      "write_s": float(np.median([r["write_s"] for r in rs])), "rounds": rs}  # fmt: skip
    base = rows[f"interpolate {DEFAULT_TOLERANCE} / held"]["frame_ms"]
    lines = [f"Demo frame rate, {args.size}x{args.size}, {args.frames} frames x {args.rounds} rounds (medians)", "",
             "| configuration | FPS | ms/frame | vs default | outside the network | write s | stages (ms) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, row in rows.items():
        st = ", ".join(f"{k} {v:.1f}" for k, v in row["stages_ms"].items() if k != "frame")
        lines.append(f"| {name} | {row['fps']:.1f} | {row['frame_ms']:.1f} | {row['frame_ms'] / base:.2f}x | {100 * row['outside_share']:.0f} % | {row['write_s']:.2f} | {st} |")
    default = rows[f"interpolate {DEFAULT_TOLERANCE} / held"]
    lines += ["", f"Targets (issue 44), the default: >= 30 FPS: {'met' if default['fps'] >= 30 else 'missed'} ({default['fps']:.1f}); "
              f"the stages outside the network <= 40 % of the frame: {'met' if default['outside_share'] <= 0.4 else 'missed'} "
              f"({100 * default['outside_share']:.0f} %)"]  # fmt: skip
    lines += ["", "PNG of one frame: " + ", ".join(f"zlib level {k}: {v['ms']:.1f} ms, {v['bytes']} bytes" for k, v in png.items())]
    text = "\n".join(lines)
    load = other_cpu_share(load_start, time.perf_counter() - wall_start)
    text += f"\n\nOther processes' share of the CPUs during the run: {load}"
    print(text)
    if args.json:
        record = {"provenance": provenance(gl_renderer=ctx.info.get("GL_RENDERER"), other_cpu_share=load),
                  "size": args.size, "frames": args.frames, "rows": rows, "png": png}  # fmt: skip
        atomic_write_bytes(args.json, json.dumps(record, indent=1).encode())
    if args.md:
        atomic_write_bytes(args.md, (text + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
