"""The mixed-scene showcase: figure and G-buffer cost of a built mixed scene (issue 15).

usage: python studies/mixed_scene.py SCENE_DIR [--image docs/mixed_scene.png] [--size 512]
                                           [--frames 7] [--out docs/benchmarks/mixed_scene_gbuffer]

SCENE_DIR is a build of ``docs/benchmarks/mixed_scene.json`` (``prt-train`` with that spec; the
spec names the bunny's neural SDF, ``stanford_bunny_hr.sdf.onnx``, built beside it with
``prt-train ../shared/data/meshes/stanford_bunny_hr.obj --neural-sdf -o DIR`` and copied or linked).

1. Figure: left, the scene rendered by the GLSL backend at ``--size``, lit by a sky light (a
   bright cap around ``--sun``, projected onto the scene's SH bands, so shadows are soft);
   right, the shadowing alone: the cosine-weighted share of each point's hemisphere that no
   object blocks (``T_0 / Y_00`` of the networks' transfer: 1 white, 0 black), where the shadows
   each kind of object casts on the others stand out.
2. G-buffer cost per frame at ``--size``, in one run, median of ``--frames`` frames after a
   warm-up, default camera: the scene's own mixed G-buffer (the ground rasterised, the
   bunny, ball and ring sphere traced) beside a mesh G-buffer of the same shapes (every object
   rasterised: the marching-cubes proxies of the SDF objects, as the build composed them),
   and the mesh draw and the SDF pass of the mixed G-buffer apart; for a scene built before
   the GLSL skipped a neural object by its box bound, also with ``scene_sdf.glsl`` written
   by the current code (``regenerated_*``).
3. Who shadows whom: for every receiver object and caster object, the share of the receiver's
   cosine-weighted hemisphere the caster alone blocks (ray traced; mean and 99th percentile
   over samples of the receiver).  Writes ``<out>.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np


def sky_light(bands: int, sun=(0.45, 0.8, 0.35), sun_power: float = 3.0, ambient: float = 0.12) -> np.ndarray:
    """(bands^2, 3) SH of a sky: uniform radiance ``ambient`` plus a cap of half-angle 15 degrees
    around ``sun`` giving irradiance ``sun_power`` head on (band-limited, so its shadows are soft)."""
    from prt.runtime import sh

    n = 200_000
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    r = np.sqrt(1.0 - z * z)
    dirs = np.stack([r * np.cos(phi), z, r * np.sin(phi)], axis=1)  # Fibonacci sphere, +y up
    s = np.asarray(sun, dtype=np.float64) / np.linalg.norm(sun)
    cap = (dirs @ s > np.cos(np.radians(15.0))).astype(np.float64)
    radiance = ambient + sun_power * cap / (4 * np.pi * cap.mean())
    coeffs = sh.basis(dirs, bands).T @ radiance * (4 * np.pi / n)
    return np.repeat(coeffs[:, None], 3, axis=1) * np.array([1.0, 0.97, 0.92])


def recompose(scene_dir: Path):
    """The scene's geometry composed again from its ``mixed.json`` (as the build composed it)."""
    from prt.train.inputs.mixed import compose_objects, parse_objects

    record = json.loads((scene_dir / "mixed.json").read_text())
    entries = []
    for entry in record["objects"]:
        spec = dict(entry["spec"])
        if entry["kind"] == "neural_sdf":
            spec["neural_sdf"] = str(scene_dir / entry["source"])
        entries.append(spec)
    return compose_objects(parse_objects(entries))


def regenerated(scene_dir: Path, geometry, work: Path) -> Path | None:
    """A copy of the scene with ``scene_sdf.glsl`` written by this code (None if it is the same):
    a scene built before the GLSL's box culling of neural objects measured as a build now would be."""
    text = geometry.mixed.glsl("scene_sdf")
    if (scene_dir / "scene_sdf.glsl").read_text() == text:
        return None
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(scene_dir, work)
    (work / "scene_sdf.glsl").write_text(text)
    return work / "scene.json"


