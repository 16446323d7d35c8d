"""glTF 2.0 scenes as the build reads them: one object per (node, triangle primitive), named deterministically.

:func:`read_gltf_scene` walks the default scene (``scene``, else the first of ``scenes``, else
every node that is no node's child) depth first, children in their order, and gives one
:class:`GltfPart` per triangle primitive (modes 4, 5 and 6; points and lines have no surface) of
every node with a mesh.  A mesh used by several nodes (instancing) gives a part per node.  Each
part's vertices are in world space (the node's world matrix, ``matrix`` or ``T * R * S``
composed from the root); where that matrix has a negative determinant the triangles' winding is
reversed, as the glTF specification defines front faces (counter-clockwise only for a positive
determinant).  Skins and morph targets are not applied (the bind pose as stored).

Object names (the same file always gives the same names; nothing random):

- a node's label: its ``name``, else its mesh's ``name``, else ``node<i>`` (``i`` its index);
- a label already taken by an earlier node (in traversal order) gets the first free ``_1``,
  ``_2``, ... suffix, never one that another node's label is;
- a part of a mesh with one triangle primitive is named by its node's label; a mesh with several
  gives ``<label>/<k>``, ``k`` the primitive's index in the mesh's ``primitives``; a name still
  repeated (a node literally called ``A/0`` beside node ``A``'s primitive 0) takes a suffix too;
- a file with a single part names it after the file (as for every other single-mesh format).

The materials' images (:meth:`GltfScene.image`) are decoded from buffer views, data URIs or files
beside the scene; texture coordinates (:meth:`GltfScene.texcoords`) are returned in OBJ's
convention (``v = 0`` at the image's bottom: ``v = 1 - v_gltf``).  Every failure is a one-line
:class:`~prt.runtime.errors.GeometryError` naming the file.
"""

from __future__ import annotations

import base64
import os
from dataclasses import dataclass, field

import numpy as np

from ...runtime.errors import GeometryError
from ..deform.gltf_animation import GltfFile, malformed_gltf, read_gltf, trs_matrix
from .cutout import CUT_BUDGET, DEFAULT_CUTOFF, cut_within_budget

__all__ = ["GltfPart", "GltfScene", "read_gltf_scene", "unique_names", "albedo_texture_info", "SPEC_GLOSS", "alpha_cutoff", "cut_parts"]

SPEC_GLOSS = "KHR_materials_pbrSpecularGlossiness"

_TRIANGLES, _STRIP, _FAN = 4, 5, 6
_MIME_EXTENSIONS = {"image/png": ".png", "image/jpeg": ".jpg", "image/webp": ".webp", "image/bmp": ".bmp", "image/gif": ".gif"}
# Texture containers for GPUs (block-compressed), by their first bytes: read as no image (a warning), not as a corrupt file.
_GPU_FORMATS = ((b"\xabKTX 20\xbb\r\n\x1a\n", "KTX2"), (b"\xabKTX 11\xbb\r\n\x1a\n", "KTX"), (b"DDS ", "DDS"))


@dataclass
class GltfPart:
    """One triangle primitive of one node: an object of the scene.

    Attributes
    ----------
    name : str
    node, mesh, primitive : int
        Indices in the document (``primitive`` within the mesh).
    material : int or None
        The primitive's ``material`` index; None when it has none.
    vertices : (V, 3) float64
        World-space positions.
    faces : (F, 3) int64
        Triangles over ``vertices`` (winding reversed under a negative-determinant matrix).
    attributes : dict
        The primitive's ``attributes`` (accessor indices by semantic).
    """

    name: str
    node: int
    mesh: int
    primitive: int
    material: int | None
    vertices: np.ndarray
    faces: np.ndarray
    attributes: dict = field(default_factory=dict)
    # Cut along its material's alpha (:func:`cut_parts`): (the primitive's faces, each piece's face index
    # in them, each piece's corners as barycentric weights, the primitive's vertex count); then
    # ``vertices`` and ``faces`` are the pieces' (three vertices each).
    remap: tuple | None = None


