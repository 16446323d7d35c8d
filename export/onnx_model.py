"""Segment networks as ONNX files, built from plain arrays (no torch needed here).

Graph (opset 17), one input and one output, dynamic batch ``N``:

    x : float32 [N, 6]   position (scene units), normal (any length)
    code : float32 [1, d]   only a shape-conditioned network's (deformable scenes): the frame's shape
           code; its features ``[code, sin(code @ enc_code_freq), cos(...)] @ code_weight`` are added to
           the first layer's output once per call (:mod:`prt.runtime.deformation`)
    transfer : float32 [N, bands^2]   (or [N, architecture["outputs"]]: 4 bands^2 for the
               "direct+rgb" layout of interreflection: direct, then indirect R, G, B)

The encoding is part of the graph (Split, Sub/Mul/Clip, ReduceL2/Max/Div, MatMul, Sin, Cos,
Concat), then ``layers`` x (Gemm, LeakyRelu), Gemm, Tanh, Mul, Add; a log-DC head's then
(:func:`add_log_dc_head`) Mul, Add, Min, MatMul, Exp, MatMul, Sub, Mul, Add, Mul; a residual network's
(:class:`prt.train.networks.network.Architecture`, ``residual``) then adds ``q(n) @ out_normal_quad``
(Mul, Gather, Mul, Concat, MatMul, Add; ``q(n) = [n, n * n, n * n.yzx]`` of the unit normal).  Initialiser names match
:meth:`prt.train.networks.network.TransferMLP.arrays`; the GLSL generator reads the weights back from
the file by those names.  Metadata (``metadata_props``) records the format, SH bands,
architecture, encoding and output scale, so a file explains itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["OPSET", "FORMAT", "LEAKY_SLOPE", "POSITION_CLIP", "NORMAL_EPS", "build_model", "add_log_dc_head", "save_model", "read_arrays", "read_metadata"]

OPSET = 17
FORMAT = "prt-transfer-mlp/1"
LEAKY_SLOPE = 0.01
POSITION_CLIP = 2.0  # normalised positions are clipped to [-2, 2]: finite output anywhere
NORMAL_EPS = 1e-8


def add_log_dc_head(add, inits: list, z: str, shifted: str, output: str) -> None:
    """A log-DC head's nodes after ``shifted`` = tanh(z) * out_scale + out_offset: + z * out_linear,
    Min out_max, the DC columns through MatMul out_dc_select, Exp, MatMul out_dc_spread, times
    the ratios (``u * (1 - out_dc_mask) + out_dc_mask``)."""
    from onnx import numpy_helper

    inits.append(numpy_helper.from_array(np.array(1.0, dtype=np.float32), "head_one"))
    add("Mul", [z, "out_linear"], ["head_linear"])
    add("Add", [shifted, "head_linear"], ["head_v"])
    add("Min", ["head_v", "out_max"], ["head_u"])
    add("MatMul", ["head_u", "out_dc_select"], ["head_log_dc"])
    add("Exp", ["head_log_dc"], ["head_dc"])
    add("MatMul", ["head_dc", "out_dc_spread"], ["head_dc_wide"])
    add("Sub", ["head_one", "out_dc_mask"], ["head_ratio_mask"])
    add("Mul", ["head_u", "head_ratio_mask"], ["head_ratios"])
    add("Add", ["head_ratios", "out_dc_mask"], ["head_factors"])
    add("Mul", ["head_dc_wide", "head_factors"], [output])


def build_model(arrays: dict[str, np.ndarray], architecture: dict, *, name: str = "segment"):
    """An ``onnx.ModelProto`` for one segment network.

    Parameters
    ----------
    arrays : initialiser name -> float32 array (see :meth:`TransferMLP.arrays`)
    architecture : ``{"hidden", "layers", "pos_freqs", "normal_freqs", "bands", "input_dim"}``
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    layers = int(architecture["layers"])
    bands = int(architecture["bands"])
    outputs = int(architecture.get("outputs", bands * bands))  # 4 bands^2 with interreflection ("direct+rgb")
    nodes = []
    inits = [numpy_helper.from_array(np.asarray(v, dtype=np.float32), k) for k, v in sorted(arrays.items())]
    inits += [
        numpy_helper.from_array(np.array([3, 3], dtype=np.int64), "split_sizes"),
        numpy_helper.from_array(np.array(-POSITION_CLIP, dtype=np.float32), "clip_lo"),
        numpy_helper.from_array(np.array(POSITION_CLIP, dtype=np.float32), "clip_hi"),
        numpy_helper.from_array(np.array(NORMAL_EPS, dtype=np.float32), "normal_eps"),
    ]
    add = lambda op, ins, outs, **kw: nodes.append(helper.make_node(op, ins, outs, **kw))  # noqa: E731
    add("Split", ["x", "split_sizes"], ["p", "n_raw"], axis=1)
    add("Sub", ["p", "enc_centre"], ["p_centred"])
    add("Mul", ["p_centred", "enc_inv_half"], ["p_scaled"])
    add("Clip", ["p_scaled", "clip_lo", "clip_hi"], ["p_enc"])
    add("ReduceL2", ["n_raw"], ["n_len"], axes=[1], keepdims=1)
    add("Max", ["n_len", "normal_eps"], ["n_len_safe"])
    add("Div", ["n_raw", "n_len_safe"], ["n_enc"])
    features = ["p_enc"]
    if int(architecture["pos_freqs"]) > 0:
        add("MatMul", ["p_enc", "enc_pos_freq"], ["p_angle"])
        add("Sin", ["p_angle"], ["p_sin"])
        add("Cos", ["p_angle"], ["p_cos"])
        features += ["p_sin", "p_cos"]
    features.append("n_enc")
    if int(architecture["normal_freqs"]) > 0:
        add("MatMul", ["n_enc", "enc_normal_freq"], ["n_angle"])
        add("Sin", ["n_angle"], ["n_sin"])
        add("Cos", ["n_angle"], ["n_cos"])
        features += ["n_sin", "n_cos"]
    add("Concat", features, ["features"], axis=1)
    h = "features"
    coded = "code_weight" in arrays
    if coded:  # the shape code's features, one row: added to the first layer's output (its bias per frame)
        code_parts = ["code"]
        if np.asarray(arrays["enc_code_freq"]).shape[1]:
            add("MatMul", ["code", "enc_code_freq"], ["code_angle"])
            add("Sin", ["code_angle"], ["code_sin"])
            add("Cos", ["code_angle"], ["code_cos"])
            code_parts += ["code_sin", "code_cos"]
        add("Concat", code_parts, ["code_features"], axis=1)
        add("MatMul", ["code_features", "code_weight"], ["code_bias"])
    for i in range(layers):
        add("Gemm", [h, f"layer{i}_weight", f"layer{i}_bias"], [f"pre{i}"])
        if coded and i == 0:
            add("Add", ["pre0", "code_bias"], ["pre0_coded"])
        add("LeakyRelu", ["pre0_coded" if coded and i == 0 else f"pre{i}"], [f"h{i}"], alpha=LEAKY_SLOPE)
        h = f"h{i}"
    add("Gemm", [h, "out_weight", "out_bias"], ["out_pre"])
    add("Tanh", ["out_pre"], ["out_tanh"])
    add("Mul", ["out_tanh", "out_scale"], ["out_scaled"])
    residual = "out_normal_quad" in arrays
    log_dc = "out_dc_select" in arrays
    add("Add", ["out_scaled", "out_offset"], ["out_shifted" if residual or log_dc else "transfer"])
    if log_dc:  # each group's DC = exp(its capped log), the other columns ratios to it (prt.train.networks.network)
        add_log_dc_head(add, inits, "out_pre", "out_shifted", "transfer")
    if residual:  # q(n) = [n, n * n, n * n.yzx] @ out_normal_quad: the unshadowed transfer's quadratic part
        inits.append(numpy_helper.from_array(np.array([1, 2, 0], dtype=np.int64), "quad_roll"))
        add("Mul", ["n_enc", "n_enc"], ["n_squares"])
        add("Gather", ["n_enc", "quad_roll"], ["n_rolled"], axis=1)
        add("Mul", ["n_enc", "n_rolled"], ["n_products"])
        add("Concat", ["n_enc", "n_squares", "n_products"], ["n_quad"], axis=1)
        add("MatMul", ["n_quad", "out_normal_quad"], ["unshadowed"])
        add("Add", ["out_shifted", "unshadowed"], ["transfer"])
    graph = helper.make_graph(
        nodes,
        name,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 6])]
        + ([helper.make_tensor_value_info("code", TensorProto.FLOAT, [1, int(np.asarray(arrays["enc_code_freq"]).shape[0])])] if coded else []),
        [helper.make_tensor_value_info("transfer", TensorProto.FLOAT, ["N", outputs])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="prt-runtime")
    model.ir_version = 8  # readable by onnxruntime >= 1.10
    meta = {
        "prt.format": FORMAT,
        "prt.sh_bands": str(bands),
        "prt.architecture": json.dumps(architecture, sort_keys=True),
        "prt.encoding": json.dumps(
            {
                "position": "clip((p - enc_centre) * enc_inv_half, -2, 2); sin/cos of (x @ enc_pos_freq)",
                "normal": f"n / max(|n|, {NORMAL_EPS}); sin/cos of (n @ enc_normal_freq)",
                "features": "[p, sin_p, cos_p, n, sin_n, cos_n]",
                "activation": f"leaky_relu({LEAKY_SLOPE})",
                "output": "tanh(z) * out_scale + out_offset" + (" + [n, n * n, n * n.yzx] @ out_normal_quad (residual network)" if residual else "")
                + ("; log-DC head: u = min(that + z * out_linear, out_max), T = (exp(u @ out_dc_select) @ out_dc_spread) * "
                   "(u * (1 - out_dc_mask) + out_dc_mask)" if log_dc else ""),
            }
        ),
        "prt.output_scale": json.dumps(np.asarray(arrays["out_scale"]).tolist()),
        "prt.output_offset": json.dumps(np.asarray(arrays["out_offset"]).tolist()),
        "prt.input": "x float32 [N, 6]: position (scene units), normal" + ("; code float32 [1, d]: the frame's shape code" if coded else ""),
    }
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    return model


def save_model(model, path) -> None:
    """Write an ONNX model atomically."""
    from ..runtime.files import atomic_write_bytes

    atomic_write_bytes(Path(path), model.SerializeToString())


def read_arrays(path) -> tuple[dict[str, np.ndarray], dict]:
    """Initialisers (name -> float32 array) and the architecture recorded in an exported file."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    arrays = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    meta = {p.key: p.value for p in model.metadata_props}
    if meta.get("prt.format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} model (prt.format = {meta.get('prt.format')!r})")
    return arrays, json.loads(meta["prt.architecture"])


def read_metadata(path) -> dict[str, str]:
    import onnx

    return {p.key: p.value for p in onnx.load(str(path)).metadata_props}
