"""Which segments hold a build's image error: per segment, its share of the pixels and of the squared error.

usage: python studies/segment_error_share.py BUILD [BUILD ...] [--views 4] [--size 256] [--rays 256]
                                                   [--json OUT] [--md OUT] [--png OUT]

For each build folder (direct transfer: ``prt-train ... --bounces 0``), ``--views`` orbit views
(``orbit_views`` of the manifest's camera, as ``prt-bench --views``) at ``--size``: the ONNX backend's
transfer at the covered pixels against transfer ray traced there with ``--rays`` rays, both shaded
diffuse under the scene's light and the manifest's albedo and tone-mapped (``tonemap``), as prt-bench
compares them.  Per segment (the G-buffer's segment id): its share of the covered pixels and of the
squared error, its own PSNR, and the whole image's PSNR if that segment's pixels were exact (what
capacity there could buy at most).  A capacity rule that puts networks where the error is should
move error shares toward pixel shares.  ``--png``: per build, view 0 cropped to the segment with the
most error (ONNX | reference | 5 x |difference|, diffuse, tone-mapped), the builds one under another, at twice the size.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from prt.bench.metrics import psnr_from_mse as psnr
from prt.bench.reference import load_scene_geometry
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.files import atomic_write_bytes
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import tonemap
from prt.train.transport.transfer import compute_transfer, make_tracer


def measure(build: Path, views: int, size: int, rays: int) -> dict:
    scene = Scene.load(build / "scene.json")
    geometry, _ = load_scene_geometry(scene.manifest)
    tracer = make_tracer(geometry)
    albedo = np.asarray(scene.manifest.material.albedo, dtype=np.float64)
    shade = lambda x: tonemap((np.clip(x, 0, None) * albedo).astype(np.float32)).astype(np.float64)  # noqa: E731
    errors, segments, first = [], [], None
    with Renderer(scene, size, size, "onnx") as r:
        light = np.asarray(r.lighting.sh, dtype=np.float64)
        for v, camera in enumerate(orbit_views(Camera.from_manifest(scene.manifest.camera), views)):
            r.set_camera_object(camera)
            g = r.gbuffer_image()
            transfer = r.render_transfer()
            if transfer.shape[-1] != light.shape[0]:
                raise SystemExit(f"{build}: transfer has {transfer.shape[-1]} columns; this study takes direct builds (--bounces 0)")
            net = transfer[g.covered].astype(np.float64) @ light
            ref = compute_transfer(geometry, g.position[g.covered], g.normal[g.covered], rays=rays, seed=v, tracer=tracer,
                                   progress=False).astype(np.float64) @ light  # fmt: skip
            net, ref = shade(net), shade(ref)
            errors.append(((net - ref) ** 2).mean(axis=1))
            segments.append(g.segment[g.covered])
            if first is None:  # view 0's images, for the crop
                first = (g.covered, g.segment, net, ref)
    err, seg = np.concatenate(errors), np.concatenate(segments)
    total, mse = err.sum(), err.mean()
    rows = []
    for s in np.unique(seg):
        m = seg == s
        rows.append({"segment": int(s), "pixel_share": float(m.mean()), "error_share": float(err[m].sum() / total),
                     "psnr_db": psnr(float(err[m].mean())), "psnr_if_exact_db": psnr(float(err[~m].sum() / len(err)))})  # fmt: skip
    rows.sort(key=lambda r: -r["error_share"])
    return {"build": str(build), "covered_pixels": int(len(err)), "psnr_db": psnr(float(mse)), "segments": rows, "_view0": first}


def crop_box(view0, segment: int, pad: int = 8) -> tuple[slice, slice]:
    """Rows and columns around ``segment``'s pixels in view 0 (all covered pixels if it has none there)."""
    covered, seg = view0[0], view0[1]
    ys, xs = np.nonzero(covered & (seg == segment))
    if len(ys) == 0:
        ys, xs = np.nonzero(covered)
    return (slice(max(ys.min() - pad, 0), min(ys.max() + pad + 1, covered.shape[0])),
            slice(max(xs.min() - pad, 0), min(xs.max() + pad + 1, covered.shape[1])))  # fmt: skip


def crop_strip(view0, box) -> np.ndarray:
    """View 0 inside ``box``: ONNX | reference | 5 x |difference| (H, 3W, 3) in [0, 1]."""
    covered, _, net, ref = view0
    images = [np.zeros((*covered.shape, 3)) for _ in range(2)]
    images[0][covered], images[1][covered] = net, ref
    parts = [im[box] for im in images]
    return np.concatenate([*parts, np.clip(5 * np.abs(parts[0] - parts[1]), 0, 1)], axis=1)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("builds", nargs="+", type=Path)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    p.add_argument("--png", type=Path, default=None)
    args = p.parse_args(argv)
    command = "python studies/segment_error_share.py " + " ".join(argv if argv is not None else sys.argv[1:])
    results = [measure(b, args.views, args.size, args.rays) for b in args.builds]
    lines = [f"Made by `{command}` on {time.strftime('%Y-%m-%d')}.", ""]
    for res in results:
        lines += [f"**{res['build']}**: diffuse PSNR {res['psnr_db']:.2f} dB over {res['covered_pixels']:,} covered pixels "
                  f"({args.views} views, {args.rays}-ray reference)", "",
                  "| segment | pixels % | squared error % | its PSNR dB | image PSNR if it were exact dB |", "|---:|---:|---:|---:|---:|"]  # fmt: skip
        for r in res["segments"]:
            lines.append(f"| {r['segment']} | {100 * r['pixel_share']:.1f} | {100 * r['error_share']:.1f} | {r['psnr_db']:.2f} | {r['psnr_if_exact_db']:.2f} |")
        lines.append("")
    text = "\n".join(lines)
    print(text)
    if args.png:
        import io

        import imageio.v3 as iio

        box = crop_box(results[0]["_view0"], results[0]["segments"][0]["segment"])  # the first build's worst segment
        strips = [np.pad(crop_strip(res["_view0"], box), ((0, 4), (0, 0), (0, 0))) for res in results]  # same camera: same box
        buf = io.BytesIO()
        strip = np.concatenate(strips).repeat(2, axis=0).repeat(2, axis=1)  # 2x, nearest: the pixels stay visible
        iio.imwrite(buf, (strip * 255).round().astype(np.uint8), extension=".png")
        atomic_write_bytes(args.png, buf.getvalue())
    for res in results:
        res.pop("_view0")
    if args.json:
        atomic_write_bytes(args.json, json.dumps({"command": command, "results": results}, indent=1).encode())
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
