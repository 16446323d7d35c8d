"""UV atlases for texture-space transfer: the mesh's own UVs where usable, else xatlas.

An atlas gives every face one UV triangle per lit side: open (two-sided) faces get a second
chart copy for their back, so a texel always holds the transfer of one side of one point.
Layouts:

- ``"shared"``: one atlas for the whole scene;
- ``"per_object"``: one atlas per object (texture sets, as for large scenes), same size each.

The mesh's own UVs (OBJ ``vt``) are used when every face has them (moved into ``[0, 1]`` by one
uniform scale and shift if they leave it), no face is two-sided, the layout is shared (or the scene has one object), and no two UV triangles
overlap.  Overlap is found by rasterising the UV triangles at the texture's size with additive
blending and counting texels covered twice (GL's fill rule gives a texel centre on a shared
edge to one triangle only, so charts meeting along edges count once).  Otherwise the scene is
re-atlased with xatlas, with one warning line saying why.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import moderngl
import numpy as np

from ...runtime.errors import GeometryError
from ...runtime.gl import bind_framebuffer

__all__ = ["UVAtlas", "build_atlas", "read_obj_uvs", "uv_overlap", "LAYOUTS", "ATLAS_PADDING"]

LAYOUTS = ("shared", "per_object")
# Texels between charts (xatlas padding): a bilinear fetch near a chart's edge never reads another chart.
ATLAS_PADDING = 2
# Texels covered twice tolerated before UVs count as overlapping (fraction of covered texels).
OVERLAP_TOLERANCE = 1e-3


@dataclass
class UVAtlas:
    """UV triangles of every lit side of every face, in one or more atlases (texture sets).

    Attributes
    ----------
    corner_uv : (F, 2, 3, 2) float32
        UV of each corner, front side ``[:, 0]`` and back side ``[:, 1]`` (the back equals the
        front for one-sided faces, which show no back), in ``[0, 1]``.
    atlas : (F,) int32
        Atlas (texture set) of each face.
    two_sided : (F,) bool
        Faces with a back-side chart.
    n_atlases : int
    source : str
        ``"mesh"`` (the file's own UVs) or ``"xatlas"``.
    note : str
        Why the UVs came from where they did (one line).
    seconds : float
        Time spent making the atlas (reading, checking, xatlas).
    """

    corner_uv: np.ndarray
    atlas: np.ndarray
    two_sided: np.ndarray
    n_atlases: int
    source: str
    note: str
    seconds: float = 0.0

    def sides(self):
        """The lit sides as ``(faces (N,), side (N,) 0 front / 1 back)``: every face, then the open ones' backs."""
        faces = np.arange(len(self.atlas))
        back = np.flatnonzero(self.two_sided)
        return np.concatenate([faces, back]), np.concatenate([np.zeros(len(faces), np.int64), np.ones(len(back), np.int64)])


# --------------------------------------------------------------------------- the file's own UVs


def read_obj_uvs(path, vertices, faces, to_source) -> np.ndarray | None:
    """The OBJ file's own UVs at the corners of the cleaned geometry's faces, or None.

    The geometry's faces are matched to the file's (fan-triangulated) triangles by centroid in
    source units, and each corner to the file corner at the same position (cleaning may turn a
    face's winding).  None when the file is not an OBJ, has no ``vt``, or some face or corner
    has no match.

    Returns
    -------
    (F, 3, 2) float32 or None
    """
    path = os.fspath(path)
    if not path.lower().endswith(".obj"):
        return None
    positions, uvs, tri_v, tri_t = [], [], [], []
    with open(path, encoding="utf-8", errors="replace") as handle:
        for line in handle:
            parts = line.split("#", 1)[0].split()
            if not parts:
                continue
            if parts[0] == "v" and len(parts) >= 4:
                positions.append([float(x) for x in parts[1:4]])
            elif parts[0] == "vt" and len(parts) >= 3:
                uvs.append([float(x) for x in parts[1:3]])
            elif parts[0] == "f" and len(parts) >= 4:
                corners = [c.split("/") for c in parts[1:]]
                if any(len(c) < 2 or not c[1] for c in corners):
                    return None  # a face without UVs
                v = [int(c[0]) for c in corners]
                t = [int(c[1]) for c in corners]
                v = [i - 1 if i > 0 else len(positions) + i for i in v]
                t = [i - 1 if i > 0 else len(uvs) + i for i in t]
                for k in range(1, len(v) - 1):  # the fan objfile.read_obj makes
                    tri_v.append((v[0], v[k], v[k + 1]))
                    tri_t.append((t[0], t[k], t[k + 1]))
    if not uvs or not tri_v:
        return None
    from scipy.spatial import cKDTree

    positions, uvs = np.asarray(positions), np.asarray(uvs)
    tri_v, tri_t = np.asarray(tri_v), np.asarray(tri_t)
    if tri_v.max() >= len(positions) or tri_t.max() >= len(uvs) or min(tri_v.min(), tri_t.min()) < 0:
        return None
    file_corners = positions[tri_v]  # (Fs, 3, 3) source units
    ours = np.asarray(vertices, np.float64)[faces] @ to_source[:3, :3].T + to_source[:3, 3]  # (F, 3, 3)
    distance, match = cKDTree(file_corners.mean(axis=1)).query(ours.mean(axis=1))
    scale = float(np.linalg.norm(np.ptp(positions, axis=0))) or 1.0
    if not np.all(distance <= 1e-5 * scale):
        return None
    # Each of our corners takes the UV of the matched triangle's corner nearest to it.
    gap = np.linalg.norm(ours[:, :, None, :] - file_corners[match][:, None, :, :], axis=-1)  # (F, 3, 3)
    nearest = gap.argmin(axis=2)
    if not np.all(gap.min(axis=2) <= 1e-5 * scale):
        return None
    return uvs[tri_t[match][np.arange(len(faces))[:, None], nearest]].astype(np.float32)


def uv_overlap(ctx: moderngl.Context, uv_triangles: np.ndarray, size: int) -> tuple[int, int]:
    """Texels covered by more than one UV triangle when rasterised at ``size x size``.

    Parameters
    ----------
    uv_triangles : (N, 3, 2) float
        UV triangles in ``[0, 1]``.

    Returns
    -------
    twice, covered : int
        Texels covered at least twice, and at least once.
    """
    program = ctx.program(
        vertex_shader="#version 330\nin vec2 in_uv;\nvoid main() { gl_Position = vec4(2.0 * in_uv - 1.0, 0.0, 1.0); }\n",
        fragment_shader="#version 330\nout vec4 o_count;\nvoid main() { o_count = vec4(1.0); }\n",
    )
    target = ctx.texture((size, size), 1, dtype="f4")
    fbo = ctx.framebuffer([target])
    vbo = ctx.buffer(np.ascontiguousarray(uv_triangles, dtype=np.float32).tobytes())
    vao = ctx.vertex_array(program, [(vbo, "2f", "in_uv")])
    previous = ctx.fbo  # bound again before our framebuffer is released
    try:
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE, moderngl.ONE
        vao.render(moderngl.TRIANGLES, vertices=3 * len(uv_triangles))
        ctx.disable(moderngl.BLEND)
        ctx.blend_func = moderngl.DEFAULT_BLENDING
        count = np.frombuffer(fbo.read(components=1, dtype="f4"), dtype=np.float32)
    finally:
        bind_framebuffer(ctx, previous)
        for obj in (vao, vbo, fbo, target, program):
            obj.release()
    return int(np.count_nonzero(count > 1.5)), int(np.count_nonzero(count > 0.5))


# --------------------------------------------------------------------------- xatlas


def _xatlas_uvs(vertices: np.ndarray, faces: np.ndarray, size: int) -> np.ndarray:
    """(F, 3, 2) float32 UVs of one xatlas atlas of ``size x size`` texels for these triangles."""
    try:
        import xatlas
    except ImportError:
        raise GeometryError("generating UVs needs xatlas: pip install 'prt-runtime[train]' (or pip install xatlas)") from None
    # Unshared corners: xatlas then cuts charts only where we allow it, and maps back 1:1.
    positions = np.ascontiguousarray(vertices[faces].reshape(-1, 3), dtype=np.float32)
    indices = np.arange(3 * len(faces), dtype=np.uint32).reshape(-1, 3)
    # Merge coincident corners again so charts are connected surfaces, not single triangles.
    _, first, inverse = np.unique(positions, axis=0, return_index=True, return_inverse=True)
    atlas = xatlas.Atlas()
    atlas.add_mesh(positions[first], inverse.reshape(-1).astype(np.uint32)[indices])
    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = ATLAS_PADDING
    pack.bilinear = True
    pack.bruteForce = False
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:
        raise GeometryError(f"xatlas made {atlas.atlas_count} atlases for a {size}x{size} texture (expected 1)")
    vmapping, out_indices, uvs = atlas.get_mesh(0)
    if len(out_indices) != len(faces):
        raise GeometryError(f"xatlas returned {len(out_indices)} faces for {len(faces)}")
    return uvs[out_indices].astype(np.float32)  # faces keep their order


def build_atlas(geometry_or_mesh, size: int, layout: str = "shared", *, source_path=None, ctx=None, log=print) -> UVAtlas:
    """The UV atlas of a mesh scene for ``size x size`` transfer textures.

    Parameters
    ----------
    geometry_or_mesh : prt.train.inputs.geometry.Geometry or dict
        The scene (a Geometry, or ``prt.runtime.gbuffer.load_mesh``'s dict plus ``to_source``).
    size : int
        Texture size in texels (charts are packed and padded for it).
    layout : ``"shared"`` or ``"per_object"``
    source_path : path, optional
        The mesh file, to use its own UVs (default: ``geometry.source``).
    ctx : moderngl.Context, optional
        For the overlap check (default: a new headless context).
    log : callable
        Gets the one warning line when the file's UVs overlap.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    t0 = time.perf_counter()
    vertices, faces, object_ids, two_sided, to_source, source = _mesh_arrays(geometry_or_mesh)
    if source_path is None:
        source_path = source
    n_objects = int(object_ids.max()) + 1 if len(object_ids) else 1
    own, note = None, "the mesh file has no UVs"
    if source_path is not None and os.path.isfile(source_path):
        own = read_obj_uvs(source_path, vertices, faces, to_source)
    if own is not None:
        if two_sided.any():
            own, note = None, "the mesh has open (two-sided) faces, whose backs need charts of their own"
        elif layout == "per_object" and n_objects > 1:
            own, note = None, "per-object atlases need one UV layout per object"
        else:
            own, moved = _fit_unit_square(own, ATLAS_PADDING / size)
            from ...runtime.gl import create_context

            check_ctx = ctx if ctx is not None else create_context()
            try:
                twice, covered = uv_overlap(check_ctx, own, size)
            finally:
                if ctx is None:
                    check_ctx.release()
            if twice > OVERLAP_TOLERANCE * covered:
                own, note = None, f"the mesh's UVs overlap ({twice} of {covered} texels covered twice at {size}x{size})"
                log(f"warning: {source_path}: UVs overlap ({twice} of {covered} texels covered twice); re-atlased with xatlas")
            else:
                note = f"the mesh's own UVs{moved} ({twice} of {covered} texels covered twice at {size}x{size})"
    corner_uv = np.zeros((len(faces), 2, 3, 2), dtype=np.float32)
    atlas = np.zeros(len(faces), dtype=np.int32)
    if own is not None:
        corner_uv[:, 0] = corner_uv[:, 1] = own
        return UVAtlas(corner_uv, atlas, two_sided.copy(), 1, "mesh", note, time.perf_counter() - t0)
    groups = [np.arange(len(faces))] if layout == "shared" else [np.flatnonzero(object_ids == o) for o in range(n_objects)]
    for index, members in enumerate(groups):
        if len(members) == 0:
            continue
        back = members[two_sided[members]]
        # Back sides are the same triangles again, wound the other way, as charts of their own.
        tri = np.concatenate([faces[members], faces[back][:, ::-1]])
        # Offset back copies apart so xatlas never merges them with the front.
        verts = np.concatenate([vertices, vertices + np.float32(1e3)])
        tri[len(members):] += len(vertices)
        uv = _xatlas_uvs(verts, tri, size)
        corner_uv[members, 0] = corner_uv[members, 1] = uv[: len(members)]
        corner_uv[back, 1] = uv[len(members):][:, ::-1]
        atlas[members] = index
    note = f"xatlas ({note})"
    return UVAtlas(corner_uv, atlas, two_sided.copy(), len(groups), "xatlas", note, time.perf_counter() - t0)


def _fit_unit_square(uv: np.ndarray, margin: float) -> tuple[np.ndarray, str]:
    """UVs moved into ``[margin, 1 - margin]`` by one uniform scale and shift when they leave [0, 1]."""
    low, high = uv.reshape(-1, 2).min(axis=0), uv.reshape(-1, 2).max(axis=0)
    if np.all(low >= 0.0) and np.all(high <= 1.0):
        return uv, ""
    scale = (1.0 - 2.0 * margin) / max(float(np.max(high - low)), 1e-12)
    return ((uv - low) * scale + margin).astype(np.float32), f" (moved into [0, 1]: they spanned {_pair(low)}..{_pair(high)})"


def _mesh_arrays(geometry_or_mesh):
    if isinstance(geometry_or_mesh, dict):
        m = geometry_or_mesh
        return (
            np.asarray(m["vertices"], np.float32), np.asarray(m["faces"], np.int64), np.asarray(m["object_ids"], np.int64),
            np.asarray(m["two_sided"], bool), np.asarray(m.get("to_source", np.eye(4))), m.get("source"),
        )  # fmt: skip
    g = geometry_or_mesh
    return (
        np.asarray(g.mesh.vertices, np.float32), np.asarray(g.mesh.faces, np.int64), np.asarray(g.object_ids, np.int64),
        np.asarray(g.two_sided, bool), np.asarray(g.to_source), g.source,
    )  # fmt: skip


def _pair(values) -> str:
    return "(" + ", ".join(f"{float(v):.3f}" for v in values) + ")"
