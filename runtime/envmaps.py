"""The environment maps shipped with the package (CC0, 256x128), by short name.

``potsdamer`` (soft overcast), ``interior`` (windows), ``studio`` (small bright sources).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["BUNDLED_ENVMAPS", "DEFAULT_ENVMAP", "bundled_envmap_path"]

BUNDLED_ENVMAPS = {
    "potsdamer": "potsdamer_platz_256.hdr",
    "interior": "st_fagans_interior_256.hdr",
    "studio": "studio_small_03_256.hdr",
}
"""Short name -> file of every bundled env map (the one list of them), the default first."""

DEFAULT_ENVMAP = next(iter(BUNDLED_ENVMAPS))
"""The light of a scene whose manifest gives none."""


def bundled_envmap_path(name: str) -> Path:
    """Path of a bundled env map by short name (see :data:`BUNDLED_ENVMAPS`)."""
    from .errors import EnvmapError

    if name not in BUNDLED_ENVMAPS:
        raise EnvmapError(f"unknown bundled env map {name!r} (known: {', '.join(BUNDLED_ENVMAPS)})")
    return Path(str(resources.files(__package__).joinpath("data", "envmaps", BUNDLED_ENVMAPS[name])))
