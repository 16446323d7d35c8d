"""Per-fragment speed of one compact GLSL network on llvmpipe (docs/benchmarks/glsl_compile.md).

usage: python studies/glsl_speed/compact_speed.py K L [rgb]

Exports a random k x l frequency network to ONNX (in $TMPDIR), evaluates its compact function over
65,536 fragments and prints the link, first-draw and draw seconds and the error against ONNX Runtime.
"""
import os, sys, time
os.environ.setdefault("MESA_SHADER_CACHE_DISABLE", "true")
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2] / "tests"))
import numpy as np, torch, moderngl
torch.set_num_threads(1)
from pathlib import Path
from test_glsl import export_random, onnxruntime_transfer, hard_inputs
from prt.train.networks.network import Architecture
from prt.export import glsl_compact as gc
from prt.runtime.gl import create_context, run_fragment_program
from prt.shaders import assemble
ctx = create_context()
k, l = int(sys.argv[1]), int(sys.argv[2])
rgb = len(sys.argv) > 3
arch = Architecture(hidden=k, layers=l, pos_freqs=6, normal_freqs=2, **({"outputs": 64} if rgb else {}))
path = export_random(Path(__import__("tempfile").gettempdir()) / f"exp_k{k}_l{l}.onnx", arch)
src = gc.freq_source(path)
fn = [ln.split()[5] for ln in src.splitlines() if ln.startswith(gc.FORMAT_LINE)][0]
tex = gc.weights_array(gc.freq_texels(path))
outs = int(src.split("outputs ")[1].split()[0])
cnt = min(outs, 8)
main = f"""
uniform sampler2D u_position; uniform sampler2D u_normal;
layout(location = 0) out vec4 f_out[{cnt}];
{src}
void main() {{ ivec2 px = ivec2(gl_FragCoord.xy); vec4 t[{outs}];
 {fn}(0, texelFetch(u_position, px, 0).xyz, texelFetch(u_normal, px, 0).xyz, t);
 for (int j = 0; j < {cnt}; ++j) f_out[j] = t[j]; }}
"""
full = assemble("transfer_weights.glsl", fills={}) .replace("#version 330\n", "#version 330\n") + main
x = hard_inputs(256*256)
t0 = time.perf_counter()
prog = ctx.program(vertex_shader=assemble("fullscreen.vert"), fragment_shader=full)
t1 = time.perf_counter()
w = ctx.texture((tex.shape[1], tex.shape[0]), 4, tex.tobytes(), dtype="f4"); w.filter = (moderngl.NEAREST, moderngl.NEAREST)
out = run_fragment_program(ctx, prog, {"u_position": x[:16, :3], "u_normal": x[:16, 3:]}, 4*cnt, attachments=cnt, textures={"prt_weights": w})
t2 = time.perf_counter()
out = run_fragment_program(ctx, prog, {"u_position": x[:, :3], "u_normal": x[:, 3:]}, 4*cnt, attachments=cnt, textures={"prt_weights": w})
t3 = time.perf_counter()
ref = onnxruntime_transfer(path, x)[:, :4*cnt]
print(f"k{k} l{l} chars {len(src)} link {t1-t0:.2f} first draw {t2-t1:.2f} 65536 frags {t3-t2:.2f} maxerr {np.abs(out-ref).max():.2e}")
