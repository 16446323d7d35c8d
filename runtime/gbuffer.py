"""The G-buffer pass: per pixel scene-space position, normal, segment id and depth.

The first pass of a frame.  Mesh scenes are rasterised; SDF scenes are sphere traced in one
full-screen pass writing the same targets, so the later passes never know which it was.  Mixed
scenes (geometry type ``"mixed"``) do both into one framebuffer: the mesh objects are drawn
first, then the SDF pass writes ``gl_FragDepth`` of its hits (the same view-projection) under
the depth test, so the nearer surface wins per pixel; an SDF hit takes the object id the scene's
GLSL recorded (``prt_scene_object``, the nearest SDF object at the hit) for its segment and
material.

Render targets (RGBA32F, ``width x height``, plus a depth texture):

- attachment 0 (:attr:`GBufferPass.position_texture`): ``position.xyz, covered`` with
  covered 1.0 on geometry and 0.0 on background;
- attachment 1 (:attr:`GBufferPass.normal_texture`): ``normal.xyz, segment`` with a unit
  normal facing the camera (``dot(n, eye - p) >= 0``) and the segment id as a float;
- attachment 2 (:attr:`GBufferPass.uv_texture`), only for scenes with a transfer texture:
  ``u, v, atlas, covered``, the UV of the visible side (open faces have one chart per side);
- the next attachment (:attr:`GBufferPass.material_texture`), only for mesh and mixed scenes shaded with
  per-object materials (:mod:`prt.runtime.materials`): ``u, v, object id, covered``;
- background is ``(0, 0, 0, 0)`` and ``(0, 0, 0, -1)`` (and ``(0, 0, 0, 0)``); depth is GL's window depth in
  ``[0, 1]`` (1 on background), written by both paths from the hit's clip-space depth.

Faces: two-sided faces (open surfaces) show the side facing the camera, their normal
flipped accordingly; back faces of closed surfaces are discarded in the fragment shader.  The
vertex buffer lists closed faces first and two-sided faces after them, so the closed ones are
drawn with GL's back-face culling on (the same fragments dropped before any runs) and the
two-sided ones in a second draw without it (:attr:`GBufferPass.cull`; off, one draw without
culling: the reference twin, tested to give the same targets).

Segments are computed in the shader (``shaders/segment_lookup.glsl``) by the rule of
:func:`prt.runtime.segmentation.segment_of`: descend the object's k-d tree, or, for an object
without a root, take the segment whose box is nearest to the point.  Nearest-box is applied
per fragment, exactly as ``segment_of`` does per point, so both agree everywhere.  SDF
scenes are object id 0; in mixed scenes an SDF hit has its object's id.  Mesh triangles that lie
wholly in one leaf (:func:`prt.runtime.segmentation.face_segments`, with a margin) are drawn by a
second program that takes their segment as a flat vertex attribute (``PRT_KNOWN_SEGMENT``): the
descent per fragment, most of the pass's fragment work on llvmpipe, runs only on the triangles
across a split (:attr:`GBufferPass.known_segments`; off: the reference twin, tested to give the
same targets).

Read-backs are (H, W, ...) arrays with row 0 at the top of the image.
"""

from __future__ import annotations

import re
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from ..shaders import Source, assemble
from .camera import Camera
from .checks import read_text
from .errors import GeometryError, InputError, SpecError
from .gl import bind_framebuffer, compile_program
from .manifest import Manifest
from .normals import corner_normals
from .segmentation import face_segments

__all__ = ["GBuffer", "GBufferPass", "segment_tables", "load_mesh", "PACKED_COLUMNS", "PACKED_COVERED", "PACKED_SEGMENT"]

# Columns of :meth:`GBufferPass.read_packed`'s rows: ``pos.xyz, covered, n.xyz, segment``.
# The networks' input (position + normal, float32 [N, 6]) is these columns, in this order.
PACKED_COLUMNS = (0, 1, 2, 4, 5, 6)
PACKED_COVERED = 3
PACKED_SEGMENT = 7

# Half size of the box every scene lies in ([-1, 1]^3), padded so surfaces on it are found.
SCENE_BOX = 1.001
# Uniform vectors the G-buffer shaders need besides the segment tables (matrices, camera).
_OTHER_UNIFORM_VECTORS = 24
# Largest object id the root table (one uniform slot per id up to it) is built for.
_MAX_OBJECT_ID = 1 << 16

# One vertex of the unindexed mesh buffer, matching gbuffer_mesh.vert's inputs.
_VERTEX = np.dtype([("position", "<f4", 3), ("normal", "<f4", 3), ("face_normal", "<f4", 3), ("info", "<i4", 2)])


