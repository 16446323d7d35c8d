"""prt-train: build a deployable scene: precompute -> train -> export (ONNX, GLSL, scene.json).

usage: prt-train INPUT -o OUTDIR [--quality draft|standard|high] [--samples N] [--rays R] [--segments S] [--steps N] [--seed K]
                 [--bounces N|auto] [--hidden K --layers L | --vertex-margin DB | --target MAE | --target-db DB | --match 64x4]
                 [--encoding freq|grid|auto [--grid L6-F2-T12-N4-32]] [--cluster auto|ADDRESS] [--force]
                 [--neural-sdf [--sdf-size KxL] [--sdf-samples N] [--sdf-steps N]] [--sdf-trace auto|band|sphere]

INPUT is a mesh file, a built-in SDF scene name (``prt-precompute --list-sdf``) or a build spec
(``.json``; the flat fields of :meth:`prt.train.build.BuildSpec.to_dict`, flags override them).
Every stage is cached in OUTDIR: rerun the same command after an interruption to resume.  OUTDIR must be
new, empty or one of our build folders (marked by ``.prt-build``); ``--force`` writes into any other.
"""

from __future__ import annotations

import time

_MODULE_START = time.perf_counter()  # ``python -m prt.train.train_cli``: the build's time counts from here, before the imports

import argparse
import json
import os
import sys
from pathlib import Path

from ..runtime.errors import InputError, PRTError, SpecError
from .build import DEFAULT_TARGET, BuildSpec, load_spec, run_build, spec_from_dict
from .presets import DEFAULT_QUALITY, PRESETS, QUALITIES, describe
from .progress import BuildProgress
from .refine import stop_lines
from .networks.fit import DEVICES, resolve_device
from .cluster import open_executor
from .executor import add_cluster_argument
from .outdir import check_output_folder
from .networks.segments import SPLIT_BY
from .transport.transfer import SDF_TRACE_CHOICES

__all__ = ["main", "build_parser"]


