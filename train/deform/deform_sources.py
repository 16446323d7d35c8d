"""Deforming surfaces as a rest mesh plus frames with one shared vertex and face list.

Three sources (``prt-train INPUT --deform SPEC``, :func:`parse_deform`):

- ``sequence``: a folder of ``.obj`` / ``.ply`` frames in natural sort order (:func:`load_sequence`);
- ``gltf``: a skinned or morph-target glTF animation sampled to frames (:func:`load_gltf`,
  posing in :mod:`prt.train.deform.gltf_animation`);
- procedural deformers of a mesh: ``bend``, ``twist``, and ``fold``, a sheet folding over
  itself through a smooth crease (:func:`procedural`, the sheet :func:`make_sheet`).

Vertices are never merged or dropped, so vertex ``i`` is the same surface point in every frame.
Faces are oriented once, on the rest mesh: consistent winding, closed parts outward, judged on
the vertices welded by position (split UV seams do not break a closed surface); only the winding
is taken from that, the vertex list stays as read.  Every failure is one line
(:class:`~prt.runtime.errors.SpecError` for the spec, :class:`~prt.runtime.errors.GeometryError`
for the files) naming the file and field; nothing is written.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass

import numpy as np

from ...runtime.errors import GeometryError, SpecError
from ..inputs.geometry import _coincident_vertex_labels, _orient, _read_mesh_file
from .gltf_animation import AnimatedScene, malformed_gltf, read_gltf

__all__ = ["DeformSource", "load_sequence", "load_gltf", "procedural", "make_sheet", "parse_deform", "DEFORMERS"]

SEQUENCE_EXTENSIONS = (".obj", ".ply")
DEFORMERS = ("bend", "twist", "fold")
FOLD_RADIUS = 0.08  # default crease radius of "fold", in mesh units (the generated sheet is 2 wide)
DEFAULT_FRAMES = {"gltf": 24, "bend": 16, "twist": 16, "fold": 16}
_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class DeformSource:
    """A deforming triangle mesh: a rest pose and K frames over the same vertices and faces.

    Attributes
    ----------
    kind : str
        ``"sequence"``, ``"gltf"`` or ``"procedural"``.
    rest : (V, 3) float64
        Rest-pose vertices.
    faces : (F, 3) int64
        Shared by every frame; consistently wound, closed parts outward.
    frames : (K, V, 3) float64
        Deformed vertices, in the units of ``rest``.
    parameters : (K, P) float64
        Each frame's native parameters (sequence: its index; gltf: clip time in s; procedural:
        the deformer's value).
    parameter_names : tuple of str
        Name of each parameter column.
    frame_names : tuple of str
        One label per frame (a file name, ``"walk t=0.533"``, ``"fold angle=90"``).
    description : dict
        JSON-able record for the manifest: ``kind``, ``path`` (as given), ``animation``,
        ``frames``, ``parameters`` (name -> [first, last]) and per-kind details.
    """

    kind: str
    rest: np.ndarray
    faces: np.ndarray
    frames: np.ndarray
    parameters: np.ndarray
    parameter_names: tuple[str, ...]
    frame_names: tuple[str, ...]
    description: dict

    def normalised(self) -> tuple["DeformSource", dict]:
        """The source moved and scaled like :func:`prt.train.inputs.geometry.load_geometry` scales a mesh.

        One similarity for rest and every frame: the centre of the bounding box of all their
        vertices goes to the origin and its largest half-extent becomes 1 (so every frame lies
        in [-1, 1]^3).

        Returns
        -------
        source : DeformSource
            Same faces, parameters and names.
        transform : dict
            ``{"centre": [x, y, z], "scale": s}`` with ``x_new = (x - centre) * scale``.
        """
        points = np.concatenate([self.rest[None], self.frames]).reshape(-1, 3)
        low, high = points.min(axis=0), points.max(axis=0)
        centre = (low + high) / 2
        half_extent = float((high - low).max()) / 2
        if not half_extent > 0:
            raise GeometryError(f"{self.description.get('path')}: every vertex of every frame is at one point")
        scale = 1.0 / half_extent
        source = dataclasses.replace(
            self,
            rest=_frozen((self.rest - centre) * scale),
            frames=_frozen((self.frames - centre) * scale),
        )
        return source, {"centre": [float(c) for c in centre], "scale": scale}


def _frozen(array: np.ndarray, dtype=np.float64) -> np.ndarray:
    """A read-only contiguous copy."""
    array = np.array(array, dtype=dtype, copy=True, order="C")
    array.setflags(write=False)
    return array


def _source(kind, rest, faces, frames, parameters, parameter_names, frame_names, description) -> DeformSource:
    """Build a :class:`DeformSource` with oriented faces and read-only arrays."""
    rest = np.asarray(rest, dtype=np.float64)
    faces = orient_faces(rest, np.asarray(faces, dtype=np.int64))
    return DeformSource(
        kind=kind,
        rest=_frozen(rest),
        faces=_frozen(faces, np.int64),
        frames=_frozen(frames),
        parameters=_frozen(np.asarray(parameters, dtype=np.float64).reshape(len(frames), -1)),
        parameter_names=tuple(parameter_names),
        frame_names=tuple(frame_names),
        description=description,
    )


def orient_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Consistent winding, closed components outward, without merging any vertex (:func:`orientation`'s faces)."""
    return orientation(vertices, faces)[0]


