"""Where a neural-SDF build's image error sits, and whether its ground truth has samples traced black.

usage: python studies/neural_sdf_dark_samples.py BUILD [BUILD ...] [--size 128] [--rays 256] [--view 0]

For each build folder (``prt-train MESH -o BUILD --neural-sdf``), from its precompute:

- the share of training samples whose transfer's DC term is under 0.01 (fully shadowed), and the
  slope of the field (gradient magnitude) there and at the other samples;
- the field 2e-3 along the normal (the fixed start offset of the rays before
  :meth:`prt.train.sdf.SDF.start_points`) against the sphere tracer's hit threshold (1e-4).

Then one orbit view (``--view`` of 2, as ``prt-bench --views 2``) at ``--size``: the transfer ray
traced at the covered pixels (once; the builds share their SDF network and so their G-buffer), and
per build the diffuse image's PSNR (tone-mapped, covered pixels), the pixels whose shaded network
transfer is under half the reference's, and their share of the squared error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from prt.bench.reference import load_scene_geometry
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import tonemap
from prt.train.transport.transfer import SDF_RAY_OFFSET, compute_transfer, make_tracer

HIT_THRESHOLD = 1e-4  # SDF.sphere_trace's eps at t = 0


def sample_report(build: Path, geometry) -> None:
    with np.load(build / "precompute" / "samples.npz") as d:
        points, normals, transfer = d["points"].astype(np.float64), d["normals"].astype(np.float64), d["transfer"]
    dark = transfer[:, 0] < 0.01
    rng = np.random.default_rng(0)
    pick = lambda m: rng.permutation(np.flatnonzero(m))[:2000]  # noqa: E731
    print(f"{build}: {dark.mean() * 100:.2f} % of {len(dark):,} samples have DC < 0.01")
    for name, idx in (("dark", pick(dark)), ("lit", pick(~dark))):
        if idx.size == 0:
            continue
        slope = np.linalg.norm(geometry.sdf.gradient(points[idx]), axis=1)
        f = geometry.sdf.evaluate(points[idx] + SDF_RAY_OFFSET * normals[idx])
        print(f"  {name:4s} samples: field slope 10/50/90 % {np.quantile(slope, [0.1, 0.5, 0.9]).round(3)}; "
              f"field at the fixed offset under the hit threshold: {(f < HIT_THRESHOLD).mean() * 100:.1f} %")  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("builds", nargs="+", type=Path)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--view", type=int, default=0)
    args = p.parse_args(argv)
    reference = None
    for build in args.builds:
        scene = Scene.load(build / "scene.json")
        geometry, _ = load_scene_geometry(scene.manifest)
        sample_report(build, geometry)
        with Renderer(scene, args.size, args.size, "onnx") as r:
            r.set_camera_object(orbit_views(Camera.from_manifest(scene.manifest.camera), 2)[args.view])
            g = r.gbuffer_image()
            points, normals = g.position[g.covered], g.normal[g.covered]
            if reference is None:  # the same SDF network: the same G-buffer and reference
                reference = (points, compute_transfer(geometry, points, normals, rays=args.rays, seed=0, tracer=make_tracer(geometry)))
            elif not np.array_equal(reference[0], points):
                raise SystemExit(f"{build}: another G-buffer than the first build's (another SDF network?)")
            light = np.asarray(r.lighting.sh)
            albedo = np.asarray(scene.manifest.material.albedo, dtype=np.float64)
            net = r.render_transfer()[g.covered][:, : light.shape[0]].astype(np.float64) @ light
        ref = reference[1].astype(np.float64) @ light
        err = ((tonemap((np.clip(net, 0, None) * albedo).astype(np.float32))
                - tonemap((np.clip(ref, 0, None) * albedo).astype(np.float32))) ** 2).mean(axis=1)  # fmt: skip
        black = net.mean(axis=1) < 0.5 * ref.mean(axis=1)
        rest = err[~black].mean() if (~black).any() else float("nan")
        print(f"  view {args.view} at {args.size}x{args.size}, {args.rays}-ray reference: diffuse PSNR {10 * np.log10(1 / err.mean()):.2f} dB; "
              f"{black.sum()} of {len(err)} pixels under half the reference hold {err[black].sum() / err.sum() * 100:.1f} % "
              f"of the squared error (PSNR without them {10 * np.log10(1 / rest):.2f} dB)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