def _bounce_count(value: str):
    """``--bounces``: a count, or "auto" (:func:`prt.train.transport.bounce_depth.auto_bounces`)."""
    if value == "auto":
        return value
    try:
        return int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of bounces or 'auto', got {value!r}") from None


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults shown where they say something: not for flags, nor for options whose help gives theirs ([...])."""

    def _get_help_string(self, action):
        if action.default in (None, False) or "[" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    d = BuildSpec()
    p = argparse.ArgumentParser(
        prog="prt-train",
        description="Build a PRT scene: ray-traced ground truth, one right-sized network per segment, "
        "ONNX + generated GLSL + scene.json.  A preset (--quality) sets how long it takes; the flags of each stage "
        "below override it.",
        epilog="Every stage is cached in OUTDIR: rerun the same command after an interruption to resume.  "
        "Guide: docs/guides/build.md.",
        formatter_class=_Formatter,
    )
    p.add_argument("input", help="mesh file, built-in SDF scene name, or build spec (.json)")
    p.add_argument("-o", "--out", type=Path, required=True, help="output folder (created; stages cached and resumable)")

    g = p.add_argument_group("preset", "one flag for the whole build; any flag below overrides its value")
    g.add_argument("--quality", choices=QUALITIES, default=None,
                   help="; ".join(f"{q}: {describe(q)}" for q in QUALITIES) + f" [{DEFAULT_QUALITY}]")

    g = p.add_argument_group("input", "what is built and where")
    g.add_argument("--name", default=None, help="scene name in the manifest (default: the input's stem)")
    g.add_argument("--force", action="store_true", help="write into OUTDIR even if it is a non-empty folder that is not a prt build")
    g.add_argument("--neural-sdf", action="store_true",
                   help="fit a small MLP to the mesh's signed distance first and build the scene from it (a neural SDF scene)")
    g.add_argument("--sdf-size", default="64x4", metavar="KxL", help="with --neural-sdf: width x hidden layers of the SDF network (the paper: 32x4, 64x4)")
    g.add_argument("--sdf-samples", type=int, default=200_000, help="with --neural-sdf: points with a signed distance to fit")
    g.add_argument("--sdf-steps", type=int, default=3000, help="with --neural-sdf: Adam steps of the SDF fit")
    g.add_argument("--sdf-trace", choices=SDF_TRACE_CHOICES, default=None,
                   help="how SDF scenes are ray traced for the ground truth: 'band' (Embree on marching-cubes shells around the "
                        "surface, the field evaluated only between them), 'sphere' (plain sphere tracing, its reference twin), "
                        "'auto': band where the scene holds a neural SDF [auto]")
    g.add_argument("--deform", default=None, metavar="SPEC",
                   help="a deformable object (INPUT: a folder of frames, a .glb/.gltf, a mesh, or 'sheet' for fold): 'sequence', "
                        "'gltf[:animation=walk,frames=24,start=S,end=E]', 'bend:angle=0..90,frames=16[,axis=x]', 'twist:angle=0..180', "
                        "'fold:angle=0..175[,radius=0.08]'; --samples then counts per training frame")
    g.add_argument("--code-dim", type=int, default=0, help="with --deform: shape-code dimensions [0: the fewest PCA components keeping 99.9%% of the offsets' variance, at most 8]")
    g.add_argument("--code-scale", choices=("common", "component"), default="common",
                   help="with --deform: one scale for every PCA component of the shape code, so codes keep the shapes' distances, or each "
                        "component to [-1, 1] (builds before issue 38) [common]")
    g.add_argument("--code-freqs", type=int, default=None, help="with --deform: sin/cos frequencies of each code component in the first layer [0: the code alone]")
    g.add_argument("--holdout-every", type=int, default=4, help="with --deform: every N-th frame is held out as an unseen pose between training poses")
    g.add_argument("--extrapolate", type=int, default=1, help="with --deform: the N most extreme poses (farthest from the mean pose) are held out, outside the training range")
    g.add_argument("--extrapolate-from", choices=("extreme", "first", "last"), default="extreme",
                   help="with --deform: which poses --extrapolate holds out: the most extreme (farthest from the mean pose), or the source's first or last frames")

    g = p.add_argument_group("precompute", "ground truth: samples, rays, segments, bounces")
    g.add_argument("--samples", type=int, default=None, help=f"training surface samples [preset; standard {PRESETS['standard']['samples']:,}]")
    g.add_argument("--validation", type=int, default=None, help="held-out samples [5%% of --samples, at least 1000]")
    g.add_argument("--rays", type=int, default=None, help=f"rays per sample for the ground truth [preset; standard {PRESETS['standard']['rays']}]")
    g.add_argument("--segments", type=int, default=None, help=f"leaf budget of the spatial split before merging [preset; standard {PRESETS['standard']['segments']}]")
    g.add_argument("--split", choices=SPLIT_BY, default=None,
                   help="which leaf the spatial split cuts next: the one with the most samples (equal areas), or the one whose "
                        "transfer is least explained by a rank-8 PCA (more networks where shadows make it complex) [samples]")
    g.add_argument("--adaptive", type=float, default=None, metavar="SHARE",
                   help="share of --samples drawn by a second pass where the first pass's transfer varies fastest (contact shadows, creases) [0: all area-uniform]")
    g.add_argument("--seed", type=int, default=None, help=f"seed of sampling, ray frames and training [{d.seed}]")
    g.add_argument("--bounces", type=_bounce_count, default=None, metavar="N",
                   help=f"diffuse interreflection: N bounces of light between surfaces, albedos from the mesh's own materials (0: direct light only; "
                        f"auto: the smallest N whose truncation PSNR on the validation samples is >= 50 dB under the bundled env maps) [{d.bounces}]")
    g.add_argument("--bounce-rays", type=int, default=None, metavar="M", help=f"with --bounces: rays per sample of the bounce stage [preset; standard {PRESETS['standard']['bounce_rays']}]")
    g.add_argument("--threads", type=int, default=os.cpu_count(), help="CPU threads for ray tracing and training")
    g.add_argument("--device", choices=DEVICES, default="auto",
                   help="where the networks train: auto (a CUDA GPU when torch sees one, else the CPU), cpu, cuda; keys no cache (grid networks train on the CPU)")
    add_cluster_argument(g)

    g = p.add_argument_group("networks", "fitting and right-sizing: by default each segment gets the cheapest size whose held-out "
                             "error is the preset's margin below per-vertex PRT's, within its share of per-vertex PRT's bytes")
    g.add_argument("--steps", type=int, default=None, help=f"Adam steps per network whatever its sample count (early stopping on validation) [preset; standard {PRESETS['standard']['steps']}]")
    g.add_argument("--epochs", type=int, default=None, help="alone: the old epoch-based run, E passes over each network's samples (a small segment then gets few steps); "
                   "with --steps: at least E passes [off]")
    g.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="wall-clock seconds per network fit: training (and its learning-rate decay) ends by then; not reproducible bit for bit [off]")
    g.add_argument("--batch", type=int, default=None, help=f"batch size [preset; standard {PRESETS['standard']['batch']}]")
    g.add_argument("--lr", type=float, default=None, help=f"peak learning rate (warm-up, then cosine) [{d.lr}]")
    g.add_argument("--vertex-margin", type=float, default=None, metavar="DB",
                   help="the default rule's margin: dB of held-out shaded PSNR above the per-vertex PRT estimate each segment's network "
                        f"must reach [preset; standard {PRESETS['standard']['vertex_margin']:g}]")
    g.add_argument("--floor", type=float, default=None, metavar="DB",
                   help="the absolute floor of the held-out PSNR (diffuse under the scene's lighting): while under it, the build splits the "
                        "segments holding most of the error and grows their networks, within --build-budget; 0: no floor "
                        f"[preset; standard {PRESETS['standard']['floor_db']:g}]")
    g.add_argument("--build-budget", type=float, default=None, metavar="SECONDS",
                   help=f"wall-clock seconds of the whole build that refinement toward --floor may use [preset; standard {PRESETS['standard']['build_budget']:g}]")
    g.add_argument("--hidden", type=int, default=None, help="force k neurons per layer for every network (with --layers)")
    g.add_argument("--layers", type=int, default=None, help="force l hidden layers for every network (with --hidden)")
    g.add_argument("--pos-freqs", type=int, default=None, help="with --hidden/--layers: position encoding frequencies [6]")
    g.add_argument("--match", default=None, metavar="KxL", help="right-size to the accuracy of this size instead: train it, then keep the cheapest smaller size on the ladder "
                   "within --match-tolerance of its validation MAE (SDF and mixed scenes: 64x4, their default)")
    g.add_argument("--match-tolerance", type=float, default=None, help=f"with --match: share by which the validation MAE may exceed the reference's [{d.match_tolerance}]")
    g.add_argument("--target", type=float, default=None, help=f"right-size to a validation MAE (SH coefficients) instead [{DEFAULT_TARGET} with --encoding grid|auto]")
    g.add_argument("--target-db", type=float, default=None, metavar="DB",
                   help="right-size to a shaded target instead: per segment the cheapest size whose held-out diffuse "
                        "shading, tone-mapped as prt-bench's images, reaches DB dB PSNR under every bundled env map (e.g. 40)")
    g.add_argument("--encoding", choices=("freq", "grid", "auto"), default=None,
                   help="the networks' encoding of position: the paper's frequency-encoded MLP, a multiresolution feature grid "
                        "(dense coarse levels, hashed fine ones) feeding a small MLP that --hidden/--layers size, or auto: per segment "
                        "the cheapest of both ladders (by FLOPs per fragment) that meets the target [freq]")
    g.add_argument("--grid", default=None, metavar="L6-F2-T12-N4-32",
                   help="with --encoding grid: L levels of F features, at most 2^T table rows per level, N_min-N_max cells per axis "
                        "[L6-F2-T12-N4-32; without --hidden/--layers the MLP is right-sized over 16x1, 32x2, 64x2, 64x3]")
    g.add_argument("--loss", choices=("auto", "l2", "l1", "relative"), default=None,
                   help="fitting loss: auto (per segment: l1 where its samples see >= 80 %% of their cosine lobe, else l2), squared error "
                        "on the transfer coefficients (fits the Monte Carlo targets' mean), L1 on them (the paper's; fits their median: too "
                        "dark where few rays see light, rooms lit through windows), or each sample's L1 over its brightness [auto]")
    g.add_argument("--residual", choices=("auto", "on", "off"), default=None,
                   help="frequency networks learn the direct transfer's residual from the unshadowed transfer of the normal (the graph adds "
                        "it back): auto per segment where its samples see >= 80 %% of their cosine lobe on average, on, off [auto]")
    g.add_argument("--head", choices=("auto", "linear", "log-dc"), default=None,
                   help="frequency networks' output head: log-dc (each group's DC coefficient in log space, the others as ratios to it: "
                        "errors relative to the local brightness), linear (tanh, scaled), or auto: log-dc where a segment's samples see "
                        "< 80 %% of their cosine lobe on average (rooms lit through windows), else linear [linear]")
    g.add_argument("--no-analytic", action="store_true", help="give every segment a network, even unshadowed ones")
    g.add_argument("--bf16", action="store_true", help="train the MLP layers under bf16 autocast (about 2x faster where the CPU has native bf16, slightly less accurate)")

    g = p.add_argument_group("export", "the scene folder")
    g.add_argument("--glsl-layout", choices=("auto", "const", "texture"), default=None, help="auto: one GLSL function per network architecture, every segment's weights in one scene texture (compiles in seconds on llvmpipe); "
                        "const / texture: the older per-segment functions, weights as baked mat4 constants (fastest per fragment, slow to compile) or in a texture [auto]")
    g.add_argument("--transfer-texture", type=int, default=None, metavar="SIZE",
                   help="also bake a SIZE x SIZE transfer texture (texture-space PRT, the runtime's texture backend) into the scene")
    g.add_argument("--texture-layout", choices=("shared", "per_object"), default="shared",
                   help="with --transfer-texture: one atlas for the scene, or one per object (texture sets)")
    g.add_argument("--no-progress", action="store_true", help="no progress line (it is drawn only when stderr is a terminal)")
    return p


def _spec_from_args(args):
    """The build spec of the command line: the spec file's own fields (or the input alone), the
    flags over them, then the preset's values where neither gives one (:func:`prt.train.presets.resolve`)."""
    source = str(args.input)
    if source.lower().endswith(".json"):
        spec = load_spec(source)  # checks the file and resolves its paths
        raw = json.loads(Path(source).read_bytes())  # valid: load_spec read it
        data = {k: v for k, v in spec.to_dict().items() if k in raw or k in ("geometry", "objects")}
    else:
        data = {"geometry": source}
    overrides = {
        "quality": args.quality,
        "name": args.name,
        "samples": args.samples,
        "validation": args.validation,
        "rays": args.rays,
        "segments": args.segments,
        "adaptive": args.adaptive,
        "split": args.split,
        "sdf_trace": args.sdf_trace,
        "steps": args.steps,
        "epochs": args.epochs,
        "time_budget": args.time_budget,
        "batch": args.batch,
        "lr": args.lr,
        "seed": args.seed,
        "target": args.target,
        "target_db": args.target_db,
        "vertex_margin": args.vertex_margin,
        "match_tolerance": args.match_tolerance,
        "glsl_layout": args.glsl_layout,
        "bounces": args.bounces,
        "bounce_rays": args.bounce_rays,
        "encoding": args.encoding,
        "grid": args.grid,
        "loss": args.loss,
        "residual": args.residual,
        "head": args.head,
        "floor_db": args.floor,
        "build_budget": args.build_budget,
    }
    data.update({k: v for k, v in overrides.items() if v is not None})
    if args.floor == 0:  # no floor
        data["floor_db"] = None
    if args.no_analytic:
        data["analytic"] = False
    if args.bf16:
        data["bf16"] = True
    if (args.hidden is None) != (args.layers is None):
        raise SpecError("--hidden and --layers go together")
    flag_rule = any(v is not None for v in (args.hidden, args.match, args.target, args.target_db, args.vertex_margin))
    if flag_rule or args.encoding not in (None, "freq"):  # a rule named on the command line replaces the spec file's
        for key in ("fixed", "match", "target", "target_db", "vertex_margin", "ladder"):
            if overrides.get(key) is None:
                data.pop(key, None)
    if args.hidden is not None:
        fixed = {"hidden": args.hidden, "layers": args.layers}
        if args.pos_freqs is not None:
            fixed["pos_freqs"] = args.pos_freqs
        data["fixed"] = fixed
    if args.match is not None:
        try:
            k, l = (int(v) for v in args.match.lower().split("x"))
        except ValueError:
            raise SpecError(f"--match: expected KxL such as 64x4, got {args.match!r}") from None
        data["match"] = {"hidden": k, "layers": l}
    spec = spec_from_dict(data)
    return spec