def orientation(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Consistent winding and sidedness, closed components outward, without merging any vertex.

    The winding is decided on the mesh welded by position (so faces split at UV seams still form
    one closed surface) with :mod:`prt.train.inputs.geometry`'s orientation; each face of the original
    mesh is then flipped wherever its welded twin was.  Faces that collapse when welded keep their
    winding and count as two-sided.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64

    Returns
    -------
    faces : (F, 3) int64
        The faces, some reversed.
    two_sided : (F,) bool
        Faces of open components (of the welded mesh): both of their sides are surfaces.
    """
    two_sided = np.ones(len(faces), dtype=bool)
    if len(faces) == 0:
        return faces, two_sided
    labels = _coincident_vertex_labels(vertices, faces, np.zeros(len(faces), dtype=np.int64))
    welded = labels[faces]
    usable = np.flatnonzero((welded[:, 0] != welded[:, 1]) & (welded[:, 1] != welded[:, 2]) & (welded[:, 2] != welded[:, 0]))
    if len(usable) == 0:
        return faces, two_sided
    welded_vertices = np.zeros((labels.max() + 1, 3))
    welded_vertices[labels] = vertices
    oriented, open_faces = _orient(welded_vertices, welded[usable])
    flipped = np.any(oriented != welded[usable], axis=1)
    result = faces.copy()
    result[usable[flipped]] = faces[usable[flipped]][:, ::-1]
    two_sided[usable] = open_faces
    return result, two_sided


def _check_finite(points: np.ndarray, where: str) -> None:
    """Refuse NaN or infinite coordinates, counting the vertices that have them."""
    bad = ~np.isfinite(points).all(axis=-1)
    if bad.any():
        raise GeometryError(f"{where}: {int(bad.sum())} of {bad.size} vertices have NaN or infinite coordinates")


# --------------------------------------------------------------------------------------------
# Mesh sequences


def _natural_key(name: str) -> list:
    """Sort key that orders ``frame2`` before ``frame10``."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def _read_frame_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of one frame file exactly as stored (no merging, no dropping)."""
    vertices, faces, _, _ = _read_mesh_file(path)
    if len(faces) == 0:
        raise GeometryError(f"{path}: no triangles")
    return np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)


def _topology_difference(
    faces: np.ndarray, reference: np.ndarray, n_vertices: int, n_reference: int, rest_name: str
) -> str | None:
    """What differs between a frame's topology and the rest mesh's, or None."""
    if n_vertices != n_reference:
        return f"{n_vertices} vertices, {rest_name} has {n_reference}"
    if len(faces) != len(reference):
        return f"{len(faces)} triangles, {rest_name} has {len(reference)}"
    differs = np.flatnonzero(np.any(faces != reference, axis=1))
    if len(differs):
        face = int(differs[0])
        return (
            f"{len(differs)} triangles differ from {rest_name}, first triangle {face}: "
            f"{faces[face].tolist()} vs {reference[face].tolist()}"
        )
    return None


