"""Rebuild the demo scene shipped in the package (runtime/data/demo): Keenan Crane's Spot
(public domain) standing on a round ground plane that receives its soft shadow, lit by a
bundled CC0 env map that is also drawn as the background; networks of the default size rule
(per segment the cheapest ladder size as accurate as k = 64, l = 4) trained 2000 steps each.

usage: python scripts/build_demo_scene.py [--work DIR] [--skip-train]

Writes a combined OBJ (Spot + a ground disc, an open surface and so two-sided), runs
prt-train on it into a work folder (cached: a rerun only re-exports), then copies only what
the runtime needs (scene.json, geometry.npz compressed, segments/*, the env map) into
runtime/data/demo and turns the env-map background on.  Precompute about 25 s on 2 cores; the
fits (k = 64, l = 4 first, then smaller sizes while they stay as accurate) a few minutes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "runtime" / "data" / "demo"
SPOT = ROOT / "tests" / "data" / "spot.obj"
ENVMAP = ROOT / "runtime" / "data" / "envmaps" / "potsdamer_platz_256.hdr"
GROUND_RADIUS = 1.4  # Spot's units; the disc's area is about 1.5x Spot's, so Spot keeps most samples
GROUND_SIDES = 48
CAMERA = {"eye": [1.45, 0.55, -2.1], "target": [0.0, -0.12, 0.0], "up": [0.0, 1.0, 0.0], "fov": 40.0}  # scene space


def combined_obj(spot: Path) -> str:
    """Spot (object ``spot``) on a ground disc (object ``ground``) just below its lowest vertex."""
    lines = spot.read_text().splitlines()
    vertices = np.array([ln.split()[1:4] for ln in lines if ln.startswith("v ")], dtype=np.float64)
    low = vertices[:, 1].min() - 0.002  # just under the hooves: no coplanar faces
    cx, cz = (vertices[:, 0].min() + vertices[:, 0].max()) / 2, (vertices[:, 2].min() + vertices[:, 2].max()) / 2
    out = ["# Spot (Keenan Crane, public domain) on a ground disc; written by scripts/build_demo_scene.py", "o spot"]
    out += [ln for ln in lines if ln.startswith(("v ", "f "))]
    n = len(vertices)
    out.append("o ground")
    out.append(f"v {cx:.6f} {low:.6f} {cz:.6f}")
    for k in range(GROUND_SIDES):
        a = 2 * math.pi * k / GROUND_SIDES
        out.append(f"v {cx + GROUND_RADIUS * math.cos(a):.6f} {low:.6f} {cz + GROUND_RADIUS * math.sin(a):.6f}")
    centre = n + 1
    for k in range(GROUND_SIDES):  # counter-clockwise seen from above: the normal points up
        a, b = centre + 1 + k, centre + 1 + (k + 1) % GROUND_SIDES
        out.append(f"f {centre} {b} {a}")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    from prt.export.manifest import write_manifest
    from prt.runtime.manifest import load_manifest
    from prt.train.train_cli import main as prt_train

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-demo-build"))
    p.add_argument("--skip-train", action="store_true", help="only copy a finished build in --work into the package")
    args = p.parse_args(argv)
    args.work.parent.mkdir(parents=True, exist_ok=True)
    obj = args.work.parent / "prt-demo-spot-ground.obj"
    obj.write_text(combined_obj(SPOT))
    spec = args.work.parent / "prt-demo-spec.json"
    spec.write_text(json.dumps({
        "geometry": str(obj),
        "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]},
        "camera": CAMERA,
    }))  # fmt: skip
    rc = 0 if args.skip_train else prt_train(
        [
            str(spec),
            "-o", str(args.work),
            "--name", "spot",
            "--samples", "300000",
            "--rays", "512",
            "--segments", "4",
            "--steps", "2000",  # the default network size rule: per segment the cheapest as accurate as k = 64, l = 4
            "--glsl-layout", "auto",  # the compact GLSL (prt.export.glsl_compact)
            "--bounces", "0",  # the demo stays direct-only (the paper's transfer)
            "--no-progress",
        ]
    )  # fmt: skip
    if rc != 0:
        return rc
    demo = DEMO.with_name("demo.new")  # staged beside, swapped in at the end
    if demo.exists():
        shutil.rmtree(demo)
    (demo / "segments").mkdir(parents=True)
    for name in ("scene.json", "build.json"):
        shutil.copy2(args.work / name, demo / name)
    with np.load(args.work / "geometry.npz") as geometry:  # the same arrays, compressed
        np.savez_compressed(demo / "geometry.npz", **geometry)
    for f in sorted((args.work / "segments").iterdir()):
        shutil.copy2(f, demo / "segments" / f.name)
    shutil.copy2(ENVMAP, demo / "envmap.hdr")
    manifest = load_manifest(demo)  # the map lights the scene (its SH stays too) and is drawn behind it
    manifest.lighting = dataclasses.replace(manifest.lighting, envmap=demo / "envmap.hdr", background=True)
    manifest.camera = dataclasses.replace(manifest.camera, **{k: np.asarray(v, dtype=np.float64) if k != "fov" else v for k, v in CAMERA.items()})
    manifest.raw = None
    write_manifest(demo / "scene.json", manifest)
    (demo / "LICENSE.md").write_text(
        "# Demo scene\n\nSpot by Keenan Crane, released into the public domain (see tests/data/LICENSES.md), on a\n"
        "ground disc added by the build script. envmap.hdr is potsdamer_platz (Poly Haven, CC0), as bundled\n"
        "in runtime/data/envmaps (see its LICENSE.md). Networks trained with `python scripts/build_demo_scene.py`.\n"
    )
    if DEMO.exists():
        shutil.rmtree(DEMO)
    demo.rename(DEMO)
    size = sum(f.stat().st_size for f in DEMO.rglob("*") if f.is_file())
    print(f"demo scene: {DEMO} ({size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
