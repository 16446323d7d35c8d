"""How well the build's held-out estimate predicts the image comparison with per-vertex PRT.

usage: python studies/vertex_estimate_check.py BUILD --json OUT.json [--cache DIR] [--quiet-rays N]

For a finished mesh build with bounces (a ``prt-train`` folder): the per-vertex PRT estimate
(:mod:`prt.train.transport.vertex_estimate`, as the default sizing rule computes it now) and the
build's networks (from ``train/segNNN.npz``), both on the build's held-out samples, all of them and
split by side (samples whose normal agrees with their triangle's winding, "front", and the rest),
shaded, tone-mapped PSNR under the bundled env maps.  Set it beside ``prt-bench``'s image PSNR of
the same build (``BUILD/bench.json`` from ``studies/builds_vs_vertex.py``) to see how far the
held-out samples' verdict is from the images'.

``--quiet-rays N`` also traces the held-out samples' direct transfer again with N rays and another
seed, a truth whose noise is independent of the build's and N / rays times smaller: the direct
parts of the networks, the vertex estimate and the build's own held-out truth are set against it
(``direct_vs_quiet_psnr_db``), which says whether the build-time verdict is the noise's or the
predictors'.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_json
from prt.runtime.sh import unshadowed_transfer
from prt.train.build import _env_lights, _hash
from prt.train.inputs.geometry import load_geometry
from prt.train.networks.network import Architecture
from prt.train.networks.rightsize import predict_numpy, shaded_psnr
from prt.train.transport.interreflection import bounce_stage
from prt.train.transport.precompute import load_precompute
from prt.train.transport.vertex_estimate import estimate_vertex_prt


def _psnr(pred, truth, lights, mask=None) -> dict:
    sel = slice(None) if mask is None else mask
    return {k: round(v, 2) for k, v in shaded_psnr(pred[sel], truth[sel], lights, 16, [0.7, 0.7, 0.7]).items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("build", type=Path)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--cache", type=Path, default=Path("/tmp/prt-vertex-estimate-check"))
    p.add_argument("--quiet-rays", type=int, default=0, help="also a direct-transfer truth of N rays with another seed")
    args = p.parse_args(argv)
    b = args.build
    rep = json.loads((b / "build.json").read_text())
    spec = rep["spec"]
    geometry = load_geometry(spec["geometry"])
    data = load_precompute(b / "precompute")
    valid = data["validation"]
    bounces = rep["interreflection"]["bounces"]
    albedos = rep["interreflection"]["albedos"]
    face_albedo = np.asarray([albedos[n] for n in geometry.object_names])[geometry.object_ids]
    est = estimate_vertex_prt(geometry, args.cache, rays=spec["rays"], bands=4, seed=spec["seed"], chunk_size=2048, bounces=bounces,
                              face_albedo=face_albedo, threads=1)  # fmt: skip
    pre = json.loads((b / "precompute" / "precompute.json").read_text())
    key = _hash(pre["key"], spec["bounce_rays"], spec["seed"], 2048, "v2")  # the build's bounce cache (prt.train.build)
    _, vind = bounce_stage(geometry.mesh, b / "precompute" / "cache", data["samples"], valid, face_albedo, bounces, rays=spec["bounce_rays"],
                           seed=spec["seed"], chunk_size=2048, key=key, threads=1, progress=False, log=lambda s: None)  # fmt: skip
    truth = np.concatenate([valid["transfer"], vind.transpose(0, 2, 1).reshape(len(vind), -1)], axis=1)
    vertex = est.predict(valid["points"], valid["normals"], valid["face_index"])
    network = np.zeros_like(truth)
    for r in rep["segments"]:
        sel = valid["segment"] == r["id"]
        if r["kind"] == "analytic":
            network[sel, :16] = unshadowed_transfer(valid["normals"][sel], 4)
            continue
        with np.load(b / "train" / f"seg{r['id']:03d}.npz") as f:
            arrays = dict(f)
        arch = Architecture(**{k: v for k, v in r["arch"].items() if k in Architecture.__dataclass_fields__})
        network[sel] = predict_numpy(arch, arrays, valid["points"][sel], valid["normals"][sel])
    tri = geometry.mesh.vertices[geometry.mesh.faces[valid["face_index"]]]
    front = np.einsum("mc,mc->m", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), valid["normals"]) > 0
    lights = _env_lights(4)
    out = {"provenance": provenance(), "build": str(b), "held_out_samples": int(len(truth)), "front_share": round(float(front.mean()), 4),
           "held_out_psnr_db": {"networks": _psnr(network, truth, lights), "vertex": _psnr(vertex, truth, lights)},
           "front_psnr_db": {"networks": _psnr(network, truth, lights, front), "vertex": _psnr(vertex, truth, lights, front)},
           "back_psnr_db": {"networks": _psnr(network, truth, lights, ~front), "vertex": _psnr(vertex, truth, lights, ~front)}}  # fmt: skip
    if args.quiet_rays:
        from prt.train.transport.transfer import compute_transfer

        quiet = compute_transfer(geometry, valid["points"], valid["normals"], rays=args.quiet_rays, bands=4, seed=spec["seed"] + 1009,
                                 threads=2, cache_dir=args.cache / "quiet")  # fmt: skip
        out["quiet_rays"] = args.quiet_rays
        out["direct_vs_quiet_psnr_db"] = {name: {side: _psnr(pred[:, :16], quiet, lights, mask) for side, mask in
                                                 (("all", None), ("front", front), ("back", ~front))}
                                          for name, pred in (("networks", network), ("vertex", vertex), ("build truth", truth))}  # fmt: skip
        out["direct_vs_build_truth_psnr_db"] = {name: _psnr(pred[:, :16], truth[:, :16], lights) for name, pred in
                                                (("networks", network), ("vertex", vertex))}  # fmt: skip
    bench = b / "bench.json"
    if bench.is_file():
        records = [r for r in json.loads(bench.read_text())["records"] if r["material"] == "diffuse" and r["precision"] == "fp32"]
        out["image_psnr_db"] = {f"{r['scene']} {r['label']}": r["psnr"] for r in records}
    atomic_write_json(args.json, out)
    json.dump(out, sys.stdout, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