def load_sequence(folder) -> DeformSource:
    """A folder of ``.obj`` / ``.ply`` frames with one vertex and face list.

    Parameters
    ----------
    folder : str or os.PathLike
        Frames in natural sort order of their file names; a file named ``rest.obj`` or
        ``rest.ply`` is the rest pose (and no frame), else the first frame is.

    Returns
    -------
    DeformSource
        ``kind`` ``"sequence"``, one parameter ``frame`` (0, 1, ...), frame names the file names.

    Raises
    ------
    GeometryError
        Not a folder, fewer than 2 frames, an unreadable frame, a frame whose vertex count or
        triangle list differs from the rest mesh's, NaN or infinite coordinates.
    """
    given = os.fspath(folder)
    if not os.path.isdir(given):
        raise GeometryError(f"{given}: not a folder of mesh frames")
    names = sorted(
        (n for n in os.listdir(given) if n.lower().endswith(SEQUENCE_EXTENSIONS) and os.path.isfile(os.path.join(given, n))),
        key=_natural_key,
    )
    rest_names = [n for n in names if os.path.splitext(n)[0].lower() == "rest"]
    frame_files = [n for n in names if n not in rest_names]
    if len(rest_names) > 1:
        raise GeometryError(f"{given}: more than one rest mesh ({', '.join(rest_names)})")
    if len(frame_files) < 2:
        raise GeometryError(
            f"{given}: {len(frame_files)} mesh frames ({'/'.join(SEQUENCE_EXTENSIONS)}), a sequence needs at least 2"
        )
    rest_name = rest_names[0] if rest_names else frame_files[0]
    rest, faces = _read_frame_mesh(os.path.join(given, rest_name))
    _check_finite(rest, os.path.join(given, rest_name))
    frames = []
    for index, name in enumerate(frame_files):
        path = os.path.join(given, name)
        vertices, frame_faces = (rest, faces) if name == rest_name else _read_frame_mesh(path)
        difference = _topology_difference(frame_faces, faces, len(vertices), len(rest), rest_name)
        if difference:
            raise GeometryError(f"{path} (frame {index}): topology differs: {difference}")
        _check_finite(vertices, f"{path} (frame {index})")
        frames.append(vertices)
    description = {
        "kind": "sequence",
        "path": given,
        "animation": None,
        "frames": len(frames),
        "parameters": {"frame": [0.0, float(len(frames) - 1)]},
        "rest": rest_name,
        "files": frame_files,
    }
    indices = np.arange(len(frames), dtype=np.float64)
    return _source("sequence", rest, faces, np.stack(frames), indices, ("frame",), frame_files, description)


# --------------------------------------------------------------------------------------------
# glTF


def load_gltf(
    path, animation: str | None = None, frames: int = 24, time_range: tuple[float, float] | None = None
) -> DeformSource:
    """Frames of a skinned or morph-target glTF animation, sampled uniformly in time.

    Parameters
    ----------
    path : str or os.PathLike
        ``.glb`` or ``.gltf`` (buffers embedded as base64 or in files beside it).  Every mesh of
        the default scene is merged, in scene order.
    animation : str or None
        The clip's name; None takes the only one (an error lists them when there are several).
    frames : int
        K >= 2 frames at ``start + k (end - start) / (K - 1)``.
    time_range : (float, float) or None
        ``(start, end)`` in seconds; None: the clip's first and last key.

    Returns
    -------
    DeformSource
        ``kind`` ``"gltf"``; ``rest`` the bind pose (skins at their bind matrices, so the
        skinned ``POSITION``, and morph weights at the mesh defaults; unskinned meshes placed by
        their node's world matrix), one parameter ``time`` (s).

    Raises
    ------
    GeometryError
        Unreadable file, no skin and no morph targets, no such animation, NaN poses.
    SpecError
        ``frames`` < 2 or an empty or non-finite time range.
    """
    given = os.fspath(path)
    count = _frame_count(frames, "frames")
    if time_range is not None:
        try:
            time_range = (float(time_range[0]), float(time_range[1]))
        except (TypeError, ValueError, IndexError):
            raise SpecError(f"{given}: time_range {time_range!r} is not two numbers (start, end)") from None
    with malformed_gltf(given):
        return _sample_gltf(given, animation, count, time_range)


