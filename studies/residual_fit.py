"""Would networks fit better if they learnt the transfer's residual from the unshadowed transfer?

usage: python studies/residual_fit.py BUILD [--segments 0 1 ...] [--hidden 64] [--layers 4]
                                            [--steps 2000] [--json OUT]

BUILD is a ``prt-train`` output folder or a ``prt-precompute`` one (its ``precompute/`` or
itself holding ``samples.npz``, ``validation.npz``, ``segment_members.npz``).  For each segment
the study fits two networks of the same size, seed and steps with :func:`prt.train.networks.fit.fit_segment`:

- ``T``: the direct transfer itself (what ``prt-train`` fits today);
- ``T-U``: the residual ``T - U(n)``, ``U`` the unshadowed transfer of the sample's normal
  (:func:`prt.runtime.sh.unshadowed_transfer`), added back before scoring.

Both are scored on the segment's held-out samples on the transfer ``T``: MAE, RMSE and the
RMSE ratio in dB (``20 log10(rmse_T / rmse_T-U)``; positive: the residual fits better); with the
segment's mean visibility (the visible share of the cosine lobe, ``T_00 / U_00``).  Where
nothing occludes, the residual is 0 and the cosine lobe's dependence on the normal is exact;
the runtime's screen-space interpolation uses the same residual (``runtime/interpolation.py``).
Only the direct transfer is studied (``samples.npz`` holds it; bounces would add an indirect part
that has no analytic term).  Nothing is written but ``--json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from prt.runtime.files import atomic_write_bytes
from prt.runtime.sh import unshadowed_transfer
from prt.train.networks.fit import FitSettings, _as_input, _predict, fit_segment
from prt.train.networks.network import Architecture


def folder(build: Path) -> Path:
    for candidate in (build / "precompute", build):
        if (candidate / "samples.npz").is_file():
            return candidate
    raise SystemExit(f"residual_fit: {build}: no samples.npz in it or in its precompute/ folder")


def study_segment(samples, validation, members, s: int, arch: Architecture, steps: int) -> dict:
    p, n, t = samples["points"][members], samples["normals"][members], samples["transfer"][members].astype(np.float64)
    held = validation["segment"] == s
    vp, vn, vt = validation["points"][held], validation["normals"][held], validation["transfer"][held].astype(np.float64)
    if len(vp) == 0 or len(p) == 0:
        return {"segment": s, "skipped": "no samples"}
    bounds = np.stack([p.min(0), p.max(0)]).astype(np.float32)
    u, vu = unshadowed_transfer(n, arch.bands, np.float64), unshadowed_transfer(vn, arch.bands, np.float64)
    # The visible share of each sample's cosine lobe (T's constant coefficient over U's): 1 unoccluded.
    row = {"segment": s, "samples": int(len(p)), "held_out": int(len(vp)),
           "mean_visibility": round(float(np.mean(t[:, 0] / u[:, 0])), 4)}  # fmt: skip
    for name, target, v_target, back in (("T", t, vt, 0.0 * vu), ("T-U", t - u, vt - vu, vu)):
        fit = fit_segment(p, n, target.astype(np.float32), vp, vn, v_target.astype(np.float32), arch, bounds, FitSettings(steps=steps, seed=0))
        pred = _predict(fit.model, _as_input(vp, vn)).astype(np.float64) + back
        row[name] = {"val_mae": round(float(np.abs(pred - vt).mean()), 6), "val_rmse": round(float(np.sqrt(((pred - vt) ** 2).mean())), 6),
                     "steps": fit.steps, "seconds": round(fit.seconds, 1)}  # fmt: skip
    row["gain_db"] = round(20 * np.log10(row["T"]["val_rmse"] / row["T-U"]["val_rmse"]), 2)
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("build", type=Path)
    p.add_argument("--segments", type=int, nargs="+", default=None, help="segment ids (default: all)")
    p.add_argument("--hidden", type=int, default=64)
    p.add_argument("--layers", type=int, default=4)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    root = folder(args.build)
    samples, validation = np.load(root / "samples.npz"), np.load(root / "validation.npz")
    members = np.load(root / "segment_members.npz")
    ids = args.segments if args.segments is not None else sorted(int(k.split("_")[1]) for k in members.files)
    arch = Architecture(hidden=args.hidden, layers=args.layers)
    rows = []
    for s in ids:
        row = study_segment(samples, validation, members[f"members_{s}"], s, arch, args.steps)
        rows.append(row)
        if "gain_db" in row:
            print(f"segment {s}: RMSE {row['T']['val_rmse']:.5f} (T) vs {row['T-U']['val_rmse']:.5f} (T-U): {row['gain_db']:+.2f} dB; "
                  f"MAE {row['T']['val_mae']:.5f} vs {row['T-U']['val_mae']:.5f}; mean visibility {row['mean_visibility']:.2f}", flush=True)  # fmt: skip
    gains = [r["gain_db"] for r in rows if "gain_db" in r]
    summary = {"build": str(args.build), "hidden": args.hidden, "layers": args.layers, "steps": args.steps, "segments": rows,
               "median_gain_db": round(float(np.median(gains)), 2) if gains else None,
               "command": "python studies/residual_fit.py " + " ".join(sys.argv[1:] if argv is None else argv)}  # fmt: skip
    print(f"median gain {summary['median_gain_db']} dB over {len(gains)} segments (k = {args.hidden}, l = {args.layers}, {args.steps} steps)")
    if args.json is not None:
        atomic_write_bytes(args.json, (json.dumps(summary, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
