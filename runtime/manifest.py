"""The scene manifest ``scene.json``: loading, validation and the point -> segment rule.

A trained scene is a folder holding ``scene.json`` plus the files it names (geometry, one
ONNX model and GLSL file per network segment, an optional environment map).  The format is
described by the JSON Schema ``schemas/scene.schema.json`` (format version 1); the checks a
schema cannot express are made here:

- segment ids are ``0 .. S-1`` in list order;
- every index of the k-d tree is in range (roots and children -> nodes, leaves ->
  ``leaf_segment``, ``leaf_segment`` -> segments) and the nodes form trees (no cycles);
- boxes have ``min <= max``; ``lighting.sh`` has ``sh_bands**2`` rows; ``lighting.rotation``
  is a rotation; the camera's eye, target and up define a view;
- every path is relative and resolves (symlinks followed) to a file inside the scene folder.

Every failure raises :class:`~prt.runtime.errors.SpecError` with a one-line message naming
the file and the field, e.g. ``scene.json: segments[1].kind: 'netwrk' is not one of
['network', 'analytic']``.  The writer lives in :mod:`prt.export.manifest` and runs the same
checks before writing.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
from jsonschema import Draft202012Validator
from jsonschema.exceptions import ValidationError, best_match

from .camera import DEFAULT_CAMERA
from .errors import InputError, SpecError

__all__ = [
    "SCENE_SCHEMA",
    "FORMAT",
    "FORMAT_VERSION",
    "MANIFEST_NAME",
    "DEFAULT_CAMERA",
    "SegmentInfo",
    "Manifest",
    "load_manifest",
    "validate_manifest_dict",
    "segment_of",
    "format_field_path",
]

FORMAT = "prt-scene"
FORMAT_VERSION = 1
MANIFEST_NAME = "scene.json"


def _load_schema() -> dict:
    """The bundled JSON Schema (package data, so it is found in wheels and zip imports too)."""
    text = resources.files("prt.runtime").joinpath("schemas", "scene.schema.json").read_text("utf-8")
    return json.loads(text)


SCENE_SCHEMA: dict = _load_schema()
_VALIDATOR = Draft202012Validator(SCENE_SCHEMA)

# Schema messages quote the offending value; a whole array in an error line helps nobody.
_MAX_MESSAGE = 200


@dataclass
class SegmentInfo:
    """One segment of a loaded manifest.

    Attributes
    ----------
    id : int
        Segment id, equal to its index in :attr:`Manifest.segments`.
    kind : str
        ``"network"`` (an MLP gives the transfer) or ``"analytic"`` (unshadowed transfer, a
        function of the normal alone).
    model : Path or None
        Absolute, resolved path of the ONNX model; None for analytic segments.
    glsl : Path or None
        Absolute, resolved path of the generated GLSL, if any.
    glsl_weights : Path or None
        ``.npy`` (H, W, 4) float32 weight texture for GLSL generated with the texture layout.
    bounds : ndarray, shape (2, 3)
        ``[min, max]`` corners of the box the network's input encoding normalises to.
    architecture : dict or None
        ``hidden``, ``layers``, ``pos_freqs``, ``normal_freqs``, ``input_dim``; None when
        analytic.
    flops_per_fragment, weight_bytes : int
        Cost of evaluating the network per fragment and size of its weights (0 when absent).
    samples : int
        Training samples of the segment.
    validation : dict
        ``coeff_mae`` (float) and ``shaded_mae`` (dict of lighting name -> float).
    """

    id: int
    kind: str
    model: Path | None
    glsl: Path | None
    bounds: np.ndarray
    architecture: dict | None
    flops_per_fragment: int
    weight_bytes: int
    samples: int
    validation: dict
    glsl_weights: Path | None = None

    @property
    def is_network(self) -> bool:
        return self.kind == "network"


@dataclass
class Manifest:
    """A loaded, validated ``scene.json``.

    Attributes
    ----------
    path : Path
        Absolute, resolved path of the manifest file.
    root : Path
        The scene folder (``path.parent``); every referenced file lies inside it.
    name : str
        Scene name.
    generator : str or None
        What wrote the manifest, e.g. ``"prt-train 0.1.0"``.
    sh_bands : int
        SH bands of the transfer; each segment outputs ``sh_bands**2`` coefficients.
    geometry : dict
        The manifest's geometry object plus ``"path"``: the absolute, resolved path of its
        ``file`` (mesh) or ``glsl`` (sdf).
    segmentation : dict
        ``roots`` (dict of int object id -> node index), ``nodes`` (list of dicts) and
        ``leaf_segment`` (int64 ndarray); see :func:`segment_of`.
    segments : list of SegmentInfo
        Indexed by segment id.
    lighting : dict
        ``envmap`` (absolute Path or None), ``sh`` ((sh_bands**2, 3) ndarray or None) and
        ``rotation`` ((3, 3) ndarray or None).
    material : dict
        ``type`` (``"diffuse"`` or ``"glossy"``), ``albedo`` ((3,) ndarray), ``specular``
        ((3,) ndarray or None), ``exponent`` (float or None).
    camera : dict
        ``eye``, ``target``, ``up`` ((3,) ndarrays) and ``fov`` (vertical, degrees); fields
        the manifest leaves out come from :data:`DEFAULT_CAMERA`.
    memory : dict or None
        ``weight_bytes`` and ``vertex_storage_bytes``, if recorded.
    raw : dict
        The parsed JSON, unchanged.
    """

    path: Path
    root: Path
    name: str
    generator: str | None
    sh_bands: int
    geometry: dict
    segmentation: dict
    segments: list[SegmentInfo]
    lighting: dict
    material: dict
    camera: dict
    memory: dict | None
    raw: dict = field(repr=False)

    @property
    def bounds(self) -> np.ndarray:
        """(S, 2, 3) boxes of all segments, indexed by segment id."""
        return np.stack([s.bounds for s in self.segments])

    @cached_property
    def _kd_arrays(self) -> tuple[np.ndarray, ...]:
        """The k-d tree as flat arrays (axis -1 marks a leaf) for vectorised descent."""
        return kd_arrays(self.segmentation["nodes"])


def kd_arrays(nodes: list[dict]) -> tuple[np.ndarray, ...]:
    """A k-d tree's nodes as flat arrays ``(axis, split, left, right, leaf)``; axis -1 marks a leaf."""
    axis = np.array([n.get("axis", -1) for n in nodes], dtype=np.int64)
    split = np.array([n.get("split", 0.0) for n in nodes], dtype=np.float64)
    left = np.array([n.get("left", -1) for n in nodes], dtype=np.int64)
    right = np.array([n.get("right", -1) for n in nodes], dtype=np.int64)
    leaf = np.array([n.get("leaf", -1) for n in nodes], dtype=np.int64)
    return axis, split, left, right, leaf


