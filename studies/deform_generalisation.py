"""Why deformable networks lose on poses they did not train on, and what the design should be (issue 38).

usage::

    python studies/deform_generalisation.py [--characters cesium fox minetest] [--work DIR]
        [--variants NAME ...] [--steps 1500] [--segments 8] [--json OUT] [--md OUT]

For each skinned character (a glTF walk clip sampled to 48 frames, split as ``prt-train --deform``
does: 35 training frames, every 4th of the others unseen, the 2 most extreme poses extrapolated),
on the same ray-traced samples (``prt-train``'s per-frame precompute, cached under ``--work``):

- **the shape code's range and spectrum**: the PCA variance share of each component, and each
  held-out frame's code against the training range (is an "extrapolated" pose outside it?);
- **baselines at the held-out samples**: per-vertex transfer traced on each pose (the same
  estimator as ``prt-bench deform``'s baselines), interpolated at the samples by their barycentric
  weights: the pose's own vertex PRT (the best any per-vertex method can do), the nearest training
  frame's, and the linear morphable model (PCA of the training frames' vertex transfer regressed
  linearly on the code, :func:`prt.bench.deform_bench.fit_lmm`);
- **network variants** fitted on the same samples, one change at a time: the code's scaling
  (each component to [-1, 1], or one scale for all so the code keeps the offsets' geometry), its
  dimension, its sin/cos frequencies, the capacity per segment.

Every figure is the held-out samples' PSNR of tone-mapped diffuse shading (dB) under the bundled
env maps (``prt.train.networks.rightsize.shaded_psnr``), mean per frame role.  Fits and baselines
are cached under ``--work``; a rerun only computes what is missing.  Characters are read from
``--models`` (see ``docs/guides/deformable.md`` for where each comes from); one that is missing
is skipped with a note.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from prt.bench.deform_bench import fit_lmm, nearest_training_frame
from prt.bench.provenance import provenance
from prt.bench.vertex_prt import vertex_transfer
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.train.build import _env_lights
from prt.train.deform.deform_build import (VALID_STREAM, DeformSpec, _pose_geometry, _precompute_frames, shape_code,
                                           split_frames)  # fmt: skip
from prt.train.deform.deform_sources import orientation, parse_deform
from prt.train.inputs.sampling import sample_surface
from prt.train.networks.fit import FitSettings, fit_segment
from prt.train.networks.network import Architecture, evaluate_numpy
from prt.train.networks.rightsize import shaded_psnr
from prt.train.networks.segments import segment_samples
from prt.train.transport.transfer import make_tracer

ROOT = Path(__file__).resolve().parents[1]
CHARACTERS = {  # name -> (file under --models, or a repository path; the --deform spec)
    "cesium": ("CesiumMan.gltf", "gltf:frames=48"),
    "fox": ("Fox.gltf", "gltf:animation=Walk,frames=48"),
    "figure": ("RiggedFigure.gltf", "gltf:frames=48"),
    "minetest": (str(ROOT / "tests" / "data" / "character" / "minetest_character.glb"), "gltf:animation=walk,frames=48"),
}
ROLES = ("train", "unseen", "extrapolated")


@dataclasses.dataclass(frozen=True)
class Variant:
    """One network design: the code's scaling / dimension / frequencies and the capacity."""

    scale: str = "component"  # "component": each PCA component to [-1, 1]; "common": one scale (the first component's)
    dim: int = 0  # 0: the build's rule (99.9 % of the variance, at most 8)
    freqs: int = 2
    hidden: int = 64
    layers: int = 4
    segments: int = 8
    steps: int = 1500
    batch: int = 8192
    per_frame: int = 0  # training samples used per frame (0: all the precompute has)
    keep: float = 0.999
    max_dim: int = 8
    residual: bool = False  # learn T - U(n): the unshadowed transfer of the posed normal is exact for any pose

    def key(self) -> str:
        return hashlib.sha1(json.dumps(dataclasses.asdict(self), sort_keys=True).encode()).hexdigest()[:12]


VARIANTS = {
    "as-built": Variant(),
    "common-scale": Variant(scale="common"),
    "linear-code": Variant(freqs=0),
    "common-linear": Variant(scale="common", freqs=0),
    "common-f1": Variant(scale="common", freqs=1),
    "common-16d": Variant(scale="common", keep=0.99999, max_dim=16),
    "common-2d": Variant(scale="common", dim=2),
    "common-linear-16seg": Variant(scale="common", freqs=0, segments=16),
    "as-built-res": Variant(residual=True),
    "common-linear-res": Variant(scale="common", freqs=0, residual=True),
}


