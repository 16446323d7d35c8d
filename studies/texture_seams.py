"""Seams of texture-space transfer: is the error larger where a bilinear fetch reaches a chart's gutter?

usage: python studies/texture_seams.py SCENE CACHE [--size 256] [--views 4] [--ref-rays 256] [--json OUT]

Reads the transfer textures ``prt-bench --backends texture`` cached in CACHE (the bench's
``--cache``) for SCENE, renders ``--views`` orbit views with the ``texture`` backend, and splits
the covered pixels in two: those whose bilinear footprint (the 2x2 texels a fetch reads) holds a
texel outside what the rasteriser drew of the charts (filled by a border sample or by dilation: a
chart's border, where a seam would show) and the rest.  Reported per
texture size: pixels of each kind and the RMS transfer error (all 16 coefficients) against the
bench's ray-traced reference (the same cache, ``--ref-rays``, seed 0) for each.  A seam shows as a
border RMS well above the interior RMS.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from prt.bench.reference import cached_transfer, load_scene_geometry
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.gl import create_context
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.transfer_texture import TransferTextureInfo
from prt.train.transport.transfer import make_tracer
from prt.train.transport.transfer_texture import scene_geometry, uv_gbuffer
from prt.train.inputs.uv_atlas import build_atlas


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("cache", type=Path)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--ref-rays", type=int, default=256)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    scene = Scene.load(args.scene)
    manifest = scene.manifest
    geometry, info = load_scene_geometry(manifest)
    tracer = make_tracer(geometry)
    cameras = orbit_views(Camera.from_manifest(manifest.camera), args.views)
    ctx = create_context()
    rows = []
    for stats_path in sorted((args.cache / manifest.name).glob(f"transfer_texture-*-r{args.ref_rays}.json")):
        stats = json.loads(stats_path.read_text())
        size = stats["size"]
        path = stats_path.with_suffix(".npz")
        # What the rasteriser drew of the bake's atlas (deterministic): a footprint reaching past it is a border.
        source = json.loads((manifest.root / "build.json").read_text()).get("source") if (manifest.root / "build.json").is_file() else None
        atlas = build_atlas(scene_geometry(manifest), size, stats["layout"], source_path=source, ctx=ctx, log=lambda line: None)
        _, _, covered = uv_gbuffer(ctx, np.asarray(geometry.mesh.vertices, np.float32), np.asarray(geometry.mesh.faces), atlas, size, border=False)
        entry = TransferTextureInfo(path=path, size=size, atlases=stats["atlases"])
        errors = {"border": [], "interior": []}
        with Renderer(Scene(dataclasses.replace(manifest, transfer_texture=entry)), args.size, args.size, backend="texture", ctx=ctx) as r:
            for v, camera in enumerate(cameras):
                r.set_camera_object(camera)
                transfer = r.render_transfer()
                gbuffer = r.gbuffer_image()
                uv = np.frombuffer(r.gbuffer.uv_texture.read(), np.float32).reshape(args.size, args.size, 4)[::-1]
                mask = gbuffer.covered
                reference, _ = cached_transfer(args.cache / "transfer", f"view{v:03d}-{args.size}x{args.size}", geometry, tracer,
                                               gbuffer.position[mask], gbuffer.normal[mask], args.ref_rays, 0, info["checksum"])  # fmt: skip
                x = np.floor(uv[mask][:, 0] * size - 0.5).astype(int)
                y = np.floor(uv[mask][:, 1] * size - 0.5).astype(int)
                a = np.rint(uv[mask][:, 2]).astype(int)
                footprint = np.ones(len(x), dtype=bool)
                for dy in (0, 1):
                    for dx in (0, 1):
                        footprint &= covered[a, np.clip(y + dy, 0, size - 1), np.clip(x + dx, 0, size - 1)]
                error = ((transfer[mask] - reference) ** 2).mean(axis=1)
                errors["interior"].append(error[footprint])
                errors["border"].append(error[~footprint])
        row = {"size": size, "views": len(cameras)}
        for kind, parts in errors.items():
            values = np.concatenate(parts)
            row[f"{kind}_pixels"] = int(len(values))
            row[f"{kind}_rms"] = float(np.sqrt(values.mean())) if len(values) else None
        row["border_over_interior"] = row["border_rms"] / row["interior_rms"] if row["border_rms"] and row["interior_rms"] else None
        rows.append(row)
        print(f"{manifest.name} texture {size}: border {row['border_pixels']} px, RMS {row['border_rms']:.5f}; "
              f"interior {row['interior_pixels']} px, RMS {row['interior_rms']:.5f}; ratio {row['border_over_interior']:.2f}")  # fmt: skip
    if args.json is not None:
        args.json.write_text(json.dumps({"scene": manifest.name, "seams": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
