"""The Cornell box direct-only, with 1 and 2 bounces, and the path-traced reference: docs/cornell_bounces.png.

usage: python studies/cornell_bounces.py [MESH] [--work DIR] [--samples N] [--rays R] [--steps S]
           [--bounces 0 1 2] [--hidden 32 --layers 3] [--size 256] [--views 3] [--ref-rays 256] [--ref-hit-rays 64]
           [--ref-hit-transfer-rays N] [--noise] [--envmap studio] [--exposure 2]
           [--json docs/benchmarks/cornell_bounces.json] [--figure docs/cornell_bounces.png]

MESH defaults to the shared Cornell box (the tests/data copy with its MTL colours).  For every N
in ``--bounces`` the study builds the scene with ``prt-train MESH --bounces N`` (in ``--work``;
an existing build is reused), times the build, renders ``--views`` orbit views with the ONNX
backend and the file's colours (every object diffuse with its ``Kd``: the reference shades
diffuse receivers), and compares each with the reference of the same N:

- direct transfer ray traced at every covered pixel (``--ref-rays``);
- the indirect part from :mod:`prt.bench.bounce_reference` (first bounce ray traced at the exact
  hit points, higher bounces from independent samples), with the albedos the build recorded;
- shaded per channel, ``albedo_c (T_direct + T_indirect,c) . L_c``, each pixel with the albedo
  of the object an eye ray hits there (Embree, independent of the G-buffer's object ids).

Reported per N: PSNR / SSIM over covered pixels (tone-mapped, ``--exposure``), the build's
seconds, the frame time (median of ``--frames``), and colour bleeding: the red/green ratio of the
floor's radiance in the third next to the red wall against the third next to the green wall, in
the render and in the reference.  "GI off" is the direct-only render against the 2-bounce
reference.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from prt.bench.bounce_reference import HIT_RAYS, cached_indirect, face_albedo, higher_bounce_samples
from prt.bench.metrics import image_metrics
from prt.bench.reference import cached_transfer, load_scene_geometry
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import to_srgb8, tonemap
from prt.train.transport.transfer import make_tracer

ROOT = Path(__file__).resolve().parents[1]
CORNELL = ROOT / "tests" / "data" / "CornellBox-Original.obj"


def build(mesh: Path, out: Path, bounces: int, args) -> float | None:
    """``prt-train`` into ``out`` (resumable: a finished build whose caches match this code only
    re-exports; one made by older code is refitted where its keys changed); seconds taken."""
    cmd = [str(Path(sys.executable).with_name("prt-train")), str(mesh), "-o", str(out), "--samples", str(args.samples),
           "--rays", str(args.rays), "--steps", str(args.steps), "--bounces", str(bounces), *args.size_flags]  # fmt: skip
    if out.exists():
        cmd.append("--force")  # an interrupted build of ours: resume (the precompute cache is kept)
    print(" ".join(cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def interreflection_record(manifest) -> dict:
    raw = manifest.raw or {}
    return raw.get("interreflection") or {"bounces": 0, "albedos": {}}


def object_albedos(manifest, geometry) -> dict:
    """{object name: diffuse albedo} the renderer shades with (the file's Kd per object)."""
    names = list(geometry.object_names)
    found = {m["object"]: m["albedo"] for m in (manifest.raw or {}).get("materials", []) if "object" in m}
    default = list(map(float, manifest.material.albedo))
    return {n: found.get(n, default) for n in names}


def pixel_objects(tracer, geometry, eye, points) -> np.ndarray:
    """Object id of the first surface an eye ray through each point hits (-1: none)."""
    origins = np.repeat(np.asarray(eye, np.float32)[None], len(points), axis=0)
    dirs = points.astype(np.float32) - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    faces = tracer._scene.run(origins, dirs, output=1)["primID"].astype(np.int64)
    return np.where(faces >= 0, np.asarray(geometry.object_ids)[np.maximum(faces, 0)], -1)


def bleeding(radiance, objects, positions, names) -> dict:
    """Red/green ratio of the floor's radiance next to the red (left, -x) wall and next to the green (+x) one."""
    floor = objects == names.index("floor") if "floor" in names else np.zeros(len(objects), bool)
    if not floor.any():
        return {}
    x = positions[:, 0]
    lo, hi = np.quantile(x[floor], [1 / 3, 2 / 3])
    out = {}
    for side, mask in (("red_side", floor & (x <= lo)), ("green_side", floor & (x >= hi))):
        rgb = radiance[mask].mean(axis=0)
        out[side] = round(float(rgb[0] / max(rgb[1], 1e-12)), 4)
    out["redder_next_to_red"] = bool(out["red_side"] > out["green_side"])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mesh", nargs="?", type=Path, default=CORNELL)
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-cornell-bounces"))
    p.add_argument("--samples", type=int, default=100_000)
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--bounces", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--hidden", type=int, default=32, help="fixed network size (0: prt-train's right-sizing ladder)")
    p.add_argument("--layers", type=int, default=3)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--views", type=int, default=3)
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--ref-rays", type=int, default=256)
    p.add_argument("--ref-hit-rays", type=int, default=HIT_RAYS, help="bounce rays per pixel of the indirect reference (prt-bench's --ref-hit-rays)")
    p.add_argument("--ref-hit-transfer-rays", type=int, default=None,
                   help="rays per bounce hit of the indirect reference [min(--ref-rays, 128)] (prt-bench's --ref-hit-transfer-rays)")
    p.add_argument("--noise", action="store_true", help="also trace view 0's reference with a second seed: the reference's own noise (PSNR)")
    p.add_argument("--envmap", default="studio")
    p.add_argument("--exposure", type=float, default=2.0, help="the box is lit through its open side only")
    p.add_argument("--json", type=Path, default=ROOT / "docs" / "benchmarks" / "cornell_bounces.json")
    p.add_argument("--figure", type=Path, default=ROOT / "docs" / "cornell_bounces.png")
    args = p.parse_args(argv)

    if args.ref_hit_rays < 1 or (args.ref_hit_transfer_rays is not None and args.ref_hit_transfer_rays < 1):
        p.error("--ref-hit-rays and --ref-hit-transfer-rays must be >= 1")
    hit_transfer_rays = args.ref_hit_transfer_rays or min(args.ref_rays, 128)
    args.size_flags = ["--hidden", str(args.hidden), "--layers", str(args.layers)] if args.hidden else []
    args.work.mkdir(parents=True, exist_ok=True)
    cache = args.work / "reference"
    cache.mkdir(exist_ok=True)
    seconds = {n: build(args.mesh, args.work / f"b{n}", n, args) for n in args.bounces}
    scenes = {n: Scene.load(args.work / f"b{n}" / "scene.json") for n in args.bounces}
    top = max(args.bounces)
    geometry, info = load_scene_geometry(scenes[top].manifest)
    tracer = make_tracer(geometry)
    names = list(geometry.object_names)
    record = interreflection_record(scenes[top].manifest)
    albedo = face_albedo(record["albedos"], geometry) if top > 0 else None
    receivers = object_albedos(scenes[top].manifest, geometry)
    higher = higher_bounce_samples(geometry, tracer, albedo, top, rays=args.ref_rays, cache=cache, geometry_id=info["checksum"]) if top >= 2 else None

    cameras = orbit_views(Camera.from_manifest(scenes[top].manifest.camera), args.views)
    result = {"mesh": str(args.mesh), "envmap": args.envmap, "exposure": args.exposure, "size": args.size, "views": args.views,
              "samples": args.samples, "rays": args.rays, "steps": args.steps, "network": args.size_flags or "right-sized",
              "ref_rays": args.ref_rays, "ref_hit_rays": args.ref_hit_rays, "ref_hit_transfer_rays": hit_transfer_rays, "command": "python studies/cornell_bounces.py " + " ".join(sys.argv[1:]), "builds": {}}  # fmt: skip
    panels, pixels, refs = {}, {}, {}
    for n in args.bounces:
        psnr, ssim, frame_ms, bleed_render, bleed_ref, gi_off = [], [], [], [], [], []
        with Renderer(scenes[n], args.size, args.size, backend="onnx") as r:
            r.set_envmap(args.envmap)
            for name in names:  # every object diffuse with its own colour (the reference's receivers)
                r.set_material("diffuse", albedo=receivers[name], object=name)
            for v, camera in enumerate(cameras):
                r.set_camera_object(camera)
                image = r.render()
                times = []
                for _ in range(args.frames):
                    r.set_camera_object(camera.orbit(1e-4))  # a new view: the networks run
                    t0 = time.perf_counter()
                    r.render()
                    times.append(1e3 * (time.perf_counter() - t0))
                frame_ms.append(float(np.median(times)))
                r.set_camera_object(camera)
                g = r.gbuffer_image()
                cov = g.covered
                pts, nrm = g.position[cov], g.normal[cov]
                if v not in pixels:  # the same G-buffer for every build (one mesh, one camera)
                    direct, _ = cached_transfer(cache, f"v{v}-{args.size}", geometry, tracer, pts, nrm, args.ref_rays, 0, info["checksum"])
                    objects = pixel_objects(tracer, geometry, camera.eye, pts)
                    rec_albedo = np.array([receivers[names[o]] if o >= 0 else [0, 0, 0] for o in objects], dtype=np.float64)
                    pixels[v] = (cov, direct, objects, rec_albedo)
                if not np.array_equal(pixels[v][0], cov):
                    raise SystemExit(f"view {v}: the builds' G-buffers differ (not one mesh?)")
                _, direct, objects, rec_albedo = pixels[v]
                lighting = r.lighting.sh.astype(np.float64)  # (16, 3)
                for m in {0, n, top} - {k[1] for k in refs if k[0] == v and len(k) == 2}:
                    for seed in (0, 1) if (args.noise and v == 0) else (0,):
                        d = direct if seed == 0 else cached_transfer(cache, f"v{v}-{args.size}", geometry, tracer, pts, nrm, args.ref_rays, seed, info["checksum"])[0]
                        indirect = cached_indirect(cache, f"v{v}-{args.size}", geometry, tracer, pts, nrm, albedo, m, geometry_id=info["checksum"],
                                                   higher=higher if m >= 2 else None, seed=seed, hit_rays=args.ref_hit_rays,
                                                   rays=hit_transfer_rays)[0] if m > 0 else 0.0  # fmt: skip
                        t = d.astype(np.float64)[:, :, None] + indirect
                        ref = np.zeros(cov.shape + (3,), np.float32)
                        ref[cov] = np.maximum(rec_albedo * np.einsum("pkc,kc->pc", t, lighting), 0)
                        refs[(v, m) if seed == 0 else (v, m, "seed1")] = ref
                metrics = image_metrics(tonemap(image, args.exposure), tonemap(refs[(v, n)], args.exposure), cov)
                psnr.append(metrics["psnr"])
                ssim.append(metrics["ssim"])
                gi_off.append(image_metrics(tonemap(image, args.exposure), tonemap(refs[(v, top)], args.exposure), cov)["psnr"])
                bleed_render.append(bleeding(image[cov], objects, pts, names))
                bleed_ref.append(bleeding(refs[(v, n)][cov], objects, pts, names))
                if v == 0 and (0, n, "seed1") in refs:  # the reference against its second seed (the higher bounces' samples shared)
                    noise = image_metrics(tonemap(refs[(0, n, "seed1")], args.exposure), tonemap(refs[(0, n)], args.exposure), cov)["psnr"]
                    result.setdefault("reference_noise_view0", {})[str(n)] = round(noise, 2)
                if v == 0:
                    panels[n] = to_srgb8(image, args.exposure)
                    panels["reference"] = to_srgb8(refs[(v, top)], args.exposure)
        result["builds"][str(n)] = {
            "build_s": None if seconds[n] is None else round(seconds[n], 1),
            "psnr": round(float(np.mean(psnr)), 2), "psnr_views": [round(x, 2) for x in psnr], "ssim": round(float(np.mean(ssim)), 4),
            "psnr_against_top_reference": round(float(np.mean(gi_off)), 2),
            "frame_ms": round(float(np.median(frame_ms)), 2), "bleeding_render": bleed_render[0], "bleeding_reference": bleed_ref[0],
        }  # fmt: skip
        print(f"bounces {n}: {result['builds'][str(n)]}", flush=True)
    base = result["builds"].get("0", {}).get("frame_ms")
    if base:
        for n in args.bounces:
            result["builds"][str(n)]["frame_ratio_to_direct"] = round(result["builds"][str(n)]["frame_ms"] / base, 3)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    gap = np.full((args.size, 8, 3), 255, np.uint8)
    row = []
    for key in [*args.bounces, "reference"]:
        row += [panels[key], gap]
    iio.imwrite(args.figure, np.concatenate(row[:-1], axis=1))
    print(f"wrote {args.json} and {args.figure} (panels: {', '.join(map(str, args.bounces))} bounces, reference with {top})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
