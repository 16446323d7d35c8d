"""A perspective look-at camera: view and projection matrices, per-pixel rays, orbiting.

Conventions (shared by every pass of the runtime):

- Matrices are row-major numpy arrays acting on column vectors (``clip = P @ V @ [p, 1]``);
  upload them to GLSL transposed (GLSL matrices are column-major).
- The projection is OpenGL's: the camera looks down its -Z axis, visible depths map to
  normalised device z in ``[-1, 1]`` (near -> -1, far -> +1).
- Images are (H, W, C) arrays with row 0 at the TOP; pixel ``(row, col)`` has its centre at
  ``ndc = ((col + 0.5) / W * 2 - 1, 1 - (row + 0.5) / H * 2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .checks import FLOAT32_MAX, check_finite, finite_array
from .errors import InputError

__all__ = ["Camera", "DEFAULT_CAMERA", "orbit_views", "walk", "walk_speed", "scene_box", "inside_bounds", "fit_near",
           "WALK_NEAR", "MAX_PITCH", "walk_info"]

# The camera of a scene whose manifest leaves fields out (scene space is [-1, 1]^3, +Y up).
DEFAULT_CAMERA: dict[str, Any] = {
    "eye": (0.0, 0.6, 3.2),
    "target": (0.0, 0.0, 0.0),
    "up": (0.0, 1.0, 0.0),
    "fov": 40.0,
}

# Relative tolerance below which two directions count as parallel.
_PARALLEL_TOL = 1e-9


def _vec3(value: Any, what: str) -> np.ndarray:
    """``value`` as a float64 (3,) array finite in float32 (the precision of the shaders' matrices),
    or an InputError naming it (ArgumentTypeError for what is not numbers)."""
    return finite_array(value, f"Camera: {what}", (3,))


def _number(value: Any, what: str) -> float:
    return float(finite_array(value, f"Camera: {what}", ()))


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about the unit ``axis`` (right-handed, Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


@dataclass(frozen=True, eq=False)
class Camera:
    """Perspective camera looking from ``eye`` at ``target``.

    Parameters
    ----------
    eye, target : array_like, shape (3,)
        Camera position and the point it looks at (scene units); they must differ.
    up : array_like, shape (3,)
        Approximate up direction; must not be parallel to ``target - eye``.
    fov_y : float
        Vertical field of view in degrees, in (0, 180).
    near, far : float
        Clip distances along the view axis, ``0 < near < far``.

    Raises
    ------
    InputError
        (a ValueError) if the parameters do not define a view in float32; ArgumentTypeError
        if they are not numbers.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_CAMERA["up"], dtype=np.float64))
    fov_y: float = DEFAULT_CAMERA["fov"]
    near: float = 0.05
    far: float = 50.0

    def __post_init__(self) -> None:
        # Frozen dataclass: normalised copies are stored through object.__setattr__.
        eye, target, up = _vec3(self.eye, "eye"), _vec3(self.target, "target"), _vec3(self.up, "up")
        view = target - eye
        distance = float(np.linalg.norm(view))
        if distance < _PARALLEL_TOL:
            raise InputError(f"Camera: eye and target coincide at {eye.tolist()}")
        if not distance <= FLOAT32_MAX:
            raise InputError(f"Camera: eye and target are too far apart ({distance:.4g}) for float32")
        if np.linalg.norm(np.cross(view, up)) <= _PARALLEL_TOL * distance * max(np.linalg.norm(up), 1.0):
            raise InputError(f"Camera: up {up.tolist()} is zero or parallel to the view direction")
        fov_y, near, far = _number(self.fov_y, "fov_y"), _number(self.near, "near"), _number(self.far, "far")
        if not 0.0 < fov_y < 180.0:
            raise InputError(f"Camera: fov_y must be in (0, 180) degrees, got {self.fov_y!r}")
        if not (0.0 < near < far and math.isfinite(far)):
            raise InputError(f"Camera: need 0 < near < far, got near={self.near!r}, far={self.far!r}")
        for name, value in (("eye", eye), ("target", target), ("up", up)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "fov_y", fov_y)
        object.__setattr__(self, "near", near)
        object.__setattr__(self, "far", far)
        check_finite(self.view_projection(1.0), "Camera: view-projection matrix (eye too far from the origin?)")

    # ----------------------------------------------------------------- construction

    @classmethod
    def from_manifest(cls, camera: Any, near: float = 0.05, far: float = 50.0) -> "Camera":
        """The camera stored in a manifest.

        Parameters
        ----------
        camera : CameraInfo or Manifest
            ``Manifest.camera`` (``eye``, ``target``, ``up``, ``fov`` in degrees), or the
            manifest itself.
        near, far : float
            Clip distances (the manifest does not store them).

        Returns
        -------
        Camera
        """
        camera = getattr(camera, "camera", camera)
        return cls(camera.eye, camera.target, camera.up, camera.fov, near, far)

    def orbit(self, angle: float, axis: Any = None) -> "Camera":
        """This camera rotated about ``target`` by ``angle`` radians.

        Parameters
        ----------
        angle : float
            Rotation angle in radians (right-handed about ``axis``).
        axis : array_like, shape (3,), optional
            Rotation axis through ``target``; defaults to ``up``.  ``eye`` and ``up`` are
            both rotated, so the distance to the target and the roll are kept.

        Returns
        -------
        Camera
        """
        axis = self.up if axis is None else _vec3(axis, "axis")
        length = float(np.linalg.norm(axis))
        if length == 0.0:
            raise InputError("Camera.orbit: axis must be non-zero")
        rot = _rotation(axis / length, float(angle))
        eye = self.target + rot @ (self.eye - self.target)
        return Camera(eye, self.target, rot @ self.up, self.fov_y, self.near, self.far)

    # ----------------------------------------------------------------- basis

    @property
    def forward(self) -> np.ndarray:
        """(3,) unit view direction, from ``eye`` towards ``target``."""
        view = self.target - self.eye
        return view / np.linalg.norm(view)

    @property
    def right(self) -> np.ndarray:
        """(3,) unit direction of increasing image column."""
        r = np.cross(self.forward, self.up)
        return r / np.linalg.norm(r)

    @property
    def true_up(self) -> np.ndarray:
        """(3,) unit direction towards the top of the image (``up`` made orthogonal to the view)."""
        return np.cross(self.right, self.forward)

    # ----------------------------------------------------------------- matrices

    def view(self) -> np.ndarray:
        """(4, 4) float64 world -> camera matrix (camera at the origin, looking down -Z, +Y up)."""
        r, u, f = self.right, self.true_up, self.forward
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = r, u, -f
        m[:3, 3] = -m[:3, :3] @ self.eye
        return m

    def projection(self, aspect: float) -> np.ndarray:
        """(4, 4) float64 OpenGL perspective matrix.

        Parameters
        ----------
        aspect : float
            Image width / height.
        """
        aspect = float(aspect)
        if not (aspect > 0.0 and math.isfinite(aspect)):
            raise InputError(f"Camera.projection: aspect must be positive, got {aspect!r}")
        f = 1.0 / math.tan(math.radians(self.fov_y) / 2.0)
        n, fa = self.near, self.far
        m = np.zeros((4, 4))
        m[0, 0] = f / aspect
        m[1, 1] = f
        m[2, 2] = (fa + n) / (n - fa)
        m[2, 3] = 2.0 * fa * n / (n - fa)
        m[3, 2] = -1.0
        return m

    def view_projection(self, aspect: float) -> np.ndarray:
        """(4, 4) float64 ``projection(aspect) @ view()``: world -> clip space."""
        return self.projection(aspect) @ self.view()

    def ray_directions(self, width: int, height: int) -> np.ndarray:
        """Unit world-space directions of the rays through the pixel centres.

        Parameters
        ----------
        width, height : int
            Image size in pixels.

        Returns
        -------
        ndarray of float64, shape (height, width, 3)
            Row 0 is the top of the image; every ray starts at ``eye``.
        """
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise InputError(f"Camera.ray_directions: size must be positive, got {width}x{height}")
        half_y = math.tan(math.radians(self.fov_y) / 2.0)
        half_x = half_y * width / height
        x = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * half_x
        y = (1.0 - (np.arange(height) + 0.5) / height * 2.0) * half_y
        d = (
            self.forward[None, None, :]
            + x[None, :, None] * self.right[None, None, :]
            + y[:, None, None] * self.true_up[None, None, :]
        )
        return d / np.linalg.norm(d, axis=2, keepdims=True)

    def __repr__(self) -> str:
        return (
            f"Camera(eye={self.eye.tolist()}, target={self.target.tolist()}, up={self.up.tolist()}, "
            f"fov_y={self.fov_y}, near={self.near}, far={self.far})"
        )


