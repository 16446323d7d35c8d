"""Animated glTF 2.0: reading a ``.glb`` / ``.gltf`` and posing its meshes at any clip time.

Only what a deforming surface needs is read: the default scene's node hierarchy, triangle
primitives (``POSITION``, ``JOINTS_n`` / ``WEIGHTS_n``, morph-target ``POSITION``), skins and the
animations' node TRS and morph ``weights`` channels.  Posing follows the specification:

- a node's local matrix is its ``matrix`` or ``T * R * S``; animation channels replace T, R, S or
  the morph weights; samplers interpolate ``STEP`` or ``LINEAR`` (spherical for rotations) and
  hold the end keys outside their range; ``CUBICSPLINE`` is refused;
- a skinned primitive is linear-blend skinned, ``sum_k w_k (world[joint_k] @ inverse_bind[joint_k])``,
  and the skinned node's own transform is ignored; other primitives take their node's world matrix;
- morph targets add ``sum_i weight_i * target_i`` to ``POSITION`` before skinning.

Every failure is a one-line :class:`~prt.runtime.errors.GeometryError` naming the file.
:func:`write_glb` packs arrays into a binary glTF (tests and ``scripts/prepare_character.py``).
"""

from __future__ import annotations

import base64
import json
import os
import struct
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from ...runtime.errors import GeometryError, PRTError
from ...runtime.files import atomic_write_bytes

__all__ = [
    "GltfFile",
    "read_gltf",
    "malformed_gltf",
    "AnimatedScene",
    "linear_blend_skinning",
    "sample_channel",
    "pack_accessors",
    "write_glb",
]

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
# Extensions this reader reads or that change nothing it uses (quantized accessors are read like any other;
# texture transforms: prt.train.inputs.gltf_scene.GltfScene.texture_coords).
_HARMLESS_EXTENSIONS = {"KHR_mesh_quantization", "KHR_materials_pbrSpecularGlossiness", "KHR_texture_transform"}


@dataclass
class GltfFile:
    """A parsed glTF: its JSON document and the bytes of each buffer.

    Attributes
    ----------
    path : str
        The file as given, for error messages.
    document : dict
        The JSON document.
    buffers : list of bytes
        ``buffers[i]`` holds buffer ``i`` (the GLB binary chunk, a data URI or an external file).
    """

    path: str
    document: dict
    buffers: list

    def accessor(self, index: int) -> np.ndarray:
        """Accessor ``index`` as a float64 or int64 array of shape ``(count, width)``.

        Normalised integer components are mapped to [0, 1] / [-1, 1]; sparse accessors are
        applied; an accessor without a buffer view reads as zeros.
        """
        accessors = self.document.get("accessors", [])
        if not 0 <= index < len(accessors):
            raise GeometryError(f"{self.path}: accessor {index} does not exist ({len(accessors)} accessors)")
        spec = accessors[index]
        try:
            dtype = np.dtype(_COMPONENTS[spec["componentType"]]).newbyteorder("<")
            width, count = _WIDTH[spec["type"]], int(spec["count"])
        except KeyError as error:
            raise GeometryError(f"{self.path}: accessor {index}: bad or missing {error}") from None
        if "bufferView" in spec:
            values = self._view_elements(spec["bufferView"], int(spec.get("byteOffset", 0)), dtype, width, count, index)
        else:
            values = np.zeros((count, width), dtype=dtype)
        if "sparse" in spec:
            values = values.copy()
            sparse = spec["sparse"]
            index_type = _COMPONENTS[sparse["indices"]["componentType"]]
            rows = self._sparse_part(sparse["indices"], index_type, 1, sparse["count"], index)
            values[rows[:, 0].astype(np.int64)] = self._sparse_part(sparse["values"], dtype, width, sparse["count"], index)
        if dtype.kind == "f":
            return values.astype(np.float64)
        if spec.get("normalized", False):
            limit = float(np.iinfo(dtype).max)
            return np.maximum(values.astype(np.float64) / limit, -1.0)
        return values.astype(np.int64)

    def _sparse_part(self, part: dict, dtype, width: int, count: int, index: int) -> np.ndarray:
        """The indices or values block of a sparse accessor."""
        dtype = np.dtype(dtype).newbyteorder("<")
        return self._view_elements(part["bufferView"], int(part.get("byteOffset", 0)), dtype, width, int(count), index)

    def _view_elements(self, view_index: int, offset: int, dtype, width: int, count: int, accessor: int) -> np.ndarray:
        """``count`` elements of ``width`` components read from a buffer view (strided or packed)."""
        views = self.document.get("bufferViews", [])
        if not 0 <= view_index < len(views):
            raise GeometryError(f"{self.path}: accessor {accessor}: buffer view {view_index} does not exist")
        view = views[view_index]
        buffer_index = view.get("buffer", 0)
        if not 0 <= buffer_index < len(self.buffers):
            raise GeometryError(f"{self.path}: buffer view {view_index}: buffer {buffer_index} does not exist")
        data = self.buffers[buffer_index]
        start = int(view.get("byteOffset", 0)) + offset
        element = dtype.itemsize * width
        stride = int(view.get("byteStride", 0)) or element
        end = start + stride * (count - 1) + element if count else start
        if end > min(len(data), int(view.get("byteOffset", 0)) + int(view["byteLength"])):
            raise GeometryError(f"{self.path}: accessor {accessor} reads past the end of buffer view {view_index}")
        raw = np.frombuffer(data, dtype=np.uint8, count=end - start, offset=start) if count else np.zeros(0, np.uint8)
        if stride == element:
            return raw.view(dtype).reshape(count, width)
        padded = np.concatenate([raw, np.zeros(stride - element, np.uint8)]).reshape(count, stride)
        return np.ascontiguousarray(padded[:, :element]).view(dtype).reshape(count, width)


