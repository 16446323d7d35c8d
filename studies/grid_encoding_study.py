"""Multiresolution feature grids (``prt.train.networks.grid_encoding``) against the paper's frequency MLP,
per segment of existing precomputed samples (issue 12, item 2a).

Every variant is fitted on the same segments at the same steps, batch and learning rate (the
frequency MLPs by :func:`prt.train.networks.fit.fit_segment`, the grids by
:func:`prt.train.networks.grid_encoding.fit_grid_segment`, same loss, schedule and early stop) and
reports validation MAE, the shaded relative MAE under the bundled env maps (as fit_segment
reports it) and its dB figure ``-20 log10(mean relative MAE)`` (the same for all), FLOPs per
fragment, bytes and training seconds; the Pareto fronts of dB against FLOPs and against bytes
are taken over the variants' means across all measured segments.

    nice -n 10 .venv/bin/python studies/grid_encoding_study.py \\
        --data spot=/tmp/i12/spotA/precompute:0,3 --data demo=/tmp/prt-demo-build/precompute:0 \\
        --json docs/benchmarks/grid_encoding.json --md docs/benchmarks/grid_encoding.md

Results are appended to the JSON after each fit (a rerun skips what it holds); ``--report``
rewrites the Markdown from the JSON alone.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

VARIANTS = {  # name -> ("freq", Architecture kwargs) or ("grid", GridArchitecture kwargs)
    "freq-k64-l4": ("freq", {"hidden": 64, "layers": 4, "pos_freqs": 6}),
    "freq-k64-l3": ("freq", {"hidden": 64, "layers": 3, "pos_freqs": 6}),
    "freq-k32-l2": ("freq", {"hidden": 32, "layers": 2, "pos_freqs": 5}),
    "grid-L8-F2-T14-k32-l2": ("grid", {"levels": 8, "features": 2, "log2_table": 14, "base_resolution": 4, "max_resolution": 128, "hidden": 32, "layers": 2}),
    "grid-L8-F2-T12-k32-l2": ("grid", {"levels": 8, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 128, "hidden": 32, "layers": 2}),
    "grid-L8-F2-T14-k16-l1": ("grid", {"levels": 8, "features": 2, "log2_table": 14, "base_resolution": 4, "max_resolution": 128, "hidden": 16, "layers": 1}),
    "grid-L4-F4-T12-k32-l2": ("grid", {"levels": 4, "features": 4, "log2_table": 12, "base_resolution": 4, "max_resolution": 32, "hidden": 32, "layers": 2}),
    "grid-L12-F2-T16-k32-l2": ("grid", {"levels": 12, "features": 2, "log2_table": 16, "base_resolution": 4, "max_resolution": 256, "hidden": 32, "layers": 2}),
    "grid-L8-F2-T14-k32-l2-nf2": ("grid", {"levels": 8, "features": 2, "log2_table": 14, "base_resolution": 4, "max_resolution": 128, "hidden": 32, "layers": 2, "normal_freqs": 2}),
    "grid-L6-F2-T12-N4-32-k32-l2": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 32, "hidden": 32, "layers": 2}),
    "grid-L6-F2-T12-N4-64-k32-l2": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 64, "hidden": 32, "layers": 2}),
    "grid-L8-F4-T12-N4-64-k32-l2": ("grid", {"levels": 8, "features": 4, "log2_table": 12, "base_resolution": 4, "max_resolution": 64, "hidden": 32, "layers": 2}),
    "grid-L4-F4-T12-N8-32-k32-l2": ("grid", {"levels": 4, "features": 4, "log2_table": 12, "base_resolution": 8, "max_resolution": 32, "hidden": 32, "layers": 2}),
    "grid-L6-F2-T12-N4-32-k32-l2-nf2": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 32, "hidden": 32, "layers": 2, "normal_freqs": 2}),
    "grid-L6-F2-T12-N4-32-k64-l2": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 32, "hidden": 64, "layers": 2}),
    "grid-L6-F2-T12-N4-32-k16-l1": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 32, "hidden": 16, "layers": 1}),
    "grid-L4-F2-T12-N2-16-k32-l2": ("grid", {"levels": 4, "features": 2, "log2_table": 12, "base_resolution": 2, "max_resolution": 16, "hidden": 32, "layers": 2}),
    "grid-L6-F2-T12-N4-64-k64-l2": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 64, "hidden": 64, "layers": 2}),
    "grid-L4-F2-T12-N2-16-k64-l2": ("grid", {"levels": 4, "features": 2, "log2_table": 12, "base_resolution": 2, "max_resolution": 16, "hidden": 64, "layers": 2}),
    "grid-L6-F2-T12-N4-32-k64-l3": ("grid", {"levels": 6, "features": 2, "log2_table": 12, "base_resolution": 4, "max_resolution": 32, "hidden": 64, "layers": 3}),
}
DEFAULT_VARIANTS = [  # measured in this order (the frequency MLPs first)
    "freq-k64-l4", "freq-k64-l3", "freq-k32-l2",
    "grid-L6-F2-T12-N4-32-k64-l2", "grid-L6-F2-T12-N4-32-k32-l2", "grid-L8-F2-T12-k32-l2", "grid-L4-F2-T12-N2-16-k32-l2",
    "grid-L6-F2-T12-N4-64-k64-l2", "grid-L4-F2-T12-N2-16-k64-l2", "grid-L6-F2-T12-N4-32-k64-l3", "grid-L6-F2-T12-N4-32-k16-l1",
]  # fmt: skip


def shaded_db(relative_mae: float) -> float:
    """The PSNR-like figure of a shaded relative MAE: ``-20 log10(rel MAE)`` (1 % -> 40 dB)."""
    return float(-20 * math.log10(max(relative_mae, 1e-12)))


def make_arch(name: str):
    from prt.train.networks.grid_encoding import GridArchitecture
    from prt.train.networks.network import Architecture

    kind, kw = VARIANTS[name]
    return Architecture(**kw) if kind == "freq" else GridArchitecture(**kw)


def arch_costs(arch) -> dict:
    if getattr(arch, "kind", "freq") == "grid":
        return {"flops": arch.flops_per_fragment(), "bytes": arch.bytes(2, 4), "bytes_fp32": arch.bytes(4, 4), "weights": arch.weight_count(),
                "flops_breakdown": arch.flops_breakdown(), "arch": arch.as_dict()}  # fmt: skip
    return {"flops": arch.flops_per_fragment(), "bytes": 4 * arch.weight_count(), "bytes_fp32": 4 * arch.weight_count(), "weights": arch.weight_count(),
            "arch": arch.as_dict()}  # fmt: skip


def segment_data(folder: Path, s: int):
    from prt.train.transport.precompute import load_precompute

    d = load_precompute(folder)
    samples, valid, members = d["samples"], d["validation"], d["members"]
    idx = members[s]
    v = np.flatnonzero(valid["segment"] == s)
    p, n, t = samples["points"][idx], samples["normals"][idx], samples["transfer"][idx]
    b = np.array([p.min(0), p.max(0)])
    b = b + np.array([[-1.0], [1.0]]) * 0.01 * np.maximum(b[1] - b[0], 1e-3)  # as train/build.py
    return p, n, t, valid["points"][v], valid["normals"][v], valid["transfer"][v], b


def glsl_check(arrays, points, normals, reference) -> dict:
    """The generated GLSL (``export.grid_onnx.glsl_function``) on llvmpipe against the reference:
    max abs difference, PSNR over the reference's peak, compile seconds."""
    from prt.export.grid_onnx import glsl_function, table_texture
    from prt.runtime.gl import create_context, run_fragment_program

    ctx = create_context()
    outputs = reference.shape[1]
    k = outputs // 4
    frag = "\n".join(["#version 330", "uniform sampler2D u_p;", "uniform sampler2D u_n;", glsl_function(arrays, "seg"),
                      *[f"layout(location = {j}) out vec4 o{j};" for j in range(k)],
                      "void main() {", "    ivec2 c = ivec2(gl_FragCoord.xy);", f"    vec4 t[{k}];",
                      "    seg(texelFetch(u_p, c, 0).xyz, texelFetch(u_n, c, 0).xyz, t);",
                      *[f"    o{j} = t[{j}];" for j in range(k)], "}"])  # fmt: skip
    texels, _ = table_texture(arrays)
    texture = ctx.texture((texels.shape[1], texels.shape[0]), 4, texels.tobytes(), dtype="f4")
    texture.filter = (0x2600, 0x2600)  # GL_NEAREST
    t0 = time.perf_counter()
    got = run_fragment_program(ctx, frag, {"u_p": points, "u_n": normals}, components=outputs, attachments=k, textures={"seg_table": texture})
    seconds = time.perf_counter() - t0
    texture.release()
    ctx.release()
    mse = float(np.mean((got - reference) ** 2))
    return {"max_abs_vs_reference": float(np.abs(got - reference).max()), "psnr_db": float(10 * np.log10(np.abs(reference).max() ** 2 / max(mse, 1e-30))),
            "compile_and_run_seconds": seconds}  # fmt: skip