def _neural_sdf_spec(args, spec):
    """``--neural-sdf``: fit the mesh's SDF network into OUTDIR; the build's geometry becomes that network."""
    from .sdf.neural_fit import prepare_neural_sdf, require_torch
    from .outdir import mark_output_folder
    from .sdf.neural import parse_sdf_size

    require_torch()
    try:
        size = parse_sdf_size(args.sdf_size)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if args.sdf_samples < 1000 or args.sdf_steps < 1:
        raise InputError(f"--sdf-samples >= 1000 and --sdf-steps >= 1, got {args.sdf_samples} and {args.sdf_steps}")
    source = spec.geometry
    mark_output_folder(args.out, "scene")
    network = prepare_neural_sdf(source, args.out, size=size, samples=args.sdf_samples, steps=args.sdf_steps, seed=spec.precompute.seed)
    data = spec.to_dict()
    data["geometry"] = str(network)
    data["name"] = spec.name or Path(source).stem
    return spec_from_dict(data)


def _bake_texture(args, spec) -> None:
    """``--transfer-texture``: bake the scene's transfer texture at the build's rays (resumable)."""
    from .transport.transfer_texture import add_transfer_texture

    if args.transfer_texture < 8:
        raise InputError(f"--transfer-texture: expected a size >= 8, got {args.transfer_texture}")
    try:
        add_transfer_texture(args.out, args.transfer_texture, layout=args.texture_layout, rays=spec.precompute.rays,
                             seed=spec.precompute.seed, progress=not args.no_progress and sys.stderr.isatty())  # fmt: skip
    except ValueError as exc:  # an SDF scene
        raise InputError(f"--transfer-texture: {exc}") from None


