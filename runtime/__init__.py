"""prt.runtime: everything needed to render a trained scene.  Depends on numpy, onnxruntime
and moderngl only; it never imports torch (a test enforces this).

- :class:`Scene`, :class:`Renderer`  the embedding API (:mod:`prt.runtime.renderer`)
- :mod:`prt.runtime.sh`          real spherical harmonics: basis, env-map projection, rotation,
                                 Gaunt tensor, clamped-cosine and Phong band factors, windowing
- :mod:`prt.runtime.shading`     diffuse and glossy PRT shading (numpy twin of the shaders)
- :mod:`prt.runtime.manifest`    scene.json: schema validation, confined paths
- :mod:`prt.runtime.gbuffer`     the G-buffer pass (rasterised meshes, sphere-traced SDFs)
- :mod:`prt.runtime.backends`    transfer backends by name behind one interface: ``onnx`` (packed
                                 per-segment inference with ONNX Runtime), ``glsl`` (generated GLSL)
- :mod:`prt.runtime.camera`      the look-at camera, the default camera, orbits
- :mod:`prt.runtime.orbit`       turntables and camera paths to PNG, linear EXR or MP4, with median
                                 stage timings
- :mod:`prt.runtime.camera_path` camera paths: the versioned JSON of keyframes, interpolation
- :mod:`prt.runtime.background`  the env map drawn where no geometry is
- :mod:`prt.runtime.envmap`      reading HDR environment maps (.hdr, .exr)
- :mod:`prt.runtime.envmaps`     the bundled environment maps, by name
- :mod:`prt.runtime.gl`          headless OpenGL contexts (EGL), full-screen programs, the GLSL
                                 evaluation harness
- :mod:`prt.runtime.viewer`, :mod:`prt.runtime.cli`  the viewer window and ``prt-runtime``
- :mod:`prt.runtime.errors`      the exception types
- :mod:`prt.runtime.checks`      the checks of user values (finite in float32, counts, UTF-8 text)
- :mod:`prt.runtime.onnxfile`    ONNX model files checked before ONNX Runtime loads them (no external data)
"""

from .errors import (
    ArgumentTypeError,
    EnvmapError,
    FrameError,
    GeometryError,
    GLContextError,
    InputError,
    OutputError,
    PRTError,
    RendererStateError,
    SpecError,
)

__all__ = ["Scene", "Renderer", "PRTError", "InputError", "ArgumentTypeError", "GeometryError", "EnvmapError", "SpecError",
           "GLContextError", "FrameError", "RendererStateError", "OutputError"]  # fmt: skip


def __getattr__(name: str):
    # Scene and Renderer pull in moderngl; load them on first use so `prt.runtime.sh` stays light.
    if name in ("Scene", "Renderer"):
        from . import renderer

        return getattr(renderer, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
