"""Why a room lit through its windows rendered dark: the fitting loss (L1's median against L2's mean).

usage: python studies/loss_l2.py BUILD CAMERAS.json [--view 0] [--size 160] [--rays 512] [--steps 1000]
           [--json OUT.json] [--md OUT.md]

``BUILD`` is a finished ``prt-train`` build (its ``precompute/`` kept).  At view ``--view`` of
``CAMERAS.json`` (``{"views": [{"eye", "target", "fov"}]}``, the scene's normalised space), for every
segment covering >= 2 % of the view's pixels:

- the truth: direct transfer ray-traced at the pixels now (``compute_transfer``, ``--rays`` rays,
  the G-buffer's positions and normals), shaded under the build's light (diffuse, ``T . L``);
- the build's own network at the pixels (the ONNX backend, every pixel; its direct part);
- the mean of the nearest training samples on the same side (normals within 25 degrees), so a
  wrong sample placement would show;
- the segment refitted with each loss (``l1``, ``l2``; direct transfer only, the build's hidden
  width, layers and frequencies, ``--steps`` Adam steps, 10 % of the segment's samples held out):
  mean at the pixels and PSNR there (peak: the truth's largest value), and on the held-out
  samples the bias of the mean and the PSNR against their (noisy) targets.

Scene files are not part of the repository (``studies/scenes_real.py``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import provenance
from prt.bench.reference import load_scene_geometry
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.gl import create_context
from prt.runtime.renderer import Renderer, Scene
from prt.train.networks.fit import FitSettings, _as_input, _predict, fit_segment
from prt.train.networks.network import Architecture
from prt.train.transport.transfer import compute_transfer, make_tracer


def psnr(pred: np.ndarray, truth: np.ndarray) -> float:
    mse = float(np.mean((pred - truth) ** 2))
    return round(10 * np.log10(float(truth.max()) ** 2 / max(mse, 1e-30)), 2)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("build", type=Path)
    p.add_argument("cameras", type=Path)
    p.add_argument("--view", type=int, default=0)
    p.add_argument("--size", type=int, default=160)
    p.add_argument("--rays", type=int, default=512)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--json", type=Path)
    p.add_argument("--md", type=Path)
    args = p.parse_args(argv)
    busy0, wall0 = busy_seconds(), time.perf_counter()
    scene = Scene.load(args.build / "scene.json")
    build = json.loads((args.build / "build.json").read_text())
    r = Renderer(scene, args.size, args.size, ctx=create_context(), interpolate=None)
    view = json.loads(args.cameras.read_text())["views"][args.view]
    r.set_camera(eye=view["eye"], target=view["target"], fov=view.get("fov", 40.0))
    r.render()
    transfer = r.render_transfer()
    mask = r.covered_mask()
    pos, nor = r.gbuffer.read_targets()  # top row first, as the mask
    pos, nor = pos[mask], nor[mask]
    segment = nor[:, 3].astype(np.int64)
    light = np.asarray(r.lighting.sh, np.float64)  # (16, 3)
    net = transfer[mask][:, :16].astype(np.float64) @ light
    geometry, _ = load_scene_geometry(scene.manifest)
    truth_t = compute_transfer(geometry, pos[:, :3].copy(), nor[:, :3].copy(), rays=args.rays, tracer=make_tracer(geometry))
    truth = truth_t.astype(np.float64) @ light
    samples = np.load(args.build / "precompute" / "samples.npz")
    members = np.load(args.build / "precompute" / "segment_members.npz")
    P, N, T = samples["points"], samples["normals"], samples["transfer"]
    from scipy.spatial import cKDTree

    tree = cKDTree(P)
    _, near = tree.query(pos[:, :3], k=16)
    same = (N[near] * nor[:, None, :3]).sum(axis=2) > 0.9
    rows = []
    for s in np.unique(segment):
        px = np.flatnonzero(segment == s)
        if len(px) < 0.02 * len(segment) or s < 0:
            continue
        seg_arch = build["segments"][int(s)]["arch"]
        arch = Architecture(hidden=seg_arch["hidden"], layers=seg_arch["layers"], pos_freqs=seg_arch["pos_freqs"],
                            normal_freqs=seg_arch["normal_freqs"])  # fmt: skip
        nearest = []
        for i in px:
            k = near[i][same[i]]
            if len(k):
                nearest.append(float((T[k[0]].astype(np.float64) @ light).mean()))
        idx = members[f"members_{int(s)}"].copy()
        np.random.default_rng(0).shuffle(idx)
        held, train = idx[: len(idx) // 10], idx[len(idx) // 10 :]
        bounds = np.stack([P[idx].min(axis=0), P[idx].max(axis=0)])
        row = {"segment": int(s), "pixels": int(len(px)), "samples": int(len(idx)), "arch": arch.label(),
               "truth_mean": round(float(truth[px].mean()), 5), "build_network_mean": round(float(net[px].mean()), 5),
               "build_network_psnr_db": psnr(net[px], truth[px]), "nearest_samples_mean": round(float(np.mean(nearest)), 5) if nearest else None,
               "refits": {}}  # fmt: skip
        for loss in ("l1", "l2"):
            t0 = time.perf_counter()
            fit = fit_segment(P[train], N[train], T[train], P[held], N[held], T[held], arch, bounds,
                              FitSettings(steps=args.steps, batch=4096, lr=0.01, patience=10, loss=loss))  # fmt: skip
            at_px = _predict(fit.model, _as_input(pos[px, :3], nor[px, :3])).astype(np.float64) @ light
            pv = _predict(fit.model, _as_input(P[held], N[held])).astype(np.float64) @ light
            tv = T[held].astype(np.float64) @ light
            row["refits"][loss] = {"pixels_mean": round(float(at_px.mean()), 5), "pixels_psnr_db": psnr(at_px, truth[px]),
                                   "held_out_bias_pct": round(100 * (float(pv.mean()) / float(tv.mean()) - 1), 1),
                                   "held_out_psnr_db": psnr(pv, tv), "steps": fit.steps, "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
        print(json.dumps(row), flush=True)
        rows.append(row)
    prov = provenance()
    prov["machine"]["other_cpu_share"] = round(other_cpu_share(busy0, time.perf_counter() - wall0), 3)
    out = {"provenance": prov, "build": str(args.build), "build_loss": build["spec"].get("loss", "l1"), "view": view, "size": args.size,
           "rays": args.rays, "steps": args.steps, "view_truth_mean": round(float(truth.mean()), 5),
           "view_build_network_mean": round(float(net.mean()), 5), "segments": rows}  # fmt: skip
    if args.json:
        atomic_write_json(args.json, out)
    if args.md:
        atomic_write_bytes(args.md, markdown(out).encode())
    return 0


def markdown(out: dict) -> str:
    prov = out["provenance"]
    lines = [f"Made by `{prov['command']}` ({prov['date']}, {prov['machine']['cpu']}, {prov['machine']['cores']} cores, "
             f"other processes {100 * prov['machine'].get('other_cpu_share', 0):.0f} %).", "",
             f"View {out['view']} of `{out['build']}` (built with loss `{out['build_loss']}`), {out['size']}x{out['size']}: diffuse direct "
             f"radiance `T . L` under the build's light; truth ray-traced at the pixels ({out['rays']} rays); view mean: truth "
             f"{out['view_truth_mean']}, the build's networks {out['view_build_network_mean']}.", "",
             "| segment | pixels | arch | truth | build's network (PSNR) | nearest samples | refit L1 at pixels (PSNR) | refit L2 at pixels (PSNR) "
             "| held-out bias L1 / L2 | held-out PSNR L1 / L2 |", "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in out["segments"]:
        a, b = r["refits"]["l1"], r["refits"]["l2"]
        lines.append(f"| {r['segment']} | {r['pixels']:,} | {r['arch']} | {r['truth_mean']:.4f} | {r['build_network_mean']:.4f} "
                     f"({r['build_network_psnr_db']} dB) | {r['nearest_samples_mean']} | {a['pixels_mean']:.4f} ({a['pixels_psnr_db']} dB) "
                     f"| {b['pixels_mean']:.4f} ({b['pixels_psnr_db']} dB) | {a['held_out_bias_pct']:+.1f} % / {b['held_out_bias_pct']:+.1f} % "
                     f"| {a['held_out_psnr_db']} / {b['held_out_psnr_db']} dB |")  # fmt: skip
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
