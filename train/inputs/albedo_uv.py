"""The mesh's own texture coordinates, carried onto the built geometry's faces (for albedo textures).

:func:`prt.train.inputs.geometry.load_geometry` cleans, re-orients, drops and renumbers triangles and
keeps no map back to the file.  Rather than thread UVs through every cleaning step, the UVs
are found again afterwards: each built triangle is matched to the file's triangle with the same
three corner positions (in source units, through ``Geometry.to_source``, rounded to a grid of
1e-7 of the mesh's size), and each corner takes the UV of the file corner at its position.  A
triangle without a match (none is expected) gets UV 0.

UV convention: OBJ's (``v = 0`` at the bottom of the image); glTF UVs are flipped to it
(:meth:`prt.train.inputs.gltf_scene.GltfScene.texcoords`).
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["file_corner_uvs", "match_corner_uvs"]

_GRID = 1e-7  # position rounding, relative to the largest extent


def file_corner_uvs(path: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Triangles of a mesh file with their corner UVs, in source units.

    Returns
    -------
    (positions (T, 3, 3) float64, uvs (T, 3, 2) float64), or None when the file has no UVs
    (a format without them, or no corner with a ``vt`` index).
    """
    extension = os.path.splitext(path)[1][1:].lower()
    if extension == "obj":
        return _obj_corner_uvs(path)
    if extension in ("gltf", "glb"):
        return _gltf_corner_uvs(path, extension)
    return None


def _obj_corner_uvs(path: str):
    with open(path, "rb") as handle:
        text = handle.read().decode("utf-8-sig", errors="replace")
    vertices: list[list[float]] = []
    texcoords: list[list[float]] = []
    tri_v: list[tuple[int, int, int]] = []
    tri_t: list[tuple[int, int, int]] = []
    for line in text.replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        parts = line.partition("#")[0].split()
        if not parts:
            continue
        if parts[0] == "v" and len(parts) >= 4:
            vertices.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt" and len(parts) >= 2:
            values = [float(x) for x in parts[1:3]]
            texcoords.append(values + [0.0] * (2 - len(values)))
        elif parts[0] == "f" and len(parts) >= 4:
            vs, ts = [], []
            for corner in parts[1:]:
                fields = corner.split("/")
                v = int(fields[0])
                vs.append(v - 1 if v > 0 else len(vertices) + v)
                t = int(fields[1]) if len(fields) > 1 and fields[1] else 0
                ts.append(t - 1 if t > 0 else (len(texcoords) + t if t < 0 else -1))
            for k in range(1, len(vs) - 1):  # the reader's fan around the first corner
                tri_v.append((vs[0], vs[k], vs[k + 1]))
                tri_t.append((ts[0], ts[k], ts[k + 1]))
    if not texcoords or not tri_t:
        return None
    v = np.asarray(vertices, dtype=np.float64)
    t = np.vstack([np.asarray(texcoords, dtype=np.float64), np.zeros((1, 2))])  # index -1: no UV
    tri_v_arr, tri_t_arr = np.asarray(tri_v, dtype=np.int64), np.asarray(tri_t, dtype=np.int64)
    if (tri_t_arr < 0).all():
        return None
    tri_t_arr = np.where((tri_t_arr >= 0) & (tri_t_arr < len(texcoords)), tri_t_arr, len(texcoords))
    return v[tri_v_arr], t[tri_t_arr]


def _gltf_corner_uvs(path: str, extension: str):
    """Each part's triangles with the UV set its albedo texture reads (zeros where it has none)."""
    from .gltf_scene import albedo_texture_info, read_gltf_scene

    scene = read_gltf_scene(path)
    positions, uvs, any_uv = [], [], False
    for part in scene.parts:
        info = albedo_texture_info(scene.document, part.material)
        uv = scene.texture_coords(part, info)
        any_uv |= uv is not None
        uv = np.zeros((len(part.vertices), 2)) if uv is None else uv
        positions.append(part.vertices[part.faces])
        uvs.append(uv[part.faces])
    if not any_uv:
        return None
    return np.concatenate(positions), np.concatenate(uvs)


def match_corner_uvs(geometry, positions: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, int]:
    """UV of every corner of ``geometry``'s triangles, from the file's triangles (see the module docstring).

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
    positions : (T, 3, 3) float64
        The file's triangles, source units.
    uvs : (T, 3, 2) float64

    Returns
    -------
    albedo_uv : (F, 3, 2) float32
    unmatched : int
        Built triangles that found no file triangle (their UVs are 0).
    """
    mesh = geometry.mesh
    to_source = np.asarray(geometry.to_source, dtype=np.float64)
    built = np.asarray(mesh.vertices, dtype=np.float64) @ to_source[:3, :3].T + to_source[:3, 3]
    corners = built[np.asarray(mesh.faces, dtype=np.int64)]  # (F, 3, 3)
    extent = float(np.ptp(positions.reshape(-1, 3), axis=0).max()) or 1.0
    step = extent * _GRID

    def keys(tri: np.ndarray) -> np.ndarray:
        q = np.round(tri / step).astype(np.int64)  # (N, 3, 3)
        order = np.lexsort((q[:, :, 2], q[:, :, 1], q[:, :, 0]), axis=-1)
        return np.take_along_axis(q, order[:, :, None], axis=1).reshape(len(q), 9), q

    file_keys, file_q = keys(positions)
    built_keys, built_q = keys(corners)
    lookup: dict[bytes, int] = {}
    for index, row in enumerate(file_keys):
        lookup.setdefault(row.tobytes(), index)
    out = np.zeros((len(corners), 3, 2), dtype=np.float32)
    unmatched = 0
    for f, row in enumerate(built_keys):
        index = lookup.get(row.tobytes())
        if index is None:
            unmatched += 1
            continue
        for c in range(3):
            same = np.flatnonzero((file_q[index] == built_q[f, c]).all(axis=1))
            out[f, c] = uvs[index, same[0] if len(same) else c]
    return out, unmatched