def code_for(rest, frames, train, v: Variant) -> dict:
    """The shape code of variant ``v`` (``shape_code``'s PCA, re-scaled when ``v.scale == 'common'``)."""
    code = shape_code(rest, frames, train, v.dim, keep=v.keep, max_auto=v.max_dim)
    if v.scale == "common":
        first = float(np.abs(code["theta"][train, 0]).max())  # component scales are folded into basis; undo per column
        per = np.abs(code["theta"][train]).max(axis=0)  # 1 by construction
        raw_scale = np.linalg.norm(code["basis"].reshape(code["dim"], -1), axis=1) / per  # |coeff| max per component
        theta = code["theta"] * raw_scale[None] / raw_scale[0] / first
        code = {**code, "theta": theta.astype(np.float32)}
    return code


def load_character(name: str, models: Path, work: Path, spec: DeformSpec, log):
    """Frames, roles and the per-frame samples (cached) of one character."""
    file, deform = CHARACTERS[name]
    path = Path(file) if Path(file).is_absolute() else models / file
    if not path.is_file():
        log(f"{name}: {path} not found; skipped")
        return None
    source = parse_deform(deform, str(path))
    normalised, _ = source.normalised()
    rest = np.asarray(normalised.rest, np.float64)
    frames = np.asarray(normalised.frames, np.float64)
    faces, two_sided = orientation(rest, np.asarray(normalised.faces, np.int64))
    offsets = (frames - rest[None]).reshape(len(frames), -1)
    roles = split_frames(len(frames), spec.holdout_every, spec.extrapolate, np.linalg.norm(offsets - offsets.mean(axis=0), axis=1))
    out = work / name
    out.mkdir(parents=True, exist_ok=True)
    data, _ = _precompute_frames(out, spec, rest, frames, faces, two_sided, roles, name, threads=None, progress=False, log=log)
    return {"name": name, "path": str(path), "deform": deform, "rest": rest, "frames": frames, "faces": faces, "two_sided": two_sided,
            "roles": roles, "data": data, "out": out}  # fmt: skip


def code_report(ch: dict) -> dict:
    """The build's code (99.9 %, at most 8, per-component scale): its spectrum and the held-out frames' range."""
    rest, frames, roles = ch["rest"], ch["frames"], ch["roles"]
    code = shape_code(rest, frames, roles["train"])
    offsets = (frames - rest[None]).reshape(len(frames), -1)[roles["train"]]
    sing = np.linalg.svd(offsets - offsets.mean(axis=0), compute_uv=False)
    share = sing**2 / float((sing**2).sum())
    theta = code["theta"]
    return {"vertices": int(len(rest)), "triangles": int(len(ch["faces"])), "dim": int(code["dim"]), "explained": round(code["explained"], 6),
            "variance_share": [round(float(s), 6) for s in share[:12]],
            "max_abs_theta": {r: [round(float(x), 3) for x in np.abs(theta[ch["roles"][r]]).max(axis=0)] for r in ("unseen", "extrapolated")},
            "extrapolated_frames": ch["roles"]["extrapolated"],
            "rms_offset_scene_units": round(float(np.sqrt((offsets**2).mean() * 3)), 4)}  # fmt: skip


def _samples_at(ch: dict, f: int, spec: DeformSpec):
    """The held-out samples of frame ``f`` again (same seed and stream as the precompute): faces, weights, normals."""
    pose = _pose_geometry(ch["frames"][f], ch["faces"], ch["two_sided"], f"{ch['name']} frame {f}")
    s = sample_surface(pose, spec.validation, seed=spec.seed + 7919 * f, stream=VALID_STREAM)
    return pose, s


