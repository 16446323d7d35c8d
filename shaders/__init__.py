"""GLSL sources and templates, loaded by name; :func:`assemble` builds every program from them.

A program stage is assembled from files of this package, in order: the ``#version`` line,
one ``#define`` per entry of ``defines`` (the values Python owns, e.g. the tone-map ceiling
``prt.runtime.shading.TONEMAP_MAX``), then each file without its own ``#version`` line.
Generated text (a scene's networks, its SDF, a dispatch switch) goes in through named
placeholders ``${name}`` of the files, filled with :class:`string.Template`: a placeholder left
unfilled is an error, and nothing else in the text is touched.
"""

from collections.abc import Mapping
from importlib import resources
from string import Template

__all__ = ["source", "assemble", "GLSL_VERSION"]

GLSL_VERSION = 330
"""The GLSL version every program is written for (OpenGL 3.3 core)."""


def source(name: str) -> str:
    """Text of the shader file ``name`` shipped in this package."""
    return resources.files(__name__).joinpath(name).read_text(encoding="utf-8")


def assemble(*files: str, defines: Mapping[str, object] | None = None, fills: Mapping[str, str] | None = None,
             version: int | None = GLSL_VERSION) -> str:
    """One shader stage's source from files of this package.

    Parameters
    ----------
    *files : str
        Names of shader files (see :func:`source`), concatenated in this order; a file's own
        leading ``#version`` line is dropped.
    defines : mapping of str to object, optional
        ``#define NAME value`` lines after the ``#version`` line, in order; floats are written
        in the fewest digits that read back as the same number, ints and strings as they are.
    fills : mapping of str to str, optional
        Text for the files' ``${name}`` placeholders (:class:`string.Template`; the values are
        inserted as they are, never scanned for placeholders themselves).
    version : int or None
        The ``#version`` of the stage; None for a part to paste into another source.

    Returns
    -------
    str

    Raises
    ------
    KeyError
        If a file has a placeholder that ``fills`` does not give.
    """
    fills = dict(fills or {})
    lines = [] if version is None else [f"#version {version}"]
    lines += [f"#define {name} {_glsl_value(value)}" for name, value in (defines or {}).items()]
    for name in files:
        lines.append(Template(_without_version(source(name))).substitute(fills))
    return "\n".join(lines) + "\n"


def _without_version(text: str) -> str:
    """``text`` without a leading ``#version`` line (an included file must not repeat it)."""
    stripped = text.lstrip()
    return stripped.partition("\n")[2] if stripped.startswith("#version") else text


def _glsl_value(value: object) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            raise ValueError(f"no GLSL literal for {value}")
        return repr(float(value))  # the shortest decimal that reads back as this float ("1.0", "1e-05")
    return str(value)
