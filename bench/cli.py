"""Speed against error of the PRT renderer, with baselines, precision variants and the machine limit.

usage::

    prt-bench scene.json [more scenes] [--json out.json] [--md out.md]
        [--plot out.png] [--views 30 | --cameras views.json] [--exposure 1|auto] [--size 512 [256 ...]] [--ref-rays 1024] [--ref-rays-max 4096]
        [--ref-hit-rays 64] [--ref-hit-rays-max 1024] [--ref-budget 3600] [--baseline-rays N] [--warmup 3]
        [--reference ours|mitsuba] [--mitsuba-spp 1024] [--mitsuba-views 3] [--mitsuba-variant auto]
        [--precisions fp32 fp16 fp16-mlp int8] [--interpolate TOL ...] [--backends onnx glsl vertex texture probes] [--texture-size N ...] [--cache DIR]
        [--gemm-size 4096] [--blas-threads N] [--config-budget SECONDS] [--packing-views N]
        [--images DIR] [--fresh] [--cluster auto|ADDRESS] [--gl-device NAME|INDEX]

What is measured: :mod:`prt.bench.scene_bench`; the report's format: :mod:`prt.bench.report`.
Every scene is checked before anything is measured; a scene that fails (then or while it is
measured) is reported on stderr, one line each, and left out; the reports are written for the
rest, and the exit status is 2.  Also ``python -m prt.bench.cli``.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

# Everything else is imported when the command runs (after :func:`_load`), so that a runtime-only
# install (no [train] extra: scipy, scikit-image, trimesh, ...) gets one line saying what to install.

__all__ = ["parse_args", "main"]


def parse_args(argv=None) -> argparse.Namespace:
    """The command line's options, checked (``fp32`` is always measured: the others are compared with it)."""
    from prt.bench.bounce_reference import HIT_RAYS, HIT_TRANSFER_RAYS
    from prt.export.precision import PRECISIONS
    from prt.train.executor import add_cluster_argument

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+", type=Path, help="scene.json files (or their folders)")
    p.add_argument("--json", type=Path, default=None, help="write the JSON report here")
    p.add_argument("--md", type=Path, default=None, help="write the Markdown table here")
    p.add_argument("--plot", type=Path, default=None, help="write the FPS-PSNR plot (PNG) here")
    p.add_argument("--views", type=int, default=30, help="orbit views per configuration (default 30)")
    p.add_argument("--cameras", type=Path, default=None, metavar="FILE",
                   help='render the views a JSON file gives instead of the orbit: {"views": [{"eye": [x, y, z], "target": [x, y, z], '
                        '"fov": degrees}, ...]} in the scene\'s normalised space (scene.json\'s camera convention), views inside '
                        'the scene included (replaces --views)')  # fmt: skip
    p.add_argument("--exposure", type=_exposure, default=1.0, metavar="auto|E",
                   help="the exposure every image is tone-mapped and scored at: a number, or auto: per view and material the "
                        "exposure auto-exposure gives the reference's frame (interiors; default 1)")  # fmt: skip
    p.add_argument("--size", type=int, nargs="+", default=[512], help="image sizes, square (default 512)")
    p.add_argument("--ref-rays", type=int, default=1024, help="rays per pixel of the reference (default 1024)")
    p.add_argument("--ref-rays-max", type=int, default=4096, metavar="N",
                   help="more reference rays, up to N, where the reference's noise is not 6 dB above the best PSNR (default 4096)")
    p.add_argument("--ref-hit-rays-max", type=int, default=1024, metavar="N",
                   help="scenes with bounces: more bounce rays per pixel, up to N, likewise (default 1024)")
    p.add_argument("--ref-budget", type=float, default=3600.0, metavar="SECONDS",
                   help="time the reference of one scene and size may take, predicted from view 0's: rays are raised only "
                        "within it (default 3600; 0: no limit)")  # fmt: skip
    p.add_argument("--ref-hit-rays", type=int, default=HIT_RAYS, metavar="N",
                   help=f"scenes with bounces: bounce rays per pixel of the reference's indirect light (default {HIT_RAYS}); its noise "
                        "is usually the reference's floor there")  # fmt: skip
    p.add_argument("--ref-hit-transfer-rays", type=int, default=HIT_TRANSFER_RAYS, metavar="N",
                   help=f"scenes with bounces: rays of the direct transfer traced at each bounce hit (default {HIT_TRANSFER_RAYS})")
    p.add_argument("--baseline-rays", type=int, default=None, metavar="N",
                   help="rays per vertex / texel of the vertex and texture baselines' direct transfer and bounces, e.g. the "
                        "build's own --rays, so a quieter reference does not also raise the baselines (default: --ref-rays)")  # fmt: skip
    p.add_argument("--equal-bytes", action="store_true",
                   help="also measure the vertex baseline at the build's bytes: per-vertex PRT of the mesh decimated until its "
                        "transfer takes the networks' fp32 bytes, resampled onto the full mesh (the paper's storage argument)")
    p.add_argument("--warmup", type=int, default=3, help="frames before timing each configuration (default 3)")
    p.add_argument("--reference", choices=("ours", "mitsuba"), default="ours",
                   help="mitsuba: also path-trace --mitsuba-views views with Mitsuba 3 (the [mitsuba] extra) and compare every "
                        "configuration and our reference with it, diffuse with per-object albedos (default: ours only)")  # fmt: skip
    p.add_argument("--mitsuba-spp", type=int, default=1024, metavar="N", help="paths per pixel of Mitsuba's images (default 1024)")
    p.add_argument("--mitsuba-views", type=int, default=3, metavar="N", help="views compared with Mitsuba, spread over the orbit (default 3)")
    p.add_argument("--mitsuba-variant", choices=("auto", "llvm_ad_rgb", "scalar_rgb"), default="auto",
                   help="auto: llvm_ad_rgb where a libLLVM works (DRJIT_LIBLLVM_PATH or Debian's libllvm19), else scalar_rgb")
    p.add_argument("--packing-views", type=int, default=None, metavar="N",
                   help="views of the naive-vs-packed baseline, spread over the orbit (default: all; the naive path "
                        "runs every pixel through every network, seconds per view at 512x512)")  # fmt: skip
    p.add_argument("--config-budget", type=float, default=None, metavar="SECONDS",
                   help="time budget of one configuration's frames: one slower than budget/views per frame (the GLSL "
                        "backend at k = 128 on llvmpipe) measures fewer views, at least 4, spread over the orbit; "
                        "its record's 'views' says how many (default: every view)")  # fmt: skip
    p.add_argument("--precisions", nargs="+", choices=PRECISIONS, default=list(PRECISIONS))
    p.add_argument("--interpolate", type=float, nargs="+", default=[], metavar="TOL",
                   help="also measure the fp32 ONNX backend with screen-space interpolation at these tolerances (prt-runtime --interpolate)")
    p.add_argument("--backends", nargs="+", choices=("onnx", "glsl", "vertex", "texture", "probes"), default=["onnx", "glsl", "vertex"],
                   help="texture: the texture-space baseline (transfer textures baked at --texture-size); probes: an L2 SH "
                        "irradiance probe grid, the engines' baseline, at equal bytes and at 1 m spacing (mesh scenes, diffuse)")  # fmt: skip
    p.add_argument("--texture-size", type=int, nargs="+", default=[1024], metavar="N",
                   help="transfer texture sizes of the texture baseline, texels per side (default 1024)")
    p.add_argument("--cache", type=Path, default=None, help="reference / variant cache (default: next to --json)")
    p.add_argument("--gemm-size", type=int, default=4096, help="matrix size of the machine-limit GEMM (default 4096)")
    p.add_argument("--gl-device", default=None, metavar="NAME|INDEX",
                   help="the EGL device that draws: an index or a name matched against GL_RENDERER, e.g. nvidia or llvmpipe "
                        "(default: $PRT_GL_DEVICE, else auto: the GPU where there is one, else llvmpipe); the report names it")  # fmt: skip
    add_cluster_argument(p)  # the reference's ray tracing
    p.add_argument("--blas-threads", type=int, default=None,
                   help="limit numpy's BLAS threads while rendering (default: leave as found)")  # fmt: skip
    p.add_argument("--images", type=Path, default=None, metavar="DIR",
                   help="write one PNG per scene and size into DIR: view 0's reference and every configuration's "
                        "error map, on one colour scale")  # fmt: skip
    p.add_argument("--fresh", action="store_true",
                   help="measure every scene again (default: a scene measured earlier with the same files and "
                        "settings is taken from its checkpoint in the cache, so an interrupted run resumes)")  # fmt: skip
    args = p.parse_args(argv)
    if args.views < 1 or min(args.size) < 1 or args.ref_rays < 1 or args.warmup < 0:
        p.error("--views, --size and --ref-rays must be positive, --warmup >= 0")
    if args.baseline_rays is not None and args.baseline_rays < 1:
        p.error(f"--baseline-rays: expected a positive integer, got {args.baseline_rays}")
    if args.ref_hit_rays < 1 or args.ref_hit_transfer_rays < 1:
        p.error("--ref-hit-rays and --ref-hit-transfer-rays must be positive")
    if args.ref_rays_max < 1 or args.ref_hit_rays_max < 1:
        p.error("--ref-rays-max and --ref-hit-rays-max must be positive")
    if not 0 <= args.ref_budget < math.inf:
        p.error(f"--ref-budget must be a non-negative number of seconds, got {args.ref_budget}")
    if args.mitsuba_spp < 2 or args.mitsuba_views < 1:
        p.error(f"--mitsuba-spp must be at least 2 and --mitsuba-views positive, got {args.mitsuba_spp} and {args.mitsuba_views}")
    for flag, value in (("--gemm-size", args.gemm_size), ("--blas-threads", args.blas_threads), ("--packing-views", args.packing_views)):
        if value is not None and value < 1:
            p.error(f"{flag} must be positive, got {value}")
    if args.config_budget is not None and not 0 < args.config_budget < math.inf:
        p.error(f"--config-budget must be a positive number of seconds, got {args.config_budget}")
    if "fp32" not in args.precisions:
        args.precisions = ["fp32", *args.precisions]  # the other precisions are compared with it
    for tol in args.interpolate:
        if not 0 < tol <= 1:
            p.error(f"--interpolate: tolerances must be in (0, 1], got {tol}")
    return args


