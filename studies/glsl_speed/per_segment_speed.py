"""Per-fragment speed of the older per-segment GLSL of one ONNX network on llvmpipe (docs/benchmarks/glsl_compile.md).

usage: python studies/glsl_speed/per_segment_speed.py NETWORK.onnx texture|const

(``compact_speed.py`` leaves its random network in $TMPDIR/exp_kK_lL.onnx.)
"""
import os, sys, time
os.environ.setdefault("MESA_SHADER_CACHE_DISABLE", "true")
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2] / "tests"))
import numpy as np
from test_glsl import hard_inputs
from prt.export.glsl import evaluate_glsl
from prt.runtime.gl import create_context
ctx = create_context()
path = sys.argv[1]; layout = sys.argv[2]
x = hard_inputs(256*256)
t0 = time.perf_counter(); evaluate_glsl(ctx, path, x[:16], layout=layout); t1 = time.perf_counter()
evaluate_glsl(ctx, path, x, layout=layout); t2 = time.perf_counter()
print(f"{path} {layout}: 16 frags (compile) {t1-t0:.2f}  65536 frags (compile again+run) {t2-t1:.2f}")