def export_check(model, arch, data, folder: Path, name: str) -> dict:
    """Write the fitted network as ONNX (the grid: both table precisions; the frequency MLP: the
    project's exporter) and measure it: agreement with the reference evaluation on the held-out
    samples (and of the GLSL), ONNX Runtime's CPU time per fragment (1 thread, 262,144 fragments = 512 x 512)."""
    import onnxruntime as ort

    vp, vn = data[3], data[4]
    x = np.concatenate([vp, vn], axis=1).astype(np.float32)
    big = np.tile(x, (-(-262144 // len(x)), 1))[:262144]
    arrays = model.arrays()
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    if getattr(arch, "kind", "freq") == "grid":
        from prt.export.grid_onnx import build_grid_model, save_grid_model
        from prt.train.networks.grid_encoding import evaluate_numpy

        files = {dt: (build_grid_model(arrays, arch.as_dict(), table_dtype=dt), folder / f"{name}-{dt}.onnx") for dt in ("float32", "float16")}
        refs = {"float32": evaluate_numpy(arrays, vp, vn),
                "float16": evaluate_numpy({**arrays, "grid_table": arrays["grid_table"].astype(np.float16).astype(np.float32)}, vp, vn)}  # fmt: skip
    else:
        import torch

        from prt.export.onnx_model import build_model, save_model as save_grid_model

        files = {"float32": (build_model(arrays, arch.as_dict()), folder / f"{name}-float32.onnx")}
        with torch.no_grad():
            refs = {"float32": model(torch.from_numpy(x)).numpy()}
    if getattr(arch, "kind", "freq") == "grid":
        out["glsl"] = glsl_check(arrays, vp, vn, refs["float32"])
    for dt, (proto, path) in files.items():
        save_grid_model(proto, path)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        got = sess.run(None, {"x": x})[0]
        sess.run(None, {"x": big})
        t0 = time.process_time()
        sess.run(None, {"x": big})
        out[dt] = {"max_abs_vs_reference": float(np.abs(got - refs[dt]).max()), "file_bytes": path.stat().st_size,
                   "ort_cpu_ns_per_fragment": 1e9 * (time.process_time() - t0) / len(big)}  # fmt: skip
    return out


def measure_costs(names, fragments: int = 65536, steps: int = 8) -> dict:
    """Per variant, in CPU seconds of this process (``time.process_time``, 1 thread; wall time on a
    shared machine says little): one Adam step at batch 8192 (forward, backward, update) and ONNX
    Runtime's time per fragment of the exported graph (random weights: the time does not depend
    on them)."""
    import onnxruntime as ort
    import torch

    from prt.export.grid_onnx import build_grid_model
    from prt.export.onnx_model import build_model
    from prt.train.networks.grid_encoding import GridTransfer
    from prt.train.networks.network import TransferMLP

    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (fragments, 6)).astype(np.float32)
    xb = torch.from_numpy(x[:8192])
    box = np.array([[-1.0, -1, -1], [1, 1, 1]])
    out = {}
    for name in names:
        arch = make_arch(name)
        grid = VARIANTS[name][0] == "grid"
        model = (GridTransfer if grid else TransferMLP)(arch, box, np.full(16, 0.4, np.float32), np.zeros(16, np.float32))
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        for i in range(steps + 2):
            if i == 2:
                t0 = time.process_time()
            loss = model(xb).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        step = (time.process_time() - t0) / steps
        proto = build_grid_model(model.arrays(), arch.as_dict()) if grid else build_model(model.arrays(), arch.as_dict())
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        sess = ort.InferenceSession(proto.SerializeToString(), opts, providers=["CPUExecutionProvider"])
        sess.run(None, {"x": x})
        runs = []
        for _ in range(3):  # the best of three
            t0 = time.process_time()
            sess.run(None, {"x": x})
            runs.append(time.process_time() - t0)
        ort_ns = 1e9 * min(runs) / fragments
        out[name] = {"train_cpu_s_per_step": step, "ort_cpu_ns_per_fragment": ort_ns}
        print(f"{name:>30}: {1000 * step:.1f} ms CPU per step, ONNX Runtime {ort_ns:.0f} ns CPU per fragment", flush=True)
    return out


def fit_one(name: str, data, args, lights) -> dict:
    from prt.train.networks.fit import FitSettings, fit_segment, transfer_error
    from prt.train.networks.grid_encoding import evaluate_numpy, fit_grid_segment

    arch = make_arch(name)
    p, n, t, vp, vn, vt, bounds = data
    settings = FitSettings(steps=args.steps, batch=args.batch, lr=args.lr, patience=args.patience, seed=0)
    if VARIANTS[name][0] == "grid":
        r = fit_grid_segment(p, n, t, vp, vn, vt, arch, bounds, settings, lights=lights, table_lr_scale=args.table_lr_scale)
        arrays = r.model.arrays()
        exact = evaluate_numpy(arrays, vp, vn)
        half = evaluate_numpy({**arrays, "grid_table": arrays["grid_table"].astype(np.float16).astype(np.float32)}, vp, vn)
        extra = {"val_mae_numpy": transfer_error(exact, vt), "val_mae_fp16_tables": transfer_error(half, vt)}
    else:
        r = fit_segment(p, n, t, vp, vn, vt, arch, bounds, settings, lights=lights)
        extra = {}
    if args.export is not None:
        extra["onnx"] = export_check(r.model, arch, data, args.export, name)
    mean_rel = float(np.mean(list(r.shaded.values())))
    return {"variant": name, "kind": VARIANTS[name][0], "val_mae": r.val_mae, "shaded": r.shaded, "shaded_mean": mean_rel, "shaded_db": shaded_db(mean_rel),
            "seconds": r.seconds, "steps_run": r.steps, **arch_costs(arch), **extra}  # fmt: skip


def _rows(by_variant: dict, segs: list, costs: dict) -> list[dict]:
    """One row per variant: means over ``segs`` (each variant must have them all); Pareto flags."""
    from prt.bench.metrics import pareto_front

    rows = []
    for name, by_seg in by_variant.items():
        rs = [by_seg[k] for k in segs]
        mean_rel = float(np.mean([r["shaded_mean"] for r in rs]))
        fp16 = [r["val_mae_fp16_tables"] for r in rs if "val_mae_fp16_tables" in r]
        rows.append({"variant": name, "kind": rs[0]["kind"], "segments": len(rs), "val_mae": float(np.mean([r["val_mae"] for r in rs])),
                     "val_mae_fp16_tables": float(np.mean(fp16)) if fp16 else None, "shaded_mean": mean_rel, "shaded_db": shaded_db(mean_rel),
                     "flops": rs[0]["flops"], "bytes": rs[0]["bytes"], "seconds": float(np.mean([r["seconds"] for r in rs])),
                     **costs.get(name, {})})  # fmt: skip
    for key in ("flops", "bytes"):
        front = set(pareto_front([(-row[key], row["shaded_db"]) for row in rows]))
        for i, row in enumerate(rows):
            row[f"pareto_{key}"] = i in front
    return sorted(rows, key=lambda row: row["flops"])


def summarise(results: list[dict], costs: dict | None = None) -> dict:
    """``overall``: the variants measured on every segment, means over all segments; ``per_segment``:
    every variant measured on that segment.  Pareto fronts of dB against FLOPs and against bytes."""
    costs = costs or {}
    keys = {}
    for r in results:
        keys.setdefault(r["variant"], {})[f"{r['data']} {r['segment']}"] = r
    segments = sorted({k for v in keys.values() for k in v})
    full = {name: v for name, v in keys.items() if set(v) == set(segments)}
    out = {"segments": segments, "overall": _rows(full, segments, costs) if full else [], "per_segment": {}}
    for seg in segments:
        out["per_segment"][seg] = _rows({name: v for name, v in keys.items() if seg in v}, [seg], costs)
    return out


def _table(rows: list[dict]) -> list[str]:
    lines = [
        "| variant | val MAE | val MAE, fp16 tables | shaded rel. MAE | dB | FLOPs/fragment | bytes | train ms CPU/step | ORT ns CPU/fragment | Pareto: FLOPs | Pareto: bytes |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        fp16 = f"{r['val_mae_fp16_tables']:.5f}" if r.get("val_mae_fp16_tables") is not None else "-"
        step = f"{1000 * r['train_cpu_s_per_step']:.0f}" if "train_cpu_s_per_step" in r else "-"
        ort = f"{r['ort_cpu_ns_per_fragment']:,.0f}" if "ort_cpu_ns_per_fragment" in r else "-"
        lines.append(f"| {r['variant']} | {r['val_mae']:.5f} | {fp16} | {100 * r['shaded_mean']:.2f} % | {r['shaded_db']:.2f} | {r['flops']:,} | "
                     f"{r['bytes']:,} | {step} | {ort} | {'**yes**' if r['pareto_flops'] else ''} | {'**yes**' if r['pareto_bytes'] else ''} |")  # fmt: skip
    return lines


def write_markdown(path: Path, report: dict) -> None:
    summary, st = report["summary"], report["settings"]
    lines = [
        "# Multiresolution feature grids against the frequency MLP (issue 12, item 2a)",
        "",
        f"Per-segment fits, every variant at {st['steps']} Adam steps (the build's default), batch {st['batch']}, lr {st['lr']} "
        f"(grid tables x{st['table_lr_scale']}), L1, warm-up + cosine, early stop with patience {st['patience']} "
        f"(`fit_segment`; the grids by `fit_grid_segment`, same conventions), seed 0, 1 torch thread, {report['machine']}.",
        "Segments: `spot` = the 100k-sample Spot build (/tmp/i12/spotA, 8 segments of ~15k samples), "
        "`demo` = the bundled demo's 300k-sample build (/tmp/prt-demo-build, 3 segments; segment 0 has 82k).",
        "",
        "- **dB** = -20 log10(shaded relative MAE): the relative MAE of the diffuse shading T.L on the held-out samples under the "
        "bundled env maps (potsdamer, interior, studio), as `fit_segment` reports it, averaged over env maps (and segments).",
        "- **FLOPs/fragment**: the frequency MLP by `Architecture.flops_per_fragment`; the grid by `GridArchitecture.flops_breakdown` "
        "(position, per level: cell, 8 corner rows (dense or hashed), trilinear weights, interpolation; normal; MLP). "
        "A grid also makes 8 texel fetches per level (not in the FLOPs).",
        "- **bytes**: fp32 MLP weights; grid tables in fp16 (the fp16 column: validation MAE with the tables rounded to fp16).",
        "- **train ms CPU/step**, **ORT ns CPU/fragment**: CPU time of this process (`time.process_time`, 1 thread) for one Adam step "
        "at batch 8192 and for the exported ONNX graph (`export/grid_onnx.py`, `export/onnx_model.py`) in ONNX Runtime; "
        "wall-clock training seconds on this shared machine are in the JSON but say little.",
        "",
    ]
    if summary["overall"]:
        lines += [f"## Variants measured on every segment ({', '.join(summary['segments'])}), means", ""] + _table(summary["overall"]) + [""]
    for seg, rows in summary["per_segment"].items():
        samples = next(r["train_samples"] for r in report["results"] if f"{r['data']} {r['segment']}" == seg)
        lines += [f"## Segment {seg} ({samples:,} training samples)", ""]
        lines += _table(rows) + [""]
    lines += ["## What it means", "", report.get("notes", "(see the report of the study)"), "", "## Commands", "", "```"]
    lines += [*report.get("commands", [report["command"]]), "```", ""]
    path.write_text("\n".join(lines))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", action="append", default=[], help="NAME=PRECOMPUTE_FOLDER:SEG,SEG")
    ap.add_argument("--variants", default=",".join(DEFAULT_VARIANTS))
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=8192)
    ap.add_argument("--lr", type=float, default=1e-2)
    ap.add_argument("--table-lr-scale", type=float, default=1.0)
    ap.add_argument("--patience", type=int, default=10)
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path)
    ap.add_argument("--export", type=Path, help="write each fit as ONNX here and measure it (agreement, ONNX Runtime time)")
    ap.add_argument("--costs", action="store_true", help="measure CPU time per training step and per ONNX fragment of each variant")
    ap.add_argument("--notes", type=Path, help="a Markdown paragraph for 'What it means'")
    ap.add_argument("--report", action="store_true", help="only rewrite the Markdown from the JSON")
    ap.add_argument("--merge", type=Path, nargs="*", default=[], help="other JSON files of this study (e.g. run in parallel) to merge in")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    report = json.loads(args.json.read_text()) if args.json.is_file() else {"results": []}
    for other in args.merge:
        more = json.loads(other.read_text())
        have = {(r["data"], r["segment"], r["variant"]) for r in report["results"]}
        report["results"] += [r for r in more["results"] if (r["data"], r["segment"], r["variant"]) not in have]
        if "costs" in more:
            report["costs"] = {**report.get("costs", {}), **more["costs"]}
        report["segments"] = report.get("segments", []) + [s for s in more.get("segments", []) if s not in report.get("segments", [])]
        report.setdefault("commands", []).extend(c for c in more.get("commands", [more.get("command")]) if c and c not in report["commands"])
    report["command"] = "nice -n 10 .venv/bin/python studies/grid_encoding_study.py " + " ".join(sys.argv[1:] if argv is None else argv)
    if not args.report and report["command"] not in report.setdefault("commands", []):
        report["commands"].append(report["command"])
    report["settings"] = {"steps": args.steps, "batch": args.batch, "lr": args.lr, "table_lr_scale": args.table_lr_scale, "patience": args.patience}
    report["machine"] = report.get("machine", "2 shared CPU cores, no GPU")
    if args.notes is not None:
        report["notes"] = args.notes.read_text().strip()
    if args.costs:
        report["costs"] = measure_costs(args.variants.split(","))
    elif not args.report:
        from prt.train.build import _env_lights

        lights = _env_lights(4)
        segments = report.setdefault("segments", [])
        for spec in args.data:
            name, rest = spec.split("=", 1)
            folder, segs = rest.rsplit(":", 1)
            for s in map(int, segs.split(",")):
                if [name, s] not in segments:
                    segments.append([name, s])
                data = None
                for variant in args.variants.split(","):
                    if any(r["data"] == name and r["segment"] == s and r["variant"] == variant for r in report["results"]):
                        continue
                    data = data or segment_data(Path(folder), s)
                    t0 = time.perf_counter()
                    r = {"data": name, "segment": s, "train_samples": len(data[0]), "val_samples": len(data[3]), **fit_one(variant, data, args, lights)}
                    report["results"].append(r)
                    print(f"{name} seg {s} {variant:>28}: val MAE {r['val_mae']:.5f}  {r['shaded_db']:.2f} dB  {r['flops']:>7,} FLOPs  {r['bytes']:>9,} B  "
                          f"{r['steps_run']} steps {time.perf_counter() - t0:.0f} s", flush=True)  # fmt: skip
                    report["summary"] = summarise(report["results"], report.get("costs"))
                    args.json.parent.mkdir(parents=True, exist_ok=True)
                    args.json.write_text(json.dumps(report, indent=1) + "\n")
    report["summary"] = summarise(report["results"], report.get("costs"))
    args.json.write_text(json.dumps(report, indent=1) + "\n")
    if args.md is not None:
        write_markdown(args.md, report)


if __name__ == "__main__":
    main()
