"""Validation of scene manifests: the JSON Schema, the semantic rules it cannot express, the
referenced paths, and the one-line messages (moved out of :mod:`prt.runtime.manifest`, which
re-exports the public names).

Every failure raises :class:`~prt.runtime.errors.SpecError` with a one-line message naming the
file and the field, e.g. ``scene.json: segments[1].kind: 'netwrk' is not one of ['network',
'analytic']``.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from importlib import resources
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
from jsonschema import Draft202012Validator
from jsonschema.exceptions import ValidationError, best_match

from .camera import DEFAULT_CAMERA, Camera
from .checks import unusable_json_number
from .errors import InputError, SpecError
from .transfer_texture import TransferTextureInfo

__all__ = ["SCENE_SCHEMA", "MANIFEST_NAME", "validate_manifest_dict", "validate_manifest_field", "format_field_path"]

MANIFEST_NAME = "scene.json"


def _load_schema() -> dict:
    """The bundled JSON Schema (package data, so it is found in wheels and zip imports too)."""
    text = resources.files("prt.runtime").joinpath("schemas", "scene.schema.json").read_text("utf-8")
    return json.loads(text)


SCENE_SCHEMA: dict = _load_schema()
_VALIDATOR = Draft202012Validator(SCENE_SCHEMA)

# Schema messages quote the offending value; a whole array in an error line helps nobody.
_MAX_MESSAGE = 200


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
    number = unusable_json_number(data)  # e.g. 1e39 where float32 is used, an integer beyond int64
    if number is not None:
        raise _fail(source, *number)
    _check_semantics(data, source)
    if root is not None:
        _resolve_paths(data, Path(root), source)


def validate_manifest_field(name: str, value: Any, source: str = MANIFEST_NAME) -> None:
    """Check one top-level field (``"material"``, ``"camera"``, ...) against its schema.

    The message of a failure is the one :func:`validate_manifest_dict` gives for the same
    field in a whole manifest, e.g. ``scene.json: material: 'albedo' is a required property``.

    Raises
    ------
    SpecError
        If ``value`` breaks the schema of field ``name``.
    """
    schema = {"$defs": SCENE_SCHEMA["$defs"], **SCENE_SCHEMA["properties"][name]}
    error = best_match(Draft202012Validator(schema).iter_errors(value))
    if error is not None:
        raise _fail(source, [name, *error.absolute_path], _schema_message(error))


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
    interreflection = data.get("interreflection")
    if interreflection is not None:  # albedos are per object: a mesh with named objects
        geometry = data["geometry"]
        if geometry["type"] != "mesh":
            raise _fail(source, ["interreflection"], "needs a mesh geometry (bounces are traced on triangles)")
        objects = geometry.get("objects") or []
        for name in interreflection["albedos"]:
            if name not in objects:
                raise _fail(source, ["interreflection", "albedos", name], f"{name!r} is not an object of the geometry ({', '.join(objects) or 'none named'})")

    deformation = data.get("deformation")
    if deformation is not None:  # every network takes the shape code
        for i, seg in enumerate(segments):
            if seg["kind"] == "network" and ("code" not in seg or (seg.get("architecture") or {}).get("code_dim") != deformation["code"]["dim"]):
                raise _fail(source, ["segments", i], f"a deformable scene's network needs a 'code' file and architecture.code_dim {deformation['code']['dim']}")
    geometry = data["geometry"]
    if geometry["type"] == "mixed":  # (the schema ties version 2 to mixed geometry)
        if len(geometry["kinds"]) != len(geometry["objects"]):
            raise _fail(source, ["geometry", "kinds"], f"expected one kind per object ({len(geometry['objects'])}), got {len(geometry['kinds'])}")

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
    if np.linalg.norm(view) < 1e-9:
        raise _fail(source, ["camera"], "eye and target coincide")
    if np.linalg.norm(np.cross(view, camera["up"])) < 1e-9 * np.linalg.norm(view):
        raise _fail(source, ["camera", "up"], "is zero or parallel to the view direction")
    # The renderer's own checks, so that a valid manifest is a scene the renderer accepts.
    try:
        Camera(camera["eye"], camera["target"], camera["up"], camera["fov"])
    except InputError as exc:
        raise _fail(source, ["camera"], str(exc)) from None
    if "sh" in lighting and bands**2 == len(lighting["sh"]):
        from .shading import Lighting  # shading pulls in the shader sources; only needed here

        try:
            Lighting.from_sh(lighting["sh"], rotation=lighting.get("rotation"))
        except InputError as exc:
            raise _fail(source, ["lighting", "sh"], str(exc)) from None


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
    keys = {"mesh": ["file"], "sdf": ["glsl"], "mixed": ["file", "glsl"]}[geometry["type"]]
    fields: list[tuple[list[str | int], str]] = [(["geometry", key], geometry[key]) for key in keys]
    for i, seg in enumerate(data["segments"]):
        fields += [(["segments", i, k], seg[k]) for k in ("model", "glsl", "glsl_weights", "code") if k in seg]
    if "deformation" in data:
        fields.append((["deformation", "file"], data["deformation"]["file"]))
    envmap = data["lighting"].get("envmap")
    if envmap is not None:
        fields.append((["lighting", "envmap"], envmap))
    return fields + TransferTextureInfo.path_fields(data)


def _resolve_inside(root: Path, rel: str, parts: list[str | int], source: str) -> Path:
    """Absolute, resolved path of ``rel`` below ``root``; SpecError unless an existing file inside."""
    if any(ord(c) < 32 for c in rel):  # a NUL byte ends the path inside the OS; line breaks hide in messages
        raise _fail(source, parts, f"path {rel!r} holds a control character (NUL, line break)")
    windows = PureWindowsPath(rel)
    if PurePosixPath(rel).is_absolute() or windows.is_absolute() or windows.drive:
        message = f"path {rel!r} is absolute; paths must be relative to the scene folder"
        raise _fail(source, parts, message)
    try:
        real_root = root.resolve()
        # resolve() follows symlinks, so a link pointing outside is caught like a '..' escape.
        target = (root / rel).resolve()
    except (OSError, RuntimeError, ValueError) as exc:  # symlink loops: RuntimeError before 3.13; ValueError: unencodable
        raise _fail(source, parts, f"cannot resolve path {rel!r} ({_one_line(exc)})") from None
    if not target.is_relative_to(real_root):
        raise _fail(source, parts, f"path {rel!r} escapes the scene folder")
    try:
        is_file = target.is_file()
    except (OSError, ValueError):
        is_file = False
    if not is_file:
        what = "is not a file" if target.exists() else "does not exist"
        raise _fail(source, parts, f"file {rel!r} {what} (scene folder {root})")
    return target


def _resolve_paths(data: dict, root: Path, source: str) -> dict[str, Path]:
    """Resolve every referenced path; keys are field paths such as ``segments[0].model``."""
    return {
        format_field_path(parts): _resolve_inside(root, rel, parts, source)
        for parts, rel in _path_fields(data)
    }
