"""GLSL emitted by an SDF node tree: the writer that nodes append to, and float literals.

Helper functions are templates in ``prt/shaders`` named ``sdf_<stem>.glsl.tmpl``; each is
instantiated with a prefixed name (``${fn}``) so several scenes can share one shader.
"""

from __future__ import annotations

import math
from functools import lru_cache
from string import Template

from ...shaders import source as shader_source

__all__ = ["GLSLWriter", "glsl_float", "glsl_vec3", "helper_template"]


def glsl_float(x: float) -> str:
    """Format a float as a GLSL literal; ``repr`` round-trips, so numpy and GLSL agree."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot write non-finite constant {x!r} to GLSL")
    return repr(x)


def glsl_vec3(v) -> str:
    """Format three floats as a GLSL ``vec3`` constructor."""
    return "vec3({}, {}, {})".format(*(glsl_float(c) for c in v))


@lru_cache(maxsize=None)
def helper_template(stem: str) -> str:
    """Text of the helper template ``shaders/sdf_<stem>.glsl.tmpl``."""
    return shader_source(f"sdf_{stem}.glsl.tmpl")


class GLSLWriter:
    """Collects the statements and helper functions of one generated GLSL SDF function.

    Nodes call :meth:`let` to append ``type name = expr;`` statements to the function body
    and :meth:`helper` / :meth:`add_helper` to declare helper functions (emitted once each,
    named ``<prefix>_<key>`` so they do not clash with other code in the shader).

    Parameters
    ----------
    prefix : str
        Prefix of every helper name (the scene function's name).
    """

    def __init__(self, prefix: str):
        self.prefix = prefix
        self.helpers: dict[str, str] = {}
        self.body: list[str] = []
        self._count = 0

    def let(self, glsl_type: str, expr: str, stem: str = "d") -> str:
        """Append ``glsl_type <new name> = expr;`` to the body and return the new name."""
        self._count += 1
        name = f"{stem}{self._count}"
        self.body.append(f"    {glsl_type} {name} = {expr};")
        return name

    def helper(self, key: str) -> str:
        """Declare the standard helper ``key`` (box, torus, capsule, smin, smax); return its name."""
        return self.add_helper(key, helper_template(key))

    def add_helper(self, key: str, template: str, **values: str) -> str:
        """Declare a helper from a template whose ``${fn}`` is its name; return that name.

        ``values`` fill the template's other placeholders (e.g. a node's constant arrays).
        """
        name = f"{self.prefix}_{key}"
        if key not in self.helpers:
            self.helpers[key] = Template(template).substitute(values, fn=name)
        return name

    def unique_key(self, stem: str) -> str:
        """A helper key not used yet, for helpers specific to one node (e.g. a polyline)."""
        i = 0
        while f"{stem}{i}" in self.helpers:
            i += 1
        return f"{stem}{i}"
