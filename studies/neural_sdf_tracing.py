"""Neural-SDF ground truth at a practical cost: the band tracer against the plain sphere tracer (issue 38).

usage: python studies/neural_sdf_tracing.py [--mesh MESH] [--work DIR] [--samples 8192] [--rays 64]
                                           [--repeats 3] [--precompute-repeats 2] [--repeat-below 120]
                                           [--sizes 20000x64 200000x256] [--today-sizes 20000x64]
                                           [--analytic creature sphere_plane torus_knot] [--no-mixed]
                                           [--threads 2] [--out docs/benchmarks/neural_sdf_tracing]

The neural SDF is the README's (``prt-train MESH --neural-sdf --sdf-size 64x4 --sdf-samples 150000
--sdf-steps 1500``), fitted once into ``--work`` (default mesh: the shared bunny).  Every timing is a
ratio within this run: the two cores are shared, so A and B run interleaved, ``--repeats`` times,
medians, and the share of the cores other processes used is recorded beside them.

1. **Tracing, the same rays.**  ``--samples`` surface samples with ``--rays`` rays each, the
   precompute's own rays (:class:`prt.train.transport.transfer.TransferIntegrator`), traced as the
   precompute traces them (``compute_transfer``, chunks of 2048 samples over ``--threads`` threads) by
   - *today*: the plain sphere tracer with the network evaluated as on ``main`` before this work
     (whole 32768-row chunks, BLAS threads as found; :class:`LegacyNode`);
   - *plain*: the plain sphere tracer with the network evaluated as now (the band tracer's twin:
     the same bytes as *today*);
   - *band*: :class:`prt.train.sdf.band_trace.BandTracer` (its build timed apart).
   Error of band against plain on those rays: hit/miss disagreements (and how many of them are rays
   on which the plain tracer spent its 256 steps: traced again with 4096 steps, do they agree with
   the band tracer?), mean and largest |T_band - T_plain| over samples and coefficients, and the
   shaded PSNR of the two transfers against each other (tone-mapped diffuse radiance under the
   bundled env maps); beside it, the Monte Carlo noise of the estimator itself (the band tracer
   with another ray seed).
2. **Precompute** (``run_precompute`` into a fresh folder) of the mesh and of its neural SDF at
   each of ``--sizes`` (samples x rays): stage times and the ratio neural / mesh; *today*'s neural
   precompute at ``--today-sizes`` (hours at the default size: not run there).  Runs of more than
   ``--repeat-below`` seconds are not repeated.  Geometry loading
   is timed apart (a neural SDF's sampling grid evaluates the network 2.3 million times).
3. **Analytic SDFs** (``--analytic``) and **a mixed scene** (the objects of
   ``docs/benchmarks/mixed_scene.json`` with this network): plain against band on the same rays.

Writes ``<out>.json`` (with provenance) and ``<out>.md``.
"""

from __future__ import annotations

import argparse
import copy
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import default_mesh  # noqa: E402

from prt.bench.machine import busy_seconds, cpu_name, other_cpu_share  # noqa: E402
from prt.bench.provenance import provenance  # noqa: E402
from prt.runtime.files import atomic_write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NETWORK = {"size": (64, 4), "samples": 150_000, "steps": 1500}  # the README's neural bunny


def _size(text: str) -> tuple[int, int]:
    try:
        samples, rays = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected SAMPLESxRAYS such as 20000x64, got {text!r}") from None
    if samples < 1000 or rays < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1000 samples and 1 ray, got {text!r}")
    return samples, rays


def legacy_sdf(sdf):
    """The SDF with its network evaluated as ``main`` did before this work (the *today* baseline)."""
    from prt.train.sdf import SDF
    from prt.train.sdf.neural import LEAKY_SLOPE, NeuralNode

    class LegacyNode(NeuralNode):
        """``NeuralNode._eval`` as it was: 32768-row chunks, whole-chunk temporaries, BLAS threads as found."""

        def _eval(self, x, y, z):
            dtype = x.dtype
            a = {k: v.astype(dtype) for k, v in self.arrays.items()}
            p_all = np.stack([x, y, z], axis=1)
            out = np.empty(len(x), dtype=dtype)
            chunk = 1 << 15
            for s in range(0, len(x), chunk):
                p = np.clip((p_all[s : s + chunk] - a["enc_centre"]) * a["enc_inv_half"], -2.0, 2.0)
                angle = p @ a["enc_pos_freq"]
                h = np.concatenate([p, np.sin(angle), np.cos(angle)], axis=1)
                for i in range(int(self.arch["layers"])):
                    w = a[f"layer{i}_weight"]
                    h = h @ w[: h.shape[1]] + a[f"layer{i}_bias"] if i == 0 else h @ w + a[f"layer{i}_bias"]
                    h = np.maximum(h, dtype.type(LEAKY_SLOPE) * h)
                z_out = h @ a["out_weight"] + a["out_bias"]
                out[s : s + chunk] = (np.tanh(z_out) * a["out_scale"] + a["out_offset"])[:, 0]
            return out

    return SDF(sdf.name, LegacyNode(sdf.root.path), sdf.description)


