"""Scene geometry: a cleaned, consistently oriented triangle mesh in normalised scene units.

:func:`load_geometry` turns a mesh file (OBJ through :func:`prt.train.inputs.objfile.read_obj`; PLY, STL,
OFF through trimesh; GLB and glTF through :func:`prt.train.inputs.gltf_scene.read_gltf_scene`) or the
name of a built-in SDF scene into a :class:`Geometry`:

1. read triangles and per-face object ids (a trimesh scene gives one object per geometry node; a
   glTF file one per node and triangle primitive, named by :mod:`prt.train.inputs.gltf_scene`);
2. clean: drop faces touching non-finite vertices, merge coincident vertices (within an object)
   and drop faces that collapse to a repeated vertex; faces keep their order and object id;
3. orient: make the winding consistent over each connected component, turn every watertight
   component outward, and mark the faces of open components two-sided;
4. drop zero-area faces (closedness was judged with them, so a closed surface with slivers
   stays closed; its mesh then has holes of zero area) and unreferenced vertices;
5. normalise into [-1, 1]^3 (AABB centre to the origin, the largest extent to exactly 2) and
   record ``to_source``, the transform back to the file's units.

Every failure is a :class:`~prt.runtime.errors.GeometryError` whose one-line message names the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import trimesh

from ...runtime.errors import GeometryError
from .objfile import DEFAULT_OBJECT, read_obj

__all__ = ["Geometry", "load_geometry", "MESH_EXTENSIONS"]

# Faces whose area is at most this times the squared bounding-box diagonal are degenerate.
DEGENERATE_AREA = 1e-12

# Extensions read by trimesh; .obj is read by our own parser (trimesh resolves negative indices wrongly),
# .glb/.gltf by gltf_scene (deterministic object names).
_TRIMESH_EXTENSIONS = ("ply", "stl", "off", "glb", "gltf")
MESH_EXTENSIONS = ("obj",) + _TRIMESH_EXTENSIONS


@dataclass
class Geometry:
    """A triangulated scene with per-face object identity and sidedness.

    Attributes
    ----------
    mesh : trimesh.Trimesh
        (V, 3) vertices and (F, 3) faces in scene units; for files normalised into [-1, 1]^3
        with the bounding-box centre at the origin.  Watertight components face outward.
    object_ids : (F,) int64
        Object of each face, ``0 .. len(object_names) - 1``; every object has faces.
    object_names : list of str
        Name of each object.
    two_sided : (F,) bool
        True for faces of open (non-watertight) components: both of their sides are surfaces.
    to_source : (4, 4) float64
        Scene units to source units: ``source = to_source @ [x, y, z, 1]``.
    source : str
        The file path or the SDF scene name.
    sdf : object or None
        The :mod:`prt.train.sdf` object of an SDF scene, else None.
    dropped_nonfinite : int
        Faces of the file dropped because a vertex had a NaN or infinite coordinate.
    mixed : prt.train.inputs.mixed.MixedParts or None
        A scene composed from a spec's ``objects`` (:mod:`prt.train.inputs.mixed`): which faces are SDF
        proxies, the SDF objects' fields, the objects' materials; else None.
    """

    mesh: trimesh.Trimesh
    object_ids: np.ndarray
    object_names: list[str]
    two_sided: np.ndarray
    to_source: np.ndarray
    source: str
    sdf: object | None = None
    dropped_nonfinite: int = 0
    mixed: object | None = None
    see_through: list = field(default_factory=list)  # parts left out as glass (gltf_scene.is_see_through; OBJ d < 0.5)
    cut_out: dict = field(default_factory=dict)  # parts cut along their alpha (glTF MASK, OBJ map_d): name -> (pieces, triangles before)
    cut_away: list = field(default_factory=list)  # parts whose alpha leaves nothing, left out
    uncut: list = field(default_factory=list)  # alpha-masked parts drawn opaque: their alpha unreadable (a GPU texture, a missing file) or not lined up (OBJ)

    @property
    def kind(self) -> str:
        """``"sdf"`` for an SDF scene, ``"mixed"`` for composed objects with an SDF among them
        (:mod:`prt.train.inputs.mixed`), else ``"mesh"``."""
        if self.mixed is not None and self.mixed.sdfs:
            return "mixed"
        return "sdf" if self.sdf is not None else "mesh"

    @property
    def scale(self) -> float:
        """Source units per scene unit (the uniform scale of ``to_source``)."""
        return float(np.cbrt(abs(np.linalg.det(self.to_source[:3, :3]))))

    @property
    def n_objects(self) -> int:
        """Number of objects."""
        return len(self.object_names)

    @property
    def watertight(self) -> bool:
        """True when every component is closed (no face is two-sided)."""
        return not bool(np.any(self.two_sided))

    def source_bounds(self) -> np.ndarray:
        """Axis-aligned bounds of the mesh in source units.

        Returns
        -------
        (2, 3) float64
            Minimum and maximum corner.
        """
        corners = np.array(np.meshgrid(*self.mesh.bounds.T, indexing="ij")).reshape(3, -1).T
        points = corners @ self.to_source[:3, :3].T + self.to_source[:3, 3]
        return np.stack([points.min(axis=0), points.max(axis=0)])

    def summary(self) -> str:
        """One line for command-line tools: counts, closedness and source-unit bounds."""
        n_faces = len(self.mesh.faces)
        n_open = int(np.count_nonzero(self.two_sided))
        closed = "watertight" if n_open == 0 else f"open ({n_open} of {n_faces} triangles two-sided)"
        low, high = (", ".join(f"{x:.4g}" for x in corner) for corner in self.source_bounds())
        dropped = f", {self.dropped_nonfinite} triangles with NaN/Inf vertices dropped" if self.dropped_nonfinite else ""
        if self.see_through:
            dropped += f"; {len(self.see_through)} see-through (glass) parts left out, light passes them: {_listed(self.see_through)}"
        if self.cut_out:
            before, after = sum(v[1] for v in self.cut_out.values()), sum(v[0] for v in self.cut_out.values())
            dropped += (f"; {len(self.cut_out)} alpha-masked parts cut along their texture's alpha ({before} triangles -> {after}): "
                        f"{_listed(list(self.cut_out))}")  # fmt: skip
        if self.cut_away:
            dropped += f"; {len(self.cut_away)} parts left out, wholly clear under their alpha cutoff: {_listed(self.cut_away)}"
        if self.uncut:
            dropped += f"; WARNING: {len(self.uncut)} alpha-masked parts drawn opaque (their alpha could not be read or lined up): {_listed(self.uncut)}"
        return (
            f"{self.source} [{self.kind}]: {n_faces} triangles, {len(self.mesh.vertices)} vertices, "
            f"{self.n_objects} objects, {closed}, bounds [{low}]..[{high}] (source units){dropped}"
        )


def _listed(names: list, shown: int = 3) -> str:
    """The first ``shown`` names, and how many more."""
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def load_geometry(source, *, normalise: bool = True, sdf_resolution: int = 128) -> Geometry:
    """Load a mesh file or a built-in SDF scene as a :class:`Geometry`.

    Parameters
    ----------
    source : str or os.PathLike
        An existing mesh file (see ``MESH_EXTENSIONS``) or the name of a built-in SDF scene.
    normalise : bool
        Move and scale a mesh file into [-1, 1]^3; if False, scene units are source units.
        SDF scenes are defined in scene units already and are never rescaled.
    sdf_resolution : int
        Grid resolution of the marching-cubes mesh of an SDF scene.

    Returns
    -------
    Geometry

    Raises
    ------
    GeometryError
        Unreadable, empty, corrupt or unsupported file, or a name that is neither a file nor an
        SDF scene.

    Notes
    -----
    An existing file wins over an SDF scene of the same name; a missing path that has a mesh
    extension or a directory separator is reported as a missing file, not looked up as a scene.
    """
    name = os.fspath(source)
    if not isinstance(name, str) or not name.strip() or "\0" in name:
        raise GeometryError(f"{name!r}: not a file name or SDF scene name")
    if os.path.isdir(name):
        raise GeometryError(f"{name}: is a directory, not a mesh file")
    if os.path.isfile(name) and name.lower().endswith(".sdf.onnx"):  # a neural SDF (prt.train.sdf.neural)
        return _load_neural_sdf(name, sdf_resolution)
    if os.path.exists(name):
        report: dict = {}
        vertices, faces, object_ids, object_names = _read_mesh_file(name, report=report)
        geometry = _build_geometry(vertices, faces, object_ids, object_names, name, normalise=normalise)
        geometry.see_through, geometry.cut_out = report.get("see_through", []), report.get("cut", {})
        geometry.cut_away, geometry.uncut = report.get("cut_away", []), report.get("uncut", [])
        return geometry
    if _extension(name) in MESH_EXTENSIONS or os.sep in name or (os.altsep and os.altsep in name):
        raise GeometryError(f"{name}: no such file")
    return _load_sdf_scene(name, sdf_resolution)


def _extension(path: str) -> str:
    """Lower-case file extension without the dot (``"mesh.PLY"`` -> ``"ply"``), or ``""``."""
    return os.path.splitext(path)[1][1:].lower()


def _one_line(error: BaseException) -> str:
    """``"Type: message"`` of an exception, squeezed onto one line."""
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _read_mesh_file(path: str, *, report: dict | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Read triangles and object ids of a mesh file, in source units.

    Parameters
    ----------
    path : str
        An existing file.

    Returns
    -------
    vertices : (V, 3) float64
    faces : (F, 3) int64
    object_ids : (F,) int64
    object_names : list of str
    """
    extension = _extension(path)
    stem = os.path.splitext(os.path.basename(path))[0]
    if extension not in MESH_EXTENSIONS:
        shown = f"'.{extension}'" if extension else "(no extension)"
        raise GeometryError(
            f"{path}: unsupported mesh format {shown} "
            f"(supported: {', '.join('.' + e for e in MESH_EXTENSIONS)})"
        )
    try:
        empty = os.path.getsize(path) == 0
    except OSError as error:
        raise GeometryError(f"{path}: cannot read file ({error.strerror or error})") from None
    if empty:
        raise GeometryError(f"{path}: empty file")
    if extension == "obj":
        vertices, faces, object_ids, object_names = read_obj(path)
        # A file without groups is one object: name it after the file rather than "default".
        if object_names == [DEFAULT_OBJECT]:
            object_names = [stem]
        from .materials import obj_cut  # dissolved materials: glass left out, map_d cut-outs cut

        vertices, faces, object_ids, cut_report, _ = obj_cut(path, vertices, faces, object_ids, object_names)
        if report is not None:
            report.update(cut_report)
        return vertices, faces, object_ids, object_names
    if extension in ("glb", "gltf"):  # our reader: deterministic object names (gltf_scene)
        from .gltf_scene import read_gltf_scene

        try:
            scene = read_gltf_scene(path, stem)
            if report is not None:
                report.update(see_through=scene.transparent, cut=scene.cut, cut_away=scene.cut_away, uncut=scene.uncut)
            return scene.arrays()
        except GeometryError as error:
            detail = str(error).removeprefix(f"{path}: ")
            raise GeometryError(f"{path}: cannot read {extension.upper()} file, corrupt or not {extension.upper()} ({detail})") from None
    if extension == "stl":
        _check_stl(path)
    try:
        scene = trimesh.load_scene(path, file_type=extension, process=False)
    except Exception as error:  # trimesh raises anything from ValueError to UnicodeDecodeError on bad bytes
        kind = extension.upper()
        raise GeometryError(
            f"{path}: cannot read {kind} file, corrupt or not {kind} ({_one_line(error)})"
        ) from None
    return _scene_triangles(scene, stem)


