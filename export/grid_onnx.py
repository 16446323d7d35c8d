"""A grid-encoded segment network (``prt.train.networks.grid_encoding``) as an ONNX file (and as GLSL), built from plain
arrays (no torch here; this module never imports ``prt.train``).

Graph (opset 18: ``BitwiseXor`` / ``BitwiseAnd`` and the Reduce* ops with ``axes`` as an input),
one input and one output, dynamic batch ``N``:

    x : float32 [N, 6]   position (scene units), normal (any length)
    transfer : float32 [N, bands^2]

    x_n  = Clip((p - enc_centre) * enc_inv_half, -1, 1);  u = x_n * 0.5 + 0.5
    pos  = u @ spread                                 (N, 24 L): column a 8 L + k L + l = u_a N_l
    i0   = Min(Floor(pos), N_l - 1);  w = pos - i0;  w_k = bit ? w : 1 - w (as bit w + (1 - bit) (1 - w))
    c    = Cast<int64>(i0 + bit) * (hashed_l ? P_a : (N_l + 1)^a)
    rows = Where(hashed_l, BitwiseAnd(BitwiseXor(c_x, c_y, c_z), T - 1), c_x + c_y + c_z) + offset_l
    f    = Concat_f(Gather(grid_table_f, rows) * w_x w_y w_z) @ corner_sum             (N, L F)
    h    = [f, x_n (if the network takes it), n / max(|n|, eps), sin/cos(n @ enc_normal_freq)]
    then ``layers`` x (Gemm, LeakyRelu), Gemm, Tanh, Mul, Add.

:func:`glsl_function` writes the same network as GLSL 3.30 (the table and the MLP weights in one texture
read with ``texelFetch``, :func:`table_texture`; the hash in ``uint``), a function per segment; scenes
are exported in the compact form built on it (:func:`prt.export.glsl_compact.grid_source`: one function
per architecture, the box and output scaling in the texture too).

The table can be stored as float16 (``table_dtype="float16"``, a Cast to float32 in the graph).
The level constants are recorded in the metadata (``prt.grid``), so :func:`read_arrays` gives back
the arrays ``prt.train.networks.grid_encoding.evaluate_numpy`` takes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .onnx_model import LEAKY_SLOPE, NORMAL_EPS

__all__ = ["OPSET", "FORMAT", "PRIMES", "build_grid_model", "save_grid_model", "read_arrays", "LEVEL_KEYS"]

OPSET = 18
FORMAT = "prt-transfer-grid/1"
PRIMES = (1, 2654435761, 805459861)
LEVEL_KEYS = ("grid_resolution", "grid_hashed", "grid_size", "grid_offset", "grid_table_size", "mlp_position")


def _layers(arrays) -> int:
    i = 0
    while f"layer{i}_weight" in arrays:
        i += 1
    return i


def build_grid_model(arrays: dict[str, np.ndarray], architecture: dict | None = None, *, name: str = "segment", table_dtype: str = "float32"):
    """An ``onnx.ModelProto`` for one grid-encoded segment network.

    Parameters
    ----------
    arrays : as ``GridTransfer.arrays()``: ``enc_centre``, ``enc_inv_half``, ``enc_normal_freq``,
        ``grid_table`` (rows, F), the level constants :data:`LEVEL_KEYS`, ``layer{i}_weight``
        (in, out), ``layer{i}_bias``, ``out_weight``, ``out_bias``, ``out_scale``, ``out_offset``
    architecture : recorded in the metadata as it is (e.g. ``GridArchitecture.as_dict()``)
    table_dtype : "float32" or "float16" (the table's storage; computed in float32)
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    res = np.asarray(arrays["grid_resolution"], dtype=np.int64)
    hashed = np.asarray(arrays["grid_hashed"], dtype=bool)
    offsets = np.asarray(arrays["grid_offset"], dtype=np.int64)
    table_size = int(arrays["grid_table_size"])
    if table_size & (table_size - 1):
        raise ValueError(f"the hashed table size must be a power of two, got {table_size}")
    levels = len(res)
    table = np.asarray(arrays["grid_table"], dtype=np.float32)
    features = table.shape[1]
    layers = _layers(arrays)
    outputs = int(np.asarray(arrays["out_bias"]).shape[0])
    # Every per-level, per-corner, per-axis quantity is a column of an (N, K) tensor, so each
    # operator broadcasts at most one constant row over N (ONNX Runtime's fast path; 4-D broadcasts
    # over tiny axes and column Gathers ran several times slower).  Column a 8 L + k L + l: axis a,
    # corner k, level l; the grid features come out as column l F + f.
    bit = lambda k, a: (k >> a) & 1  # noqa: E731
    ak = [(a, k, lv) for a in range(3) for k in range(8) for lv in range(levels)]  # (24 L,) columns
    spread = np.zeros((3, 24 * levels), np.float32)  # u @ spread = u_a N_l in every column
    for j, (a, k, lv) in enumerate(ak):
        spread[a, j] = res[lv]
    corner_sum = np.zeros((features * 8 * levels, levels * features), np.float32)  # sums the 8 corners
    for f in range(features):
        for k in range(8):
            for lv in range(levels):
                corner_sum[f * 8 * levels + k * levels + lv, lv * features + f] = 1.0
    bits = np.array([bit(k, a) for a, k, lv in ak], np.float32)
    consts = {
        "clip_lo": np.array(-1.0, np.float32),
        "clip_hi": np.array(1.0, np.float32),
        "half": np.array(0.5, np.float32),
        "one": np.array(1.0, np.float32),
        "normal_eps": np.array(NORMAL_EPS, np.float32),
        "split_sizes": np.array([3, 3], np.int64),
        "split_axes": np.array([8 * levels] * 3, np.int64),
        "axis1": np.array([1], np.int64),
        "level_spread": spread,
        "level_res_m1": np.array([res[lv] - 1 for a, k, lv in ak], np.float32),
        "corner_on": bits,
        "corner_off": 1.0 - bits,
        "corner_mult": np.array([PRIMES[a] if hashed[lv] else (res[lv] + 1) ** a for a, k, lv in ak], np.int64),
        "hash_mask": np.array(table_size - 1, np.int64),
        "level_hashed": np.array([bool(hashed[lv]) for k in range(8) for lv in range(levels)]),
        "level_offset": np.array([offsets[lv] for k in range(8) for lv in range(levels)], np.int64),
        "corner_sum": corner_sum,
    }
    nodes = []
    inits = [numpy_helper.from_array(v, k) for k, v in consts.items()]
    weights = {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items() if k.startswith(("enc_", "layer", "out_")) and np.size(v)}
    inits += [numpy_helper.from_array(v, k) for k, v in sorted(weights.items())]
    add = lambda op, ins, outs, **kw: nodes.append(helper.make_node(op, ins, outs, **kw))  # noqa: E731
    if table_dtype not in ("float32", "float16"):
        raise ValueError(f"table_dtype: float32 or float16, got {table_dtype!r}")
    for f in range(features):  # one 1-D table per feature: Gather then gives (N, 8 L) directly
        column = np.ascontiguousarray(table[:, f])
        if table_dtype == "float16":
            inits.append(numpy_helper.from_array(column.astype(np.float16), f"grid_table{f}_fp16"))
            add("Cast", [f"grid_table{f}_fp16"], [f"grid_table{f}"], to=TensorProto.FLOAT)
        else:
            inits.append(numpy_helper.from_array(column, f"grid_table{f}"))
    # position into [0, 1]^3, then per (axis, corner, level) column: cell, weight, row term
    add("Split", ["x", "split_sizes"], ["p", "n_raw"], axis=1)
    add("Sub", ["p", "enc_centre"], ["p_centred"])
    add("Mul", ["p_centred", "enc_inv_half"], ["p_scaled"])
    add("Clip", ["p_scaled", "clip_lo", "clip_hi"], ["p_enc"])
    add("Mul", ["p_enc", "half"], ["u_half"])
    add("Add", ["u_half", "half"], ["u"])
    add("MatMul", ["u", "level_spread"], ["pos"])  # exact: one non-zero product per column
    add("Floor", ["pos"], ["pos_floor"])
    add("Min", ["pos_floor", "level_res_m1"], ["i0f"])
    add("Sub", ["pos", "i0f"], ["w"])
    add("Sub", ["one", "w"], ["v"])
    add("Mul", ["w", "corner_on"], ["w_on"])
    add("Mul", ["v", "corner_off"], ["v_off"])
    add("Add", ["w_on", "v_off"], ["wk"])  # w where the corner's bit is 1, else 1 - w (exact)
    add("Split", ["wk", "split_axes"], ["wx", "wy", "wz"], axis=1)
    add("Mul", ["wx", "wy"], ["wxy"])
    add("Mul", ["wxy", "wz"], ["weight"])  # (N, 8 L)
    add("Add", ["i0f", "corner_on"], ["cf"])  # exact: small integers in float32
    add("Cast", ["cf"], ["c"], to=TensorProto.INT64)
    add("Mul", ["c", "corner_mult"], ["c_mult"])  # dense: (N_l + 1)^a; hashed: the axis prime
    add("Split", ["c_mult", "split_axes"], ["tx", "ty", "tz"], axis=1)
    add("Add", ["tx", "ty"], ["txy"])
    add("Add", ["txy", "tz"], ["rows_dense"])
    add("BitwiseXor", ["tx", "ty"], ["hxy"])
    add("BitwiseXor", ["hxy", "tz"], ["hxyz"])
    add("BitwiseAnd", ["hxyz", "hash_mask"], ["rows_hashed"])
    add("Where", ["level_hashed", "rows_hashed", "rows_dense"], ["rows_level"])
    add("Add", ["rows_level", "level_offset"], ["rows"])  # (N, 8 L)
    weighted = []
    for f in range(features):
        add("Gather", [f"grid_table{f}", "rows"], [f"vals{f}"], axis=0)
        add("Mul", [f"vals{f}", "weight"], [f"vals{f}_w"])
        weighted.append(f"vals{f}_w")
    add("Concat", weighted, ["vals_w"], axis=1)  # (N, F 8 L)
    add("MatMul", ["vals_w", "corner_sum"], ["grid_features"])  # (N, L F)
    # normal, features, MLP
    add("ReduceL2", ["n_raw", "axis1"], ["n_len"], keepdims=1)
    add("Max", ["n_len", "normal_eps"], ["n_len_safe"])
    add("Div", ["n_raw", "n_len_safe"], ["n_enc"])
    parts = ["grid_features"] + (["p_enc"] if int(arrays["mlp_position"]) else []) + ["n_enc"]
    if "enc_normal_freq" in weights and weights["enc_normal_freq"].shape[1] > 0:
        add("MatMul", ["n_enc", "enc_normal_freq"], ["n_angle"])
        add("Sin", ["n_angle"], ["n_sin"])
        add("Cos", ["n_angle"], ["n_cos"])
        parts += ["n_sin", "n_cos"]
    add("Concat", parts, ["features"], axis=1)
    h = "features"
    for i in range(layers):
        add("Gemm", [h, f"layer{i}_weight", f"layer{i}_bias"], [f"pre{i}"])
        add("LeakyRelu", [f"pre{i}"], [f"h{i}"], alpha=LEAKY_SLOPE)
        h = f"h{i}"
    add("Gemm", [h, "out_weight", "out_bias"], ["out_pre"])
    add("Tanh", ["out_pre"], ["out_tanh"])
    add("Mul", ["out_tanh", "out_scale"], ["out_scaled"])
    add("Add", ["out_scaled", "out_offset"], ["transfer"])
    graph = helper.make_graph(
        nodes,
        name,
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 6])],
        [helper.make_tensor_value_info("transfer", TensorProto.FLOAT, ["N", outputs])],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="prt-runtime")
    model.ir_version = 8
    grid = {k: np.asarray(arrays[k]).tolist() for k in LEVEL_KEYS}
    meta = {
        "prt.format": FORMAT,
        "prt.architecture": json.dumps(architecture or {}, sort_keys=True, default=str),
        "prt.grid": json.dumps({**grid, "features": features, "table_dtype": table_dtype, "primes": list(PRIMES)}, sort_keys=True),
        "prt.input": "x float32 [N, 6]: position (scene units), normal",
    }
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    return model


