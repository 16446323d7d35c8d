"""``prt-bench --cameras FILE``: the views a JSON file gives, instead of the orbit.

The file::

    {"views": [{"eye": [x, y, z], "target": [x, y, z], "fov": 40.0, "up": [0, 1, 0]}, ...]}

in the scene's normalised space (the space of ``scene.json``'s ``camera`` and of
:mod:`prt.runtime.camera_path`'s keyframes: +Y up, the object inside [-1, 1]^3), ``fov`` the
vertical field of view in degrees, ``up`` optional (default +Y), ``fov`` optional (default
:data:`prt.runtime.camera.DEFAULT_CAMERA`'s).  Views may stand anywhere, inside a room included
(the cameras' near plane is 0.05 scene units).  :func:`load_views` reads and checks a file; a
malformed one is one :class:`~prt.runtime.errors.InputError` line naming the file and the field.
"""

from __future__ import annotations

import json
from pathlib import Path

from prt.runtime.camera import DEFAULT_CAMERA, Camera
from prt.runtime.camera_path import read_json_file
from prt.runtime.errors import InputError

__all__ = ["load_views", "views_from_dict", "camera_record", "MAX_VIEWS"]

MAX_VIEWS = 10_000
MAX_FILE_BYTES = 16 * 2**20
_KEYS = {"eye", "target", "up", "fov"}


def load_views(path) -> list[Camera]:
    """The cameras of a views file (module docstring), in order.

    Raises
    ------
    InputError
        ``"<file>: <field>: <what is wrong>"``: unreadable, not JSON, no ``views`` list, a view
        with a missing or malformed field or no usable camera.
    """
    path = Path(path)
    data = read_json_file(path, folder="a views file", large="a views file", unreadable="the views file", max_bytes=MAX_FILE_BYTES)
    return views_from_dict(data, path)


def _clip(value) -> str:
    text = json.dumps(value) if isinstance(value, (list, dict, str, int, float, bool, type(None))) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _number(value) -> bool:
    return type(value) in (int, float)


def views_from_dict(data, source=None) -> list[Camera]:
    """The cameras of parsed JSON (InputError ``"<source>: <field>: ..."``)."""
    where = f"{source}: " if source is not None else ""
    if not isinstance(data, dict):
        raise InputError(f"{where}a views file must be a JSON object with a 'views' list, got {type(data).__name__}")
    unknown = sorted(set(data) - {"views"}, key=str)
    if unknown:
        raise InputError(f"{where}{unknown[0]}: unknown field (allowed: views)")
    views = data.get("views")
    if not isinstance(views, list) or not views:
        raise InputError(f"{where}views: expected a non-empty list of views, got {_clip(views)}")
    if len(views) > MAX_VIEWS:
        raise InputError(f"{where}views: {len(views)} views, at most {MAX_VIEWS}")
    cameras = []
    for i, view in enumerate(views):
        name = f"views[{i}]"
        if not isinstance(view, dict):
            raise InputError(f"{where}{name}: expected an object with eye, target, fov (up optional), got {_clip(view)}")
        unknown = sorted(set(view) - _KEYS, key=str)
        if unknown:
            raise InputError(f"{where}{name}.{unknown[0]}: unknown field (allowed: eye, target, up, fov)")
        for key in ("eye", "target"):
            if key not in view:
                raise InputError(f"{where}{name}.{key}: missing")
        for key in ("eye", "target", "up"):
            v = view.get(key, DEFAULT_CAMERA.get(key))
            if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(_number(x) for x in v)):
                raise InputError(f"{where}{name}.{key}: expected 3 numbers, got {_clip(v)}")
        fov = view.get("fov", DEFAULT_CAMERA["fov"])
        if not _number(fov) or not 0.0 < fov < 180.0:
            raise InputError(f"{where}{name}.fov: expected a number of degrees in (0, 180), got {_clip(fov)}")
        try:
            cameras.append(Camera(view["eye"], view["target"], view.get("up", DEFAULT_CAMERA["up"]), float(fov)))
        except (InputError, TypeError, ValueError) as exc:
            raise InputError(f"{where}{name}: {' '.join(str(exc).removeprefix('Camera: ').split())}") from None
    return cameras


def camera_record(camera: Camera) -> list:
    """``[eye, target, up, fov]`` as plain numbers (settings, checkpoint keys)."""
    return [[float(x) for x in camera.eye], [float(x) for x in camera.target], [float(x) for x in camera.up], float(camera.fov_y)]
