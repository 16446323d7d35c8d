"""Seams: how far two segments' networks disagree where one surface passes from one to the other.

usage: python studies/seam_steps.py BUILD_DIR[:LABEL] [...] --json OUT.json [--md OUT.md] [--radius 0.01]

For every training sample of a finished build that has a sample of another segment on its own
surface within ``--radius`` (normalised units; normals within 25 degrees, the other sample within
30 degrees of the tangent plane, the margin's ``MARGIN_SLOPE``), both segments' networks are evaluated at the sample (the ONNX
files the runtime runs, :class:`prt.runtime.backends.onnx.OnnxTransfer`) and shaded under the
scene's light (diffuse, the total transfer with its bounces).  Their difference relative to their
mean is the step an image shows where the two segments meet; the truth is one value there, so the
step is the two networks' errors together.  Reported: the samples at a seam, the median and 90th
percentile step, the share over 5 %, and whether the two segments hold the same object.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from prt.bench.machine import cpu_name
from prt.bench.provenance import provenance
from prt.runtime.backends.onnx import OnnxTransfer
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.renderer import Scene
from prt.runtime.segmentation import segment_of
from prt.train.build import _env_lights
from prt.train.networks.fit import total_transfer
from prt.train.networks.segments import MARGIN_SLOPE

sys.path.insert(0, str(Path(__file__).resolve().parent))
from view_error import LIGHT, shade  # noqa: E402

NEIGHBOURS = 12
SAME_NORMAL = 0.9  # cos 25 degrees


def seam_steps(build: Path, radius: float) -> dict:
    manifest = Scene.load(build / "scene.json").manifest
    with np.load(build / "precompute" / "samples.npz") as s:
        points, normals, objects = s["points"].astype(np.float64), s["normals"].astype(np.float64), s["object_ids"]
    seg = segment_of(manifest, points, objects)
    dist, idx = cKDTree(points).query(points, k=NEIGHBOURS, distance_upper_bound=radius)
    found = np.isfinite(dist)
    j = np.where(found, idx, 0)
    across = found & (seg[j] != seg[:, None]) & (np.einsum("nkc,nc->nk", normals[j], normals) > SAME_NORMAL)
    across &= np.abs(np.einsum("nkc,nkc->nk", normals[j], points[:, None] - points[j])) <= MARGIN_SLOPE * np.where(found, dist, 0.0) + 1e-9
    at = np.flatnonzero(across.any(axis=1))
    other = j[at, across[at].argmax(axis=1)]
    light = _env_lights(manifest.sh_bands)[LIGHT]
    networks = OnnxTransfer(manifest, threads=2)
    x = np.concatenate([points[at], normals[at]], axis=1).astype(np.float32)

    def shaded(segments):
        _, t = networks.compute(x, segments)
        return shade(total_transfer(t, light.shape[0]), light)

    a, b = shaded(seg[at]), shaded(seg[other])
    step = np.abs(a - b) / np.maximum(0.5 * (np.abs(a) + np.abs(b)), 0.05 * np.median(np.abs(a)))
    same = objects[at] == objects[other]
    row = {"build": str(build), "segments": len(manifest.segments), "samples": len(points), "at_seams": len(at), "same_object": int(same.sum())}
    if len(at):
        row |= {"median_pct": round(100 * float(np.median(step)), 2), "p90_pct": round(100 * float(np.percentile(step, 90)), 2),
                "over_5_pct": round(100 * float(np.mean(step > 0.05)), 2)}  # fmt: skip
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("builds", nargs="+", help="BUILD_DIR or BUILD_DIR:LABEL")
    parser.add_argument("--json", type=Path, required=True)
    parser.add_argument("--md", type=Path)
    parser.add_argument("--radius", type=float, default=0.01)
    args = parser.parse_args(argv)
    rows = []
    for item in args.builds:
        path, _, label = item.partition(":")
        build = Path(path)
        if not (build / "scene.json").is_file() or not (build / "precompute" / "samples.npz").is_file():
            parser.error(f"{build}: not a finished prt-train folder (no scene.json or precompute/samples.npz)")
        rows.append({"label": label or build.name, **seam_steps(build, args.radius)})
        print(rows[-1], flush=True)
    result = {"provenance": provenance(), "cpu": cpu_name(), "radius": args.radius, "light": LIGHT, "builds": rows}
    atomic_write_json(args.json, result)
    if args.md:
        lines = [f"Made by `{result['provenance']['command']}` ({result['provenance']['date']}, {cpu_name()}).", "",
                 f"Training samples with another segment's sample on their own surface within {args.radius}: both networks there, "
                 f"shaded under {LIGHT}; the step is |A - B| / their mean.", "",
                 "| build | segments | samples at a seam (same object) | median step | 90th percentile | over 5 % |", "|---|---:|---:|---:|---:|---:|"]  # fmt: skip
        for r in rows:
            lines.append(f"| {r['label']} | {r['segments']} | {r['at_seams']:,} ({r['same_object']:,}) | {r.get('median_pct', '-')} % | "
                         f"{r.get('p90_pct', '-')} % | {r.get('over_5_pct', '-')} % |")  # fmt: skip
        atomic_write_bytes(args.md, ("\n".join(lines) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
