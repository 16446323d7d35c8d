"""Headless OpenGL contexts (EGL), full-screen programs, and the one harness that evaluates
GLSL over inputs.

Mesa's llvmpipe through EGL is enough: no display and no GPU are needed.  Where a GPU is
there, headless contexts take it (:mod:`prt.runtime.gl_devices` chooses the EGL device: the
GPU, llvmpipe, or the one named by ``--gl-device`` / ``PRT_GL_DEVICE``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping

import moderngl
import numpy as np

from ..shaders import assemble
from .errors import GLContextError, PRTError
from .gl_devices import describe_devices, resolve_device

__all__ = [
    "create_context",
    "list_devices",
    "context_info",
    "compile_program",
    "draw_fullscreen",
    "bind_framebuffer",
    "run_fragment_program",
    "FlagCounter",
    "ShaderCompileError",
]

_INSTALL_HINT = (
    "install Mesa's EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
    "or run on a machine with a GPU driver"
)

_FULLSCREEN_VERTEX = assemble("fullscreen.vert")

# Texels per row of the packed input grid.
_GRID_WIDTH = 1024


class ShaderCompileError(PRTError):
    """A generated or bundled shader failed to compile; the message names the source file."""


def create_context(require: int = 330, device: str | int | None = None, *, origin: str = "gl_device") -> moderngl.Context:
    """Create a standalone (headless) OpenGL context through EGL, on the device chosen.

    Parameters
    ----------
    require : int
        Minimum OpenGL version as major * 100 + minor * 10 (330 = OpenGL 3.3).
    device : str or int, optional
        The EGL device: ``"auto"`` (the GPU where there is one, else llvmpipe), an index or a
        name matched against GL_RENDERER / GL_VENDOR (:mod:`prt.runtime.gl_devices`).  None: the
        environment variable ``PRT_GL_DEVICE``, else ``"auto"``.
    origin : str
        What ``device`` came from, for messages (``"--gl-device"``).

    Returns
    -------
    moderngl.Context
        :func:`context_info` says which renderer it is.

    Raises
    ------
    GLContextError
        One line with the reason and how to get a context.
    InputError
        ``device`` (or ``PRT_GL_DEVICE``) names no device: one line listing the devices there are.
    """

    def open_context(index):
        kwargs = {} if index is None else {"device_index": int(index)}
        return moderngl.create_standalone_context(backend="egl", require=require, **kwargs)

    try:
        ctx = resolve_device(device, open_context, origin=origin)
    except PRTError:
        raise
    except Exception as exc:  # moderngl raises plain Exception subclasses that vary by version
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise GLContextError(f"no OpenGL context via EGL ({reason}): {_INSTALL_HINT}") from None
    if ctx.version_code < require:
        found = ctx.version_code
        ctx.release()
        reason = f"got OpenGL version code {found}, need {require}"
        raise GLContextError(f"no OpenGL context via EGL ({reason}): {_INSTALL_HINT}")
    return ctx


def list_devices() -> list[dict]:
    """The EGL devices headless contexts can use, each with its GL renderer
    (:func:`prt.runtime.gl_devices.describe_devices`; a context is opened on each)."""
    return describe_devices(lambda index: moderngl.create_standalone_context(backend="egl", **({} if index is None else {"device_index": int(index)})))


def context_info(ctx: moderngl.Context) -> dict:
    """Describe a context: ``renderer``, ``version``, ``vendor`` (strings) and ``version_code``."""
    info = ctx.info
    return {
        "renderer": info.get("GL_RENDERER", ""),
        "version": info.get("GL_VERSION", ""),
        "vendor": info.get("GL_VENDOR", ""),
        "version_code": ctx.version_code,
    }


def compile_program(ctx: moderngl.Context, fragment: str, name: str, vertex: str | None = None) -> moderngl.Program:
    """Compile a full-screen program (vertex stage ``fullscreen.vert`` unless ``vertex`` is given).

    A failure becomes one :class:`ShaderCompileError` line naming ``name`` and the driver's message.
    """
    vertex = vertex or _FULLSCREEN_VERTEX
    try:
        return ctx.program(vertex_shader=vertex, fragment_shader=fragment)
    except moderngl.Error as exc:
        raise ShaderCompileError(_compile_message(str(exc), name, {"vertex_shader": vertex, "fragment_shader": fragment})) from None


# "0:12(5): error: ..." (Mesa), "0(12) : error ..." (NVIDIA), "ERROR: 0:12: ..." (AMD, ANGLE)
_LOG_LINE = re.compile(r"^\s*(?:ERROR:\s*)?\d+[:(](\d+)\)?(?:\(\d+\))?\s*:\s*(.*)$")


def _compile_message(log: str, name: str, stages: dict) -> str:
    """One line for a compiler log: the first error, at the file and line it came from.

    A stage assembled by :func:`prt.shaders.assemble` knows the ``(file, line)`` of each of its
    lines, so the error names the file a person has (a scene's ``segments/seg003.glsl``, a
    bundled shader) and its own line, not the line of the concatenated program.
    """
    stage, first = None, None
    for raw in log.splitlines():
        line = raw.strip()
        if line in stages:
            stage = line
        elif "error" in line.lower() and first is None:
            first = (stage, line)
    if first is None:
        return f"{name}: GLSL compile failed: {' '.join(log.split())[:300]}"
    stage, line = first
    match = _LOG_LINE.match(line)
    where = getattr(stages.get(stage), "where", None)
    origin = where(int(match.group(1))) if match and where else None
    if origin is None:
        return f"{name}: GLSL compile failed: {line[:300]}"
    return f"{origin[0]}:{origin[1]}: GLSL compile failed ({name}): {match.group(2)[:300]}"


def draw_fullscreen(ctx: moderngl.Context, fbo, vao, textures) -> None:
    """Clear ``fbo`` and draw one full-screen triangle with ``textures`` ((texture, unit) pairs) bound."""
    for tex, unit in textures:
        tex.use(unit)
    fbo.use()
    ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
    fbo.clear(0.0, 0.0, 0.0, 0.0)
    vao.render(moderngl.TRIANGLES, vertices=3)


def run_fragment_program(
    ctx: moderngl.Context,
    fragment: str | moderngl.Program,
    inputs,
    components: int = 4,
    *,
    attachments: int = 1,
    uniforms: Mapping[str, np.ndarray] | None = None,
    textures: Mapping[str, moderngl.Texture] | None = None,
) -> np.ndarray:
    """Evaluate a fragment shader once per input row, on packed float32 textures.

    The N input rows are laid out row-major in a grid ``_GRID_WIDTH`` texels wide (row i
    at texel ``(i % width, i // width)``), each input its own float texture; a full-screen
    triangle is drawn into RGBA32F framebuffer attachments of the same size and read back.

    A source without its own ``#version`` line is assembled into ``shaders/packed_eval.frag``,
    which declares ``uniform sampler2D u_input``, ``out vec4 f_out`` and ``vec4 prt_input()``
    (this fragment's input, unused channels 0); the source then only defines ``void main()``
    writing ``f_out`` (plus any functions it needs).  A source with ``#version`` (or a
    program) declares its samplers and outputs itself.  Blending is left disabled; the
    framebuffer bound before the call is bound again.

    Parameters
    ----------
    ctx : moderngl.Context
    fragment : str or moderngl.Program
        GLSL fragment shader source (see above), or a linked full-screen program, which
        the caller keeps (and releases).
    inputs : (N, K) array_like, K in 1..4, or mapping of str to (N, K) array_like
        Values per invocation, converted to float32: one array is bound as ``u_input``, a
        mapping binds each array to the sampler it names (texture units 0, 1, ... in order).
    components : int
        Output channels C kept, counted across the attachments (1 .. 4 * attachments).
    attachments : int
        Colour attachments the program writes (``layout(location = j)``).
    uniforms : mapping of str to ndarray, optional
        Uniform values, written as their bytes (names the compiler dropped are skipped).
    textures : mapping of str to moderngl.Texture, optional
        Further textures (e.g. network weights) bound to the samplers they name, on the
        units after the inputs; the caller keeps them.

    Returns
    -------
    (N, C) float32 ndarray
        The outputs of each invocation, attachment 0 first.

    Raises
    ------
    moderngl.Error
        If the shader does not compile or link (the message holds the compiler log).
    """
    named = dict(inputs) if isinstance(inputs, Mapping) else {"u_input": inputs}
    arrays = {}
    for name, values in named.items():
        data = np.asarray(values, dtype=np.float32)
        if data.ndim == 1:
            data = data[:, None]
        if data.ndim != 2 or not 1 <= data.shape[1] <= 4:
            raise ValueError(f"inputs must be (N, K) with K in 1..4, got shape {data.shape} for {name}")
        arrays[name] = data
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) != 1:
        raise ValueError(f"inputs must all have the same number of rows, got {sorted(lengths)}")
    if not 1 <= components <= 4 * attachments:
        raise ValueError(f"components must be in 1..{4 * attachments}, got {components}")
    n = lengths.pop()
    out = np.empty((n, components), dtype=np.float32)
    if n == 0:
        return out

    width = min(n, _GRID_WIDTH)
    rows_per_pass = max(1, min(ctx.info.get("GL_MAX_TEXTURE_SIZE", 4096), 4096))
    per_pass = width * rows_per_pass
    own_program = not isinstance(fragment, moderngl.Program)
    if own_program:
        source = fragment if fragment.lstrip().startswith("#version") else assemble("packed_eval.frag", fills={"body": fragment})
        program = ctx.program(vertex_shader=_FULLSCREEN_VERTEX, fragment_shader=source)
    else:
        program = fragment
    vao = ctx.vertex_array(program, [])
    previous_fbo = ctx.fbo
    ctx.disable(moderngl.BLEND)  # blending would mix f_out with the cleared target
    try:
        for unit, name in enumerate([*arrays, *(textures or {})]):
            if name in program:
                program[name] = unit
        for unit, texture in enumerate((textures or {}).values(), start=len(arrays)):
            texture.use(unit)
        for name, value in (uniforms or {}).items():
            if name in program:
                program[name].write(np.ascontiguousarray(value).tobytes())
        for start in range(0, n, per_pass):
            chunks = [a[start : start + per_pass] for a in arrays.values()]
            rows = len(chunks[0])
            height = math.ceil(rows / width)
            grids = []
            for chunk in chunks:
                grid = np.zeros((height * width, chunk.shape[1]), dtype=np.float32)
                grid[:rows] = chunk
                grids.append(grid)
            result = _draw(ctx, vao, grids, width, height, attachments)
            out[start : start + rows] = result[:rows, :components]
    finally:
        bind_framebuffer(ctx, previous_fbo)
        vao.release()
        if own_program:
            program.release()
    return out


class FlagCounter:
    """Counts the texels of an RGBA texture (``size``) whose alpha is above 1.5, on the GPU: the
    shade pass's mark of a broken transfer, checked without reading the frame back.  A pass keeps
    those texels only (``shaders/flag_count.frag``) and an occlusion query counts them."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]) -> None:
        self.ctx = ctx
        self.program = compile_program(ctx, assemble("flag_count.frag"), "flag_count.frag")
        self.vao = ctx.vertex_array(self.program, [])
        self.target = ctx.renderbuffer(size, 1, dtype="f1")
        self.fbo = ctx.framebuffer([self.target])
        self.query = ctx.query(samples=True)

    def count(self, texture: moderngl.Texture) -> int:
        previous = self.ctx.fbo
        try:
            texture.use(0)
            self.program["u_frame"].value = 0
            self.fbo.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            with self.query:
                self.vao.render(moderngl.TRIANGLES, vertices=3)
        finally:
            bind_framebuffer(self.ctx, previous)
        return int(self.query.samples)

    def release(self) -> None:  # the query goes with the context (moderngl's Query has no release)
        for obj in (self.fbo, self.target, self.vao, self.program):
            obj.release()


def bind_framebuffer(ctx: moderngl.Context, fbo) -> None:
    """Bind ``fbo`` again, or the default framebuffer if it is None or released.

    moderngl re-binds ``ctx.fbo`` when creating framebuffers, so leaving a released one
    there makes the next creation fail with GL_INVALID_OPERATION.
    """
    if fbo is None or isinstance(fbo.mglo, moderngl.InvalidObject):
        fbo = ctx.detect_framebuffer(0)
    fbo.use()


def _draw(ctx: moderngl.Context, vao, grids: list[np.ndarray], width: int, height: int, attachments: int) -> np.ndarray:
    """One pass of :func:`run_fragment_program`: (width * height, K) grids in, (width * height, 4 * attachments) out."""
    inputs = []
    targets = [ctx.renderbuffer((width, height), 4, dtype="f4") for _ in range(attachments)]
    fbo = ctx.framebuffer(color_attachments=targets)
    try:
        for unit, grid in enumerate(grids):
            texture = ctx.texture((width, height), grid.shape[1], grid.tobytes(), dtype="f4")
            texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
            texture.use(unit)
            inputs.append(texture)
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        vao.render(moderngl.TRIANGLES, vertices=3)
        blocks = [
            np.frombuffer(fbo.read(components=4, attachment=j, dtype="f4"), dtype=np.float32).reshape(width * height, 4)
            for j in range(attachments)
        ]
        return np.concatenate(blocks, axis=1)
    finally:
        fbo.release()
        for obj in [*targets, *inputs]:
            obj.release()
