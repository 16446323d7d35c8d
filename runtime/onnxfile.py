"""ONNX model files read safely, before ONNX Runtime sees them (no ``onnx`` package needed).

A scene's models are data from whoever made the scene.  A tensor of an ONNX model may keep its
values in an *external* file named by a path (``TensorProto.external_data``, with
``data_location = EXTERNAL``); an ONNX Runtime that does not confine that path reads any file
it names as weights (``../../home/you/.ssh/id_rsa``).  Our exporter never writes external
data, so :func:`read_model` refuses every model that has any, wherever the tensor sits
(initializers, sparse initializers, node attributes, subgraphs, functions, training graphs),
and hands ONNX Runtime the bytes it checked, so the file cannot change in between.

The check walks the protobuf wire format along the few messages that can hold a tensor; it
needs no schema beyond their field numbers (onnx/onnx.proto3):

- ModelProto: graph 7, training_info 20, functions 25
- TrainingInfoProto: initialization 1, algorithm 2 (graphs)
- GraphProto: node 1, initializer 5, sparse_initializer 15
- NodeProto: attribute 5;  FunctionProto: node 7, attribute_proto 11
- AttributeProto: t 5, g 6, tensors 10, graphs 11, sparse_tensor 22, sparse_tensors 23
- SparseTensorProto: values 1, indices 2
- TensorProto: external_data 13, data_location 14 (1 = EXTERNAL)
"""

from __future__ import annotations

from pathlib import Path

from .errors import InputError

__all__ = ["read_model", "external_data_tensors"]

# message kind -> {field number: kind of the embedded message}
_CHILDREN = {
    "model": {7: "graph", 20: "training", 25: "function"},
    "training": {1: "graph", 2: "graph"},
    "graph": {1: "node", 5: "tensor", 15: "sparse"},
    "node": {5: "attribute"},
    "function": {7: "node", 11: "attribute"},
    "attribute": {5: "tensor", 6: "graph", 10: "tensor", 11: "graph", 22: "sparse", 23: "sparse"},
    "sparse": {1: "tensor", 2: "tensor"},
    "tensor": {},
}
_TENSOR_EXTERNAL_DATA = 13
_TENSOR_DATA_LOCATION = 14
_EXTERNAL = 1
_MAX_DEPTH = 64  # nested subgraphs; far beyond any real model, short of a stack of bombs


class _Malformed(Exception):
    pass


def _varint(data: memoryview, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(data) or shift > 63:
            raise _Malformed(pos)
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7


def _fields(data: memoryview):
    """(field number, wire type, value) of each field of one message; value is an int or a memoryview."""
    pos = 0
    while pos < len(data):
        key, pos = _varint(data, pos)
        field, wire = key >> 3, key & 7
        if field == 0:
            raise _Malformed(pos)
        if wire == 0:
            value, pos = _varint(data, pos)
        elif wire == 1:
            value, pos = None, pos + 8
        elif wire == 5:
            value, pos = None, pos + 4
        elif wire == 2:
            length, pos = _varint(data, pos)
            value, pos = data[pos : pos + length], pos + length
        else:  # groups (3, 4) are not in ONNX; anything else is not protobuf
            raise _Malformed(pos)
        if pos > len(data):
            raise _Malformed(pos)
        yield field, wire, value


def external_data_tensors(data: bytes) -> int:
    """How many tensors of a serialised ModelProto keep their values in external files.

    Raises
    ------
    ValueError
        If ``data`` is not a well-formed protobuf message with a graph.
    """
    stack = [("model", memoryview(data), 0)]
    found, has_graph = 0, False
    while stack:
        kind, message, depth = stack.pop()
        if depth > _MAX_DEPTH:
            raise ValueError(f"models nested more than {_MAX_DEPTH} deep")
        try:
            for field, wire, value in _fields(message):
                if kind == "tensor" and (
                    field == _TENSOR_EXTERNAL_DATA or (field == _TENSOR_DATA_LOCATION and wire == 0 and value == _EXTERNAL)
                ):
                    found += 1
                    break
                child = _CHILDREN[kind].get(field)
                if child is not None and wire == 2:
                    has_graph |= kind == "model" and child == "graph"
                    stack.append((child, value, depth + 1))
        except _Malformed as exc:
            raise ValueError(f"malformed protobuf in a {kind} message (byte {exc.args[0]})") from None
    if not has_graph:
        raise ValueError("no graph (not an ONNX model)")
    return found


def read_model(path: str | Path) -> bytes:
    """The bytes of an ONNX model file, checked to hold no external data.

    Parameters
    ----------
    path : str or Path
        The model (inside its scene folder: :func:`prt.runtime.manifest.load_manifest` confines it).

    Returns
    -------
    bytes
        What to give ``onnxruntime.InferenceSession`` (not the path: the checked bytes are the
        ones loaded, and ONNX Runtime has no folder to resolve external paths against).

    Raises
    ------
    InputError
        If the file cannot be read, is not an ONNX model, or has tensors with external data.
    """
    try:
        data = Path(path).read_bytes()
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read ONNX model ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        external = external_data_tensors(data)
    except ValueError as exc:
        raise InputError(f"{path}: not a valid ONNX model ({exc})") from None
    if external:
        raise InputError(
            f"{path}: {external} tensor(s) keep their data in external files; a scene's models must hold "
            "their weights (external data could read files outside the scene folder)"
        )
    return data
