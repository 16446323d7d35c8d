"""Batch size against steps: refits of a built scene's segments at their own size (issue 43).

usage: python studies/fit_batch.py SCENE BUILD_DIR --json OUT.json [--md OUT.md] [--segments 5]
       [--ids 26,34] [--configs 4096x1000@0.01,256x4000@0.01] [--threads 2]

``BUILD_DIR`` is ``prt-train SCENE -o BUILD_DIR``'s folder: the build is resumed there with the spec its
``build.json`` recorded (every stage up to the fits read back from its caches) and stopped where
refinement would start (nothing of the build is rewritten).  For the segments holding most of the error
at that point (:func:`prt.train.refine.error_shares`; ``--ids`` adds others), each is refitted at its own
size by the call the build makes (:func:`prt.train.networks.rightsize.train_segment`, no fit cache) once
per configuration ``BATCHxSTEPS@LR``, and the held-out PSNR under the scene's light (the floor's measure)
and the seconds of each fit are recorded.  What the presets' batch and steps rest on: a fit on two cores
is bound by its count of Adam steps, not by the samples each step sees.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

import prt.train.build as build_module
from prt.bench.machine import cpu_name
from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.train import refine
from prt.train.networks.rightsize import train_segment
from prt.train.train_cli import main as train_main

DEFAULT_CONFIGS = "4096x1000@0.01,1024x2500@0.01,256x4000@0.01,256x4000@0.005"
_CONFIG = re.compile(r"^(\d+)x(\d+)@([0-9.eE+-]+)$")


class _Stop(Exception):
    pass


def parse_configs(text: str) -> list[tuple[int, int, float]]:
    """``"4096x1000@0.01,256x4000@0.005"`` -> [(batch, steps, lr), ...]."""
    out = []
    for part in text.split(","):
        m = _CONFIG.match(part.strip())
        if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1 or not float(m.group(3)) > 0:
            raise ValueError(f"--configs: {part!r} is not BATCHxSTEPS@LR (e.g. 256x4000@0.01)")
        out.append((int(m.group(1)), int(m.group(2)), float(m.group(3))))
    return out


def label(config: tuple[int, int, float]) -> str:
    return f"{config[0]}x{config[1]}@{config[2]:g}"


def measure(job, records, count: int, ids: list[int], configs, log) -> list[dict]:
    archs = [a for a in job.archs if hasattr(a, "hidden")]
    chosen = [r["segment"] for r in refine.error_shares(records)[:count]]
    chosen += [s for s in ids if s not in chosen]
    shares = {r["segment"]: r["share"] for r in refine.error_shares(records)}
    rows = []
    for s in chosen:
        record = records[s]
        rung = refine._ladder_index(record, archs)
        if rung < 0:
            log(f"segment {s}: not a network of the ladder ({record['kind']}); skipped")
            continue
        row = {"segment": s, "share": shares[s], "samples": record["samples"], "size": record["arch_label"],
               "psnr_db": round(refine.light_psnr(record), 3), "fits": {}}  # fmt: skip
        sub = dataclasses.replace(job.spec, residual="on" if (record.get("residual") or {}).get("used") else "off", analytic=False)
        for config in configs:
            settings = dataclasses.replace(job.fit_settings, batch=config[0], steps=config[1], lr=config[2])
            t0 = time.perf_counter()
            fitted = train_segment(sub, s, job.samples, job.valid, job.members[s], [archs[rung]], settings, job.lights, False,
                                   lambda *a: None, None, vertex=job.vertex if sub.vertex_rule() else None)  # fmt: skip
            row["fits"][label(config)] = {"psnr_db": round(refine.light_psnr(fitted), 3), "seconds": round(time.perf_counter() - t0, 2)}
        log(json.dumps(row))
        rows.append(row)
    return rows


def summary(rows: list[dict], configs) -> list[dict]:
    """Per configuration: the median over segments of its PSNR gain and time ratio against the first."""
    base = label(configs[0])
    out = []
    for config in configs:
        name = label(config)
        gains = [r["fits"][name]["psnr_db"] - r["fits"][base]["psnr_db"] for r in rows]
        ratios = [r["fits"][name]["seconds"] / max(r["fits"][base]["seconds"], 1e-9) for r in rows]
        out.append({"config": name, "median_gain_db": round(statistics.median(gains), 2) if gains else None,
                    "min_gain_db": round(min(gains), 2) if gains else None, "max_gain_db": round(max(gains), 2) if gains else None,
                    "median_time_ratio": round(statistics.median(ratios), 2) if ratios else None})  # fmt: skip
    return out


def markdown(result: dict) -> str:
    names = [s["config"] for s in result["summary"]]
    lines = [f"Made by `{result['provenance']['command']}` ({result['provenance']['date']}, {result['cpu']}, {result['threads']} threads).", "",
             f"Scene `{result['scene']}`; the build's own fits: {result['build_fit']}. Each segment refitted at its own size by the build's call "
             "(`train_segment`, no cache) with batch x steps @ learning rate; held-out PSNR under the scene's light (the floor's measure) and "
             "seconds per fit (one process, fits in turn; the machine's other load is not controlled).", "",
             "| configuration | median gain over the first (min, max) | median time / the first's |", "|---|---|---:|"]  # fmt: skip
    for s in result["summary"]:
        lines.append(f"| {s['config']} | {s['median_gain_db']:+.2f} dB ({s['min_gain_db']:+.2f}, {s['max_gain_db']:+.2f}) | {s['median_time_ratio']:.2f}x |")
    lines += ["", "| segment | share of the error | samples | size | build's fit | " + " | ".join(names) + " |",
              "|---:|---:|---:|---|---:|" + "---|" * len(names)]  # fmt: skip
    for r in result["segments"]:
        cells = [f"{r['fits'][n]['psnr_db']:.2f} dB, {r['fits'][n]['seconds']:.1f} s" for n in names]
        lines.append(f"| {r['segment']} | {100 * r['share']:.1f} % | {r['samples']:,} | {r['size']} | {r['psnr_db']:.2f} dB | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene")
    parser.add_argument("build", type=Path)
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--md", type=Path)
    parser.add_argument("--segments", type=int, default=5, help="the worst segments by share of the error")
    parser.add_argument("--ids", default="", help="more segments, comma-separated ids")
    parser.add_argument("--configs", default=DEFAULT_CONFIGS, help="BATCHxSTEPS@LR, comma-separated; the first is the baseline")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    try:
        configs = parse_configs(args.configs)
        ids = [int(v) for v in args.ids.split(",") if v.strip()]
    except ValueError as exc:
        parser.error(str(exc))
    if not (args.build / "build.json").is_file():
        parser.error(f"{args.build}: not a finished prt-train folder (no build.json)")
    spec = {**json.loads((args.build / "build.json").read_text())["spec"], "geometry": str(Path(args.scene).resolve())}
    found = {}

    def stop_at_refinement(job, records):
        found["rows"] = measure(job, records, args.segments, ids, configs, print)
        raise _Stop

    build_module.refine_build = stop_at_refinement
    with tempfile.TemporaryDirectory() as tmp:  # resumed with the spec the build recorded: every stage's cache serves
        spec_file = Path(tmp) / "spec.json"
        spec_file.write_text(json.dumps(spec))
        try:
            train_main([str(spec_file), "-o", str(args.build), "--no-progress", "--threads", str(args.threads)])
        except _Stop:
            pass
    if "rows" not in found:
        print(f"fit_batch: {args.build}: the build did not reach refinement (no floor?)", file=sys.stderr)
        return 1
    result = {"provenance": provenance(), "cpu": cpu_name(), "threads": args.threads, "scene": args.scene, "build": str(args.build),
              "build_fit": f"{spec['batch']}x{spec['steps']}@{spec['lr']:g}", "configs": [label(c) for c in configs],
              "summary": summary(found["rows"], configs), "segments": found["rows"]}  # fmt: skip
    atomic_write_json(args.json, result)
    if args.md:
        atomic_write_bytes(args.md, markdown(result).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
