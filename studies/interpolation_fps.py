"""Frame rate of the demo with screen-space transfer interpolation against every-pixel inference,
as ratios in one run.

usage: python studies/interpolation_fps.py [--scene scene.json] [--size 512] [--views 30]
                                                 [--rounds 3] [--tolerances 0 0.05 0.1 0.2] [--json OUT]
                                                 [--figure OUT.png] [--against OTHER/scene.json]

One renderer per tolerance (0: every covered pixel runs its network), all on one GL context, the
scene's light and background as ``make demo`` draws them; the orbit's views are rendered round
after round, the renderers taking turns at each view so that machine noise hits them alike.
Reported per tolerance: the median frame time and FPS, the median stage times, the share of
covered pixels that ran a network, the speed-up over tolerance 0, and the PSNR of its frames
against tolerance 0's (the interpolation's own error; the error against the ray-traced reference
is ``prt-bench --interpolate``'s, see README "The demo").  ``--figure``: view 0 at every pixel, with
the default tolerance, the pixels that ran a network, and the tone-mapped difference x 20.
``--against``: another build of the same scene (e.g. the demo rebuilt with other networks), its
renderers taking turns with the first scene's at every view; its rows give the speed-up over the
first scene's tolerance 0 (their PSNR is against its own tolerance 0).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from prt.runtime.camera import orbit_views
from prt.runtime.files import atomic_write_bytes
from prt.runtime.gl import create_context
from prt.runtime.renderer import Renderer, Scene


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """Over the given pixels, peak: the reference's largest value."""
    mse = float(np.mean((image - reference) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(float(reference.max()) ** 2 / mse)


def figure(exact: Renderer, camera, path: Path) -> None:
    """Every pixel | interpolated (the default tolerance) | pixels that ran a network | |difference| x 20."""
    import imageio.v3 as iio

    from prt.runtime.interpolation import DEFAULT_TOLERANCE, TransferInterpolator
    from prt.runtime.shading import to_srgb8

    exact.set_camera_object(camera)
    full = to_srgb8(exact.render())
    engine = exact._backend().engine
    position, normal = (a.copy() for a in exact.gbuffer.read_targets())
    with Renderer(exact.scene, exact.width, exact.height, ctx=exact.ctx, interpolate=DEFAULT_TOLERANCE) as r:
        r.set_camera_object(camera)
        interpolated = to_srgb8(r.render())
    sampler = TransferInterpolator(DEFAULT_TOLERANCE)
    try:
        result = sampler.run(position, normal, engine.infer_sorted, engine.n)
    finally:
        sampler.close()
    mask = np.zeros(exact.width * exact.height, np.uint8)
    mask[result.covered] = 90
    mask[result.covered[result.inferred]] = 255
    mask = np.repeat(mask.reshape(exact.height, exact.width, 1), 3, axis=2)
    diff = np.clip(20 * np.abs(full.astype(np.int16) - interpolated.astype(np.int16)), 0, 255).astype(np.uint8)
    data = iio.imwrite("<bytes>", np.concatenate([full, interpolated, mask, diff], axis=1), extension=".png")
    atomic_write_bytes(path, data)
    print(f"figure: {path} ({100 * result.fraction:.0f} % of the covered pixels ran a network at tolerance {DEFAULT_TOLERANCE})")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", type=Path, default=None, help="scene.json (default: the bundled demo)")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--views", type=int, default=30)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.2])
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--figure", type=Path, default=None)
    p.add_argument("--against", type=Path, default=None, help="another build of the scene, measured in the same run")
    args = p.parse_args(argv)
    tolerances = sorted(set(args.tolerances) | {0.0})
    scene = Scene.load(args.scene)
    scenes = [scene] + ([Scene.load(args.against)] if args.against is not None else [])
    ctx = create_context()
    keys = [(k, t) for k in range(len(scenes)) for t in tolerances]  # (scene, tolerance); scene 0's keys alone without --against
    renderers = {key: Renderer(scenes[key[0]], args.size, args.size, ctx=ctx, interpolate=key[1] or None) for key in keys}
    cameras = orbit_views(renderers[(0, 0.0)].camera, args.views)
    try:
        for r in renderers.values():
            for i in range(args.warmup):
                r.set_camera_object(cameras[0].orbit(-0.01 * (i + 1)))
                r.render()
        frames = {key: [] for key in keys}
        stages = {key: {} for key in keys}
        fractions = {key: [] for key in keys}
        errors = {key: [] for key in keys}
        for _ in range(args.rounds):
            for camera in cameras:
                images = {}
                for key, r in renderers.items():
                    r.set_camera_object(camera)
                    t0 = time.perf_counter()
                    images[key] = r.render()
                    frames[key].append(1e3 * (time.perf_counter() - t0))
                    for k, v in r.timings.items():
                        stages[key].setdefault(k, []).append(v)
                    fractions[key].append(r.stats["network_fraction"])
                for k in range(len(scenes)):
                    covered = renderers[(k, 0.0)].gbuffer_image().covered  # (not timed) the pixels the networks shade
                    for t in tolerances:
                        errors[(k, t)].append(psnr(images[(k, t)][covered], images[(k, 0.0)][covered]))
        if args.figure is not None:
            figure(renderers[(0, 0.0)], cameras[0], args.figure)
    finally:
        for r in renderers.values():
            r.close()
        ctx.release()
    base = float(np.median(frames[(0, 0.0)]))
    rows = []
    for k, t in keys:
        ms = float(np.median(frames[(k, t)]))
        rows.append({
            **({"scene": str(scenes[k].path)} if len(scenes) > 1 else {}),
            "tolerance": t, "frame_ms": round(ms, 2), "fps": round(1e3 / ms, 2), "speedup": round(base / ms, 3),
            "network_fraction": round(float(np.median(fractions[(k, t)])), 4),
            "psnr_vs_every_pixel_db": None if t == 0 else round(float(np.median(errors[(k, t)])), 2),
            "psnr_vs_every_pixel_min_db": None if t == 0 else round(float(np.min(errors[(k, t)])), 2),
            "stages_ms": {name: round(float(np.median(v)), 2) for name, v in stages[(k, t)].items() if name != "frame"},
        })  # fmt: skip
        which = f"{scenes[k].path}: " if len(scenes) > 1 else ""
        print(f"{which}tolerance {t:g}: {1e3 / ms:.1f} FPS ({ms:.1f} ms, {base / ms:.2f}x), networks on {100 * rows[-1]['network_fraction']:.0f} % "
              f"of the covered pixels" + ("" if t == 0 else f", {rows[-1]['psnr_vs_every_pixel_db']} dB against every pixel") +
              "; " + ", ".join(f"{name} {v}" for name, v in rows[-1]["stages_ms"].items()))  # fmt: skip
    if args.json is not None:
        report = {"scene": str(scene.path), "size": args.size, "views": args.views, "rounds": args.rounds, "rows": rows,
                  "command": "python studies/interpolation_fps.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:])}  # fmt: skip
        atomic_write_bytes(args.json, (json.dumps(report, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
