"""Transfer backends behind one interface (:class:`TransferBackend`), chosen by name.

- ``"onnx"`` (:mod:`.onnx`): packed per-segment inference with ONNX Runtime on the CPU (the
  analogue of the paper's CUDA path);
- ``"glsl"`` (:mod:`.glsl`): every network evaluated in a full-screen fragment pass, from GLSL
  generated out of the ONNX weights.

A new backend is one module with a :class:`TransferBackend` subclass and one entry in
:data:`_REGISTRY`.
"""

from __future__ import annotations

from ..errors import InputError
from .base import CpuTransfer, TransferBackend
from .glsl import GlslBackend
from .onnx import OnnxBackend

__all__ = ["BACKENDS", "TransferBackend", "CpuTransfer", "create_backend"]

_REGISTRY: dict[str, type[TransferBackend]] = {
    "onnx": OnnxBackend,
    "glsl": GlslBackend,
}

BACKENDS = tuple(_REGISTRY)
"""Names of the transfer backends, the default first."""


def create_backend(name: str, ctx, manifest, **options) -> TransferBackend:
    """The backend called ``name`` for a scene (see :class:`TransferBackend` for the parameters).

    Raises
    ------
    InputError
        If no backend has that name.
    """
    if name not in _REGISTRY:
        raise InputError(f"backend must be one of {BACKENDS}, got {name!r}")
    return _REGISTRY[name](ctx, manifest, **options)
