"""Interreflection on ray-traced samples: cost per stage, energy per bounce, colour bleeding.

usage: python studies/interreflection_study.py [MESH] [--samples N] [--rays R] [--bounces B] [--json OUT]

MESH defaults to the shared Cornell box (tests/data copy, with its MTL).  The study samples the
surface as the precompute does, computes the direct transfer (``compute_transfer``), traces the
bounce rays once (``trace_bounce_rays``: hit points and nearest samples) and applies the bounce
operator (``interreflect``) for 0..B bounces with the albedos of the mesh's own materials.
Reported, under the bundled env maps:

- seconds of the direct transfer, of the bounce rays and of each bounce (the precompute-time
  target: 2 bounces <= 3x the direct-only time);
- the mean outgoing radiance each bounce adds, relative to the direct-only radiance (what
  chooses the default N: the first bounce whose addition falls under 1 %);
- colour bleeding: the floor's indirect red/green ratio next to the red wall and next to the
  green one (2 bounces, under a constant white sky; upward-facing floor samples).

Transfer here is the samples' ray-traced transfer; the networks, runtime and benchmark
reference do not carry RGB interreflected transfer yet.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prt.runtime.envmap import load_envmap_sh
from prt.runtime.envmaps import bundled_envmap_path
from prt.runtime.shading import Material
from prt.train.inputs.geometry import load_geometry
from prt.train.transport.interreflection import BOUNCE_RAYS, interreflect, trace_bounce_rays
from prt.train.inputs.materials import mesh_materials
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.transfer import compute_transfer

CORNELL = Path(__file__).resolve().parents[1] / "tests" / "data" / "CornellBox-Original.obj"
LIGHTS = ("studio", "potsdamer", "interior")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mesh", nargs="?", default=str(CORNELL))
    p.add_argument("--samples", type=int, default=40000)
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--bounces", type=int, default=4)
    p.add_argument("--bounce-rays", type=int, default=BOUNCE_RAYS)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)

    geometry = load_geometry(args.mesh)
    default = {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}
    found = {m.object: m.material for m in mesh_materials(args.mesh, geometry.object_names, default, print)}
    # Bounces are diffuse: a glossy file material bounces its albedo (Kd) only.
    object_albedo = np.array([found.get(n, Material(albedo=(0.7, 0.7, 0.7))).albedo for n in geometry.object_names])
    face_albedo = object_albedo[geometry.object_ids]
    samples = sample_surface(geometry, args.samples, seed=0)

    t0 = time.perf_counter()
    direct = compute_transfer(geometry, samples.points, samples.normals, rays=args.rays, threads=2)
    t_direct = time.perf_counter() - t0
    t0 = time.perf_counter()
    rays = trace_bounce_rays(geometry.mesh, samples.points, samples.normals, rays=args.bounce_rays, seed=0, workers=2)
    t_rays = time.perf_counter() - t0
    totals, t_bounce = [], []
    for n in range(args.bounces + 1):
        t0 = time.perf_counter()
        totals.append(interreflect(direct, rays, face_albedo, n))
        t_bounce.append(time.perf_counter() - t0)

    own_albedo = face_albedo[samples.face_index]  # receivers: their own albedo
    report = {"mesh": args.mesh, "samples": args.samples, "rays": args.rays,
              "seconds": {"direct": t_direct, "bounce_rays": t_rays, "bounces": t_bounce},
              "added_radiance": {}, "bleeding": {}}  # fmt: skip
    for light_name in LIGHTS:
        light = load_envmap_sh(bundled_envmap_path(light_name), 4)  # (16, 3)
        radiance = [own_albedo * np.einsum("snc,nc->sc", t, light) for t in totals]
        base = float(np.mean(radiance[0]))
        report["added_radiance"][light_name] = [float(np.mean(radiance[k] - radiance[k - 1])) / base for k in range(1, len(radiance))]
    # Floor samples near the left (red) and right (green) walls; indirect light only, under studio.
    if "floor" in geometry.object_names:
        floor = (samples.object_ids == geometry.object_names.index("floor")) & (samples.normals[:, 1] > 0)
        x = samples.points[:, 0]
        light = np.zeros((16, 3))
        light[0] = np.sqrt(4 * np.pi)  # a constant white sky: the walls' own colours only
        indirect = np.einsum("snc,nc->sc", totals[min(2, args.bounces)] - totals[0], light)
        for side, mask in (("near_left_wall", floor & (x < x[floor].min() + 0.25)), ("near_right_wall", floor & (x > x[floor].max() - 0.25))):
            rgb = indirect[mask].mean(axis=0)
            report["bleeding"][side] = {"indirect_rgb": rgb.tolist(), "red_over_green": float(rgb[0] / max(rgb[1], 1e-12))}
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