def orbit_views(start: Camera, views: int) -> list[Camera]:
    """``views`` cameras evenly spaced on a full orbit of ``start`` about its target (view 0 is ``start``)."""
    return [start.orbit(2.0 * np.pi * i / views) for i in range(views)]


# ----------------------------------------------------------------- walking (first person)

WALK_NEAR = 0.005
"""Near plane of a camera inside the scene (a walk, a path through an interior): in the normalised
scene space ([-1, 1]^3, a house ~15 m wide makes this ~4 cm), so walls and furniture next to the
eye are not clipped; the default 0.05 stays for views from outside (their pixels do not change)."""
MAX_PITCH = math.radians(89.0)
"""How far a walking camera looks up or down (just short of the vertical, where yaw is undefined)."""
WALK_SPEED = 0.1
"""Walking speed in scene-box diagonals per second (:func:`walk_speed`; the viewer's shift x4)."""


def scene_box(manifest) -> np.ndarray:
    """(2, 3) the box around all segments of a manifest (min, max), in scene units."""
    bounds = np.asarray(manifest.bounds, dtype=np.float64).reshape(-1, 2, 3)
    return np.stack([bounds[:, 0].min(axis=0), bounds[:, 1].max(axis=0)])


def inside_bounds(point, box, margin: float = 0.0) -> bool:
    """Whether ``point`` lies in ``box`` ((2, 3) min, max), grown by ``margin`` on every side."""
    p, box = np.asarray(point, dtype=np.float64), np.asarray(box, dtype=np.float64)
    return bool(np.all(p >= box[0] - margin) and np.all(p <= box[1] + margin))


