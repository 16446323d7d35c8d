"""Many segments, one cost: the frame time of a scene with ~512 segments against the same mesh with 8,
every network of one architecture, on the ONNX backend (one session per segment, the reference
path, beside the stacked models of :mod:`prt.runtime.onnx_stack`) and the GLSL backend.

usage: python studies/many_segments_bench.py SCENE8 SCENE512 [--size 512] [--glsl-size 512]
                                             [--rounds 5] [--frames 4] [--json OUT] [--md OUT]

The two scenes are built from one mesh with ``prt-train MESH --segments 8|512 --hidden 32 --layers 2
--no-analytic --residual on ...`` (see ``docs/benchmarks/many_segments.md`` for the commands used).
One process renders both scenes; round after round, each configuration (onnx per-segment, onnx
stacked, glsl) renders ``--frames`` frames of each scene in turn (the order reversed every other
round), the camera moving a little every frame (so every frame runs the networks), the first frame
after a switch not timed.  Reported: the median frame time per configuration and scene, the ratio
512 / 8 (of the medians, and the median of each round's ratio), the stages; then the inference stage
alone on one frame's rows of each scene, per-segment and stacked, ratios taken within a round.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes
from prt.runtime.gl import create_context
from prt.runtime.renderer import Renderer, Scene

CONFIGS = ("onnx per-segment", "onnx stacked", "glsl")


def _orbit(renderer: Renderer, k: int) -> None:
    """A camera a little along the scene's orbit: a new view each frame (the transfer is recomputed)."""
    cam = renderer.scene.manifest.camera
    eye, target = np.asarray(cam.eye, float), np.asarray(cam.target, float)
    a = 0.02 * k
    d = eye - target
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    renderer.set_camera(eye=(target + rot @ d).tolist(), target=target.tolist(), up=np.asarray(cam.up, float).tolist(), fov=float(cam.fov))


def _frames(renderer: Renderer, frames: int, counter: list[int]) -> list[dict]:
    out = []
    for i in range(frames + 1):
        counter[0] += 1
        _orbit(renderer, counter[0])
        t0 = time.perf_counter()
        renderer.render()
        ms = 1e3 * (time.perf_counter() - t0)
        if i:  # the first frame after a switch is not timed
            out.append({"wall": ms, **renderer.timings})
    return out


