"""A tolerant Wavefront OBJ reader: vertex positions, triangulated faces and object identity.

Only what the transfer precomputation needs is read; texture coordinates, normals, materials,
smoothing groups, lines and free-form geometry are skipped, and ``mtllib`` files are never opened
(a missing ``.mtl`` is therefore harmless).

Object identity
---------------
Each face belongs to the object named by the most recent ``o`` or ``g`` statement before it (a
``g`` with several names is one object named by all of them, space separated; a ``g`` with no name
is the default group).  Statements that repeat a name continue the same object.  Only when the file
has no ``o`` and no ``g`` statement at all do ``usemtl`` statements define the objects instead.
Faces before the first such statement belong to the object named ``"default"``.  Objects that end
up with no faces are left out, so object ids run over non-empty objects in order of first use.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ...runtime.errors import GeometryError

__all__ = ["DEFAULT_OBJECT", "read_obj"]

DEFAULT_OBJECT = "default"

# Everything from the first slash of a face corner on ("7/3/2" -> "7", "7//2" -> "7").
_CORNER_TAIL = re.compile(r"/\S*")


def read_obj(path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Read the triangles and object groups of a Wavefront OBJ file.

    Face corners may be written ``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn``.  Negative indices are
    relative: ``-1`` is the last vertex defined before the ``f`` line.  Polygons are split into a
    fan of triangles around their first corner; faces with fewer than three corners are skipped.
    Comments (``#``), blank lines, ``\\`` line continuations and CRLF line ends are accepted.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.obj`` file.

    Returns
    -------
    vertices : (V, 3) float64
        Every ``v`` position in file order (a fourth ``w`` or trailing colour values are ignored).
    faces : (F, 3) int64
        Zero-based vertex indices of each triangle, in file order.
    object_ids : (F,) int64
        Object of each triangle, ``0 .. len(object_names) - 1`` (see the module docstring).
    object_names : list of str
        Name of each object, in order of first use.

    Raises
    ------
    GeometryError
        The file cannot be read, is binary, or has a malformed ``v`` or ``f`` line or a vertex
        index out of range; the one-line message names the file and the line number.
    """
    path = os.fspath(path)
    lines = _read_lines(path)

    coordinates: list[str] = []  # x, y, z of every vertex, flattened
    vertex_lines: list[int] = []
    corners: list[str] = []  # every face corner token, flattened
    face_sizes: list[int] = []
    face_lines: list[int] = []
    face_vertex_counts: list[int] = []  # vertices defined when the face was read
    face_groups: list[int] = []
    face_materials: list[int] = []
    groups = {DEFAULT_OBJECT: 0}
    materials = {DEFAULT_OBJECT: 0}
    group = material = 0
    has_groups = False

    for number, line in lines:
        if "#" in line:
            line = line.partition("#")[0]
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise GeometryError(f"{path}, line {number}: vertex needs 3 coordinates: {line.strip()!r}")
            coordinates.extend(parts[1:4])
            vertex_lines.append(number)
        elif key == "f":
            corners.extend(parts[1:])
            face_sizes.append(len(parts) - 1)
            face_lines.append(number)
            face_vertex_counts.append(len(vertex_lines))
            face_groups.append(group)
            face_materials.append(material)
        elif key in ("o", "g"):
            group = groups.setdefault(" ".join(parts[1:]) or DEFAULT_OBJECT, len(groups))
            has_groups = True
        elif key == "usemtl":
            material = materials.setdefault(" ".join(parts[1:]) or DEFAULT_OBJECT, len(materials))

    vertices = _parse_coordinates(path, coordinates, vertex_lines)
    sizes = np.asarray(face_sizes, dtype=np.int64)
    indices = _parse_corners(path, corners, sizes, face_lines)
    indices = _resolve_indices(path, indices, sizes, face_lines, face_vertex_counts, len(vertices))
    faces, source_face = _fan_triangulate(indices, sizes)

    if has_groups:
        labels, names = np.asarray(face_groups, dtype=np.int64), list(groups)
    else:
        labels, names = np.asarray(face_materials, dtype=np.int64), list(materials)
    labels = labels[source_face] if len(labels) else np.zeros(0, dtype=np.int64)
    # Renumber by first use so that groups without triangles disappear.
    used, first = np.unique(labels, return_index=True)
    used = used[np.argsort(first)]
    compact = np.zeros(len(names), dtype=np.int64)
    compact[used] = np.arange(len(used))
    return vertices, faces, compact[labels], [names[i] for i in used]


def _read_lines(path: str) -> list[tuple[int, str]]:
    """The logical lines of a text file with their 1-based physical line numbers.

    Parameters
    ----------
    path : str
        The file.

    Returns
    -------
    list of (int, str)
        ``(line number, text)``; a line continued with a trailing ``\\`` is joined to the next
        and carries the number of its first physical line.
    """
    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        raise GeometryError(f"{path}: cannot read file ({error.strerror or error})") from None
    if b"\x00" in data:
        raise GeometryError(f"{path}: not a text OBJ file (contains binary data)")
    try:
        text = data.decode("utf-8-sig")  # -sig: a byte-order mark would hide the first keyword
    except UnicodeDecodeError:
        # Old exporters write names in a legacy code page; latin-1 decodes any byte.
        text = data.decode("latin-1")
    physical = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if "\\" not in text:
        return list(enumerate(physical, 1))

    logical: list[tuple[int, str]] = []
    pending: list[str] = []
    start = 0
    for number, line in enumerate(physical, 1):
        stripped = line.rstrip()
        if not pending:
            start = number
        if stripped.endswith("\\"):
            pending.append(stripped[:-1])
            continue
        pending.append(line)
        logical.append((start, " ".join(pending)))
        pending = []
    if pending:
        logical.append((start, " ".join(pending)))
    return logical