@dataclass
class GltfScene:
    """A glTF file's default scene as parts (see the module docstring)."""

    gltf: GltfFile
    parts: list
    _images: dict = field(default_factory=dict)
    transparent: list = field(default_factory=list)  # names of the parts left out as see-through (is_see_through)
    cut: dict = field(default_factory=dict)  # name -> (pieces, triangles before) of the parts cut along their alpha
    cut_away: list = field(default_factory=list)  # names of the parts whose alpha leaves nothing (left out)
    uncut: list = field(default_factory=list)  # names of alpha-masked parts whose alpha could not be read (drawn opaque)
    unreadable: dict = field(default_factory=dict)  # texture -> the GPU format its image is in (not decoded here)

    @property
    def path(self) -> str:
        return self.gltf.path

    @property
    def document(self) -> dict:
        return self.gltf.document

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
        """All parts as one triangle soup: vertices, faces, object ids, object names."""
        if not self.parts:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64), []
        offsets = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        vertices = np.concatenate([p.vertices for p in self.parts])
        faces = np.concatenate([p.faces + o for p, o in zip(self.parts, offsets)])
        object_ids = np.repeat(np.arange(len(self.parts), dtype=np.int64), [len(p.faces) for p in self.parts])
        return vertices, faces, object_ids, [p.name for p in self.parts]

    def texcoords(self, part: GltfPart, index: int = 0) -> np.ndarray | None:
        """``TEXCOORD_<index>`` of ``part`` (V, 2) in OBJ's convention, or None when it has none."""
        key = f"TEXCOORD_{int(index)}"
        if key not in part.attributes:
            return None
        with malformed_gltf(self.path):
            uv = self.gltf.accessor(part.attributes[key])[:, :2].astype(np.float64)
        count = len(part.vertices) if part.remap is None else part.remap[3]
        if len(uv) != count:
            raise GeometryError(f"{self.path}: mesh {part.mesh} primitive {part.primitive}: {key} has {len(uv)} values for {count} vertices")
        uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)
        if part.remap is not None:  # the pieces' corners, each interpolated in its triangle
            faces, face, bary, _ = part.remap
            uv = np.einsum("kcj,kjd->kcd", bary, uv[faces[face]]).reshape(-1, 2)
        return uv

    def texture_coords(self, part: GltfPart, info: dict | None) -> np.ndarray | None:
        """The UVs a texture reference ``info`` (a ``textureInfo``) reads on ``part``, in OBJ's
        convention: its ``texCoord`` set, through its ``KHR_texture_transform`` where it has one
        (:func:`texture_transform`; the extension's own ``texCoord`` wins); None without that set."""
        info = info or {}
        transform = (info.get("extensions") or {}).get(TEXTURE_TRANSFORM)
        index = int((transform or {}).get("texCoord", info.get("texCoord", 0)))
        uv = self.texcoords(part, index)
        if uv is None or not transform:
            return uv
        with malformed_gltf(self.path):
            matrix = texture_transform(transform)
        gltf_uv = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)  # back to glTF's v, where the transform is defined
        moved = gltf_uv @ matrix[:2, :2].T + matrix[:2, 2]
        return np.stack([moved[:, 0], 1.0 - moved[:, 1]], axis=1)

    def mean_vertex_colour(self, part: GltfPart) -> np.ndarray | None:
        """The mean linear RGB of ``part``'s ``COLOR_0`` over its vertices, or None without one."""
        if "COLOR_0" not in part.attributes:
            return None
        with malformed_gltf(self.path):
            colours = self.gltf.accessor(part.attributes["COLOR_0"])
        if len(colours) == 0:
            return None
        return np.asarray(colours[:, :3], dtype=np.float64).mean(axis=0)

    def image(self, texture: int) -> np.ndarray | None:
        """The image of texture ``texture`` as (H, W, C) uint8 or uint16 (C 1-4), decoded once;
        None when its file is missing (the caller warns).  A corrupt image is a GeometryError."""
        if texture in self._images:
            return self._images[texture]
        with malformed_gltf(self.path):
            spec = self.document["textures"][texture]
            source = spec.get("source")
            for extension in ("EXT_texture_webp", "KHR_texture_basisu", "MSFT_texture_dds"):
                if source is None and extension in spec.get("extensions", {}):
                    source = spec["extensions"][extension].get("source")
            if source is None:
                raise GeometryError(f"{self.path}: texture {texture} has no image source")
            image = self.document["images"][source]
            data, suffix = self._image_bytes(source, image)
        kind = None if data is None else next((name for magic, name in _GPU_FORMATS if data.startswith(magic)), None)
        if kind is not None:  # a compressed GPU texture (KHR_texture_basisu without a fallback, DDS): not an image here
            self.unreadable[texture] = kind
            data = None
        decoded = None if data is None else _decode_image(data, suffix, f"{self.path}: image {source}")
        self._images[texture] = decoded
        return decoded

    def _image_bytes(self, index: int, image: dict) -> tuple[bytes | None, str | None]:
        suffix = _MIME_EXTENSIONS.get(image.get("mimeType"))
        if "bufferView" in image:
            view = self.document["bufferViews"][image["bufferView"]]
            buffer = self.gltf.buffers[view.get("buffer", 0)]
            start = int(view.get("byteOffset", 0))
            return bytes(buffer[start : start + int(view["byteLength"])]), suffix
        uri = image.get("uri")
        if not isinstance(uri, str):
            raise GeometryError(f"{self.path}: image {index} has neither a bufferView nor a uri")
        if uri.startswith("data:"):
            header, _, payload = uri.partition(",")
            suffix = _MIME_EXTENSIONS.get(header[5:].split(";")[0], suffix)
            try:
                return base64.b64decode(payload, validate=True), suffix
            except ValueError:
                raise GeometryError(f"{self.path}: image {index}: malformed base64 data URI") from None
        from urllib.parse import unquote

        external = os.path.join(os.path.dirname(self.path), unquote(uri))
        if not os.path.isfile(external):
            return None, None
        with open(external, "rb") as handle:
            return handle.read(), os.path.splitext(external)[1].lower() or suffix


