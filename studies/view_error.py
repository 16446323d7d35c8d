"""Where a build's error in a view comes from: its training targets or its networks (issue 43).

usage: python studies/view_error.py BUILD_DIR CAMERAS.json --json OUT.json [--md OUT.md] [--samples 1000] [--label NAME]

For every view of ``CAMERAS.json`` (``{"views": [{"eye", "target", "fov"}]}``, the scene's normalised
space, as ``prt-bench --cameras`` reads it), the build's own training samples that the eye sees
(facing it, within the view's cone, nothing in between: one ray each) are drawn (``--samples`` at
most), and at each the diffuse radiance under the scene's light (potsdamer; RGB mean) is compared with
a quiet reference, the benchmark's estimator (:mod:`prt.bench.bounce_reference`: direct transfer with
2048 rays, the indirect part from 256 hit rays with 128 rays of direct transfer at every hit and the
bench cache's higher bounces):

- the build's **training target** there (direct transfer + the bounce stage's indirect part, raw,
  before the neighbour mean: what the held-out samples are scored against);
- the **network** of the sample's segment (the exported ONNX, :class:`prt.runtime.backends.onnx.OnnxTransfer`;
  the segment by the manifest's rule, as the G-buffer finds it: ``samples.npz`` keeps the
  precompute's segments, before refinement cut some in two).

Figures: the median and 90th percentile of |x - reference| / reference per sample, over the view and
per segment; with bounces, the direct and the indirect part apart as well (each part's error relative
to the whole radiance, so the two say which part the error is in, and the indirect part's share of the
reference's light).  The relative error is what a view's auto-exposure shows: a room's networks at 28 %
while their targets are at 7 % is a fitting problem, not a sampling one.

``BUILD_DIR`` needs its ``precompute`` caches (samples, bounce rays) and, for bounces >= 2, a
``bench_cache`` next to it holding the reference's higher-bounce samples (``prt-bench`` made them).
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np

from prt.bench.bounce_reference import face_albedo, higher_bounce_samples, indirect_transfer
from prt.bench.machine import cpu_name
from prt.bench.provenance import provenance
from prt.bench.reference import load_scene_geometry
from prt.runtime.backends.onnx import OnnxTransfer
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.manifest import load_manifest
from prt.runtime.segmentation import segment_of
from prt.train.build import _env_lights
from prt.train.networks.fit import total_transfer
from prt.train.transport.interreflection import RAY_RULE, bounce_stage
from prt.train.transport.transfer import compute_transfer, make_tracer

LIGHT = "potsdamer"


def visible_samples(tracer, points, normals, view: dict, limit: int, seed: int = 0) -> np.ndarray:
    """Indices of the samples the view's eye sees (facing it, in its cone, unoccluded), at most ``limit``."""
    eye, target = np.asarray(view["eye"], np.float64), np.asarray(view["target"], np.float64)
    forward = (target - eye) / np.linalg.norm(target - eye)
    to_eye = eye - points
    dist = np.linalg.norm(to_eye, axis=1)
    facing = np.einsum("pc,pc->p", normals, to_eye) > 0
    cone = np.einsum("pc,c->p", -to_eye, forward) > dist * np.cos(np.radians(0.5 * float(view["fov"])) * np.sqrt(2.0))
    cand = np.flatnonzero(facing & cone & (dist > 1e-6))
    if len(cand) == 0:
        return cand
    dirs = (-to_eye[cand] / dist[cand, None]).astype(np.float32)
    result = tracer._scene.run(np.repeat(eye[None].astype(np.float32), len(cand), 0), dirs, output=1)
    seen = cand[np.abs(result["tfar"] - dist[cand]) < 1e-3 * np.maximum(dist[cand], 1.0)]
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(seen, min(limit, len(seen)), replace=False)) if len(seen) else seen


