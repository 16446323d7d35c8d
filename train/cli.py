"""prt-precompute: ground-truth transfer for a scene (the first stage of training).

usage: prt-precompute INPUT -o OUTDIR [--samples N] [--rays R] [--segments S] [--seed K] [--envmap HDR]

INPUT is a mesh file (OBJ, PLY, STL, GLB/glTF, ...) or a built-in SDF scene name
(``prt-precompute --list-sdf``).  Rerunning the same command resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..runtime.errors import PRTError

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    from .precompute import PrecomputeSettings

    d = PrecomputeSettings()
    p = argparse.ArgumentParser(
        prog="prt-precompute",
        description="Sample a scene's surface and ray trace its ground-truth SH transfer "
        "(defaults: the paper's setting, 1M samples x 512 rays).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("input", nargs="?", help="mesh file or built-in SDF scene name")
    p.add_argument("-o", "--out", type=Path, help="output folder (created; resumable)")
    p.add_argument("--samples", type=int, default=d.samples, help="training surface samples")
    p.add_argument("--validation", type=int, default=d.validation, help="held-out samples (0: 5%% of --samples, at least 1000)")
    p.add_argument("--rays", type=int, default=d.rays, help="cosine-weighted rays per sample")
    p.add_argument("--bands", type=int, default=d.bands, help="SH bands (4 -> 16 coefficients)")
    p.add_argument("--segments", type=int, default=d.segments, help="leaf budget of the spatial split before merging")
    p.add_argument("--delta", type=float, default=d.delta, help="seam margin sampled into neighbouring segments (scene units)")
    p.add_argument("--merge-tolerance", type=float, default=d.merge_tolerance, help="largest RMS PCA residual of a merged segment")
    p.add_argument("--no-merge", action="store_true", help="keep every leaf of the split as its own segment")
    p.add_argument("--no-object-split", action="store_true", help="let segments span several objects")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (samples and ray frames)")
    p.add_argument("--envmap", type=Path, default=None, help="equirectangular .hdr/.exr lighting the preview (default: a procedural sky)")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="worker threads")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--list-sdf", action="store_true", help="list the built-in SDF scenes and exit")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.list_sdf:
            from .sdf import sdf_names

            print("\n".join(sdf_names()))
            return 0
        if not args.input or args.out is None:
            parser.error("INPUT and -o OUTDIR are required")
        for name in ("samples", "rays", "bands", "segments", "threads"):
            if getattr(args, name) is None or getattr(args, name) < 1:
                raise PRTError(f"--{name} must be a positive integer")
        _check_writable(args.out)

        from .geometry import load_geometry
        from .precompute import PrecomputeSettings, run_precompute

        envmap = None
        if args.envmap is not None:  # read first: a bad file must fail before hours of work
            from ..runtime.envmap import read_envmap

            envmap = read_envmap(args.envmap)
        geometry = load_geometry(args.input)
        print(geometry.summary())
        settings = PrecomputeSettings(
            samples=args.samples,
            validation=args.validation,
            rays=args.rays,
            bands=args.bands,
            seed=args.seed,
            segments=args.segments,
            by_object=not args.no_object_split,
            merge=not args.no_merge,
            merge_tolerance=args.merge_tolerance,
            delta=args.delta,
        )
        summary = run_precompute(
            geometry, args.out, settings, threads=args.threads, progress=not args.no_progress, preview_envmap=envmap
        )
    except PRTError as exc:
        print(f"prt-precompute: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            f"prt-precompute: interrupted; finished chunks are kept in {args.out}/cache, "
            "rerun the same command to resume",
            file=sys.stderr,
        )
        return 130
    _print_summary(summary, args.out)
    return 0


def _check_writable(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise PRTError(f"{out}: output folder is not writable ({exc.strerror or exc})") from None


def _print_summary(summary: dict, out: Path) -> None:
    t = summary["timings"]
    s = summary["settings"]
    print(
        f"transfer: {s['samples']:,} samples x {s['rays']} rays in {t['transfer_s']:.1f} s "
        f"({t['rays_per_s'] / 1e6:.2f} Mrays/s); validation {summary['validation_samples']:,} samples"
    )
    print(f"{'segment':>7} {'samples':>9} {'margin':>8} {'residual':>9}  bounds")
    for seg in summary["segments"]:
        lo, hi = seg["bounds"]
        box = " ".join(f"[{a:+.2f},{b:+.2f}]" for a, b in zip(lo, hi))
        print(f"{seg['id']:>7} {seg['samples']:>9,} {seg['margin_samples']:>8,} {seg['residual_rms']:>9.4f}  {box}")
    for note in summary.get("segment_notes", []):
        print(f"note: {note}")
    print(f"wrote {out}/ ({', '.join(summary['files'])})")


if __name__ == "__main__":
    sys.exit(main())
