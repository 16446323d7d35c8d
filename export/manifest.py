"""Writing the scene manifest ``scene.json``.

:func:`write_manifest` accepts the manifest as the typed model the loader returns
(:class:`prt.runtime.manifest.Manifest`, serialised by its ``to_dict``) or as a dict that may
still hold numpy values, tuples and ``PurePath`` objects, turns it into plain JSON types,
runs exactly the checks of
:func:`prt.runtime.manifest.load_manifest` (schema, semantic rules, and by default that
every referenced file exists inside the scene folder), and only then replaces the file
atomically, so a failed export never leaves a half-written or invalid manifest behind.

The JSON is indented, with keys in a fixed readable order (``format`` and ``version``
first) and short arrays such as vectors and matrix rows on one line, so two exports of the
same scene give byte-identical files.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from prt.runtime.errors import SpecError
from prt.runtime.files import atomic_write_bytes
from prt.runtime.manifest import MANIFEST_NAME, Manifest, format_field_path, validate_manifest_dict

__all__ = ["write_manifest", "relative_to_scene"]

# Keys in the order they are written, one list for every object (identifying keys such as
# id, kind and type lead); keys not listed (object ids, lighting names) follow, sorted.
_KEY_ORDER = [
    "format", "version", "id", "kind", "type", "name", "generator", "sh_bands",
    "geometry", "segmentation", "segments", "lighting", "material", "materials", "camera", "memory",
    "file", "model", "glsl", "glsl_weights", "to_source", "triangles", "objects", "kinds",
    "roots", "nodes", "leaf_segment", "axis", "split", "left", "right", "leaf",
    "bounds", "architecture", "flops_per_fragment", "weight_bytes", "samples", "validation",
    "hidden", "layers", "pos_freqs", "normal_freqs", "input_dim", "coeff_mae", "shaded_mae",
    "envmap", "sh", "rotation", "object", "albedo", "specular", "exponent", "source",
    "eye", "target", "up", "fov", "vertex_storage_bytes",
]  # fmt: skip
_KEY_RANK = {key: rank for rank, key in enumerate(_KEY_ORDER)}

# A container whose one-line form fits in this many characters is written on one line.
_ONE_LINE = 96
_INDENT = "  "


def relative_to_scene(path: str | Path, scene_dir: str | Path) -> str:
    """The POSIX path of ``path`` relative to the scene folder, as a manifest stores it.

    Parameters
    ----------
    path : str or Path
        A file inside the scene folder.  A relative path is taken relative to the current
        directory, like any file path (not relative to ``scene_dir``).
    scene_dir : str or Path
        The folder that holds (or will hold) ``scene.json``.

    Returns
    -------
    str
        E.g. ``"segments/seg000.onnx"``.

    Raises
    ------
    SpecError
        If ``path`` is not inside ``scene_dir``, is the folder itself, or is a symlink that
        resolves outside it (the loader would reject it).
    """
    scene = Path(os.path.abspath(scene_dir))
    target = Path(os.path.abspath(path))
    if not target.is_relative_to(scene) or target == scene:
        raise SpecError(f"{path}: not a file inside the scene folder {scene_dir}")
    # The loader follows symlinks, so the check on the resolved path must hold as well.
    if not target.resolve().is_relative_to(scene.resolve()):
        raise SpecError(f"{path}: resolves outside the scene folder {scene_dir} (through a symlink)")
    return target.relative_to(scene).as_posix()


def write_manifest(path: str | Path, data: Manifest | dict, *, check_files: bool = True) -> Path:
    """Validate a manifest and write it atomically.

    Parameters
    ----------
    path : str or Path
        Destination ``scene.json``, or an existing scene folder (``scene.json`` is written
        inside it).  The folder must exist.
    data : Manifest or dict
        The manifest (format version 1).  A :class:`~prt.runtime.manifest.Manifest` has its
        file paths written relative to the folder of ``path``.  In a dict, numpy scalars and
        arrays, tuples and ``PurePath`` values (written as POSIX strings) are accepted;
        integer dict keys become strings.
    check_files : bool
        Also require every referenced path to be an existing file inside the folder, as
        :func:`~prt.runtime.manifest.load_manifest` does.  Turn off only to write a
        manifest before the files it names.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    SpecError
        If the manifest is invalid (nothing is written then); the one-line message names the
        file and the field.
    OutputError
        If the file cannot be written (a full disk); no temporary file is left.
    """
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    source = str(path)
    if not path.parent.is_dir():
        raise SpecError(f"{source}: folder {path.parent} does not exist")
    if isinstance(data, Manifest):
        data = data.to_dict(root=path.parent)
    plain = _to_json(data, [], source)
    validate_manifest_dict(plain, source, root=path.parent if check_files else None)
    text = _format(_ordered(plain)) + "\n"

    atomic_write_bytes(path, text.encode("utf-8"))  # readers see the old file or the new one, never half
    return path


def _to_json(value: Any, parts: list[str | int], source: str) -> Any:
    """``value`` as plain JSON types; SpecError for non-finite numbers and unknown types."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise SpecError(f"{source}: {format_field_path(parts)}: non-finite number {value}")
        return value
    if isinstance(value, PurePath):
        return value.as_posix()
    if isinstance(value, (list, tuple)):
        return [_to_json(v, parts + [i], source) for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for key, v in value.items():
            if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
                key = str(int(key))  # object ids in segmentation.roots
            if not isinstance(key, str):
                raise SpecError(f"{source}: {format_field_path(parts)}: key {key!r} is not a string")
            out[key] = _to_json(v, parts + [key], source)
        return out
    kind = type(value).__name__
    raise SpecError(f"{source}: {format_field_path(parts)}: cannot write a {kind} to JSON")


def _key_order(key: str) -> tuple:
    """Sort key: known keys by _KEY_ORDER, then numeric keys by value, then the rest by name."""
    if key in _KEY_RANK:
        return (0, _KEY_RANK[key], "")
    if key.isdigit():
        return (1, int(key), "")
    return (2, 0, key)


def _ordered(value: Any) -> Any:
    """Copy of ``value`` with every dict's keys in write order (dicts keep insertion order)."""
    if isinstance(value, dict):
        return {k: _ordered(value[k]) for k in sorted(value, key=_key_order)}
    if isinstance(value, list):
        return [_ordered(v) for v in value]
    return value


def _dumps(value: Any) -> str:
    return json.dumps(value, ensure_ascii=False, allow_nan=False, separators=(", ", ": "))


def _format(value: Any, depth: int = 0) -> str:
    """Indented JSON of an _ordered value; containers that fit on one line stay on one line."""
    inline = _dumps(value)
    if not isinstance(value, (dict, list)) or len(_INDENT * depth + inline) <= _ONE_LINE:
        return inline
    pad = _INDENT * (depth + 1)
    if isinstance(value, dict):
        lines = [f"{pad}{_dumps(k)}: {_format(v, depth + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(lines) + "\n" + _INDENT * depth + "}"
    lines = [pad + _format(v, depth + 1) for v in value]
    return "[\n" + ",\n".join(lines) + "\n" + _INDENT * depth + "]"