def _chunk(samples: int) -> int:
    """The precompute's chunk (2048 samples) where there are enough samples for 4 chunks; else a quarter."""
    from prt.train.transport.transfer import DEFAULT_CHUNK

    return DEFAULT_CHUNK if samples >= 4 * DEFAULT_CHUNK else max(1, samples // 4)


def _timed(fn):
    t0 = time.perf_counter()
    value = fn()
    return value, time.perf_counter() - t0


def _lights():
    from prt.runtime.envmap import load_envmap_sh
    from prt.runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path

    return {name: load_envmap_sh(bundled_envmap_path(name), 4) for name in BUNDLED_ENVMAPS}


def _agreement(sdf, band_hit, plain_hit, origins, dirs) -> dict:
    differ = np.flatnonzero(band_hit != plain_hit)
    patient = sdf.sphere_trace(origins[differ], dirs[differ], max_steps=4096) if differ.size else np.zeros(0, bool)
    return {
        "rays": int(len(band_hit)),
        "hit_share_plain": round(float(plain_hit.mean()), 5),
        "hit_share_band": round(float(band_hit.mean()), 5),
        "disagreements": int(differ.size),
        "disagreement_share": float(differ.size / max(len(band_hit), 1)),
        "band_hit_plain_miss": int((band_hit & ~plain_hit).sum()),
        "plain_hit_band_miss": int((plain_hit & ~band_hit).sum()),
        "settled_by_plain_4096_steps_as_band": int((patient == band_hit[differ]).sum()),
    }


def _transfer_error(band_t, plain_t, lights) -> dict:
    from prt.train.networks.rightsize import shaded_psnr

    diff = np.abs(band_t.astype(np.float64) - plain_t)
    return {
        "mean_abs_transfer_diff": float(diff.mean()),
        "max_abs_transfer_diff": float(diff.max()),
        "mean_abs_dc_diff": float(diff[:, 0].mean()),
        "shaded_psnr_db": {k: round(v, 2) for k, v in shaded_psnr(band_t, plain_t, lights, band_t.shape[1]).items()},
    }


def tracing_section(geometry, args, lights, log) -> dict:
    """Section 1: today / plain / band on the same rays."""
    from threadpoolctl import threadpool_limits

    from prt.train.inputs.sampling import sample_surface
    from prt.train.sdf.band_trace import BandTracer
    from prt.train.transport.transfer import SDFTracer, TransferIntegrator, compute_transfer

    samples = sample_surface(geometry, args.samples, seed=0)
    today_geometry = copy.copy(geometry)
    today_geometry.sdf = legacy_sdf(geometry.sdf)
    tracers = {"today": SDFTracer(today_geometry.sdf, "sphere"), "plain": SDFTracer(geometry.sdf, "sphere")}
    band, build_s = _timed(lambda: SDFTracer(geometry.sdf, "band", args.threads))
    tracers["band"] = band
    log(f"tracing: band built in {build_s:.1f} s ({band._band.band.stats['outer_faces']:,} + "
        f"{band._band.band.stats['inner_faces']:,} triangles, delta {band._band.band.delta:.2e})")  # fmt: skip
    run = dict(rays=args.rays, chunk_size=_chunk(args.samples), threads=args.threads)
    seconds = {k: [] for k in tracers}
    transfers = {}
    busy, t_all = busy_seconds(), time.perf_counter()
    for r in range(args.repeats):
        for name, tracer in tracers.items():
            t, s = _timed(lambda: compute_transfer(geometry, samples.points, samples.normals, tracer=tracer, **run))
            seconds[name].append(s)
            transfers[name] = t
            log(f"tracing: repeat {r + 1}/{args.repeats} {name}: {s:.2f} s")
    share = other_cpu_share(busy, time.perf_counter() - t_all)
    rays = args.samples * args.rays
    median = {k: float(np.median(v)) for k, v in seconds.items()}
    # hits ray by ray (the same rays compute_transfer traced), and what the band tracer spends
    integ = TransferIntegrator(tracers["plain"], rays=args.rays)
    origins, dirs, frames = integ.chunk_rays(samples.points, samples.normals, 0)
    counter = BandTracer(geometry.sdf, band._band.band)  # the same band, fresh counts
    with threadpool_limits(1, user_api="blas"):
        band_hit = counter.occluded(origins, dirs)
        plain_hit, plain_steps = _plain_trace_counted(geometry.sdf, origins, dirs)
        # a stricter reference: the plain tracer with 16x the step budget (grazing rays settled, not given up on)
        patient_hit = geometry.sdf.sphere_trace(origins, dirs, max_steps=4096)
    from_hits = {name: integ.integrate(hit, frames) for name, hit in
                 (("band", band_hit), ("plain", plain_hit), ("patient", patient_hit))}  # fmt: skip
    log(f"tracing: hits band {band_hit.mean():.4f}, plain {plain_hit.mean():.4f}, plain at 4096 steps {patient_hit.mean():.4f}")
    noise = compute_transfer(geometry, samples.points, samples.normals, tracer=band, seed=1, **run)
    return {
        "samples": args.samples,
        "rays_per_sample": args.rays,
        "rays": rays,
        "threads": args.threads,
        "repeats": args.repeats,
        "seconds": {k: [round(x, 3) for x in v] for k, v in seconds.items()},
        "us_per_ray": {k: round(v / rays * 1e6, 3) for k, v in median.items()},
        "speedup_band_vs_today": round(median["today"] / median["band"], 2),
        "speedup_band_vs_plain": round(median["plain"] / median["band"], 2),
        "speedup_plain_vs_today": round(median["today"] / median["plain"], 2),
        "band_build_s": round(build_s, 2),
        "band": band._band.band.stats,
        "today_equals_plain": bool(np.array_equal(transfers["today"], transfers["plain"])),
        "evaluations_per_ray": {"plain": round(plain_steps / len(origins), 2),
                                "band": round(counter.counts["evaluations"] / len(origins), 2)},  # fmt: skip
        "embree_queries_per_ray": round(counter.counts["queries"] / len(origins), 2),
        "rays_traced_plainly_by_band": int(counter.counts["plain"]),
        "agreement": _agreement(geometry.sdf, band_hit, plain_hit, origins, dirs),
        "plain_rays_out_of_steps": int((plain_hit != patient_hit).sum()),
        "band_vs_plain_4096_disagreements": int((band_hit != patient_hit).sum()),
        "error_band_vs_plain": _transfer_error(from_hits["band"], from_hits["plain"], lights),
        "error_band_vs_plain_4096": _transfer_error(from_hits["band"], from_hits["patient"], lights),
        "error_plain_vs_plain_4096": _transfer_error(from_hits["plain"], from_hits["patient"], lights),
        "error_band_vs_plain_compute_transfer": _transfer_error(transfers["band"], transfers["plain"], lights),
        "monte_carlo_noise": _transfer_error(noise, transfers["band"], lights),
        "other_cpu_share": share,
    }


def _plain_trace_counted(sdf, origins, dirs):
    """The plain sphere tracer's hits on these rays and the network evaluations it spends (counted)."""
    from prt.train.sdf import SDF, Node

    class Counted(Node):
        def __init__(self, node):
            self.node, self.count = node, 0

        def _eval(self, x, y, z):
            self.count += len(x)
            return self.node._eval(x, y, z)

        def bounds(self, level: float = 0.0):
            return self.node.bounds(level)

    counted = Counted(sdf.root)
    hit = SDF(sdf.name, counted).sphere_trace(origins, dirs)
    return hit, counted.count


def precompute_section(mesh_path: Path, network: Path, args, log) -> list[dict]:
    """Section 2: the precompute of the mesh and of its neural SDF, per size."""
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.precompute import PrecomputeSettings, run_precompute

    mesh_geometry, mesh_load = _timed(lambda: load_geometry(str(mesh_path)))
    neural_geometry, neural_load = _timed(lambda: load_geometry(str(network)))
    today_geometry = copy.copy(neural_geometry)
    today_geometry.sdf = legacy_sdf(neural_geometry.sdf)
    rows = []
    for samples, rays in args.sizes:
        runs = [("mesh", mesh_geometry, "auto"), ("neural", neural_geometry, "band")]
        if (samples, rays) in args.today_sizes:
            runs.append(("neural_today", today_geometry, "sphere"))
        row = {"samples": samples, "rays": rays, "load_s": {"mesh": round(mesh_load, 2), "neural": round(neural_load, 2)}}
        busy, t_all = busy_seconds(), time.perf_counter()
        for r in range(args.precompute_repeats):
            for name, geometry, trace in runs:
                entry = row.get(name)
                if r and (name == "neural_today" or entry["seconds"][0] > args.repeat_below):  # long runs: once
                    continue
                out = args.work / "precompute" / f"{name}_{samples}x{rays}"
                shutil.rmtree(out, ignore_errors=True)
                settings = PrecomputeSettings(samples=samples, rays=rays, sdf_trace=trace)
                summary, seconds = _timed(lambda: run_precompute(geometry, out, settings, threads=args.threads, progress=False,
                                                                 log=lambda *a: None))  # fmt: skip
                entry = row.setdefault(name, {"seconds": [], "timings": []})
                entry["seconds"].append(round(seconds, 2))
                entry["timings"].append({k: (round(v, 3) if isinstance(v, float) else v) for k, v in summary["timings"].items()})
                log(f"precompute {samples}x{rays}: {name} {seconds:.1f} s")
        row["other_cpu_share"] = other_cpu_share(busy, time.perf_counter() - t_all)
        med = {name: float(np.median(row[name]["seconds"])) for name, _, _ in runs}
        row["neural_over_mesh"] = round(med["neural"] / med["mesh"], 2)
        row["neural_over_mesh_with_load"] = round((med["neural"] + neural_load) / (med["mesh"] + mesh_load), 2)
        if "neural_today" in med:
            row["today_over_mesh"] = round(med["neural_today"] / med["mesh"], 2)
            row["today_over_neural"] = round(med["neural_today"] / med["neural"], 2)
        rows.append(row)
    return rows


def compare_tracers(geometry, band_tracer, plain_tracer, args, lights, label, log) -> dict:
    """Plain against band on one geometry's surface rays (sections 3)."""
    from threadpoolctl import threadpool_limits

    from prt.train.inputs.sampling import sample_surface
    from prt.train.transport.transfer import TransferIntegrator, compute_transfer

    samples = sample_surface(geometry, args.samples // 2, seed=0)
    run = dict(rays=args.rays, chunk_size=_chunk(args.samples // 2), threads=args.threads)
    seconds = {"plain": [], "band": []}
    transfers = {}
    busy, t_all = busy_seconds(), time.perf_counter()
    for _ in range(args.repeats):
        for name, tracer in (("plain", plain_tracer), ("band", band_tracer)):
            t, s = _timed(lambda: compute_transfer(geometry, samples.points, samples.normals, tracer=tracer, **run))
            seconds[name].append(s)
            transfers[name] = t
    share = other_cpu_share(busy, time.perf_counter() - t_all)
    integ = TransferIntegrator(plain_tracer, rays=args.rays)
    origins, dirs, _ = integ.chunk_rays(samples.points, samples.normals, 0)
    with threadpool_limits(1, user_api="blas"):
        band_hit, plain_hit = band_tracer.occluded(origins, dirs), plain_tracer.occluded(origins, dirs)
    differ = np.flatnonzero(band_hit != plain_hit)
    rays = len(origins)
    med = {k: float(np.median(v)) for k, v in seconds.items()}
    log(f"{label}: plain {med['plain'] / rays * 1e6:.1f} us/ray, band {med['band'] / rays * 1e6:.1f} us/ray, {differ.size} disagreements")
    return {
        "scene": label,
        "rays": rays,
        "us_per_ray": {k: round(v / rays * 1e6, 3) for k, v in med.items()},
        "speedup_band_vs_plain": round(med["plain"] / med["band"], 2),
        "disagreements": int(differ.size),
        "hit_share_plain": round(float(plain_hit.mean()), 5),
        "error_band_vs_plain": _transfer_error(transfers["band"], transfers["plain"], lights),
        "other_cpu_share": share,
    }


def analytic_section(args, lights, log) -> list[dict]:
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.transfer import SDFTracer

    rows = []
    for name in args.analytic:
        geometry = load_geometry(name)
        band, build_s = _timed(lambda: SDFTracer(geometry.sdf, "band", args.threads))
        row = compare_tracers(geometry, band, SDFTracer(geometry.sdf, "sphere"), args, lights, name, log)
        row["band_build_s"] = round(build_s, 2)
        rows.append(row)
    return rows


def mixed_section(network: Path, args, lights, log) -> dict:
    from prt.train.inputs.mixed import compose_objects, parse_objects
    from prt.train.transport.transfer import MixedTracer

    spec = json.loads((ROOT / "docs" / "benchmarks" / "mixed_scene.json").read_text())
    objects = []
    for entry in spec["objects"]:
        entry = dict(entry)
        if "mesh" in entry:
            entry["mesh"] = str((ROOT / "docs" / "benchmarks" / entry["mesh"]).resolve())
        if "neural_sdf" in entry:
            entry["neural_sdf"] = str(network)
        objects.append(entry)
    geometry = compose_objects(parse_objects(objects, "objects"))
    band, build_s = _timed(lambda: MixedTracer(geometry, "band", args.threads))
    row = compare_tracers(geometry, band, MixedTracer(geometry, "sphere"), args, lights, "mixed_scene", log)
    row["band_build_s"] = round(build_s, 2)
    return row


def write_markdown(path: Path, record: dict) -> None:
    t = record["tracing"]
    lines = [
        "# Neural-SDF tracing: the band tracer against the plain sphere tracer",
        "",
        f"Generated by `studies/neural_sdf_tracing.py` ({record['provenance']['date']}; {record['machine']}). "
        "Every speed is a ratio within this run (interleaved repeats, medians); the share of the cores that "
        "other processes used is given beside it.",
        "",
        f"## Tracing: {t['samples']:,} samples x {t['rays_per_sample']} rays of the neural bunny (64x4), {t['threads']} threads",
        "",
        "| tracer | us per ray | network evaluations per ray |",
        "|---|---:|---:|",
        f"| today (plain, main's evaluation) | {t['us_per_ray']['today']} | {t['evaluations_per_ray']['plain']} |",
        f"| plain (sphere tracer, the twin) | {t['us_per_ray']['plain']} | {t['evaluations_per_ray']['plain']} |",
        f"| band | {t['us_per_ray']['band']} | {t['evaluations_per_ray']['band']} (+ {t['embree_queries_per_ray']} Embree queries) |",
        "",
        f"- band vs today: **{t['speedup_band_vs_today']}x**; band vs plain: {t['speedup_band_vs_plain']}x; plain vs today "
        f"{t['speedup_plain_vs_today']}x (the same bytes: {t['today_equals_plain']}); band built in {t['band_build_s']} s; "
        f"other processes used {t['other_cpu_share']} of the cores.",
        f"- hit/miss: {t['agreement']['disagreements']} of {t['agreement']['rays']:,} rays differ "
        f"({t['agreement']['plain_hit_band_miss']} plain hit / band miss, {t['agreement']['band_hit_plain_miss']} band hit / "
        f"plain miss); the plain tracer with 4096 steps gives the band tracer's answer on "
        f"{t['agreement']['settled_by_plain_4096_steps_as_band']} of them.",
        f"- the plain tracer itself runs out of its 256 steps on {t['plain_rays_out_of_steps']} rays (4096 steps settle "
        f"them); against the plain tracer with 4096 steps the band tracer differs on {t['band_vs_plain_4096_disagreements']} rays.",
        "",
        "Transfer error on these rays (16 coefficients; shaded: tone-mapped diffuse radiance under the bundled env maps, dB):",
        "",
        "| pair | mean abs dT | largest abs dT | shaded PSNR |",
        "|---|---:|---:|---|",
        *[f"| {label} | {t[key]['mean_abs_transfer_diff']:.2e} | {t[key]['max_abs_transfer_diff']:.2e} | {t[key]['shaded_psnr_db']} |"
          for label, key in (("band vs plain", "error_band_vs_plain"), ("band vs plain at 4096 steps", "error_band_vs_plain_4096"),
                             ("plain vs plain at 4096 steps", "error_plain_vs_plain_4096"),
                             ("Monte Carlo noise: band, another ray seed", "monte_carlo_noise"))],  # fmt: skip
        "",
        "## Precompute: the mesh against its neural SDF (run_precompute, fresh folders)",
        "",
        "| samples x rays | mesh s | neural (band) s | neural / mesh | with geometry loading | today s | today / mesh | other CPU share |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in record["precompute"]:
        today = row.get("neural_today", {}).get("seconds", ["-"])[0]
        lines.append(f"| {row['samples']:,} x {row['rays']} | {np.median(row['mesh']['seconds']):.2f} | "
                     f"{np.median(row['neural']['seconds']):.2f} | **{row['neural_over_mesh']}** | {row['neural_over_mesh_with_load']} | "
                     f"{today} | {row.get('today_over_mesh', '-')} | {row['other_cpu_share']} |")  # fmt: skip
    lines += ["", "## Other SDF scenes: plain against band on the same rays", "",
              "| scene | plain us/ray | band us/ray | band speed-up | band build s | disagreements | shaded PSNR band vs plain (dB) |",
              "|---|---:|---:|---:|---:|---:|---|"]  # fmt: skip
    for row in record["analytic"] + ([record["mixed"]] if record.get("mixed") else []):
        lines.append(f"| {row['scene']} | {row['us_per_ray']['plain']} | {row['us_per_ray']['band']} | {row['speedup_band_vs_plain']} | "
                     f"{row['band_build_s']} | {row['disagreements']} of {row['rays']:,} | {row['error_band_vs_plain']['shaded_psnr_db']} |")  # fmt: skip
    lines += ["", f"Command: `{record['provenance']['command']}`", ""]
    path.write_text("\n".join(lines))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--mesh", type=Path, default=None, help="a watertight mesh (default: the shared bunny)")
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-neural-sdf-tracing"), help="the network and the precompute folders")
    p.add_argument("--samples", type=int, default=8192, help="surface samples of the tracing comparison (chunks of 2048, as the precompute)")
    p.add_argument("--rays", type=int, default=64, help="rays per sample of the tracing comparison")
    p.add_argument("--repeats", type=int, default=3, help="interleaved repeats of each tracing timing")
    p.add_argument("--precompute-repeats", type=int, default=2, help="interleaved repeats of each precompute (today's: once)")
    p.add_argument("--repeat-below", type=float, default=120.0, help="repeat only precomputes that took fewer seconds than this")
    p.add_argument("--sizes", type=_size, nargs="*", default=[(20_000, 64), (200_000, 256)], help="precompute sizes SAMPLESxRAYS")
    p.add_argument("--today-sizes", type=_size, nargs="*", default=[(20_000, 64)], help="sizes at which today's neural precompute runs too")
    p.add_argument("--analytic", nargs="*", default=["creature", "sphere_plane", "torus_knot"], help="analytic SDF scenes to compare")
    p.add_argument("--no-mixed", action="store_true", help="skip the mixed scene")
    p.add_argument("--threads", type=int, default=2, help="worker threads (the precompute's default: all cores)")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "neural_sdf_tracing", help="writes <out>.json and <out>.md")
    args = p.parse_args(argv)
    log = lambda *a: print(*a, flush=True)  # noqa: E731

    from prt.train.inputs.geometry import load_geometry
    from prt.train.sdf.neural_fit import prepare_neural_sdf

    mesh = default_mesh(args.mesh)
    args.work.mkdir(parents=True, exist_ok=True)
    network = prepare_neural_sdf(mesh, args.work / "network", size=NETWORK["size"], samples=NETWORK["samples"],
                                 steps=NETWORK["steps"], log=log)  # fmt: skip
    lights = _lights()
    geometry = load_geometry(str(network))
    record = {
        "provenance": provenance(),
        "machine": cpu_name(),
        "mesh": str(mesh),
        "network": {**NETWORK, "path": str(network), "fit": json.loads((network.parent / "neural_sdf.json").read_text())},
        "tracing": tracing_section(geometry, args, lights, log),
    }
    record["precompute"] = precompute_section(mesh, network, args, log)
    record["analytic"] = analytic_section(args, lights, log)
    record["mixed"] = None if args.no_mixed else mixed_section(network, args, lights, log)
    t = record["tracing"]
    record["targets"] = {
        "tracing_speedup_vs_today": {"target": 20.0, "measured": t["speedup_band_vs_today"],
                                     "met": t["speedup_band_vs_today"] >= 20.0},  # fmt: skip
        "neural_over_mesh_precompute": [{"size": f"{r['samples']}x{r['rays']}", "target": 5.0, "measured": r["neural_over_mesh"],
                                         "met": r["neural_over_mesh"] <= 5.0} for r in record["precompute"]],  # fmt: skip
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out.with_suffix(".json"), record)
    write_markdown(args.out.with_suffix(".md"), record)
    log(f"wrote {args.out.with_suffix('.json')} and .md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
