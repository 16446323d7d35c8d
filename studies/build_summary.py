"""Finished builds side by side, from their own records: held-out PSNR, per-vertex PRT's, the loss each
segment used, sizes and time (``build.json``); for comparing builds of one input made with different flags.

usage: python studies/build_summary.py BUILD [BUILD ...] --json OUT.json [--md OUT.md]
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes, atomic_write_json


def summary(build: Path) -> dict:
    b = json.loads((build / "build.json").read_text())
    sizing = b.get("sizing") or {}
    segments = b.get("segments", [])
    return {"build": str(build), "source": b.get("source"), "quality": b.get("preset"), "loss": b["spec"].get("loss", "l1"),
            "held_out_psnr_db": sizing.get("psnr_db"), "vertex_psnr_db": (sizing.get("vertex_psnr_db") or {}).get(sizing.get("light")),
            "light": sizing.get("light"), "segment_losses": dict(Counter(s.get("loss", b["spec"].get("loss", "l1")) for s in segments if s.get("kind") == "network")),
            "archs": [s.get("arch_label", s.get("kind")) for s in segments], "weight_bytes": b["memory"].get("weight_bytes"),
            "total_s": round(b["timings"]["total_s"], 1), "train_s": round(b["timings"].get("train_s", 0.0), 1)}  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("builds", nargs="+", type=Path)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--md", type=Path)
    args = p.parse_args(argv)
    rows = [summary(b) for b in args.builds]
    out = {"provenance": provenance(), "builds": rows}
    atomic_write_json(args.json, out)
    if args.md:
        prov = out["provenance"]
        lines = [f"Made by `{prov['command']}` ({prov['date']}, {prov['machine']['cpu']}, {prov['machine']['cores']} cores); each build's "
                 "own record (`build.json`).", "", "| build | loss | segments' losses | held-out PSNR dB (light) | vertex PRT dB | weights (bytes) "
                 "| build s (train s) |", "|---|---|---|---:|---:|---:|---:|"]  # fmt: skip
        for r in rows:
            lines.append(f"| {r['build']} | {r['loss']} | {r['segment_losses']} | {r['held_out_psnr_db']} ({r['light']}) | {r['vertex_psnr_db']} "
                         f"| {r['weight_bytes']:,} | {r['total_s']} ({r['train_s']}) |")  # fmt: skip
        atomic_write_bytes(args.md, ("\n".join(lines) + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
