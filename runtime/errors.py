"""Exception types.  Every message is one line that names the file or field at fault.

The CLIs print ``str(error)`` and exit non-zero; library callers catch the specific type.
"""

__all__ = [
    "PRTError",
    "InputError",
    "GeometryError",
    "EnvmapError",
    "SpecError",
    "GLContextError",
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


class GLContextError(PRTError, RuntimeError):
    """No usable OpenGL context (headless EGL on Mesa is enough)."""
