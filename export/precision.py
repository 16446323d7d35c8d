"""Reduced-precision variants of the exported transfer networks (ONNX), for speed against error.

``fp32``
    The exported models.
``fp16``
    Every float tensor and operator in half precision, float32 input and output (Cast nodes
    at the edges).
``fp16-mlp``
    The same for the MLP only, the input encoding kept in float32.
``int8``
    Dynamic quantisation (``onnxruntime.quantization.quantize_dynamic``, MatMulInteger with
    uint8 activations and per-channel uint8 weights: "u8u8"); ONNX Runtime's dynamic quantiser
    leaves Gemm alone, so each layer's Gemm is first rewritten as MatMul + Add, and only the
    MLP's MatMuls are quantised (the encoding's frequency MatMuls stay float32).  Not int8
    weights ("u8s8"): on x86 CPUs without VNNI (AVX2 only, e.g. AMD EPYC Rome) ONNX Runtime's
    u8s8 kernel sums pairs of products with ``vpmaddubsw``, which saturates at 16 bits, so the
    same model gave another answer there (demo networks: max error 0.107 against 0.039 with
    VNNI); u8u8 has no such pair sum and answers alike on every CPU (0.033 on both).

- :func:`variant_manifest`    a manifest whose network segments run a variant (built on demand)
- :func:`build_variant`       one model's variant, written once
- :func:`convert_to_fp16`, :func:`quantize_int8`, :func:`gemm_to_matmul`, :func:`encoding_nodes`
- :func:`model_weight_bytes`  initialiser bytes of a manifest's networks
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import os
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from onnxruntime.quantization import QuantType, quantize_dynamic

from ..runtime.files import atomic_write_bytes

__all__ = [
    "PRECISIONS", "encoding_nodes", "convert_to_fp16", "gemm_to_matmul", "quantize_int8", "build_variant",
    "variant_manifest", "model_weight_bytes",
]  # fmt: skip

PRECISIONS = ("fp32", "fp16", "fp16-mlp", "int8")
INT8_SCHEME = "u8u8"  # in the variant's file name: a variant built by an older scheme is not reused


def _float_types(model):
    """Element type of every tensor of ``model`` (inputs, initialisers, inferred intermediates)."""
    inferred = onnx.shape_inference.infer_shapes(model)
    types = {}
    for vi in (*inferred.graph.input, *inferred.graph.value_info, *inferred.graph.output):
        types[vi.name] = vi.type.tensor_type.elem_type
    for init in inferred.graph.initializer:
        types[init.name] = init.data_type
    return types


def encoding_nodes(model) -> set[int]:
    """Indices of the nodes that compute the first Gemm's input (the input encoding).

    Parameters
    ----------
    model : onnx.ModelProto
        A transfer network as exported by ``prt.export`` (encoding, then Gemm layers).

    Returns
    -------
    set of int
        Node indices (in graph order) that are ancestors of the first Gemm's data input.
    """
    nodes = list(model.graph.node)
    producer = {out: i for i, node in enumerate(nodes) for out in node.output}
    first_gemm = next(i for i, node in enumerate(nodes) if node.op_type == "Gemm")
    todo, found = [nodes[first_gemm].input[0]], set()
    while todo:
        i = producer.get(todo.pop())
        if i is not None and i not in found:
            found.add(i)
            todo.extend(nodes[i].input)
    return found


def convert_to_fp16(model, keep_fp32=frozenset()):
    """A float16 copy of an ONNX model whose input and output stay float32.

    Float initialisers read only by converted nodes are stored as float16; a Cast is inserted
    wherever a tensor crosses between a float16 and a float32 node, and after every output.

    Parameters
    ----------
    model : onnx.ModelProto
    keep_fp32 : set of int
        Indices of nodes to leave in float32 (e.g. :func:`encoding_nodes`).

    Returns
    -------
    onnx.ModelProto
        A checked model with the same input and output names and types.
    """
    f32, f16 = TensorProto.FLOAT, TensorProto.FLOAT16
    model = copy.deepcopy(model)
    graph = model.graph
    original = _float_types(model)
    half = [node.op_type != "Cast" and i not in keep_fp32 for i, node in enumerate(graph.node)]

    readers = defaultdict(list)
    for node, is_half in zip(graph.node, half):
        for name in node.input:
            readers[name].append(is_half)
    stored = {vi.name: vi.type.tensor_type.elem_type for vi in graph.input}  # type in the new graph
    for init in graph.initializer:
        if init.data_type == f32 and readers[init.name] and all(readers[init.name]):
            init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init).astype(np.float16), init.name))
        stored[init.name] = init.data_type

    nodes, casts = [], {}

    def typed(name: str, want: int) -> str:
        if stored[name] == want:
            return name
        if (name, want) not in casts:
            cast = f"{name}_as_{'fp16' if want == f16 else 'fp32'}"
            nodes.append(helper.make_node("Cast", [name], [cast], to=want, name=cast))
            stored[cast] = want
            casts[name, want] = cast
        return casts[name, want]

    for node, is_half in zip(graph.node, half):
        want = f16 if is_half else f32
        new = copy.deepcopy(node)
        for k, name in enumerate(new.input):
            if name and original.get(name) == f32:
                new.input[k] = typed(name, want)
        for attr in new.attribute:  # Constant nodes carry their value as an attribute
            if is_half and attr.type == onnx.AttributeProto.TENSOR and attr.t.data_type == f32:
                attr.t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(attr.t).astype(np.float16), attr.t.name))
        for name in new.output:
            stored[name] = want if original.get(name) == f32 else original.get(name, 0)
        nodes.append(new)

    for out in graph.output:
        if stored[out.name] == f16:  # rename the float16 result, cast it back under the output's name
            inner = out.name + "_fp16"
            for node in nodes:
                node.input[:] = [inner if n == out.name else n for n in node.input]
                node.output[:] = [inner if n == out.name else n for n in node.output]
            nodes.append(helper.make_node("Cast", [inner], [out.name], to=f32, name=out.name + "_as_fp32"))
    graph.ClearField("node")
    graph.node.extend(nodes)
    graph.ClearField("value_info")
    onnx.checker.check_model(model)
    return model


def gemm_to_matmul(model):
    """Rewrite each Gemm with an initialiser weight as MatMul + Add (dynamic quantisation skips Gemm).

    Parameters
    ----------
    model : onnx.ModelProto

    Returns
    -------
    model : onnx.ModelProto
        A copy; ``alpha``, ``beta`` and ``transB`` are folded into the new initialisers.
    matmuls : list of str
        Names of the MatMul nodes that replaced a Gemm.
    """
    model = copy.deepcopy(model)
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    nodes, matmuls = [], []
    for node in graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        if node.op_type != "Gemm" or attrs.get("transA", 0) or node.input[1] not in inits:
            nodes.append(node)
            continue
        out = node.output[0]
        weight = numpy_helper.to_array(inits[node.input[1]]).astype(np.float32)
        weight = (weight.T if attrs.get("transB", 0) else weight) * attrs.get("alpha", 1.0)
        graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(weight), f"{out}_matmul_weight"))
        name = f"{out}_matmul"
        product = out if len(node.input) < 3 or not node.input[2] else f"{out}_product"
        nodes.append(helper.make_node("MatMul", [node.input[0], f"{out}_matmul_weight"], [product], name=name))
        matmuls.append(name)
        if product != out:
            bias = numpy_helper.to_array(inits[node.input[2]]).astype(np.float32) * attrs.get("beta", 1.0)
            graph.initializer.append(numpy_helper.from_array(bias, f"{out}_bias"))
            nodes.append(helper.make_node("Add", [product, f"{out}_bias"], [out], name=f"{out}_add"))
    graph.ClearField("node")
    graph.node.extend(nodes)
    used = {name for node in nodes for name in node.input}
    kept = [t for t in graph.initializer if t.name in used]
    graph.ClearField("initializer")
    graph.initializer.extend(kept)
    return model, matmuls


def quantize_int8(model, path: Path) -> None:
    """Write a dynamically quantised (u8u8 MatMulInteger) copy of ``model`` to ``path``.

    Parameters
    ----------
    model : onnx.ModelProto
        A transfer network; its layers' Gemms are quantised, its encoding stays float32.
    path : Path
    """
    prepared, matmuls = gemm_to_matmul(model)
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the quantiser's advice to run its pre-processing is noise here
    try:
        quantize_dynamic(
            prepared, str(path), op_types_to_quantize=["MatMul"], nodes_to_quantize=matmuls,
            weight_type=QuantType.QUInt8, per_channel=True, extra_options={"MatMulConstBOnly": True},
        )  # fmt: skip
    finally:
        root.setLevel(level)


def build_variant(source: Path, precision: str, path: Path) -> Path:
    """Write the ``precision`` variant of the ONNX model ``source`` to ``path`` (unless present).

    Parameters
    ----------
    source : Path
        An exported float32 transfer network.
    precision : {"fp16", "fp16-mlp", "int8"}
    path : Path

    Returns
    -------
    Path
        ``path``.
    """
    if path.is_file():
        return path
    model = onnx.load(str(source))
    if precision == "int8":
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # a rename: never half a model
        try:
            quantize_int8(model, partial)
            os.replace(partial, path)
        finally:
            partial.unlink(missing_ok=True)
        return path
    keep = encoding_nodes(model) if precision == "fp16-mlp" else set()
    atomic_write_bytes(path, convert_to_fp16(model, keep).SerializeToString())
    return path


def variant_manifest(manifest, precision: str, folder: Path):
    """The manifest with its network segments' models replaced by their ``precision`` variants.

    Parameters
    ----------
    manifest : prt.runtime.manifest.Manifest
    precision : str
        One of :data:`PRECISIONS`; ``"fp32"`` returns ``manifest`` itself.
    folder : Path
        Where the variant models are built (keyed by the source models' contents).

    Returns
    -------
    Manifest
    """
    if precision == "fp32":
        return manifest
    segments = []
    for seg in manifest.segments:
        if seg.kind == "network":
            digest = hashlib.sha1(seg.model.read_bytes()).hexdigest()[:12]
            scheme = f"{precision}-{INT8_SCHEME}" if precision == "int8" else precision
            target = folder / f"{seg.model.stem}-{digest}-{scheme}.onnx"
            seg = dataclasses.replace(seg, model=build_variant(seg.model, precision, target))
        segments.append(seg)
    return dataclasses.replace(manifest, segments=segments)


def model_weight_bytes(manifest) -> int:
    """Bytes of every initialiser of the network segments' ONNX models."""
    total = 0
    for seg in manifest.segments:
        if seg.kind == "network":
            model = onnx.load(str(seg.model))
            total += sum(numpy_helper.to_array(t).nbytes for t in model.graph.initializer)
    return int(total)
