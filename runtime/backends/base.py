"""The interface of a transfer backend: G-buffer in, transfer out.

A backend turns the G-buffer of the current view (:class:`prt.runtime.gbuffer.GBufferPass`)
into the transfer vector of every covered pixel, in one of two places:

- on the CPU: :meth:`TransferBackend.run` returns a :class:`CpuTransfer` (the covered pixels
  and their transfer), which the renderer shades with numpy;
- on the GPU: it writes the transfer into the renderer's target framebuffer (four RGBA32F
  attachments, coefficients ``4k .. 4k+3`` in attachment ``k``, zero on background) and
  returns None; the renderer shades with ``shade_pass.frag``.

The renderer knows a backend only by its name in :data:`prt.runtime.backends.BACKENDS`; a new
one (texture-space transfer, another inference engine) is one module with a subclass of
:class:`TransferBackend` and one line in that registry.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import moderngl
import numpy as np

from ..gbuffer import GBufferPass
from ..manifest import Manifest

__all__ = ["TransferBackend", "CpuTransfer"]


@dataclass(frozen=True)
class CpuTransfer:
    """Transfer of the covered pixels of a view, computed on the CPU.

    Attributes
    ----------
    covered : (M,) int64
        Indices of the covered pixels in the image (row-major, row 0 at the top), ascending.
    transfer : (M, n) float32
        The transfer vector of each covered pixel.
    packed : (H * W, 8) float32
        The packed G-buffer the transfer came from (:meth:`GBufferPass.read_packed`; columns
        ``prt.runtime.gbuffer.PACKED_*``), for shading inputs such as normals and positions.
    """

    covered: np.ndarray
    transfer: np.ndarray
    packed: np.ndarray


class TransferBackend(ABC):
    """Computes the transfer of a view from its G-buffer.

    Parameters
    ----------
    ctx : moderngl.Context
        The renderer's context (the G-buffer's textures live in it).
    manifest : prt.runtime.manifest.Manifest
        The scene: its segments, their networks and generated GLSL.
    providers : list of str, optional
        Execution providers, for backends that run an inference engine (others ignore it).
    threads : int, optional
        CPU threads, for backends that run on the CPU (others ignore it).

    Attributes
    ----------
    timings : dict of str to float
        Milliseconds of the stages of the last :meth:`run`, in stage order (e.g. ``readback``,
        ``pack``, ``inference``, ``scatter``; or ``network``).
    """

    name: str = ""

    def __init__(self, ctx: moderngl.Context, manifest: Manifest, *, providers=None, threads: int | None = None):
        self.ctx = ctx
        self.manifest = manifest
        self.timings: dict[str, float] = {}

    @abstractmethod
    def run(self, gbuffer: GBufferPass, target: moderngl.Framebuffer) -> CpuTransfer | None:
        """Transfer of the view in ``gbuffer`` (already rendered and finished).

        Returns a :class:`CpuTransfer`, or None after writing the transfer into ``target``
        (see the module docstring); sets :attr:`timings`.
        """

    def release(self) -> None:
        """Free the backend's resources (sessions, programs, textures); it is not used again."""
