"""GLSL sources and templates, loaded by name with :func:`source`."""

from importlib import resources

__all__ = ["source"]


def source(name: str) -> str:
    """Text of the shader file ``name`` shipped in this package."""
    return resources.files(__name__).joinpath(name).read_text(encoding="utf-8")
