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

__all__ = ["TransferBackend", "CpuTransfer", "draw_transfer"]


@dataclass(frozen=True)
class CpuTransfer:
    """Transfer of the covered pixels of a view, computed on the CPU.

    Attributes
    ----------
    covered : (M,) int64
        Indices of the covered pixels in the image (row-major, row 0 at the top), in the order of
        the transfer rows (any order: the ONNX backend lists them segment by segment).
    transfer : (M, n) float32
        The transfer vector of each covered pixel.
    inputs : (M, 6) float32
        Position xyz and normal xyz of each covered pixel (the networks' input), for shading.
    segment : (M,) int
        The segment id of each covered pixel (for messages).
    """

    covered: np.ndarray
    transfer: np.ndarray
    inputs: np.ndarray
    segment: np.ndarray


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
    interpolate : float, optional
        Relative transfer tolerance of screen-space interpolation (:mod:`prt.runtime.interpolation`): the
        networks run on a coarse grid and interpolation fills the rest where it is safe.  The
        ONNX backend uses it; backends that evaluate every pixel on the GPU ignore it.

    Attributes
    ----------
    timings : dict of str to float
        Milliseconds of the stages of the last :meth:`run`, in stage order (e.g. ``readback``,
        ``pack``, ``inference``; or ``network``).
    """

    name: str = ""
    on_cpu: bool = False
    """Whether :meth:`run` returns the transfer on the CPU (the frame is then shaded there)."""

    def __init__(self, ctx: moderngl.Context, manifest: Manifest, *, providers=None, threads: int | None = None, interpolate: float | None = None):
        self.ctx = ctx
        self.manifest = manifest
        self.timings: dict[str, float] = {}

    @abstractmethod
    def run(self, gbuffer: GBufferPass, target: moderngl.Framebuffer) -> CpuTransfer | None:
        """Transfer of the view in ``gbuffer`` (already rendered and finished).

        Returns a :class:`CpuTransfer`, or None after writing the transfer into ``target``
        (see the module docstring); sets :attr:`timings`.
        """

    def set_code(self, theta: np.ndarray) -> None:
        """Deformable scenes: the shape code (d,) the networks take from the next :meth:`run` on
        (:mod:`prt.runtime.deformation`).  A backend that cannot follow a deformation raises InputError."""
        from ..errors import InputError

        raise InputError(f"{self.manifest.path}: the {self.name} backend does not render deformable scenes; use onnx or glsl")

    def release(self) -> None:
        """Free the backend's resources (sessions, programs, textures); it is not used again."""


def draw_transfer(ctx, program, vao, target, textures) -> None:
    """One full-screen transfer pass into ``target``: a framebuffer, or with interreflection's 64
    values a pair of 8-target framebuffers drawn in turn (``u_part`` selects the half)."""
    from ..gl import draw_fullscreen

    if isinstance(target, (tuple, list)):
        for part, fbo in enumerate(target):
            program["u_part"].value = part
            draw_fullscreen(ctx, fbo, vao, textures)
    else:
        draw_fullscreen(ctx, target, vao, textures)
