"""Compact scene GLSL: one network function per architecture, every segment's values in one texture.

The ``glsl`` backend assembles one full-screen program from every network segment's GLSL.
Written per segment (a function each, constants baked or per-segment samplers), its size grew
with segments x network size and llvmpipe's JIT took minutes at the first draw of a scene.
Here a segment's ``segNNN.glsl`` depends only on its architecture (the function is named after
it, so segments of one architecture have the same file and the backend keeps one copy), and all
its values -- the input box, frequencies, weights, output scaling, a grid's tables -- are texels
of ``segNNN_weights.npy``, which the backend stacks into the scene's one texture ``prt_weights``
(``shaders/transfer_weights.glsl``); the function takes the segment's first texel ``base``::

    void <fn>(int base, vec3 position, vec3 normal, out vec4 t[outputs / 4]);

Texel 0 of a segment is a header whose sizes bound the loops: hidden from the compiler, they
are not unrolled, so the code does not grow with the network's width either.

The file's fourth line is the format line the backend reads
(``// prt-glsl compact 1 function <fn> encoding <freq|grid> outputs <blocks> header <a,b,c,d>
texels <n>``: the header a segment's texel 0 holds and its texel count, which the backend checks); files without
it are the per-segment layouts of :mod:`prt.export.glsl` and :func:`prt.export.grid_onnx.glsl_function`.

Frequency networks: the header ``(feature groups, hidden blocks, output blocks, layers)``,
then :func:`prt.export.glsl.weight_texture`'s tensors in its order (``FREQ_HEADER`` texels
ahead).  Grid networks: see :func:`grid_texels`.

llvmpipe ends all loops of a shader invocation after 65,535 iterations in total
(``LP_MAX_TGSI_LOOP_ITERATIONS``); :func:`loop_iterations` counts a network's, and
:func:`freq_source` / :func:`grid_source` refuse a network over :data:`MAX_LOOP_ITERATIONS`.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

from .glsl import _OUT_FORMULA, _groups_doc, _literal, _network, _template, _texture, head_lines, residual_lines
from .grid_onnx import TABLE_WIDTH, grid_input_lines, grid_level_lines, mlp_layer_lines, table_texture
from .onnx_model import LEAKY_SLOPE, NORMAL_EPS, POSITION_CLIP

__all__ = [
    "FORMAT_LINE",
    "format_line",
    "MAX_LOOP_ITERATIONS",
    "freq_bias_texel",
    "freq_source",
    "freq_texels",
    "grid_source",
    "grid_texels",
    "loop_iterations",
    "rewrite_scene_glsl",
    "weights_array",
    "write_segment_glsl",
]

FORMAT_LINE = "// prt-glsl compact 1"
"""Start of the line that marks a compact segment file (read by ``prt.runtime.backends.glsl``)."""

MAX_LOOP_ITERATIONS = 40_000
"""Loop iterations per fragment a generated network may take: llvmpipe's cap is 65,535 for all
loops of an invocation together (the dispatch and analytic segments add a few), so a margin."""

FREQ_HEADER = 1


def format_line(encoding: str, outputs: int, header, texels: int) -> str:
    """The line that marks a compact file: its function, encoding, output blocks, the header its
    segments' texel 0 must hold and how many texels a segment has (the backend checks both)."""
    return f"{FORMAT_LINE} function FN encoding {encoding} outputs {outputs} header {','.join(str(int(v)) for v in header)} texels {int(texels)}"


def _name(prefix: str, readable: str, text: str) -> str:
    """``prt_<prefix>_<readable>_<hash>``: the function named after the architecture-only text."""
    return f"prt_{prefix}_{readable}_{hashlib.sha1(text.encode()).hexdigest()[:8]}"


# -- frequency networks --


def freq_texels(onnx_path) -> np.ndarray:
    """A frequency network's texels (N, 4) float32: header, then ``weight_texture``'s tensors."""
    network = _network(onnx_path)
    texels, meta = _texture(network)
    header = np.array([[network.groups, network.hidden, network.outputs, int(network.architecture["layers"])]], np.float32)
    return np.concatenate([header, texels.reshape(-1, 4)[: meta["texels"]]])


