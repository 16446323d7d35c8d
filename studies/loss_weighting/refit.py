"""Refit a copied build with another loss: python refit.py SRC DST LOSS [FLOOR]; then the study evaluates DST."""
import dataclasses, json, shutil, sys, time
from pathlib import Path
import torch
torch.set_num_threads(1)
from prt.train import build as B
src, dst, loss = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
floor = float(sys.argv[4]) if len(sys.argv) > 4 and sys.argv[4] != "-" else None
steps = int(sys.argv[5]) if len(sys.argv) > 5 else None
if not dst.exists():
    shutil.copytree(src, dst, symlinks=True)
spec = B.spec_from_dict(json.loads((dst / "build.json").read_text())["spec"])
spec.loss = loss
if len(sys.argv) > 6:
    k, l = sys.argv[6].split("x")
    spec.fixed = {"hidden": int(k), "layers": int(l)}
import os
if os.environ.get("BOUNCE_RAYS"):
    spec.bounce_rays = int(os.environ["BOUNCE_RAYS"])
if steps is not None:
    spec.steps = steps
if floor is not None:
    orig = B.BuildSpec.fit_settings
    B.BuildSpec.fit_settings = lambda self: dataclasses.replace(orig(self), loss_floor=floor)
t0 = time.time()
report = B.run_build(spec, dst, threads=1, progress=False)
print(f"refit {dst} loss={loss} floor={floor}: {time.time()-t0:.0f} s; timings {report['timings']}")
for s in report["segments"]:
    print(f"  seg {s['id']}: {s.get('kind')} val MAE {s['val_mae']:.5f} shaded {s['shaded']}")
