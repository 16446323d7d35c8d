"""Exception types.  Every message is one line that names the file or field at fault.

The CLIs print ``str(error)`` and exit non-zero; library callers catch the specific type.
"""

__all__ = [
    "PRTError",
    "InputError",
    "GeometryError",
    "EnvmapError",
    "SpecError",
    "OutputError",
    "GLContextError",
    "ArgumentTypeError",
    "FrameError",
    "RendererStateError",
]


class PRTError(Exception):
    """Base class of every error this package raises on purpose."""


class InputError(PRTError, ValueError):
    """A file, argument or field supplied by the user is unusable."""


class GeometryError(InputError):
    """A mesh file or SDF scene name cannot be turned into geometry."""


class EnvmapError(InputError):
    """An environment map cannot be found, read or used."""


class SpecError(InputError):
    """A build spec or manifest has a missing or wrong field."""


class OutputError(PRTError, OSError):
    """An output file cannot be written (a full disk, a read-only folder); nothing half-written is left."""


class GLContextError(PRTError, RuntimeError):
    """No usable OpenGL context (headless EGL on Mesa is enough)."""


class ArgumentTypeError(InputError, TypeError):
    """An argument of the Python API has the wrong type (e.g. a string for a size)."""


class FrameError(PRTError, RuntimeError):
    """A frame cannot be rendered correctly (a network or the lighting gives NaN or Inf):
    raised instead of returning an image with holes."""


class RendererStateError(PRTError, RuntimeError):
    """A :class:`~prt.runtime.renderer.Renderer` used after ``close()`` or from a thread other
    than the one that created it."""
