"""Where our renderer and our reference differ from Mitsuba 3 in mean brightness (issue 38).

usage: python studies/mitsuba_bias.py SCENE.json [--views 0 10 20] [--orbit 30] [--size 128] [--spp 1024]
                                      [--ref-rays 1024] [--hit-rays 64] [--hit-transfer-rays 128] [--sky scene|SH.json]
                                      [--cache DIR] [--json OUT]

For each view of the scene's orbit (prt-bench's): the G-buffer, our reference's direct transfer
(two seeds) and its indirect part (:mod:`prt.bench.bounce_reference`, two seeds), the built
networks' transfer (ONNX fp32), all shaded diffuse with per-object albedos; Mitsuba 3 direct
only (``max_depth`` 2) and with the scene's bounces.  Prints, per view and pooled, the mean
brightness bias (linear, ``sum(ours - mitsuba) / sum(mitsuba)``) of: our direct reference
against Mitsuba's direct light; our indirect reference against Mitsuba's indirect light
(full - direct), as a share of Mitsuba's total; our whole reference and the networks against
Mitsuba's full render; with standard errors from the measured noise.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from prt.bench.bounce_reference import cached_indirect, direct_rgb, face_albedo, higher_bounce_samples
from prt.bench.mitsuba_compare import compare, compared_pixels, diffuse_radiance, pixel_objects
from prt.bench.mitsuba_reference import MitsubaScene, cached_render, scene_albedos
from prt.bench.reference import cached_transfer, load_scene_geometry
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import Lighting
from prt.train.transport.transfer import make_tracer


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("--views", type=int, nargs="+", default=[0])
    p.add_argument("--orbit", type=int, default=30)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--spp", type=int, default=1024)
    p.add_argument("--ref-rays", type=int, default=1024)
    p.add_argument("--hit-rays", type=int, default=64)
    p.add_argument("--hit-transfer-rays", type=int, default=128)
    p.add_argument("--variant", default="auto")
    p.add_argument("--cache", type=Path, default=Path("/tmp/mitsuba_bias_cache"))
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)

    scene = Scene.load(args.scene)
    manifest = scene.manifest
    geometry, info = load_scene_geometry(manifest)
    geometry_id = info["checksum"]
    tracer = make_tracer(geometry)
    record = (manifest.raw or {}).get("interreflection") or {}
    bounces = int(record.get("bounces", 0))
    albedos = scene_albedos(manifest)
    table = np.array([albedos[n] for n in geometry.object_names])
    face = face_albedo(albedos, geometry)
    cache = args.cache / manifest.name
    higher = higher_bounce_samples(geometry, tracer, face, bounces, rays=args.ref_rays, cache=cache, geometry_id=geometry_id) if bounces >= 2 else None
    cameras = orbit_views(Camera.from_manifest(manifest.camera), args.orbit)
    size = args.size
    rows = []
    with Renderer(scene, size, size, backend="onnx") as renderer:
        lighting: Lighting = renderer.lighting
        key = f"{geometry_id}|{table.tolist()}|{lighting.sh.tolist()}"
        mi_full = MitsubaScene(geometry.mesh.vertices, geometry.mesh.faces, geometry.object_ids, geometry.two_sided, table, lighting.sh, bounces,
                               variant=args.variant)  # fmt: skip
        mi_direct = MitsubaScene(geometry.mesh.vertices, geometry.mesh.faces, geometry.object_ids, geometry.two_sided, table, lighting.sh, 0,
                                 variant=args.variant)  # fmt: skip
        print(f"env map: {mi_full.envmap_info}")
        for v in args.views:
            camera = cameras[v]
            renderer.set_camera_object(camera)
            g = renderer.gbuffer_image()
            covered = g.covered
            points, normals = g.position[covered], g.normal[covered]
            objects = pixel_objects(renderer.ctx, manifest, camera, size, size, g)
            albedo_rows = table[np.maximum(objects[covered], 0)]
            tag = f"view{v:03d}-{size}"
            direct = [cached_transfer(cache, tag, geometry, tracer, points, normals, args.ref_rays, s, geometry_id)[0] for s in (0, 1)]
            indirect = [cached_indirect(cache, tag, geometry, tracer, points, normals, face, bounces, higher=higher, seed=s, geometry_id=geometry_id,
                                        hit_rays=args.hit_rays, rays=args.hit_transfer_rays)[0] for s in (0, 1)] if bounces else None  # fmt: skip
            renderer.render()
            networks = renderer.render_transfer()[covered]
            full = cached_render(cache, tag, mi_full, key + f"|b{bounces}", camera, size, size, args.spp)
            only = cached_render(cache, tag, mi_direct, key + "|b0", camera, size, size, args.spp, seed=1)
            mask = compared_pixels(g, full, camera.eye) & (objects >= 0)

            def image(rows_):
                out = np.zeros((size, size, 3))
                out[covered] = rows_
                return out

            d_img = [image(diffuse_radiance(t, lighting, albedo_rows)) for t in direct]
            result = {"view": v, "pixels": int(mask.sum()), "covered": int(covered.sum())}
            result["direct"] = compare(d_img[0], only, mask, d_img[1])
            if bounces:
                full_img = [image(diffuse_radiance(direct_rgb(direct[s], indirect[s]), lighting, albedo_rows)) for s in (0, 1)]
                ind_img = [full_img[s] - d_img[s] for s in (0, 1)]
                ind_mi = {"radiance": full["radiance"] - only["radiance"], "passes": full["passes"] - only["passes"]}
                total = float(full["radiance"][mask].sum())
                ind = compare(ind_img[0], ind_mi, mask, ind_img[1])
                ind["bias_of_total"] = ind["bias"] * float(ind_mi["radiance"][mask].sum()) / total
                ind["share_of_total"] = float(ind_mi["radiance"][mask].sum()) / total
                result["indirect"] = ind
                result["reference"] = compare(full_img[0], full, mask, full_img[1])
            result["networks"] = compare(image(diffuse_radiance(networks, lighting, albedo_rows)), full, mask)
            rows.append(result)
            print(json.dumps(result))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
