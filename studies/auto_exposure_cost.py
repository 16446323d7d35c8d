"""What auto exposure adds to a frame: the GPU reduction (glsl) and numpy (onnx) against the frame.

usage: python studies/auto_exposure_cost.py [--scene scene.json] [--size 512] [--views 6]
                                            [--json OUT] [--md OUT]

Per backend, ``--views`` views of the scene's orbit, each drawn (networks run: a new view) and
then its auto exposure computed (:meth:`Renderer.frame_exposure`) and timed apart; the glsl
backend's GPU reduction (``shaders/log_luminance.frag``, 16 x 16 tiles read back) also against
its reference twin on the same frame (read the frame back, then numpy ``auto_exposure`` over
``covered_mask()``).  Reported: medians in ms, the exposure's share of the frame, the GPU
reduction's time as a ratio of the read-back twin's, and the largest relative difference of the
two exposures.  One process, the views taking turns, with the CPU named.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prt.bench.provenance import cpu_label, provenance
from prt.runtime.camera import orbit_views
from prt.runtime.exposure import auto_exposure
from prt.runtime.files import atomic_write_bytes
from prt.runtime.interpolation import DEFAULT_TOLERANCE
from prt.runtime.renderer import Renderer, Scene


def measure(scene, backend: str, size: int, views: int) -> dict:
    interpolate = DEFAULT_TOLERANCE if backend == "onnx" else None
    with Renderer(scene, size, size, backend=backend, interpolate=interpolate) as r:
        cameras = orbit_views(r.camera, views)
        r.set_camera_object(cameras[0].orbit(-0.01))  # warm-up: sessions, programs
        r.draw()
        r.frame_exposure()
        frame, exposure, twin, diff = [], [], [], []
        for cam in cameras:
            r.set_camera_object(cam)
            r.draw()
            frame.append(r.timings["frame"])
            t0 = time.perf_counter()
            e = r.frame_exposure()
            exposure.append(1e3 * (time.perf_counter() - t0))
            if backend != "onnx":
                t0 = time.perf_counter()
                image = r.read_frame()
                e_twin = auto_exposure(image, r.covered_mask())
                twin.append(1e3 * (time.perf_counter() - t0))
                diff.append(abs(e / e_twin - 1.0))
    med = lambda v: float(np.median(v))  # noqa: E731
    out = {"frame_ms": med(frame), "exposure_ms": med(exposure), "exposure_share": med(exposure) / med(frame), "views": views}
    if twin:
        out |= {"readback_numpy_ms": med(twin), "gpu_over_readback": med(exposure) / med(twin), "max_rel_diff": max(diff)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=None, help="scene.json (default: the bundled demo)")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--views", type=int, default=6)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    scene = Scene.load(args.scene)
    result = {"provenance": provenance(), "cpu": cpu_label(), "scene": scene.name, "size": args.size,
              "backends": {b: measure(scene, b, args.size, args.views) for b in ("onnx", "glsl")}}  # fmt: skip
    lines = [f"Auto exposure's cost, {scene.name} at {args.size} x {args.size}, {args.views} views, medians ({result['cpu']}; "
             f"{result['provenance']['date']}; `{result['provenance']['command']}`)", "",
             "| backend | frame ms | exposure ms | share of the frame | GPU / read-back + numpy | max rel. diff |", "|---|---|---|---|---|---|"]  # fmt: skip
    for b, m in result["backends"].items():
        gpu = f"{m['gpu_over_readback']:.2f}x ({m['readback_numpy_ms']:.2f} ms)" if "gpu_over_readback" in m else "n/a (CPU frame)"
        rel = f"{m['max_rel_diff']:.1e}" if "max_rel_diff" in m else "n/a"
        lines.append(f"| {b} | {m['frame_ms']:.1f} | {m['exposure_ms']:.2f} | {100 * m['exposure_share']:.1f} % | {gpu} | {rel} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.json:
        atomic_write_bytes(args.json, (json.dumps(result, indent=1) + "\n").encode())
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