def fit_near(camera: Camera, box) -> Camera:
    """``camera`` with the near plane :data:`WALK_NEAR` when its eye is inside ``box``; else itself."""
    if box is None or camera.near <= WALK_NEAR or not inside_bounds(camera.eye, box):
        return camera
    return Camera(camera.eye, camera.target, camera.up, camera.fov_y, WALK_NEAR, camera.far)


def walk_speed(box) -> float:
    """Scene units per second of a walk through ``box`` ((2, 3)): :data:`WALK_SPEED` of its diagonal."""
    box = np.asarray(box, dtype=np.float64)
    diagonal = float(np.linalg.norm(box[1] - box[0]))
    return WALK_SPEED * (diagonal if math.isfinite(diagonal) and diagonal > 0 else 2.0 * math.sqrt(3.0))


def walk(camera: Camera, move=(0.0, 0.0, 0.0), yaw: float = 0.0, pitch: float = 0.0) -> Camera:
    """One first-person step: turn, then move.

    Parameters
    ----------
    camera : Camera
        Its ``up`` is the world's up (kept); the eye-target distance is kept.
    move : (forward, right, up) scene units
        ``forward`` along the heading (the view direction flattened onto the ground plane, so
        looking down does not walk into the floor), ``right`` across it, ``up`` along ``up``.
    yaw : float
        Radians about ``up``, positive to the left (right-handed); a mouse moving right turns right
        with ``yaw = -dx * sensitivity``.
    pitch : float
        Radians up (positive) or down, the result clamped to +-:data:`MAX_PITCH`.
    """
    up = camera.up / np.linalg.norm(camera.up)
    f = camera.forward
    current = math.asin(float(np.clip(f @ up, -1.0, 1.0)))
    heading = f - (f @ up) * up
    if np.linalg.norm(heading) < 1e-9:  # looking straight along up: the image's up is the heading
        heading = camera.true_up * (-1.0 if f @ up > 0 else 1.0)
    heading = _rotation(up, float(yaw)) @ (heading / np.linalg.norm(heading))
    heading /= np.linalg.norm(heading)
    angle = float(np.clip(current + float(pitch), -MAX_PITCH, MAX_PITCH))
    forward = math.cos(angle) * heading + math.sin(angle) * up
    right = np.cross(heading, up)
    step = np.asarray(move, dtype=np.float64)
    eye = camera.eye + step[0] * heading + step[1] * right + step[2] * up
    distance = float(np.linalg.norm(camera.target - camera.eye))
    return Camera(eye, eye + forward * distance, camera.up, camera.fov_y, camera.near, camera.far)


def walk_info(manifest) -> dict:
    """The walk's figures for the web page (``web.json``'s ``camera``): the scene box, the interior
    near plane, the speed, the pitch limit, and the near plane of the manifest's camera (:func:`fit_near`)."""
    box = scene_box(manifest)
    return {"near": fit_near(Camera.from_manifest(manifest), box).near, "box": box.tolist(), "walk_near": WALK_NEAR,
            "walk_speed": walk_speed(box), "max_pitch": MAX_PITCH}
