"""Camera paths: a small versioned JSON format of keyframes, and the cameras along it.

The file (``format`` and ``version`` required, the rest as listed)::

    {
      "format": "prt-camera-path",
      "version": 1,
      "frames": 60,                    # optional: frames to render (default: one per keyframe)
      "interpolation": "linear",       # optional: "linear" (default) or "smooth" (Catmull-Rom)
      "loop": false,                   # optional: the path returns to its first keyframe
      "keyframes": [                   # at least one; scene units, fov in degrees (vertical)
        {"eye": [x, y, z], "target": [x, y, z], "up": [0, 1, 0], "fov": 40.0},
        ...
      ]
    }

``up`` and ``fov`` may be left out of a keyframe (then :data:`DEFAULT_CAMERA`'s).  Frames are
spread evenly over the keyframe intervals: without ``loop``, frame 0 is the first keyframe and
the last frame the last one (so ``frames`` = number of keyframes renders exactly the keyframes);
with ``loop``, the frames cover the closed path and the last one stops short of the first, so a
turntable repeats seamlessly.  Eye, target, up and fov are interpolated independently.

:func:`load_camera_path` reads and validates a file (one-line :class:`InputError` naming the
field), :func:`save_camera_path` writes one atomically, :func:`orbit_path` is the turntable of a
camera as a path, :class:`PathRecorder` collects the cameras of an interactive session.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .camera import DEFAULT_CAMERA, Camera, orbit_views
from .checks import _clip, positive_int, unusable_json_number
from .errors import ArgumentTypeError, InputError
from .files import atomic_write_json

__all__ = ["CameraPath", "PATH_FORMAT", "PATH_VERSION", "MAX_FRAMES", "load_camera_path", "save_camera_path",
           "orbit_path", "PathRecorder"]  # fmt: skip

PATH_FORMAT = "prt-camera-path"
PATH_VERSION = 1
INTERPOLATIONS = ("linear", "smooth")
MAX_FRAMES = 100_000  # frames and keyframes of one path (about an hour of video at 30 FPS)
MAX_FILE_BYTES = 64 * 2**20
_KEYS = {"format", "version", "frames", "interpolation", "loop", "keyframes"}
_KEYFRAME_KEYS = {"eye", "target", "up", "fov"}


@dataclass(frozen=True)
class CameraPath:
    """Keyframe cameras and how to go through them (see the module docstring)."""

    keyframes: tuple[Camera, ...]
    frames: int
    interpolation: str = "linear"
    loop: bool = False
    source: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not self.keyframes or not all(isinstance(k, Camera) for k in self.keyframes):
            raise ArgumentTypeError("CameraPath: keyframes must be a non-empty sequence of Camera")
        object.__setattr__(self, "keyframes", tuple(self.keyframes))
        positive_int(self.frames, "CameraPath: frames", maximum=MAX_FRAMES)
        if self.interpolation not in INTERPOLATIONS:
            raise InputError(f"CameraPath: interpolation must be one of {INTERPOLATIONS}, got {self.interpolation!r}")

    def cameras(self) -> list[Camera]:
        """The camera of every frame, in order (InputError naming the frame if one is degenerate)."""
        keys = np.array([[*k.eye, *k.target, *k.up, k.fov_y] for k in self.keyframes])  # (K, 10)
        n = len(keys)
        intervals = n if self.loop else n - 1
        out = []
        for i in range(self.frames):
            if intervals == 0:
                row = keys[0]
            else:
                denominator = self.frames if self.loop else max(self.frames - 1, 1)
                s = i * intervals / denominator
                j = min(int(s), intervals - 1)
                row = _interpolate(keys, j, s - j, self.loop, self.interpolation)
            try:
                out.append(Camera(row[0:3], row[3:6], row[6:9], float(row[9]), self.keyframes[0].near, self.keyframes[0].far))
            except InputError as exc:
                where = f"{self.source}: " if self.source else ""
                raise InputError(f"{where}frame {i}: the interpolated camera is unusable ({exc})") from None
        return out

    def to_dict(self) -> dict:
        keyframes = [{"eye": k.eye.tolist(), "target": k.target.tolist(), "up": k.up.tolist(), "fov": k.fov_y}
                     for k in self.keyframes]  # fmt: skip
        return {"format": PATH_FORMAT, "version": PATH_VERSION, "frames": self.frames,
                "interpolation": self.interpolation, "loop": self.loop, "keyframes": keyframes}  # fmt: skip


def _interpolate(keys: np.ndarray, j: int, t: float, loop: bool, kind: str) -> np.ndarray:
    """Keyframe rows ``j`` -> ``j + 1`` at ``t`` in [0, 1]; Catmull-Rom for ``"smooth"``."""
    n = len(keys)

    def at(k: int) -> np.ndarray:
        return keys[k % n] if loop else keys[min(max(k, 0), n - 1)]

    p1, p2 = at(j), at(j + 1)
    if kind == "linear":
        return p1 + (p2 - p1) * t
    p0, p3 = at(j - 1), at(j + 2)
    t2, t3 = t * t, t * t * t
    return 0.5 * (2 * p1 + (p2 - p0) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t2 + (3 * p1 - p0 - 3 * p2 + p3) * t3)


def orbit_path(start: Camera, frames: int) -> CameraPath:
    """The turntable of ``start`` (:func:`prt.runtime.camera.orbit_views`) as a path: one keyframe per frame."""
    frames = positive_int(frames, "--frames", maximum=MAX_FRAMES)
    return CameraPath(tuple(orbit_views(start, frames)), frames)


class PathRecorder:
    """The cameras of an interactive session (the viewer adds one per frame while the camera moves)."""

    def __init__(self, limit: int = MAX_FRAMES) -> None:
        self.limit = limit
        self.keyframes: list[Camera] = []

    def add(self, camera: Camera) -> None:
        """Keep ``camera`` unless it repeats the last one or the path is full."""
        if self.keyframes and len(self.keyframes) >= self.limit:
            return
        if self.keyframes and _same(self.keyframes[-1], camera):
            return
        self.keyframes.append(camera)

    def path(self) -> CameraPath | None:
        """The recorded path, one frame per recorded camera (None before any camera)."""
        return CameraPath(tuple(self.keyframes), len(self.keyframes)) if self.keyframes else None


def _same(a: Camera, b: Camera) -> bool:
    return bool(np.allclose(a.eye, b.eye) and np.allclose(a.target, b.target) and np.allclose(a.up, b.up)
                and math.isclose(a.fov_y, b.fov_y))  # fmt: skip


def save_camera_path(path, camera_path: CameraPath) -> Path:
    """Write ``camera_path`` as JSON to ``path`` atomically (never half a file); returns the path."""
    if not isinstance(camera_path, CameraPath):
        raise ArgumentTypeError(f"save_camera_path: expected a CameraPath, got {type(camera_path).__name__}")
    path = Path(path)
    atomic_write_json(path, camera_path.to_dict())  # OutputError, one line, on a full disk
    return path


def load_camera_path(path) -> CameraPath:
    """Read and validate a camera-path file.

    Raises
    ------
    InputError
        One line naming the file and the field: unreadable, not JSON, wrong format or
        version, a missing or malformed field, a keyframe that is no usable camera.
    """
    path = Path(path)
    data = read_json_file(path, folder="a camera-path file", large="a camera path", unreadable="the camera path")
    return camera_path_from_dict(data, path)



def read_json_file(path, *, folder: str, large: str, unreadable: str, max_bytes: int | None = None):
    """A user's small JSON file, parsed strictly (NaN and Infinity refused), or one :class:`InputError` line
    naming it: ``folder``, ``large`` and ``unreadable`` name the kind of file in those messages."""
    path = Path(path)
    max_bytes = MAX_FILE_BYTES if max_bytes is None else max_bytes
    try:
        if path.is_dir():
            raise InputError(f"{path}: is a folder, not {folder}")
        size = path.stat().st_size
        if size > max_bytes:
            raise InputError(f"{path}: {size} bytes is too large for {large} (at most {max_bytes})")
        text = path.read_bytes().decode("utf-8-sig")
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path, or undecodable bytes
        if isinstance(exc, InputError):
            raise
        reason = getattr(exc, "strerror", None) or ("not UTF-8 text" if isinstance(exc, UnicodeDecodeError) else exc)
        raise InputError(f"{path}: cannot read {unreadable} ({reason})") from None
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except (json.JSONDecodeError, RecursionError, ValueError) as exc:
        detail = f"line {exc.lineno} column {exc.colno}: {exc.msg}" if isinstance(exc, json.JSONDecodeError) else str(exc) or "too deeply nested"
        raise InputError(f"{path}: not valid JSON ({detail})") from None

def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def camera_path_from_dict(data: Any, source: Path | None = None) -> CameraPath:
    """A :class:`CameraPath` from parsed JSON (InputError ``"<source>: <field>: ..."``)."""
    where = f"{source}: " if source is not None else ""

    def fail(fieldname: str, message: str) -> InputError:
        return InputError(f"{where}{fieldname}: {message}")

    if not isinstance(data, dict):
        raise InputError(f"{where}a camera path must be a JSON object, got {type(data).__name__}")
    if data.get("format") != PATH_FORMAT:
        raise fail("format", f"expected {PATH_FORMAT!r}, got {_clip(data.get('format'))}")
    version = data.get("version")
    if type(version) is not int or version != PATH_VERSION:
        raise fail("version", f"expected {PATH_VERSION} (this runtime reads version {PATH_VERSION}), got {_clip(version)}")
    unknown = sorted(set(data) - _KEYS, key=str)
    if unknown:
        raise fail(str(unknown[0]), f"unknown field (allowed: {', '.join(sorted(_KEYS))})")
    found = unusable_json_number(data)
    if found is not None:
        name = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in found[0]).lstrip(".")
        raise fail(name or "(top level)", found[1])
    keyframes = data.get("keyframes")
    if not isinstance(keyframes, list) or not keyframes:
        raise fail("keyframes", f"expected a non-empty list of keyframes, got {_clip(keyframes)}")
    if len(keyframes) > MAX_FRAMES:
        raise fail("keyframes", f"{len(keyframes)} keyframes, at most {MAX_FRAMES}")
    cameras = [_keyframe(k, i, fail) for i, k in enumerate(keyframes)]
    frames = data.get("frames", len(cameras))
    if type(frames) is not int or not 1 <= frames <= MAX_FRAMES:
        raise fail("frames", f"expected an integer in 1..{MAX_FRAMES}, got {_clip(frames)}")
    interpolation = data.get("interpolation", "linear")
    if interpolation not in INTERPOLATIONS:
        raise fail("interpolation", f"expected one of {', '.join(INTERPOLATIONS)}, got {_clip(interpolation)}")
    loop = data.get("loop", False)
    if not isinstance(loop, bool):
        raise fail("loop", f"expected true or false, got {_clip(loop)}")
    return CameraPath(tuple(cameras), frames, interpolation, loop, source)


def _keyframe(value: Any, i: int, fail) -> Camera:
    name = f"keyframes[{i}]"
    if not isinstance(value, dict):
        raise fail(name, f"expected an object with eye, target (up, fov optional), got {_clip(value)}")
    unknown = sorted(set(value) - _KEYFRAME_KEYS, key=str)
    if unknown:
        raise fail(f"{name}.{unknown[0]}", "unknown field (allowed: eye, target, up, fov)")
    for key in ("eye", "target"):
        if key not in value:
            raise fail(f"{name}.{key}", "missing")
    for key in ("eye", "target", "up"):
        v = value.get(key, DEFAULT_CAMERA.get(key))
        if not (isinstance(v, (list, tuple)) and len(v) == 3 and all(type(x) in (int, float) for x in v)):
            raise fail(f"{name}.{key}", f"expected 3 numbers, got {_clip(v)}")
    fov = value.get("fov", DEFAULT_CAMERA["fov"])
    if type(fov) not in (int, float):
        raise fail(f"{name}.fov", f"expected a number of degrees, got {_clip(fov)}")
    try:
        return Camera(value["eye"], value["target"], value.get("up", DEFAULT_CAMERA["up"]), float(fov))
    except InputError as exc:
        raise fail(name, str(exc).removeprefix("Camera: ")) from None
