"""The ``"glsl"`` backend: every segment's network evaluated in one full-screen fragment pass.

The program is assembled once per scene (``shaders/transfer_pass.frag`` after
``sh_basis.glsl``, with each network segment's generated GLSL and a switch over segment ids),
as in the paper; analytic (unshadowed) segments evaluate the clamped cosine turned to the
normal, scaled by :func:`prt.runtime.sh.unshadowed_coeff_scale`.  The transfer is written to
the renderer's four RGBA32F targets and stays on the GPU.

With interreflection (the manifest's ``interreflection``, "direct+rgb" layout) each network gives
16 vec4 blocks (direct, indirect R, G, B); the renderer's target is then a pair of framebuffers
of 8 RGBA32F targets each, and the pass draws twice (``u_part`` 0 and 1), each draw evaluating
the networks and writing its 8 blocks: OpenGL 3.3 guarantees only 8 draw buffers.  So a
transfer pass costs two network evaluations per fragment there; relighting runs none.

Textures: units 0 and 1 are the G-buffer; each segment with a ``glsl_weights`` file (a frequency
network generated with the texture layout, or a grid-encoded network: its tables and MLP weights,
``prt.export.grid_onnx.table_texture``) gets the next unit, bound to ``seg<id>_transfer_weights``.
"""

from __future__ import annotations

import time

import moderngl
import numpy as np

from ...shaders import Source, assemble
from .. import sh
from ..checks import count_nonfinite, read_text
from ..errors import InputError
from ..gl import compile_program
from .base import TransferBackend, draw_transfer

__all__ = ["GlslBackend"]


class GlslBackend(TransferBackend):
    """All network segments' generated GLSL in one full-screen program, compiled once per scene.

    Timings: ``network`` (the transfer pass, finished).  ``compile_s`` is the compile time.
    """

    name = "glsl"

    def __init__(self, ctx, manifest, *, providers=None, threads: int | None = None):
        super().__init__(ctx, manifest)
        networks, cases, self._weights = [], [], []
        analytic_scale = sh.unshadowed_coeff_scale(4).astype(np.float32).reshape(4, 4)
        for seg in manifest.segments:
            if seg.kind == "analytic":
                cases.append(f"            case {seg.id}: prt_analytic_transfer(ns.xyz, t); break;")
                continue
            if seg.glsl is None:
                raise InputError(f"{manifest.path}: segments[{seg.id}] has no generated GLSL (needed by the glsl backend)")
            networks += [Source.from_file(f"// ---- {seg.glsl.name}", "transfer pass"), Source.from_file(read_text(seg.glsl, "GLSL"), str(seg.glsl))]
            cases.append(f"            case {seg.id}: seg{seg.id}_transfer(p.xyz, ns.xyz, t); break;")
            if seg.glsl_weights is None and seg.encoding == "grid":
                raise InputError(f"{manifest.path}: segments[{seg.id}] is grid-encoded but has no glsl_weights (its tables, needed by the glsl backend)")
            if seg.glsl_weights is not None:
                self._weights.append((f"seg{seg.id}_transfer_weights", _load_weights(seg.glsl_weights)))
        units = int(ctx.info.get("GL_MAX_TEXTURE_IMAGE_UNITS", 16))
        if 2 + len(self._weights) > units:
            raise InputError(f"{manifest.path}: {len(self._weights)} segments read weight textures, this GL has {units} texture units "
                             f"(2 for the G-buffer); render with the onnx backend")  # fmt: skip
        self.blocks = manifest.transfer_width // 4  # vec4 blocks per fragment: 4, or 16 with interreflection
        source = assemble(
            "sh_basis.glsl", "transfer_pass.frag", fills={"networks": Source.join(networks), "dispatch": "\n".join(cases)},
            defines={"PRT_TRANSFER_BLOCKS": self.blocks} if self.blocks != 4 else None,
        )
        t0 = time.perf_counter()
        self.program = compile_program(ctx, source, f"{manifest.path.parent / 'segments'}/*.glsl (transfer pass)")
        self.compile_s = time.perf_counter() - t0
        if "u_analytic_scale" in self.program:  # optimised away when no segment is analytic
            self.program["u_analytic_scale"].write(analytic_scale.tobytes())
        self.program["u_position"].value = 0
        self.program["u_normal"].value = 1
        self._textures = []
        for unit, (name, data) in enumerate(self._weights, start=2):
            tex = ctx.texture((data.shape[1], data.shape[0]), 4, data=np.ascontiguousarray(data, dtype=np.float32).tobytes(), dtype="f4")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self._textures.append((tex, unit))
            if name in self.program:
                self.program[name].value = unit
        self.vao = ctx.vertex_array(self.program, [])

    def run(self, gbuffer, target) -> None:
        t0 = time.perf_counter()
        textures = ((gbuffer.position_texture, 0), (gbuffer.normal_texture, 1), *self._textures)
        draw_transfer(self.ctx, self.program, self.vao, target, textures)
        self.ctx.finish()
        self.timings = {"network": 1e3 * (time.perf_counter() - t0)}
        return None

    def release(self) -> None:
        for tex, _ in self._textures:
            tex.release()
        self.vao.release()
        self.program.release()


def _load_weights(path) -> np.ndarray:
    """A segment's weight texture: (H, W, 4) finite float32 from a ``.npy`` (no pickles)."""
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: cannot read GLSL weights ({' '.join(str(exc).split())[:200]})") from None
    if not isinstance(data, np.ndarray) or data.ndim != 3 or data.shape[2] != 4 or data.dtype.kind != "f" or 0 in data.shape:
        what = f"{getattr(data, 'shape', '?')} {getattr(data, 'dtype', type(data).__name__)}"
        raise InputError(f"{path}: GLSL weights must be an (H, W, 4) float array, got {what}")
    weights = data.astype(np.float32)
    if count_nonfinite(weights):
        raise InputError(f"{path}: GLSL weights hold {count_nonfinite(weights)} NaN or Inf values (in float32)")
    return weights