@dataclass
class GBuffer:
    """A G-buffer read back to the CPU; row 0 is the top of the image.

    Attributes
    ----------
    position : ndarray of float32, shape (H, W, 3)
        Scene-space position; zeros on background.
    normal : ndarray of float32, shape (H, W, 3)
        Unit normal facing the camera; zeros on background.
    segment : ndarray of int32, shape (H, W)
        Segment id; -1 on background.
    covered : ndarray of bool, shape (H, W)
        True where geometry was hit.
    depth : ndarray of float32, shape (H, W), or None
        GL window depth in [0, 1] (1 on background), when asked for.
    """

    position: np.ndarray
    normal: np.ndarray
    segment: np.ndarray
    covered: np.ndarray
    depth: np.ndarray | None = None


# --------------------------------------------------------------------------- segment tables


def _float32_at_most(value: float) -> np.float32:
    """Largest float32 <= value, so ``p <= split`` decides alike in float32 and float64."""
    f = np.float32(value)
    return np.nextafter(f, np.float32(-np.inf)) if float(f) > value else f


def segment_tables(manifest: Manifest, object_ids: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The k-d tree of ``manifest`` as the uniform arrays of ``segment_lookup.glsl``.

    Parameters
    ----------
    manifest : Manifest
    object_ids : ndarray of int, optional
        Object ids the geometry uses; the root table then covers them too (as -1, the
        nearest-box rule, when the manifest gives them no root).

    Returns
    -------
    dict
        ``nodes`` (N, 4) float32: inner ``(axis, split, left, right)``, leaf
        ``(-1, 0, segment, segment)``; ``roots`` (M,) int32: root node per object id
        ``0 .. M-1``, -1 without one; ``segment_min``, ``segment_max`` (S, 3) float32 boxes.
    """
    seg = manifest.segmentation
    nodes = np.zeros((len(seg["nodes"]), 4), dtype=np.float32)
    for i, node in enumerate(seg["nodes"]):
        if "leaf" in node:
            segment = seg["leaf_segment"][node["leaf"]]
            nodes[i] = (-1.0, 0.0, segment, segment)
        else:
            nodes[i] = (node["axis"], _float32_at_most(node["split"]), node["left"], node["right"])
    largest = max(seg["roots"])
    if object_ids is not None and len(object_ids):
        largest = max(largest, int(np.max(object_ids)))
    if largest > _MAX_OBJECT_ID:
        message = f"object id {largest} exceeds {_MAX_OBJECT_ID}, the root table's limit"
        raise SpecError(f"{manifest.path}: segmentation: {message}")
    roots = np.full(largest + 1, -1, dtype=np.int32)
    for obj, root in seg["roots"].items():
        roots[obj] = root
    bounds = manifest.bounds.astype(np.float32)
    return {"nodes": nodes, "roots": roots, "segment_min": bounds[:, 0], "segment_max": bounds[:, 1]}


def _lookup_defines(tables: dict[str, np.ndarray]) -> dict[str, int]:
    """The #defines ``segment_lookup.glsl`` needs for these tables."""
    return {
        "PRT_KD_NODES": len(tables["nodes"]),
        "PRT_KD_OBJECTS": len(tables["roots"]),
        "PRT_SEGMENTS": len(tables["segment_min"]),
    }


def _check_uniform_budget(ctx: moderngl.Context, tables: dict[str, np.ndarray], source: str) -> None:
    """SpecError if the tables do not fit the fragment stage's uniform vectors."""
    # Every array element takes one vec4 slot in the default uniform block, whatever its type.
    needed = len(tables["nodes"]) + len(tables["roots"]) + 2 * len(tables["segment_min"])
    available = int(ctx.info.get("GL_MAX_FRAGMENT_UNIFORM_VECTORS", 256)) - _OTHER_UNIFORM_VECTORS
    if needed > available:
        raise SpecError(
            f"{source}: segmentation: the k-d tree needs {needed} fragment uniform vectors "
            f"({len(tables['nodes'])} nodes, {len(tables['roots'])} object ids, "
            f"{len(tables['segment_min'])} segments), this GPU offers {available}"
        )


def _set_tables(program: moderngl.Program, tables: dict[str, np.ndarray]) -> None:
    """Upload the segment tables; uniforms the compiler dropped are skipped."""
    uniforms = {
        "prt_kd_nodes": tables["nodes"],
        "prt_kd_roots": tables["roots"],
        "prt_segment_min": tables["segment_min"],
        "prt_segment_max": tables["segment_max"],
    }
    for name, values in uniforms.items():
        if name in program:
            program[name].write(np.ascontiguousarray(values).tobytes())


# --------------------------------------------------------------------------- mesh


def load_mesh(path: str | Path) -> dict[str, np.ndarray]:
    """Read and check a ``geometry.npz`` (as written by the build).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    dict
        ``vertices`` (V, 3) float32, ``faces`` (F, 3) int64, ``object_ids`` (F,) int32
        (zeros if the file has none), ``two_sided`` (F,) bool (False if absent); ``albedo_uv``
        (F, 3, 2) float32 per corner, only if the file has it.

    Raises
    ------
    GeometryError
        If the file cannot be read or its arrays are malformed.
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:  # a truncated or foreign file
        raise GeometryError(f"{path}: cannot read mesh ({' '.join(str(exc).split())})") from None
    for key in ("vertices", "faces"):
        if key not in arrays:
            raise GeometryError(f"{path}: no '{key}' array")
    vertices = arrays["vertices"]
    faces = arrays["faces"]
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.dtype.kind not in "fiu":
        what = f"{vertices.shape} {vertices.dtype}"
        raise GeometryError(f"{path}: vertices must be (V, 3) numbers, got {what}")
    if not np.all(np.isfinite(vertices)):
        raise GeometryError(f"{path}: vertices contain NaN or Inf")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu" or len(faces) == 0:
        what = f"{faces.shape} {faces.dtype}"
        raise GeometryError(f"{path}: faces must be (F, 3) integers with F >= 1, got {what}")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise GeometryError(f"{path}: faces index vertices outside 0..{len(vertices) - 1}")
    n_faces = len(faces)
    object_ids = arrays.get("object_ids", np.zeros(n_faces, dtype=np.int32))
    two_sided = arrays.get("two_sided", np.zeros(n_faces, dtype=bool))
    if object_ids.shape != (n_faces,) or object_ids.dtype.kind not in "iu" or object_ids.min() < 0:
        raise GeometryError(f"{path}: object_ids must be ({n_faces},) non-negative integers")
    if two_sided.shape != (n_faces,):
        raise GeometryError(f"{path}: two_sided must have shape ({n_faces},), got {two_sided.shape}")
    if two_sided.dtype != np.bool_:
        raise GeometryError(f"{path}: two_sided must be booleans, got {two_sided.dtype}")
    out = {
        "vertices": vertices.astype(np.float32),
        "faces": faces,
        "object_ids": object_ids.astype(np.int32),
        "two_sided": two_sided.astype(bool),
    }
    albedo_uv = arrays.get("albedo_uv")  # optional: the mesh's own UVs, for albedo textures
    if albedo_uv is not None:
        if albedo_uv.shape != (n_faces, 3, 2) or albedo_uv.dtype.kind != "f" or not np.all(np.isfinite(albedo_uv)):
            raise GeometryError(f"{path}: albedo_uv must be ({n_faces}, 3, 2) finite floats, got {albedo_uv.shape} {albedo_uv.dtype}")
        out["albedo_uv"] = albedo_uv.astype(np.float32)
    return out


def _mesh_vertices(mesh: dict[str, np.ndarray]) -> np.ndarray:
    """(3F,) unindexed vertex records: corner position, smooth normal, face normal, (object id, two-sided)."""
    # Degenerate faces keep a zero normal; the fragment shader substitutes one.
    normal, smooth = corner_normals(mesh["vertices"], mesh["faces"])
    records = np.empty((len(smooth), 3), dtype=_VERTEX)
    records["position"] = mesh["vertices"][mesh["faces"]]
    records["normal"] = smooth
    records["face_normal"] = normal[:, None, :]
    records["info"] = np.stack([mesh["object_ids"], mesh["two_sided"].astype(np.int32)], axis=1)[:, None, :]
    return records.reshape(-1)


def _uv_vertices(manifest: Manifest, n_faces: int) -> np.ndarray:
    """(3F, 5) float32 per corner: front UV, back UV, atlas (the scene's transfer texture)."""
    from .transfer_texture import load_transfer_texture

    arrays = load_transfer_texture(manifest.transfer_texture, n_faces, transfer=False)
    records = np.empty((n_faces, 3, 5), dtype=np.float32)
    records[..., 0:2] = arrays["corner_uv"][:, 0]
    records[..., 2:4] = arrays["corner_uv"][:, 1]
    records[..., 4] = arrays["atlas"][:, None]
    return records.reshape(-1, 5)


# A layer function of the transfer networks' GLSL generator (``void <net>_layer<k>(...)`` or
# ``void <net>_out(...)``): neural-SDF scenes built before the loop-free writer
# (``prt.train.sdf.neural_glsl``) have their network written so, with loops.
_NETWORK_LAYER = re.compile(r"^void\s+\w+_(?:layer\d+|out)\s*\([^)]*\)\s*\{", re.M)


def _refuse_looped_network(glsl: str, name) -> None:
    """GeometryError when an SDF scene's GLSL evaluates a network with loops.

    llvmpipe ends every loop of a shader invocation after 65535 iterations in total, and the
    sphere tracer calls the network inside its own loop: such a network returns a constant
    part-way through a march, so the scene renders wrongly (and slowly).  Analytic SDFs'
    loops (polylines) are not in layer functions and pass.
    """
    for match in _NETWORK_LAYER.finditer(glsl):
        end = glsl.find("\n}", match.end())
        if re.search(r"\bfor\s*\(", glsl[match.end() : len(glsl) if end < 0 else end]):
            raise GeometryError(
                f"{name}: neural-SDF GLSL from before the loop-free network writer (its network loops, which "
                f"llvmpipe cuts short mid-march): rebuild the scene with prt-train MESH -o OUT --neural-sdf"
            )


def _strip_version(glsl: str, name: str = "<sdf>") -> Source:
    """``glsl`` (the file ``name``) without a leading ``#version`` line (an included file must
    not repeat it), remembering the file's own line numbers."""
    stripped = glsl.lstrip()
    if not stripped.startswith("#version"):
        return Source.from_file(glsl, name)
    return Source.from_file(stripped.partition("\n")[2], name, glsl[: len(glsl) - len(stripped)].count("\n") + 2)


# --------------------------------------------------------------------------- the pass


class GBufferPass:
    """Renders the G-buffer of one scene at a fixed resolution.

    GPU resources (targets, geometry buffer or SDF program, segment tables) are built once
    here; :meth:`render` only sets the camera uniforms and draws.

    Parameters
    ----------
    ctx : moderngl.Context
        OpenGL 3.3+ context.
    manifest : Manifest
        The scene; its geometry is a mesh (``geometry.npz``) or an SDF (GLSL defining
        ``float scene_sdf(vec3 p)``).
    width, height : int
        Target size in pixels.
    max_steps : int
        Sphere-tracing step budget per pixel (SDF scenes).
    hit_eps : float
        Sphere-tracing hit threshold per unit of ray length: a ray hits at parameter ``t``
        when the distance drops below ``hit_eps * t`` (SDF scenes).

    Attributes
    ----------
    position_texture, normal_texture : moderngl.Texture
        The RGBA32F targets (see the module docstring), for later passes to sample.
    depth_texture : moderngl.Texture
        The depth target.
    uv_texture : moderngl.Texture or None
        The UV target of a scene with a transfer texture (see the module docstring), else None.
    kind : str
        ``"mesh"``, ``"sdf"`` or ``"mixed"``.
    cull : bool
        Mesh scenes: draw the closed faces with GL's back-face culling, apart from the two-sided
        ones (default); False draws all faces at once without culling (the reference twin).

    Raises
    ------
    GeometryError
        If the mesh file is malformed.
    SpecError
        If the segment tables exceed the GPU's uniform limits.
    moderngl.Error
        If a shader (e.g. the scene's SDF GLSL) does not compile.

    Notes
    -----
    The textures keep GL's row order (row 0 at the bottom); read-backs are flipped.

    SDF sphere tracing (``shaders/gbuffer_sdf.frag``): a ray starts where it enters the
    box ``[-SCENE_BOX, SCENE_BOX]^3`` or at the near plane, whichever is later, and misses
    once it leaves the box or passes the far plane.  A ray that runs out of steps counts
    as a hit if the last distance is within the pixel's footprint (grazing rays).  The
    normal is the tetrahedral difference gradient of ``scene_sdf``.  A ray starting inside
    the solid passes through it, as the mesh pass discards back faces of closed surfaces.
    """

    def __init__(
        self,
        ctx: moderngl.Context,
        manifest: Manifest,
        width: int,
        height: int,
        *,
        max_steps: int = 256,
        hit_eps: float = 1e-4,
        object_materials: bool | None = None,
    ) -> None:
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise ValueError(f"GBufferPass: size must be positive, got {width}x{height}")
        self.ctx = ctx
        self.width, self.height = width, height
        self.kind = manifest.geometry.type
        self._released = False
        # Mesh scenes: closed faces culled by GL in their own draw (False: one draw, no culling,
        # the reference twin); _closed_vertices is how many of the buffer's vertices are closed.
        self.cull = False
        self._closed_vertices = 0
        # Mesh scenes: triangles wholly in one k-d leaf drawn with their segment as an attribute
        # (False: every fragment descends the tree, the reference twin); _ranges: the draws.
        self.known_segments = False
        self._ranges: list[tuple[int, int, bool, bool]] = []  # (first vertex, vertices, culled, segment known)
        self._known_program = self._known_vao = self._segment_vbo = None
        self._vbo = None
        self._vao = self._program = None
        self._fbo = self._normal_fbo = None
        self.position_texture = self.normal_texture = self.depth_texture = None
        # Texture-space transfer needs the UV of each pixel; other scenes draw exactly as before.
        self._with_uv = self.kind == "mesh" and getattr(manifest, "transfer_texture", None) is not None
        self.uv_texture = self._uv_vbo = None
        # Per-object materials need each pixel's object id (None: when the manifest has materials).
        if object_materials is None:
            object_materials = bool((manifest.raw or {}).get("materials"))
        self._with_material = self.kind in ("mesh", "mixed") and bool(object_materials)
        self._sdf_program = self._sdf_vao = None  # mixed scenes: the SDF pass after the mesh draw
        self.material_texture = self._albedo_uv_vbo = None
        # Deformable scenes: the rest position in target 0, the posed one in world_texture (set_pose).
        self._deformable = self.kind == "mesh" and getattr(manifest, "deformation", None) is not None
        self.world_texture = self._rest_vbo = None
        self._pose_faces = self._mesh = None
        try:
            self._build_targets()
            if self.kind == "mesh":
                self._build_mesh(manifest)
            elif self.kind == "mixed":
                self._build_mixed(manifest, int(max_steps), float(hit_eps))
            else:
                self._build_sdf(manifest, int(max_steps), float(hit_eps))
        except BaseException:
            self.release()  # whatever was created before the failure
            raise

        # Staging for read-backs: both targets as GL gives them (bottom row first).
        self._staging = np.empty((2, height, width, 4), dtype=np.float32)
        self._packed = np.empty((height * width, 8), dtype=np.float32)

    def _build_targets(self) -> None:
        size = (self.width, self.height)
        self.position_texture = self._target_texture(size)
        self.normal_texture = self._target_texture(size)
        self.depth_texture = self.ctx.depth_texture(size)
        self.uv_texture = self._target_texture(size) if self._with_uv else None
        self.material_texture = self._target_texture(size) if self._with_material else None
        colour = [self.position_texture, self.normal_texture] + ([self.uv_texture] if self._with_uv else [])
        colour += [self.material_texture] if self._with_material else []
        self.world_texture = self._target_texture(size) if self._deformable else None
        colour += [self.world_texture] if self._deformable else []
        self._fbo = self.ctx.framebuffer(colour, self.depth_texture)

    def _target_texture(self, size: tuple[int, int]) -> moderngl.Texture:
        texture = self.ctx.texture(size, 4, dtype="f4")
        # Positions and ids must never be blended between texels.
        texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return texture

    def _build_mesh(self, manifest: Manifest, object_ids: np.ndarray | None = None) -> None:
        mesh = load_mesh(manifest.geometry.path)
        tables = segment_tables(manifest, mesh["object_ids"] if object_ids is None else object_ids)
        _check_uniform_budget(self.ctx, tables, str(manifest.path))
        uv_define = {"PRT_GBUFFER_UV": 1} if self._with_uv else {}
        material_define = {"PRT_GBUFFER_MATERIAL": self.material_attachment} if self._with_material else {}
        rest_define = {"PRT_GBUFFER_REST": 1, "PRT_GBUFFER_WORLD": self.world_attachment} if self._deformable else {}
        defines = {**_lookup_defines(tables), **uv_define, **material_define, **rest_define}
        fragment = assemble("segment_lookup.glsl", "gbuffer_mesh.frag", defines=defines)
        vertex = assemble("gbuffer_mesh.vert", defines={**uv_define, **material_define, **rest_define})
        self._program = compile_program(self.ctx, fragment, "G-buffer pass", vertex=vertex)
        _set_tables(self._program, tables)
        n_faces = len(mesh["faces"])
        # The segment of each triangle wholly in one leaf (the rest pose's: what the rule takes).
        known = face_segments(mesh["vertices"][mesh["faces"]], mesh["object_ids"], tables["nodes"], tables["roots"])
        # Closed faces first (in file order), then the two-sided ones: one culled draw, one not;
        # in each, the faces of known segment first.
        faces = np.lexsort((known < 0, mesh["two_sided"]))
        self._vbo = self.ctx.buffer(_mesh_vertices(mesh).reshape(n_faces, 3)[faces].tobytes())
        buffers = [(self._vbo, "3f 3f 3f 2i", "in_position", "in_normal", "in_face_normal", "in_info")]
        if self._with_uv:
            uv = _uv_vertices(manifest, n_faces).reshape(n_faces, 3, 5)[faces]
            self._uv_vbo = self.ctx.buffer(np.ascontiguousarray(uv).tobytes())
            buffers.append((self._uv_vbo, "4f 1f", "in_uv", "in_atlas"))
        if self._with_material:
            albedo_uv = mesh.get("albedo_uv")
            corners = np.zeros((n_faces, 3, 2), np.float32) if albedo_uv is None else albedo_uv[faces]
            self._albedo_uv_vbo = self.ctx.buffer(np.ascontiguousarray(corners, dtype=np.float32).tobytes())
            buffers.append((self._albedo_uv_vbo, "2f", "in_albedo_uv"))
        if self._deformable:  # the rest pose stays; set_pose rewrites the posed records
            self._mesh, self._pose_faces = mesh, faces
            rest = np.ascontiguousarray(mesh["vertices"][mesh["faces"]][faces], dtype=np.float32)
            self._rest_vbo = self.ctx.buffer(rest.tobytes())
            buffers.append((self._rest_vbo, "3f", "in_rest"))
        self._vao = self.ctx.vertex_array(self._program, buffers)
        self._vertices = 3 * n_faces
        # GL's culling drops exactly what the shader would discard on closed faces (gl_FrontFacing
        # and culling read the same winding), before any fragment runs.
        self._closed_vertices = 3 * int(np.count_nonzero(~mesh["two_sided"]))
        self.cull = True
        groups = [side & has for side in (~mesh["two_sided"], mesh["two_sided"]) for has in (known >= 0, known < 0)]  # the order of faces
        edges = np.cumsum([0] + [3 * int(np.count_nonzero(g)) for g in groups])
        self._ranges = [(int(edges[k]), int(edges[k + 1] - edges[k]), k < 2, k % 2 == 0) for k in range(4)]
        if (known >= 0).any():
            known_define = {"PRT_KNOWN_SEGMENT": 1}
            self._known_program = compile_program(
                self.ctx, assemble("segment_lookup.glsl", "gbuffer_mesh.frag", defines={**defines, **known_define}), "G-buffer pass",
                vertex=assemble("gbuffer_mesh.vert", defines={**uv_define, **material_define, **rest_define, **known_define}))  # fmt: skip
            self._segment_vbo = self.ctx.buffer(np.repeat(known[faces], 3).astype(np.int32).tobytes())
            self._known_vao = self.ctx.vertex_array(self._known_program, buffers + [(self._segment_vbo, "1i", "in_segment")])
            self.known_segments = True

    def _build_mixed(self, manifest: Manifest, max_steps: int, hit_eps: float) -> None:
        """Mesh objects (when there are any) as a mesh scene, then the SDF objects' pass."""
        ids = np.arange(len(manifest.geometry.objects or [0]), dtype=np.int32)
        if manifest.geometry.triangles:
            self._build_mesh(manifest, ids)
        self._sdf_program = self._sdf_program_for(manifest, Path(manifest.geometry.glsl), max_steps, hit_eps, ids)
        self._sdf_vao = self.ctx.vertex_array(self._sdf_program, [])

    def _build_sdf(self, manifest: Manifest, max_steps: int, hit_eps: float) -> None:
        self._program = self._sdf_program_for(manifest, Path(manifest.geometry.path), max_steps, hit_eps, np.zeros(1, dtype=np.int32))
        self._vbo = None
        self._vao = self.ctx.vertex_array(self._program, [])
        self._vertices = 3

    def _sdf_program_for(self, manifest: Manifest, path: Path, max_steps: int, hit_eps: float, object_ids: np.ndarray):
        """The full-screen sphere-tracing program of the SDF GLSL file ``path``."""
        if max_steps < 1 or not hit_eps > 0.0:
            message = f"need max_steps >= 1 and hit_eps > 0, got {max_steps} and {hit_eps}"
            raise ValueError(f"GBufferPass: {message}")
        try:
            scene_glsl = read_text(path, "SDF GLSL")
        except InputError as exc:
            raise GeometryError(str(exc)) from None
        _refuse_looped_network(scene_glsl, path)
        tables = segment_tables(manifest, object_ids)
        _check_uniform_budget(self.ctx, tables, str(manifest.path))
        defines = {"PRT_MAX_STEPS": max_steps, "PRT_HIT_EPS": hit_eps, "PRT_SCENE_BOX": SCENE_BOX, **_lookup_defines(tables)}
        defines |= {"PRT_SCENE_OBJECTS": 1} if self.kind == "mixed" else {}
        defines |= {"PRT_GBUFFER_MATERIAL": self.material_attachment} if self._with_material else {}
        fragment = assemble(
            "segment_lookup.glsl", "gbuffer_sdf.frag", defines=defines, fills={"scene_sdf": _strip_version(scene_glsl, str(path))}
        )
        program = compile_program(self.ctx, fragment, "G-buffer pass", vertex=assemble("fullscreen.vert"))
        _set_tables(program, tables)
        return program

    def _set(self, name: str, value) -> None:
        """Set a uniform in every program of the pass, where the compiler kept it."""
        for program in (self._program, self._known_program, self._sdf_program):
            if program is not None and name in program:
                program[name].write(np.ascontiguousarray(value, dtype=np.float32).tobytes())

    # ----------------------------------------------------------------- drawing

    def render(self, camera: Camera) -> None:
        """Draw the G-buffer seen by ``camera`` into the targets.

        The framebuffer bound before the call is bound again; depth testing, blending and
        face culling are left disabled (the GL defaults).
        """
        self._check_alive()
        aspect = self.width / self.height
        # GLSL matrices are column-major: upload the transpose of the row-major numpy matrix.
        self._set("u_view_projection", camera.view_projection(aspect).T)
        self._set("u_eye", camera.eye)
        if self.kind != "mesh":
            half_y = np.tan(np.radians(camera.fov_y) / 2.0)
            self._set("u_forward", camera.forward)
            self._set("u_right", camera.right * half_y * aspect)
            self._set("u_up", camera.true_up * half_y)
            self._set("u_size", (self.width, self.height))
            self._set("u_near", camera.near)
            self._set("u_far", camera.far)
            self._set("u_pixel_angle", 2.0 * half_y / self.height)
        previous = self.ctx.fbo
        self.ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        try:
            self._fbo.use()
            self._fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            # Clearing the main target sets both attachments alike; the normal's w needs -1.  A
            # colour mask on the same framebuffer (not a second one) keeps llvmpipe to one pass.
            everything = self._fbo.color_mask
            self._fbo.color_mask = tuple((k == 1,) * 4 for k in range(len(everything)))
            self._fbo.clear(0.0, 0.0, 0.0, -1.0, depth=1.0)
            self._fbo.color_mask = everything
            self._fbo.use()
            self._draw()
        finally:
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
            bind_framebuffer(self.ctx, previous)

    def _draw(self) -> None:
        """The geometry: closed faces with GL's back-face culling, then two-sided faces without it
        (:attr:`cull`), each part's triangles of known segment by their own program
        (:attr:`known_segments`); or everything in one draw without culling (the shader's discard
        and descent alone), in the same order."""
        if self._vao is None:  # a mixed scene without mesh objects
            self._vertices = 0
        elif not self.cull or not self._ranges:  # one draw (SDF scenes: the full-screen pass)
            self._vao.render(moderngl.TRIANGLES, vertices=self._vertices)
        else:
            for first, count, culled, known in self._ranges:
                if not count:
                    continue
                vao = self._known_vao if known and self.known_segments else self._vao
                if culled:
                    # Back faces of closed surfaces are discarded in the shader; culled by GL as well
                    # here (the same fragments, fewer of them run).
                    self.ctx.front_face, self.ctx.cull_face = "ccw", "back"
                    self.ctx.enable(moderngl.CULL_FACE)
                vao.render(moderngl.TRIANGLES, vertices=count, first=first)
                self.ctx.disable(moderngl.CULL_FACE)
        if self._sdf_vao is not None:  # mixed: SDF hits behind the meshes fail the depth test
            self._sdf_vao.render(moderngl.TRIANGLES, vertices=3)

    # ----------------------------------------------------------------- read-back

    def read_targets(self) -> np.ndarray:
        """Both targets read back: (2, H, W, 4) float32, a view with rows flipped to top-first (no
        copy; ``[:, ::-1]`` of it is GL's contiguous bottom-first order); the next call overwrites it."""
        return self._read_targets()

    def _read_targets(self) -> np.ndarray:
        """(2, H, W, 4) view of both targets, rows flipped to top-first (no copy)."""
        self._check_alive()
        for attachment in (0, 1):
            self._fbo.read_into(self._staging[attachment], components=4, attachment=attachment, dtype="f4")
        return self._staging[:, ::-1]

    def set_pose(self, vertices: np.ndarray) -> None:
        """Deformable scenes: draw the mesh with ``vertices`` (V, 3) from now on (positions, smooth and
        face normals recomputed by the rule the training samples used); the rest pose stays in target 0."""
        self._check_alive()
        if not self._deformable:
            raise ValueError("set_pose: the scene is not deformable")
        mesh = {**self._mesh, "vertices": np.asarray(vertices, np.float32)}
        n_faces = len(mesh["faces"])
        self._vbo.write(_mesh_vertices(mesh).reshape(n_faces, 3)[self._pose_faces].tobytes())

    @property
    def world_attachment(self) -> int | None:
        """Index of the posed-position target (deformable scenes), None without one."""
        return 2 + int(self._with_uv) + int(self._with_material) if self._deformable else None

    def read_world(self) -> np.ndarray | None:
        """Deformable scenes: the posed position of every pixel, (H * W, 3) float32, rows from the top."""
        self._check_alive()
        if not self._deformable:
            return None
        raw = self._fbo.read(components=4, attachment=self.world_attachment, dtype="f4")
        return np.frombuffer(raw, dtype=np.float32).reshape(self.height, self.width, 4)[::-1, :, :3].reshape(-1, 3)

    @property
    def material_attachment(self) -> int | None:
        """Index of the material target in the framebuffer, None without one."""
        return (3 if self._with_uv else 2) if self._with_material else None

    def read_material(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Per pixel, rows from the top as :meth:`read_packed`: object id (H * W,) int32 (-1 on
        background) and albedo-texture UV (H * W, 2) float32; None without a material target."""
        self._check_alive()
        if not self._with_material:
            return None
        raw = self._fbo.read(components=4, attachment=self.material_attachment, dtype="f4")
        rows = np.frombuffer(raw, dtype=np.float32).reshape(self.height, self.width, 4)[::-1].reshape(-1, 4)
        return np.where(rows[:, 3] > 0.5, rows[:, 2], -1.0).astype(np.int32), rows[:, :2].copy()

    def read_packed(self, out: np.ndarray | None = None) -> np.ndarray:
        """Both targets interleaved per pixel in one contiguous array.

        Parameters
        ----------
        out : ndarray of float32, shape (H * W, 8), optional
            C-contiguous array to fill; by default an internal buffer that the next call
            overwrites.

        Returns
        -------
        ndarray of float32, shape (H * W, 8)
            Rows are pixels in row-major order from the TOP-left (row ``i // W`` from the
            top, column ``i % W``); columns ``pos.x, pos.y, pos.z, covered, n.x, n.y, n.z,
            segment``.
        """
        shape = (self.height * self.width, 8)
        if out is None:
            out = self._packed
        elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous {shape} float32 array")
        targets = self._read_targets()
        # One strided copy interleaves the targets and flips the rows together.
        np.copyto(out.reshape(self.height, self.width, 2, 4), targets.transpose(1, 2, 0, 3))
        return out

    def read(self, depth: bool = False) -> GBuffer:
        """Read the G-buffer back into new numpy arrays (row 0 at the top).

        Parameters
        ----------
        depth : bool
            Also read the depth target.

        Returns
        -------
        GBuffer
        """
        position, normal = self._read_targets()
        depth_image = None
        if depth:
            raw = self._fbo.read(attachment=-1, components=1, dtype="f4")
            depth_image = np.frombuffer(raw, dtype=np.float32).reshape(self.height, self.width)[::-1].copy()
        return GBuffer(
            position=np.ascontiguousarray(position[..., :3]),
            normal=np.ascontiguousarray(normal[..., :3]),
            segment=normal[..., 3].astype(np.int32),
            covered=position[..., 3] > 0.5,
            depth=depth_image,
        )

    # ----------------------------------------------------------------- lifetime

    def _check_alive(self) -> None:
        if self._released:
            raise RuntimeError("GBufferPass: used after release()")

    def release(self) -> None:
        """Free the GPU resources; the pass cannot be used afterwards.  Safe to call twice."""
        if self._released:
            return
        self._released = True
        resources = [
            self._vao, self._program, self._known_vao, self._known_program, self._segment_vbo, self._sdf_vao, self._sdf_program, self._vbo, self._uv_vbo, self._albedo_uv_vbo,
            self._normal_fbo, self._fbo, self.position_texture, self.normal_texture, self.depth_texture, self.uv_texture,
            self.material_texture, self.world_texture, self._rest_vbo,
        ]  # fmt: skip
        for resource in resources:
            if resource is not None:
                resource.release()

    def __enter__(self) -> "GBufferPass":
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()
