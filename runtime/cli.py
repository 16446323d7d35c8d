"""prt-runtime: view a PRT scene, in a window or headless.

usage: prt-runtime [scene.json] [--backend onnx|glsl] [--size W[xH]] [--headless] [--frames N]
                   [--out DIR] [--envmap NAME|PATH] [--material diffuse|glossy] [--exponent E]

Without a scene it opens the bundled demo scene (Spot).  With a display (and pygame installed:
``pip install "prt-runtime[viewer]"``) it opens a window; without one, or with --headless, it
renders --frames frames along an orbit to PNG files and prints the median FPS and stage times.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from .errors import PRTError

__all__ = ["main", "build_parser", "render_orbit"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="prt-runtime",
        description="Render a precomputed-radiance-transfer scene learnt by small networks.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("scene", nargs="?", default=None, help="scene.json or its folder (default: the bundled demo scene)")
    p.add_argument("--backend", choices=("onnx", "glsl"), default="onnx", help="where the networks run")
    p.add_argument("--size", default="512", help="image size: W or WxH")
    p.add_argument("--headless", action="store_true", help="no window even if a display is available")
    p.add_argument("--frames", type=int, default=30, help="headless: frames along the orbit")
    p.add_argument("--out", type=Path, default=Path("prt_frames"), help="headless: folder for the PNG frames")
    p.add_argument("--envmap", default=None, help="bundled env map name (potsdamer, interior, studio) or an .hdr/.exr path")
    p.add_argument("--material", choices=("diffuse", "glossy"), default=None, help="override the scene's material")
    p.add_argument("--exponent", type=float, default=16.0, help="Phong exponent of the glossy material")
    p.add_argument("--exposure", type=float, default=1.0, help="exposure before tone mapping")
    p.add_argument("--providers", default=None, help="comma-separated ONNX Runtime providers (default: CUDA if present, then CPU)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads of the ONNX backend")
    return p


def _size(text: str) -> tuple[int, int]:
    try:
        parts = [int(v) for v in text.lower().split("x")]
    except ValueError:
        raise PRTError(f"--size: expected W or WxH, got {text!r}") from None
    w, h = (parts[0], parts[0]) if len(parts) == 1 else parts[:2]
    if w < 1 or h < 1 or len(parts) > 2:
        raise PRTError(f"--size: expected positive W or WxH, got {text!r}")
    return w, h


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        from .renderer import Renderer, Scene

        width, height = _size(args.size)
        scene = Scene.load(args.scene)
        providers = args.providers.split(",") if args.providers else None
        window = not args.headless and has_display()
        if window:
            from .viewer import run_window

            return run_window(scene, width, height, args, providers)
        with Renderer(scene, width, height, backend=args.backend, providers=providers, threads=args.threads) as r:
            _apply_options(r, args)
            summary = render_orbit(r, args.frames, args.out, exposure=args.exposure)
    except PRTError as exc:
        print(f"prt-runtime: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("prt-runtime: interrupted", file=sys.stderr)
        return 130
    print(summary)
    return 0


def _apply_options(r, args) -> None:
    if args.envmap:
        r.set_envmap(args.envmap)
    if args.material == "glossy":
        r.set_material("glossy", albedo=r.material.albedo, specular=(0.3, 0.3, 0.3), exponent=args.exponent)
    elif args.material == "diffuse":
        r.set_material("diffuse", albedo=r.material.albedo)


def render_orbit(r, frames: int, out: Path, *, exposure: float = 1.0, warmup: int = 2) -> str:
    """Render ``frames`` views on an orbit about the scene's target into ``out``/frame_NNN.png.

    Returns a summary: median FPS and median milliseconds per stage (warm-up frames excluded).
    """
    import imageio.v3 as iio

    from .files import atomic_write_bytes
    from .shading import to_srgb8

    if frames < 1:
        raise PRTError(f"--frames must be positive, got {frames}")
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PRTError(f"{out}: cannot create the output folder ({exc.strerror})") from None
    start = r.camera
    for i in range(warmup):
        r.set_camera_object(start.orbit(-0.01 * (i + 1)))
        r.render()
    stages: dict[str, list[float]] = {}
    for i in range(frames):
        r.set_camera_object(start.orbit(2 * np.pi * i / frames))
        image = r.render()
        for k, v in r.timings.items():
            stages.setdefault(k, []).append(v)
        atomic_write_bytes(out / f"frame_{i:03d}.png", iio.imwrite("<bytes>", to_srgb8(image, exposure), extension=".png"))
    r.set_camera_object(start)
    med = {k: float(np.median(v)) for k, v in stages.items()}
    fps = 1000.0 / med["frame"]
    parts = ", ".join(f"{k} {v:.1f}" for k, v in med.items() if k != "frame")
    return (
        f"{r.scene.name}: {frames} frames {r.width}x{r.height}, backend {r.backend}: median {fps:.1f} FPS "
        f"({med['frame']:.1f} ms/frame; {parts} ms); wrote {out}/frame_000.png ..."
    )


if __name__ == "__main__":
    sys.exit(main())