TEXTURE_TRANSFORM = "KHR_texture_transform"


def texture_transform(spec: dict) -> np.ndarray:
    """The 3x3 UV matrix of a ``KHR_texture_transform`` (glTF's UV convention): translation times
    rotation times scale, as the extension defines it (``offset``, ``rotation`` in radians,
    ``scale``)."""
    ox, oy = (float(v) for v in spec.get("offset", [0.0, 0.0]))
    sx, sy = (float(v) for v in spec.get("scale", [1.0, 1.0]))
    c, s = np.cos(float(spec.get("rotation", 0.0))), np.sin(float(spec.get("rotation", 0.0)))
    translation = np.array([[1.0, 0.0, ox], [0.0, 1.0, oy], [0.0, 0.0, 1.0]])
    rotation = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return translation @ rotation @ np.diag([sx, sy, 1.0])


def albedo_texture_info(document: dict, material: int | None) -> dict | None:
    """The ``textureInfo`` of material ``material``'s albedo texture (the spec-gloss extension's
    ``diffuseTexture`` where the extension is present, else ``baseColorTexture``), or None."""
    if material is None:
        return None
    spec = document["materials"][material]
    gloss = spec.get("extensions", {}).get(SPEC_GLOSS)
    if gloss is not None:
        return gloss.get("diffuseTexture")
    return spec.get("pbrMetallicRoughness", {}).get("baseColorTexture")


def _decode_image(data: bytes, suffix: str | None, where: str) -> np.ndarray:
    import warnings

    import imageio.v3 as iio

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            image = np.asarray(iio.imread(data, extension=suffix) if suffix else iio.imread(data))
    except Exception as exc:  # imageio raises many kinds on bad bytes
        text = " ".join(str(exc).split())[:160]
        raise GeometryError(f"{where}: cannot decode the image, corrupt or an unsupported format ({type(exc).__name__}: {text})") from None
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 2, 3, 4) or image.dtype.kind != "u" or min(image.shape[:2]) < 1:
        raise GeometryError(f"{where}: expected a grey, RGB or RGBA image, got shape {image.shape} {image.dtype}")
    return image