def baselines(ch: dict, spec: DeformSpec, lights: dict, log) -> dict:
    """Held-out sample PSNR per role of per-vertex transfer: own pose, nearest training frame, LMM (cached)."""
    cache = ch["out"] / "baselines.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    t0 = time.perf_counter()
    vertex = {}
    for f in range(len(ch["frames"])):
        pose = _pose_geometry(ch["frames"][f], ch["faces"], ch["two_sided"], f"{ch['name']} frame {f}")
        front, back, _ = vertex_transfer(pose, make_tracer(pose), spec.rays, ch["out"] / "vertex", f"{ch['name']}-f{f}-{spec.rays}")
        vertex[f] = (front, back)
    train = ch["roles"]["train"]
    theta = shape_code(ch["rest"], ch["frames"], train)["theta"]
    lmm = fit_lmm(np.stack([np.concatenate(vertex[f], axis=1) for f in train]), theta[train])
    rows = {}
    for role in ROLES:
        for f in ch["roles"][role]:
            pose, s = _samples_at(ch, f, spec)
            truth = ch["data"][f]["valid_transfer"]
            assert np.allclose(s.normals, ch["data"][f]["valid_normals"], atol=1e-5)
            faces = ch["faces"][s.face_index]
            face_n = np.asarray(pose.mesh.face_normals)[s.face_index]
            back = (np.einsum("nc,nc->n", s.normals, face_n) < 0) & ch["two_sided"][s.face_index]

            def at(front_back):
                front, backs = front_back
                a = np.einsum("nk,nkc->nc", s.weights, front[faces])
                b = np.einsum("nk,nkc->nc", s.weights, backs[faces])
                return np.where(back[:, None], b, a)

            nearest = nearest_training_frame(theta[f], theta, train)
            predicted = lmm.predict(theta[f])
            rows[f] = {"role": role, "own_vertex": shaded_psnr(at(vertex[f]), truth, lights, 16),
                       "nearest_vertex": shaded_psnr(at(vertex[nearest]), truth, lights, 16),
                       "lmm": shaded_psnr(at((predicted[:, :16], predicted[:, 16:])), truth, lights, 16)}  # fmt: skip
    out = {"per_frame": rows, "means": _means(rows, ("own_vertex", "nearest_vertex", "lmm")), "lmm_components": lmm.components,
           "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    atomic_write_json(cache, out)
    log(f"{ch['name']}: baselines in {out['seconds']} s")
    return json.loads(cache.read_text())


def _means(rows: dict, methods) -> dict:
    out = {}
    for method in methods:
        for role in ROLES:
            vals = [r[method] for r in rows.values() if r["role"] == role]
            if vals:
                out.setdefault(method, {})[role] = {k: round(float(np.mean([v[k] for v in vals])), 3) for k in vals[0]}
    return out


def fit_variant(ch: dict, v: Variant, spec: DeformSpec, lights: dict, log) -> dict:
    """Networks of variant ``v`` on the character's samples; held-out sample PSNR per frame and role (cached)."""
    cache = ch["out"] / f"variant-{v.key()}.json"
    if cache.is_file():
        return json.loads(cache.read_text())
    t0 = time.perf_counter()
    roles, data = ch["roles"], ch["data"]
    code = code_for(ch["rest"], ch["frames"], roles["train"], v)
    theta = code["theta"]

    def stack(part, indices):
        cut = slice(None, v.per_frame or None) if part == "train" else slice(None)
        cols = {k: np.concatenate([data[f][f"{part}_{k}"][cut] for f in indices]) for k in ("rest", "normals", "transfer")}
        cols["theta"] = np.concatenate([np.repeat(theta[f][None], len(data[f][f"{part}_rest"][cut]), axis=0) for f in indices])
        return cols

    train, valid = stack("train", roles["train"]), stack("valid", roles["train"])
    seg = segment_samples(train["rest"], np.zeros(len(train["rest"]), np.int64), train["transfer"], normals=None, max_segments=v.segments)
    home = seg.assign(valid["rest"], np.zeros(len(valid["rest"]), np.int64))
    arch = Architecture(hidden=v.hidden, layers=v.layers, pos_freqs=spec.pos_freqs, normal_freqs=spec.normal_freqs, bands=4,
                        code_dim=code["dim"], code_freqs=v.freqs, residual=v.residual)  # fmt: skip
    nets = {}
    for s in range(seg.count):
        m, vm = seg.members[s], np.flatnonzero(home == s)
        vm = vm if len(vm) else m[: max(1, len(m) // 20)]
        vsrc = valid if (home == s).any() else train
        result = fit_segment(train["rest"][m], train["normals"][m], train["transfer"][m], vsrc["rest"][vm], vsrc["normals"][vm],
                             vsrc["transfer"][vm], arch, seg.bounds[s], FitSettings(steps=v.steps, seed=spec.seed, batch=v.batch), lights=lights,
                             codes=train["theta"][m], val_codes=vsrc["theta"][vm])  # fmt: skip
        nets[s] = result.model.arrays()
    rows = {}
    for role in ROLES:
        for f in roles[role]:
            p, n, truth = data[f]["valid_rest"], data[f]["valid_normals"], data[f]["valid_transfer"]
            h = seg.assign(p, np.zeros(len(p), np.int64))
            pred = np.zeros_like(truth)
            for s, arrays in nets.items():
                sel = h == s
                if sel.any():
                    pred[sel] = evaluate_numpy(arrays, p[sel], n[sel], np.repeat(theta[f][None], int(sel.sum()), axis=0))
            rows[f] = {"role": role, "ours": shaded_psnr(pred, truth, lights, 16),
                       "theta_max_abs": round(float(np.abs(theta[f]).max()), 3)}  # fmt: skip
    out = {"variant": dataclasses.asdict(v), "code_dim": int(code["dim"]), "segments": int(seg.count), "per_frame": rows,
           "means": _means(rows, ("ours",))["ours"], "seconds": round(time.perf_counter() - t0, 1),
           "weight_bytes": int(seg.count * 4 * arch.weight_count())}  # fmt: skip
    atomic_write_json(cache, out)
    log(f"{ch['name']} {v}: {out['means']} ({out['seconds']} s)")
    return json.loads(cache.read_text())


def markdown(report: dict) -> str:
    """Tables of the figures: per character, the baselines and every variant by role (first light, then the second)."""
    out = ["# Deformable networks on poses they did not train on: the study", "",
           f"{report['provenance']['date']}, `{report['provenance']['command']}`, CPU {report['provenance'].get('cpu', {}).get('model', '?')}.",
           "Held-out samples, PSNR of tone-mapped diffuse shading, dB, mean per frame role; lights " + ", ".join(report["lights"]) + ".", ""]  # fmt: skip
    for name, ch in report["characters"].items():
        c = ch["code"]
        out += [f"## {name} ({c['vertices']:,} vertices; code {c['dim']}-d, {100 * c['explained']:.2f} % of the offsets' variance)", "",
                f"Variance share of the PCA components: {', '.join(f'{x:.4f}' for x in c['variance_share'][:9])}.",
                f"Largest |theta| per component on the extrapolated frames {c['extrapolated_frames']}: {c['max_abs_theta']['extrapolated']}; "
                f"on unseen frames: {c['max_abs_theta']['unseen']}.", ""]  # fmt: skip
        lights = report["lights"]
        out += ["| method | " + " | ".join(f"{r} ({l})" for l in lights for r in ROLES) + " | bytes |",
                "|---|" + "---|" * (len(lights) * len(ROLES) + 1)]  # fmt: skip
        rows = [(k, ch["baselines"]["means"][k], "") for k in ("own_vertex", "nearest_vertex", "lmm")]
        rows += [(k, r["means"], f"{r['weight_bytes']:,}") for k, r in ch["variants"].items()]
        for label, means, size in rows:
            cells = [f"{means[r][l]:.2f}" if r in means else "-" for l in lights for r in ROLES]
            out.append(f"| {label} | " + " | ".join(cells) + f" | {size} |")
        out.append("")
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--characters", nargs="+", default=["cesium", "fox", "minetest"], choices=sorted(CHARACTERS))
    p.add_argument("--models", type=Path, default=Path("/tmp/models"), help="folder holding the characters' glTF files")
    p.add_argument("--work", type=Path, default=Path("/tmp/deform_study"))
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=sorted(VARIANTS))
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--batch", type=int, default=8192)
    p.add_argument("--per-frame", type=int, default=0, help="training samples per frame (0: all 10,000)")
    p.add_argument("--size", default="64x4", help="hidden x layers of every network")
    p.add_argument("--segments", type=int, default=8)
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared, oversubscribed machine)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    hidden, layers = (int(x) for x in args.size.split("x"))
    torch.set_num_threads(args.threads)
    spec = DeformSpec(samples=10_000, validation=2_000, rays=256, extrapolate=2)
    lights = _env_lights(4)
    lights = {k: lights[k] for k in ("potsdamer",) if k in lights} | {k: v for k, v in lights.items() if k != "potsdamer"}
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    report = {"provenance": provenance(), "lights": list(lights), "spec": dataclasses.asdict(spec), "characters": {}}
    for name in args.characters:
        ch = load_character(name, args.models, args.work, spec, log)
        if ch is None:
            continue
        entry = {"path": ch["path"], "deform": ch["deform"], "roles": ch["roles"], "code": code_report(ch),
                 "baselines": baselines(ch, spec, lights, log), "variants": {}}  # fmt: skip
        for vname in args.variants:
            v = dataclasses.replace(VARIANTS[vname], steps=args.steps, batch=args.batch, per_frame=args.per_frame, hidden=hidden,
                                    layers=layers, segments=VARIANTS[vname].segments * args.segments // 8)  # fmt: skip
            entry["variants"][vname] = fit_variant(ch, v, spec, lights, log)
        report["characters"][name] = entry
        if args.json:
            atomic_write_json(args.json, report)
        if args.md:
            atomic_write_bytes(args.md, markdown(report).encode())
    print(markdown(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
