"""How many bounces: the truncation error of N = 0, 1, 2, ... bounces on the shared meshes and the Cornell box.

usage: python studies/bounce_depth.py [--meshes spot bunny teapot daffodil cornell] [--work DIR]
           [--samples 60000] [--validation 6000] [--rays 128] [--bounce-rays 32] [--show 4] [--terms 16]
           [--exposure 1] [--threads 1] [--json docs/benchmarks/bounce_depth.json]
           [--md docs/benchmarks/bounce_depth.md] [--figure docs/bounce_depth.png]

For every mesh, with the build's own machinery (``run_precompute``, then the bounce stage's
:func:`prt.train.transport.interreflection.trace_stage` and :func:`~prt.train.transport.interreflection.bounce_terms`,
the albedos the build would use: the mesh's per-object ``Kd``, else 0.7 grey), the study computes
the bounce terms ``T_1 .. T_K`` (K = ``--terms``, the rays traced once) of the held-out
(validation) samples and measures, under every bundled env map and the shared sunset map, the
error of stopping after N bounces against the sum of all K (:func:`prt.train.transport.bounce_depth.truncation_errors`:
relative MAE of the shaded linear RGB radiance, PSNR of the tone-mapped values, exposure
``--exposure``, over samples).  Times, from this one run: the direct precompute, the bounce rays
(traced once whatever N) and each bounce's sparse products; ratios to the direct precompute.

Beside it, the error floor the networks reach on the same scenes, from the figures already in
``docs/benchmarks`` (PSNR over covered pixels, diffuse; they are pixel figures, these are sample
figures): ``paper.json`` (k = 64, 1M samples) for the four meshes, ``texture_bounces_cornell.json``
and ``cornell_bounces.json`` for the Cornell box.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from prt.runtime.camera import DEFAULT_CAMERA, Camera, orbit_views
from prt.runtime.envmap import load_envmap_sh
from prt.runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path
from prt.train.transport.bounce_depth import AUTO_PSNR, choose_bounces, truncation_errors
from prt.train.build import BuildSpec, _object_albedos
from prt.train.executor import LocalExecutor
from prt.train.inputs.geometry import load_geometry
from prt.train.transport.interreflection import BOUNCE_RAYS, bounce_terms, trace_stage
from prt.train.inputs.materials import mesh_materials
from prt.train.transport.precompute import PrecomputeSettings, load_precompute, run_precompute

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
MESHES = {
    "spot": SHARED / "meshes" / "spot.obj",
    "bunny": SHARED / "meshes" / "stanford_bunny_hr.obj",
    "teapot": SHARED / "meshes" / "utah_teapot.obj",
    "daffodil": SHARED / "meshes" / "daffodil_plant.obj",
    "cornell": SHARED / "meshes" / "cornell_box" / "CornellBox-Original.obj",
}
SUNSET = SHARED / "envmaps" / "venice_sunset_1k.hdr"
VERDICT = [  # the recorded run's figures (the tables above are computed; these words are not: update them with a rerun)
    "- **N = 0 (the paper's direct transfer) is above the networks' floor on every scene**, the convex-looking Spot and bunny "
    "included: at albedo 0.7 a few % of their light has bounced (relative MAE 3-6 % visible, 20-33 dB; all five scenes 13-33 dB), "
    "so a direct-only build's error against a bounce-aware reference is the truncation, not the network.",
    "- **No single small N is below the floor everywhere.** Spot and bunny: 2 (N = 1 is 4-6 dB short); daffodil: 3 (its "
    "floor is low, 34.7 dB); the Cornell box: 3 against its outside views' 47.4 dB; the Utah teapot: 6 (its cavities, the "
    "inside of the body and spout, hold light that bounces on: the terms fall by only ~0.7 per bounce, an integrating sphere; "
    "the error sits in < 5 % of the visible samples, where a cavity opening shows).",
    "- **Extra bounces are nearly free**: the rays are traced once whatever N, each further bounce is a sparse product "
    "(0.09-0.20 s per 110k samples, 2-3 % of the bounce-ray tracing), and the frame costs the same for any N >= 1 (one network layout).",
    "- Verdict, adopted as `prt-train`'s default for meshes: `--bounces auto` (the smallest N >= 50 dB under every bundled env "
    "map on the validation samples: Spot 3, bunny 2, teapot 11, daffodil 7, Cornell box 4 here); for a fixed count, N = 4 is "
    "below the floor on all but the teapot (39.9 dB under studio against 44.9).  `--bounces 0` keeps the paper's direct-only "
    "comparisons (the paper table and the bundled demo use it).",
]
PLOT_BOUNCES = 8  # the figure shows N = 0 .. this (the tables stop at --show)


def network_floor(name: str) -> dict:
    """What the networks reach on this scene, from the recorded benchmarks (PSNR over covered pixels, diffuse)."""
    bench = ROOT / "docs" / "benchmarks"
    if name == "cornell":
        out = {}
        try:
            tb = json.loads((bench / "texture_bounces_cornell.json").read_text())
            psnr = [r["psnr"] for r in tb["records"] if r["backend"] == "onnx" and r["material"] == "diffuse" and r["precision"] == "fp32"]
            out["networks_2_bounces_outside_views"] = {"psnr": round(float(psnr[0]), 2), "source": "docs/benchmarks/texture_bounces_cornell.json (onnx fp32 diffuse, 20k samples, k = 32, l = 3, 128x128, 2 views)"}
            cb = json.loads((bench / "cornell_bounces.json").read_text())
            views = cb["builds"]["2"]["psnr_views"]
            out["networks_2_bounces_view_into_box"] = {"psnr": views[0], "source": "docs/benchmarks/cornell_bounces.json (view 0, 100k samples, k = 32, l = 3, 256x256, exposure 2)"}
        except (OSError, KeyError, IndexError, ValueError):
            pass
        return out
    try:
        paper = json.loads((bench / "paper.json").read_text())
        psnr = [r["psnr"] for r in paper["records"] if r["scene"] == f"{name}-k64" and r["backend"] == "onnx" and r["material"] == "diffuse"
                and r["precision"] == "fp32"]  # fmt: skip
        return {"networks_k64": {"psnr": round(float(psnr[0]), 2), "source": "docs/benchmarks/paper.json (onnx fp32 diffuse, 1M samples, k = 64, l = 4, 256x256, 10 views)"}}
    except (OSError, KeyError, IndexError, ValueError):
        return {}


def visible_from_orbit(mesh, points, normals, views: int) -> np.ndarray:
    """(V,) bool: samples some view of the default orbit (``prt-bench``'s views of a scene with the
    default camera) sees: inside the frustum, facing the eye, nothing in between."""
    from prt.train.transport.transfer import EmbreeTracer

    tracer = EmbreeTracer(mesh)
    seen = np.zeros(len(points), dtype=bool)
    start = Camera(np.asarray(DEFAULT_CAMERA["eye"], float), np.asarray(DEFAULT_CAMERA["target"], float))
    for camera in orbit_views(start, views):
        eye = np.asarray(camera.eye, dtype=np.float64)
        clip = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ camera.view_projection(1.0).T
        inside = (np.abs(clip[:, :2]) <= clip[:, 3:4]).all(axis=1) & (clip[:, 3] > 0)
        towards = eye - points
        distance = np.linalg.norm(towards, axis=1)
        facing = np.einsum("vc,vc->v", normals, towards) > 0
        dirs = (points - eye) / distance[:, None]
        hit = tracer._scene.run(np.repeat(eye[None].astype(np.float32), len(points), axis=0), dirs.astype(np.float32), output=1)["tfar"]
        seen |= inside & facing & (hit >= distance - 1e-3)
    return seen


def lights() -> dict:
    out = {name: load_envmap_sh(bundled_envmap_path(name), 4) for name in BUNDLED_ENVMAPS}
    if SUNSET.is_file():
        out["venice_sunset"] = load_envmap_sh(SUNSET, 4)
    else:
        print(f"note: {SUNSET} not found; bundled env maps only")
    return out


def study(name: str, path: Path, args, env: dict) -> dict:
    geometry = load_geometry(str(path))
    spec = BuildSpec(geometry=str(path))
    materials = mesh_materials(str(path), geometry.object_names, spec.material, print)
    albedos = _object_albedos(geometry, materials, spec.material)
    settings = PrecomputeSettings(samples=args.samples, validation=args.validation, rays=args.rays)
    folder = args.work / name
    t0 = time.perf_counter()
    summary = run_precompute(geometry, folder, settings, threads=args.threads, progress=False)
    wall = time.perf_counter() - t0
    timings = summary["timings"]
    direct_s = sum(timings[k] for k in ("sampling_s", "transfer_s", "validation_transfer_s", "segments_s") if k in timings)
    data = load_precompute(folder)
    train, valid = data["samples"], data["validation"]
    face_albedo = np.asarray([albedos[n] for n in geometry.object_names], dtype=np.float64)[geometry.object_ids]

    t0 = time.perf_counter()
    found = trace_stage(geometry.mesh, folder / "bounce-cache", train, valid, rays=args.bounce_rays, key=f"study-{summary['key']}-{args.bounce_rays}",
                        executor=LocalExecutor(args.threads), progress=False)  # fmt: skip
    trace_s = time.perf_counter() - t0
    terms, product_s, magnitude = [], [], []
    t0 = time.perf_counter()
    for b, term, valid_term in bounce_terms(found, face_albedo, train["transfer"], args.terms):
        product_s.append(time.perf_counter() - t0)
        terms.append(valid_term)
        magnitude.append(float(np.abs(term[:, 0]).mean()))
        t0 = time.perf_counter()
    receiver = np.asarray([albedos[n] for n in geometry.object_names], dtype=np.float64)[valid["object_ids"]]
    errors = truncation_errors(valid["transfer"], terms, receiver, env, exposure=args.exposure)
    seen = visible_from_orbit(geometry.mesh, valid["points"].astype(np.float64), valid["normals"].astype(np.float64), args.views)
    visible = truncation_errors(valid["transfer"][seen], [t[seen] for t in terms], receiver[seen], env, exposure=args.exposure)
    direct0 = float(np.abs(train["transfer"][:, 0]).mean())
    bounce_s = [trace_s + sum(product_s[:n]) for n in range(args.show + 1)]
    return {
        "mesh": str(path),
        "albedos": albedos,
        "train_samples": int(len(train["points"])),
        "validation_samples": int(len(valid["points"])),
        "faces": int(len(geometry.mesh.faces)),
        "precompute_cached": wall < 0.5 * direct_s,
        "times_s": {"direct_precompute": round(direct_s, 2), "bounce_rays": round(trace_s, 2), "products_per_bounce": [round(x, 3) for x in product_s[: args.show]]},
        "bounce_stage_over_direct": {str(n): round(bounce_s[n] / direct_s, 3) for n in range(1, args.show + 1)},
        "term_dc_over_direct": [round(m / direct0, 5) for m in magnitude],
        "truncation": {k: ({"rel_mae": [round(x, 6) for x in v["rel_mae"]], "psnr": [round(x, 2) for x in v["psnr"]], "mean_radiance": round(v["mean_radiance"], 6)}
                           if isinstance(v, dict) else v) for k, v in errors.items()},  # fmt: skip
        "visible_samples": int(seen.sum()),
        "truncation_visible": {k: ({"rel_mae": [round(x, 6) for x in v["rel_mae"]], "psnr": [round(x, 2) for x in v["psnr"]], "mean_radiance": round(v["mean_radiance"], 6)}
                                   if isinstance(v, dict) else v) for k, v in visible.items()},  # fmt: skip
        "auto_pick": {"threshold_psnr": AUTO_PSNR, "bounces": choose_bounces(errors, AUTO_PSNR), "bounces_visible": choose_bounces(visible, AUTO_PSNR)},
        "network_floor": network_floor(name),
    }


def _table(result: dict, show: int, key: str) -> list[str]:
    lines = ["| scene | env map | " + " | ".join(f"N = {n}" for n in range(show + 1)) + " |", "|---|---|" + "---|" * (show + 1)]
    for name, r in result["scenes"].items():
        for env, v in r[key].items():
            if env != "reference_bounces":
                cells = [f"{v['psnr'][n]:.1f} dB / {100 * v['rel_mae'][n]:.2f} %" for n in range(show + 1)]
                lines.append(f"| {name} | {env} | " + " | ".join(cells) + " |")
    return lines


def _worst(r: dict, key: str) -> list[float]:
    """Per N, the lowest PSNR over the env maps."""
    t = r[key]
    envs = [e for e in t if e != "reference_bounces"]
    return [min(t[e]["psnr"][n] for e in envs) for n in range(t["reference_bounces"])]


def _first(values: list[float], bar: float) -> int | None:
    return next((n for n, v in enumerate(values) if v >= bar), None)


def verdict(result: dict) -> list[str]:
    """Per scene: how many bounces put the truncation error below the networks' floor (the higher floor
    where there are two) and below the auto threshold; the lines of the Markdown's verdict table."""
    lines = ["| scene | networks' floor | worst N = 0 (visible) | worst N = 2 (visible) | worst N = 4 (visible) | N below the floor (visible / all) | "
             f"N >= {AUTO_PSNR:g} dB (visible / all = auto) |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, r in result["scenes"].items():
        floors = [v["psnr"] for v in r["network_floor"].values()]
        vis, every = _worst(r, "truncation_visible"), _worst(r, "truncation")
        floor = max(floors) if floors else None
        below = f"{_first(vis, floor)} / {_first(every, floor)}" if floor is not None else "-"
        lines.append(f"| {name} | {floor if floor is not None else '-'} dB | {vis[0]:.1f} dB | {vis[2]:.1f} dB | {vis[4]:.1f} dB | {below} | "
                     f"{_first(vis, AUTO_PSNR)} / {_first(every, AUTO_PSNR)} |")  # fmt: skip
    return lines


def markdown(result: dict, show: int) -> str:
    lines = [
        "# Bounce depth: the truncation error of N bounces",
        "",
        f"Command: `{result['command']}`",
        "",
        f"Settings: {result['samples']:,} samples ({result['validation']:,} held out, on which the errors are measured), "
        f"{result['rays']} direct rays, {result['bounce_rays']} bounce rays per sample, terms T_1 .. T_{result['terms']} "
        f"(their sum is the reference), tone map exposure {result['exposure']} (as `prt-bench`), receivers diffuse with the "
        "albedos the bounces use.  Cells: PSNR of the tone-mapped radiance / relative MAE of the linear radiance, "
        "against the reference.",
        "",
        f"## Held-out samples visible from the {result['views']} orbit views of the default camera",
        "",
        *_table(result, show, "truncation_visible"),
        "",
        "## All held-out samples (hidden surfaces too: the teapot's and the pot's insides)",
        "",
        *_table(result, show, "truncation"),
        "",
        "## Verdict",
        "",
        "Worst env map per scene; 'N below the floor': the smallest N whose truncation PSNR is at least the PSNR the networks "
        "reach on the scene (pixels; the Cornell box's higher, outside-view figure).",
        "",
        *verdict(result),
        "",
        "From the recorded run (`docs/benchmarks/bounce_depth.json`):",
        "",
        *VERDICT,
        "",
        "## Cost and the networks' floor",
        "",
        "Bounce stage time relative to the direct precompute (one run per scene, `--threads 1`; the rays are traced once "
        "whatever N, each bounce is a sparse product).  Floor: PSNR over covered pixels the networks reach on the scene "
        "(recorded benchmarks, see the JSON for their sources).  Auto pick: the smallest N whose PSNR is >= "
        f"{AUTO_PSNR:g} dB under every env map (all samples / visible ones).  'each bounce': the median of the first "
        f"{show} bounces' products (the first also builds the sparse matrices).  The direct precompute casts {result['rays']} "
        "rays per sample and the bounce stage's cost does not depend on that count: with the build's 512 rays a 2-bounce "
        "precompute (direct + bounce stage) took 2.27x the direct-only one on the Cornell box, 100k samples (`docs/benchmarks/interreflection_costs_cornell.json`).",
        "",
        "| scene | direct precompute s | bounce rays s | each bounce s | " + " | ".join(f"N = {n}" for n in range(1, show + 1))
        + " | networks' floor (pixels) | auto pick |",
        "|---|---|---|---|" + "---|" * show + "---|---|",
    ]
    for name, r in result["scenes"].items():
        floor = "; ".join(f"{v['psnr']} dB ({k})" for k, v in r["network_floor"].items()) or "-"
        ratios = " | ".join(f"{r['bounce_stage_over_direct'][str(n)]:.2f}x" for n in range(1, show + 1))
        each = float(np.median(r["times_s"]["products_per_bounce"]))
        lines.append(f"| {name} | {r['times_s']['direct_precompute']:.1f} | {r['times_s']['bounce_rays']:.1f} | {each:.2f} | {ratios} | {floor} | "
                     f"{r['auto_pick']['bounces']} / {r['auto_pick']['bounces_visible']} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def figure(result: dict, path: Path, show: int) -> None:
    show = min(max(show, PLOT_BOUNCES), result["terms"] - 1)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(result["scenes"])
    fig, axes = plt.subplots(1, len(scenes), figsize=(3.2 * len(scenes), 3.6), sharey=True, squeeze=False)
    for ax, name in zip(axes[0], scenes):
        r = result["scenes"][name]
        for i, env in enumerate(e for e in r["truncation"] if e != "reference_bounces"):
            colour = f"C{i}"
            ax.plot(range(show + 1), r["truncation_visible"][env]["psnr"][: show + 1], marker="o", color=colour, label=f"{env}")
            ax.plot(range(show + 1), r["truncation"][env]["psnr"][: show + 1], ls="--", lw=0.8, color=colour)
        for v in r["network_floor"].values():
            ax.axhline(v["psnr"], color="grey", lw=2, alpha=0.5)
        ax.axhline(AUTO_PSNR, color="black", ls=":", lw=0.8)
        ax.set_title(name)
        ax.set_xlabel("bounces kept N")
        ax.set_xticks(range(show + 1))
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f"PSNR against {result['terms']} bounces (dB)")
    axes[0][-1].legend(fontsize=7)
    fig.suptitle("Truncation error of N bounces, held-out samples (solid: visible from the orbit views, dashed: all); "
                 f"grey: the networks' floor (pixels), dotted: {AUTO_PSNR:g} dB", fontsize=8)  # fmt: skip
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-bounce-depth"))
    p.add_argument("--samples", type=int, default=60_000)
    p.add_argument("--validation", type=int, default=6_000)
    p.add_argument("--rays", type=int, default=128)
    p.add_argument("--bounce-rays", type=int, default=BOUNCE_RAYS)
    p.add_argument("--terms", type=int, default=16, help="bounce terms computed; their sum is the reference")
    p.add_argument("--show", type=int, default=4, help="N = 0 .. show in the table, the figure and the times")
    p.add_argument("--exposure", type=float, default=1.0)
    p.add_argument("--views", type=int, default=4, help="orbit views of the default camera deciding which samples are visible")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", type=Path, default=ROOT / "docs" / "benchmarks" / "bounce_depth.json")
    p.add_argument("--md", type=Path, default=ROOT / "docs" / "benchmarks" / "bounce_depth.md")
    p.add_argument("--figure", type=Path, default=ROOT / "docs" / "bounce_depth.png")
    p.add_argument("--replot", action="store_true", help="only rewrite --md and --figure from --json")
    args = p.parse_args(argv)
    if args.replot:
        result = json.loads(args.json.read_text())
        args.md.write_text(markdown(result, args.show))
        figure(result, args.figure, args.show)
        return 0

    import torch

    torch.set_num_threads(args.threads)
    args.work.mkdir(parents=True, exist_ok=True)
    env = lights()
    result = {"command": "python studies/bounce_depth.py " + " ".join(sys.argv[1:] if argv is None else argv), "samples": args.samples,
              "validation": args.validation, "rays": args.rays, "bounce_rays": args.bounce_rays, "terms": args.terms, "exposure": args.exposure,
              "threads": args.threads, "views": args.views, "envmaps": list(env), "scenes": {}}  # fmt: skip
    for name in args.meshes:
        print(f"== {name}", flush=True)
        result["scenes"][name] = study(name, MESHES[name], args, env)
        r = result["scenes"][name]
        print(json.dumps({k: r[k] for k in ("times_s", "bounce_stage_over_direct", "term_dc_over_direct", "auto_pick")}), flush=True)
        for env_name, v in r["truncation"].items():
            if env_name != "reference_bounces":
                print(f"  {env_name}: psnr {v['psnr'][: args.show + 1]} rel_mae {v['rel_mae'][: args.show + 1]}", flush=True)
                w = r["truncation_visible"][env_name]
                print(f"  {env_name} (visible {r['visible_samples']}): psnr {w['psnr'][: args.show + 1]} rel_mae {w['rel_mae'][: args.show + 1]}", flush=True)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")  # after every scene: a partial run keeps what it measured
    args.md.write_text(markdown(result, args.show))
    figure(result, args.figure, args.show)
    print(f"wrote {args.json}, {args.md}, {args.figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