def _sample_gltf(given: str, animation: str | None, count: int, time_range) -> DeformSource:
    """The body of :func:`load_gltf`, its arguments checked."""
    scene = AnimatedScene(read_gltf(given))
    if not scene.deforms:
        raise GeometryError(f"{given}: has no skin and no morph targets: no animation can deform its meshes")
    clip = scene.clip(animation)
    start, end = clip.time_range if time_range is None else time_range
    if not (math.isfinite(start) and math.isfinite(end) and end > start):
        raise SpecError(f"{given}: animation {clip.name!r}: time range {start}..{end} s is empty")
    times = np.linspace(start, end, count)
    rest = scene.rest()
    _check_finite(rest, f"{given} (bind pose)")
    poses = []
    for time in times:
        pose = scene.pose(clip, float(time))
        _check_finite(pose, f"{given} (animation {clip.name!r} t={time:.4g})")
        poses.append(pose)
    description = {
        "kind": "gltf",
        "path": given,
        "animation": clip.name,
        "frames": count,
        "parameters": {"time": [float(start), float(end)]},
        "clip_range": [float(t) for t in clip.time_range],
    }
    opaque = _masked_primitives(scene)
    if opaque:
        description["drawn_opaque"] = opaque
    names = [f"{clip.name} t={t:.3f}" for t in times]
    return _source("gltf", rest, scene.faces, np.stack(poses), times, ("time",), names, description)


def _masked_primitives(scene: AnimatedScene) -> list[str]:
    """Primitives of an animated scene whose material lets light through (alpha cut-outs, glass:
    :func:`prt.train.inputs.gltf_scene.alpha_cutoff`, ``is_see_through``), which a deformable build
    draws and traces opaque (it keeps the skinned vertices as they are), as ``mesh M primitive K``."""
    from ..inputs.gltf_scene import alpha_cutoff, is_see_through

    document = scene.gltf.document
    materials, meshes, out = document.get("materials", []), document.get("meshes", []), []
    for mesh in sorted({int(scene.nodes[node]["mesh"]) for node, _ in scene._order if "mesh" in scene.nodes[node]}):
        for number, prim in enumerate(meshes[mesh].get("primitives", [])):
            material = prim.get("material")
            spec = materials[material] if isinstance(material, int) and 0 <= material < len(materials) else None
            if spec is not None and (alpha_cutoff(spec) is not None or is_see_through(spec)):
                out.append(f"mesh {mesh} primitive {number}")
    return out


def _frame_count(value, field: str) -> int:
    """A frame count of at least 2."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
        raise SpecError(f"{field}: {value!r} frames, need an integer >= 2")
    return int(value)


# --------------------------------------------------------------------------------------------
# Procedural deformers


def make_sheet(n: int = 48, size: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat square grid in the xz plane (y = 0), centred at the origin, facing +y.

    Parameters
    ----------
    n : int
        Quads per side ((n + 1)^2 vertices, 2 n^2 triangles).
    size : float
        Side length.

    Returns
    -------
    vertices : (V, 3) float64
    faces : (F, 3) int64
        Wound counter-clockwise seen from +y.
    """
    steps = np.linspace(-size / 2, size / 2, n + 1)
    x, z = np.meshgrid(steps, steps, indexing="ij")
    vertices = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    corner = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    # Vertex (i, j) is i (n + 1) + j; (x, z) -> (i, j), and z x x = +y, so (i,j), (i,j+1), (i+1,j) is CCW from +y.
    a, b, c, d = corner, corner + 1, corner + n + 1, corner + n + 2
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([c, b, d], axis=1)])
    return vertices, faces.astype(np.int64)


