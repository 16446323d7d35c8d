"""Runtime frame timings: per-stage milliseconds, the share of a frame spent outside the
network, and the speed-up of relight-only frames (cached transfer, no network).

usage: python studies/runtime_bench.py [--scene scene.json] [--size 512] [--views 30] [--json OUT]

Without --scene it builds (once, cached in /tmp/prt-runtime-bench) the paper-size network
(k = 64, l = 4) on the bundled Spot, 300k samples.  Both backends, diffuse, after warm-up;
medians over --views orbit views, then --views relight-only frames (the env map turns).
Targets (issue 4, 512x512, k = 64): time outside the network <= 15 % of a frame; relight-only
frames >= 20x faster than full frames.  Absolute FPS on llvmpipe / 2 CPU cores is not a target.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from common import ROOT, write_figures  # beside this script (its folder is sys.path[0])

from prt.runtime.renderer import Renderer, Scene


def build_default_scene(work: Path) -> Path:
    scene = work / "scene.json"
    if not scene.is_file():
        cmd = [sys.executable, "-m", "prt.train.train_cli", str(ROOT / "tests" / "data" / "spot.obj"), "-o", str(work),
               "--samples", "300000", "--segments", "4", "--hidden", "64", "--layers", "4", "--no-analytic", "--no-progress"]  # fmt: skip
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return scene


def rotation_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", type=Path, default=None)
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--views", type=int, default=30)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    scene_path = args.scene or build_default_scene(Path("/tmp/prt-runtime-bench"))
    scene = Scene.load(scene_path)
    archs = sorted({f"k{s.architecture['hidden']}-l{s.architecture['layers']}" for s in scene.network_segments})
    results = {}
    for backend in ("onnx", "glsl"):
        with Renderer(scene, args.size, args.size, backend=backend) as r:
            start = r.camera
            for i in range(3):  # warm-up: sessions, shader compilation, caches
                r.set_camera_object(start.orbit(0.01 * i))
                r.render()
            full, stages = [], {}
            for i in range(args.views):
                r.set_camera_object(start.orbit(2 * np.pi * i / args.views))
                r.render()
                full.append(r.timings["frame"])
                for k, v in r.timings.items():
                    stages.setdefault(k, []).append(v)
            covered = int(r.gbuffer_image().covered.sum())
            relight = []
            for i in range(args.views):
                r.set_envmap("potsdamer", rotation=rotation_y(0.2 * i))
                r.render()
                relight.append(r.timings["frame"])
        med = {k: float(np.median(v)) for k, v in stages.items()}
        network = med.get("inference", med.get("network", 0.0))
        frame = float(np.median(full))
        results[backend] = {
            "frame_ms": round(frame, 2),
            "fps": round(1000 / frame, 2),
            "stages_ms": {k: round(v, 2) for k, v in med.items() if k != "frame"},
            "network_ms": round(network, 2),
            "outside_network_share": round(1 - network / frame, 3),
            "relight_frame_ms": round(float(np.median(relight)), 2),
            "relight_speedup": round(frame / float(np.median(relight)), 1),
            "covered_pixels": covered,
        }
        print(f"{backend}: {json.dumps(results[backend])}")
    figures = {"scene": str(scene_path), "networks": archs, "size": args.size, "views": args.views, "backends": results}
    print(json.dumps(figures, indent=2))
    for b, res in results.items():
        print(
            f"{b}: {res['fps']} FPS, network {res['network_ms']} ms of {res['frame_ms']} ms "
            f"({100 * res['outside_network_share']:.0f} % outside; target <= 15 %), relight-only {res['relight_speedup']}x faster (target >= 20x)"
        )
    write_figures(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
