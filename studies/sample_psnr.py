"""The held-out shaded PSNR of a finished build, per segment and pooled (what ``--target-db`` measures).

usage: python studies/sample_psnr.py BUILD_FOLDER

For each network segment: its fitted arrays evaluated in numpy on the segment's held-out samples,
the tone-mapped diffuse shading under each bundled env map against the ray-traced transfer
(:func:`prt.train.networks.rightsize.shaded_psnr`, albedo 0.7); then pooled over every held-out sample
(analytic segments: the unshadowed transfer).  Used in docs/benchmarks/rightsize_auto.md to set
the samples' PSNR beside the rendered images' PSNR that prt-bench measures.
"""
import sys, json, numpy as np
from pathlib import Path
from prt.train.transport.precompute import load_precompute
from prt.train.build import _env_lights
from prt.train.networks.rightsize import validation_split, shaded_psnr, predict_numpy
from prt.train.networks.network import Architecture
from prt.train.networks.grid_encoding import GridArchitecture
out = Path(sys.argv[1])
data = load_precompute(out / "precompute")
samples, valid = data["samples"], data["valid"] if "valid" in data else data["validation"]
lights = _env_lights(4)
rep = json.loads((out / "build.json").read_text())
allp = []
for rec in rep["segments"]:
    s = rec["id"]
    seg_valid = np.flatnonzero(valid["segment"] == s)
    vp, vn, vt = valid["points"][seg_valid], valid["normals"][seg_valid], valid["transfer"][seg_valid]
    if rec["kind"] != "network":
        print(s, "analytic"); continue
    arrays = dict(np.load(out / "train" / f"seg{s:03d}.npz"))
    a = rec["arch"]
    arch = GridArchitecture(**{k: v for k, v in a.items() if k in GridArchitecture.__dataclass_fields__}) if a.get("kind") == "grid" or "levels" in a else Architecture(**{k: v for k, v in a.items() if k in Architecture.__dataclass_fields__})
    pred = predict_numpy(arch, arrays, vp, vn)
    ps = shaded_psnr(pred, vt, lights, 16)
    print(s, rec["arch_label"], len(vt), {k: round(v, 2) for k, v in ps.items()})
# pooled over all validation samples (analytic segments: unshadowed), per light
from prt.runtime.sh import unshadowed_transfer
preds = np.zeros_like(valid["transfer"])
for rec in rep["segments"]:
    s = rec["id"]; idx = np.flatnonzero(valid["segment"] == s)
    if rec["kind"] != "network":
        preds[idx] = unshadowed_transfer(valid["normals"][idx], 4); continue
    arrays = dict(np.load(out / "train" / f"seg{s:03d}.npz")); a = rec["arch"]
    arch = GridArchitecture(**{k: v for k, v in a.items() if k in GridArchitecture.__dataclass_fields__}) if "levels" in a else Architecture(**{k: v for k, v in a.items() if k in Architecture.__dataclass_fields__})
    preds[idx] = predict_numpy(arch, arrays, valid["points"][idx], valid["normals"][idx])
print("pooled", {k: round(v, 2) for k, v in shaded_psnr(preds, valid["transfer"], lights, 16).items()})
