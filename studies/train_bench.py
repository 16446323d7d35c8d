"""Training time per scene at the paper's setting: 1M samples, k = 64, l = 4, on this CPU.

usage: python studies/train_bench.py [--mesh PATH] [--samples N] [--out DIR] [--json OUT] [--no-fp32]

Runs ``prt-train``'s build (precompute cached in --out, so only the first run pays for it) with
the paper's fixed size, once with bf16 autocast (where the CPU has native bf16) and once in
fp32, and reports per run: training seconds for the whole scene (every segment, early
stopping on the held-out validation set), epochs, and the validation error reached.  The
fp32 run's error is the reference ("paper-level"); the report gives the bf16 run's speed-up
and its error relative to that reference.  Target (issue 3): <= 5 minutes per scene.

Reads the bunny from ../shared/data/meshes (research-only, not shipped); without it the
script says so and uses the bundled Spot.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from common import default_mesh, write_figures  # beside this script (its folder is sys.path[0])

from prt.train.build import BuildSpec, run_build
from prt.train.networks.fit import bf16_supported
from prt.train.transport.precompute import PrecomputeSettings


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", type=Path, default=None)
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--out", type=Path, default=Path("/tmp/prt-train-bench"))
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--no-fp32", action="store_true", help="skip the fp32 reference run")
    args = p.parse_args(argv)
    mesh = default_mesh(args.mesh)

    runs = {}
    variants = [("bf16", True)] if bf16_supported() else []
    if not args.no_fp32 or not variants:
        variants.append(("fp32", False))
    for label, bf16 in variants:
        spec = BuildSpec(geometry=str(mesh), precompute=PrecomputeSettings(samples=args.samples), fixed={"hidden": 64, "layers": 4}, analytic=False, bf16=bf16, bounces=0)
        out = args.out / label
        # share the (expensive) precompute between the two runs
        if label != variants[0][0] and not (out / "precompute").exists():
            (out).mkdir(parents=True, exist_ok=True)
            (out / "precompute").symlink_to((args.out / variants[0][0] / "precompute").resolve())
        for stale in (out / "train").glob("seg*.json") if (out / "train").exists() else []:
            stale.unlink()  # always retrain: this is what we time
        t0 = time.perf_counter()
        report = run_build(spec, out, progress=False, log=lambda *a: None)
        segs = report["segments"]
        weights = np.array([s["samples"] + s["margin_samples"] for s in segs], dtype=float)
        runs[label] = {
            "train_s": round(report["timings"]["train_s"], 1),
            "total_s": round(time.perf_counter() - t0, 1),
            "segments": len(segs),
            "epochs": [s["epochs"] for s in segs],
            "val_mae": float(np.average([s["val_mae"] for s in segs], weights=weights)),
            "val_mae_per_segment": [round(s["val_mae"], 5) for s in segs],
            "shaded_rel_mae": {k: float(np.average([s["shaded"][k] for s in segs], weights=weights)) for k in segs[0]["shaded"]},
        }
        print(f"{label}: train {runs[label]['train_s']} s for {len(segs)} segments, val MAE {runs[label]['val_mae']:.5f}, epochs {runs[label]['epochs']}")

    figures = {"mesh": mesh.name, "samples": args.samples, "arch": "k64-l4-f6", "runs": runs, "bf16_supported": bf16_supported()}
    if "bf16" in runs and "fp32" in runs:
        figures["bf16_speedup"] = round(runs["fp32"]["train_s"] / runs["bf16"]["train_s"], 2)
        figures["bf16_error_ratio"] = round(runs["bf16"]["val_mae"] / runs["fp32"]["val_mae"], 3)
    best = min(runs.values(), key=lambda r: r["train_s"])
    print(json.dumps(figures, indent=2))
    print(f"fastest: {best['train_s']} s per scene (target <= 300 s)")
    write_figures(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