def _inference_pairs(renderers, engines, pairs: int) -> dict:
    """The inference stage alone on one frame's rows of each scene (captured from the renderer): each
    round calls the four (scene, path) pairs in turn (in reverse every other round) -- per-segment sessions and stacked models, 8 and
    ~512 segments -- and the ratios are taken within a round (medians over ``pairs`` rounds), steadier
    than frames on a busy machine."""
    rows = []
    for j, engine in enumerate(engines):
        captured = {}
        run = engine.infer_sorted
        engine.infer_sorted = lambda x, offsets: captured.update(x=x.copy(), offsets=np.asarray(offsets).copy()) or run(x, offsets)
        try:
            _frames(renderers[("onnx", j)], 1, [1000])
        finally:
            del engine.infer_sorted
        rows.append((captured["x"], captured["offsets"]))
    times = {(j, b): [] for j in range(2) for b in (False, True)}
    for k in range(pairs):
        for (j, batched), out in list(times.items())[:: 1 if k % 2 else -1]:  # the order reversed every other round (caches)
            engines[j].batched = batched
            t0 = time.perf_counter()
            engines[j].infer_sorted(*rows[j])
            out.append(1e3 * (time.perf_counter() - t0))
    t = {k: np.array(v) for k, v in times.items()}
    scenes = []
    for j, (x, offsets) in enumerate(rows):
        counts = np.diff(offsets)
        scenes.append({"segments": engines[j].segment_count, "rows": int(len(x)), "segments_with_rows": int((counts > 0).sum()),
                       "per_segment_ms": float(np.median(t[j, False])), "stacked_ms": float(np.median(t[j, True])),
                       "stacked_over_per_segment": float(np.median(t[j, True] / t[j, False]))})  # fmt: skip
    return {"pairs": pairs, "scenes": scenes, "ratio_per_segment": float(np.median(t[1, False] / t[0, False])),
            "ratio_stacked": float(np.median(t[1, True] / t[0, True])),
            "stacked_512_over_per_segment_8": float(np.median(t[1, True] / t[0, False]))}  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs=2, type=Path, help="the 8-segment scene.json, then the ~512-segment one")
    p.add_argument("--size", type=int, default=512, help="ONNX frames' size [512]")
    p.add_argument("--glsl-size", type=int, default=512, help="GLSL frames' size [512]")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--frames", type=int, default=4)
    p.add_argument("--glsl-frames", type=int, default=2)
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=CONFIGS)
    p.add_argument("--pairs", type=int, default=20, help="inference-only pairs (per-segment, stacked) per scene [20]")
    p.add_argument("--block-rows", type=int, default=None, help="rows per block of the stacked models [the engine's default]")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    ctx = create_context()
    scenes = [Scene.load(s) for s in args.scenes]
    counts = [len(s.manifest.segments) for s in scenes]
    renderers = {}
    load_s = {}
    for j, scene in enumerate(scenes):
        t0 = time.perf_counter()
        r = Renderer(scene, args.size, args.size, "onnx", ctx=ctx)
        r.render()
        load_s[f"onnx {counts[j]}"] = time.perf_counter() - t0
        renderers[("onnx", j)] = r
        if "glsl" in args.configs:
            t0 = time.perf_counter()
            g = Renderer(scene, args.glsl_size, args.glsl_size, "glsl", ctx=ctx)
            g.render()
            load_s[f"glsl {counts[j]}"] = time.perf_counter() - t0
            renderers[("glsl", j)] = g
    engines = [renderers[("onnx", j)]._backends["onnx"].engine for j in range(2)]
    stacks = [[len(s.segments) for s in e.stacks] for e in engines]
    for e in engines:
        e.block_rows = args.block_rows or e.block_rows
    load_start, wall_start = busy_seconds(), time.perf_counter()
    runs: dict[str, list[list[dict]]] = {c: [[], []] for c in args.configs}
    counter = [0]
    for k in range(args.rounds):
        for config in args.configs[:: 1 if k % 2 else -1]:  # the order reversed every other round
            for j in range(2)[:: 1 if k % 2 else -1]:
                if config == "glsl":
                    frames = _frames(renderers[("glsl", j)], args.glsl_frames, counter)
                else:
                    engines[j].batched = config == "onnx stacked"
                    frames = _frames(renderers[("onnx", j)], args.frames, counter)
                runs[config][j] += [{**f, "round": k} for f in frames]
        print(f"round {k + 1}: " + ", ".join(f"{c} {np.median([f['wall'] for f in runs[c][0]]):.1f} / "
                                             f"{np.median([f['wall'] for f in runs[c][1]]):.1f} ms" for c in args.configs), flush=True)  # fmt: skip
    inference = _inference_pairs(renderers, engines, args.pairs)
    load = other_cpu_share(load_start, time.perf_counter() - wall_start)
    for r in renderers.values():
        r.close()
    rows = {}
    for config in args.configs:
        per = []
        for j in range(2):
            frames = runs[config][j]
            stages = {st: float(np.median([f[st] for f in frames if st in f])) for st in frames[0] if st != "round"}
            per.append({"segments": counts[j], "frame_ms": stages["wall"], "stages_ms": stages, "frames": len(frames)})
        size = args.glsl_size if config == "glsl" else args.size
        by_round = [np.median([f["wall"] for f in runs[config][1] if f["round"] == k]) / np.median([f["wall"] for f in runs[config][0] if f["round"] == k])
                    for k in range(args.rounds)]  # fmt: skip
        rows[config] = {"size": size, "scenes": per, "ratio": per[1]["frame_ms"] / per[0]["frame_ms"], "ratio_within_rounds": float(np.median(by_round))}
    lines = [f"| configuration | size | {counts[0]} segments (ms) | {counts[1]} segments (ms) | ratio (of medians) | ratio (within rounds) | stages at {counts[0]} (ms) | stages at {counts[1]} (ms) |",
             "|---|---:|---:|---:|---:|---:|---|---|"]  # fmt: skip
    for config, row in rows.items():
        st = [", ".join(f"{k} {v:.1f}" for k, v in row["scenes"][j]["stages_ms"].items() if k not in ("wall", "frame")) for j in range(2)]
        lines.append(f"| {config} | {row['size']} | {row['scenes'][0]['frame_ms']:.1f} | {row['scenes'][1]['frame_ms']:.1f} | "
                     f"{row['ratio']:.2f} | {row['ratio_within_rounds']:.2f} | {st[0]} | {st[1]} |")  # fmt: skip
    lines += ["", f"Inference stage alone, one frame's rows, the four (scene, path) pairs called in turn, {args.pairs} rounds (medians):", "",
              "| segments | rows (segments with rows) | per-segment ms | stacked ms | stacked / per-segment |", "|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['segments']} | {r['rows']} ({r['segments_with_rows']}) | {r['per_segment_ms']:.1f} | {r['stacked_ms']:.1f} | "
              f"{r['stacked_over_per_segment']:.2f} |" for r in inference["scenes"]]  # fmt: skip
    lines += ["", f"Inference at {counts[1]} / at {counts[0]} segments (ratios within a round): per-segment {inference['ratio_per_segment']:.2f}, "
              f"stacked {inference['ratio_stacked']:.2f}; stacked at {counts[1]} / per-segment at {counts[0]}: "
              f"{inference['stacked_512_over_per_segment_8']:.2f}"]  # fmt: skip
    lines += ["", f"Stacked models (segments each): {stacks[0]} / {stacks[1]}; first frame incl. load (s): "
              + ", ".join(f"{k} {v:.2f}" for k, v in load_s.items()), f"Other processes' share of the CPUs during the run: {load}"]  # fmt: skip
    text = "\n".join(lines)
    print(text)
    if args.json:
        record = {"provenance": provenance(gl_renderer=ctx.info.get("GL_RENDERER"), other_cpu_share=load),
                  "scenes": [str(s) for s in args.scenes], "rounds": args.rounds, "frames": args.frames,
                  "glsl_frames": args.glsl_frames, "stacks": stacks, "block_rows": engines[0].block_rows, "first_frame_s": load_s, "rows": rows, "inference": inference}  # fmt: skip
        atomic_write_bytes(args.json, json.dumps(record, indent=1).encode())
    if args.md:
        atomic_write_bytes(args.md, (text + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