def _check_stl(path: str) -> None:
    """Reject a file that is neither a binary nor an ASCII STL before trimesh guesses at it.

    trimesh falls back to decoding unrecognised bytes as text, which fails with unrelated errors
    (a missing charset module, for one); the size and header tell the two STL kinds apart.

    Parameters
    ----------
    path : str
        An existing ``.stl`` file.
    """
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as handle:
            head = handle.read(84)
    except OSError as error:
        raise GeometryError(f"{path}: cannot read file ({error.strerror or error})") from None
    binary = size >= 84 and size == 84 + 50 * int(np.frombuffer(head[80:84], dtype="<u4")[0])
    if not binary and not head.lstrip().lower().startswith(b"solid"):
        raise GeometryError(
            f"{path}: not an STL file (neither a binary STL of matching size nor ASCII 'solid')"
        )


def _scene_triangles(scene: trimesh.Scene, stem: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Flatten a trimesh scene into one triangle soup, one object per geometry node.

    Parameters
    ----------
    scene : trimesh.Scene
        The loaded file; point clouds and paths in it are ignored.
    stem : str
        File name without extension, the object name of a single-mesh file.

    Returns
    -------
    vertices : (V, 3) float64
        With each node's scene-graph transform applied.
    faces : (F, 3) int64
    object_ids : (F,) int64
    object_names : list of str
    """
    # nodes_geometry is sorted by name; order by the file's geometry order instead.
    geometry_order = {key: index for index, key in enumerate(scene.geometry)}

    def file_order(node):
        return geometry_order[scene.graph[node][1]], str(node)

    names, vertices, faces = [], [], []
    n_vertices = 0
    for node in sorted(scene.graph.nodes_geometry, key=file_order):
        transform, geometry_name = scene.graph[node]
        mesh = scene.geometry[geometry_name]
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            continue  # point clouds, paths and empty meshes have no surface
        names.append(str(node))
        points = np.asarray(mesh.vertices, dtype=np.float64)
        vertices.append(trimesh.transformations.transform_points(points, transform))
        faces.append(np.asarray(mesh.faces, dtype=np.int64) + n_vertices)
        n_vertices += len(mesh.vertices)
    if not names:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0, dtype=np.int64), []
    if len(names) == 1:
        names = [stem]
    object_ids = np.repeat(np.arange(len(names), dtype=np.int64), [len(f) for f in faces])
    return np.concatenate(vertices), np.concatenate(faces), object_ids, names


def _load_sdf_scene(name: str, resolution: int) -> Geometry:
    """Build the geometry of a built-in SDF scene, or explain that ``name`` is neither kind.

    Parameters
    ----------
    name : str
        The argument of :func:`load_geometry`, already known not to be an existing path.
    resolution : int
        Marching-cubes grid resolution.

    Returns
    -------
    Geometry
        In scene units, ``to_source`` the identity, ``sdf`` set.
    """
    try:
        from ..sdf import get_sdf
    except ModuleNotFoundError as error:
        if error.name not in (f"{__package__}.sdf", "sdf"):
            raise
        raise GeometryError(
            f"{name}: no such file and not a built-in SDF scene (SDF scenes unavailable)"
        ) from None
    try:
        sdf = get_sdf(name)
    except GeometryError as error:
        raise GeometryError(f"{name}: no such file and not a built-in SDF scene ({error})") from None
    return _sdf_geometry(sdf, name, resolution)


def _load_neural_sdf(path: str, resolution: int) -> Geometry:
    """The geometry of an SDF network file (``*.sdf.onnx``, :mod:`prt.train.sdf.neural`)."""
    from ..sdf.neural import load_neural_sdf

    try:
        sdf = load_neural_sdf(path)
    except (ValueError, OSError) as error:
        raise GeometryError(f"{path}: not a neural SDF network ({error})") from None
    return _sdf_geometry(sdf, path, resolution)


def _sdf_geometry(sdf, name: str, resolution: int) -> Geometry:
    """Marching-cubes mesh of an SDF in scene units, ``sdf`` attached."""
    mesh = sdf.to_mesh(resolution=resolution)
    geometry = _build_geometry(
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.faces, dtype=np.int64),
        np.zeros(len(mesh.faces), dtype=np.int64),
        [str(getattr(sdf, "name", name))],
        name,
        normalise=False,
    )
    geometry.sdf = sdf
    return geometry


def _build_geometry(
    vertices: np.ndarray,
    faces: np.ndarray,
    object_ids: np.ndarray,
    object_names: list[str],
    source: str,
    *,
    normalise: bool,
) -> Geometry:
    """Clean, orient and normalise triangles into a :class:`Geometry`.

    Parameters
    ----------
    vertices : (V, 3) float64
        Source-unit positions.
    faces : (F, 3) int64
        Triangles.
    object_ids : (F,) int64
        Object of each triangle, indexing ``object_names``.
    object_names : list of str
    source : str
        File path or scene name, for the result and for error messages.
    normalise : bool
        Map into [-1, 1]^3.

    Returns
    -------
    Geometry
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    object_ids = np.asarray(object_ids, dtype=np.int64).reshape(-1)
    vertices, faces, object_ids, dropped_nonfinite = _clean(vertices, faces, object_ids, source)
    prescale = 1.0
    if normalise:
        # A power-of-two rescale is exact and keeps areas and volumes of coordinates near 1e300
        # (or 1e-300) from overflowing (underflowing) in float64; it is folded into to_source.
        prescale = _power_of_two_scale(vertices[np.unique(faces)])
        vertices = vertices / prescale
    # Judge closedness before dropping slivers: their removal leaves zero-area holes only.
    faces, two_sided = _orient(vertices, faces)
    keep = _nondegenerate(vertices, faces)
    if not keep.any():
        raise GeometryError(f"{source}: every triangle is degenerate (zero area)")
    faces, object_ids, two_sided = faces[keep], object_ids[keep], two_sided[keep]
    referenced, faces = np.unique(faces, return_inverse=True)
    vertices, faces = vertices[referenced], faces.reshape(-1, 3).astype(np.int64)
    object_ids, object_names = _drop_empty_objects(object_ids, object_names)

    to_source = np.eye(4)
    if normalise:
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        centre = (low + high) / 2
        half_extent = float((high - low).max()) / 2
        vertices = (vertices - centre) / half_extent
        to_source[:3, :3] *= half_extent * prescale
        to_source[:3, 3] = centre * prescale

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False, validate=False)
    return Geometry(
        mesh=mesh,
        object_ids=object_ids,
        object_names=list(object_names),
        two_sided=two_sided,
        to_source=to_source,
        source=source,
        dropped_nonfinite=dropped_nonfinite,
    )


