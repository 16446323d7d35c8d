"""Loop-free GLSL of an SDF network (``*.sdf.onnx``), for sphere tracing in a shader.

The transfer networks' generator (:func:`prt.export.glsl.generate_glsl`) writes every layer
as a loop over ``mat4`` blocks, about 900 loop iterations per evaluation of a 64x4 network.
That is fine once per pixel, but a sphere tracer evaluates the network inside its own step
loop, and Mesa's llvmpipe ends **every** loop of a shader invocation once 65535 iterations
have run in total (``LP_MAX_TGSI_LOOP_ITERATIONS``, one counter shared by all loops, per
SIMD group of pixels), silently: past about 70 evaluations a 64x4 network's layer loops stop
at once and it returns a constant.  On the bunny (64x4, 128x128) that broke 18 % of the
G-buffer pixels: hits where the network is not zero, normals from a constant field (pointing
into the solid at 1.8 % of the pixels), so their shadow rays started inside the solid.

This writes the same arithmetic with no loop at all: constant ``mat4`` arrays indexed by
constants, one statement per 4 outputs of a layer.  Only the sphere tracer's own loop is
left, so the limit is never near.  The values are the ONNX initialisers (float32 literals
that read back exactly) and the summation is the ONNX graph's up to rounding order, so the
GLSL agrees with ONNX Runtime and numpy to float32 rounding (``tests/test_neural_sdf.py``).

Supported: the networks of :func:`prt.train.sdf.neural.fit_neural_sdf` (one output; the
normal input is fed 0, so its rows drop out and the cosines of its frequencies, all 1, fold
into the first bias).
"""

from __future__ import annotations

import math
from string import Template

import numpy as np

from ...shaders import source as shader_source
from ...export.onnx_model import LEAKY_SLOPE, POSITION_CLIP

__all__ = ["network_glsl", "activation_glsl"]


def _lit(v) -> str:
    """A GLSL float literal that reads back as exactly this float32 (numpy's shortest repr)."""
    v = np.float32(v)
    if not np.isfinite(v):
        raise ValueError(f"no GLSL literal for {v}")
    text = str(v)
    return text if any(c in text for c in ".e") else text + ".0"


def _vec4(values) -> str:
    return "vec4(" + ", ".join(_lit(x) for x in values) + ")"


def _blocks(w: np.ndarray) -> tuple[np.ndarray, int, int]:
    """(in, out) weight -> mat4 blocks (n_out * n_in, 4, 4), block (i, o) at ``o * n_in + i``,
    column ``c`` = row ``4i + c`` of the zero-padded weight (so ``M * x_i`` adds x_i's share)."""
    n_in, n_out = math.ceil(w.shape[0] / 4), math.ceil(w.shape[1] / 4)
    padded = np.zeros((4 * n_in, 4 * n_out), dtype=np.float32)
    padded[: w.shape[0], : w.shape[1]] = w
    blocks = padded.reshape(n_in, 4, n_out, 4).transpose(2, 0, 1, 3).reshape(n_out * n_in, 4, 4)
    return blocks, n_in, n_out


def activation_glsl(name: str) -> str:
    """GLSL expression of the hidden activation applied to ``vec4 z``."""
    if name == "leaky_relu":
        return f"max(z, {_lit(LEAKY_SLOPE)} * z)"
    raise ValueError(f"unknown activation {name!r}")