def bend(vertices: np.ndarray, angle: float, axis: int) -> np.ndarray:
    """Bend about ``axis``: the longer of the two other directions curls onto a circular arc.

    The mesh's extent L along that length direction ``l`` becomes an arc of ``angle`` degrees
    (radius ``L / angle``), centred on the middle of the extent, which stays in place; the arc
    curls towards +``n``, the remaining direction.  Lengths along the middle surface are kept.

    Parameters
    ----------
    vertices : (V, 3) float64
    angle : float
        Degrees over the whole length.
    axis : int
        0, 1 or 2: the axis the mesh bends about (its coordinate is unchanged).

    Returns
    -------
    (V, 3) float64
    """
    others = [a for a in range(3) if a != axis]
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    extent = high - low
    length, normal = sorted(others, key=lambda a: -extent[a])
    theta = math.radians(angle)
    if theta == 0.0 or extent[length] == 0.0:
        return vertices.copy()
    centre = (low + high) / 2
    radius = extent[length] / theta
    s = vertices[:, length] - centre[length]
    d = vertices[:, normal] - centre[normal]
    phi = s / radius
    result = vertices.copy()
    result[:, length] = centre[length] + (radius - d) * np.sin(phi)
    result[:, normal] = centre[normal] + radius - (radius - d) * np.cos(phi)
    return result


def twist(vertices: np.ndarray, angle: float, axis: int) -> np.ndarray:
    """Twist about the line along ``axis`` through the bounding-box centre.

    A vertex turns by ``angle * (a - centre) / extent`` degrees, ``a`` its coordinate along the
    axis, so the two ends turn by -angle/2 and +angle/2.

    Parameters
    ----------
    vertices : (V, 3) float64
    angle : float
        Degrees between the two ends.
    axis : int
        0, 1 or 2.

    Returns
    -------
    (V, 3) float64
    """
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    centre, extent = (low + high) / 2, float(high[axis] - low[axis])
    if extent == 0.0:
        return vertices.copy()
    u, v = (axis + 1) % 3, (axis + 2) % 3  # right-handed: rotating u towards v turns about +axis
    phi = np.radians(angle) * (vertices[:, axis] - centre[axis]) / extent
    du, dv = vertices[:, u] - centre[u], vertices[:, v] - centre[v]
    result = vertices.copy()
    result[:, u] = centre[u] + np.cos(phi) * du - np.sin(phi) * dv
    result[:, v] = centre[v] + np.sin(phi) * du + np.cos(phi) * dv
    return result


def fold(vertices: np.ndarray, angle: float, radius: float) -> np.ndarray:
    """Fold the part with x > 0 up and over about the crease line x = 0, y = 0 (along z).

    The crease is a circular arc of ``radius`` about the line x = 0, y = ``radius``: the strip
    0 <= x <= radius * angle wraps onto it and the rest follows flat along the arc's end tangent,
    so the fold has no kink and keeps lengths (y is the offset along the sheet's normal, kept).
    At 180 degrees the folded half lies flat at y = 2 radius over the other half, mirrored about
    x = pi radius / 2.

    Parameters
    ----------
    vertices : (V, 3) float64
    angle : float
        Degrees, 0 (flat) to 180 (folded flat over).
    radius : float
        Crease radius, > 0, in mesh units.

    Returns
    -------
    (V, 3) float64
    """
    theta = math.radians(angle)
    x, y = vertices[:, 0], vertices[:, 1]
    arc = radius * theta
    phi = np.clip(x, 0.0, arc) / radius  # the angle reached along the crease
    beyond = np.maximum(x - arc, 0.0)  # length past the crease, along the end tangent
    bent = x > 0
    result = vertices.copy()
    new_x = (radius - y) * np.sin(phi) + beyond * math.cos(theta)
    new_y = radius - (radius - y) * np.cos(phi) + beyond * math.sin(theta)
    result[:, 0] = np.where(bent, new_x, x)
    result[:, 1] = np.where(bent, new_y, y)
    return result


