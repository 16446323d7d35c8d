"""The ``"glsl"`` backend: every segment's network evaluated in one full-screen fragment pass.

The program is assembled once per scene (``shaders/transfer_pass.frag`` after
``sh_basis.glsl``, with the segments' generated GLSL), as in the paper.  Compact files
(``prt.export.glsl_compact``: a ``// prt-glsl compact 1 ...`` format line) define one function
per architecture: the program holds each distinct function once, every compact segment's texels
(``glsl_weights``) are stacked into one texture ``prt_weights``, and per segment id the uniform
arrays ``u_segment_net`` / ``u_segment_base`` give its function and first texel, so the program's
size (llvmpipe's JIT time at the first draw) does not grow with the number of segments.  Files
of the older per-segment layouts (a function and a sampler per segment) still run, through a
switch over their segment ids; analytic (unshadowed) segments evaluate the clamped cosine turned to the
normal, scaled by :func:`prt.runtime.sh.unshadowed_coeff_scale`.  The transfer is written to
the renderer's four RGBA32F targets and stays on the GPU.

With interreflection (the manifest's ``interreflection``, "direct+rgb" layout) each network gives
16 vec4 blocks (direct, indirect R, G, B); the renderer's target is then a pair of framebuffers
of 8 RGBA32F targets each.  OpenGL 3.3 guarantees only 8 draw buffers, so there the pass draws
twice (``u_part`` 0 and 1), each draw evaluating the networks and writing its 8 blocks.  Where the
context has OpenGL 4.3 (llvmpipe has 4.5, every current GPU driver too) the pass is one draw
(``PRT_ONE_PASS``): the networks run once per fragment, blocks 0..7 go to the first framebuffer's
8 targets and blocks 8..15 by ``imageStore`` into the second one's textures, bound to image
units 0..7 (a driver that refuses the program at link time gets the two draws).  Relighting runs
no network either way.

Textures: units 0 and 1 are the G-buffer; then ``prt_weights`` when a segment is compact; then
each per-segment file with a ``glsl_weights`` file (a frequency network generated with the
texture layout, or a grid-encoded network: ``prt.export.grid_onnx.table_texture``) gets the next
unit, bound to ``seg<id>_transfer_weights``.  A compact segment's weights must hold the header and
texel count its file's format line names (else one line naming the weights file).
"""

from __future__ import annotations

import re
import time

import moderngl
import numpy as np

from ...shaders import Source, assemble, source
from .. import sh
from ..checks import count_nonfinite, read_text
from ..errors import InputError
from ..gl import ShaderCompileError, compile_program
from ..deformation import code_bias, load_code_arrays
from .base import TransferBackend, draw_transfer

__all__ = ["GlslBackend"]


