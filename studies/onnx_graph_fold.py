"""How much of a k = 64 network call would a leaner ONNX graph of the encoding save?

usage: python studies/onnx_graph_fold.py SCENE.json [--rows 4096] [--repeats 30] [--json out.json]

The exported graph (``prt.export.onnx_model``) spends ~40 % of a k = 64 call outside the
MLP's Gemms: Split, Sub, Mul (broadcast over 3 columns), Sin and Cos of two angle matrices,
Concat, and Mul + Add on the output.  This builds, from the same weights, a *folded* graph
that computes the same function with fewer, larger operations:

- the position's centring and scaling as one Gemm of the 6-wide input (a 6x3 selector holding
  the scale, the centre in the bias), the normal as one MatMul with a selector;
- every angle (position and normal, sine and cosine) from one Gemm of ``[p, n]``, with the
  cosines' pi/2 phase in the bias (cos x = sin(x + pi/2)), then one Sin;
- layer 0's weight rows permuted to the new feature order;
- the output's ``* out_scale + out_offset`` as one 16x16 diagonal Gemm (a residual network's
  ``q(n) @ out_normal_quad`` after it, as exported).

For every network segment of a scene built by ``prt-train`` (``precompute/`` beside
``scene.json``) both graphs run one slice of ``--rows`` surface points on one thread,
alternating so that machine noise hits them alike.  Reported per segment and as medians: the
time per call, the speed-up, and the largest difference between the two graphs' outputs on
the held-out samples (it should be float32 rounding, ~1e-6).  Nothing here changes the
exported files; it measures whether changing them would pay.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from prt.bench.segment_study import StudyError, study_parser, interleaved_ms, network_segments, session, write_report
from prt.export.onnx_model import LEAKY_SLOPE, NORMAL_EPS, OPSET, POSITION_CLIP, read_arrays


def folded_model(arrays: dict[str, np.ndarray], architecture: dict) -> bytes:
    """The folded graph (see the module docstring) of one exported network, serialised."""
    F, G = int(architecture["pos_freqs"]), int(architecture["normal_freqs"])
    layers, outputs = int(architecture["layers"]), int(architecture["bands"]) ** 2
    nodes, inits = [], []

    def const(name, value):
        inits.append(numpy_helper.from_array(np.asarray(value, dtype=np.float32), name))

    def add(op, ins, outs, **kw):
        nodes.append(helper.make_node(op, ins, outs, **kw))

    scale, centre = arrays["enc_inv_half"], arrays["enc_centre"]
    select_p = np.zeros((6, 3), np.float32)
    select_p[:3] = np.diag(scale)
    select_n = np.zeros((6, 3), np.float32)
    select_n[3:] = np.eye(3)
    const("select_p", select_p)
    const("select_p_bias", -centre * scale)
    const("select_n", select_n)
    const("clip_lo", -POSITION_CLIP)
    const("clip_hi", POSITION_CLIP)
    const("normal_eps", NORMAL_EPS)
    add("Gemm", ["x", "select_p", "select_p_bias"], ["p_scaled"])
    add("Clip", ["p_scaled", "clip_lo", "clip_hi"], ["p_enc"])
    add("MatMul", ["x", "select_n"], ["n_raw"])
    add("ReduceL2", ["n_raw"], ["n_len"], axes=[1], keepdims=1)
    add("Max", ["n_len", "normal_eps"], ["n_len_safe"])
    add("Div", ["n_raw", "n_len_safe"], ["n_enc"])
    add("Concat", ["p_enc", "n_enc"], ["pn"], axis=1)
    # exported feature order: [p, sin p, cos p, n, sin n, cos n]; folded: [p, n, sin p, cos p, sin n, cos n]
    w0 = arrays["layer0_weight"]
    p_end = 3 + 6 * F
    order = [*range(0, 3), *range(p_end, p_end + 3), *range(3, p_end), *range(p_end + 3, p_end + 3 + 6 * G)]
    features = "pn"
    if F + G > 0:
        angle_w = np.zeros((6, 6 * (F + G)), np.float32)
        angle_b = np.zeros(6 * (F + G), np.float32)
        if F:
            angle_w[:3, : 3 * F] = angle_w[:3, 3 * F : 6 * F] = arrays["enc_pos_freq"]
            angle_b[3 * F : 6 * F] = np.pi / 2
        if G:
            angle_w[3:, 6 * F : 6 * F + 3 * G] = angle_w[3:, 6 * F + 3 * G :] = arrays["enc_normal_freq"]
            angle_b[6 * F + 3 * G :] = np.pi / 2
        const("angle_w", angle_w)
        const("angle_b", angle_b)
        add("Gemm", ["pn", "angle_w", "angle_b"], ["angles"])
        add("Sin", ["angles"], ["waves"])
        add("Concat", ["pn", "waves"], ["features"], axis=1)
        features = "features"
    const("layer0_weight", w0[order])
    h = features
    for i in range(layers):
        if i:
            const(f"layer{i}_weight", arrays[f"layer{i}_weight"])
        const(f"layer{i}_bias", arrays[f"layer{i}_bias"])
        add("Gemm", [h, f"layer{i}_weight", f"layer{i}_bias"], [f"pre{i}"])
        add("LeakyRelu", [f"pre{i}"], [f"h{i}"], alpha=LEAKY_SLOPE)
        h = f"h{i}"
    const("out_weight", arrays["out_weight"])
    const("out_bias", arrays["out_bias"])
    const("out_scale_diag", np.diag(arrays["out_scale"]))
    const("out_offset", arrays["out_offset"])
    add("Gemm", [h, "out_weight", "out_bias"], ["out_pre"])
    add("Tanh", ["out_pre"], ["out_tanh"])
    residual = "out_normal_quad" in arrays
    add("Gemm", ["out_tanh", "out_scale_diag", "out_offset"], ["out_shifted" if residual else "transfer"])
    if residual:  # + q(n) @ out_normal_quad, the normal's roll as a permutation MatMul
        const("roll", np.eye(3, dtype=np.float32)[:, [1, 2, 0]])
        const("out_normal_quad", arrays["out_normal_quad"])
        add("Mul", ["n_enc", "n_enc"], ["n_squares"])
        add("MatMul", ["n_enc", "roll"], ["n_rolled"])
        add("Mul", ["n_enc", "n_rolled"], ["n_products"])
        add("Concat", ["n_enc", "n_squares", "n_products"], ["n_quad"], axis=1)
        add("MatMul", ["n_quad", "out_normal_quad"], ["unshadowed"])
        add("Add", ["out_shifted", "unshadowed"], ["transfer"])
    graph = helper.make_graph(
        nodes, "folded",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 6])],
        [helper.make_tensor_value_info("transfer", TensorProto.FLOAT, ["N", outputs])],
        initializer=inits,
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="prt-runtime bench")
    model.ir_version = 8
    onnx.checker.check_model(model, full_check=True)
    return model.SerializeToString()


def main(argv=None) -> int:
    p = study_parser(__doc__.splitlines()[0])
    args = p.parse_args(argv)

    try:
        segments = network_segments(args.scene)
    except StudyError as exc:
        print(f"onnx_graph_fold: error: {exc}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(0)
    rows = []
    for item in segments:
        seg = item.segment
        arrays, arch = read_arrays(seg.model)
        sessions = {"exported": session(seg.model), "folded": session(folded_model(arrays, arch))}
        out = {k: s.run(None, {"x": item.held})[0] for k, s in sessions.items()}
        diff = float(np.abs(out["folded"] - out["exported"]).max())
        x = item.train[rng.choice(len(item.train), args.rows, replace=len(item.train) < args.rows)]
        ms = interleaved_ms(sessions, x, args.repeats)
        row = {"segment": seg.id, "arch": arch, "ms": ms, "speedup": ms["exported"] / ms["folded"], "max_abs_diff": diff}
        rows.append(row)
        print(f"segment {seg.id}: exported {ms['exported']:.2f} ms, folded {ms['folded']:.2f} ms "
              f"({row['speedup']:.2f}x), largest output difference {diff:.1e}")  # fmt: skip
    summary = {"speedup": float(np.median([r["speedup"] for r in rows])), "max_abs_diff": max(r["max_abs_diff"] for r in rows)}
    print(f"median over segments: {summary['speedup']:.2f}x; largest output difference {summary['max_abs_diff']:.1e}")
    write_report(args.json, args.scene, args.rows, args.repeats, rows, summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