def read_gltf_scene(path, stem: str | None = None) -> GltfScene:
    """Read a ``.glb`` / ``.gltf`` file's default scene as named parts (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
    stem : str, optional
        The name of a single-part file's object (default: the file name without extension).

    Raises
    ------
    GeometryError
        Unreadable or malformed file (one line naming it).
    """
    path = os.fspath(path)
    gltf = read_gltf(path)
    with malformed_gltf(path):
        parts = _scene_parts(gltf)
    names = unique_names([p.name for p in parts])
    if len(parts) == 1:
        names = [stem if stem is not None else os.path.splitext(os.path.basename(path))[0]]
    for part, name in zip(parts, names):
        part.name = name
    materials = gltf.document.get("materials", [])
    clear = [p for p in parts if p.material is not None and 0 <= p.material < len(materials) and is_see_through(materials[p.material])]
    if clear and len(clear) < len(parts):
        parts = [p for p in parts if not any(p is c for c in clear)]
    else:
        clear = []
    scene = GltfScene(gltf=gltf, parts=parts, transparent=[p.name for p in clear])
    cut_parts(scene)
    return scene


def alpha_cutoff(material: dict) -> float | None:
    """The alpha below which a glTF material has no surface: ``alphaCutoff`` (0.5 by default) for
    ``alphaMode`` MASK; :data:`SEE_THROUGH_ALPHA` for BLEND (its clear texels let light through, as
    a clear blended material does: :func:`is_see_through`); None for OPAQUE."""
    if not isinstance(material, dict):
        return None
    mode = material.get("alphaMode", "OPAQUE")
    if mode == "MASK":
        cutoff = material.get("alphaCutoff", DEFAULT_CUTOFF)
        return float(cutoff) if isinstance(cutoff, (int, float)) and np.isfinite(cutoff) else DEFAULT_CUTOFF
    return SEE_THROUGH_ALPHA if mode == "BLEND" else None


def factor_alpha(material: dict) -> float:
    """The alpha of a material's base colour factor (the spec-gloss extension's ``diffuseFactor``
    where present), 1 where it gives none."""
    gloss = (material.get("extensions") or {}).get(SPEC_GLOSS)
    factor = (gloss or {}).get("diffuseFactor") if gloss is not None else (material.get("pbrMetallicRoughness") or {}).get("baseColorFactor")
    if isinstance(factor, list) and len(factor) == 4 and isinstance(factor[3], (int, float)):
        return float(factor[3])
    return 1.0


def _albedo_info(scene: GltfScene, part: GltfPart) -> dict | None:
    return albedo_texture_info(scene.document, part.material)


def alpha_image(scene: GltfScene, texture: int) -> np.ndarray | None:
    """The alpha channel of texture ``texture``'s image, (H, W) float64 in [0, 1], row 0 at the top;
    None when its image has no alpha channel or its file is missing (the materials' reader says so)."""
    image = scene.image(int(texture))
    if image is None or image.shape[2] not in (2, 4):
        return None
    return image[:, :, -1].astype(np.float64) / float(np.iinfo(image.dtype).max)