def read_gltf(path) -> GltfFile:
    """Read a ``.glb`` or ``.gltf`` file with its buffers (embedded, data URIs or files beside it).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    GltfFile

    Raises
    ------
    GeometryError
        Unreadable, not glTF 2.0, a missing buffer file, or a required extension this reader lacks.
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        raise GeometryError(f"{path}: cannot read file ({error.strerror or error})") from None
    binary = None
    if data[:4] == b"glTF":
        document, binary = _split_glb(path, data)
    else:
        try:
            document = json.loads(data.decode("utf-8-sig"))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise GeometryError(f"{path}: not a glTF file (neither GLB nor JSON: {error})") from None
    if not isinstance(document, dict) or not str(document.get("asset", {}).get("version", "")).startswith("2"):
        raise GeometryError(f"{path}: not a glTF 2.0 file (asset.version must be 2.x)")
    unsupported = sorted(set(document.get("extensionsRequired", [])) - _HARMLESS_EXTENSIONS)
    if unsupported:
        raise GeometryError(f"{path}: requires unsupported glTF extensions {', '.join(unsupported)}")
    buffers = [_load_buffer(path, index, spec, binary) for index, spec in enumerate(document.get("buffers", []))]
    return GltfFile(path=path, document=document, buffers=buffers)


def _split_glb(path: str, data: bytes) -> tuple[dict, bytes | None]:
    """The JSON document and binary chunk of a GLB container."""
    if len(data) < 20:
        raise GeometryError(f"{path}: truncated GLB header")
    _, version, length = struct.unpack_from("<III", data, 0)
    if version != 2:
        raise GeometryError(f"{path}: GLB container version {version}, only version 2 is supported")
    chunks, offset = {}, 12
    while offset + 8 <= min(length, len(data)):
        size, kind = struct.unpack_from("<II", data, offset)
        chunks.setdefault(kind, data[offset + 8 : offset + 8 + size])
        offset += 8 + size + (-size) % 4
    if _JSON_CHUNK not in chunks:
        raise GeometryError(f"{path}: GLB file without a JSON chunk")
    try:
        document = json.loads(chunks[_JSON_CHUNK].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise GeometryError(f"{path}: GLB JSON chunk is not valid JSON ({error})") from None
    return document, chunks.get(_BIN_CHUNK)


def _load_buffer(path: str, index: int, spec: dict, binary: bytes | None) -> bytes:
    """The bytes of buffer ``index``: the GLB chunk, a base64 data URI, or a file beside ``path``."""
    uri = spec.get("uri")
    if uri is None:
        if binary is None:
            raise GeometryError(f"{path}: buffer {index} has no uri and the file has no GLB binary chunk")
        return binary
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1], validate=True)
        except (IndexError, ValueError):
            raise GeometryError(f"{path}: buffer {index}: malformed base64 data URI") from None
    from urllib.parse import unquote

    external = os.path.join(os.path.dirname(path), unquote(uri))
    try:
        with open(external, "rb") as handle:
            return handle.read()
    except OSError as error:
        raise GeometryError(f"{path}: buffer {index}: cannot read {external} ({error.strerror or error})") from None


@contextmanager
def malformed_gltf(path: str):
    """Turn the lookup errors of a document that breaks the glTF schema into one-line GeometryErrors.

    A missing key, an index past a list or a value of the wrong type anywhere in reading or
    posing becomes ``GeometryError("PATH: malformed glTF (...)")``; the project's own errors pass.
    """
    try:
        yield
    except PRTError:
        raise
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as error:
        text = " ".join(str(error).split())
        raise GeometryError(f"{path}: malformed glTF ({type(error).__name__}: {text})") from None


# --------------------------------------------------------------------------------------------
# Transforms and sampling


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of glTF quaternions ``(x, y, z, w)``, normalised first: (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def trs_matrix(translation, rotation, scale) -> np.ndarray:
    """The 4 x 4 matrix ``T * R * S`` of a glTF node."""
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_matrix(rotation) * np.asarray(scale, dtype=np.float64)[None, :]
    matrix[:3, 3] = translation
    return matrix


def slerp(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions by the shorter arc (``u`` in [0, 1])."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    dot = float(np.dot(a, b))
    if dot < 0.0:
        b, dot = -b, -dot
    if dot > 0.9995:  # nearly equal: the normalised lerp is exact to rounding
        q = a + u * (b - a)
        return q / np.linalg.norm(q)
    angle = np.arccos(dot)
    return (np.sin((1 - u) * angle) * a + np.sin(u * angle) * b) / np.sin(angle)


def sample_channel(times: np.ndarray, values: np.ndarray, t: float, interpolation: str, rotation: bool) -> np.ndarray:
    """The value of an animation sampler at time ``t``.

    Parameters
    ----------
    times : (N,) float64
        Increasing key times.
    values : (N, W) float64
        Key values (a rotation's are quaternions ``x, y, z, w``).
    t : float
        Clip time; before the first key the first value, after the last the last.
    interpolation : str
        ``"LINEAR"`` or ``"STEP"``.
    rotation : bool
        Interpolate linearly on the sphere (slerp) instead of componentwise.

    Returns
    -------
    (W,) float64
    """
    if t <= times[0] or len(times) == 1:
        return values[0].copy()
    if t >= times[-1]:
        return values[-1].copy()
    k = int(np.searchsorted(times, t, side="right")) - 1
    if interpolation == "STEP":
        return values[k].copy()
    u = (t - times[k]) / (times[k + 1] - times[k])
    if rotation:
        return slerp(values[k], values[k + 1], u)
    return (1 - u) * values[k] + u * values[k + 1]


def linear_blend_skinning(points: np.ndarray, joints: np.ndarray, weights: np.ndarray, matrices: np.ndarray) -> np.ndarray:
    """Linear blend skinning: ``p' = sum_k weights[:, k] * (matrices[joints[:, k]] @ [p, 1])``.

    Parameters
    ----------
    points : (V, 3) float64
    joints : (V, K) int64
        Skin joint index of each influence.
    weights : (V, K) float64
        Influence weights (summing to 1 per vertex).
    matrices : (J, 4, 4) float64
        Skinning matrix of each joint (joint world matrix times inverse bind matrix).

    Returns
    -------
    (V, 3) float64
    """
    blended = np.einsum("vk,vkij->vij", weights, matrices[joints])
    return np.einsum("vij,vj->vi", blended[:, :3, :3], points) + blended[:, :3, 3]


# --------------------------------------------------------------------------------------------
# Scenes


@dataclass
class _Primitive:
    """One triangle primitive of a mesh node in the default scene."""

    node: int
    positions: np.ndarray  # (V, 3) mesh space
    targets: np.ndarray  # (T, V, 3) morph-target position offsets
    faces: np.ndarray  # (F, 3) local vertex indices
    skin: int | None
    joints: np.ndarray | None  # (V, K) skin joint slots
    weights: np.ndarray | None  # (V, K) normalised


@dataclass
class Clip:
    """An animation: ``channels`` of ``(node, path, times, values, interpolation)``."""

    name: str
    channels: list

    @property
    def time_range(self) -> tuple[float, float]:
        """The first and last key time over all channels."""
        return min(c[2][0] for c in self.channels), max(c[2][-1] for c in self.channels)


class AnimatedScene:
    """The default scene of a glTF file, merged into one triangle list and posable by a clip.

    Parameters
    ----------
    gltf : GltfFile
    """

    def __init__(self, gltf: GltfFile):
        self.gltf, self.path = gltf, gltf.path
        document = gltf.document
        self.nodes = document.get("nodes", [])
        self._order = self._scene_order(document)
        self.primitives = [p for node, _ in self._order for p in self._node_primitives(node)]
        if not self.primitives:
            raise GeometryError(f"{self.path}: the default scene has no triangle meshes")
        self._inverse_binds = {}
        for primitive in self.primitives:
            if primitive.skin is not None and primitive.skin not in self._inverse_binds:
                self._inverse_binds[primitive.skin] = self._inverse_bind_matrices(primitive.skin)
        offsets = np.cumsum([0] + [len(p.positions) for p in self.primitives])
        self.faces = np.concatenate([p.faces + o for p, o in zip(self.primitives, offsets)])

    @property
    def deforms(self) -> bool:
        """Whether any primitive is skinned or has morph targets."""
        return any(p.skin is not None or len(p.targets) for p in self.primitives)

    @property
    def animation_names(self) -> list[str]:
        """Each animation's name (``#i`` for an unnamed one)."""
        return [a.get("name") or f"#{i}" for i, a in enumerate(self.gltf.document.get("animations", []))]

    # ---- structure ----------------------------------------------------------------------

    def _scene_order(self, document: dict) -> list[tuple[int, int | None]]:
        """``(node, parent)`` of every node of the default scene, parents first."""
        scenes = document.get("scenes")
        if scenes:
            roots = scenes[document.get("scene", 0)].get("nodes", [])
        else:
            children = {c for n in self.nodes for c in n.get("children", [])}
            roots = [i for i in range(len(self.nodes)) if i not in children]
        order, stack, seen = [], [(r, None) for r in reversed(roots)], set()
        while stack:
            node, parent = stack.pop()
            if not 0 <= node < len(self.nodes) or node in seen:
                raise GeometryError(f"{self.path}: node {node} is missing or appears twice in the scene graph")
            seen.add(node)
            order.append((node, parent))
            stack.extend((c, node) for c in reversed(self.nodes[node].get("children", [])))
        return order

    def _node_primitives(self, node: int) -> list[_Primitive]:
        """The triangle primitives of ``node``'s mesh (none if it has no mesh)."""
        spec = self.nodes[node]
        if "mesh" not in spec:
            return []
        result = []
        for number, prim in enumerate(self.gltf.document["meshes"][spec["mesh"]]["primitives"]):
            where = f"mesh {spec['mesh']} primitive {number}"
            if prim.get("mode", 4) != 4:
                raise GeometryError(f"{self.path}: {where}: mode {prim['mode']} is not triangles (4)")
            attributes = prim.get("attributes", {})
            if "POSITION" not in attributes:
                raise GeometryError(f"{self.path}: {where}: no POSITION attribute")
            positions = self.gltf.accessor(attributes["POSITION"])
            faces = (self.gltf.accessor(prim["indices"]).reshape(-1) if "indices" in prim else np.arange(len(positions)))
            if len(faces) % 3 or (len(faces) and (faces.min() < 0 or faces.max() >= len(positions))):
                raise GeometryError(f"{self.path}: {where}: indices are not triangles over its {len(positions)} vertices")
            targets = [
                self.gltf.accessor(t["POSITION"]) if "POSITION" in t else np.zeros_like(positions)
                for t in prim.get("targets", [])
            ]
            skin, joints, weights = spec.get("skin"), None, None
            if skin is not None:
                joints, weights = self._influences(attributes, where, len(positions))
            targets = np.asarray(targets).reshape(-1, len(positions), 3)
            result.append(_Primitive(node, positions, targets, faces.reshape(-1, 3), skin, joints, weights))
        return result

    def _influences(self, attributes: dict, where: str, count: int) -> tuple[np.ndarray, np.ndarray]:
        """All ``JOINTS_n`` / ``WEIGHTS_n`` sets side by side, weights normalised per vertex."""
        sets = sorted(int(k.split("_")[1]) for k in attributes if k.startswith("JOINTS_"))
        if not sets or any(f"WEIGHTS_{n}" not in attributes for n in sets):
            raise GeometryError(f"{self.path}: {where}: skinned but without matching JOINTS_n / WEIGHTS_n")
        joints = np.concatenate([self.gltf.accessor(attributes[f"JOINTS_{n}"]) for n in sets], axis=1)
        weights = np.concatenate([self.gltf.accessor(attributes[f"WEIGHTS_{n}"]) for n in sets], axis=1)
        total = weights.sum(axis=1, keepdims=True)
        if len(joints) != count or not np.all(total > 0):
            raise GeometryError(f"{self.path}: {where}: {int(np.sum(total <= 0))} vertices have no skin weight")
        return joints, weights / total

    def _inverse_bind_matrices(self, skin: int) -> np.ndarray:
        """(J, 4, 4) inverse bind matrices of a skin (identity where the file gives none)."""
        spec = self.gltf.document["skins"][skin]
        if "inverseBindMatrices" not in spec:
            return np.tile(np.eye(4), (len(spec["joints"]), 1, 1))
        # glTF matrices are column-major.
        return self.gltf.accessor(spec["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)

    # ---- animation ----------------------------------------------------------------------

    def clip(self, name: str | None) -> Clip:
        """The animation called ``name`` (``None``: the only one), its channels checked and read."""
        names = self.animation_names
        if not names:
            raise GeometryError(f"{self.path}: has no animations")
        if name is None:
            if len(names) > 1:
                raise GeometryError(f"{self.path}: has {len(names)} animations, name one: {', '.join(names)}")
            name = names[0]
        if name not in names:
            raise GeometryError(f"{self.path}: no animation {name!r} (it has: {', '.join(names)})")
        spec = self.gltf.document["animations"][names.index(name)]
        channels = []
        for number, channel in enumerate(spec.get("channels", [])):
            target = channel.get("target", {})
            if "node" not in target:
                continue  # an extension's target (e.g. KHR_animation_pointer) moves no node
            sampler = spec["samplers"][channel["sampler"]]
            where = f"{self.path}: animation {name!r} channel {number}"
            interpolation = sampler.get("interpolation", "LINEAR")
            if interpolation not in ("LINEAR", "STEP"):
                raise GeometryError(f"{where}: {interpolation} interpolation is not supported (re-export with LINEAR or STEP)")
            path = target.get("path")
            if path not in ("translation", "rotation", "scale", "weights"):
                raise GeometryError(f"{where}: unknown target path {path!r}")
            if path != "weights" and "matrix" in self.nodes[target["node"]]:
                raise GeometryError(f"{where}: animates node {target['node']}, which has a matrix instead of TRS")
            times = self.gltf.accessor(sampler["input"]).reshape(-1)
            values = self.gltf.accessor(sampler["output"])
            if not len(times) or np.any(np.diff(times) < 0) or len(values) * values.shape[1] % len(times):
                raise GeometryError(f"{where}: key times are empty, decreasing or do not match the values")
            channels.append((target["node"], path, times, values.reshape(len(times), -1), interpolation))
        if not channels:
            raise GeometryError(f"{self.path}: animation {name!r} has no node channels")
        return Clip(name, channels)

    def _local_trs(self, node: int) -> tuple | np.ndarray:
        """A node's rest transform: ``(T, R, S)`` or its 4 x 4 matrix."""
        spec = self.nodes[node]
        if "matrix" in spec:
            return np.asarray(spec["matrix"], dtype=np.float64).reshape(4, 4).T
        return (
            np.asarray(spec.get("translation", [0, 0, 0]), dtype=np.float64),
            np.asarray(spec.get("rotation", [0, 0, 0, 1]), dtype=np.float64),
            np.asarray(spec.get("scale", [1, 1, 1]), dtype=np.float64),
        )

    def _world_matrices(self, overrides: dict) -> dict[int, np.ndarray]:
        """World matrix of every scene node, ``overrides[(node, path)]`` replacing rest TRS values."""
        world = {}
        for node, parent in self._order:
            local = self._local_trs(node)
            if not isinstance(local, np.ndarray):
                t, r, s = (overrides.get((node, p), v) for p, v in zip(("translation", "rotation", "scale"), local))
                local = trs_matrix(t, r, s)
            world[node] = local if parent is None else world[parent] @ local
        return world

    def _morph_weights(self, node: int, overrides: dict) -> np.ndarray:
        """The morph weights of a mesh node: animated, else the node's, else the mesh's defaults."""
        if (node, "weights") in overrides:
            return overrides[(node, "weights")]
        spec = self.nodes[node]
        return np.asarray(spec.get("weights", self.gltf.document["meshes"][spec["mesh"]].get("weights", [])), dtype=np.float64)

    def _positions(self, world: dict, overrides: dict, bind: bool) -> np.ndarray:
        """Merged (V, 3) positions; ``bind``: skinned primitives at their bind pose."""
        result = []
        for primitive in self.primitives:
            points = primitive.positions
            if len(primitive.targets):
                weights = self._morph_weights(primitive.node, overrides)
                if len(weights) != len(primitive.targets):
                    raise GeometryError(
                        f"{self.path}: node {primitive.node}: {len(weights)} morph weights for {len(primitive.targets)} targets"
                    )
                points = points + np.einsum("t,tvi->vi", weights, primitive.targets)
            if primitive.skin is None:
                matrix = world[primitive.node]
                points = points @ matrix[:3, :3].T + matrix[:3, 3]
            elif not bind:
                joints = self.gltf.document["skins"][primitive.skin]["joints"]
                if any(j not in world for j in joints):
                    raise GeometryError(f"{self.path}: skin {primitive.skin} has joints outside the default scene")
                matrices = np.stack([world[j] for j in joints]) @ self._inverse_binds[primitive.skin]
                if primitive.joints.max() >= len(joints):
                    raise GeometryError(f"{self.path}: skin {primitive.skin}: JOINTS_n index out of range ({len(joints)} joints)")
                points = linear_blend_skinning(points, primitive.joints, primitive.weights, matrices)
            result.append(points)
        return np.concatenate(result)

    def rest(self) -> np.ndarray:
        """The bind pose: skins at their bind matrices, morph weights at their defaults, (V, 3)."""
        return self._positions(self._world_matrices({}), {}, bind=True)

    def pose(self, clip: Clip, t: float) -> np.ndarray:
        """The merged (V, 3) positions at clip time ``t``."""
        overrides = {
            (node, path): sample_channel(times, values, t, interpolation, rotation=path == "rotation")
            for node, path, times, values, interpolation in clip.channels
        }
        return self._positions(self._world_matrices(overrides), overrides, bind=False)


# --------------------------------------------------------------------------------------------
# Writing


def pack_accessors(arrays: list[np.ndarray]) -> tuple[list[dict], list[dict], bytes]:
    """Pack arrays into one binary buffer: one buffer view and one accessor each.

    Parameters
    ----------
    arrays : list of (N, W) arrays
        float32 (W 1, 2, 3, 4 or 16), uint8/uint16 (W 4: joints) or uint32 (W 1: indices).

    Returns
    -------
    buffer_views, accessors : list of dict
        Accessor ``i`` reads ``arrays[i]``; float accessors carry ``min`` / ``max``.
    binary : bytes
        The buffer, each view 4-byte aligned.
    """
    types = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
    codes = {np.dtype(v).newbyteorder("<"): k for k, v in _COMPONENTS.items()}
    views, accessors, chunks, offset = [], [], [], 0
    for index, array in enumerate(arrays):
        array = np.asarray(array)
        array = array.reshape(len(array), -1).astype(array.dtype.newbyteorder("<"))
        data = array.tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
        accessor = {"bufferView": index, "componentType": codes[array.dtype], "count": len(array), "type": types[array.shape[1]]}
        if array.dtype.kind == "f":
            accessor["min"], accessor["max"] = array.min(axis=0).tolist(), array.max(axis=0).tolist()
        accessors.append(accessor)
        chunks.append(data + b"\0" * ((-len(data)) % 4))
        offset += len(chunks[-1])
    return views, accessors, b"".join(chunks)


def write_glb(path, document: dict, binary: bytes) -> None:
    """Write a GLB file (atomically): ``document`` with ``buffers`` set to the binary chunk."""
    document = dict(document, buffers=[{"byteLength": len(binary)}])
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * ((-len(text)) % 4)
    binary += b"\0" * ((-len(binary)) % 4)
    length = 12 + 8 + len(text) + 8 + len(binary)
    header = struct.pack("<III", _GLB_MAGIC, 2, length)
    json_chunk = struct.pack("<II", len(text), _JSON_CHUNK) + text
    atomic_write_bytes(path, header + json_chunk + struct.pack("<II", len(binary), _BIN_CHUNK) + binary)