def _power_of_two_scale(vertices: np.ndarray) -> float:
    """The power of two that brings the largest coordinate of ``vertices`` into [0.5, 1)."""
    biggest = float(np.abs(vertices).max()) if len(vertices) else 0.0
    return float(2.0 ** np.frexp(biggest)[1]) if biggest > 0 else 1.0


def _clean(
    vertices: np.ndarray, faces: np.ndarray, object_ids: np.ndarray, source: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove what cannot be part of a surface, keeping face order and object ids aligned.

    Faces touching a NaN or infinite vertex are dropped; vertices at exactly the same position
    that are used by the same object are merged (vertices already shared stay shared, and
    separate objects are not stitched together); faces left with a repeated vertex are dropped.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64
    object_ids : (F,) int64
    source : str
        For error messages.

    Returns
    -------
    vertices : (V', 3) float64
        Merged vertices; some may be unreferenced.
    faces : (F', 3) int64
        The surviving faces, in their original order.
    object_ids : (F',) int64
    dropped_nonfinite : int
        Faces dropped for a NaN or infinite vertex coordinate.
    """
    if len(faces) == 0:
        raise GeometryError(f"{source}: no triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise GeometryError(f"{source}: face index out of range ({len(vertices)} vertices)")
    finite = np.isfinite(vertices).all(axis=1)
    keep = finite[faces].all(axis=1)
    if not keep.any():
        raise GeometryError(f"{source}: every triangle has a NaN or infinite vertex coordinate")
    dropped_nonfinite = int(len(keep) - np.count_nonzero(keep))
    faces, object_ids = faces[keep], object_ids[keep]
    # No face uses them any more; zeroing keeps NaN out of the position comparison.
    vertices = np.where(finite[:, None], vertices, 0.0)

    labels = _coincident_vertex_labels(vertices, faces, object_ids)
    merged = np.zeros((labels.max() + 1, 3))
    merged[labels] = vertices
    faces = labels[faces]

    collapsed = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    if collapsed.all():
        raise GeometryError(f"{source}: every triangle is degenerate (repeated vertices)")
    return merged, faces[~collapsed], object_ids[~collapsed], dropped_nonfinite


def _nondegenerate(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces with an area above ``DEGENERATE_AREA`` times the squared bounding-box diagonal.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64

    Returns
    -------
    (F,) bool
    """
    used = vertices[np.unique(faces)]
    diagonal_squared = float(np.sum((used.max(axis=0) - used.min(axis=0)) ** 2))
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    return area > DEGENERATE_AREA * diagonal_squared


def _coincident_vertex_labels(vertices: np.ndarray, faces: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
    """Label vertices so that equal positions used by one object share a label.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64
    object_ids : (F,) int64

    Returns
    -------
    (V,) int64
        Merged vertex index of each vertex, ``0 .. V' - 1``; all vertices with one label have the
        same position.
    """
    # Adding 0.0 turns -0.0 into 0.0 so that both compare equal.
    position = _row_labels(vertices + 0.0)
    corner_vertex = faces.reshape(-1)
    corner_object = np.repeat(object_ids, 3)
    corner_position = position[corner_vertex]
    order = np.lexsort((corner_vertex, corner_position, corner_object))
    vertex, same_run = corner_vertex[order], _equal_to_previous(corner_object[order], corner_position[order])
    # Within a run of equal (object, position), link each vertex to the previous one.
    links = scipy.sparse.coo_matrix(
        (np.ones(np.count_nonzero(same_run)), (vertex[1:][same_run], vertex[:-1][same_run])),
        shape=(len(vertices), len(vertices)),
    )
    _, labels = scipy.sparse.csgraph.connected_components(links, directed=False)
    return labels.astype(np.int64)


def _row_labels(rows: np.ndarray) -> np.ndarray:
    """Label equal rows alike (a faster ``np.unique(rows, axis=0, return_inverse=True)[1]``).

    Parameters
    ----------
    rows : (N, K) array

    Returns
    -------
    (N,) int64
        Equal rows get equal labels, ``0 .. n_distinct - 1``.
    """
    order = np.lexsort(rows.T[::-1])
    starts = ~_equal_to_previous(*rows[order].T)
    labels = np.empty(len(rows), dtype=np.int64)
    labels[order] = np.cumsum(np.r_[True, starts]) - 1
    return labels


def _equal_to_previous(*columns: np.ndarray) -> np.ndarray:
    """Whether each row of sorted columns equals the row before it.

    Parameters
    ----------
    *columns : (N,) arrays
        Columns of rows already in sorted order.

    Returns
    -------
    (N - 1,) bool
        Entry i compares row i + 1 with row i.
    """
    equal = np.ones(max(len(columns[0]) - 1, 0), dtype=bool)
    for column in columns:
        equal &= column[1:] == column[:-1]
    return equal


def _drop_empty_objects(object_ids: np.ndarray, object_names: list[str]) -> tuple[np.ndarray, list[str]]:
    """Renumber objects so that only those with faces remain, in their original order.

    Parameters
    ----------
    object_ids : (F,) int64
    object_names : list of str

    Returns
    -------
    object_ids : (F,) int64
    object_names : list of str
    """
    used = np.unique(object_ids)
    compact = np.zeros(len(object_names), dtype=np.int64)
    compact[used] = np.arange(len(used))
    return compact[object_ids], [object_names[i] for i in used]


def _orient(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Make winding consistent per component, closed components outward; flag open ones.

    Components are sets of faces joined through manifold edges (edges of exactly two faces).
    Within each, faces are flipped to agree with a spanning tree; the component as a whole then
    keeps the winding the majority of its faces had in the file.  A component is closed when
    every edge of its faces is manifold and consistently oriented; closed components with
    negative signed volume are flipped, all others are two-sided.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64

    Returns
    -------
    faces : (F, 3) int64
        Same faces, some with reversed winding.
    two_sided : (F,) bool
        Faces of open components.
    """
    n_faces = len(faces)
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    edge_face = np.repeat(np.arange(n_faces), 3)
    forward = edges[:, 0] < edges[:, 1]
    key = edges.min(axis=1) * (int(faces.max()) + 1) + edges.max(axis=1)
    order = np.argsort(key, kind="stable")
    key, edge_face, forward = key[order], edge_face[order], forward[order]
    run_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    run_length = np.diff(np.r_[run_start, len(key)])

    manifold = run_start[run_length == 2]
    face_a, face_b = edge_face[manifold], edge_face[manifold + 1]
    # Two faces traversing their shared edge in the same direction disagree: one must flip.
    disagree = forward[manifold] == forward[manifold + 1]
    bad_edge_faces = edge_face[np.repeat(run_length != 2, run_length)]

    n_components, component = scipy.sparse.csgraph.connected_components(
        scipy.sparse.coo_matrix((np.ones(len(face_a)), (face_a, face_b)), shape=(n_faces, n_faces)),
        directed=False,
    )
    flip = _spanning_tree_parity(n_faces, face_a, face_b, disagree, component, n_components)

    # Keep each component's majority winding from the file.
    flipped_share = np.bincount(component, weights=flip, minlength=n_components) / np.bincount(component)
    flip ^= flipped_share[component] > 0.5

    inconsistent = (flip[face_a] ^ flip[face_b]) != disagree
    is_open = np.zeros(n_components, dtype=bool)
    is_open[component[bad_edge_faces]] = True
    is_open[component[face_a[inconsistent]]] = True

    faces = np.where(flip[:, None], faces[:, ::-1], faces)
    corners = vertices[faces]
    corners = corners - corners.reshape(-1, 3).mean(axis=0)  # a nearby origin keeps the volume sum accurate
    signed = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2]))
    volume = np.bincount(component, weights=signed, minlength=n_components)
    inward = ~is_open & (volume < 0)
    faces = np.where(inward[component][:, None], faces[:, ::-1], faces)
    return np.ascontiguousarray(faces), is_open[component]


def _spanning_tree_parity(
    n_faces: int,
    face_a: np.ndarray,
    face_b: np.ndarray,
    disagree: np.ndarray,
    component: np.ndarray,
    n_components: int,
) -> np.ndarray:
    """Which faces to flip so that each agrees with its breadth-first-tree parent.

    Parameters
    ----------
    n_faces : int
    face_a, face_b : (M,) int64
        The two faces of each manifold edge.
    disagree : (M,) bool
        True where those two faces wind the edge the same way.
    component : (F,) int64
        Component label of each face.
    n_components : int

    Returns
    -------
    (F,) bool
        Flip of each face relative to the first face of its component.
    """
    root = n_faces  # a virtual face linked to one face per component, so one search spans all
    seeds = np.unique(component, return_index=True)[1]
    rows = np.r_[face_a, np.full(n_components, root)]
    cols = np.r_[face_b, seeds]
    graph = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_faces + 1, n_faces + 1))
    _, parent = scipy.sparse.csgraph.breadth_first_order(
        graph, root, directed=False, return_predecessors=True
    )
    parent[root] = root

    # Parity of each tree edge (parent, face), looked up by an order-independent pair key.
    pair_key = np.minimum(face_a, face_b) * (n_faces + 1) + np.maximum(face_a, face_b)
    order = np.argsort(pair_key)
    pair_key, pair_disagree = pair_key[order], disagree[order]
    child = np.arange(n_faces)
    tree_key = np.minimum(parent[child], child) * (n_faces + 1) + np.maximum(parent[child], child)
    slot = np.minimum(np.searchsorted(pair_key, tree_key), max(len(pair_key) - 1, 0))
    parity = np.zeros(n_faces + 1, dtype=bool)
    if len(pair_key):
        parity[:n_faces] = (pair_key[slot] == tree_key) & pair_disagree[slot]

    # Pointer jumping: XOR the parities along each path to the root in O(log depth) passes.
    while np.any(parent != root):
        parity = parity ^ parity[parent]
        parent = parent[parent]
    return parity[:n_faces]
