"""Headless OpenGL contexts (EGL) and a helper that evaluates GLSL over packed inputs.

Mesa's llvmpipe through EGL is enough: no display and no GPU are needed.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from ..shaders import source as shader_source
from .errors import GLContextError

__all__ = ["create_context", "context_info", "run_fragment_program", "FRAGMENT_HEADER"]

_INSTALL_HINT = (
    "install Mesa's EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
    "or run on a machine with a GPU driver"
)

_FULLSCREEN_VERTEX = shader_source("fullscreen.vert")

FRAGMENT_HEADER = shader_source("packed_eval_header.frag")
"""Prepended by :func:`run_fragment_program` to sources without a ``#version`` line."""

# Texels per row of the packed input grid.
_GRID_WIDTH = 1024


def create_context(require: int = 330) -> moderngl.Context:
    """Create a standalone (headless) OpenGL context through EGL.

    Parameters
    ----------
    require : int
        Minimum OpenGL version as major * 100 + minor * 10 (330 = OpenGL 3.3).

    Returns
    -------
    moderngl.Context

    Raises
    ------
    GLContextError
        One line with the reason and how to get a context.
    """
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=require)
    except Exception as exc:  # moderngl raises plain Exception subclasses that vary by version
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise GLContextError(f"no OpenGL context via EGL ({reason}): {_INSTALL_HINT}") from None
    if ctx.version_code < require:
        found = ctx.version_code
        ctx.release()
        reason = f"got OpenGL version code {found}, need {require}"
        raise GLContextError(f"no OpenGL context via EGL ({reason}): {_INSTALL_HINT}")
    return ctx


def context_info(ctx: moderngl.Context) -> dict:
    """Describe a context: ``renderer``, ``version``, ``vendor`` (strings) and ``version_code``."""
    info = ctx.info
    return {
        "renderer": info.get("GL_RENDERER", ""),
        "version": info.get("GL_VERSION", ""),
        "vendor": info.get("GL_VENDOR", ""),
        "version_code": ctx.version_code,
    }


def run_fragment_program(
    ctx: moderngl.Context,
    fragment_source: str,
    inputs: np.ndarray,
    components: int = 4,
) -> np.ndarray:
    """Evaluate a fragment shader once per input row, on packed float32 textures.

    The N input rows are laid out row-major in a grid ``_GRID_WIDTH`` texels wide (row i
    at texel ``(i % width, i // width)``), bound as the float texture ``u_input``; a
    full-screen triangle is drawn into an RGBA32F framebuffer of the same size and read back.

    Without its own ``#version`` line, the source is prefixed with :data:`FRAGMENT_HEADER`,
    which declares ``uniform sampler2D u_input``, ``out vec4 f_out`` and
    ``vec4 prt_input()`` (this fragment's input, unused channels 0); the source then only
    defines ``void main()`` writing ``f_out`` (plus any functions it needs).  A source with
    ``#version`` must declare those names itself.  Blending is left disabled; the
    framebuffer bound before the call is bound again.

    Parameters
    ----------
    ctx : moderngl.Context
    fragment_source : str
        GLSL fragment shader source (see above).
    inputs : (N, K) array_like, K in 1..4
        Values per invocation, converted to float32.
    components : int
        Output channels C kept from ``f_out`` (1..4).

    Returns
    -------
    (N, C) float32 ndarray
        ``f_out`` of each invocation.

    Raises
    ------
    moderngl.Error
        If the shader does not compile or link (the message holds the compiler log).
    """
    data = np.asarray(inputs, dtype=np.float32)
    if data.ndim == 1:
        data = data[:, None]
    if data.ndim != 2 or not 1 <= data.shape[1] <= 4:
        raise ValueError(f"inputs must be (N, K) with K in 1..4, got shape {data.shape}")
    if not 1 <= components <= 4:
        raise ValueError(f"components must be in 1..4, got {components}")
    has_version = fragment_source.lstrip().startswith("#version")
    source = fragment_source if has_version else FRAGMENT_HEADER + fragment_source
    n, k = data.shape
    out = np.empty((n, components), dtype=np.float32)
    if n == 0:
        return out

    width = min(n, _GRID_WIDTH)
    rows_per_pass = max(1, min(ctx.info.get("GL_MAX_TEXTURE_SIZE", 4096), 4096))
    per_pass = width * rows_per_pass
    program = ctx.program(vertex_shader=_FULLSCREEN_VERTEX, fragment_shader=source)
    vao = ctx.vertex_array(program, [])
    previous_fbo = ctx.fbo
    ctx.disable(moderngl.BLEND)  # blending would mix f_out with the cleared target
    try:
        if "u_input" in program:
            program["u_input"] = 0
        for start in range(0, n, per_pass):
            chunk = data[start : start + per_pass]
            height = math.ceil(len(chunk) / width)
            grid = np.zeros((height * width, k), dtype=np.float32)
            grid[: len(chunk)] = chunk
            out[start : start + len(chunk)] = _draw(ctx, vao, grid, width, height)[: len(chunk), :components]
    finally:
        _rebind(ctx, previous_fbo)
        vao.release()
        program.release()
    return out


def _rebind(ctx: moderngl.Context, fbo) -> None:
    """Bind ``fbo`` again, or the default framebuffer if it is None or released.

    moderngl re-binds ``ctx.fbo`` when creating framebuffers, so leaving a released one
    there makes the next creation fail with GL_INVALID_OPERATION.
    """
    if fbo is None or isinstance(fbo.mglo, moderngl.InvalidObject):
        fbo = ctx.detect_framebuffer(0)
    fbo.use()


def _draw(ctx: moderngl.Context, vao, grid: np.ndarray, width: int, height: int) -> np.ndarray:
    """One pass of :func:`run_fragment_program`: (width * height, K) in, (width * height, 4) out."""
    texture = ctx.texture((width, height), grid.shape[1], grid.tobytes(), dtype="f4")
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    target = ctx.renderbuffer((width, height), 4, dtype="f4")
    fbo = ctx.framebuffer(color_attachments=[target])
    try:
        texture.use(0)
        fbo.use()
        fbo.viewport = (0, 0, width, height)
        vao.render(moderngl.TRIANGLES, vertices=3)
        raw = fbo.read(components=4, dtype="f4")
        return np.frombuffer(raw, dtype=np.float32).reshape(width * height, 4).copy()
    finally:
        fbo.release()
        target.release()
        texture.release()