def cut_parts(scene: GltfScene, budget: int = CUT_BUDGET) -> None:
    """Cut every part of an alpha-masked material (:func:`alpha_cutoff`) along its alpha
    (:func:`prt.train.inputs.cutout.cut_triangles`), in place: a part whose alpha leaves nothing
    is left out (``scene.cut_away``), one cut into pieces gets them as its triangles (``scene.cut``).
    The alpha is the factor's times the colour texture's; without a texture alpha a part is
    whole or wholly gone."""
    materials = scene.document.get("materials", [])
    jobs = []  # (part, cutoff, alpha image or None, factor)
    shared: dict = {}  # (texture, factor) -> factor x its alpha: one array for every part using it
    for part in scene.parts:
        if part.material is None or not 0 <= part.material < len(materials):
            continue
        cutoff = alpha_cutoff(materials[part.material])
        if cutoff is None:
            continue
        factor = factor_alpha(materials[part.material])
        with malformed_gltf(scene.path):
            info, alpha = _albedo_info(scene, part), None
            if info is not None and scene.texture_coords(part, info) is not None:
                key = (int(info["index"]), factor)
                if key not in shared:
                    image = alpha_image(scene, key[0])
                    shared[key] = None if image is None else (factor * image).astype(np.float32)
                alpha = shared[key]
                if alpha is None and scene.image(key[0]) is None:  # an alpha we cannot read: drawn opaque, and said so
                    scene.uncut.append(part.name)
            jobs.append((part, cutoff, alpha, factor))
    if not jobs:
        return
    textured = [k for k, job in enumerate(jobs) if job[2] is not None]
    cuts = cut_within_budget([(scene.texture_coords(jobs[k][0], _albedo_info(scene, jobs[k][0]))[jobs[k][0].faces], jobs[k][2], jobs[k][1])
                              for k in textured], budget)  # fmt: skip
    results = dict(zip(textured, cuts))
    for k, (_, cutoff, image, factor) in enumerate(jobs):
        if image is None:  # the factor alone: all or nothing
            results[k] = None if factor >= cutoff else (np.zeros(0, np.int64), np.zeros((0, 3, 3)))
    gone = {id(jobs[k][0]) for k, r in results.items() if r is not None and not len(r[0])}
    if len(gone) == len(scene.parts):  # nothing would be left: keep the file as it is drawn opaque
        return
    for k, result in results.items():
        part = jobs[k][0]
        if result is None or id(part) in gone:
            continue
        face, bary = result
        if len(face) == len(part.faces) and np.array_equal(bary, np.broadcast_to(np.eye(3), bary.shape)):
            continue  # every triangle opaque
        scene.cut[part.name] = (len(face), len(part.faces))
        corners = np.einsum("kcj,kjd->kcd", bary, part.vertices[part.faces[face]])
        part.remap = (part.faces, face, bary, len(part.vertices))
        part.vertices = corners.reshape(-1, 3)
        part.faces = np.arange(3 * len(face), dtype=np.int64).reshape(-1, 3)
    scene.cut_away = [p.name for p in scene.parts if id(p) in gone]
    scene.parts = [p for p in scene.parts if id(p) not in gone]


# Glass: a blended material this transparent, or one that transmits this much, lets light through.
SEE_THROUGH_ALPHA = 0.5
SEE_THROUGH_TRANSMISSION = 0.5


def is_see_through(material: dict) -> bool:
    """Whether a glTF material is glass-like: ``alphaMode`` BLEND with a base (or spec-gloss diffuse)
    alpha below ``SEE_THROUGH_ALPHA``, or ``KHR_materials_transmission`` at least
    ``SEE_THROUGH_TRANSMISSION``.  Transfer here is opaque occlusion, so such parts are left out
    of the scene (light passes through them, as the camera looks through them)."""
    if not isinstance(material, dict):
        return False
    extensions = material.get("extensions") or {}
    transmission = (extensions.get("KHR_materials_transmission") or {}).get("transmissionFactor", 0.0)
    if isinstance(transmission, (int, float)) and transmission >= SEE_THROUGH_TRANSMISSION:
        return True
    if material.get("alphaMode") != "BLEND":
        return False
    factor = (material.get("pbrMetallicRoughness") or {}).get("baseColorFactor")
    gloss = (extensions.get("KHR_materials_pbrSpecularGlossiness") or {}).get("diffuseFactor")
    alpha = [f[3] for f in (factor, gloss) if isinstance(f, list) and len(f) == 4 and isinstance(f[3], (int, float))]
    return bool(alpha) and min(alpha) < SEE_THROUGH_ALPHA


def unique_names(names: list[str]) -> list[str]:
    """``names`` with each repeat given the first free ``_1``, ``_2``, ... suffix, in order.

    A suffix never produces a name that appears anywhere in ``names``.
    """
    given, taken, out = set(names), set(), []
    for name in names:
        unique, k = name, 0
        while unique in taken or (k and unique in given):
            k += 1
            unique = f"{name}_{k}"
        taken.add(unique)
        out.append(unique)
    return out


