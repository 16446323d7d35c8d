"""How right the bounce stage's first bounce is: its nearest-sample lookups against the direct light traced at the hits (issue 43).

usage: python studies/bounce_lookup.py BUILD_DIR --json OUT.json [--md OUT.md] [--cameras CAMERAS.json]
           [--samples 2000] [--rays 64] [--hit-rays 128] [--label NAME]

The bounce stage (:mod:`prt.train.transport.interreflection`) reads, at every hit of a sample's
cosine rays, the direct transfer of the training sample nearest to the hit on its side
(:meth:`~prt.train.transport.interreflection.BounceJob.choose`).  The benchmark's reference instead
traces the direct transfer at the hit itself (:mod:`prt.bench.bounce_reference`).  Here both are
computed on the same rays of the same samples (the build's own training samples: ``--samples`` drawn
at random, or with ``--cameras`` the one nearest each pixel of its views, so that a surface weighs as
much as it covers), under the build's albedos and the potsdamer light,
and the first bounce ``mean_j a(q_j) T_0(.) . L`` (RGB mean) compared for two lookup rules:

- **unchecked**: the best-ranked candidate (the rule before 2026-12-07, and per-vertex PRT's);
- **clear**: the best-ranked candidate whose segment from the hit crosses no surface, none: no light
  (the build's rule since);
- **clear + traced**: as clear, the hits without a clear candidate reading the direct transfer traced
  there (what the next step would give the first bounce; not a rule of the build);
- **clear + traced far**: as clear + traced, and so the hits whose clear sample lies farther from them
  than twice the median such distance (with the share of hits that is);
- **build** (since 2026-12-07): the bounce stage's own first bounce, :meth:`BounceJob.traced_chunk` with
  ``trace_far`` = :data:`TRACE_FAR` times the training samples' spacing and its 32-ray traced transfer
  (:func:`traced_term`): the implementation of the row above, checked on the same rays.

Figures: the ratio of the mean first bounce to the traced one, over all samples and over three
groups by the sample's own direct light (open: > 0.05, dim, dark: < 0.002: voids, gaps); the
share of hits whose chosen sample's segment is blocked (unchecked) or that have no clear one (clear);
the per-sample ratio's 10th / 50th / 90th percentiles where the traced bounce is above 1e-4.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from prt.bench.machine import cpu_name
from prt.bench.provenance import provenance
from prt.bench.reference import load_scene_geometry
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.manifest import load_manifest
from prt.train.build import _env_lights
from prt.train.transport.interreflection import TRACE_FAR, BounceJob, BounceRays, bounce_matrices, clear_between, sample_spacing, traced_term
from prt.train.transport.transfer import EmbreeTracer, compute_transfer

LIGHT = "potsdamer"
GROUPS = {"open": (0.05, np.inf), "dim": (0.002, 0.05), "dark": (-np.inf, 0.002)}


def pixel_samples(tracer, points, normals, view: dict, size: int) -> np.ndarray:
    """Indices of the training samples a view's pixels show, one per covered pixel of a ``size`` x ``size``
    grid (repeats kept: a near wall weighs as much as it covers): the sample nearest to the pixel's
    surface point on the side facing the eye, in (position, 0.25 x normal), as the bounce lookups measure."""
    from scipy.spatial import cKDTree

    from prt.train.transport.interreflection import NORMAL_WEIGHT

    eye, target = np.asarray(view["eye"], np.float64), np.asarray(view["target"], np.float64)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = np.tan(np.radians(0.5 * float(view.get("fov", 40.0))))
    u, v = np.meshgrid(np.linspace(-half, half, size), np.linspace(half, -half, size))
    dirs = forward + u.reshape(-1, 1) * right + v.reshape(-1, 1) * up
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    result = tracer._scene.run(np.repeat(eye[None].astype(np.float32), len(dirs), 0), dirs.astype(np.float32), output=1)
    hit = result["primID"] >= 0
    q = eye + result["tfar"][hit, None].astype(np.float64) * dirs[hit]
    ng = result["Ng"][hit].astype(np.float64)
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-30)
    ng *= -np.sign(np.einsum("qc,qc->q", ng, dirs[hit]))[:, None]
    tree = cKDTree(np.concatenate([points, NORMAL_WEIGHT * normals], axis=1))
    return tree.query(np.concatenate([q, NORMAL_WEIGHT * ng], axis=1))[1].astype(np.int64)


def first_bounce(per_hit: np.ndarray, rows: np.ndarray, count: int, rays: int) -> np.ndarray:
    """(count,) per-sample mean over its ``rays`` rays of the per-hit values (hits' sample ``rows``)."""
    out = np.zeros(count)
    np.add.at(out, rows, per_hit)
    return out / rays


def ratios(values: np.ndarray, traced: np.ndarray, direct: np.ndarray) -> dict:
    out = {"all": round(float(values.sum() / max(traced.sum(), 1e-30)), 4)}
    for name, (lo, hi) in GROUPS.items():
        m = (direct > lo) & (direct <= hi)
        out[name] = round(float(values[m].sum() / max(traced[m].sum(), 1e-30)), 4) if m.any() else None
    lit = traced > 1e-4
    out["per_sample_p10_p50_p90"] = [round(float(v), 3) for v in np.percentile(values[lit] / traced[lit], [10, 50, 90])] if lit.any() else []
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("build", type=Path)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--md", type=Path)
    p.add_argument("--cameras", type=Path, help="draw the samples these views see (default: at random over the scene)")
    p.add_argument("--samples", type=int, default=2000)
    p.add_argument("--rays", type=int, default=64, help="cosine rays per sample")
    p.add_argument("--hit-rays", type=int, default=128, help="rays of the direct transfer traced at each hit")
    p.add_argument("--label", default="")
    args = p.parse_args(argv)

    manifest = load_manifest(args.build / "scene.json")
    raw = json.loads((args.build / "scene.json").read_text())
    info = raw.get("interreflection") or {}
    if not info.get("albedos"):
        print(f"bounce_lookup: {args.build / 'scene.json'}: no interreflection albedos (a build with bounces is needed)", file=sys.stderr)
        return 2
    geometry, _ = load_scene_geometry(manifest)
    with np.load(args.build / "precompute" / "samples.npz") as s:
        samples = {k: s[k] for k in ("points", "normals", "face_index", "transfer")}
    face_albedo = np.asarray([info["albedos"][n] for n in geometry.object_names], np.float64)[np.asarray(geometry.object_ids)]
    light = np.asarray(_env_lights(4)[LIGHT], np.float64).reshape(16, -1)
    light = np.repeat(light, 3, axis=1) if light.shape[1] == 1 else light
    tracer = EmbreeTracer(geometry.mesh)
    points, normals = samples["points"].astype(np.float64), samples["normals"].astype(np.float64)
    if args.cameras:
        views = json.loads(args.cameras.read_text())["views"]
        size = max(1, int(np.sqrt(args.samples / len(views))))
        pick = np.concatenate([pixel_samples(tracer, points, normals, v, size) for v in views])
    else:
        pick = np.sort(np.random.default_rng(7).choice(len(points), min(args.samples, len(points)), replace=False))
    jobs = {rule: BounceJob(tracer, points, normals, rays=args.rays, seed=7, workers=1, clear=(rule == "clear")) for rule in ("unchecked", "clear")}
    faces, q, ng = jobs["clear"].hits(points[pick], normals[pick], 0, samples["face_index"][pick])
    hit = faces >= 0
    rows = np.nonzero(hit)[0]
    albedo = face_albedo[faces[hit]]

    def radiance(transfer, where=slice(None)):
        return np.einsum("pc,pk,kc->p", albedo[where], np.asarray(transfer, np.float64), light) / 3.0

    traced_t = compute_transfer(geometry, q.astype(np.float32), ng.astype(np.float32), rays=args.hit_rays, seed=11, tracer=tracer)
    traced = first_bounce(radiance(traced_t), rows, len(pick), args.rays)
    direct = np.einsum("pk,kc->p", samples["transfer"][pick].astype(np.float64), light) / 3.0
    result = {"provenance": provenance(), "cpu": cpu_name(), "build": str(args.build), "label": args.label, "light": LIGHT,
              "selection": f"one per pixel of {args.cameras}'s views" if args.cameras else "random", "samples": int(len(pick)), "rays": args.rays,
              "hit_rays": args.hit_rays, "hits": int(hit.sum()), "traced_mean": round(float(traced.mean()), 6), "rules": {}}  # fmt: skip
    for rule, job in jobs.items():
        chosen = job.choose(q, ng)
        found = chosen >= 0
        values = np.zeros(len(q))
        values[found] = radiance(samples["transfer"][chosen[found]], found)
        entry = {"ratio_to_traced": ratios(first_bounce(values, rows, len(pick), args.rays), traced, direct)}
        if rule == "unchecked":
            ok = clear_between(tracer, q[found], ng[found], points[chosen[found]], normals[chosen[found]])
            entry["hits_blocked_share"] = round(float((~ok).sum() / len(q)), 4)
        else:
            entry["hits_without_clear_sample_share"] = round(float((~found).sum() / len(q)), 4)
            per_hit = radiance(traced_t)
            entry["their_traced_light_share"] = round(float(per_hit[~found].sum() / max(per_hit.sum(), 1e-30)), 4)
        result["rules"][rule] = entry
        print(json.dumps({"rule": rule, **entry}), flush=True)
        if rule == "clear":
            values[~found] = per_hit[~found]
            result["rules"]["clear + traced"] = {"ratio_to_traced": ratios(first_bounce(values, rows, len(pick), args.rays), traced, direct)}
            gap = np.full(len(q), np.inf)
            gap[found] = np.linalg.norm(points[chosen[found]] - q[found], axis=1)
            far = gap > 2.0 * float(np.median(gap[found]))
            values[far] = per_hit[far]
            result["rules"]["clear + traced far"] = {"ratio_to_traced": ratios(first_bounce(values, rows, len(pick), args.rays), traced, direct),
                                                     "traced_hits_share": round(float(far.mean()), 4),
                                                     "far_beyond": round(2.0 * float(np.median(gap[found])), 5)}  # fmt: skip
    far = TRACE_FAR * sample_spacing(points, normals)
    build = BounceJob(tracer, points, normals, rays=args.rays, seed=7, workers=1, trace_far=far)
    nearest, hit_face, traced_rows, traced_transfer = build.traced_chunk(points[pick], normals[pick], 0, samples["face_index"][pick])
    rays_build = BounceRays(nearest, hit_face, traced_rows, traced_transfer)
    first = bounce_matrices(rays_build, face_albedo, targets=len(points), first=True)
    t1 = np.stack([first[c] @ samples["transfer"].astype(np.float64) for c in range(3)], axis=2) + traced_term(rays_build, face_albedo)
    values = np.einsum("snc,nc->s", t1, light) / 3.0
    result["rules"]["build"] = {"ratio_to_traced": ratios(values, traced, direct), "traced_hits_share": round(float((traced_rows >= 0).sum() / hit.sum()), 4),
                                "far_beyond": round(far, 5)}  # fmt: skip
    print(json.dumps({"rule": "build", **result["rules"]["build"]}), flush=True)
    atomic_write_json(args.json, result)
    if args.md:
        lines = [f"Made by `{result['provenance']['command']}` ({result['provenance']['date']}, {result['cpu']}).",
                 "", f"Build `{args.build}`; {result['samples']:,} training samples ({result['selection']}), {args.rays} rays each, "
                 f"{result['hits']:,} hits; the direct transfer traced at each hit with {args.hit_rays} rays; light {LIGHT}. "
                 "Mean first bounce of each lookup rule over the traced one (1 = unbiased):", "",
                 "| rule | all | open | dim | dark | per sample p10 / p50 / p90 | hits blocked, without a clear sample, or traced |", "|---|---:|---:|---:|---:|---|---|"]  # fmt: skip
        for rule, entry in result["rules"].items():
            r = entry["ratio_to_traced"]
            share = entry.get("hits_blocked_share", entry.get("hits_without_clear_sample_share", entry.get("traced_hits_share")))
            extra = f" (carrying {100 * entry['their_traced_light_share']:.1f} % of the traced light)" if "their_traced_light_share" in entry else ""
            extra += f" traced (none clear, or clear farther than {entry['far_beyond']:g})" if "far_beyond" in entry else ""
            lines.append(f"| {rule} | {r['all']} | {r['open']} | {r['dim']} | {r['dark']} | {' / '.join(map(str, r['per_sample_p10_p50_p90']))} | "
                         f"{'-' if share is None else f'{100 * share:.2f} %'}{extra} |")  # fmt: skip
        atomic_write_bytes(args.md, ("\n".join(lines) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
