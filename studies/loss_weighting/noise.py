import numpy as np, glob
d = np.load("/tmp/loss/diag_b0_v0.npz")
f0 = glob.glob("/tmp/loss/cb/reference/v0-256-r256-s0-*.npz")[0]; f1 = glob.glob("/tmp/loss/cb/reference/v0-256-r256-s1-*.npz")[0]
t0 = np.load(f0)["transfer"].astype(np.float64); t1 = np.load(f1)["transfer"].astype(np.float64)
ref, net, obj = d["ref"], d["net"], d["objects"]
# shaded ratio: radiance is albedo * T.L; the relative difference does not depend on albedo
L_rows = None
lum = lambda x: x.mean(1)
r1 = ref * 0
import sys
from prt.train.build import _env_lights
L = _env_lights(4)["potsdamer"]
s0, s1 = t0 @ L, t1 @ L
tn = d["tnet"][:, :16] @ L
for o, name in ((0, "floor"), (1, "ceiling"), (2, "backWall"), (3, "rightWall"), (4, "leftWall")):
    m = obj == o
    a, b, c = s0[m].mean(1), s1[m].mean(1), tn[m].mean(1)
    print(f"{name:>10}: median |ref_s1-ref_s0|/ref {np.median(np.abs(b-a)/np.abs(a)):.3f}  median |net-ref_s0|/ref {np.median(np.abs(c-a)/np.abs(a)):.3f}  |net-avg|/avg {np.median(np.abs(c-(a+b)/2)/np.abs((a+b)/2)):.3f}  mean signed (net-avg)/avg {np.mean((c-(a+b)/2))/np.mean((a+b)/2):+.3f}")