def _exposure(text: str):
    """argparse type of ``--exposure``: ``auto`` or a positive number."""
    try:
        from prt.bench.exposure import parse_exposure

        return parse_exposure(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected auto or a positive number, got {text!r}") from None


def _load(module: str, command: str):
    """``module`` imported, or None after one line naming the missing package and the extra to install."""
    from prt.train.entry import load_command

    return load_command(module, command, purpose="benchmarking")


def main(argv=None) -> int:
    """``prt-bench``: measure, print the Markdown table, write the reports asked for; the exit status.
    ``prt-bench deform SCENE...``: deformable scenes (:mod:`prt.bench.deform_bench`)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["deform"]:
        deform = _load("prt.bench.deform_bench", "prt-bench deform")
        return 2 if deform is None else deform.main(argv[1:])
    if _load("prt.bench.scene_bench", "prt-bench") is None:
        return 2
    import importlib.util

    from prt.bench.report import markdown, plot
    from prt.bench.scene_bench import Settings, run
    from prt.runtime.errors import PRTError
    from prt.runtime.files import atomic_write_bytes, atomic_write_json
    from prt.runtime.gl import create_context
    from prt.train.cluster import open_executor

    args = parse_args(argv)
    if args.reference == "mitsuba" and importlib.util.find_spec("mitsuba") is None:  # before hours of measuring
        print("prt-bench: error: --reference mitsuba needs Mitsuba 3: pip install 'prt-runtime[mitsuba]' (or pip install mitsuba)", file=sys.stderr)
        return 2
    cameras = None
    if args.cameras is not None:  # a malformed file: one line naming it and the field, before any measuring
        from prt.bench.cameras import camera_record, load_views

        try:
            cameras = tuple(tuple(camera_record(c)) for c in load_views(args.cameras))
        except PRTError as exc:
            print(f"prt-bench: error: {exc}", file=sys.stderr)
            return 2
        args.views = len(cameras)
    cache = args.cache
    if cache is None and args.json is not None:
        cache = args.json.parent / f"{args.json.stem}_cache"
    settings = Settings(
        views=args.views, sizes=tuple(args.size), ref_rays=args.ref_rays, ref_rays_max=args.ref_rays_max, warmup=args.warmup, config_budget=args.config_budget,
        ref_hit_rays_max=args.ref_hit_rays_max, ref_budget=args.ref_budget or None,
        reference=args.reference, mitsuba_spp=args.mitsuba_spp, mitsuba_views=args.mitsuba_views, mitsuba_variant=args.mitsuba_variant,
        baseline_rays=args.baseline_rays, equal_bytes=args.equal_bytes,
        packing_views=args.packing_views,
        precisions=tuple(dict.fromkeys(args.precisions)), backends=tuple(args.backends), cache=cache,
        interpolate=tuple(dict.fromkeys(args.interpolate)),
        texture_sizes=tuple(dict.fromkeys(args.texture_size)),
        gemm_size=args.gemm_size, blas_threads=args.blas_threads, fresh=args.fresh, images=args.images,
        ref_hit_rays=args.ref_hit_rays, ref_hit_transfer_rays=args.ref_hit_transfer_rays, gl_device=args.gl_device,
        cameras=cameras, cameras_file=None if args.cameras is None else str(args.cameras), exposure=args.exposure,
    )  # fmt: skip
    try:
        if args.gl_device is not None:  # a device that does not exist: one line now, before minutes of work
            create_context(device=args.gl_device, origin="--gl-device").release()
        with open_executor(args.cluster) as executor:
            report = run(args.scenes, settings, executor=executor)
    except PRTError as exc:  # --cluster without Ray, or no cluster at the address
        print(f"prt-bench: error: {exc}", file=sys.stderr)
        return 2
    for failure in report["failed"]:
        print(f"prt-bench: error: {' '.join(failure['error'].split())} (scene skipped)", file=sys.stderr)
    if not report["scenes"]:
        return 2  # nothing measured: no report to write
    text = markdown(report)
    print(text)
    if args.json:
        atomic_write_json(args.json, report)
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    if args.plot:
        plot(report, args.plot)
    return 2 if report["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