def save_grid_model(model, path) -> None:
    """Write an ONNX model atomically."""
    from ..runtime.files import atomic_write_bytes

    atomic_write_bytes(Path(path), model.SerializeToString())


def read_arrays(path) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays (as ``GridTransfer.arrays()``, the table as float32) and the architecture of a file."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    if meta.get("prt.format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} model (prt.format = {meta.get('prt.format')!r})")
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    arrays = {k: v for k, v in inits.items() if k.startswith(("enc_", "layer", "out_"))}
    arrays.setdefault("enc_normal_freq", np.zeros((3, 0), np.float32))  # no normal frequencies: not in the graph
    grid = json.loads(meta["prt.grid"])
    columns = [inits.get(f"grid_table{f}", inits.get(f"grid_table{f}_fp16")) for f in range(int(grid["features"]))]
    arrays["grid_table"] = np.stack(columns, axis=1).astype(np.float32)
    arrays |= {k: np.asarray(grid[k], dtype=np.int64) for k in LEVEL_KEYS}
    return arrays, json.loads(meta["prt.architecture"])


# -- GLSL: the same network in a fragment shader, tables and weights in a texture read with texelFetch --

TABLE_WIDTH = 1024  # texels per row of the texture; texel i is (i % W, i / W)


def _mlp_blocks(arrays) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.asarray(arrays[f"layer{i}_weight"], np.float32), np.asarray(arrays[f"layer{i}_bias"], np.float32)) for i in range(_layers(arrays))] + [
        (np.asarray(arrays["out_weight"], np.float32), np.asarray(arrays["out_bias"], np.float32))
    ]


