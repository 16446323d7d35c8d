"""Do a build's training samples agree with what a camera sees?  Per pixel of one view: transfer
ray-traced at the pixel (its G-buffer position and the normal of the side facing the camera) against
the mean of the nearest training samples on the same side (16 nearest by position, normals within
25 degrees): the least a network fitted to those samples can do.  Run on builds of one scene side by
side (before and after a sampling rule).

usage: python studies/nearest_samples.py CAMERAS.json BUILD [BUILD ...] --json OUT.json [--md OUT.md]
       [--view 0] [--size 160] [--rays 512]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from prt.bench.provenance import provenance
from prt.bench.reference import load_scene_geometry
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.gl import create_context
from prt.runtime.renderer import Renderer, Scene
from prt.train.transport.transfer import compute_transfer, make_tracer

NEAREST = 16
SAME_SIDE = 0.9  # cosine between a sample's normal and the pixel's


def agreement(build: Path, view: dict, size: int, rays: int) -> dict:
    scene = Scene.load(build / "scene.json")
    geometry, _ = load_scene_geometry(scene.manifest)
    r = Renderer(scene, size, size, ctx=create_context(), interpolate=None)
    r.set_camera(eye=view["eye"], target=view["target"], fov=view.get("fov", 40.0))
    r.render()
    mask = r.covered_mask()
    pos, nor = r.gbuffer.read_targets()
    pos, nor = pos[mask], nor[mask]
    light = np.asarray(r.lighting.sh, np.float64)
    truth_t = compute_transfer(geometry, pos[:, :3].copy(), nor[:, :3].copy(), rays=rays, tracer=make_tracer(geometry))
    truth = (truth_t.astype(np.float64) @ light).mean(axis=1)
    with np.load(build / "precompute" / "samples.npz") as s:
        points, normals, transfer = s["points"], s["normals"], s["transfer"]
    _, near = cKDTree(points).query(pos[:, :3], k=NEAREST)
    same = np.einsum("pkc,pc->pk", normals[near], nor[:, :3]) > SAME_SIDE
    shaded = (transfer.astype(np.float64) @ light).mean(axis=1)  # (S,) grey
    values = np.where(same, shaded[near], 0.0).sum(axis=1) / np.maximum(same.sum(axis=1), 1)
    ok = same.any(axis=1)
    return {"build": str(build), "pixels": int(len(pos)), "pixels_with_same_side_samples": int(ok.sum()),
            "truth_mean": round(float(truth.mean()), 5), "nearest_samples_mean": round(float(values[ok].mean()), 5),
            "relative_mean_abs_difference": round(float(np.abs(values[ok] - truth[ok]).mean() / max(np.abs(truth[ok]).mean(), 1e-12)), 4)}  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("cameras", type=Path)
    ap.add_argument("builds", type=Path, nargs="+")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--md", type=Path)
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--size", type=int, default=160)
    ap.add_argument("--rays", type=int, default=512)
    args = ap.parse_args(argv)
    view = json.loads(args.cameras.read_text())["views"][args.view]
    rows = [agreement(b, view, args.size, args.rays) for b in args.builds]
    record = {"provenance": provenance(), "view": view, "size": args.size, "rays": args.rays, "rows": rows}
    atomic_write_json(args.json, record)
    if args.md:
        p = record["provenance"]
        lines = [f"Made by `{p['command']}` ({p['date']}, {p['machine']['cpu']}, {p['machine']['cores']} cores).", "",
                 f"View {view} at {args.size}x{args.size}: diffuse direct radiance `T . L` under each build's light, ray-traced at the "
                 f"pixels ({args.rays} rays) against the mean of the {NEAREST} nearest training samples on the same side.", "",
                 "| build | pixels | truth mean | nearest samples mean | relative mean abs. difference |", "|---|---:|---:|---:|---:|"]  # fmt: skip
        lines += [f"| {r['build']} | {r['pixels']:,} | {r['truth_mean']} | {r['nearest_samples_mean']} | {100 * r['relative_mean_abs_difference']:.1f} % |"
                  for r in rows]  # fmt: skip
        atomic_write_bytes(args.md, ("\n".join(lines) + "\n").encode())
    for r in rows:
        print(f"{r['build']}: truth {r['truth_mean']}, nearest samples {r['nearest_samples_mean']}, "
              f"{100 * r['relative_mean_abs_difference']:.1f} % apart")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
