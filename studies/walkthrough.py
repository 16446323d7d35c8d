"""A walkthrough video of a scene's interior, rendered headless from a camera path, its frame times recorded.

usage: python studies/walkthrough.py SCENE [--camera-path PATH.json] [--size 1280x720] [--frames 90]
                                     [--backend onnx|glsl] [--exposure auto|E] [--out walk.mp4]
                                     [--json OUT] [--md OUT]

Without ``--camera-path`` the walk is generated (:func:`straight_walk`): level, at 40 % of the
scene box's height, along its longer horizontal axis from 15 % to 85 % of it, from the end nearer
the scene's camera, looking ahead (no
collision: in a building it goes through walls, which the interior near plane shows as they are).
The frames go through :func:`prt.runtime.orbit.render_camera_path` (``prt-runtime --headless
--camera-path ... --format mp4``): rendered back to back, auto exposure smoothed along the path at
``1 / fps``; recorded: the median frame time and FPS, the stages, the exposure range, the video's
bytes, the CPU and the command.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import cpu_label, provenance
from prt.runtime.camera import Camera, scene_box
from prt.runtime.camera_path import CameraPath, load_camera_path, save_camera_path
from prt.runtime.files import atomic_write_bytes
from prt.runtime.orbit import render_camera_path
from prt.runtime.renderer import Renderer, Scene


def straight_walk(manifest, frames: int) -> CameraPath:
    """A level walk through the scene box (module docstring); scene units, +Y up."""
    lo, hi = scene_box(manifest)
    size = hi - lo
    axis = 0 if size[0] >= size[2] else 2
    y = lo[1] + 0.4 * size[1]
    start, end = lo + 0.15 * size, lo + 0.85 * size
    mid = (lo + hi) / 2
    a = np.array([mid[0], y, mid[2]])
    b = a.copy()
    a[axis], b[axis] = start[axis], end[axis]
    if abs(manifest.camera.eye[axis] - b[axis]) < abs(manifest.camera.eye[axis] - a[axis]):
        a, b = b, a  # enter from the side the scene's camera looks from
    ahead = (b - a) / np.linalg.norm(b - a)
    keys = tuple(Camera(eye, eye + ahead, (0.0, 1.0, 0.0), 60.0) for eye in (a, b))
    return CameraPath(keys, frames)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--camera-path", type=Path, default=None)
    p.add_argument("--size", default="1280x720")
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--backend", default="onnx")
    p.add_argument("--exposure", default="auto")
    p.add_argument("--out", type=Path, default=None, help="the MP4 (default: a temporary file, removed)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    p.add_argument("--figure", type=Path, default=None, help="PNG: the path's first view at exposure 1 beside auto exposure")
    p.add_argument("--note", default="", help="a line for the record (what the scene is)")
    args = p.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    scene = Scene.load(args.scene)
    path = load_camera_path(args.camera_path) if args.camera_path else straight_walk(scene.manifest, args.frames)
    figure_exposure = None
    with tempfile.TemporaryDirectory() as tmp, Renderer(scene, width, height, backend=args.backend) as r:
        out = args.out or Path(tmp) / "walk.mp4"
        busy, t0 = busy_seconds(), time.perf_counter()
        summary = render_camera_path(r, path, out, exposure=args.exposure, fmt="mp4", fps=args.fps)
        others = other_cpu_share(busy, time.perf_counter() - t0)  # other processes' share of the cores meanwhile
        video_bytes = out.stat().st_size
        if args.figure:  # the first view: exposure 1 (left) and its auto exposure (right)
            from prt.runtime.camera import fit_near
            from prt.runtime.shading import to_srgb8

            cameras = path.cameras()
            r.set_camera_object(fit_near(cameras[0], scene_box(scene.manifest)))
            image = r.render()
            figure_exposure = r.frame_exposure(image)
            step = 2 if width > 640 else 1  # a figure for the docs: every second pixel of a large frame
            panels = [to_srgb8(image, 1.0)[::step, ::step], to_srgb8(image, figure_exposure)[::step, ::step]]
            atomic_write_bytes(args.figure, iio.imwrite("<bytes>", np.concatenate(panels, axis=1), extension=".png"))
        if args.json and args.camera_path is None:
            save_camera_path(args.json.with_suffix(".path.json"), path)  # the walk, to render again
    result = {"provenance": provenance(), "cpu": cpu_label(), "scene": scene.name, "segments": len(scene.manifest.segments),
              "size": [width, height], "frames": summary.frames, "backend": args.backend, "renderer": summary.renderer,
              "median_ms": summary.median_ms, "fps": summary.fps, "exposure": summary.exposure, "video_bytes": video_bytes,
              "write_s": summary.write_s, "other_cpu_share": others, "note": args.note, "figure_exposure": figure_exposure, "camera_path": str(args.camera_path) if args.camera_path else "straight_walk"}  # fmt: skip
    stages = ", ".join(f"{k} {v:.1f}" for k, v in summary.median_ms.items() if k != "frame")
    text = (f"Walkthrough of {scene.name} ({result['segments']} segments) at {width} x {height}, {summary.frames} frames, "
            f"backend {args.backend} on {summary.renderer} ({result['cpu']}; {result['provenance']['date']}; "
            f"`{result['provenance']['command']}`; other processes used {others if others is not None else 'n/a'} of the cores)\n\n"
            + (f"{args.note}\n\n" if args.note else "") +
            f"| median frame ms | FPS | stages (ms) | exposure | video |\n|---|---|---|---|---|\n"
            f"| {summary.median_ms['frame']:.1f} | {summary.fps:.2f} | {stages} | {summary.exposure} | {video_bytes / 1e6:.2f} MB |\n")  # fmt: skip
    print(text)
    if args.json:
        atomic_write_bytes(args.json, (json.dumps(result, indent=1) + "\n").encode())
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
