"""Train longer or grow? Refits of a built scene's worst segments along both axes (issue 43).

usage: python studies/refine_steps.py SCENE BUILD_DIR --json OUT.json [--md OUT.md] [--segments 5] [--threads 2]

``BUILD_DIR`` is ``prt-train SCENE -o BUILD_DIR``'s folder (the standard preset): the build is resumed
there, every stage up to the fits read back from its caches, and stopped where refinement would start
(nothing of the build is rewritten).  For the segments holding most of the error at that point
(:func:`prt.train.refine.error_shares`), each is refitted by the same call refinement makes
(:func:`prt.train.networks.rightsize.train_segment`, no fit cache) at:

- its own size, 3x the build's steps ("longer 3x");
- one size up the build's ladder, the build's steps ("grow 1x");
- one size up, 2x the build's steps ("grow 2x");

and the held-out PSNR under the scene's light (refinement's measure) and the seconds of each are
recorded.  What :mod:`prt.train.refine`'s ``REFIT_STEPS`` and ``longer`` action rest on.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import prt.train.build as build_module
from prt.bench.machine import cpu_name
from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.train import refine
from prt.train.networks.rightsize import train_segment
from prt.train.train_cli import main as train_main

TRIALS = (("longer 3x", 0, 3), ("grow 1x", 1, 1), ("grow 2x", 1, 2))  # (name, rungs up, times the build's steps)


class _Stop(Exception):
    pass


def measure(job, records, count: int, log) -> list[dict]:
    archs = [a for a in job.archs if hasattr(a, "hidden")]
    rows = []
    for share in refine.error_shares(records)[:count]:
        s = share["segment"]
        record = records[s]
        rung = refine._ladder_index(record, archs)
        row = {"segment": s, "share": share["share"], "samples": record["samples"], "size": record.get("arch_label", record["kind"]),
               "psnr_db": round(refine.light_psnr(record), 3), "trials": {}}  # fmt: skip
        for name, up, times in TRIALS:
            if rung < 0 or rung + up >= len(archs):
                continue
            arch = archs[rung + up]
            sub = dataclasses.replace(job.spec, residual="on" if (record.get("residual") or {}).get("used") else "off", analytic=False)
            t0 = time.perf_counter()
            fitted = train_segment(sub, s, job.samples, job.valid, job.members[s], [arch], refine.scaled_steps(job.fit_settings, times),
                                   job.lights, False, lambda *a: None, None, vertex=job.vertex if sub.vertex_rule() else None)  # fmt: skip
            row["trials"][name] = {"size": arch.label(), "psnr_db": round(refine.light_psnr(fitted), 3),
                                   "gain_db": round(refine.light_psnr(fitted) - refine.light_psnr(record), 3),
                                   "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
        log(json.dumps(row))
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene")
    parser.add_argument("build", type=Path)
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--md", type=Path)
    parser.add_argument("--segments", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    if not (args.build / "build.json").is_file():
        parser.error(f"{args.build}: not a finished prt-train folder (no build.json)")
    found = {}

    def stop_at_refinement(job, records):
        found["rows"] = measure(job, records, args.segments, print)
        raise _Stop

    build_module.refine_build = stop_at_refinement
    try:
        train_main([args.scene, "-o", str(args.build), "--no-progress", "--threads", str(args.threads)])
    except _Stop:
        pass
    if "rows" not in found:
        print(f"refine_steps: {args.build}: the build did not reach refinement (over its floor?)", file=sys.stderr)
        return 1
    result = {"provenance": provenance(), "cpu": cpu_name(), "scene": args.scene, "build": str(args.build), "trials": [t[0] for t in TRIALS],
              "segments": found["rows"]}  # fmt: skip
    atomic_write_json(args.json, result)
    if args.md:
        lines = [f"Made by `{result['provenance']['command']}` ({result['provenance']['date']}, {cpu_name()}, {args.threads} threads).", "",
                 "Held-out PSNR under the scene's light (refinement's measure) of each refit, gain over the build's fit, seconds.", "",
                 "| segment | share of the error | samples | build's fit | " + " | ".join(t[0] for t in TRIALS) + " |",
                 "|---:|---:|---:|---|" + "---|" * len(TRIALS)]  # fmt: skip
        for r in found["rows"]:
            cells = [f"{t['size']}: {t['psnr_db']:.2f} dB ({t['gain_db']:+.2f}), {t['seconds']:.1f} s" if (t := r["trials"].get(name)) else "-"
                     for name, _, _ in TRIALS]  # fmt: skip
            lines.append(f"| {r['segment']} | {100 * r['share']:.1f} % | {r['samples']:,} | {r['size']}: {r['psnr_db']:.2f} dB | " + " | ".join(cells) + " |")
        atomic_write_bytes(args.md, ("\n".join(lines) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