def shade(transfer: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Diffuse radiance (RGB mean) of (P, 16) direct or (P, 16, 3) RGB transfer under ``light`` (16, 3)."""
    if transfer.ndim == 2:
        return np.einsum("pk,kc->p", transfer.astype(np.float64), light) / 3.0
    return np.einsum("pkc,kc->p", transfer.astype(np.float64), light) / 3.0


def relative(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.abs(x - ref) / np.maximum(ref, 1e-6)


def summary(rel: np.ndarray) -> dict:
    return {"median_pct": round(100 * float(np.median(rel)), 2), "p90_pct": round(100 * float(np.percentile(rel, 90)), 2)} if len(rel) else {}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("build", type=Path)
    parser.add_argument("cameras", type=Path)
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--md", type=Path)
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--label", default="")
    args = parser.parse_args(argv)
    b = args.build
    manifest = load_manifest(b / "scene.json")
    geometry, _ = load_scene_geometry(manifest)
    tracer = make_tracer(geometry)
    samples = dict(np.load(b / "precompute" / "samples.npz"))
    valid = dict(np.load(b / "precompute" / "validation.npz"))
    light = _env_lights(4)[LIGHT]
    info = manifest.interreflection
    bounces = int(info.bounces) if info is not None else 0
    indirect = None
    if bounces:
        albedo = face_albedo(info.albedos, geometry)
        stores = glob.glob(str(b / "precompute" / "cache" / "bounce-train-*"))
        if not stores:
            parser.error(f"{b}: no bounce-ray cache under precompute/cache")
        key = Path(stores[0]).name[len("bounce-train-"):].split("-" + RAY_RULE)[0]  # the store is named KEY-RULE
        indirect, _ = bounce_stage(geometry.mesh, b / "precompute" / "cache", samples, valid, albedo, bounces, rays=info.bounce_rays,
                                   key=key, progress=False, log=lambda *a: None)  # fmt: skip
        higher = None
        if bounces >= 2:
            found = sorted(glob.glob(str(b.parent / "bench_cache" / f"higher-b{bounces}-*.npz")))
            if not found:
                higher = higher_bounce_samples(geometry, tracer, albedo, bounces, rays=512, log=lambda *a: None)
            else:
                with np.load(found[0]) as data:
                    higher = (data["points"], data["normals"], data["higher"])
    networks = OnnxTransfer(manifest)
    views = json.loads(args.cameras.read_text())["views"]
    rows = []
    for v, view in enumerate(views):
        idx = visible_samples(tracer, samples["points"].astype(np.float64), samples["normals"].astype(np.float64), view, args.samples, seed=v)
        if len(idx) == 0:
            rows.append({"view": v, "samples": 0})
            continue
        pts, nrm = samples["points"][idx], samples["normals"][idx]
        ref = shade(compute_transfer(geometry, pts, nrm, rays=2048, seed=5, tracer=tracer), light)
        target = shade(samples["transfer"][idx, :16], light)
        # the segments by the manifest's rule: samples.npz keeps the precompute's, before refinement's splits
        seg = segment_of(manifest, pts.astype(np.float64), samples["object_ids"][idx]).astype(np.int64)
        _, out = networks.compute_reference(np.concatenate([pts, nrm], axis=1).astype(np.float32), seg)
        net = shade(total_transfer(out, light.shape[0]), light)
        parts = {}
        if bounces:
            n = light.shape[0]
            ref_ind = shade(indirect_transfer(geometry, tracer, pts, nrm, albedo, bounces, hit_rays=256, rays=128, higher=higher, seed=11), light)
            target_ind, net_ind = shade(indirect[idx], light), shade(out[:, n:].reshape(len(out), 3, n).transpose(0, 2, 1), light)
            ref_dir, target_dir, net_dir = ref.copy(), target.copy(), net - net_ind
            ref, target = ref + ref_ind, target + target_ind
            whole = np.maximum(ref, 1e-6)
            parts = {"indirect_share_of_reference": round(float(ref_ind.sum() / max(ref.sum(), 1e-30)), 4),
                     "direct": {"target": summary(np.abs(target_dir - ref_dir) / whole), "network": summary(np.abs(net_dir - ref_dir) / whole)},
                     "indirect": {"target": summary(np.abs(target_ind - ref_ind) / whole), "network": summary(np.abs(net_ind - ref_ind) / whole)}}  # fmt: skip
        rt, rn = relative(target, ref), relative(net, ref)
        segs = []
        for s in np.unique(seg):
            k = seg == s
            segs.append({"segment": int(s), "samples": int(k.sum()), "reference_mean": round(float(ref[k].mean()), 5),
                         "target": summary(rt[k]), "network": summary(rn[k])})  # fmt: skip
        rows.append({"view": v, "eye": view["eye"], "samples": int(len(idx)), "target": summary(rt), "network": summary(rn),
                     "mean_ratio_target": round(float(target.mean() / ref.mean()), 4), "mean_ratio_network": round(float(net.mean() / ref.mean()), 4),
                     **parts, "segments": sorted(segs, key=lambda r: -r["samples"])})  # fmt: skip
        print(json.dumps({k: rows[-1][k] for k in ("view", "samples", "target", "network")}), flush=True)
    result = {"provenance": provenance(), "cpu": cpu_name(), "build": str(b), "label": args.label, "light": LIGHT, "bounces": bounces,
              "segments": len(manifest.segments), "views": rows}  # fmt: skip
    atomic_write_json(args.json, result)
    if args.md:
        lines = [f"Made by `{result['provenance']['command']}` ({result['provenance']['date']}, {cpu_name()}).", "",
                 f"Build `{b}` ({args.label or 'no label'}, {len(manifest.segments)} segments). Relative error of the diffuse radiance under "
                 f"{LIGHT} at the training samples each view sees, against a quiet reference (the benchmark's estimator, more rays).", "",
                 "| view | samples | targets median / p90 | networks median / p90 | mean ratio targets / networks | indirect share | "
                 "direct part: targets / networks median | indirect part: targets / networks median |", "|---:|---:|---|---|---|---:|---|---|"]  # fmt: skip
        for r in rows:
            if r["samples"]:
                split = (f"{100 * r['indirect_share_of_reference']:.1f} % | {r['direct']['target']['median_pct']} % / {r['direct']['network']['median_pct']} % | "
                         f"{r['indirect']['target']['median_pct']} % / {r['indirect']['network']['median_pct']} %") if "direct" in r else "- | - | -"  # fmt: skip
                lines.append(f"| {r['view']} | {r['samples']} | {r['target']['median_pct']} % / {r['target']['p90_pct']} % | "
                             f"{r['network']['median_pct']} % / {r['network']['p90_pct']} % | {r['mean_ratio_target']} / {r['mean_ratio_network']} | {split} |")  # fmt: skip
        if any("direct" in r for r in rows):
            lines += ["", "The parts' errors are relative to the whole reference radiance at the sample (|part - its reference| / whole)."]
        atomic_write_bytes(args.md, ("\n".join(lines) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
