"""Precompute throughput: end-to-end transfer rays/s next to raw Embree occlusion rays/s.

usage: python studies/precompute_bench.py [--mesh PATH] [--samples N] [--rays R] [--threads T] [--repeat K] [--json OUT]

Both figures come from one run on the same machine: first the end-to-end precompute
(``compute_transfer``: ray generation, Embree, integration, SH rotation, all threads), then
the bare ``EmbreeScene.run(query="OCCLUDED")`` calls, on the same threads, over the very same
rays of a subset of the chunks (every ``--raw-stride``-th chunk, generated beforehand and
kept in memory).  The two are measured alternately ``--repeat`` times and medians are
reported (the machine is shared and noisy).  Target (issue 2): end-to-end >= 85 % of raw, and 1M samples x 512 rays of
the 60k-triangle bunny within 60 s on 2 cores.

The bunny lives in ../shared/data/meshes (research-only licence, not shipped); without it the
script says so and falls back to the bundled Spot cow.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from common import default_mesh, write_figures  # beside this script (its folder is sys.path[0])

from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.transfer import DEFAULT_CHUNK, EmbreeTracer, TransferIntegrator, compute_transfer


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", type=Path, default=None)
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--rays", type=int, default=512)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--raw-stride", type=int, default=8, help="time raw Embree on every n-th chunk")
    p.add_argument("--repeat", type=int, default=3, help="alternate end-to-end and raw runs this often; medians reported")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)

    mesh_path = default_mesh(args.mesh)
    geometry = load_geometry(str(mesh_path))
    print(f"mesh: {mesh_path.name}: {len(geometry.mesh.faces):,} triangles; {args.samples:,} samples x {args.rays} rays; {args.threads} threads")

    samples = sample_surface(geometry, args.samples, seed=0)
    tracer = EmbreeTracer(geometry.mesh)

    integrator = TransferIntegrator(tracer, rays=args.rays)
    chunk = DEFAULT_CHUNK
    n_chunks = (args.samples + chunk - 1) // chunk
    batches = []
    for k in range(0, n_chunks, args.raw_stride):
        sl = slice(k * chunk, (k + 1) * chunk)
        origins, dirs, _ = integrator.chunk_rays(samples.points[sl], samples.normals[sl], k)
        batches.append((origins, dirs))
    raw_rays = sum(len(o) for o, _ in batches)
    total_rays = args.samples * args.rays

    e2e_times, raw_times = [], []
    with ThreadPoolExecutor(max_workers=args.threads) as pool:
        for r in range(args.repeat):
            t0 = time.perf_counter()
            compute_transfer(
                geometry, samples.points, samples.normals, rays=args.rays, threads=args.threads, progress=r == 0, tracer=tracer
            )
            e2e_times.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            list(pool.map(lambda b: tracer.occluded(*b), batches))
            raw_times.append(time.perf_counter() - t0)
            print(f"run {r + 1}: end-to-end {total_rays / e2e_times[-1] / 1e6:.2f} Mrays/s, raw {raw_rays / raw_times[-1] / 1e6:.2f} Mrays/s")
    e2e_s = float(np.median(e2e_times))
    raw_s = float(np.median(raw_times))

    e2e_rate = total_rays / e2e_s
    raw_rate = raw_rays / raw_s
    figures = {
        "mesh": mesh_path.name,
        "triangles": int(len(geometry.mesh.faces)),
        "samples": args.samples,
        "rays_per_sample": args.rays,
        "threads": args.threads,
        "repeats": args.repeat,
        "end_to_end_s": round(e2e_s, 2),
        "end_to_end_s_all": [round(t, 2) for t in e2e_times],
        "end_to_end_mrays_per_s": round(e2e_rate / 1e6, 3),
        "raw_embree_mrays_per_s": round(raw_rate / 1e6, 3),
        "raw_embree_rays_timed": raw_rays,
        "ratio_end_to_end_over_raw": round(e2e_rate / raw_rate, 3),
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
    }
    print(json.dumps(figures, indent=2))
    print(
        f"end-to-end {e2e_rate / 1e6:.2f} Mrays/s = {100 * e2e_rate / raw_rate:.0f} % of raw Embree "
        f"{raw_rate / 1e6:.2f} Mrays/s (target >= 85 %); {args.samples:,} x {args.rays} in {e2e_s:.1f} s (target <= 60 s)"
    )
    write_figures(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
