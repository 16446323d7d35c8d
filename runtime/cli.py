"""prt-runtime: view a PRT scene, in a window or headless.

usage: prt-runtime [scene.json] [--backend onnx|glsl] [--size W[xH]] [--headless] [--frames N]
                   [--out DIR] [--envmap NAME|PATH] [--material diffuse|glossy] [--exponent E]
                   [--camera-path PATH.json] [--format png|exr|mp4] [--fps F]
                   [--background envmap|black] [--target-fps F] [--interpolate TOL]
                   [--exposure E|auto] [--object-albedo NAME=R,G,B ...] [--gl-device NAME|INDEX] [--onnx-providers LIST]

Without a scene it opens the bundled demo scene (Spot).  With a display (and pygame installed:
``pip install "prt-runtime[viewer]"``) it opens a window; without one, or with --headless, it
renders --frames frames along an orbit (or the views of --camera-path) to PNG files (linear EXR
files, or an MP4 video with --format) and prints the median FPS and stage times, with the GL
renderer that drew the frames (--gl-device chooses it).
A thin layer over the library: :class:`prt.runtime.viewer.ViewerOptions`,
:func:`prt.runtime.viewer.run_window` and :func:`prt.runtime.orbit.render_orbit`.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .interpolation import DEFAULT_TOLERANCE as DEFAULT_INTERPOLATE, check_tolerance
from .backends import ALL_BACKENDS, BACKENDS
from .backends.onnx import check_providers
from .gl import create_context
from .envmaps import BUNDLED_ENVMAPS
from .checks import finite_array, positive_int
from .errors import InputError, PRTError
from .exposure import parse_exposure
from .materials import parse_object_albedo
from .camera_path import CameraPath, load_camera_path
from .orbit import FORMATS, render_camera_path, render_orbit
from .renderer import Scene
from .viewer import ViewerOptions, run_window

__all__ = ["main", "build_parser", "options_from_args"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="prt-runtime",
        description="Render a precomputed-radiance-transfer scene learnt by small networks.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("scene", nargs="?", default=None, help="scene.json or its folder (default: the bundled demo scene)")
    p.add_argument("--backend", choices=ALL_BACKENDS, default=BACKENDS[0], help="where the networks run (texture: a scene's transfer texture)")
    p.add_argument("--size", default="512", help="image size: W or WxH")
    p.add_argument("--headless", action="store_true", help="no window even if a display is available")
    p.add_argument("--frames", type=int, default=30, help="headless: frames along the orbit")
    p.add_argument("--out", type=Path, default=Path("prt_frames"), help="headless: folder for the PNG frames")
    p.add_argument("--envmap", default=None, help=f"bundled env map name ({', '.join(BUNDLED_ENVMAPS)}) or an .hdr/.exr path")
    p.add_argument("--material", choices=("diffuse", "glossy"), default=None, help="override the scene's material")
    p.add_argument("--exponent", type=float, default=16.0, help="Phong exponent of the glossy material")
    p.add_argument("--object-albedo", action="append", default=[], metavar="NAME=R,G,B",
                   help="albedo of one object of the scene (repeatable; after --material)")
    p.add_argument("--exposure", default=None, metavar="E|auto",
                   help="exposure before tone mapping: a number, or auto (the frame's log-average luminance to middle grey, smoothed across frames); default: auto for a scene (camera inside its bounds, or >= 10 objects), else 1")
    p.add_argument("--onnx-providers", "--providers", dest="providers", default=None, metavar="LIST",
                   help="comma-separated ONNX Runtime providers, e.g. cuda,cpu or tensorrt,cuda,cpu (default: $PRT_ONNX_PROVIDERS, else CUDA if present, then CPU); one this onnxruntime lacks is an error")
    p.add_argument("--gl-device", default=None, metavar="NAME|INDEX",
                   help="headless: the EGL device that draws, an index or a name matched against GL_RENDERER, e.g. nvidia or llvmpipe (default: $PRT_GL_DEVICE, else auto: the GPU where there is one, else llvmpipe)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads of the ONNX backend")
    p.add_argument("--interpolate", type=float, default=DEFAULT_INTERPOLATE, metavar="TOL",
                   help=f"onnx backend: run the networks on a coarse pixel grid and interpolate where the transfer of the neighbours agrees within TOL (relative; default {DEFAULT_INTERPOLATE}); 0: every pixel runs its network")
    p.add_argument("--animate", action="store_true", help="headless, deformable scenes: --frames frames at the scene camera playing the recorded poses (instead of an orbit)")
    p.add_argument("--pose", type=int, default=None, metavar="FRAME", help="headless, deformable scenes: render the orbit at this recorded frame")
    p.add_argument("--camera-path", type=Path, default=None, help="headless: render the views of this camera-path JSON (saved by the viewer's c / o keys)")
    p.add_argument("--format", choices=FORMATS, default="png", help="headless: PNG frames, linear EXR frames, or one MP4 video (--out DIR or FILE.mp4)")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of an MP4")
    p.add_argument("--background", choices=("envmap", "black"), default=None, help="what is drawn where no geometry is (default: the scene's choice)")
    p.add_argument("--target-fps", type=float, default=30.0, help="window: render smaller while the camera moves to hold this (0: always full size)")
    return p


def _size(text: str) -> tuple[int, int]:
    try:
        parts = [int(v) for v in text.lower().split("x")]
    except ValueError:
        raise InputError(f"--size: expected W or WxH, got {text!r}") from None
    w, h = (parts[0], parts[0]) if len(parts) == 1 else parts[:2]
    if w < 1 or h < 1 or len(parts) > 2:
        raise InputError(f"--size: expected positive W or WxH, got {text!r}")
    return w, h


def options_from_args(args: argparse.Namespace) -> ViewerOptions:
    """The viewer's options from parsed flags (InputError, naming the flag, for a bad value)."""
    width, height = _size(args.size)
    positive_int(args.frames, "--frames")
    if args.threads is not None:
        positive_int(args.threads, "--threads")
    exposure = None if args.exposure is None else parse_exposure(args.exposure, "--exposure")
    if not float(finite_array(args.exponent, "--exponent", ())) > 0:
        raise InputError(f"--exponent must be > 0, got {args.exponent}")
    target_fps = float(finite_array(args.target_fps, "--target-fps", (), minimum=0.0))
    object_albedo = tuple(parse_object_albedo(text) for text in args.object_albedo)
    providers = check_providers(args.providers, "--onnx-providers")  # one line here, before any renderer
    if args.gl_device is not None:
        create_context(device=args.gl_device, origin="--gl-device").release()
    return ViewerOptions(
        object_albedo=object_albedo,
        width=width, height=height, backend=args.backend, envmap=args.envmap, material=args.material,
        exponent=args.exponent, exposure=exposure,
        providers=providers, threads=args.threads, gl_device=args.gl_device,
        interpolate=check_tolerance(args.interpolate, "--interpolate"),
        background=None if args.background is None else args.background == "envmap", target_fps=target_fps or None,
    )  # fmt: skip


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        options = options_from_args(args)
        path = load_camera_path(args.camera_path) if args.camera_path is not None else None
        scene = Scene.load(args.scene)
        if not args.headless and has_display() and path is None:
            return run_window(scene, options)
        with options.renderer(scene) as r:
            if args.pose is not None:
                r.set_deformation(frame=args.pose)
            if args.animate:
                deformation = scene.deformation
                if deformation is None:
                    raise InputError(f"{scene.path}: --animate needs a deformable scene (built with prt-train --deform)")
                frames = positive_int(args.frames, "--frames")
                poses = [round(i * (deformation.frame_count - 1) / max(frames - 1, 1)) for i in range(frames)]
                summary = render_camera_path(r, CameraPath((r.camera,), frames), args.out, exposure=options.exposure, fmt=args.format,
                                             fps=args.fps, poses=poses)  # fmt: skip
            elif path is not None:
                summary = render_camera_path(r, path, args.out, exposure=options.exposure, fmt=args.format, fps=args.fps)
            else:
                summary = render_orbit(r, args.frames, args.out, exposure=options.exposure, fmt=args.format, fps=args.fps)
    except PRTError as exc:
        print(f"prt-runtime: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("prt-runtime: interrupted", file=sys.stderr)
        return 130
    print(summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
