"""Transfer backends behind one interface (:class:`TransferBackend`), chosen by name.

- ``"onnx"`` (:mod:`.onnx`): packed per-segment inference with ONNX Runtime on the CPU (the
  analogue of the paper's CUDA path);
- ``"glsl"`` (:mod:`.glsl`): every network evaluated in a full-screen fragment pass, from GLSL
  generated out of the ONNX weights;
- ``"texture"`` (:mod:`.texture`): texture-space PRT, transfer fetched bilinearly from the
  scene's baked transfer texture (scenes built with one only).

A new backend is one module with a :class:`TransferBackend` subclass and one entry in
:data:`_REGISTRY`.
"""

from __future__ import annotations

from ..errors import InputError
from .base import CpuTransfer, TransferBackend
from .glsl import GlslBackend
from .onnx import OnnxBackend
from .texture import TextureBackend

__all__ = ["BACKENDS", "ALL_BACKENDS", "TransferBackend", "CpuTransfer", "create_backend"]

_REGISTRY: dict[str, type[TransferBackend]] = {
    "onnx": OnnxBackend,
    "glsl": GlslBackend,
    "texture": TextureBackend,
}

BACKENDS = tuple(name for name, cls in _REGISTRY.items() if getattr(cls, "requires", None) is None)
"""Names of the transfer backends that render every scene, the default first."""

ALL_BACKENDS = tuple(_REGISTRY)
"""Every backend name, also those needing what only some scenes have (``texture``: a transfer texture)."""


def create_backend(name: str, ctx, manifest, **options) -> TransferBackend:
    """The backend called ``name`` for a scene (see :class:`TransferBackend` for the parameters).

    Raises
    ------
    InputError
        If no backend has that name.
    """
    if name not in _REGISTRY:
        raise InputError(f"backend must be one of {ALL_BACKENDS}, got {name!r}")
    return _REGISTRY[name](ctx, manifest, **options)