def main(argv: list[str] | None = None, started: float | None = None) -> int:
    """``started``: the ``time.perf_counter()`` of the process's start (:func:`prt.train.entry.train_main`),
    from which the build's time budget counts; default: now."""
    started = time.perf_counter() if started is None else started
    args = build_parser().parse_args(argv)
    try:
        if args.threads is not None and args.threads < 1:
            raise InputError(f"--threads: expected a positive integer, got {args.threads}")
        device = resolve_device(args.device)  # --device cuda without a GPU: one line, nothing written
        if args.deform is not None:
            return _deform_main(args)
        spec = _spec_from_args(args)
        check_output_folder(args.out, "scene", force=args.force)
        if args.neural_sdf:
            spec = _neural_sdf_spec(args, spec)
        display = BuildProgress(enabled=not args.no_progress)  # drawn only on a terminal
        try:
            with open_executor(args.cluster, args.threads) as executor:
                report = run_build(spec, args.out, threads=args.threads, progress=display, log=display.log, force=args.force,
                                   executor=executor, device=device, started=started)  # fmt: skip
        finally:
            display.close()
        if args.transfer_texture is not None:
            _bake_texture(args, spec)
    except PRTError as exc:
        print(f"prt-train: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the system's, not the input's: a full disk, a lost mount
        print(f"prt-train: error: {exc.filename or args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"prt-train: interrupted; finished work is kept in {args.out}, rerun the same command to resume", file=sys.stderr)
        return 130
    print_report(report, args.out)
    return 0


def _deform_main(args) -> int:
    """``--deform``: a deformable object (:mod:`prt.train.deform.deform_build`)."""
    from .deform.deform_build import DeformSpec, run_deform_build
    from .deform.deform_sources import parse_deform

    fields = {"samples": args.samples, "validation": args.validation, "rays": args.rays, "segments": args.segments, "steps": args.steps,
              "seed": args.seed, "hidden": args.hidden, "layers": args.layers, "pos_freqs": args.pos_freqs}  # fmt: skip
    fields |= {"code_freqs": args.code_freqs, "residual": args.residual, "batch": args.batch}
    spec = DeformSpec(**{k: v for k, v in fields.items() if v is not None}, code_dim=args.code_dim, holdout_every=args.holdout_every,
                      extrapolate=args.extrapolate, extrapolate_from=args.extrapolate_from, code_scale=args.code_scale)  # fmt: skip
    check_output_folder(args.out, "scene", force=args.force)
    source = parse_deform(args.deform, args.input)
    report = run_deform_build(source, args.out, spec, name=args.name, threads=args.threads, progress=not args.no_progress, force=args.force)
    means = report["frame_errors"]["mean"]
    print()
    for role, psnr in means.items():
        print(f"{role:>13}: held-out sample PSNR " + ", ".join(f"{k} {v:.1f} dB" for k, v in psnr.items()))
    m = report["memory"]
    print(f"weights: {m['weight_bytes']:,} bytes for {m['frames']} frames ({report['code']['dim']}-dimensional shape code)")
    t = report["timings"]
    print(f"time: precompute {t['precompute_s']:.1f} s, train {t['train_s']:.1f} s, export {t['export_s']:.1f} s")
    print(f"wrote {args.out}/scene.json")
    return 0


_ENDED = {"error": "margin", "bytes": "bytes", "ladder": "ladder"}


def print_report(report: dict, out: Path) -> None:
    """The build's summary table: per segment its size, errors, cost; the sizing rule's outcome; memory; time."""
    vertex = "sizing" in report
    sizes = [(r["arch_label"] if r["kind"] == "network" else "analytic") + ("*" if r["kind"] == "network" and not r.get("met_target", True) else "")
             for r in report["segments"]]  # fmt: skip
    width = max([14, *map(len, sizes)])
    print()
    print(f"{'seg':>3} {'samples':>9} {'kind/size':>{width}} {'val MAE':>9} {'shaded err %':>18} {'FLOPs/frag':>11} {'bytes':>9}"
          + (f" {'vs vertex':>9} {'ended':>6}" if vertex else ""))  # fmt: skip
    for r, size in zip(report["segments"], sizes):
        shaded = " ".join(f"{100 * v:5.2f}" for v in r["shaded"].values())
        extra = f" {r['vertex']['gain_db']:>+6.2f} dB {_ENDED[r['vertex']['ended']]:>6}" if vertex and "vertex" in r else ""
        print(f"{r['id']:>3} {r['samples']:>9,} {size:>{width}} {r['val_mae']:>9.5f} {shaded:>18} {r['flops_per_fragment']:>11,} {r['weight_bytes']:>9,}"
              + extra)  # fmt: skip
    names = ", ".join(report["segments"][0]["shaded"]) if report["segments"] else ""
    print(f"shaded error: relative MAE of dot(T, L) on held-out samples under the bundled env maps ({names})")
    if any(r["kind"] == "network" and not r.get("met_target", True) for r in report["segments"]):
        print("* no size on the ladder met the target; the best one tried is used")
    if vertex:
        z = report["sizing"]
        light = min(z["network_psnr_db"], key=lambda k: z["network_psnr_db"][k] - z["vertex_psnr_db"][k], default=None)
        ended = {"error": f"the margin (+{z['margin_db']:g} dB over vertex PRT) reached",
                 "bytes": "vertex PRT's bytes reached before the margin", "ladder": "the largest network size reached before the margin"}[z["ended"]]
        print(f"sizing: networks {z['gain_db']:+.2f} dB over the per-vertex PRT estimate on {z['held_out_samples']:,} held-out samples "
              f"(worst light {light}: {z['network_psnr_db'].get(light, 0):.2f} vs {z['vertex_psnr_db'].get(light, 0):.2f} dB), "
              f"{z['network_bytes']:,} vs {z['vertex_bytes']:,} bytes of per-vertex transfer with its back sides; ended: {ended}")  # fmt: skip
    held = report.get("held_out")
    if held:
        vertex_db = report.get("sizing", {}).get("vertex_psnr_db", {}).get(held["light"])
        floor = (f"; floor {held['floor_db']:g} dB {'met' if held['psnr_db'] >= held['floor_db'] else 'NOT MET'}"
                 if held.get("floor_db") is not None else "")
        refined = report.get("refinement") or {}
        rounds = f" after {refined['rounds']} refinement round(s) from {refined['start_psnr_db']:.2f} dB" if refined.get("rounds") else ""
        print(f"held-out PSNR: {held['psnr_db']:.2f} dB (diffuse, under {held['light']})"
              + (f" vs per-vertex PRT's {vertex_db:.2f} dB" if vertex_db is not None else "") + rounds + floor)  # fmt: skip
        for line in stop_lines(refined):
            print(line)
    preset = report.get("preset") or {}
    if preset.get("quality"):
        changed = ", ".join(f"{k} {v[1]}" for k, v in preset.get("differs", {}).items())
        print(f"preset: {preset['quality']}" + (f" (set by hand: {changed})" if changed else ""))
    m = report["memory"]
    print(
        f"weights: {m['weight_bytes']:,} bytes for the scene vs {m['vertex_storage_bytes']:,} bytes of per-vertex "
        f"transfer ({m['vertex_storage_bytes'] // max(4 * m['vertices'], 1)} floats x {m['vertices']:,} vertices)"
    )
    t = report["timings"]
    bounce = f", bounces {t['bounce_s']:.1f} s" if "bounce_s" in t else ""
    bounce += f", vertex estimate {t['vertex_s']:.1f} s" if "vertex_s" in t else ""
    bounce += f", refinement {t['refine_s']:.1f} s" if "refine_s" in t else ""
    print(f"time: precompute {t['precompute_s']:.1f} s{bounce}, train {t['train_s']:.1f} s, export {t['export_s']:.1f} s "
          f"(total {t['total_s']:.1f} s)")  # fmt: skip
    print(f"wrote {out}/scene.json")


if __name__ == "__main__":
    sys.exit(main(started=_MODULE_START))
