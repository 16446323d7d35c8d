"""Where the renderer's and its reference's mean brightness differ from Mitsuba 3's (issue 38).

usage: python studies/mitsuba_bias.py SCENE.json [--views 0 10 20] [--orbit 30] [--size 128] [--spp 1024]
                                      [--ref-rays 1024] [--hit-rays 64] [--hit-transfer-rays 128] [--cache DIR] [--json OUT]

Per view of the scene's orbit (prt-bench's), at the G-buffer's pixels, diffuse with per-object
albedos, under the scene's own lighting (give it a band-limited, non-negative sky: see
``studies/mitsuba_reference_bench.py``), the mean brightness bias (``sum(ours - mitsuba) /
sum(mitsuba)`` of the linear radiance, with its standard error) of:

- ``direct``: our reference's direct transfer against Mitsuba with ``max_depth`` 2;
- ``indirect`` / ``indirect_before``: its indirect part against Mitsuba's (full minus direct), with
  the rule for bounce rays entering the surface and without it (the estimator before issue 38),
  also as a share of the total (``bias_of_total``);
- ``reference`` / ``reference_before``: both together against Mitsuba's full render;
- ``networks``: the built networks (ONNX fp32) against Mitsuba's full render;
- ``standard_sensor``: Mitsuba's own perspective camera (samples over each pixel's area, box
  filter) against its pixel-centre render, on the covered pixels and on the interior ones
  (eroded by a pixel): how much a comparison with an ordinary Mitsuba render moves the mean.

Writes the rows (with ``provenance``) to ``--json``; prints them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

from prt.bench.bounce_reference import direct_rgb, face_albedo, higher_bounce_samples, indirect_transfer
from prt.bench.mitsuba_compare import compare, compared_pixels, diffuse_radiance, pixel_objects
from prt.bench.mitsuba_reference import MitsubaScene, cached_render, scene_albedos
from prt.bench.provenance import provenance
from prt.bench.reference import cached_transfer, load_scene_geometry
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.files import atomic_write_json
from prt.runtime.renderer import Renderer, Scene
from prt.train.transport.transfer import make_tracer


def _standard_render(scene: MitsubaScene, camera, size: int, spp: int, passes: int = 8) -> dict:
    """Mitsuba's own perspective sensor and box filter (samples over the pixel's area): ``radiance``, ``passes``."""
    mi = scene.mi
    loaded = mi.load_dict({
        "type": "scene", "emitter": scene.emitter, **scene.shapes,
        "sensor": {"type": "perspective", "fov": camera.fov_y, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=camera.eye.tolist(), target=camera.target.tolist(), up=camera.up.tolist()),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}, "pixel_format": "rgb"}},
        "integrator": {"type": "path", "max_depth": 2 + scene.bounces, "rr_depth": 3 + scene.bounces, "hide_emitters": True},
    })  # fmt: skip
    images = np.stack([np.asarray(mi.render(loaded, spp=max(1, spp // passes), seed=7919 + k), dtype=np.float32) for k in range(passes)])
    return {"radiance": images.mean(axis=0), "passes": images}


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
    bounces = int(((manifest.raw or {}).get("interreflection") or {}).get("bounces", 0))
    albedos = scene_albedos(manifest)
    table = np.array([albedos[n] for n in geometry.object_names])
    face = face_albedo(albedos, geometry)
    cache = args.cache / manifest.name
    higher = higher_bounce_samples(geometry, tracer, face, bounces, rays=args.ref_rays, cache=cache, geometry_id=geometry_id) if bounces >= 2 else None
    cameras = orbit_views(Camera.from_manifest(manifest.camera), args.orbit)
    size, rows = args.size, []
    with Renderer(scene, size, size, backend="onnx") as renderer:
        lighting = renderer.lighting
        key = f"{geometry_id}|{table.tolist()}|{lighting.sh.tolist()}"
        full_scene = MitsubaScene(geometry.mesh.vertices, geometry.mesh.faces, geometry.object_ids, geometry.two_sided, table, lighting.sh,
                                  bounces, variant=args.variant)  # fmt: skip
        direct_scene = MitsubaScene(geometry.mesh.vertices, geometry.mesh.faces, geometry.object_ids, geometry.two_sided, table, lighting.sh, 0,
                                    variant=args.variant)  # fmt: skip
        for v in args.views:
            camera = cameras[v]
            renderer.set_camera_object(camera)
            g = renderer.gbuffer_image()
            covered = g.covered
            points, normals = g.position[covered], g.normal[covered]
            objects = pixel_objects(renderer.ctx, manifest, camera, size, size, g)
            albedo_rows = table[np.maximum(objects[covered], 0)]
            tag = f"view{v:03d}-{size}"

            def image(transfer):
                out = np.zeros((size, size, 3))
                out[covered] = diffuse_radiance(transfer, lighting, albedo_rows)
                return out

            full = cached_render(cache, tag, full_scene, key + f"|b{bounces}", camera, size, size, args.spp)
            only = cached_render(cache, tag, direct_scene, key + "|b0", camera, size, size, args.spp, seed=1)
            mask = compared_pixels(g, full, camera.eye) & (objects >= 0)
            direct = [cached_transfer(cache, tag, geometry, tracer, points, normals, args.ref_rays, s, geometry_id)[0] for s in (0, 1)]
            d_img = [image(t) for t in direct]
            row = {"view": v, "covered": int(covered.sum()), "pixels": int(mask.sum()), "direct": compare(d_img[0], only, mask, d_img[1])}
            if bounces:
                ind_mi = {"radiance": full["radiance"] - only["radiance"], "passes": full["passes"] - only["passes"]}
                total = float(full["radiance"][mask].sum())
                for name, rule in (("", True), ("_before", False)):
                    indirect = [indirect_transfer(geometry, tracer, points, normals, face, bounces, hit_rays=args.hit_rays, rays=args.hit_transfer_rays,
                                                  higher=higher, seed=s, entering_rule=rule) for s in (0, 1)]  # fmt: skip
                    whole = [image(direct_rgb(direct[s], indirect[s])) for s in (0, 1)]
                    ind = compare(whole[0] - d_img[0], ind_mi, mask, whole[1] - d_img[1])
                    ind["bias_of_total"] = ind["bias"] * float(ind_mi["radiance"][mask].sum()) / total
                    ind["share_of_total"] = float(ind_mi["radiance"][mask].sum()) / total
                    row[f"indirect{name}"] = ind
                    row[f"reference{name}"] = compare(whole[0], full, mask, whole[1])
            renderer.render()
            row["networks"] = compare(image(renderer.render_transfer()[covered]), full, mask)
            standard = _standard_render(full_scene, camera, size, args.spp)
            inner = binary_erosion(covered, iterations=1)
            row["standard_sensor"] = {"covered": compare(standard["radiance"], full, covered), "interior": compare(standard["radiance"], full, inner),
                                      "silhouette_share": round(1.0 - inner.sum() / max(covered.sum(), 1), 4)}  # fmt: skip
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        atomic_write_json(args.json, {"provenance": provenance(), "scene": str(args.scene), "bounces": bounces, "size": size, "spp": args.spp,
                                      "ref_rays": args.ref_rays, "hit_rays": args.hit_rays, "hit_transfer_rays": args.hit_transfer_rays,
                                      "envmap": full_scene.envmap_info, "views": rows})  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