def network_glsl(arrays: dict, arch: dict, fn: str, activation: str = "leaky_relu") -> str:
    """GLSL defining ``float <fn>(vec3 position)``: the first output of the network.

    Parameters
    ----------
    arrays : dict
        The ONNX initialisers (:func:`prt.export.onnx_model.read_arrays`).
    arch : dict
        Its recorded architecture.
    fn : str
        Function name; helpers and constants are named ``<fn>_...``.
    activation : str
        The hidden activation (``"leaky_relu"``, the exporter's).
    """
    a = {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()}
    layers, pos_freqs = int(arch["layers"]), int(arch["pos_freqs"])
    normal_freqs = int(arch.get("normal_freqs", 0))
    p3, q3 = 3 * pos_freqs, 3 * normal_freqs
    constants, body = [], []

    # features in vec4 groups: (x, 0), sin(angles) 4 at a time, cos(angles) 4 at a time
    chunks = math.ceil(p3 / 4)
    centre = ", ".join(_lit(v) for v in a["enc_centre"][:3])
    inv_half = ", ".join(_lit(v) for v in a["enc_inv_half"][:3])
    clip = _lit(POSITION_CLIP)
    body.append(f"    vec3 x = clamp((position - vec3({centre})) * vec3({inv_half}), -{clip}, {clip});")
    features, rows = ["vec4(x, 0.0)"], [0, 1, 2, -1]
    if chunks:
        freq = np.zeros((3, 4 * chunks), dtype=np.float32)
        freq[:, :p3] = a["enc_pos_freq"]
        for j in range(chunks):
            cols = freq[:, 4 * j : 4 * j + 4]
            body.append(f"    vec4 a{j} = x.x * {_vec4(cols[0])} + x.y * {_vec4(cols[1])} + x.z * {_vec4(cols[2])};")
        for kind, first in (("sin", 3), ("cos", 3 + p3)):
            for j in range(chunks):
                features.append(f"{kind}(a{j})")
                rows += [first + 4 * j + c if 4 * j + c < p3 else -1 for c in range(4)]
    for i, expr in enumerate(features):
        body.append(f"    vec4 f{i} = {expr};")

    w0 = a["layer0_weight"] if layers else a["out_weight"]
    b0 = (a["layer0_bias"] if layers else a["out_bias"]).astype(np.float64)
    normal_start = 3 + 2 * p3
    if q3:  # the normal input is 0: sin(0) = 0 drops, cos(0) = 1 adds its rows to the bias
        b0 = b0 + w0[normal_start + 3 + q3 : normal_start + 3 + 2 * q3].astype(np.float64).sum(axis=0)
    order = np.array(rows)
    first = np.zeros((len(order), w0.shape[1]), dtype=np.float32)
    first[order >= 0] = w0[order[order >= 0]]
    b0 = b0.astype(np.float32)

    inputs = [f"f{i}" for i in range(len(features))]
    for layer in range(layers + 1):
        last = layer == layers
        weight = first if layer == 0 else a["out_weight" if last else f"layer{layer}_weight"]
        bias = b0 if layer == 0 else a["out_bias" if last else f"layer{layer}_bias"]
        name = f"{fn}_{'wo' if last else f'w{layer}'}"
        if last:  # one output: dot products with vec4 rows of the weight column
            column = np.zeros(4 * len(inputs), dtype=np.float32)
            column[: weight.shape[0]] = weight[:, 0]
            items = [_vec4(column[4 * i : 4 * i + 4]) for i in range(len(inputs))]
            constants.append(f"const vec4 {name}[{len(items)}] = vec4[{len(items)}](\n    " + ",\n    ".join(items) + "\n);")
            terms = " + ".join(f"dot({name}[{i}], {x})" for i, x in enumerate(inputs))
            body.append(f"    float z = {_lit(bias[0])} + {terms};")
            break
        blocks, n_in, n_out = _blocks(weight)
        assert n_in == len(inputs), (n_in, len(inputs))
        items = [f"mat4({', '.join(_lit(v) for v in blk.reshape(-1))})" for blk in blocks]
        constants.append(f"const mat4 {name}[{len(items)}] = mat4[{len(items)}](\n    " + ",\n    ".join(items) + "\n);")
        padded = np.zeros(4 * n_out, dtype=np.float32)
        padded[: len(bias)] = bias
        outputs = []
        for o in range(n_out):
            terms = " + ".join(f"{name}[{o * n_in + i}] * {x}" for i, x in enumerate(inputs))
            body.append(f"    vec4 h{layer}_{o} = {fn}_act({_vec4(padded[4 * o : 4 * o + 4])} + {terms});")
            outputs.append(f"h{layer}_{o}")
        inputs = outputs
    body.append("    float e = exp(-2.0 * abs(z));  // tanh(z), finite for any z")
    scale, offset = _lit(a["out_scale"].reshape(-1)[0]), _lit(a["out_offset"].reshape(-1)[0])
    body.append(f"    return sign(z) * (1.0 - e) / (1.0 + e) * {scale} + {offset};")
    constants.append(f"vec4 {fn}_act(vec4 z) {{ return {activation_glsl(activation)}; }}")
    architecture = f"hidden {arch['hidden']}, layers {layers}, pos_freqs {pos_freqs}"
    return Template(shader_source("sdf_network.glsl.tmpl")).substitute(
        fn=fn, architecture=architecture, layers=layers, activation=activation,
        constants="\n\n".join(constants), body="\n".join(body),
    )  # fmt: skip