def freq_source(onnx_path) -> str:
    """The compact GLSL of a frequency network (depends only on its architecture)."""
    network = _network(onnx_path)
    _, meta = _texture(network)
    offsets = {name: FREQ_HEADER + t["offset"] for name, t in meta["tensors"].items()}
    arch = network.architecture
    layers = int(arch["layers"])
    iterations = loop_iterations({"encoding": "freq", "groups": network.groups, "hidden": network.hidden,
                                  "outputs": network.outputs, "layers": layers})  # fmt: skip
    if iterations > MAX_LOOP_ITERATIONS:
        raise ValueError(f"{onnx_path}: the network takes {iterations} loop iterations per fragment, over llvmpipe's margin {MAX_LOOP_ITERATIONS}")
    widths = [network.groups] + [network.hidden] * layers + [network.outputs]
    shapes, forward = {}, ["    vec4 f[%d];" % network.groups, "    FN_encode(base, position, normal, f);"]
    x = "f"
    for i in range(layers + 1):
        last = i == layers
        n_in, n_out = widths[i], widths[i + 1]
        kind = ("out" if last else "hidden") if i else ("first_out" if last else "first")
        shapes[kind] = (n_in, n_out, last)
        in_bound = "groups" if i == 0 else "hidden"
        w = offsets["out_weight" if last else f"layer{i}_weight"]
        if last:
            forward.append(f"    FN_{kind}(base + {w}, {in_bound}, outputs, {x}, t);")
            forward += residual_lines(network) + head_lines(network)
        else:
            forward += [f"    vec4 h{i}[{n_out}];", f"    FN_{kind}(base + {w}, {in_bound}, hidden, {x}, h{i});"]
            x = f"h{i}"
    layer_text = []
    for kind, (n_in, n_out, last) in shapes.items():
        layer_text.append(
            _template("mlp_compact_layer.glsl.tmpl").substitute(
                fn="FN", name=kind, title="output layer" if last else ("first hidden layer" if kind == "first" else "hidden layer"),
                formula=_OUT_FORMULA[bool(network.log_dc)] if last else "leaky_relu(W^T x + b)",
                extra_doc=(", out_scale, out_offset, out_linear and out_max (n_out texels each)" if network.log_dc
                           else ", out_scale and out_offset (n_out texels each)") if last else "",
                n_in=n_in, n_out=n_out,
                activation=(("min(FN_tanh(z) * prt_weight(bias + n_out + o) + prt_weight(bias + 2 * n_out + o) + z * prt_weight(bias + 3 * n_out + o), "
                             "prt_weight(bias + 4 * n_out + o))") if network.log_dc
                            else "FN_tanh(z) * prt_weight(bias + n_out + o) + prt_weight(bias + 2 * n_out + o)") if last else "FN_leaky_relu(z)",
            )
        )  # fmt: skip
    padding = 4 * network.outputs - network.coefficients
    header = [network.groups, network.hidden, network.outputs, layers]
    text = _template("mlp_compact.glsl.tmpl").substitute(
        fn="FN",
        format_line=format_line("freq", network.outputs, header, FREQ_HEADER + meta["texels"]),
        coefficients=network.coefficients,
        architecture=", ".join(f"{k} {arch[k]}" for k in ("hidden", "layers", "pos_freqs", "normal_freqs", "bands")),
        padding_note=f" (the last {padding} are 0)" if padding else "",
        iterations=iterations,
        slope=_literal(LEAKY_SLOPE),
        clip=_literal(POSITION_CLIP),
        eps=_literal(NORMAL_EPS),
        centre=offsets["enc_centre"],
        inv_half=offsets["enc_inv_half"],
        groups=network.groups,
        groups_doc=_groups_doc(network),
        encode="\n".join(_encode_lines(network, offsets)),
        layers="".join(layer_text),
        outputs=network.outputs,
        forward="\n".join(forward),
    )
    readable = (f"k{arch['hidden']}_l{layers}_p{arch['pos_freqs']}_n{arch['normal_freqs']}_o{network.coefficients}" + ("_res" if network.quad is not None else "")
                + ("_logdc" if network.log_dc else ""))  # fmt: skip
    return _rename(text, _name("freq", readable, text))