def mesh_twin(scene_dir: Path, geometry, work: Path) -> Path:
    """A copy of the scene whose geometry is every object rasterised (SDF proxies included)."""
    from prt.runtime.files import atomic_save_npz

    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(scene_dir, work)
    atomic_save_npz(work / "geometry.npz", vertices=np.asarray(geometry.mesh.vertices, dtype=np.float32),
                    faces=np.asarray(geometry.mesh.faces, dtype=np.uint32), object_ids=geometry.object_ids.astype(np.int32),
                    two_sided=geometry.two_sided)  # fmt: skip
    data = json.loads((work / "scene.json").read_text())
    g = data["geometry"]
    data["geometry"] = {"type": "mesh", "file": g["file"], "to_source": g["to_source"], "triangles": int(len(geometry.mesh.faces)),
                        "objects": g["objects"]}  # fmt: skip
    data["version"] = 1
    (work / "scene.json").write_text(json.dumps(data, indent=1))
    return work / "scene.json"


def cross_shadows(geometry, samples_per_object: int = 3000, rays: int = 64, seed: int = 0) -> dict:
    """Who shadows whom: for receiver r and caster c, the share of r's cosine-weighted hemisphere
    that c alone blocks, over samples of r (mean and 99th percentile), by ray tracing c alone."""
    import trimesh

    from prt.train.inputs.sampling import sample_surface
    from prt.train.transport.transfer import EmbreeTracer, SDFTracer, cosine_directions, make_tracer, orthonormal_frames

    names, parts = geometry.object_names, geometry.mixed
    s = sample_surface(geometry, samples_per_object * len(names) * 4, seed=seed)
    local = cosine_directions(rays)
    casters = {}
    for c, name in enumerate(names):
        if c in parts.sdfs:
            casters[name] = SDFTracer(parts.sdfs[c])
        else:
            faces = np.asarray(geometry.mesh.faces)[(geometry.object_ids == c) & ~parts.proxy_faces]
            casters[name] = EmbreeTracer(trimesh.Trimesh(np.asarray(geometry.mesh.vertices), faces, process=False))
    scene_tracer = make_tracer(geometry)  # its ray origins: lifted off slow SDF fields as in the precompute
    table = {}
    for r, receiver in enumerate(names):
        idx = np.flatnonzero(s.object_ids == r)[:samples_per_object]
        frames = orthonormal_frames(s.normals[idx].astype(np.float64))
        dirs = np.einsum("sij,mj->smi", frames, local).reshape(-1, 3).astype(np.float32)
        origins = np.repeat(scene_tracer.origins(s.points[idx], s.normals[idx]), rays, axis=0)  # the precompute's rule
        table[receiver] = {}
        for caster, tracer in casters.items():
            blocked = tracer.occluded(origins, dirs).reshape(len(idx), rays).mean(axis=1)
            table[receiver][caster] = {"mean": float(blocked.mean()), "p99": float(np.percentile(blocked, 99))}
    return {"samples_per_object": samples_per_object, "rays": rays, "receiver_caster": table}