class GlslBackend(TransferBackend):
    """All network segments' generated GLSL in one full-screen program, compiled once per scene.

    Timings: ``network`` (the transfer pass, finished).  ``compile_s`` is the compile time,
    ``source_chars`` the program's length, ``functions`` its network functions, ``one_pass``
    whether a 64-wide transfer is written in one draw (OpenGL 4.3) or two (3.3).

    ``one_pass``: None (default) takes one draw where the context has OpenGL 4.3; False forces the
    3.3 path's two draws (its tests, and the comparison of the two).
    """

    name = "glsl"

    def __init__(self, ctx, manifest, *, providers=None, threads: int | None = None, interpolate: float | None = None,
                 one_pass: bool | None = None):  # fmt: skip
        super().__init__(ctx, manifest)
        self.blocks = manifest.transfer_width // 4  # vec4 blocks per fragment: 4, or 16 with interreflection
        self.one_pass = self.blocks > 8 and ctx.version_code >= 430 and one_pass is not False
        networks, cases, self._weights, per_segment = [], [], [], []
        compact = _CompactNetworks(manifest.path, self.blocks)
        analytic_scale = sh.unshadowed_coeff_scale(4).astype(np.float32).reshape(4, 4)
        for seg in manifest.segments:
            if seg.kind == "analytic":
                compact.add_analytic(seg.id)
                cases.append(f"            case {seg.id}: prt_analytic_transfer(ns.xyz, t); break;")
                continue
            if seg.glsl is None:
                raise InputError(f"{manifest.path}: segments[{seg.id}] has no generated GLSL (needed by the glsl backend)")
            text = read_text(seg.glsl, "GLSL")
            if compact.add(seg, text):
                continue
            networks += [Source.from_file(f"// ---- {seg.glsl.name}", "transfer pass"), Source.from_file(text, str(seg.glsl))]
            cases.append(f"            case {seg.id}: seg{seg.id}_transfer(p.xyz, ns.xyz, t); break;")
            per_segment.append(f"seg{seg.id}_transfer")
            if seg.glsl_weights is None and seg.encoding == "grid":
                raise InputError(f"{manifest.path}: segments[{seg.id}] is grid-encoded but has no glsl_weights (its tables, needed by the glsl backend)")
            if seg.glsl_weights is not None:
                self._weights.append((f"seg{seg.id}_transfer_weights", _load_weights(seg.glsl_weights)))
        units = int(ctx.info.get("GL_MAX_TEXTURE_IMAGE_UNITS", 16))
        # Deformable scenes: per network, its code rows and the texel of its first bias (set_code rewrites those texels).
        self._codes = {}
        for seg in manifest.segments:
            if getattr(seg, "code", None) is not None:
                if seg.id not in compact.base:
                    raise InputError(f"{manifest.path}: segments[{seg.id}] takes a shape code but its GLSL is not compact; render with the onnx backend")
                arrays = load_code_arrays(seg.code)
                with np.load(seg.code, allow_pickle=False) as f:
                    texel = int(f["bias_texel"]) if "bias_texel" in f.files else -1
                if not 0 < texel < len(compact.texels[list(compact.base).index(seg.id)]):
                    raise InputError(f"{seg.code}: bias_texel missing or outside the segment's texels")
                self._codes[seg.id] = (arrays, compact.base[seg.id] + texel)
        if compact:
            self._weights.insert(0, ("prt_weights", compact.texture(int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 16384)))))
            networks = [*compact.sources(), *networks]
        if 2 + len(self._weights) > units:
            raise InputError(f"{manifest.path}: {len(self._weights)} segments read weight textures, this GL has {units} texture units "
                             f"(2 for the G-buffer); render with the onnx backend")  # fmt: skip
        dispatch = compact.dispatch(cases) if compact else ["        switch (segment) {", *cases, "        }"]
        defines = {"PRT_TRANSFER_BLOCKS": self.blocks} if self.blocks != 4 else {}
        if compact:
            defines["PRT_SEGMENTS"] = compact.segments
        fills = {"networks": Source.join(networks), "dispatch": "\n".join(dispatch)}
        name = f"{manifest.path.parent / 'segments'}/*.glsl (transfer pass)"
        t0 = time.perf_counter()
        if self.one_pass:
            source = assemble("sh_basis.glsl", "transfer_pass.frag", fills=fills, defines={**defines, "PRT_ONE_PASS": 1}, version=430)
            try:
                self.program = compile_program(ctx, source, name)
            except ShaderCompileError:  # a driver with fewer image units or outputs than 4.3 allows: two draws
                self.one_pass = False
        if not self.one_pass:
            source = assemble("sh_basis.glsl", "transfer_pass.frag", fills=fills, defines=defines or None)
            self.program = compile_program(ctx, source, name)
        self.compile_s = time.perf_counter() - t0
        self.source_chars = len(source)  # the program's size: what llvmpipe's JIT time follows
        self.functions = [*compact.functions, *per_segment]
        if "u_analytic_scale" in self.program:  # optimised away when no segment is analytic
            self.program["u_analytic_scale"].write(analytic_scale.tobytes())
        for name, values in compact.uniforms().items():
            if name in self.program:
                self.program[name].write(values.tobytes())
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

    def set_code(self, theta) -> None:
        """Rewrite each shape-conditioned network's first bias texels for code ``theta`` (d,): the
        code's features times the first layer's code rows, once per frame (:mod:`prt.runtime.deformation`)."""
        if not self._codes:
            return super().set_code(theta)
        weights, tex = self._weights[0][1], self._textures[0][0]  # the compact texture (H, 1024, 4), unit 2
        flat = weights.reshape(-1, 4)
        rows = set()
        for arrays, texel in self._codes.values():
            bias = code_bias(arrays, theta)
            n = -(-bias.size // 4)
            flat[texel : texel + n] = np.pad(bias, (0, 4 * n - bias.size)).reshape(n, 4)
            rows.update(range(texel // _WIDTH, (texel + n - 1) // _WIDTH + 1))
        for y in sorted(rows):
            tex.write(np.ascontiguousarray(weights[y]).tobytes(), viewport=(0, y, _WIDTH, 1))

    def run(self, gbuffer, target) -> None:
        t0 = time.perf_counter()
        textures = ((gbuffer.position_texture, 0), (gbuffer.normal_texture, 1), *self._textures)
        if self.one_pass:  # blocks 8..15 into the second framebuffer's textures, as images
            for unit, texture in enumerate(target[1].color_attachments):
                texture.bind_to_image(unit, read=False, write=True)
            draw_transfer(self.ctx, self.program, self.vao, target[0], textures)
            self.ctx.memory_barrier(moderngl.TEXTURE_FETCH_BARRIER_BIT | moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT)
        else:
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


_FORMAT = re.compile(r"// prt-glsl compact (\d+) function ([A-Za-z_][A-Za-z0-9_]*) encoding (freq|grid) outputs (\d+) header ([0-9,]+) texels (\d+)\Z")
_WIDTH = 1024  # texels per row of the scene's weight texture (PRT_WEIGHTS_WIDTH)


class _CompactNetworks:
    """The compact segments of a scene (``prt.export.glsl_compact``): one function per distinct
    architecture (segments of one architecture have the same file), the segments' texels stacked
    into one texture, and per segment its function's index and first texel (uniform arrays
    ``u_segment_net``, ``u_segment_base``; -1 marks an analytic segment, -2 one with a per-segment
    function, reached through the switch)."""

    def __init__(self, manifest_path, blocks: int):
        self.path, self.blocks = manifest_path, blocks
        self.functions: dict[str, tuple[str, object]] = {}  # name -> (text, file)
        self.net: dict[int, int] = {}
        self.base: dict[int, int] = {}
        self.texels: list[np.ndarray] = []
        self.used = 0

    def __bool__(self) -> bool:
        return bool(self.functions)

    def add_analytic(self, segment: int) -> None:
        self.net[segment] = -1

    def add(self, seg, text: str) -> bool:
        """Take a compact segment (True), or leave a per-segment one to the caller (False)."""
        head = [line for line in text.split("\n", 12)[:12] if line.startswith("// prt-glsl compact")]
        if not head:
            self.net[seg.id] = -2
            return False
        match = _FORMAT.match(head[0].rstrip())
        if match is None or match.group(1) != "1":
            raise InputError(f"{seg.glsl}: not a compact GLSL file this runtime reads ({head[0][:80]!r}); rebuild the scene with this version")
        _, name, _, outputs, header, count = match.groups()
        if int(outputs) != self.blocks:
            raise InputError(f"{seg.glsl}: the network gives {outputs} vec4 blocks, the scene's transfer has {self.blocks}")
        if name in self.functions and self.functions[name][0] != text:
            raise ShaderCompileError(f"{seg.glsl}: error: defines {name} unlike {self.functions[name][1]} (transfer pass: "
                                     "segments of one architecture share one function, so their files must be the same)")
        if seg.glsl_weights is None:
            raise InputError(f"{self.path}: segments[{seg.id}] has compact GLSL but no glsl_weights (its texels, needed by the glsl backend)")
        texels = _load_weights(seg.glsl_weights).reshape(-1, 4)
        count, expected = int(count), [float(v) for v in header.split(",")]
        if len(texels) < count or texels[0].tolist() != expected:
            found = f"{len(texels)} texels, header {texels[0].tolist()}"
            raise InputError(f"{seg.glsl_weights}: does not fit {seg.glsl.name} ({found}; expected >= {count} texels, header {expected})")
        self.functions.setdefault(name, (text, seg.glsl))
        self.net[seg.id] = list(self.functions).index(name)
        self.base[seg.id] = self.used
        self.texels.append(texels[:count])
        self.used += count
        return True

    @property
    def segments(self) -> int:
        return max(self.net) + 1

    def sources(self) -> list:
        out = [Source.from_file(source("transfer_weights.glsl"), "transfer_weights.glsl")]
        for text, path in self.functions.values():
            out += [Source.from_file(f"// ---- {path.name} (and every segment of its architecture)", "transfer pass"), Source.from_file(text, str(path))]
        return out

    def dispatch(self, cases: list[str]) -> list[str]:
        """The statements of the transfer pass's main: a compact segment's function at its base;
        analytic and per-segment ones through the switch."""
        calls = [f"            {'if' if i == 0 else 'else if'} (net == {i}) {name}(u_segment_base[segment], p.xyz, ns.xyz, t);"
                 for i, name in enumerate(self.functions)]  # fmt: skip
        legacy = [c for c in cases if "prt_analytic_transfer" not in c]
        return [
            "        int net = segment >= 0 && segment < PRT_SEGMENTS ? u_segment_net[segment] : -3;",
            "        if (net >= 0) {",
            *calls,
            "        } else if (net == -1) {",
            "            prt_analytic_transfer(ns.xyz, t);",
            *(["        } else if (net == -2) {", "            switch (segment) {", *legacy, "            }"] if legacy else []),
            "        }",
        ]

    def uniforms(self) -> dict[str, np.ndarray]:
        if not self:
            return {}
        net = np.full(self.segments, -3, np.int32)
        base = np.zeros(self.segments, np.int32)
        for s, n in self.net.items():
            net[s] = n
        for s, b in self.base.items():
            base[s] = b
        return {"u_segment_net": net, "u_segment_base": base}

    def texture(self, max_size: int) -> np.ndarray:
        """All compact segments' texels as one ``(height, 1024, 4)`` texture."""
        height = -(-self.used // _WIDTH)
        if height > max_size:
            raise InputError(f"{self.path}: the networks' weights take {self.used} texels, over this GL's {_WIDTH} x {max_size} texture; "
                             "render with the onnx backend")
        data = np.zeros((height * _WIDTH, 4), np.float32)
        data[: self.used] = np.concatenate(self.texels)
        return data.reshape(height, _WIDTH, 4)
