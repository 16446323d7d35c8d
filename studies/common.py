"""Shared by the stage-timing studies beside it: which mesh to use, and writing the figures.

A sibling script imports it as ``common`` (a script's own folder is first on ``sys.path``).
"""

from __future__ import annotations

import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # the checkout
SHARED_BUNNY = ROOT.parent / "shared" / "data" / "meshes" / "stanford_bunny_hr.obj"
BUNDLED_SPOT = ROOT / "tests" / "data" / "spot.obj"


def default_mesh(mesh: Path | None) -> Path:
    """``mesh`` if given, else the shared bunny, else (saying so) the bundled Spot."""
    if mesh is not None:
        return mesh
    if SHARED_BUNNY.is_file():
        return SHARED_BUNNY
    print(f"note: {SHARED_BUNNY} not found (no ../shared here); using the bundled Spot cow")
    return BUNDLED_SPOT


def write_figures(path: Path | None, figures: dict) -> None:
    """Write the figures as JSON (if a path is given)."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(figures, indent=2) + "\n")