def assign_segments(kd: tuple[np.ndarray, ...], roots: dict[int, int], leaf_segment: np.ndarray,
                    bounds: np.ndarray, points: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The segment rule shared by training and runtime (see :func:`segment_of`).

    kd : :func:`kd_arrays` of the nodes; roots : object id -> root node; leaf_segment : (L,);
    bounds : (S, 2, 3) segment boxes; points : (N, 3) float64; ids : (N,) int -> (N,) int64
    """
    axis, split, left, right, leaf = kd
    node = np.full(len(points), -1, dtype=np.int64)
    for obj, root in roots.items():
        node[ids == obj] = root
    # One tree level per pass over the points still at inner nodes; validation ruled out cycles.
    active = np.flatnonzero(node >= 0)
    while active.size:
        current = node[active]
        inner = axis[current] >= 0
        active, current = active[inner], current[inner]
        go_left = points[active, axis[current]] <= split[current]
        node[active] = np.where(go_left, left[current], right[current])

    out = np.empty(len(points), dtype=np.int64)
    rooted = node >= 0
    out[rooted] = np.asarray(leaf_segment)[leaf[node[rooted]]]
    if not rooted.all():
        p = points[~rooted][:, None, :]
        gap = np.maximum(bounds[None, :, 0] - p, 0.0) + np.maximum(p - bounds[None, :, 1], 0.0)
        out[~rooted] = np.argmin(np.linalg.norm(gap, axis=2), axis=1)
    return out


# --------------------------------------------------------------------------- messages


def format_field_path(parts: Iterable[str | int]) -> str:
    """Readable path of a field: ``["segments", 2, "id"]`` -> ``segments[2].id``.

    Keys that are not identifiers (object ids in ``segmentation.roots``, lighting names) are
    quoted: ``segmentation.roots["0"]``.
    """
    out = ""
    for part in parts:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part.isidentifier():
            out += f".{part}" if out else part
        else:
            out += f"[{json.dumps(part)}]"
    return out or "(top level)"


def _one_line(text: object, limit: int = _MAX_MESSAGE) -> str:
    """Collapse whitespace so the message is one line, and clip it to ``limit`` characters."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _fail(source: str, parts: Iterable[str | int], message: str) -> SpecError:
    """The one-line error for ``message`` about field ``parts`` of manifest ``source``."""
    return SpecError(f"{source}: {format_field_path(parts)}: {message}")


def _schema_message(error: ValidationError) -> str:
    """Message of one schema error, friendlier than jsonschema's for forbidden fields."""
    if error.validator == "not" and error.validator_value == {}:
        # The schema forbids a field with {"not": {}} only for analytic segments' network fields.
        return "not allowed here (analytic segments have no network)"
    return _one_line(error.message)


# --------------------------------------------------------------------------- validation


def validate_manifest_dict(
    data: Any, source: str = MANIFEST_NAME, root: str | Path | None = None
) -> None:
    """Check an in-memory manifest against the schema and the semantic rules.

    Parameters
    ----------
    data : dict
        Parsed manifest (plain JSON types).
    source : str
        Name used at the start of error messages (the manifest's file name or path).
    root : str or Path, optional
        The scene folder.  When given, every referenced path must also resolve to an
        existing file inside it.

    Raises
    ------
    SpecError
        On the first problem found, with a one-line message naming ``source`` and the field.
    """
    error = best_match(_VALIDATOR.iter_errors(data))
    if error is not None:
        raise _fail(source, error.absolute_path, _schema_message(error))
    _check_semantics(data, source)
    if root is not None:
        _resolve_paths(data, Path(root), source)


def _check_semantics(data: dict, source: str) -> None:
    """The rules the schema cannot express; ``data`` already satisfies the schema."""
    segments = data["segments"]
    for i, seg in enumerate(segments):
        if seg["id"] != i:
            message = f"expected {i} (ids are 0..{len(segments) - 1} in order), got {seg['id']}"
            raise _fail(source, ["segments", i, "id"], message)
        lo, hi = np.asarray(seg["bounds"], dtype=np.float64)
        if np.any(lo > hi):
            message = f"min corner {lo.tolist()} exceeds max corner {hi.tolist()}"
            raise _fail(source, ["segments", i, "bounds"], message)
    _check_tree(data["segmentation"], len(segments), source)

    lighting = data["lighting"]
    bands = data["sh_bands"]
    if "sh" in lighting and len(lighting["sh"]) != bands**2:
        message = f"expected {bands**2} rows (sh_bands {bands}), got {len(lighting['sh'])}"
        raise _fail(source, ["lighting", "sh"], message)
    if "rotation" in lighting:
        r = np.asarray(lighting["rotation"], dtype=np.float64)
        if not (np.allclose(r @ r.T, np.eye(3), atol=1e-4) and np.linalg.det(r) > 0):
            message = "not a rotation matrix (orthonormal, determinant +1)"
            raise _fail(source, ["lighting", "rotation"], message)

    camera = {**DEFAULT_CAMERA, **data.get("camera", {})}
    view = np.subtract(camera["target"], camera["eye"], dtype=np.float64)
    up = np.asarray(camera["up"], dtype=np.float64)
    if np.linalg.norm(view) < 1e-9:
        raise _fail(source, ["camera"], "eye and target coincide")
    if np.linalg.norm(np.cross(view, up)) < 1e-9 * np.linalg.norm(view):
        raise _fail(source, ["camera", "up"], "is zero or parallel to the view direction")


def _check_tree(seg: dict, n_segments: int, source: str) -> None:
    """Indices of the k-d tree are in range and every root spans a proper tree."""
    nodes, leaf_segment = seg["nodes"], seg["leaf_segment"]
    base: list[str | int] = ["segmentation"]
    for j, s in enumerate(leaf_segment):
        if s >= n_segments:
            message = f"segment {s} does not exist (there are {n_segments})"
            raise _fail(source, base + ["leaf_segment", j], message)
    for i, node in enumerate(nodes):
        if "leaf" in node:
            if node["leaf"] >= len(leaf_segment):
                message = f"leaf {node['leaf']} does not exist (leaf_segment has {len(leaf_segment)})"
                raise _fail(source, base + ["nodes", i, "leaf"], message)
            continue
        for child in ("left", "right"):
            if node[child] >= len(nodes):
                message = f"node {node[child]} does not exist (there are {len(nodes)})"
                raise _fail(source, base + ["nodes", i, child], message)
    for key, root in seg["roots"].items():
        if root >= len(nodes):
            message = f"node {root} does not exist (there are {len(nodes)})"
            raise _fail(source, base + ["roots", key], message)

    # A node reached twice means a cycle (descent would never end) or a shared subtree.
    seen = np.zeros(len(nodes), dtype=bool)
    for key, root in seg["roots"].items():
        stack = [(root, base + ["roots", key])]
        while stack:
            index, parts = stack.pop()
            if seen[index]:
                message = f"node {index} is reached twice; nodes must form trees (no cycles, no sharing)"
                raise _fail(source, parts, message)
            seen[index] = True
            node = nodes[index]
            if "leaf" not in node:
                stack.extend((node[c], base + ["nodes", index, c]) for c in ("left", "right"))


# --------------------------------------------------------------------------- paths


def _path_fields(data: dict) -> list[tuple[list[str | int], str]]:
    """(field path, relative path) of every file the manifest references."""
    geometry = data["geometry"]
    key = "file" if geometry["type"] == "mesh" else "glsl"
    fields: list[tuple[list[str | int], str]] = [(["geometry", key], geometry[key])]
    for i, seg in enumerate(data["segments"]):
        fields += [(["segments", i, k], seg[k]) for k in ("model", "glsl", "glsl_weights") if k in seg]
    envmap = data["lighting"].get("envmap")
    if envmap is not None:
        fields.append((["lighting", "envmap"], envmap))
    return fields


def _resolve_inside(root: Path, rel: str, parts: list[str | int], source: str) -> Path:
    """Absolute, resolved path of ``rel`` below ``root``; SpecError unless an existing file inside."""
    windows = PureWindowsPath(rel)
    if PurePosixPath(rel).is_absolute() or windows.is_absolute() or windows.drive:
        message = f"path {rel!r} is absolute; paths must be relative to the scene folder"
        raise _fail(source, parts, message)
    try:
        real_root = root.resolve()
        # resolve() follows symlinks, so a link pointing outside is caught like a '..' escape.
        target = (root / rel).resolve()
    except (OSError, RuntimeError) as exc:  # symlink loops: RuntimeError before Python 3.13
        raise _fail(source, parts, f"cannot resolve path {rel!r} ({_one_line(exc)})") from None
    if not target.is_relative_to(real_root):
        raise _fail(source, parts, f"path {rel!r} escapes the scene folder")
    if not target.is_file():
        what = "is not a file" if target.exists() else "does not exist"
        raise _fail(source, parts, f"file {rel!r} {what} (scene folder {root})")
    return target


def _resolve_paths(data: dict, root: Path, source: str) -> dict[str, Path]:
    """Resolve every referenced path; keys are field paths such as ``segments[0].model``."""
    return {
        format_field_path(parts): _resolve_inside(root, rel, parts, source)
        for parts, rel in _path_fields(data)
    }


# --------------------------------------------------------------------------- loading


class _JSONValueError(Exception):
    """Raised from json hooks: a value that parses but that a manifest must not hold."""


def _reject_constant(name: str) -> None:
    raise _JSONValueError(f"non-finite number {name} is not allowed")


def _object_without_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    # json keeps the last of duplicated keys silently; in a hand-edited manifest that hides mistakes.
    obj: dict = {}
    for key, value in pairs:
        if key in obj:
            raise _JSONValueError(f"duplicate key {key!r}")
        obj[key] = value
    return obj


def _read_json(path: Path, source: str) -> Any:
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise SpecError(f"{source}: manifest not found") from None
    except UnicodeDecodeError as exc:
        raise SpecError(f"{source}: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise SpecError(f"{source}: cannot read manifest ({_one_line(exc.strerror or exc)})") from None
    try:
        return json.loads(
            text, parse_constant=_reject_constant, object_pairs_hook=_object_without_duplicates
        )
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno}, column {exc.colno}"
        raise SpecError(f"{source}: invalid JSON at {where}: {exc.msg}") from None
    except _JSONValueError as exc:
        raise SpecError(f"{source}: invalid manifest JSON: {exc}") from None


def load_manifest(path: str | Path) -> Manifest:
    """Read, validate and resolve a scene manifest.

    Parameters
    ----------
    path : str or Path
        The ``scene.json`` file, or the scene folder holding it.

    Returns
    -------
    Manifest
        With every referenced path resolved to an absolute path inside the scene folder.

    Raises
    ------
    SpecError
        If the file is missing or not JSON (line and column given), breaks the schema or a
        semantic rule, or references a path that is absolute, escapes the folder (also via a
        symlink) or does not exist.  The message is one line naming the file and the field.
    """
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    source = str(path)
    data = _read_json(path, source)
    validate_manifest_dict(data, source)
    resolved = path.resolve()
    root = resolved.parent
    files = _resolve_paths(data, root, source)

    geometry = dict(data["geometry"])
    geometry["path"] = files[f"geometry.{'file' if geometry['type'] == 'mesh' else 'glsl'}"]

    seg = data["segmentation"]
    segmentation = {
        "roots": {int(k): v for k, v in seg["roots"].items()},
        "nodes": [dict(n) for n in seg["nodes"]],
        "leaf_segment": np.asarray(seg["leaf_segment"], dtype=np.int64),
    }

    segments = [
        SegmentInfo(
            id=s["id"],
            kind=s["kind"],
            model=files.get(f"segments[{i}].model"),
            glsl=files.get(f"segments[{i}].glsl"),
            glsl_weights=files.get(f"segments[{i}].glsl_weights"),
            bounds=np.asarray(s["bounds"], dtype=np.float64),
            architecture=dict(s["architecture"]) if "architecture" in s else None,
            flops_per_fragment=s.get("flops_per_fragment", 0),
            weight_bytes=s.get("weight_bytes", 0),
            samples=s["samples"],
            validation={
                "coeff_mae": s["validation"]["coeff_mae"],
                "shaded_mae": dict(s["validation"]["shaded_mae"]),
            },
        )
        for i, s in enumerate(data["segments"])
    ]

    light = data["lighting"]
    lighting = {
        "envmap": files.get("lighting.envmap"),
        "sh": np.asarray(light["sh"], dtype=np.float64) if "sh" in light else None,
        "rotation": np.asarray(light["rotation"], dtype=np.float64) if "rotation" in light else None,
    }

    mat = data["material"]
    material = {
        "type": mat["type"],
        "albedo": np.asarray(mat["albedo"], dtype=np.float64),
        "specular": np.asarray(mat["specular"], dtype=np.float64) if "specular" in mat else None,
        "exponent": float(mat["exponent"]) if "exponent" in mat else None,
    }

    cam = {**DEFAULT_CAMERA, **data.get("camera", {})}
    camera = {k: np.asarray(cam[k], dtype=np.float64) for k in ("eye", "target", "up")}
    camera["fov"] = float(cam["fov"])

    return Manifest(
        path=resolved,
        root=root,
        name=data["name"],
        generator=data.get("generator"),
        sh_bands=data["sh_bands"],
        geometry=geometry,
        segmentation=segmentation,
        segments=segments,
        lighting=lighting,
        material=material,
        camera=camera,
        memory=dict(data["memory"]) if "memory" in data else None,
        raw=data,
    )


# --------------------------------------------------------------------------- segments


def segment_of(manifest: Manifest, points: Any, object_ids: Any) -> np.ndarray:
    """Segment of each surface point, by the manifest's k-d tree.

    From ``roots[object_id]`` the descent goes left when ``point[axis] <= split`` and right
    otherwise, down to a leaf ``i``; the segment is ``leaf_segment[i]``.  Points of an object
    with no root go to the segment whose box is nearest (Euclidean distance to the box, 0
    inside it; ties to the lowest id), the same rule as training.

    Parameters
    ----------
    manifest : Manifest
    points : array_like, shape (N, 3)
        Scene-space positions.
    object_ids : array_like of int, shape (N,)
        Object of each point.

    Returns
    -------
    ndarray of int64, shape (N,)

    Raises
    ------
    InputError
        If the shapes or the id dtype are wrong.
    """
    points = np.asarray(points, dtype=np.float64)
    ids = np.asarray(object_ids)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"segment_of: points must have shape (N, 3), got {points.shape}")
    if ids.shape != (len(points),):
        raise InputError(f"segment_of: object_ids must have shape ({len(points)},), got {ids.shape}")
    if len(ids) and ids.dtype.kind not in "iu":
        raise InputError(f"segment_of: object_ids must be integers, got dtype {ids.dtype}")

    seg = manifest.segmentation
    return assign_segments(manifest._kd_arrays, seg["roots"], seg["leaf_segment"], manifest.bounds, points, ids)
