"""prt.runtime: everything needed to render a trained scene.  Depends on numpy, onnxruntime
and moderngl only; it never imports torch (a test enforces this).

- :mod:`prt.runtime.sh`      real spherical harmonics: basis, env-map projection, rotation,
                             Gaunt tensor, clamped-cosine and Phong band factors, windowing.
- :mod:`prt.runtime.envmap`  reading HDR environment maps (.hdr, .exr).
- :mod:`prt.runtime.gl`      headless OpenGL contexts (EGL).
- :mod:`prt.runtime.errors`  the exception types.
"""

from .errors import EnvmapError, GeometryError, GLContextError, InputError, PRTError, SpecError

__all__ = ["PRTError", "InputError", "GeometryError", "EnvmapError", "SpecError", "GLContextError"]
