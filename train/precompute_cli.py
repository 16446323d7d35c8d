"""prt-precompute: ground-truth transfer for a scene (the first stage of training).

usage: prt-precompute INPUT -o OUTDIR [--samples N] [--rays R] [--segments S] [--seed K] [--envmap HDR]
                      [--sdf-trace auto|band|sphere] [--cluster auto|ADDRESS] [--force]

INPUT is a mesh file (OBJ, PLY, STL, GLB/glTF, ...) or a built-in SDF scene name
(``prt-precompute --list-sdf``).  Rerunning the same command resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..runtime.envmap import read_envmap
from ..runtime.errors import InputError, PRTError
from .cluster import open_executor
from .executor import add_cluster_argument
from .inputs.geometry import load_geometry
from .outdir import check_output_folder
from .transport.precompute import PrecomputeSettings, check_settings, run_precompute
from .transport.transfer import SDF_TRACE_CHOICES
from .sdf import sdf_names

__all__ = ["main", "build_parser", "settings_from_args", "check_writable"]

# The options that set PrecomputeSettings, in --help order: (field, flag, help).  Types and
# defaults come from the dataclass; a --no-* flag clears a field that is True by default.
SETTINGS_OPTIONS = (
    ("samples", "--samples", "training surface samples"),
    ("validation", "--validation", "held-out samples (0: 5%% of --samples, at least 1000)"),
    ("rays", "--rays", "cosine-weighted rays per sample"),
    ("bands", "--bands", "SH bands (4 -> 16 coefficients)"),
    ("segments", "--segments", "leaf budget of the spatial split before merging"),
    ("delta", "--delta", "seam margin: neighbours' samples on a segment's own surface within this distance (scene units)"),
    ("merge_tolerance", "--merge-tolerance", "largest RMS PCA residual of a merged segment"),
    ("merge", "--no-merge", "keep every leaf of the split as its own segment"),
    ("by_object", "--no-object-split", "let segments span several objects"),
    ("seed", "--seed", "random seed (samples and ray frames)"),
    ("adaptive", "--adaptive", "share of --samples drawn by a second pass where the first pass's transfer varies fastest"),
    ("sdf_trace", "--sdf-trace", "how SDF scenes are traced: band (Embree on shells around the surface, the field evaluated "
                                 "only between them), sphere (plain sphere tracing), auto (band where a neural SDF is in the scene)"),
)


def build_parser() -> argparse.ArgumentParser:
    d = PrecomputeSettings()
    p = argparse.ArgumentParser(
        prog="prt-precompute",
        description="Sample a scene's surface and ray trace its ground-truth SH transfer "
        "(defaults: the paper's setting, 1M samples x 512 rays).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("input", nargs="?", help="mesh file or built-in SDF scene name")
    p.add_argument("-o", "--out", type=Path, help="output folder (created; resumable)")
    p.add_argument("--force", action="store_true", help="write into OUTDIR even if it is a non-empty folder that is not a prt build")
    for name, flag, text in SETTINGS_OPTIONS:
        default = getattr(d, name)
        if flag.startswith("--no-"):
            p.add_argument(flag, action="store_true", help=text)
        elif name == "sdf_trace":
            p.add_argument(flag, choices=SDF_TRACE_CHOICES, default=default, help=text)
        else:
            p.add_argument(flag, type=type(default), default=default, help=text)
    p.add_argument("--envmap", type=Path, default=None, help="equirectangular .hdr/.exr lighting the preview (default: a procedural sky)")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="worker threads")
    add_cluster_argument(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--list-sdf", action="store_true", help="list the built-in SDF scenes and exit")
    return p


def settings_from_args(args: argparse.Namespace) -> PrecomputeSettings:
    """The PrecomputeSettings of parsed :func:`build_parser` options."""
    values = {}
    for name, flag, _ in SETTINGS_OPTIONS:
        value = getattr(args, flag[2:].replace("-", "_"))
        values[name] = not value if flag.startswith("--no-") else value
    return PrecomputeSettings(**values)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.list_sdf:
            print("\n".join(sdf_names()))
            return 0
        if not args.input or args.out is None:
            parser.error("INPUT and -o OUTDIR are required")
        if args.threads is None or args.threads < 1:
            raise InputError(f"--threads: expected a positive integer, got {args.threads}")
        settings = settings_from_args(args)
        check_settings(settings, flags=True)
        check_output_folder(args.out, "precompute", force=args.force)

        envmap = None
        if args.envmap is not None:  # read first: a bad file must fail before hours of work
            envmap = read_envmap(args.envmap)
        geometry = load_geometry(args.input)
        print(geometry.summary())
        with open_executor(args.cluster, args.threads) as executor:
            summary = run_precompute(
                geometry, args.out, settings, threads=args.threads, progress=not args.no_progress, preview_envmap=envmap,
                force=args.force, executor=executor,
            )
    except PRTError as exc:
        print(f"prt-precompute: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the system's, not the input's: a full disk, a lost mount
        print(f"prt-precompute: error: {exc.filename or args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(
            f"prt-precompute: interrupted; finished chunks are kept in {args.out}/cache, "
            "rerun the same command to resume",
            file=sys.stderr,
        )
        return 130
    _print_summary(summary, args.out)
    return 0


def check_writable(out: Path, kind: str = "precompute", force: bool = False) -> None:
    """OutputError unless ``out`` can be written and is ours, empty or new (creates nothing)."""
    check_output_folder(out, kind, force=force)


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
