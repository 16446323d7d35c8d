"""Interreflection measurements on the Cornell box (issue 13): output layout, frame time.

usage:
  python scripts/interreflection_measure.py layout [--samples N] [--steps K] [--json OUT]
  python scripts/interreflection_measure.py frame SCENE_DIRECT SCENE_BOUNCES [--size 512] [--frames 12]

``layout``: on the floor of the Cornell box (the surface with the most colour bleeding), 2
bounces, fit the same sizes with the two RGB layouts the issue names, "direct+rgb" (64 outputs:
direct + indirect R, G, B) and "rgb" (48: three total transfers), and report the validation MAE
of the total RGB transfer and the FLOPs per fragment of each.

``frame``: milliseconds per frame of two built scenes (same precompute and network size, one
direct-only and one with ``--bounces``) at SIZE x SIZE with the ONNX backend, every frame a new
view (so the networks run), interleaved, median over FRAMES.

The precompute-time figure comes from ``build.json`` (``timings.precompute_s`` and
``timings.bounce_s``) of a ``prt-train --bounces 2`` build.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

CORNELL = Path(__file__).resolve().parents[1] / "tests" / "data" / "CornellBox-Original.obj"


def layout(args) -> dict:
    import tempfile

    from prt.train.networks.fit import FitSettings, fit_segment
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.interreflection import bounce_stage
    from prt.train.inputs.materials import mesh_materials
    from prt.train.networks.network import Architecture
    from prt.train.inputs.sampling import VALIDATION_STREAM, sample_surface
    from prt.train.transport.transfer import compute_transfer

    geometry = load_geometry(str(CORNELL))
    found = {m.object: m.material.albedo for m in mesh_materials(str(CORNELL), geometry.object_names, {"type": "diffuse", "albedo": [0.7] * 3})}
    face_albedo = np.array([found.get(n, (0.7, 0.7, 0.7)) for n in geometry.object_names])[geometry.object_ids]
    parts = []
    for stream, count in ((0, args.samples), (VALIDATION_STREAM, max(1000, args.samples // 5))):
        s = sample_surface(geometry, count, seed=0, stream=stream)
        parts.append({"points": s.points, "normals": s.normals, "object_ids": s.object_ids,
                      "transfer": compute_transfer(geometry, s.points, s.normals, rays=args.rays, threads=2)})  # fmt: skip
    with tempfile.TemporaryDirectory() as cache:
        indirect = bounce_stage(geometry.mesh, cache, parts[0], parts[1], face_albedo, 2, rays=64, threads=2, progress=False)
    floor = geometry.object_names.index("floor")
    data = []
    for part, extra in zip(parts, indirect):
        keep = part["object_ids"] == floor
        direct, ind = part["transfer"][keep], extra[keep]  # (M, 16), (M, 16, 3)
        targets = {"direct+rgb": np.concatenate([direct, ind.transpose(0, 2, 1).reshape(len(ind), -1)], axis=1),
                   "rgb": (direct[:, :, None] + ind).transpose(0, 2, 1).reshape(len(ind), -1)}  # fmt: skip
        data.append((part["points"][keep], part["normals"][keep], targets))
    (p, n, t), (vp, vn, vt) = data
    bounds = np.array([p.min(axis=0), p.max(axis=0)])
    bounds += np.array([[-1.0], [1.0]]) * 0.01 * np.maximum(bounds[1] - bounds[0], 1e-3)
    settings = FitSettings(steps=args.steps, lr=1e-2, seed=0)
    rows = []
    for hidden, layers in ((16, 2), (32, 2), (32, 3), (64, 3)):
        for kind in ("direct+rgb", "rgb"):
            arch = Architecture(hidden=hidden, layers=layers, pos_freqs=6, layout=kind)
            result = fit_segment(p, n, t[kind], vp, vn, vt[kind], arch, bounds, settings)
            rows.append({"layout": kind, "hidden": hidden, "layers": layers, "outputs": arch.outputs, "flops": arch.flops_per_fragment(),
                         "val_mae_rgb": result.val_mae, "seconds": result.seconds})  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    return {"mesh": str(CORNELL), "object": "floor", "samples": args.samples, "floor_samples": int(len(p)), "rays": args.rays,
            "bounces": 2, "bounce_rays": 64, "steps": args.steps, "fits": rows}  # fmt: skip


def frame(args) -> dict:
    from prt.runtime.camera import orbit_views
    from prt.runtime.renderer import Renderer, Scene

    renderers = {name: Renderer(Scene.load(path), args.size, args.size, backend="onnx") for name, path in (("direct", args.direct), ("bounces", args.bounces))}
    # Small turns about the default view (inside the box): every frame a new view, the networks run.
    views = orbit_views(renderers["direct"].camera, 72)[: args.frames + 2]
    times = {name: [] for name in renderers}
    for k in range(args.frames + 2):  # two warm-up frames
        for name, r in renderers.items():
            r.set_camera_object(views[k])
            t0 = time.perf_counter()
            r.render()
            if k >= 2:
                times[name].append(1e3 * (time.perf_counter() - t0))
    out = {name: {"median_ms": float(np.median(v)), "all_ms": v} for name, v in times.items()}
    out["ratio"] = out["bounces"]["median_ms"] / out["direct"]["median_ms"]
    for r in renderers.values():
        r.close()
    return {"size": args.size, "frames": args.frames, **out}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="mode", required=True)
    a = sub.add_parser("layout")
    a.add_argument("--samples", type=int, default=20000)
    a.add_argument("--rays", type=int, default=256)
    a.add_argument("--steps", type=int, default=1000)
    a.add_argument("--json", type=Path)
    b = sub.add_parser("frame")
    b.add_argument("direct")
    b.add_argument("bounces")
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--frames", type=int, default=12)
    b.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    report = layout(args) if args.mode == "layout" else frame(args)
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
