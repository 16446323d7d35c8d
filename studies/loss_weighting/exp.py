"""Segment-level: refit one segment of a copied build with each loss; errors on its held-out samples."""
import sys, json, time
import numpy as np, torch
torch.set_num_threads(1)
from prt.train.transport.precompute import load_precompute
from prt.train.build import _env_lights
from prt.train.networks.rightsize import validation_split as _validation_split
from prt.train.networks.fit import FitSettings, fit_segment, _predict, _as_input, total_transfer, brightness
from prt.train.networks.network import Architecture
from prt.runtime.shading import tonemap

build, s = sys.argv[1], int(sys.argv[2])
variants = sys.argv[3:] or ["l1", "relative:0.02"]
spec = json.load(open(f"{build}/build.json"))["spec"]
d = load_precompute(f"{build}/precompute")
samples, valid, members = d["samples"], d["validation"], d["members"]
assert spec["bounces"] == 0
member_idx = members[s]
own_idx = member_idx[samples["segment"][member_idx] == s]
vsel, held = _validation_split(s, valid, own_idx, spec["seed"])
assert held is None
vp, vn, vt = valid["points"][vsel], valid["normals"][vsel], valid["transfer"][vsel]
p, n, t = samples["points"][member_idx], samples["normals"][member_idx], samples["transfer"][member_idx]
import os
if os.environ.get("SIDE"):
    sgn = 1 if os.environ["SIDE"] == "inside" else -1
    keep = sgn * (n * -p).sum(1) > 0; p, n, t = p[keep], n[keep], t[keep]
    keep = sgn * (vn * -vp).sum(1) > 0; vp, vn, vt = vp[keep], vn[keep], vt[keep]
    print("side", os.environ["SIDE"], len(p), len(vp))
bounds = np.array([p.min(axis=0), p.max(axis=0)]); bounds = bounds + np.array([[-1.0], [1.0]]) * 0.01 * np.maximum(bounds[1] - bounds[0], 1e-3)
L = _env_lights(4)["potsdamer"]
arch = Architecture(hidden=spec["fixed"]["hidden"], layers=spec["fixed"]["layers"])
m = brightness(vt, 16)
groups = {"dim (DC<0.1)": m < 0.1, "bright": m >= 0.1}
import prt.train.networks.fit as F
_orig = F.loss_weights
arch0, steps0 = arch, spec["steps"]
for v in variants:
    v, *extra = v.split("@")
    arch = Architecture(hidden=int(extra[0].split("x")[0]), layers=int(extra[0].split("x")[1])) if extra else arch0
    spec["steps"] = int(extra[1]) if len(extra) > 1 else steps0
    loss, _, floor = v.partition(":")
    floor, _, power = floor.partition(":")
    if loss == "norm":
        loss = "relative"
        def lw(transfer, n, loss="relative", floor=0.05):
            if loss == "l1": return None
            tt = F.total_transfer(np.asarray(transfer, np.float64), n)
            m = np.linalg.norm(tt, axis=1)
            m = m if m.ndim == 1 else m.mean(1)
            w = 1.0 / (floor + m)
            return (w / w.mean()).astype(np.float32)
        F.loss_weights = lw
    elif power:
        def lw(transfer, n, loss="relative", floor=0.02, _p=float(power)):
            if loss == "l1": return None
            w = 1.0 / (floor + F.brightness(transfer, n)) ** _p
            return (w / w.mean()).astype(np.float32)
        F.loss_weights = lw
    else:
        F.loss_weights = _orig
    fs = FitSettings(epochs=None, batch=spec["batch"], lr=spec["lr"], patience=spec["patience"], seed=spec["seed"], steps=spec["steps"], loss=loss,
                     **({"loss_floor": float(floor)} if floor else {}))
    t0 = time.time()
    r = fit_segment(p, n, t, vp, vn, vt, arch, bounds, fs)
    pred = _predict(r.model, _as_input(vp, vn))
    shp, sht = np.maximum(pred @ L, 0), np.maximum(vt @ L, 0)
    tm = lambda x: tonemap(x, 2.0).astype(np.float64)
    line = f"seg {s} {v:>14}: val MAE {r.val_mae:.5f} steps {r.steps} {time.time()-t0:.0f}s |"
    for g, sel in groups.items():
        rel = np.abs(shp[sel] - sht[sel]).mean(1) / np.maximum(sht[sel].mean(1), 1e-4)
        mse = ((tm(shp[sel]) - tm(sht[sel])) ** 2).mean()
        line += f" {g} n={sel.sum()} MAE {np.abs(pred[sel]-vt[sel]).mean():.5f} med rel {np.median(rel):.3f} tm-PSNR {10*np.log10(1/mse):.2f} |"
    pt = _predict(r.model, _as_input(p, n)); mt = brightness(t, 16); sel = mt < 0.1
    relt = np.abs(np.maximum(pt[sel] @ L, 0) - np.maximum(t[sel] @ L, 0)).mean(1) / np.maximum(np.maximum(t[sel] @ L, 0).mean(1), 1e-4)
    line += f" TRAIN dim med rel {np.median(relt):.3f} | {arch.label()} {spec['steps']}"
    print(line, flush=True)