def gbuffer_ms(manifest, size: int, frames: int, ctx, part: str = "all") -> dict:
    """Median ms per G-buffer frame (``part``: all, mesh draw only, SDF pass only) and covered pixels."""
    from prt.runtime.camera import Camera
    from prt.runtime.gbuffer import GBufferPass

    camera = Camera.from_manifest(manifest)
    with GBufferPass(ctx, manifest, size, size) as gbuffer:
        if part == "mesh":
            gbuffer._sdf_vao = None
        elif part == "sdf":
            gbuffer._vao = None
        gbuffer.render(camera)
        ctx.finish()
        times = []
        for _ in range(frames):
            t0 = time.perf_counter()
            gbuffer.render(camera)
            ctx.finish()
            times.append(1e3 * (time.perf_counter() - t0))
        covered = int(gbuffer.read().covered.sum())
    return {"ms": float(np.median(times)), "frames_ms": times, "covered_pixels": covered, "part": part}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("--image", type=Path, default=Path("docs/mixed_scene.png"))
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--frames", type=int, default=7)
    p.add_argument("--out", type=Path, default=Path("docs/benchmarks/mixed_scene_gbuffer"))
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-mixed-scene-study"))
    p.add_argument("--sun", type=float, nargs=3, default=[0.8, 0.45, 0.3], help="sun direction of the figure's sky light")
    args = p.parse_args(argv)

    import imageio.v3 as iio

    from prt.runtime.files import atomic_write_bytes, atomic_write_json
    from prt.runtime.gl import context_info, create_context
    from prt.runtime.manifest import load_manifest
    from prt.runtime.renderer import Renderer, Scene

    ctx = create_context()
    scene = Scene.load(args.scene / "scene.json")
    from prt.runtime.sh import basis

    light = sky_light(scene.manifest.sh_bands, sun=args.sun, sun_power=4.0, ambient=0.05)
    with Renderer(scene, args.size, args.size, backend="glsl", ctx=ctx) as r:
        r.set_lighting_sh(light)
        image = r.render_srgb()
        transfer = r.render_transfer()
        g = r.gbuffer_image()
    y00 = float(basis(np.array([[0.0, 0.0, 1.0]]), 1)[0, 0])
    visible = np.where(g.covered, np.clip(transfer[..., 0] / y00, 0.0, 1.0), 0.0)
    panel = np.repeat((255 * visible + 0.5).astype(np.uint8)[..., None], 3, axis=2)
    figure = np.concatenate([image[..., :3], np.full((args.size, 8, 3), 255, np.uint8), panel], axis=1)
    atomic_write_bytes(args.image, iio.imwrite("<bytes>", figure, extension=".png"))
    print(f"wrote {args.image}")

    mixed = load_manifest(args.scene / "scene.json")
    geometry = recompose(args.scene)
    twin = load_manifest(mesh_twin(args.scene, geometry, args.work / "mesh"))
    again = regenerated(args.scene, geometry, args.work / "glsl")
    report = {
        "command": " ".join([Path(sys.argv[0]).as_posix()] + (argv if argv is not None else sys.argv[1:])),
        "size": args.size, "frames": args.frames, "gl": context_info(ctx),
        "mixed_gbuffer": gbuffer_ms(mixed, args.size, args.frames, ctx),
        "mixed_mesh_draw_only": gbuffer_ms(mixed, args.size, args.frames, ctx, "mesh"),
        "mixed_sdf_pass_only": gbuffer_ms(mixed, args.size, args.frames, ctx, "sdf"),
        "mesh_gbuffer_same_shapes": gbuffer_ms(twin, args.size, args.frames, ctx),
        "mesh_triangles": twin.geometry.triangles,
    }  # fmt: skip
    if again is not None:
        current = load_manifest(again)
        report["regenerated_glsl_mixed_gbuffer"] = gbuffer_ms(current, args.size, args.frames, ctx)
        report["regenerated_glsl_sdf_pass_only"] = gbuffer_ms(current, args.size, args.frames, ctx, "sdf")
    report["cross_shadows"] = cross_shadows(geometry)
    atomic_write_json(args.out.with_suffix(".json"), report)
    names = list(report["cross_shadows"]["receiver_caster"])
    print("blocked share of the receiver's hemisphere by each caster alone, p99 over samples (mean):")
    print("receiver \\ caster  " + "  ".join(f"{n:>14}" for n in names))
    for receiver, row in report["cross_shadows"]["receiver_caster"].items():
        print(f"{receiver:>18}  " + "  ".join(f"{row[n]['p99']:6.3f} ({row[n]['mean']:.3f})" for n in names))
    for key in [k for k in report if isinstance(report[k], dict) and "ms" in report[k]]:
        print(f"{key}: {report[key]['ms']:.1f} ms per frame at {args.size}x{args.size} ({report[key]['covered_pixels']} covered pixels)")
    print(f"wrote {args.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
