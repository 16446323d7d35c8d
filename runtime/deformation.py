"""Deformable objects: the shape code, the frames, and what a new pose changes at run time.

A deformable scene (``prt-train INPUT --deform ...``) is one triangle mesh with a fixed topology
whose vertices move.  Its networks learn transfer as a function of the *rest-space* position, the
*deformed* normal and a low-dimensional shape code ``theta``::

    T = sigma(rest position, deformed normal, theta)

The shape code is the PCA of the vertex offsets ``frame - rest`` over the training frames (the
same for every source: mesh sequences, skinned or morphing glTF clips, procedural deformers).
Scenes built since issue 38 divide every component by one number, the first component's largest
magnitude on the training frames (``deformation.code.scale == "common"``), so the first spans
``[-1, 1]``, the others their share of the motion, and distances between codes are distances
between shapes; older scenes divided each component by its own (``"component"``, or no
``scale``).  The runtime does not depend on which: ``basis`` carries the scale.

The code enters the network only through its first layer: the encoded code
``g(theta) = [theta, sin(theta * w_k), cos(theta * w_k)]`` (``w_k = 2^k pi / 2``, ``k < code_freqs``)
is multiplied by the first layer's code rows, which is one vector per frame: the first hidden
layer's bias becomes ``b_0 + g(theta) @ W_code`` (:func:`code_bias`).  A network conditioned on
the shape therefore costs per fragment exactly what a static one costs, both backends evaluate it
with their static code paths (the GLSL backend rewrites the bias texels of the scene texture, the
ONNX graph takes ``code`` as a second input), and this is the same function as feeding the
concatenated features ``[f(x, n), g(theta)]`` to the first layer.

Scene files: ``deformation.npz`` holds ``rest`` (V, 3), ``frames`` (K, V, 3), ``theta`` (K, d),
``mean`` (V, 3) and ``basis`` (d, V, 3) (offset = mean + sum_i theta_i basis_i, the code's scale
folded into the basis); ``segments/segNNN_code.npz`` holds each network's ``layer0_bias``,
``code_weight`` and ``enc_code_freq``.
"""

from __future__ import annotations

import math
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import GeometryError, InputError
from .normals import corner_normals

__all__ = ["Deformation", "code_frequencies", "code_features", "code_bias", "load_code_arrays", "CODE_BASE_FREQUENCY", "MAX_CODE_DIM"]

CODE_BASE_FREQUENCY = math.pi / 2  # theta in [-1, 1] spans half a period of the lowest frequency
MAX_CODE_DIM = 16


def code_frequencies(dim: int, freqs: int) -> np.ndarray:
    """(dim, dim * freqs) float32: column ``dim * k + i`` holds ``2^k pi / 2`` on row ``i``."""
    b = np.zeros((dim, dim * freqs), dtype=np.float32)
    for k in range(freqs):
        for i in range(dim):
            b[i, dim * k + i] = (2.0**k) * CODE_BASE_FREQUENCY
    return b


def code_features(theta: np.ndarray, frequency: np.ndarray) -> np.ndarray:
    """``[theta, sin(theta @ B), cos(theta @ B)]`` (float32) of codes (..., d); ``frequency`` B (d, d F)."""
    t = np.asarray(theta, dtype=np.float32)
    a = t @ np.asarray(frequency, dtype=np.float32)
    return np.concatenate([t, np.sin(a), np.cos(a)], axis=-1).astype(np.float32)


def code_bias(arrays: dict, theta: np.ndarray) -> np.ndarray:
    """The first hidden layer's bias for code ``theta`` (d,): ``layer0_bias + g(theta) @ code_weight``."""
    g = code_features(np.asarray(theta, dtype=np.float32).reshape(1, -1), arrays["enc_code_freq"])
    return (np.asarray(arrays["layer0_bias"], np.float32) + g @ np.asarray(arrays["code_weight"], np.float32))[0]


def load_code_arrays(path) -> dict[str, np.ndarray]:
    """A segment's ``segNNN_code.npz`` (``layer0_bias``, ``code_weight``, ``enc_code_freq``), checked."""
    arrays = _read_npz(path)
    for key in ("layer0_bias", "code_weight", "enc_code_freq"):
        if key not in arrays or arrays[key].dtype.kind != "f" or not np.isfinite(arrays[key]).all():
            raise InputError(f"{path}: '{key}' missing or not finite floats")
    d = arrays["enc_code_freq"].shape[0]
    width = arrays["code_weight"].shape[0]
    if arrays["enc_code_freq"].ndim != 2 or width != d + 2 * arrays["enc_code_freq"].shape[1]:
        raise InputError(f"{path}: code_weight has {width} rows, the code's features are {d} + 2 x {arrays['enc_code_freq'].shape[1]}")
    if arrays["code_weight"].shape[1] != arrays["layer0_bias"].size:
        raise InputError(f"{path}: code_weight has {arrays['code_weight'].shape[1]} columns, layer0_bias {arrays['layer0_bias'].size} values")
    return {k: np.asarray(arrays[k], np.float32) for k in ("layer0_bias", "code_weight", "enc_code_freq")}