def procedural(kind: str, values, *, mesh: tuple[np.ndarray, np.ndarray] | None = None, **options) -> DeformSource:
    """Frames of a procedural deformer, one per value.

    Parameters
    ----------
    kind : str
        ``"bend"`` or ``"twist"`` (options ``axis``: ``"x"``, ``"y"`` (default) or ``"z"``; see
        :func:`bend`, :func:`twist`), or ``"fold"`` (option ``radius``, default ``FOLD_RADIUS``;
        see :func:`fold`).
    values : sequence of float
        The deformer's angle in degrees for each frame (at least 2).
    mesh : (vertices, faces) or None
        The mesh to deform; None is allowed for ``fold`` only (:func:`make_sheet`).
    **options
        ``axis``, ``radius``, and ``path`` (the mesh's name for the description).

    Returns
    -------
    DeformSource
        ``kind`` ``"procedural"``, rest the undeformed mesh, one parameter ``angle``.

    Raises
    ------
    SpecError
        Unknown kind or option, fewer than 2 values, a bad axis or radius, a fold angle outside
        [0, 180].
    GeometryError
        NaN or infinite mesh coordinates.
    """
    if kind not in DEFORMERS:
        raise SpecError(f"deform kind {kind!r} is not one of {', '.join(DEFORMERS + ('sequence', 'gltf'))}")
    allowed = {"bend": {"axis", "path"}, "twist": {"axis", "path"}, "fold": {"radius", "path"}}[kind]
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise SpecError(f"{kind}: unknown option {unknown[0]!r} (allowed: {', '.join(sorted(allowed - {'path'}))})")
    angles = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(angles) < 2 or not np.isfinite(angles).all():
        raise SpecError(f"{kind}: angle: need at least 2 finite values, got {angles.tolist()}")
    path = options.get("path", "sheet" if mesh is None else "mesh")
    if mesh is None:
        if kind != "fold":
            raise SpecError(f"{kind}: needs a mesh (only fold has a generated sheet)")
        mesh = make_sheet()
    vertices, faces = np.asarray(mesh[0], dtype=np.float64), np.asarray(mesh[1], dtype=np.int64)
    _check_finite(vertices, str(path))
    deform, extra = _deformer(kind, angles, options)
    frames = np.stack([deform(vertices, float(a)) for a in angles])
    description = {
        "kind": "procedural",
        "path": str(path),
        "animation": None,
        "frames": len(angles),
        "parameters": {"angle": [float(angles[0]), float(angles[-1])]},
        "deformer": kind,
        "options": extra,
    }
    names = [f"{kind} angle={a:g}" for a in angles]
    return _source("procedural", vertices, faces, frames, angles, ("angle",), names, description)


def _deformer(kind: str, angles: np.ndarray, options: dict):
    """The function ``(vertices, angle) -> vertices`` of a deformer and its options as recorded."""
    if kind == "fold":
        radius = options.get("radius", FOLD_RADIUS)
        if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not (math.isfinite(radius) and radius > 0):
            raise SpecError(f"fold: radius: {radius!r} is not a positive number")
        if angles.min() < 0 or angles.max() > 180:
            raise SpecError(f"fold: angle: values must lie in 0..180 degrees, got {angles.min():g}..{angles.max():g}")
        return (lambda v, a: fold(v, a, float(radius))), {"radius": float(radius)}
    axis = options.get("axis", "y")
    if axis not in _AXES:
        raise SpecError(f"{kind}: axis: {axis!r} is not x, y or z")
    function = bend if kind == "bend" else twist
    return (lambda v, a: function(v, a, _AXES[axis])), {"axis": axis}


# --------------------------------------------------------------------------------------------
# The --deform option