def _scene_parts(gltf: GltfFile) -> list[GltfPart]:
    document, path = gltf.document, gltf.path
    nodes = document.get("nodes", [])
    meshes = document.get("meshes", [])
    scenes = document.get("scenes")
    if scenes:
        roots = scenes[int(document.get("scene", 0))].get("nodes", [])
    else:
        children = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    labelled: list[tuple[str, bool, list[GltfPart]]] = []  # per mesh node: label, several primitives, parts
    stack = [(int(r), np.eye(4)) for r in reversed(roots)]
    seen: set[int] = set()
    while stack:
        index, parent = stack.pop()
        if not 0 <= index < len(nodes):
            raise GeometryError(f"{path}: node {index} does not exist ({len(nodes)} nodes)")
        if index in seen:  # a node with two parents (or a cycle) breaks the spec; one visit
            continue
        seen.add(index)
        node = nodes[index]
        world = parent @ _local_matrix(node, f"{path}: node {index}")
        if "mesh" in node:
            mesh_index = int(node["mesh"])
            mesh = meshes[mesh_index]
            label = _label(node.get("name")) or _label(mesh.get("name")) or f"node{index}"
            triangle_prims = [k for k, p in enumerate(mesh["primitives"]) if p.get("mode", _TRIANGLES) in (_TRIANGLES, _STRIP, _FAN)]
            node_parts = [_part(gltf, mesh_index, k, mesh["primitives"][k], index, world) for k in triangle_prims]
            node_parts = [p for p in node_parts if len(p.faces)]
            if node_parts:
                labelled.append((label, len(triangle_prims) > 1, node_parts))
        stack.extend((int(c), world) for c in reversed(node.get("children", [])))
    # Repeated node labels are told apart first (Door, Door_1), then primitives (Door_1/0, Door_1/1).
    parts = []
    for label, (_, several, node_parts) in zip(unique_names([entry[0] for entry in labelled]), labelled):
        for part in node_parts:
            part.name = f"{label}/{part.primitive}" if several else label
            parts.append(part)
    return parts


def _label(name) -> str | None:
    return name.strip() if isinstance(name, str) and name.strip() else None


def _local_matrix(node: dict, where: str) -> np.ndarray:
    if "matrix" in node:
        matrix = np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    else:
        matrix = trs_matrix(node.get("translation", [0.0, 0.0, 0.0]), node.get("rotation", [0.0, 0.0, 0.0, 1.0]), node.get("scale", [1.0, 1.0, 1.0]))
    if not np.isfinite(matrix).all():
        raise GeometryError(f"{where}: non-finite transform")
    return matrix


def _part(gltf: GltfFile, mesh: int, number: int, prim: dict, node: int, world: np.ndarray) -> GltfPart:
    where = f"{gltf.path}: mesh {mesh} primitive {number}"
    attributes = prim.get("attributes", {})
    if "POSITION" not in attributes:
        raise GeometryError(f"{where}: no POSITION attribute")
    positions = gltf.accessor(attributes["POSITION"])[:, :3]
    indices = gltf.accessor(prim["indices"]).reshape(-1) if "indices" in prim else np.arange(len(positions), dtype=np.int64)
    if len(indices) and (indices.min() < 0 or indices.max() >= len(positions)):
        raise GeometryError(f"{where}: an index is outside its {len(positions)} vertices")
    faces = _triangles(indices, prim.get("mode", _TRIANGLES))
    if np.linalg.det(world[:3, :3]) < 0:
        faces = faces[:, ::-1]  # front faces are clockwise under a mirroring transform
    vertices = positions @ world[:3, :3].T + world[:3, 3]
    material = prim.get("material")
    return GltfPart(name="", node=node, mesh=mesh, primitive=number, material=None if material is None else int(material),
                    vertices=vertices, faces=np.ascontiguousarray(faces, dtype=np.int64), attributes=dict(attributes))  # fmt: skip


def _triangles(indices: np.ndarray, mode: int) -> np.ndarray:
    """Triangles of a triangle list, strip or fan (the glTF specification's vertex order)."""
    indices = np.asarray(indices, dtype=np.int64)
    if mode == _TRIANGLES:
        return indices[: len(indices) - len(indices) % 3].reshape(-1, 3)
    count = max(len(indices) - 2, 0)
    i = np.arange(count)
    if mode == _STRIP:  # p_i = {v_i, v_{i+(1+i%2)}, v_{i+(2-i%2)}}
        return np.stack([indices[i], indices[i + 1 + i % 2], indices[i + 2 - i % 2]], axis=1)
    return np.stack([indices[i + 1], indices[i + 2], np.full(count, indices[0] if len(indices) else 0)], axis=1)  # fan
