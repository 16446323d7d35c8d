"""GLSL sources and templates, loaded by name; :func:`assemble` builds every program from them.

A program stage is assembled from files of this package, in order: the ``#version`` line,
one ``#define`` per entry of ``defines`` (the values Python owns, e.g. the tone-map ceiling
``prt.runtime.shading.TONEMAP_MAX``), then each file without its own ``#version`` line.
Generated text (a scene's networks, its SDF, a dispatch switch) goes in through named
placeholders ``${name}`` of the files, filled with :class:`string.Template`: a placeholder left
unfilled is an error, and nothing else in the text is touched.

The assembled text is a :class:`Source`: it knows the file and line each of its lines came
from (a fill given as a Source keeps its own, e.g. a scene's ``segments/seg003.glsl``), so a
compile error names the file a person has and its own line
(:func:`prt.runtime.gl.compile_program`).
"""

from collections.abc import Mapping
from importlib import resources
from string import Template

__all__ = ["source", "assemble", "Source", "GLSL_VERSION", "GLSL_ES_VERSION"]

GLSL_VERSION = 330
"""The GLSL version every program is written for (OpenGL 3.3 core)."""

GLSL_ES_VERSION = "300 es"
"""The dialect of the web page's programs (WebGL2, :mod:`prt.export.web`): the same files, with
this ``#version`` and the precision statements GLSL ES needs (:data:`ES_PRECISION`)."""

ES_PRECISION = ("float", "int", "sampler2D", "sampler2DArray")
"""Types given ``highp`` in a GLSL ES program: a fragment stage's ints are ``mediump`` by default
(too few bits for the weight texture's texel indices) and ``sampler2DArray`` has no default."""


def source(name: str) -> str:
    """Text of the shader file ``name`` shipped in this package."""
    return resources.files(__name__).joinpath(name).read_text(encoding="utf-8")


def assemble(*files: str, defines: Mapping[str, object] | None = None, fills: Mapping[str, str] | None = None,
             version: int | str | None = GLSL_VERSION) -> str:
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
    version : int, str or None
        The ``#version`` of the stage (:data:`GLSL_VERSION`; :data:`GLSL_ES_VERSION` for WebGL2,
        which adds ``precision highp`` statements for :data:`ES_PRECISION`); None for a part to
        paste into another source.

    Returns
    -------
    Source
        The text (a str) with the ``(file, line)`` each of its lines came from.

    Raises
    ------
    KeyError
        If a file has a placeholder that ``fills`` does not give.
    """
    fills = dict(fills or {})
    lines: list[tuple[str, tuple[str, int]]] = [] if version is None else [(f"#version {version}", ("#version", 1))]
    if isinstance(version, str) and version.endswith(" es"):
        lines += [(f"precision highp {t};", ("#precision", i + 1)) for i, t in enumerate(ES_PRECISION)]
    for i, (name, value) in enumerate((defines or {}).items()):
        lines.append((f"#define {name} {_glsl_value(value)}", ("#define", i + 1)))
    for name in files:
        body, first = _without_version(source(name))
        for k, line in enumerate(body.split("\n")):
            lines += _fill_line(line, fills, (name, first + k))
    text = "\n".join(t for t, _ in lines) + "\n"
    return Source(text, [o for _, o in lines] + [lines[-1][1] if lines else ("", 0)])


class Source(str):
    """Shader text that remembers where each line came from, so that a compile error can name
    the file a person has and its own line, not the assembled program's.

    ``origins[i]`` is the ``(file, line)`` of line ``i + 1`` of the text.  :func:`assemble`
    returns one; a fill given as a Source (e.g. a scene's generated GLSL, read with
    :meth:`from_file`) keeps its own origins inside the program.
    """

    origins: tuple

    def __new__(cls, text: str, origins):
        obj = super().__new__(cls, text)
        obj.origins = tuple(origins)
        return obj

    @classmethod
    def from_file(cls, text: str, name: str, first_line: int = 1) -> "Source":
        """``text`` read from the file ``name``, its first line being line ``first_line`` there."""
        return cls(text, [(name, first_line + k) for k in range(text.count("\n") + 1)])

    @classmethod
    def join(cls, parts, separator: str = "\n") -> "Source":
        """The parts (Source or plain str) joined by ``separator``, each part's origins kept."""
        out = _Lines()
        for i, part in enumerate(parts):
            if i:
                out.add(separator, None)
            out.add(part, _origins_of(part, "<generated>"))
        return cls(out.text(), out.origins(("<generated>", 1)))

    def where(self, line: int) -> tuple[str, int] | None:
        """``(file, line)`` of line ``line`` (1-based) of this text, or None out of range."""
        return self.origins[line - 1] if 1 <= line <= len(self.origins) else None


class _Lines:
    """Text built piece by piece, each line remembering where its first non-blank character came from."""

    def __init__(self) -> None:
        self.lines: list[list] = [["", None]]

    def add(self, text: str, origin_of) -> None:
        """Append ``text``; ``origin_of(k)`` is the origin of its line ``k`` (None: unknown)."""
        for k, part in enumerate(text.split("\n")):
            if k:
                self.lines.append(["", None])
            self.lines[-1][0] += part
            if self.lines[-1][1] is None and part.strip() and origin_of is not None:
                self.lines[-1][1] = origin_of(k)

    def text(self) -> str:
        return "\n".join(t for t, _ in self.lines)

    def origins(self, default: tuple[str, int]) -> list[tuple[str, int]]:
        return [o or default for _, o in self.lines]


def _origins_of(text: str, name: str):
    """The origin of line ``k`` of a fill: its own (a Source), else ``(name, k + 1)``."""
    own = getattr(text, "origins", None)
    if own:
        return lambda k: own[min(k, len(own) - 1)]
    return lambda k: (name, k + 1)


def _fill_line(line: str, fills: Mapping[str, str], origin: tuple[str, int]) -> list[tuple[str, tuple[str, int]]]:
    """One template line with its placeholders filled, as output lines with their origins.

    A line's origin is that of its first non-blank character (the fill's own line for text that
    came in through a placeholder), else the template line's.
    """
    out = _Lines()
    pos = 0
    for m in Template.pattern.finditer(line):
        out.add(line[pos : m.start()], lambda k: origin)
        name = m.group("named") or m.group("braced")
        if name is not None:
            value = fills[name]  # KeyError for a placeholder not filled, as Template.substitute
            out.add(value, _origins_of(value, f"${{{name}}}"))
        elif m.group("escaped") is not None:
            out.add("$", lambda k: origin)
        else:
            raise ValueError(f"{origin[0]}:{origin[1]}: invalid placeholder {m.group(0)!r}")
        pos = m.end()
    out.add(line[pos:], lambda k: origin)
    return list(zip(out.text().split("\n"), out.origins(origin)))


def _without_version(text: str) -> tuple[str, int]:
    """``text`` without a leading ``#version`` line (an included file must not repeat it), and
    the line of ``text`` that the result starts at."""
    stripped = text.lstrip()
    if not stripped.startswith("#version"):
        return text, 1
    skipped = len(text) - len(stripped)
    return stripped.partition("\n")[2], text[:skipped].count("\n") + 2


def _glsl_value(value: object) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            raise ValueError(f"no GLSL literal for {value}")
        return repr(float(value))  # the shortest decimal that reads back as this float ("1.0", "1e-05")
    return str(value)