def parse_deform(spec: str, input_path) -> DeformSource:
    """The deforming source of ``prt-train INPUT --deform SPEC``.

    ``SPEC`` is a kind, then optionally ``:`` and comma-separated ``key=value`` options:

    - ``sequence`` (INPUT a folder of frames);
    - ``gltf[:animation=NAME][,frames=24][,start=S][,end=E]`` (INPUT a .glb / .gltf; S, E in s);
    - ``bend:angle=A..B[,frames=16][,axis=y]``, ``twist:angle=A..B[,frames=16][,axis=y]``
      (INPUT a mesh file);
    - ``fold:angle=A..B[,frames=16][,radius=0.08]`` (INPUT a mesh file or the word ``sheet``).

    ``A..B`` with ``frames=K`` is K values evenly spaced from A to B, both included.

    Parameters
    ----------
    spec : str
    input_path : str or os.PathLike

    Returns
    -------
    DeformSource

    Raises
    ------
    SpecError
        Unknown kind or option, bad value syntax, fewer than 2 frames.
    GeometryError
        From the loaders.
    """
    text = str(spec).strip()
    kind, _, rest = text.partition(":")
    kind = kind.strip().lower()
    where = f"--deform {text!r}"
    options = _parse_options(rest, where)
    allowed = {
        "sequence": set(),
        "gltf": {"animation", "frames", "start", "end"},
        "bend": {"angle", "frames", "axis"},
        "twist": {"angle", "frames", "axis"},
        "fold": {"angle", "frames", "radius"},
    }
    if kind not in allowed:
        raise SpecError(f"{where}: unknown deform kind {kind!r} (one of {', '.join(allowed)})")
    unknown = sorted(set(options) - allowed[kind])
    if unknown:
        shown = ", ".join(sorted(allowed[kind])) or "none"
        raise SpecError(f"{where}: unknown option {unknown[0]!r} for {kind} (options: {shown})")
    path = os.fspath(input_path)
    if kind == "sequence":
        return load_sequence(path)
    count = _number(options.get("frames", str(DEFAULT_FRAMES[kind])), "frames", where, integer=True)
    frames = _frame_count(count, f"{where}: frames")
    if kind == "gltf":
        return _parse_gltf(path, options, frames, where)
    if "angle" not in options:
        raise SpecError(f"{where}: angle: missing (e.g. angle=0..90)")
    angles = _value_range(options["angle"], frames, "angle", where)
    extra = {}
    if "axis" in options:
        extra["axis"] = options["axis"].lower()
    if "radius" in options:
        extra["radius"] = _number(options["radius"], "radius", where)
    mesh = None
    if not (kind == "fold" and path == "sheet"):
        mesh = _read_mesh(path)
    try:
        return procedural(kind, angles, mesh=mesh, path=path, **extra)
    except SpecError as error:
        raise SpecError(f"{where}: {error}") from None


def _parse_gltf(path: str, options: dict, frames: int, where: str) -> DeformSource:
    """``load_gltf`` with the spec's options; a half-given time range is completed from the clip."""
    start = _number(options["start"], "start", where) if "start" in options else None
    end = _number(options["end"], "end", where) if "end" in options else None
    time_range = None
    if start is not None or end is not None:
        with malformed_gltf(path):
            clip_start, clip_end = AnimatedScene(read_gltf(path)).clip(options.get("animation")).time_range
        time_range = (clip_start if start is None else start, clip_end if end is None else end)
    try:
        return load_gltf(path, options.get("animation"), frames, time_range)
    except SpecError as error:
        raise SpecError(f"{where}: {error}") from None


def _read_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    """A mesh file's vertices and triangles as stored, for a procedural deformer."""
    if os.path.isdir(path):
        raise GeometryError(f"{path}: is a folder; bend, twist and fold deform one mesh file")
    if not os.path.isfile(path):
        raise GeometryError(f"{path}: no such file")
    return _read_frame_mesh(path)


def _parse_options(text: str, where: str) -> dict[str, str]:
    """``"a=1,b=x"`` -> ``{"a": "1", "b": "x"}``."""
    options: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, equals, value = item.partition("=")
        key, value = key.strip().lower(), value.strip()
        if not equals or not key or not value:
            raise SpecError(f"{where}: option {item!r} is not key=value")
        if key in options:
            raise SpecError(f"{where}: option {key!r} given twice")
        options[key] = value
    return options


def _number(text: str, field: str, where: str, *, integer: bool = False) -> float | int:
    """A finite number (an integer when ``integer``) from an option's text."""
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        kind = "an integer" if integer else "a number"
        raise SpecError(f"{where}: {field}: {text!r} is not {kind}") from None
    if not math.isfinite(value):
        raise SpecError(f"{where}: {field}: {text!r} is not finite")
    return value


def _value_range(text: str, frames: int, field: str, where: str) -> np.ndarray:
    """``"A..B"`` -> ``frames`` evenly spaced values from A to B, both included."""
    low, dots, high = text.partition("..")
    if not dots:
        raise SpecError(f"{where}: {field}: {text!r} is not a range A..B")
    return np.linspace(_number(low, field, where), _number(high, field, where), frames)
