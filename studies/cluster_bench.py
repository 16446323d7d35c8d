"""Precompute on a Ray cluster: 1 against 2 single-CPU worker nodes, Ray's cost per chunk, a projection.

usage: python studies/cluster_bench.py [--mesh PATH] [--samples N] [--rays R] [--json OUT]

On this machine: a Ray head that runs no tasks (``num_cpus=0``, the driver's node) and one,
then two, worker nodes of one CPU each (``ray.cluster_utils.Cluster``: separate raylets and
object stores, as on separate machines, only sharing the cores).  The same transfer
(``compute_transfer``, ``--samples`` x ``--rays``, chunks of 2048 samples) runs on the threads of
this process (1 thread: the per-chunk cost of one CPU), then on 1 and 2 nodes (after a warm-up
that starts the workers and builds their Embree scenes).  Reported:

- the speed-up of 2 nodes over 1 (target >= 1.8x; it needs two idle cores: the load average
  before and after each timing and the CPU share other processes took are recorded);
- Ray's overhead per chunk against a thread (same chunks, one CPU), and its fixed cost per task
  (chunks of 1 ray, where the work is nearly nothing);
- the time of a 10M-sample, 1024-ray scene (plus its 5 % validation samples) on clusters of
  several sizes, from the measured per-chunk costs (work scales with the ray count).

The bunny lives in ../shared/data/meshes (research-only licence, not shipped); without it the
script says so and falls back to the bundled Spot cow.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

from common import default_mesh, write_figures  # beside this script (its folder is sys.path[0])

from prt.bench.machine import busy_seconds, cpu_name, other_cpu_share
from prt.train.cluster import RayExecutor, import_ray
from prt.train.executor import LocalExecutor
from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.transfer import DEFAULT_CHUNK, EmbreeTracer, compute_transfer

PROJECTED_SAMPLES = 10_000_000
PROJECTED_RAYS = 1024
PROJECTED_CPUS = (2, 16, 64, 256)


def timed(label, fn, repeat: int) -> dict:
    """Median wall time of ``fn()`` over ``repeat`` runs, with the machine's load around them."""
    load_before = os.getloadavg()[0]
    busy, runs = busy_seconds(), []
    t_all = time.perf_counter()
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    record = {
        "seconds": statistics.median(runs), "runs": [round(r, 3) for r in runs],
        "load_before": round(load_before, 2), "load_after": round(os.getloadavg()[0], 2),
        "other_cpu_share": other_cpu_share(busy, time.perf_counter() - t_all),
    }  # fmt: skip
    print(f"{label:>28}: {record['seconds']:7.2f} s  (runs {record['runs']}, load {record['load_before']} -> "
          f"{record['load_after']}, other processes {record['other_cpu_share']})")  # fmt: skip
    return record


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", type=Path, default=None)
    p.add_argument("--samples", type=int, default=48 * DEFAULT_CHUNK, help="samples to ray trace (48 chunks)")
    p.add_argument("--rays", type=int, default=512)
    p.add_argument("--repeat", type=int, default=2, help="timings per configuration (median reported)")
    p.add_argument("--overhead-chunks", type=int, default=200, help="chunks of 1 ray for the fixed cost per task")
    p.add_argument("--object-store-mb", type=int, default=200, help="object store of each node")
    p.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = p.parse_args(argv)
    ray = import_ray()
    from ray.cluster_utils import Cluster

    mesh_path = default_mesh(args.mesh)
    geometry = load_geometry(str(mesh_path))
    n_chunks = math.ceil(args.samples / DEFAULT_CHUNK)
    print(f"mesh: {mesh_path.name}: {len(geometry.mesh.faces):,} triangles; {args.samples:,} samples x {args.rays} rays "
          f"({n_chunks} chunks of {DEFAULT_CHUNK}); {os.cpu_count()} cores")  # fmt: skip
    samples = sample_surface(geometry, args.samples, seed=0)
    tiny = sample_surface(geometry, args.overhead_chunks * DEFAULT_CHUNK, seed=1)
    tracer = EmbreeTracer(geometry.mesh)

    def transfer(executor, points=samples.points, normals=samples.normals, rays=args.rays):
        return compute_transfer(geometry, points, normals, rays=rays, tracer=tracer, executor=executor)

    figures = {
        "mesh": mesh_path.name, "mesh_is_bunny": "bunny" in mesh_path.name, "triangles": int(len(geometry.mesh.faces)),
        "samples": args.samples, "rays": args.rays, "chunk": DEFAULT_CHUNK, "chunks": n_chunks,
        "machine": {"cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(), "ray": ray.__version__},
        "command": ".venv/bin/python " + " ".join([sys.argv[0], *(argv if argv is not None else sys.argv[1:])]),
    }  # fmt: skip
    one_thread = LocalExecutor(1)
    transfer(one_thread, rays=8)  # warm-up: page in, first allocations
    reference = transfer(one_thread)
    figures["threads_1"] = timed("threads, 1 thread", lambda: transfer(one_thread), args.repeat)
    figures["threads_1_tiny"] = timed("threads, 1 thread, 1 ray", lambda: transfer(one_thread, tiny.points, tiny.normals, 1), args.repeat)
    figures["threads_2"] = timed("threads, 2 threads", lambda: transfer(LocalExecutor(2)), args.repeat)

    node = {"num_cpus": 1, "object_store_memory": args.object_store_mb * 2**20}
    cluster = Cluster(initialize_head=True, head_node_args={**node, "num_cpus": 0, "include_dashboard": False})
    try:
        cluster.add_node(**node)
        with RayExecutor(cluster.address) as executor:
            t0 = time.perf_counter()
            transfer(executor, rays=8)  # starts the worker, which builds its Embree scene once
            figures["ray_warmup_s"] = time.perf_counter() - t0
            assert (transfer(executor) == reference).all(), "a cluster must give the local bytes"
            figures["ray_1_node"] = timed("Ray, 1 node x 1 CPU", lambda: transfer(executor), args.repeat)
            figures["ray_1_node_tiny"] = timed("Ray, 1 node, 1 ray", lambda: transfer(executor, tiny.points, tiny.normals, 1), args.repeat)
            cluster.add_node(**node)
            cluster.wait_for_nodes()
            transfer(executor, rays=8)  # the second node's worker starts and builds its scene
            figures["ray_2_nodes"] = timed("Ray, 2 nodes x 1 CPU", lambda: transfer(executor), args.repeat)
    finally:
        cluster.shutdown()

    per_chunk_thread = figures["threads_1"]["seconds"] / n_chunks
    per_chunk_ray = figures["ray_1_node"]["seconds"] / n_chunks
    per_task_thread = figures["threads_1_tiny"]["seconds"] / args.overhead_chunks
    per_task_ray = figures["ray_1_node_tiny"]["seconds"] / args.overhead_chunks
    figures["speedup_2_over_1_node"] = figures["ray_1_node"]["seconds"] / figures["ray_2_nodes"]["seconds"]
    figures["per_chunk"] = {
        "thread_s": per_chunk_thread, "ray_s": per_chunk_ray, "ray_overhead_s": per_chunk_ray - per_chunk_thread,
        "ray_overhead_share": per_chunk_ray / per_chunk_thread - 1.0,
        "fixed_cost_per_task_thread_s": per_task_thread, "fixed_cost_per_task_ray_s": per_task_ray,
    }  # fmt: skip
    # Projection: a chunk's work is linear in its rays; Ray adds its fixed cost per task.
    chunks = math.ceil(PROJECTED_SAMPLES / DEFAULT_CHUNK) + math.ceil(PROJECTED_SAMPLES // 20 / DEFAULT_CHUNK)
    work = per_chunk_thread * PROJECTED_RAYS / args.rays
    overhead = max(per_task_ray - per_task_thread, 0.0)
    figures["projection"] = {
        "samples": PROJECTED_SAMPLES, "validation_samples": PROJECTED_SAMPLES // 20, "rays": PROJECTED_RAYS, "chunks": chunks,
        "chunk_work_s": work, "chunk_overhead_s": overhead, "mesh": mesh_path.name,
        "cpu_hours": chunks * (work + overhead) / 3600,
        "hours_by_cpus": {str(c): chunks * (work + overhead) / c / 3600 for c in PROJECTED_CPUS},
        "note": "CPUs as fast as this machine's, perfect scaling (the measured 2-node speed-up says how near), "
                "transfer only (sampling, segmentation and training come on top)",
    }  # fmt: skip
    loads = [r["load_before"] for r in figures.values() if isinstance(r, dict) and "load_before" in r]
    figures["quiet_machine"] = max(loads) < 0.5
    figures["notes"] = [
        f"load average before the timings: {min(loads)} .. {max(loads)} on {os.cpu_count()} cores"
        + ("" if figures["quiet_machine"] else ": other work shared the cores, so the 2-node speed-up and the per-chunk "
           "differences are depressed and noisy; rerun on a quiet machine with the command above"),
        "other_cpu_share: share of the machine's CPU time used by processes other than this script "
        "(in the Ray rows that includes the cluster's own raylets and workers)",
    ]  # fmt: skip
    pc, pr = figures["per_chunk"], figures["projection"]
    print(f"2 nodes over 1: {figures['speedup_2_over_1_node']:.2f}x (target >= 1.8x)")
    print(f"per chunk: thread {pc['thread_s'] * 1e3:.1f} ms, Ray {pc['ray_s'] * 1e3:.1f} ms ({100 * pc['ray_overhead_share']:+.1f} %); "
          f"fixed cost per task: thread {pc['fixed_cost_per_task_thread_s'] * 1e3:.2f} ms, Ray {pc['fixed_cost_per_task_ray_s'] * 1e3:.2f} ms")  # fmt: skip
    print(f"projected {PROJECTED_SAMPLES:,} samples x {PROJECTED_RAYS} rays ({chunks} chunks): {pr['cpu_hours']:.1f} CPU-hours; "
          + ", ".join(f"{h:.2f} h on {c} CPUs" for c, h in pr["hours_by_cpus"].items()))  # fmt: skip
    write_figures(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