def _encode_lines(network, offsets) -> list[str]:
    p, q = network.pos_chunks, network.normal_chunks
    lines = ["    f[0] = vec4(x, 0.0);"]
    if p:
        lines.append(_angle_loop(offsets["enc_pos_freq"], "x", 1, p))
    lines.append(f"    f[{1 + 2 * p}] = vec4(n, 0.0);")
    if q:
        lines.append(_angle_loop(offsets["enc_normal_freq"], "n", 2 + 2 * p, q))
    return lines


def _angle_loop(offset: int, v: str, first: int, chunks: int) -> str:
    # a handful of chunks: unrolled by the compiler, which is cheap
    return (
        f"    for (int j = 0; j < {chunks}; ++j) {{\n"
        f"        vec4 a = FN_mat3x4(base + {offset} + 3 * j) * {v};\n"
        f"        f[{first} + j] = sin(a);\n"
        f"        f[{first + chunks} + j] = cos(a);\n"
        f"    }}"
    )


def _rename(text: str, fn: str) -> str:
    return text.replace("FN_", f"{fn}_").replace("FN(", f"{fn}(").replace("function FN ", f"function {fn} ").replace("// FN:", f"// {fn}:")


# -- grid networks --

def grid_texels(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """A grid network's texels (N, 4) float32: header ``(levels, hidden width, outputs / 4, MLP
    input width)``, ``(centre, 0)``, ``(inv_half, 0)``, per output block its scale then its offset
    (``outputs / 4`` texels each), the normal frequency columns ``(f_x, f_y, f_z, 0)``, then
    :func:`~prt.export.grid_onnx.table_texture`'s texels (tables, MLP layers)."""
    texels, meta = table_texture(arrays)
    flat = texels.reshape(-1, 4)[: meta["texels"]]
    outputs = meta["layers"][-1][3]
    freq = np.asarray(arrays.get("enc_normal_freq", np.zeros((3, 0))), np.float32)
    layers = meta["layers"]
    hidden = layers[0][3] if len(layers) > 1 else 0
    head = [
        [len(np.asarray(arrays["grid_resolution"]).reshape(-1)), hidden, outputs // 4, layers[0][2]],
        [*np.asarray(arrays["enc_centre"], np.float32).reshape(3), 0.0],
        [*np.asarray(arrays["enc_inv_half"], np.float32).reshape(3), 0.0],
    ]
    head += np.asarray(arrays["out_scale"], np.float32).reshape(-1, 4).tolist()
    head += np.asarray(arrays["out_offset"], np.float32).reshape(-1, 4).tolist()
    head += [[*freq[:, j], 0.0] for j in range(freq.shape[1])]
    return np.concatenate([np.asarray(head, np.float32), flat]).astype(np.float32)


def _grid_prefix(arrays) -> int:
    outputs = np.asarray(arrays["out_bias"]).size
    return 3 + 2 * (outputs // 4) + np.asarray(arrays.get("enc_normal_freq", np.zeros((3, 0)))).shape[1]


def grid_source(arrays: dict[str, np.ndarray]) -> str:
    """The compact GLSL of a grid network (:func:`prt.export.grid_onnx.glsl_function`'s evaluation;
    depends only on the architecture: levels, resolutions, table sizes, MLP sizes, frequencies)."""
    res = np.asarray(arrays["grid_resolution"], dtype=np.int64).tolist()
    hashed = np.asarray(arrays["grid_hashed"], dtype=np.int64).tolist()
    offsets = np.asarray(arrays["grid_offset"], dtype=np.int64).tolist()
    table_size = int(arrays["grid_table_size"])
    features = np.asarray(arrays["grid_table"]).shape[1]
    levels = len(res)
    prefix = _grid_prefix(arrays)
    _, layout = table_texture({k: (v[:1] if k == "grid_table" else v) for k, v in arrays.items()})  # layout only
    shift = len(np.asarray(arrays["grid_table"])) - 1 + prefix
    layout = [[w + shift, b + shift, din, dout] for w, b, din, dout in layout["layers"]]
    outputs = layout[-1][3]
    freq = np.asarray(arrays.get("enc_normal_freq", np.zeros((3, 0))), dtype=np.float32)
    cols = freq.shape[1]
    use_pos = bool(int(arrays["mlp_position"]))
    iterations = loop_iterations({"encoding": "grid", "levels": levels, "layers": [(din, dout) for _, _, din, dout in layout]})
    if iterations > MAX_LOOP_ITERATIONS:
        raise ValueError(f"the grid network takes {iterations} loop iterations per fragment, over llvmpipe's margin {MAX_LOOP_ITERATIONS}")
    ints = lambda v: ", ".join(str(int(x)) for x in v)  # noqa: E731
    width = max(max(din, dout) for _, _, din, dout in layout)
    arch = (f"{levels} levels of {features} features, resolutions {ints(res)}, {table_size} table rows at most, "
            f"MLP {' -> '.join(str(d) for d in [layout[0][2]] + [o for *_, o in layout])}, {cols} normal frequency columns")  # fmt: skip
    body = [
        f"// FN: a grid-encoded transfer network (multiresolution feature grid + MLP) -> {outputs} SH coefficients",
        f"// of every segment with this architecture: {arch}.",
        "// FN(base, position, normal, t): t[j] holds coefficients 4j .. 4j+3.",
        "// Generated by prt.export.glsl_compact; do not edit by hand.",
        format_line("grid", outputs // 4, [levels, layout[0][3] if len(layout) > 1 else 0, outputs // 4, layout[0][2]],
                    prefix + len(np.asarray(arrays["grid_table"])) + sum((din + 1) * dout // 4 for *_, din, dout in layout)),
        "// The source depends only on the architecture: a segment's values are its texels of the scene's",
        "// weight texture (prt_weight) from texel `base` on (prt.export.glsl_compact.grid_texels): a header",
        "// (levels, hidden width, output blocks, MLP input width), the box, the output scaling, the normal",
        "// frequencies, the tables, the MLP.  Loop bounds come from the header (not unrolled); a fragment",
        f"// runs {iterations} loop iterations (llvmpipe ends all loops of an invocation after 65,535).",
        f"const int FN_RES[{levels}] = int[]({ints(res)});",
        f"const int FN_HASHED[{levels}] = int[]({ints(hashed)});",
        f"const int FN_OFFSET[{levels}] = int[]({ints(offsets)});",
        f"void FN(int base, vec3 p, vec3 n_raw, out vec4 t[{outputs // 4}]) {{",
        "    vec4 dims = prt_weight(base);",
        "    int n_levels = int(dims.x), n_blocks = int(dims.z);",
        "    vec3 x = clamp((p - prt_weight(base + 1).xyz) * prt_weight(base + 2).xyz, -1.0, 1.0);",
        "    vec3 u = x * 0.5 + 0.5;",
        f"    int table = base + {prefix};",
        f"    float h[{width}];",
    ]
    body += grid_level_lines("FN", "n_levels", "prt_weight(table + row + FN_OFFSET[l])", features, table_size)
    inputs, at = grid_input_lines(levels * features, use_pos)
    body += inputs
    first_freq = 3 + 2 * (outputs // 4)
    for j in range(cols):  # column j: dot with its (block-diagonal) frequency column, exact
        body.append(f"    float a{j} = dot(n, prt_weight(base + {first_freq + j}).xyz);")
        body.append(f"    h[{at + j}] = sin(a{j});")
        body.append(f"    h[{at + cols + j}] = cos(a{j});")
    at += 2 * cols
    if at != layout[0][2]:
        raise ValueError(f"the features are {at} wide, the first layer takes {layout[0][2]}")
    body += [f"    vec4 a[{width // 4}];", "    int n_in = int(dims.w), n_hidden = int(dims.y) / 4;"]
    for i, (wbase, bbase, din, dout) in enumerate(layout):
        last = i == len(layout) - 1
        body += mlp_layer_lines(lambda e: f"prt_weight(base + {e})", wbase, bbase, "n_in" if i == 0 else "4 * n_hidden",
                                "n_blocks" if last else "n_hidden", last)  # fmt: skip
    body += [
        "    for (int q = 0; q < n_blocks; ++q) {",
        "        vec4 z = vec4(h[4 * q], h[4 * q + 1], h[4 * q + 2], h[4 * q + 3]);",
        "        vec4 e = exp(-2.0 * abs(z));",
        "        t[q] = sign(z) * (1.0 - e) / (1.0 + e) * prt_weight(base + 3 + q) + prt_weight(base + 3 + n_blocks + q);",
        "    }",
        "}",
    ]
    text = "\n".join(line for line in body if line) + "\n"
    readable = f"L{levels}_F{features}_k{layout[0][3]}_l{len(layout) - 1}_o{outputs}"
    return _rename(text, _name("grid", readable, text))


def loop_iterations(shape: dict) -> int:
    """Loop iterations per fragment of a compact network (what llvmpipe's 65,535 cap counts).

    ``shape``: ``{"encoding": "freq", "groups", "hidden", "outputs" (vec4 blocks), "layers"}`` or
    ``{"encoding": "grid", "levels", "layers": [(in, out), ...]}``."""
    if shape["encoding"] == "freq":
        widths = [shape["groups"]] + [shape["hidden"]] * shape["layers"] + [shape["outputs"]]
        return sum(o * (i + 1) for i, o in zip(widths[:-1], widths[1:])) + 10
    total = 9 * shape["levels"]
    for din, dout in shape["layers"]:
        total += 2 * dout // 4 + din * (dout // 4 + 1)
    return total + shape["layers"][-1][1] // 4


def weights_array(texels: np.ndarray) -> np.ndarray:
    """Texels (N, 4) as the ``(height, TABLE_WIDTH, 4)`` array saved in ``segNNN_weights.npy``."""
    height = max(1, math.ceil(len(texels) / TABLE_WIDTH))
    data = np.zeros((height * TABLE_WIDTH, 4), dtype=np.float32)
    data[: len(texels)] = texels
    return data.reshape(height, TABLE_WIDTH, 4)



# -- writing a segment's GLSL files --

FORMS = ("auto", "compact", "per-segment", "const", "texture")
"""``auto`` / ``compact``: this module's form (a frequency network past :data:`MAX_LOOP_ITERATIONS`,
k > ~440 at l = 4: the texture layout of :mod:`prt.export.glsl`, whose loops are unrolled); ``per-segment``: the older export's choice (per segment
its own function: :func:`prt.export.glsl.choose_layout` for a frequency network,
:func:`prt.export.grid_onnx.glsl_function` for a grid); ``const`` / ``texture``: that layout of
:mod:`prt.export.glsl` (a grid has only its per-segment function there)."""


def write_segment_glsl(info, form: str = "auto", grid_arrays: dict | None = None) -> None:
    """(Re)write a network segment's ``segNNN.glsl`` and ``segNNN_weights.npy`` from its ONNX file
    (``info.model``; a grid's arrays may be given, as the export has them); sets ``info.glsl`` and
    ``info.glsl_weights`` (None for the const layout)."""
    from ..runtime.files import atomic_save_npy, atomic_write_bytes
    from .glsl import choose_layout, generate_glsl, weight_texture
    from .grid_onnx import glsl_function, read_arrays

    if form not in FORMS:
        raise ValueError(f"form must be one of {FORMS}, got {form!r}")
    model = Path(info.model)
    s, folder = info.id, model.parent
    compact = form in ("auto", "compact")
    grid = grid_arrays is not None or (info.architecture or {}).get("encoding") == "grid"
    if grid:
        arrays = grid_arrays if grid_arrays is not None else read_arrays(model)[0]
        if compact:
            text, texels = grid_source(arrays), weights_array(grid_texels(arrays))
        else:
            name = f"seg{s}_transfer"
            text, texels = glsl_function(arrays, name=name, sampler=f"{name}_weights"), table_texture(arrays)[0]
    elif compact and freq_fits(model):
        text, texels = freq_source(model), weights_array(freq_texels(model))
    else:  # per segment; "auto" for a network past llvmpipe's loop cap: the texture layout (unrolled)
        form = "texture" if compact else form
        layout = choose_layout(read_architecture(model)) if form == "per-segment" else form
        text = generate_glsl(model, function_name=f"seg{s}_transfer", layout=layout)
        texels = weight_texture(model)[0] if layout == "texture" else None
    info.glsl = folder / f"seg{s:03d}.glsl"
    atomic_write_bytes(info.glsl, text.encode())
    info.glsl_weights = None
    if texels is not None:
        info.glsl_weights = folder / f"seg{s:03d}_weights.npy"
        atomic_save_npy(info.glsl_weights, texels)


def freq_bias_texel(onnx_path) -> int:
    """The first texel of the first hidden layer's bias among a frequency network's compact texels
    (:func:`freq_texels`): where a deformable scene writes the bias of each frame's shape code."""
    _, meta = _texture(_network(onnx_path))
    return FREQ_HEADER + int(meta["tensors"]["layer0_bias"]["offset"])


def freq_fits(model) -> bool:
    """Whether a frequency network's compact loops stay within :data:`MAX_LOOP_ITERATIONS`."""
    network = _network(model)
    shape = {"encoding": "freq", "groups": network.groups, "hidden": network.hidden, "outputs": network.outputs,
             "layers": int(network.architecture["layers"])}  # fmt: skip
    return loop_iterations(shape) <= MAX_LOOP_ITERATIONS


def read_architecture(model) -> dict:
    from .onnx_model import read_arrays

    return read_arrays(model)[1]


def rewrite_scene_glsl(scene_json, form: str = "auto") -> None:
    """Rewrite every network segment's GLSL of a built scene in ``form`` and its manifest (an
    older scene to the compact form, or a scene to the per-segment form for comparison)."""
    from ..runtime.manifest import load_manifest
    from .manifest import write_manifest

    manifest = load_manifest(scene_json)
    for seg in manifest.segments:
        if seg.is_network:
            old = seg.glsl_weights
            write_segment_glsl(seg, form)
            if old is not None and seg.glsl_weights is None:
                Path(old).unlink(missing_ok=True)
    write_manifest(scene_json, manifest)


def evaluate_compact(ctx, source: str, texels, x, segment: int = 0) -> np.ndarray:
    """Run a compact function on ``x`` (N, 6) = [position, normal] (for checks against ONNX / numpy).

    ``texels``: one segment's texels (N, 4), or a list of several segments' stacked in one texture
    as the backend does; ``segment`` picks whose (its first texel is the function's ``base``).
    Returns (N, 4 * outputs) float32; networks over 8 vec4 blocks are read 8 blocks per draw.
    """
    import moderngl

    from ..runtime.gl import run_fragment_program
    from ..shaders import assemble

    fn, outputs = _format_fields(source)
    parts = list(texels) if isinstance(texels, (list, tuple)) else [texels]
    base = sum(len(p) for p in parts[:segment])
    data = weights_array(np.concatenate(parts))
    x = np.asarray(x, dtype=np.float32)
    weights = ctx.texture((data.shape[1], data.shape[0]), 4, data.tobytes(), dtype="f4")
    weights.filter = (moderngl.NEAREST, moderngl.NEAREST)
    results = []
    try:
        for first in range(0, outputs, 8):
            count = min(8, outputs - first)
            main = (f"uniform sampler2D u_position;\nuniform sampler2D u_normal;\nlayout(location = 0) out vec4 f_out[{count}];\n{source}\n"
                    f"void main() {{\n    ivec2 px = ivec2(gl_FragCoord.xy);\n    vec4 t[{outputs}];\n"
                    f"    {fn}({base}, texelFetch(u_position, px, 0).xyz, texelFetch(u_normal, px, 0).xyz, t);\n"
                    f"    for (int j = 0; j < {count}; ++j) f_out[j] = t[{first} + j];\n}}\n")  # fmt: skip
            program = assemble("transfer_weights.glsl") + main
            inputs = {"u_position": x[:, :3], "u_normal": x[:, 3:]}
            results.append(run_fragment_program(ctx, program, inputs, 4 * count, attachments=count, textures={"prt_weights": weights}))
    finally:
        weights.release()
    return np.concatenate(results, axis=1)


def _format_fields(source: str) -> tuple[str, int]:
    """The function name and output blocks from a compact file's format line."""
    for line in source.splitlines()[:12]:
        if line.startswith(FORMAT_LINE):
            words = line.split()
            return words[words.index("function") + 1], int(words[words.index("outputs") + 1])
    raise ValueError("not a compact GLSL source (no format line)")
