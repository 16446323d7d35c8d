"""Segment networks of one architecture stacked into one ONNX model, built at load time (no ``onnx``
package: the segments' files are read and the stacked model written along the protobuf wire format).

A scene with hundreds of segments would otherwise cost one ONNX Runtime call per segment and frame
(a fixed 13-28 us each before any row, ``docs/benchmarks/many_networks.md``).  The stacked model
evaluates every segment of an architecture in one call, as a grouped GEMM: the rows of each segment
are cut into blocks of ``B`` rows (the last one padded), and the model takes

    x   : float32 [K, B, 6]   the blocks' rows (position, normal)
    seg : int64 [K]           each block's segment, as its index in the stack

Each constant of the segments' files is stacked along a new first axis (``[S, ...]``) and gathered
per block (``Gather(W, seg)``: ``[K, in, out]``), so each layer is one batched ``MatMul``
``[K, B, in] @ [K, in, out]``; the encoding's box, the output scaling, a log-DC head's constants
and a residual network's quadratic term are gathered per block the same way.  The graph repeats
:func:`prt.export.onnx_model.build_model`'s operations on the extra axis, so a block's rows get
what the segment's own file gives them up to float rounding (the GEMM kernels differ).

Only frequency networks (``prt.format`` ``prt-transfer-mlp/1``) without a shape code stack: grid
networks, shape-conditioned ones and files of any other kind keep their own sessions.  Segments
stack together when their files have the same initialisers (names and shapes) and the same
frequency matrices (:func:`stack_key`); :class:`prt.runtime.backends.onnx.OnnxTransfer` checks each
stacked model against the segments' own sessions on probe rows before it uses it.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from .onnxfile import _fields, _Malformed

__all__ = ["read_network", "stack_key", "stacked_model", "block_layout", "MLP_FORMAT", "SHARED"]

MLP_FORMAT = "prt-transfer-mlp/1"
OPSET = 17
LEAKY_SLOPE = 0.01  # prt.export.onnx_model's (the runtime does not import export)
POSITION_CLIP = 2.0
NORMAL_EPS = 1e-8
SHARED = ("enc_pos_freq", "enc_normal_freq")
"""Constants every segment of a stack must share (they are not stacked)."""
_PER_SEGMENT = ("enc_centre", "enc_inv_half", "out_scale", "out_offset", "out_weight", "out_bias")
_CONSTANTS = ("split_sizes", "clip_lo", "clip_hi", "normal_eps", "quad_roll", "head_one")  # build_model's own
_HEAD_SEGMENT = ("out_linear", "out_max")  # a log-DC head's fitted constants: stacked
_HEAD_SHARED = ("out_dc_select", "out_dc_spread", "out_dc_mask")  # its structure: the same in every member
_FLOAT, _INT64 = 1, 7
_DTYPES = {_FLOAT: np.float32, _INT64: np.int64}


# -- reading a segment's file --


def _tensor(message) -> tuple[str, np.ndarray] | None:
    """(name, array) of a TensorProto holding float32 or int64 data, else None."""
    name, dims, dtype, raw, packed = "", [], None, None, None
    for field, wire, value in _fields(message):
        if field == 1:  # dims: one varint each, or packed
            if wire == 0:
                dims.append(value)
            else:
                data, pos = bytes(value), 0
                while pos < len(data):
                    v, pos = _varint_at(data, pos)
                    dims.append(v)
        elif field == 2 and wire == 0:
            dtype = value
        elif field == 8 and wire == 2:
            name = bytes(value).decode("utf-8", "replace")
        elif field == 9 and wire == 2:
            raw = bytes(value)
        elif field == 4 and wire == 2 and dtype in (None, _FLOAT):  # packed float_data
            packed = np.frombuffer(bytes(value), "<f4")
        elif field in (4, 5, 7, 10, 11, 12, 13):  # other data fields: not a tensor we stack
            return None
    if dtype not in _DTYPES:
        return None
    if raw is not None:
        values = np.frombuffer(raw, np.dtype(_DTYPES[dtype]).newbyteorder("<"))
    elif packed is not None:
        values = packed
    else:
        values = np.zeros(0, _DTYPES[dtype])
    if values.size != int(np.prod(dims, dtype=np.int64)):
        return None
    return name, values.astype(_DTYPES[dtype]).reshape(dims)


def _varint_at(data: bytes, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7


def read_network(data: bytes) -> tuple[dict[str, np.ndarray], dict[str, str]] | None:
    """The initialisers (name -> array) and metadata of a serialised segment model, or None when
    it holds a tensor this reader does not take (then the segment is not stacked)."""
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, str] = {}
    try:
        for field, wire, value in _fields(memoryview(data)):
            if field == 14 and wire == 2:  # metadata_props: StringStringEntryProto (key 1, value 2)
                entry = {f: bytes(v).decode("utf-8", "replace") for f, w, v in _fields(value) if w == 2}
                meta[entry.get(1, "")] = entry.get(2, "")
            elif field == 7 and wire == 2:  # graph
                for gfield, gwire, gvalue in _fields(value):
                    if gfield in (5, 15) and gwire == 2:
                        tensor = _tensor(gvalue) if gfield == 5 else None
                        if tensor is None:
                            return None
                        arrays[tensor[0]] = tensor[1]
    except (_Malformed, IndexError, ValueError):
        return None
    return arrays, meta


def stack_key(arrays: dict[str, np.ndarray], meta: dict[str, str]) -> tuple | None:
    """What segments must share to be stacked together (None: this segment is not stackable):
    the format, the initialisers' names and shapes, and the shared frequency matrices' values."""
    if meta.get("prt.format") != MLP_FORMAT or "code_weight" in arrays:
        return None
    layers = 0
    while f"layer{layers}_weight" in arrays:
        layers += 1
    need = set(_PER_SEGMENT) | set(SHARED) | {f"layer{i}_{k}" for i in range(layers) for k in ("weight", "bias")}
    head = set(_HEAD_SEGMENT) | set(_HEAD_SHARED)
    if "out_dc_select" in arrays:  # a log-DC head: all of its arrays
        need |= head
    optional = {"out_normal_quad"} | set(_CONSTANTS)
    if not need <= set(arrays) or not set(arrays) <= need | optional:
        return None
    if any(arrays[k].dtype != np.float32 for k in need | ({"out_normal_quad"} & set(arrays))):
        return None
    shapes = tuple(sorted((k, arrays[k].shape) for k in need | ({"out_normal_quad"} & set(arrays))))
    shared = SHARED + (_HEAD_SHARED if "out_dc_select" in arrays else ())
    return (MLP_FORMAT, layers, shapes) + tuple(arrays[k].tobytes() for k in shared)


# -- writing the stacked model --


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _len(field: int, payload: bytes) -> bytes:
    return _varint(field << 3 | 2) + _varint(len(payload)) + payload


def _int(field: int, value: int) -> bytes:
    return _varint(field << 3) + _varint(value)


def _str(field: int, text: str) -> bytes:
    return _len(field, text.encode())


def _tensor_proto(name: str, array: np.ndarray) -> bytes:
    array = np.ascontiguousarray(array)
    dtype = _FLOAT if array.dtype == np.float32 else _INT64
    dims = b"".join(_int(1, int(d)) for d in array.shape)
    return dims + _int(2, dtype) + _str(8, name) + _len(9, array.astype(array.dtype.newbyteorder("<")).tobytes())


def _attribute(name: str, value) -> bytes:
    if isinstance(value, float):  # FLOAT = 1
        return _str(1, name) + _varint(2 << 3 | 5) + struct.pack("<f", value) + _int(20, 1)
    if isinstance(value, int):  # INT = 2
        return _str(1, name) + _int(3, value) + _int(20, 2)
    return _str(1, name) + b"".join(_int(8, int(v)) for v in value) + _int(20, 7)  # INTS = 7


def _value_info(name: str, elem: int, dims) -> bytes:
    shape = b"".join(_len(1, _str(2, d) if isinstance(d, str) else _int(1, d)) for d in dims)
    return _str(1, name) + _len(2, _len(1, _int(1, elem) + _len(2, shape)))


class _Graph:
    def __init__(self):
        self.nodes: list[bytes] = []
        self.inits: list[bytes] = []

    def init(self, name: str, array) -> str:
        self.inits.append(_tensor_proto(name, np.asarray(array)))
        return name

    def add(self, op: str, inputs, outputs, **attrs) -> None:
        body = b"".join(_str(1, i) for i in inputs) + b"".join(_str(2, o) for o in outputs)
        body += _str(3, f"{op}_{len(self.nodes)}") + _str(4, op)
        body += b"".join(_len(5, _attribute(k, v)) for k, v in attrs.items())
        self.nodes.append(body)


def stacked_model(members: list[dict[str, np.ndarray]], name: str = "stack") -> bytes:
    """A serialised ONNX model evaluating ``members`` (segments' initialisers with one
    :func:`stack_key`) on blocks of rows: inputs ``x`` [K, B, 6] and ``seg`` [K] (int64, an index
    into ``members``), output ``transfer`` [K, B, outputs]."""
    first = members[0]
    layers = 0
    while f"layer{layers}_weight" in first:
        layers += 1
    outputs = first["out_bias"].shape[0]
    g = _Graph()

    def stacked(key: str, values=None, row: bool = False) -> str:
        """Segment constants stacked [S, ...]; a vector as [S, 1, n] (it broadcasts over a block's rows)."""
        values = np.stack([m[key] for m in members] if values is None else values).astype(np.float32)
        if row:
            values = values.reshape(len(members), 1, -1)
        g.init(f"{key}_stack", values)
        g.add("Gather", [f"{key}_stack", "seg"], [f"{key}_block"], axis=0)
        return f"{key}_block"

    def with_bias(key: str, bias: str, carry: bool) -> list[np.ndarray]:
        """Each member's ``[[W, 0], [b, 1]]`` (``carry``: the last column keeps the constant 1 for the
        next layer) or ``[[W], [b]]``: the bias folded into the MatMul through the features' 1."""
        out = []
        for m in members:
            w, b = m[key], m[bias]
            if carry:
                w = np.concatenate([w, np.zeros((w.shape[0], 1), np.float32)], axis=1)
                b = np.concatenate([b, np.ones(1, np.float32)])
            out.append(np.concatenate([w, b[None, :]], axis=0))
        return out

    for key in SHARED:
        g.init(key, first[key])
    g.init("split_sizes", np.array([3, 3], np.int64))
    g.init("clip_lo", np.array(-POSITION_CLIP, np.float32))
    g.init("clip_hi", np.array(POSITION_CLIP, np.float32))
    g.init("normal_eps", np.array(NORMAL_EPS, np.float32))
    g.add("Split", ["x", "split_sizes"], ["p", "n_raw"], axis=2)
    g.add("Sub", ["p", stacked("enc_centre", row=True)], ["p_centred"])
    g.add("Mul", ["p_centred", stacked("enc_inv_half", row=True)], ["p_scaled"])
    g.add("Clip", ["p_scaled", "clip_lo", "clip_hi"], ["p_enc"])
    g.add("ReduceL2", ["n_raw"], ["n_len"], axes=[2], keepdims=1)
    g.add("Max", ["n_len", "normal_eps"], ["n_len_safe"])
    g.add("Div", ["n_raw", "n_len_safe"], ["n_enc"])
    g.add("Div", ["n_len_safe", "n_len_safe"], ["ones"])  # exactly 1 (n_len_safe >= eps > 0): the biases' input
    features = ["p_enc"]
    if first["enc_pos_freq"].shape[1]:
        g.add("MatMul", ["p_enc", "enc_pos_freq"], ["p_angle"])
        g.add("Sin", ["p_angle"], ["p_sin"])
        g.add("Cos", ["p_angle"], ["p_cos"])
        features += ["p_sin", "p_cos"]
    features.append("n_enc")
    if first["enc_normal_freq"].shape[1]:
        g.add("MatMul", ["n_enc", "enc_normal_freq"], ["n_angle"])
        g.add("Sin", ["n_angle"], ["n_sin"])
        g.add("Cos", ["n_angle"], ["n_cos"])
        features += ["n_sin", "n_cos"]
    g.add("Concat", features + ["ones"], ["features"], axis=2)
    h = "features"
    for i in range(layers):  # biases folded into the MatMuls: the features' 1, carried by each layer's last column
        g.add("MatMul", [h, stacked(f"layer{i}_weight", with_bias(f"layer{i}_weight", f"layer{i}_bias", True))], [f"pre{i}"])
        g.add("LeakyRelu", [f"pre{i}"], [f"h{i}"], alpha=LEAKY_SLOPE)  # the carried 1 stays 1
        h = f"h{i}"
    g.add("MatMul", [h, stacked("out_weight", with_bias("out_weight", "out_bias", False))], ["out_pre"])
    g.add("Tanh", ["out_pre"], ["out_tanh"])
    g.add("Mul", ["out_tanh", stacked("out_scale", row=True)], ["out_scaled"])
    residual = "out_normal_quad" in first
    log_dc = "out_dc_select" in first
    g.add("Add", ["out_scaled", stacked("out_offset", row=True)], ["out_shifted" if residual or log_dc else "transfer"])
    if log_dc:  # prt.export.onnx_model.add_log_dc_head's nodes, the fitted constants per block
        for key in _HEAD_SHARED:
            g.init(key, first[key])
        g.init("head_one", np.array(1.0, np.float32))
        g.add("Mul", ["out_pre", stacked("out_linear", row=True)], ["head_linear"])
        g.add("Add", ["out_shifted", "head_linear"], ["head_v"])
        g.add("Min", ["head_v", stacked("out_max", row=True)], ["head_u"])
        g.add("MatMul", ["head_u", "out_dc_select"], ["head_log_dc"])
        g.add("Exp", ["head_log_dc"], ["head_dc"])
        g.add("MatMul", ["head_dc", "out_dc_spread"], ["head_dc_wide"])
        g.add("Sub", ["head_one", "out_dc_mask"], ["head_ratio_mask"])
        g.add("Mul", ["head_u", "head_ratio_mask"], ["head_ratios"])
        g.add("Add", ["head_ratios", "out_dc_mask"], ["head_factors"])
        g.add("Mul", ["head_dc_wide", "head_factors"], ["transfer"])
    if residual:  # q(n) = [n, n * n, n * n.yzx] @ out_normal_quad, per block (one matrix where all share it)
        g.init("quad_roll", np.eye(3, dtype=np.float32)[:, [1, 2, 0]])  # n @ it = n.yzx, exactly
        g.add("Mul", ["n_enc", "n_enc"], ["n_squares"])
        g.add("MatMul", ["n_enc", "quad_roll"], ["n_rolled"])
        g.add("Mul", ["n_enc", "n_rolled"], ["n_products"])
        g.add("Concat", ["n_enc", "n_squares", "n_products"], ["n_quad"], axis=2)
        quads = [m["out_normal_quad"] for m in members]
        if all(np.array_equal(q, quads[0]) for q in quads):
            quad = g.init("out_normal_quad", quads[0])
        else:
            quad = stacked("out_normal_quad")
        g.add("MatMul", ["n_quad", quad], ["unshadowed"])
        g.add("Add", ["out_shifted", "unshadowed"], ["transfer"])
    graph = b"".join(_len(1, n) for n in g.nodes) + _str(2, name) + b"".join(_len(5, t) for t in g.inits)
    graph += _len(11, _value_info("x", _FLOAT, ["K", "B", 6])) + _len(11, _value_info("seg", _INT64, ["K"]))
    graph += _len(12, _value_info("transfer", _FLOAT, ["K", "B", int(outputs)]))
    meta = _len(14, _str(1, "prt.format") + _str(2, "prt-transfer-mlp-stack/1"))
    meta += _len(14, _str(1, "prt.segments") + _str(2, json.dumps(len(members))))
    return _int(1, 8) + _str(2, "prt-runtime") + _len(7, graph) + _len(8, _str(1, "") + _int(2, OPSET)) + meta


# -- the blocks of a frame --


def block_layout(starts: np.ndarray, counts: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blocks of segments' rows: segment ``j`` owns rows ``starts[j] : starts[j] + counts[j]``
    (every count > 0) and gets ``ceil(counts[j] / block)`` blocks of ``block`` rows.

    Returns
    -------
    source : (K, block) intp, the row each slot reads (a block's last row repeated past its end)
    member : (K,) intp, each block's segment as its index ``j``
    valid : (K * block,) intp, the flat slots that hold a row, in row order (``source.ravel()[valid]``
        lists the segments' rows in order)
    """
    starts = np.asarray(starts, np.intp)
    counts = np.asarray(counts, np.intp)
    blocks = -(-counts // block)
    member = np.repeat(np.arange(len(counts)), blocks)
    first_block = np.cumsum(blocks) - blocks  # each segment's first block
    first_row = starts[member] + (np.arange(len(member)) - first_block[member]) * block
    end = (starts + counts)[member]
    source = first_row[:, None] + np.arange(block)[None, :]
    inside = source < end[:, None]
    np.minimum(source, (end - 1)[:, None], out=source)
    return source, member, np.flatnonzero(inside.ravel())