def table_texture(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, dict]:
    """The texture :func:`glsl_function` reads: ``(height, TABLE_WIDTH, 4)`` float32 texels for an
    RGBA32F texture (nearest filtering).  Texel i < rows is table row i (features in R, G, B, A;
    F <= 4); then per MLP layer (the output layer last) its weights, texel ``base + j (out / 4) + q``
    = ``W[j, 4 q : 4 q + 4]`` (input j, outputs 4 q..), and its bias, ``out / 4`` texels.
    Returns the texels and the layout ``{"layers": [[weight base, bias base, in, out], ...]}``."""
    table = np.asarray(arrays["grid_table"], dtype=np.float32)
    if table.shape[1] > 4:
        raise ValueError(f"a texel holds at most 4 features, the table has {table.shape[1]}")
    texels = [np.pad(table, ((0, 0), (0, 4 - table.shape[1])))]
    at, layout = len(table), []
    for w, b in _mlp_blocks(arrays):
        din, dout = w.shape
        if dout % 4:
            raise ValueError(f"layer widths must be multiples of 4, got {dout}")
        texels += [w.reshape(-1, 4), b.reshape(-1, 4)]
        layout.append([at, at + din * dout // 4, din, dout])
        at += (din + 1) * dout // 4
    flat = np.concatenate(texels)
    height = -(-len(flat) // TABLE_WIDTH)
    data = np.zeros((height * TABLE_WIDTH, 4), dtype=np.float32)
    data[: len(flat)] = flat
    return data.reshape(height, TABLE_WIDTH, 4), {"layers": layout, "texels": int(len(flat))}


def _floats(values) -> str:
    return ", ".join(f"{float(v):.9g}" for v in np.asarray(values, dtype=np.float32).ravel())


def _vec3(values) -> str:
    return f"vec3({_floats(values)})"



def grid_level_lines(prefix: str, count: str, texel: str, features: int, table_size: int) -> list[str]:
    """GLSL of the grid lookup, shared by the per-segment and the compact generators: for each level
    ``l < count`` (``<prefix>_RES``, ``_HASHED`` arrays), the 8 cell corners' rows (hashed or dense)
    fetched by the expression ``texel`` (of ``row`` and ``l``), blended trilinearly into
    ``h[features * l + j]``; expects ``vec3 u`` (the position in [0, 1]^3) and ``float h[]``."""
    lines = [
        f"    for (int l = 0; l < {count}; ++l) {{",
        f"        float res = float({prefix}_RES[l]);",
        "        vec3 pos = u * res;",
        "        vec3 i0f = min(floor(pos), vec3(res - 1.0));",
        "        vec3 w = pos - i0f;",
        "        vec3 v = 1.0 - w;",
        "        ivec3 i0 = ivec3(i0f);",
        f"        int s1 = {prefix}_RES[l] + 1;",
        "        vec4 acc = vec4(0.0);",
        "        for (int k = 0; k < 8; ++k) {",
        "            ivec3 d = ivec3(k & 1, (k >> 1) & 1, k >> 2);",
        "            ivec3 c = i0 + d;",
        "            float weight = (d.x == 1 ? w.x : v.x) * (d.y == 1 ? w.y : v.y) * (d.z == 1 ? w.z : v.z);",
        "            int row;",
        f"            if ({prefix}_HASHED[l] == 1) row = int((uint(c.x) ^ (uint(c.y) * 2654435761u) ^ (uint(c.z) * 805459861u)) & {table_size - 1}u);",
        "            else row = c.x + s1 * c.y + s1 * s1 * c.z;",
        f"            acc += weight * {texel};",
        "        }",
    ]
    lines += [f"        h[{features} * l + {j}] = acc.{'xyzw'[j]};" for j in range(features)]
    return lines + ["    }"]


def grid_input_lines(at: int, use_pos: bool) -> tuple[list[str], int]:
    """GLSL lines putting the MLP's inputs after the ``at`` grid features into ``h``: the clipped
    position ``x`` (when the network takes it) and the normalised normal; returns the next index."""
    lines = []
    if use_pos:
        lines += [f"    h[{at + j}] = x.{'xyz'[j]};" for j in range(3)]
        at += 3
    lines.append(f"    vec3 n = n_raw / max(length(n_raw), {NORMAL_EPS:.9g});")
    lines += [f"    h[{at + j}] = n.{'xyz'[j]};" for j in range(3)]
    return lines, at + 3


def mlp_layer_lines(fetch, wbase: int, bbase: int, n_in: str, q4: str, last: bool) -> list[str]:
    """GLSL lines of one MLP layer over ``h`` in vec4 blocks: ``a = bias + h W``, then LeakyReLU
    (none on the last); ``fetch(expr)`` reads texel ``expr`` of the weights, ``n_in``/``q4`` are the
    loop bounds (constants or header values)."""
    return [
        f"    for (int q = 0; q < {q4}; ++q) a[q] = {fetch(f'{bbase} + q')};",
        f"    for (int j = 0; j < {n_in}; ++j) {{",
        "        float hj = h[j];",
        f"        for (int q = 0; q < {q4}; ++q) a[q] += hj * {fetch(f'{wbase} + j * {q4} + q')};",
        "    }",
        f"    for (int q = 0; q < {q4}; ++q) {{",
        f"        vec4 s = {'a[q]' if last else f'max(a[q], {LEAKY_SLOPE!r} * a[q])'};",
        "        h[4 * q] = s.x; h[4 * q + 1] = s.y; h[4 * q + 2] = s.z; h[4 * q + 3] = s.w;",
        "    }",
    ]


def glsl_function(arrays: dict[str, np.ndarray], name: str = "grid_transfer", sampler: str | None = None) -> str:
    """GLSL 3.30 source defining ``uniform sampler2D <sampler>`` (default ``<name>_table``; bind :func:`table_texture`)
    and ``void <name>(vec3 p, vec3 n, out vec4 t[K])``: the transfer (K = outputs / 4 vec4s), the
    same evaluation as the ONNX graph; the hash in 32-bit ``uint`` arithmetic (wrap-around), which
    gives the int64 rows since T is a power of two.  The source depends on the architecture and
    the box, not on the trained values (all in the texture)."""
    res = np.asarray(arrays["grid_resolution"], dtype=np.int64).tolist()
    hashed = np.asarray(arrays["grid_hashed"], dtype=np.int64).tolist()
    offsets = np.asarray(arrays["grid_offset"], dtype=np.int64).tolist()
    table_size = int(arrays["grid_table_size"])
    features = np.asarray(arrays["grid_table"]).shape[1]
    levels = len(res)
    _, layout = table_texture({k: (v[:1] if k == "grid_table" else v) for k, v in arrays.items()})  # layout only
    shift = len(np.asarray(arrays["grid_table"])) - 1
    layout = [[w + shift, b + shift, din, dout] for w, b, din, dout in layout["layers"]]
    outputs = layout[-1][3]
    freq = np.asarray(arrays.get("enc_normal_freq", np.zeros((3, 0))), dtype=np.float32)
    use_pos = bool(int(arrays["mlp_position"]))
    ints = lambda v: ", ".join(str(int(x)) for x in v)  # noqa: E731
    f = name
    table = sampler or f"{name}_table"
    width = max(max(din, dout) for _, _, din, dout in layout)
    body = [
        f"uniform sampler2D {table};",
        f"const int {f}_RES[{levels}] = int[]({ints(res)});",
        f"const int {f}_HASHED[{levels}] = int[]({ints(hashed)});",
        f"const int {f}_OFFSET[{levels}] = int[]({ints(offsets)});",
        f"const float {f}_SCALE[{outputs}] = float[]({_floats(arrays['out_scale'])});",
        f"const float {f}_SHIFT[{outputs}] = float[]({_floats(arrays['out_offset'])});",
        f"vec4 {f}_texel(int i) {{ return texelFetch({table}, ivec2(i % {TABLE_WIDTH}, i / {TABLE_WIDTH}), 0); }}",
        f"void {f}(vec3 p, vec3 n_raw, out vec4 t[{outputs // 4}]) {{",
        f"    vec3 x = clamp((p - {_vec3(arrays['enc_centre'])}) * {_vec3(arrays['enc_inv_half'])}, -1.0, 1.0);",
        "    vec3 u = x * 0.5 + 0.5;",
        f"    float h[{width}];",
    ]
    body += grid_level_lines(f, str(levels), f"{f}_texel(row + {f}_OFFSET[l])", features, table_size)
    inputs, at = grid_input_lines(levels * features, use_pos)
    body += inputs
    cols = freq.shape[1]
    for j in range(cols):  # column j: one axis times 2^k pi (block-diagonal)
        axis = int(np.argmax(np.abs(freq[:, j])))
        body.append(f"    h[{at + j}] = sin(n.{'xyz'[axis]} * {float(freq[axis, j]):.9g});")
        body.append(f"    h[{at + cols + j}] = cos(n.{'xyz'[axis]} * {float(freq[axis, j]):.9g});")
    at += 2 * cols
    if at != layout[0][2]:
        raise ValueError(f"the features are {at} wide, the first layer takes {layout[0][2]}")
    body.append(f"    vec4 a[{width // 4 + 1}];")
    for i, (wbase, bbase, din, dout) in enumerate(layout):
        body += mlp_layer_lines(lambda e: f"{f}_texel({e})", wbase, bbase, str(din), str(dout // 4), i == len(layout) - 1)
    body += [
        f"    for (int o = 0; o < {outputs}; ++o) h[o] = tanh(h[o]) * {f}_SCALE[o] + {f}_SHIFT[o];",
        f"    for (int q = 0; q < {outputs // 4}; ++q) t[q] = vec4(h[4 * q], h[4 * q + 1], h[4 * q + 2], h[4 * q + 3]);",
        "}",
    ]
    return "\n".join(body) + "\n"
