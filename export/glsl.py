"""GLSL for a segment network, generated from the weights in its ONNX file: a function per segment.

Scenes are exported in the compact form of :mod:`prt.export.glsl_compact` (one function per
architecture, every segment's values in one texture; ``prt-train --glsl-layout auto``), whose
scene programs compile on llvmpipe in seconds where these per-segment functions took minutes
(``docs/benchmarks/glsl_compile.md``); the layouts here remain for ``--glsl-layout const`` /
``texture``, for older scenes (the ``glsl`` backend still runs their files), and as the
compact form's building blocks (its tensors are :func:`weight_texture`'s).

The runtime evaluates ``sigma(position, normal)`` in a fragment shader, as in the paper
(Dhawal, KT, Narayanan 2022).  :func:`generate_glsl` reads the initialisers back from the
exported file (:func:`prt.export.onnx_model.read_arrays`, never torch) and fills the
templates ``shaders/mlp*.glsl.tmpl``.  The snippet has no ``#version`` line and defines::

    void <fn>(vec3 position, vec3 normal, out vec4 t[ceil(bands^2 / 4)]);

with ``t[j]`` holding coefficients ``4j .. 4j+3`` (padding coefficients are 0), plus helpers
whose names all start with ``<fn>_``, so several segments' networks fit in one shader.

The arithmetic is the ONNX graph's, in vec4 blocks: features are grouped into vec4s
(``(x, 0)``, sin and cos of 4 frequency columns at a time, ``(n, 0)``, ...), the first
layer's rows are permuted and zero-padded to match, every weight matrix is cut into
``mat4`` blocks (hidden and output widths padded to multiples of 4 with zeros) and each
layer is ``z_o = b_o + sum_i W(o, i) * x_i`` followed by a vec4 activation.

Layouts
-------
``"const"``
    Every tensor is a ``const`` array (``mat4[]`` weights, ``vec4[]`` biases) baked into the
    source with float32 values written in the fewest digits that read back exactly.
``"texture"``
    The same code reads the tensors from ``uniform sampler2D <fn>_weights`` with
    ``texelFetch``.  The source then depends only on the architecture, so one compiled
    program serves every segment of that size with its own texture.
``"auto"``
    ``"const"`` while the network has at most :data:`AUTO_CONST_MAX_BLOCKS` ``mat4``
    weight blocks, ``"texture"`` above (see :func:`choose_layout`).

Texture layout (:func:`weight_texture`)
---------------------------------------
An RGBA32F texture holds a sequence of texels, texel ``t`` at ``(t % width, t // width)``
(``width = min(texels, 1024)``; unused texels of the last row are 0).  The tensors follow
one another in this order, each item taking consecutive texels, a matrix one texel per
column (GLSL's column-major order):

==================  ========  =======================================================
tensor              type      item ``i``
==================  ========  =======================================================
enc_centre          vec4      ``(centre, 0)``
enc_inv_half        vec4      ``(inv_half, 0)``
enc_pos_freq        mat3x4    column ``r`` = row ``r`` of ``enc_pos_freq``, columns 4i..4i+3
enc_normal_freq     mat3x4    the same for ``enc_normal_freq``
                              (either is absent when its frequency count is 0)
layer{l}_weight     mat4      block ``(in i % n_in, out i // n_in)``: column ``c`` = row
                              ``4 (i % n_in) + c`` of the padded weight, 4 outputs wide
layer{l}_bias       vec4      outputs ``4i .. 4i+3``
out_weight          mat4      as ``layer{l}_weight``
out_bias            vec4      outputs ``4i .. 4i+3``
out_scale           vec4      outputs ``4i .. 4i+3``
out_offset          vec4      outputs ``4i .. 4i+3``
==================  ========  =======================================================

``meta["tensors"]`` gives each tensor's first texel and item count.  The ``"const"`` layout
bakes exactly these values, in this order.

Compile times
-------------
:func:`compile_report` on Mesa 22.3.6 llvmpipe (LLVM 15, 2 CPU cores, shader cache off),
F = 6 position and 2 normal frequencies, 4 SH bands; seconds for link + first draw
(llvmpipe generates the machine code at the first draw):

======  ======  ======  =================  =================  ==================
hidden  layers  blocks  const link + draw  texture link+draw  chars const / tex
======  ======  ======  =================  =================  ==================
16      2       96      0.05 + 0.20        0.02 + 0.17        25 k / 4.7 k
16      4       128     0.06 + 0.23        0.03 + 0.22        34 k / 6.2 k
32      2       224     0.13 + 0.41        0.03 + 0.36        52 k / 4.7 k
32      3       288     0.18 + 0.52        0.05 + 0.47        66 k / 5.5 k
32      4       352     0.26 + 0.67        0.06 + 0.61        81 k / 6.2 k
64      2       576     0.62 + 1.26        0.09 + 1.36        125 k / 4.8 k
64      3       832     1.19 + 2.21        0.14 + 2.30        181 k / 5.5 k
64      4       1088    2.27 + 3.73        0.22 + 3.16        236 k / 6.2 k
128     2       1664    5.55 + 6.81        0.36 + 6.79        354 k / 4.8 k
128     3       2688    15.7 + 16.1        1.15 + 19.3        575 k / 5.5 k
128     4       3712    31.6 + 34.7        1.66 + 39.2        796 k / 6.2 k
======  ======  ======  =================  =================  ==================

``blocks`` counts mat4 weight blocks (:func:`choose_layout`).  Mesa unrolls the layer loops
in both layouts (they index local arrays), so machine-code generation costs about the same;
baked constants add a front-end cost that grows faster than the network (31.6 s at k=128,
l=4).  Evaluating is about 5x faster with baked constants (llvmpipe, 65536 fragments:
0.6 s vs 3.2 s per million fragments at k=64, l=4).  Mesa's shader cache makes a second
compile of the same source take ~0.05 s.

``"auto"`` therefore bakes constants up to 1536 blocks (any network with k <= 64, l <= 4 and
F, Fn <= 6; about 6 s on llvmpipe at most), where running fast matters most, and
reads a texture above (k = 128: 12 s to 66 s baked), where one compiled program per
architecture serves every segment.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from functools import lru_cache
from string import Template

import moderngl
import numpy as np

from ..runtime.gl import run_fragment_program
from ..shaders import assemble
from ..shaders import source as shader_source
from .onnx_model import LEAKY_SLOPE, NORMAL_EPS, POSITION_CLIP, read_arrays

__all__ = [
    "AUTO_CONST_MAX_BLOCKS",
    "LAYOUTS",
    "TEXTURE_WIDTH",
    "choose_layout",
    "compile_report",
    "evaluate_glsl",
    "evaluation_program",
    "generate_glsl",
    "weight_texture",
]

LAYOUTS = ("auto", "const", "texture")

AUTO_CONST_MAX_BLOCKS = 1536
"""Largest network (in ``mat4`` weight blocks) that ``layout="auto"`` bakes as constants."""

TEXTURE_WIDTH = 1024
"""Texels per row of the weight texture (the GL 3.3 minimum of GL_MAX_TEXTURE_SIZE)."""

_TEXELS = {"vec4": 1, "mat3x4": 3, "mat4": 4}
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


@dataclass(frozen=True)
class _Tensor:
    """One tensor as GLSL sees it: ``count`` items of ``glsl_type``, ``data`` (count, texels, 4)."""

    name: str
    glsl_type: str
    data: np.ndarray

    @property
    def count(self) -> int:
        return self.data.shape[0]


@dataclass(frozen=True)
class _Network:
    """A network cut into vec4 blocks: its tensors and the block counts of every stage."""

    tensors: list[_Tensor]
    architecture: dict
    pos_chunks: int  # vec4 chunks of position frequency columns
    normal_chunks: int
    groups: int  # vec4 feature groups into the first layer
    hidden: int  # vec4 blocks per hidden layer
    outputs: int  # vec4 blocks of output
    coefficients: int
    quad: np.ndarray | None = None  # (9, coefficients) out_normal_quad of a residual network, else None
    log_dc: int = 0  # a log-DC head's group width (bands^2: out_linear, out_max follow out_offset), else 0

    @property
    def texels(self) -> int:
        return sum(t.data.shape[0] * t.data.shape[1] for t in self.tensors)


def generate_glsl(onnx_path, function_name: str = "prt_transfer", layout: str = "auto") -> str:
    """GLSL 330 snippet (no ``#version``) that evaluates the network in an ONNX file.

    Parameters
    ----------
    onnx_path : str or os.PathLike
        A segment network written by :func:`prt.export.onnx_model.save_model`.
    function_name : str
        Name of the generated function; every helper's name starts with it plus ``_``.
    layout : {"auto", "const", "texture"}
        Where the weights live (see the module docstring).  ``"texture"`` needs the
        texture from :func:`weight_texture` bound to ``uniform sampler2D <fn>_weights``.

    Returns
    -------
    str
        Source defining ``void <fn>(vec3 position, vec3 normal, out vec4 t[M])``,
        ``M = ceil(bands^2 / 4)``.

    Raises
    ------
    ValueError
        For an unknown layout, an invalid function name, a file that is not a segment
        network or a weight that is not finite.
    """
    fn = _check_name(function_name)
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    return _source(_network(onnx_path), fn, layout)


def weight_texture(onnx_path) -> tuple[np.ndarray, dict]:
    """Contents of the weight texture that the ``"texture"`` layout reads.

    Upload it as a ``width x height`` RGBA32F texture (nearest filtering, no mipmaps) and
    bind it to ``uniform sampler2D <fn>_weights``; the texel layout is in the module
    docstring.

    Parameters
    ----------
    onnx_path : str or os.PathLike
        A segment network written by :func:`prt.export.onnx_model.save_model`.

    Returns
    -------
    data : (height, width, 4) float32 ndarray
        Row ``y`` is texture row ``y`` (``data.tobytes()`` is ready for upload).
    meta : dict
        ``width``, ``height``, ``texels`` (used texels), ``format`` (``"RGBA32F"``) and
        ``tensors``: name -> ``{"type", "offset", "count"}`` (first texel, items).
    """
    return _texture(_network(onnx_path))


def _texture(network: _Network) -> tuple[np.ndarray, dict]:
    """:func:`weight_texture` for a network already read."""
    texels = np.concatenate([t.data.reshape(-1, 4) for t in network.tensors])
    width = min(len(texels), TEXTURE_WIDTH)
    height = math.ceil(len(texels) / width)
    data = np.zeros((height * width, 4), dtype=np.float32)
    data[: len(texels)] = texels
    tensors, offset = {}, 0
    for t in network.tensors:
        tensors[t.name] = {"type": t.glsl_type, "offset": offset, "count": t.count}
        offset += t.data.shape[0] * t.data.shape[1]
    meta = {"width": width, "height": height, "texels": len(texels), "format": "RGBA32F", "tensors": tensors}
    return data.reshape(height, width, 4), meta


def choose_layout(architecture: dict) -> str:
    """The layout ``"auto"`` picks: ``"const"`` up to :data:`AUTO_CONST_MAX_BLOCKS` mat4 blocks.

    Parameters
    ----------
    architecture : dict
        ``hidden``, ``layers``, ``pos_freqs``, ``normal_freqs``, ``bands`` (as recorded in
        the ONNX file or :meth:`prt.train.networks.network.Architecture.as_dict`).
    """
    return "const" if _weight_blocks(architecture) <= AUTO_CONST_MAX_BLOCKS else "texture"


def evaluation_program(snippet: str, function_name: str = "prt_transfer", outputs: int = 4) -> str:
    """Fragment shader that runs a generated snippet once per fragment.

    The position and normal of a fragment come from texel ``gl_FragCoord.xy`` of the float
    textures ``u_position`` and ``u_normal`` (xyz used); ``t[j]`` goes to colour attachment
    ``j`` (``layout(location = 0) out vec4 f_out[outputs]``).

    Parameters
    ----------
    snippet : str
        Source from :func:`generate_glsl`.
    function_name : str
        The ``function_name`` the snippet was generated with.
    outputs : int
        Length of its ``t`` array, ``ceil(bands^2 / 4)``.
    """
    fn = _check_name(function_name)
    return assemble("mlp_eval.glsl.tmpl", fills={"fn": fn, "outputs": str(outputs), "snippet": snippet})


def compile_report(ctx, source: str, function_name: str = "prt_transfer", outputs: int = 4) -> dict:
    """Time compiling a generated snippet into a program and running it once.

    llvmpipe translates the shader to machine code at the first draw, so the draw of one
    fragment is timed as well; the inputs are zeros (the texture layout reads an unbound
    sampler, which is fine for timing).

    Parameters
    ----------
    ctx : moderngl.Context
    source : str
        Snippet from :func:`generate_glsl`.
    function_name, outputs
        As for :func:`evaluation_program`.

    Returns
    -------
    dict
        ``link_s`` (compile + link), ``first_draw_s``, ``total_s`` and ``source_chars``.
    """
    program_source = evaluation_program(source, function_name, outputs)
    start = time.perf_counter()
    program = ctx.program(vertex_shader=assemble("fullscreen.vert"), fragment_shader=program_source)
    linked = time.perf_counter()
    try:
        zeros = np.zeros((1, 4), dtype=np.float32)
        run_fragment_program(ctx, program, {"u_position": zeros, "u_normal": zeros}, 4 * outputs, attachments=outputs)
    finally:
        program.release()
    drawn = time.perf_counter()
    return {
        "link_s": linked - start,
        "first_draw_s": drawn - linked,
        "total_s": drawn - start,
        "source_chars": len(source),
    }


def evaluate_glsl(ctx, onnx_path, x, layout: str = "auto", function_name: str = "prt_transfer") -> np.ndarray:
    """Run the generated GLSL on ``x`` (N, 6) = [position, normal], like the ONNX graph.

    For checking the shader against onnxruntime and for timing, through
    :func:`prt.runtime.gl.run_fragment_program`; the framebuffer bound before the call is
    bound again.

    Parameters
    ----------
    ctx : moderngl.Context
    onnx_path : str or os.PathLike
    x : (N, 6) array_like
    layout : {"auto", "const", "texture"}
    function_name : str

    Returns
    -------
    (N, bands^2) float32 ndarray
    """
    data = np.asarray(x, dtype=np.float32)
    if data.ndim != 2 or data.shape[1] != 6:
        raise ValueError(f"x must be (N, 6), got shape {data.shape}")
    fn = _check_name(function_name)
    network = _network(onnx_path)
    if layout == "auto":
        layout = choose_layout(network.architecture)
    outputs = network.outputs
    snippet = _source(network, fn, layout)
    # At most 8 colour attachments (GL 3.3's guaranteed draw buffers): wider networks (the
    # 64 outputs of interreflection) are read 8 vec4 blocks per draw, through a wrapper.
    parts = [(0, outputs)] if outputs <= _MAX_ATTACHMENTS else [(a, min(_MAX_ATTACHMENTS, outputs - a)) for a in range(0, outputs, _MAX_ATTACHMENTS)]
    results = []
    for first, count in parts:
        name, source = fn, snippet
        if len(parts) > 1:
            name = f"{fn}_part{first}"
            source += (f"\nvoid {name}(vec3 position, vec3 normal, out vec4 t[{count}]) {{\n    vec4 all_t[{outputs}];\n"
                       f"    {fn}(position, normal, all_t);\n    for (int j = 0; j < {count}; ++j) t[j] = all_t[{first} + j];\n}}\n")
        program = ctx.program(vertex_shader=assemble("fullscreen.vert"), fragment_shader=evaluation_program(source, name, count))
        textures = {}
        try:
            if layout == "texture":
                texels, meta = _texture(network)
                weights = ctx.texture((meta["width"], meta["height"]), 4, texels.tobytes(), dtype="f4")
                weights.filter = (moderngl.NEAREST, moderngl.NEAREST)
                textures[f"{fn}_weights"] = weights
            inputs = {"u_position": data[:, :3], "u_normal": data[:, 3:]}
            results.append(run_fragment_program(ctx, program, inputs, 4 * count, attachments=count, textures=textures))
        finally:
            for texture in textures.values():
                texture.release()
            program.release()
    return np.concatenate(results, axis=1)[:, : network.coefficients]


_MAX_ATTACHMENTS = 8


def _network(onnx_path) -> _Network:
    """Read an ONNX segment network and cut its tensors into GLSL vec4/mat blocks."""
    arrays, arch = read_arrays(onnx_path)
    for name, value in arrays.items():
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            raise ValueError(f"{onnx_path}: initialiser {name} holds a non-finite value")
    layers, bands = int(arch["layers"]), int(arch["bands"])
    hidden, coefficients = int(arch["hidden"]), int(arch.get("outputs", bands * bands))  # 4 bands^2: interreflection
    pos_freqs, normal_freqs = int(arch["pos_freqs"]), int(arch["normal_freqs"])
    expected = {
        "enc_pos_freq": (3, 3 * pos_freqs),
        "enc_normal_freq": (3, 3 * normal_freqs),
        "out_weight": (hidden if layers else int(arch["input_dim"]), coefficients),
    }
    for name, shape in expected.items():
        if name not in arrays or arrays[name].shape != shape:
            found = arrays[name].shape if name in arrays else "missing"
            raise ValueError(f"{onnx_path}: {name} should be {shape}, found {found}")

    pos = _freq_chunks(arrays["enc_pos_freq"])
    normal = _freq_chunks(arrays["enc_normal_freq"])
    order, groups = _feature_order(pos_freqs, normal_freqs)
    tensors = [
        _Tensor("enc_centre", "vec4", _vec4_items(arrays["enc_centre"])),
        _Tensor("enc_inv_half", "vec4", _vec4_items(arrays["enc_inv_half"])),
    ]
    # without frequencies there is no angle to compute, and GLSL has no empty arrays
    tensors += [_Tensor(n, "mat3x4", c) for n, c in (("enc_pos_freq", pos), ("enc_normal_freq", normal)) if len(c)]
    for i in range(layers + 1):
        prefix = f"layer{i}" if i < layers else "out"
        weight = np.asarray(arrays[f"{prefix}_weight"], dtype=np.float32)
        if i == 0:  # rows follow the features' vec4 grouping; -1 marks a padding row
            rows = np.zeros((len(order), weight.shape[1]), dtype=np.float32)
            rows[order >= 0] = weight[order[order >= 0]]
            weight = rows
        tensors.append(_Tensor(f"{prefix}_weight", "mat4", _mat4_blocks(weight)))
        tensors.append(_Tensor(f"{prefix}_bias", "vec4", _vec4_items(arrays[f"{prefix}_bias"])))
    tensors.append(_Tensor("out_scale", "vec4", _vec4_items(arrays["out_scale"])))
    tensors.append(_Tensor("out_offset", "vec4", _vec4_items(arrays["out_offset"])))
    log_dc = 0
    if "out_dc_select" in arrays:  # a log-DC head: its fitted constants after out_offset; its groups must be bands^2 wide
        log_dc = bands * bands
        sets = coefficients // log_dc
        select = np.zeros((coefficients, sets), np.float32)
        select[np.arange(sets) * log_dc, np.arange(sets)] = 1.0
        if coefficients % log_dc or not np.array_equal(arrays["out_dc_select"], select):
            raise ValueError(f"{onnx_path}: out_dc_select is not the log-DC head of {sets} groups of {log_dc} coefficients")
        tensors.append(_Tensor("out_linear", "vec4", _vec4_items(arrays["out_linear"])))
        tensors.append(_Tensor("out_max", "vec4", _vec4_items(arrays["out_max"])))
    quad = arrays.get("out_normal_quad")
    if quad is not None and quad.shape != (9, coefficients):
        raise ValueError(f"{onnx_path}: out_normal_quad should be {(9, coefficients)}, found {quad.shape}")
    return _Network(
        tensors=tensors,
        architecture=dict(arch),
        pos_chunks=pos.shape[0],
        normal_chunks=normal.shape[0],
        groups=groups,
        hidden=math.ceil(hidden / 4),
        outputs=math.ceil(coefficients / 4),
        coefficients=coefficients,
        quad=None if quad is None else np.asarray(quad, np.float32),
        log_dc=log_dc,
    )


def head_lines(network: _Network) -> list[str]:
    """Statements that turn a log-DC head's ``t`` (each group's capped log DC, then ratios) into the
    transfer (none for another network): ``dc_g = exp(t[DC of g])``, then every coefficient ``dc_g``
    (its group's DC column) or ``dc_g * t`` (the others); padding stays 0."""
    n = network.log_dc
    if not n:
        return []
    lines = ["    // log-DC head: each group's DC = exp(its log), the other coefficients ratios to it"]
    lines += [f"    float dc{g} = exp(t[{g * n // 4}].{'xyzw'[g * n % 4]});" for g in range(network.coefficients // n)]
    for block in range(network.outputs):
        items = []
        for k in range(4 * block, 4 * block + 4):
            if k >= network.coefficients:
                items.append("0.0")
            else:
                items.append(f"dc{k // n}" if k % n == 0 else f"dc{k // n} * t[{block}].{'xyzw'[k % 4]}")
        lines.append(f"    t[{block}] = vec4({', '.join(items)});")
    return lines


_QUAD_TERMS = ("q.x", "q.y", "q.z", "q2.x", "q2.y", "q2.z", "qx.x", "qx.y", "qx.z")  # prt.runtime.sh.QUADRATIC_TERMS


def residual_lines(network: _Network) -> list[str]:
    """Statements that add a residual network's ``q(n) @ out_normal_quad`` to ``t`` (none for
    another network): the constant matrix's non-zero entries as literals, the same for every
    residual network of a layout (it is the unshadowed transfer's), so the compact form's
    function still depends on the architecture alone."""
    if network.quad is None:
        return []
    lines = ["    // residual network: + the unshadowed transfer's quadratic part, q(n) @ out_normal_quad",
             f"    vec3 q = normal / max(length(normal), {_literal(NORMAL_EPS)});",
             "    vec3 q2 = q * q, qx = q * q.yzx;"]  # fmt: skip
    for block in range(network.outputs):
        items = []
        for k in range(4 * block, min(4 * block + 4, network.coefficients)):
            terms = [f"{_literal(w)} * {_QUAD_TERMS[i]}" for i, w in enumerate(network.quad[:, k]) if w != 0.0]
            items.append(" + ".join(terms) if terms else "0.0")
        items += ["0.0"] * (4 - len(items))
        if any(item != "0.0" for item in items):
            lines.append(f"    t[{block}] += vec4({', '.join(items)});")
    return lines


def _feature_order(pos_freqs: int, normal_freqs: int) -> tuple[np.ndarray, int]:
    """Feature index behind each component of the vec4 groups (-1: padding), and group count.

    Groups: ``(x, 0)``, sin then cos of the position angles 4 at a time, ``(n, 0)``, sin
    then cos of the normal angles; feature indices follow the ONNX Concat order.
    """

    def chunks(first: int, count: int) -> list[int]:
        padded = 4 * math.ceil(count / 4)
        return [first + c if c < count else -1 for c in range(padded)]

    p, q = 3 * pos_freqs, 3 * normal_freqs
    normal_start = 3 + 2 * p
    order = (
        [0, 1, 2, -1]
        + chunks(3, p)
        + chunks(3 + p, p)
        + [normal_start, normal_start + 1, normal_start + 2, -1]
        + chunks(normal_start + 3, q)
        + chunks(normal_start + 3 + q, q)
    )
    return np.array(order), len(order) // 4


def _weight_blocks(arch: dict) -> int:
    """mat4 blocks of all layers for an architecture (what ``choose_layout`` measures)."""
    hidden, layers = math.ceil(int(arch["hidden"]) / 4), int(arch["layers"])
    groups = 2 + 2 * math.ceil(3 * int(arch["pos_freqs"]) / 4) + 2 * math.ceil(3 * int(arch["normal_freqs"]) / 4)
    outputs = math.ceil(int(arch.get("outputs", int(arch["bands"]) ** 2)) / 4)
    if layers == 0:
        return groups * outputs
    return groups * hidden + (layers - 1) * hidden * hidden + hidden * outputs


def _pad(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    out = np.zeros(shape, dtype=np.float32)
    out[tuple(slice(0, n) for n in a.shape)] = a
    return out


def _vec4_items(v: np.ndarray) -> np.ndarray:
    """(n,) -> (ceil(n / 4), 1, 4), zero-padded."""
    v = np.asarray(v, dtype=np.float32).reshape(-1)
    n = max(1, math.ceil(len(v) / 4))
    return _pad(v, (4 * n,)).reshape(n, 1, 4)


def _freq_chunks(p: np.ndarray) -> np.ndarray:
    """(3, m) frequencies -> (ceil(m / 4), 3, 4): chunk j, column r = row r, columns 4j..4j+3."""
    n = math.ceil(p.shape[1] / 4)
    return _pad(p, (3, 4 * n)).reshape(3, n, 4).transpose(1, 0, 2).copy()


def _mat4_blocks(w: np.ndarray) -> np.ndarray:
    """(in, out) weight (x @ W) -> (n_out * n_in, 4, 4) mat4 columns, block (i, o) at o * n_in + i.

    Column ``c`` of block (i, o) is row ``4i + c`` of W, outputs ``4o .. 4o+3``, so
    ``block * x_i`` is block i's contribution to outputs ``4o .. 4o+3``.
    """
    n_in, n_out = math.ceil(w.shape[0] / 4), math.ceil(w.shape[1] / 4)
    blocks = _pad(w, (4 * n_in, 4 * n_out)).reshape(n_in, 4, n_out, 4).transpose(2, 0, 1, 3)
    return blocks.reshape(n_out * n_in, 4, 4).copy()


# The output layer's formula, linear head / log-DC head (then head_lines).
_OUT_FORMULA = ("tanh(W^T x + b) * out_scale + out_offset", "min(tanh(W^T x + b) * out_scale + out_offset + (W^T x + b) * out_linear, out_max)")


def _source(network: _Network, fn: str, layout: str) -> str:
    """Fill the main template: the layout's tensor storage and getters, then the network."""
    if layout == "auto":
        layout = choose_layout(network.architecture)
    if layout == "const":
        storage = "\n\n".join(_const_tensor(fn, t) for t in network.tensors)
    elif layout == "texture":
        storage = _texture_storage(fn, network)
    else:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    arch = network.architecture
    widths = [network.groups] + [network.hidden] * int(arch["layers"]) + [network.outputs]
    inputs = ["f"] + [f"h{i}" for i in range(int(arch["layers"]))]
    layers, forward = [], [f"    vec4 f[{network.groups}];", f"    {fn}_encode(position, normal, f);"]
    for i, (n_in, n_out, x) in enumerate(zip(widths[:-1], widths[1:], inputs)):
        last = i == len(widths) - 2
        name = "out" if last else f"layer{i}"
        layers.append(
            _template("mlp_layer.glsl.tmpl").substitute(
                fn=fn,
                name=name,
                title="output layer" if last else f"hidden layer {i}",
                formula=(_OUT_FORMULA[bool(network.log_dc)]) if last else "leaky_relu(W^T x + b)",
                n_in=n_in,
                n_out=n_out,
                weight=f"{name}_weight",
                bias=f"{name}_bias",
                activation=((f"min({fn}_tanh(z) * {fn}_out_scale(o) + {fn}_out_offset(o) + z * {fn}_out_linear(o), {fn}_out_max(o))"
                             if network.log_dc else f"{fn}_tanh(z) * {fn}_out_scale(o) + {fn}_out_offset(o)") if last else f"{fn}_leaky_relu(z)"),
            )
        )
        if last:
            forward.append(f"    {fn}_out({x}, t);")
            forward += residual_lines(network) + head_lines(network)
        else:
            forward += [f"    vec4 h{i}[{n_out}];", f"    {fn}_{name}({x}, h{i});"]
    padding = 4 * network.outputs - network.coefficients
    return _template("mlp.glsl.tmpl").substitute(
        fn=fn,
        coefficients=network.coefficients,
        architecture=", ".join(f"{k} {arch[k]}" for k in ("hidden", "layers", "pos_freqs", "normal_freqs", "bands")),
        layout=layout,
        padding_note=f" (the last {padding} are 0)" if padding else "",
        storage=storage,
        slope=_literal(LEAKY_SLOPE),
        clip=_literal(POSITION_CLIP),
        eps=_literal(NORMAL_EPS),
        groups=network.groups,
        groups_doc=_groups_doc(network),
        encode="\n".join(_encode_lines(fn, network)),
        layers="\n".join(layers).rstrip("\n"),
        outputs=network.outputs,
        forward="\n".join(forward),
    )


def _groups_doc(network: _Network) -> str:
    p, q = network.pos_chunks, network.normal_chunks
    parts, start = ["f[0] = (x, 0)"], 1
    if p:
        parts += [f"f[{_span(start, p)}] = sin(x * pos_freq)", f"f[{_span(start + p, p)}] = cos(x * pos_freq)"]
        start += 2 * p
    parts.append(f"f[{start}] = (n, 0)")
    if q:
        parts += [f"f[{_span(start + 1, q)}] = sin(n * normal_freq)", f"f[{_span(start + 1 + q, q)}] = cos(n * normal_freq)"]
    return ", ".join(parts)


def _span(first: int, count: int) -> str:
    return str(first) if count == 1 else f"{first}..{first + count - 1}"


def _encode_lines(fn: str, network: _Network) -> list[str]:
    """Statements filling ``f`` in the order of :func:`_feature_order`."""
    p, q = network.pos_chunks, network.normal_chunks
    lines = ["    f[0] = vec4(x, 0.0);"]
    if p:
        lines.append(_angle_loop(fn, "enc_pos_freq", "x", 1, p))
    lines.append(f"    f[{1 + 2 * p}] = vec4(n, 0.0);")
    if q:
        lines.append(_angle_loop(fn, "enc_normal_freq", "n", 2 + 2 * p, q))
    return lines


def _angle_loop(fn: str, tensor: str, v: str, first: int, chunks: int) -> str:
    return (
        f"    for (int j = 0; j < {chunks}; ++j) {{\n"
        f"        vec4 a = {fn}_{tensor}(j) * {v};\n"
        f"        f[{first} + j] = sin(a);\n"
        f"        f[{first + chunks} + j] = cos(a);\n"
        f"    }}"
    )


def _const_tensor(fn: str, tensor: _Tensor) -> str:
    """A tensor as a const array plus its getter."""
    items = [f"{tensor.glsl_type}({', '.join(_literal(v) for v in item.reshape(-1))})" for item in tensor.data]
    return _template("mlp_const.glsl.tmpl").substitute(
        fn=fn, name=tensor.name, type=tensor.glsl_type, count=tensor.count, items=",\n    ".join(items)
    ).rstrip("\n")


def _texture_storage(fn: str, network: _Network) -> str:
    """The sampler, its texel fetch and one getter per tensor at the tensor's texel offset."""
    texels = network.texels
    width = min(texels, TEXTURE_WIDTH)
    getters, offset = [], 0
    for tensor in network.tensors:
        size = _TEXELS[tensor.glsl_type]
        columns = [f"{fn}_texel(t{f' + {c}' if c else ''})" for c in range(size)]
        value = columns[0] if size == 1 else f"{tensor.glsl_type}({', '.join(columns)})"
        getters.append(
            _template("mlp_texture_tensor.glsl.tmpl").substitute(
                fn=fn, type=tensor.glsl_type, name=tensor.name, offset=offset, texels=size, value=value
            )
        )
        offset += tensor.count * size
    prelude = _template("mlp_texture.glsl.tmpl").substitute(fn=fn, texels=texels, width=width)
    return prelude + "\n" + "".join(getters).rstrip("\n")


def _literal(value) -> str:
    """A GLSL float literal that reads back as exactly this float32.

    numpy prints a float32 in the fewest digits that round-trip (``0.1``, ``1e-05``,
    ``3.0``), each a valid GLSL float literal.
    """
    v = np.float32(value)
    if not np.isfinite(v):
        raise ValueError(f"no GLSL literal for {v}")
    return str(v)


def _check_name(name: str) -> str:
    """``name`` if it can prefix GLSL identifiers (not reserved: no ``gl_`` start, no ``__``)."""
    if not _IDENTIFIER.match(name) or name.startswith("gl_") or "__" in name:
        raise ValueError(f"function_name must be a GLSL identifier without 'gl_' prefix or '__', got {name!r}")
    return name


@lru_cache(maxsize=None)
def _template(name: str) -> Template:
    return Template(shader_source(name))