def _parse_coordinates(path: str, coordinates: list[str], vertex_lines: list[int]) -> np.ndarray:
    """Convert the flattened coordinate tokens to a (V, 3) float64 array.

    Parameters
    ----------
    path : str
        The file, for error messages.
    coordinates : list of str, length 3 V
        x, y, z tokens of every vertex.
    vertex_lines : list of int, length V
        Line number of every vertex.

    Returns
    -------
    (V, 3) float64
    """
    try:
        return np.asarray(coordinates, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        pass
    # The bulk conversion failed: find the first bad token to report its line.
    for position, token in enumerate(coordinates):
        try:
            float(token)
        except ValueError:
            line = vertex_lines[position // 3]
            raise GeometryError(f"{path}, line {line}: vertex coordinate {token!r} is not a number") from None
    raise AssertionError("unreachable: every coordinate parsed one by one")


def _parse_corners(path: str, corners: list[str], sizes: np.ndarray, face_lines: list[int]) -> np.ndarray:
    """Extract the (one-based or negative) vertex index of every face corner.

    Parameters
    ----------
    path : str
        The file, for error messages.
    corners : list of str, length C
        Corner tokens such as ``"7"``, ``"7/3"``, ``"7//2"`` or ``"-1/-1/-1"``.
    sizes : (F,) int64
        Corners of each face; they sum to C.
    face_lines : list of int, length F
        Line number of each face.

    Returns
    -------
    (C,) int64
        The vertex index as written (not yet resolved).
    """
    # One regex pass over the joined text is far faster than splitting each token.
    tokens = _CORNER_TAIL.sub("", " ".join(corners)).split() if corners else []
    if len(tokens) == len(corners):
        try:
            return np.asarray(tokens, dtype=np.int64).reshape(-1)
        except ValueError:
            pass
    corner_face = np.repeat(np.arange(len(sizes)), sizes)
    for position, corner in enumerate(corners):
        try:
            int(corner.split("/", 1)[0])
        except ValueError:
            line = face_lines[corner_face[position]]
            raise GeometryError(f"{path}, line {line}: face corner {corner!r} has no vertex index") from None
    raise AssertionError("unreachable: every corner parsed one by one")


def _resolve_indices(
    path: str,
    indices: np.ndarray,
    sizes: np.ndarray,
    face_lines: list[int],
    face_vertex_counts: list[int],
    n_vertices: int,
) -> np.ndarray:
    """Turn written vertex indices into zero-based ones and check their range.

    Parameters
    ----------
    path : str
        The file, for error messages.
    indices : (C,) int64
        Indices as written: positive one-based, or negative relative to the face's line.
    sizes : (F,) int64
        Corners of each face.
    face_lines : list of int, length F
        Line number of each face.
    face_vertex_counts : list of int, length F
        Vertices defined before each face, the base of its negative indices.
    n_vertices : int
        Vertices in the whole file, the bound of positive indices (forward references allowed).

    Returns
    -------
    (C,) int64
        Zero-based vertex indices.
    """
    defined = np.repeat(np.asarray(face_vertex_counts, dtype=np.int64), sizes)
    resolved = np.where(indices < 0, defined + indices, indices - 1)
    bad = (indices == 0) | (resolved < 0) | (resolved >= n_vertices)
    if bad.any():
        corner = int(np.argmax(bad))
        face = int(np.searchsorted(np.cumsum(sizes), corner, side="right"))
        raise GeometryError(
            f"{path}, line {face_lines[face]}: vertex index {int(indices[corner])} out of range "
            f"({int(defined[corner])} vertices defined before this line, {n_vertices} in the file)"
        )
    return resolved


def _fan_triangulate(indices: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split polygons into triangle fans around their first corner.

    Parameters
    ----------
    indices : (C,) int64
        Zero-based vertex index of every corner, face after face.
    sizes : (F,) int64
        Corners of each face.

    Returns
    -------
    faces : (T, 3) int64
        Triangles, face order kept; faces with fewer than 3 corners give none.
    source_face : (T,) int64
        The polygon each triangle came from.
    """
    starts = np.cumsum(sizes) - sizes
    per_face = np.maximum(sizes - 2, 0)
    source_face = np.repeat(np.arange(len(sizes)), per_face)
    # k-th triangle of its polygon: corners (0, k + 1, k + 2).
    k = np.arange(len(source_face)) - np.repeat(np.cumsum(per_face) - per_face, per_face)
    first = starts[source_face]
    faces = np.stack([indices[first], indices[first + k + 1], indices[first + k + 2]], axis=1)
    return faces.astype(np.int64, copy=False).reshape(-1, 3), source_face