def _read_npz(path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise GeometryError(f"{path}: cannot read ({' '.join(str(exc).split())})") from None


@dataclass
class Deformation:
    """A deformable scene's frames and shape code (``deformation.npz``, see the module docstring).

    Attributes
    ----------
    rest : (V, 3) float32, the rest pose (the networks' position input)
    frames : (K, V, 3) float32, the recorded poses
    theta : (K, d) float32, each frame's shape code
    mean, basis : (V, 3) and (d, V, 3) float32, offsets from a code: ``mean + theta @ basis``
    """

    rest: np.ndarray
    frames: np.ndarray
    theta: np.ndarray
    mean: np.ndarray
    basis: np.ndarray
    path: Path | None = None

    @property
    def dim(self) -> int:
        return int(self.theta.shape[1])

    @property
    def frame_count(self) -> int:
        return int(self.frames.shape[0])

    @classmethod
    def load(cls, path, n_vertices: int | None = None) -> "Deformation":
        """Read and check ``deformation.npz`` (``n_vertices``: the geometry's vertex count)."""
        a = _read_npz(path)
        for key in ("rest", "frames", "theta", "mean", "basis"):
            if key not in a:
                raise GeometryError(f"{path}: no '{key}' array")
            if a[key].dtype.kind != "f" or not np.isfinite(a[key]).all():
                raise GeometryError(f"{path}: '{key}' must be finite floats")
        v = a["rest"].shape[0]
        k, d = a["theta"].shape if a["theta"].ndim == 2 else (-1, -1)
        expected = {"rest": (v, 3), "frames": (k, v, 3), "theta": (k, d), "mean": (v, 3), "basis": (d, v, 3)}
        for key, shape in expected.items():
            if a[key].shape != shape:
                raise GeometryError(f"{path}: '{key}' should have shape {shape}, found {a[key].shape}")
        if k < 1 or not 1 <= d <= MAX_CODE_DIM:
            raise GeometryError(f"{path}: needs at least one frame and 1..{MAX_CODE_DIM} code dimensions, found {k} and {d}")
        if n_vertices is not None and v != n_vertices:
            raise GeometryError(f"{path}: {v} vertices, the scene's mesh has {n_vertices}")
        return cls(*(np.ascontiguousarray(a[key], np.float32) for key in ("rest", "frames", "theta", "mean", "basis")), path=Path(path))

    def check_frame(self, frame) -> int:
        """``frame`` as an index into the recorded frames (InputError naming the range)."""
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
            raise InputError(f"frame must be an integer, got {type(frame).__name__}")
        if not 0 <= int(frame) < self.frame_count:
            raise InputError(f"frame {frame} out of range: the scene has frames 0..{self.frame_count - 1}")
        return int(frame)

    def check_theta(self, theta) -> np.ndarray:
        """``theta`` as a finite float32 (d,) code (InputError naming the expected length)."""
        try:
            t = np.asarray(theta, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(f"theta must be {self.dim} numbers, got {theta!r:.60}") from None
        if t.size != self.dim or not np.isfinite(t).all() or np.abs(t).max(initial=0) > 1e6:
            raise InputError(f"theta must be {self.dim} finite numbers of magnitude <= 1e6, got {np.array2string(t, precision=3)[:80]}")
        return t.astype(np.float32)

    def vertices_for(self, theta) -> np.ndarray:
        """(V, 3) float32 vertices of a code: the rest pose plus the PCA offsets (exact for the
        recorded frames only as far as the d components span them)."""
        t = self.check_theta(theta)
        return (self.rest + self.mean + np.tensordot(t, self.basis, axes=1)).astype(np.float32)

    def pose(self, *, frame=None, theta=None) -> tuple[np.ndarray, np.ndarray]:
        """``(vertices (V, 3), theta (d,))`` of a recorded frame or of a code (exactly one given)."""
        if (frame is None) == (theta is None):
            raise InputError("set_deformation: give exactly one of frame= or theta=")
        if frame is not None:
            i = self.check_frame(frame)
            return self.frames[i], self.theta[i]
        t = self.check_theta(theta)
        return self.vertices_for(t), t

    @staticmethod
    def normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face and corner normals of a pose (the G-buffer's and the training samples' rule)."""
        return corner_normals(np.asarray(vertices, np.float64), np.asarray(faces))
