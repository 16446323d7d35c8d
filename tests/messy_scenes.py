"""Small synthetic scenes with what real scene files carry (tests/test_messy_geometry.py).

Each function writes one file into a folder and returns its path.  Boxes are written as
exporters write them: every face with its own vertices (no shared corners).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh


def box(lo, hi, *, flip_every: int = 0) -> trimesh.Trimesh:
    """A closed box with per-face vertices; ``flip_every`` > 0 reverses every n-th triangle."""
    m = trimesh.creation.box(extents=np.subtract(hi, lo))
    m.apply_translation((np.add(lo, hi)) / 2)
    faces = np.arange(len(m.faces) * 3).reshape(-1, 3)
    if flip_every:
        faces[::flip_every] = faces[::flip_every, ::-1]
    return trimesh.Trimesh(m.vertices[m.faces].reshape(-1, 3), faces, process=False)


def ground(y: float, half: float) -> trimesh.Trimesh:
    """An open square at height ``y`` (two-sided in the loader)."""
    v = [[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]]
    return trimesh.Trimesh(v, [[0, 2, 1], [0, 3, 2]], process=False)


def _write(scene: trimesh.Scene, path: Path) -> Path:
    scene.export(path)
    return path


def layered_wall(folder: Path) -> Path:
    """A BIM wall: three closed layer solids in one mesh sharing coincident faces, on a ground."""
    scene = trimesh.Scene()
    layers, z = (0.03, 0.25, 0.05), -0.15
    parts = []
    for thickness in layers:
        parts.append(box((-2, 0, z), (2, 2.5, z + thickness)))
        z += thickness
    scene.add_geometry(trimesh.util.concatenate(parts), node_name="wall")
    scene.add_geometry(ground(0.0, 4.0), node_name="ground")
    return _write(scene, Path(folder) / "layered_wall.glb")


def interpenetrating(folder: Path) -> Path:
    """CAD parts: a block with a shaft through it and a plate sunk half into it, on a ground."""
    scene = trimesh.Scene()
    scene.add_geometry(box((-1, 0, -1), (1, 1, 1)), node_name="block")
    scene.add_geometry(box((-0.2, -0.0, -2), (0.2, 0.4, 2)), node_name="shaft")
    scene.add_geometry(box((-1.5, 0.7, -0.5), (1.5, 1.3, 0.5)), node_name="plate")
    scene.add_geometry(ground(0.0, 4.0), node_name="ground")
    return _write(scene, Path(folder) / "interpenetrating.glb")


def flipped(folder: Path) -> Path:
    """Inconsistent winding: a closed box with every third triangle reversed, an open roof sheet
    with one triangle reversed, on a ground."""
    scene = trimesh.Scene()
    scene.add_geometry(box((-1, 0, -1), (1, 1.5, 1), flip_every=3), node_name="box")
    sheet = trimesh.Trimesh([[-1.5, 2, -1.5], [1.5, 2, -1.5], [1.5, 2.2, 1.5], [-1.5, 2.2, 1.5]], [[0, 2, 1], [0, 2, 3]], process=False)
    scene.add_geometry(sheet, node_name="sheet")
    scene.add_geometry(ground(0.0, 4.0), node_name="ground")
    return _write(scene, Path(folder) / "flipped.glb")


def mirrored_instances(folder: Path) -> Path:
    """One mesh instanced by two nodes, one of them mirrored (a negative-determinant transform)."""
    scene = trimesh.Scene()
    wedge = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False)
    name = scene.add_geometry(wedge, node_name="left", transform=trimesh.transformations.translation_matrix((0.5, 0, 0)))
    mirror = trimesh.transformations.translation_matrix((-0.5, 0, 0)) @ np.diag([-1.0, 1.0, 1.0, 1.0])
    scene.graph.update(frame_to="right", frame_from=scene.graph.base_frame, geometry=name, matrix=mirror)
    scene.add_geometry(ground(0.0, 3.0), node_name="ground")
    return _write(scene, Path(folder) / "mirrored.glb")


def slivers(folder: Path) -> Path:
    """A box whose top is fanned into needle-thin slivers, and degenerate triangles, as OBJ."""
    b = box((-1, 0, -1), (1, 1, 1))
    v = [list(p) for p in b.vertices]
    f = [list(t) for t in b.faces]
    base = len(v)
    v += [[0.0, 1.5, 0.0], [1.0, 1.5, 0.0], [1.0, 1.5, 1e-7], [0.5, 1.5, 0.5]]
    f += [[base, base + 1, base + 2], [base, base + 3, base + 3]]  # a needle, a repeated vertex
    path = Path(folder) / "slivers.obj"
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a + 1} {b_ + 1} {c + 1}\n" for a, b_, c in f))
    return path


def doubled_sheets(folder: Path) -> Path:
    """Petals as plant models build them: each a curved open sheet doubled by a copy a hair above
    it (0.0005 of the scene's 2-unit span), six of them round a stem, over a ground, as OBJ."""
    v, f = [], []

    def sheet(points: np.ndarray, columns: int) -> None:
        base = len(v)
        v.extend(points.tolist())
        rows = len(points) // columns
        for i in range(rows - 1):
            for j in range(columns - 1):
                a = base + i * columns + j
                f.extend([[a, a + columns, a + 1], [a + 1, a + columns, a + columns + 1]])

    s, t = np.meshgrid(np.linspace(0.08, 0.9, 12), np.linspace(-0.18, 0.18, 6), indexing="ij")
    for k in range(6):
        angle = k * np.pi / 3
        # A petal leaving the stem upwards and curling down at its tip, cupped across.
        radial, height = s, 0.6 + 0.5 * s - 0.6 * s**2 + 0.4 * t**2
        lateral = t
        x = radial * np.cos(angle) - lateral * np.sin(angle)
        z = radial * np.sin(angle) + lateral * np.cos(angle)
        under = np.stack([x, height, z], axis=-1).reshape(-1, 3)
        sheet(under, 6)
        sheet(under + (0.0, 0.0005, 0.0), 6)
    g = len(v)
    v.extend([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]])
    f.extend([[g, g + 2, g + 1], [g, g + 3, g + 2]])
    path = Path(folder) / "doubled_sheets.obj"
    lines = [f"o petals\n"] + [f"v {x:.7f} {y:.7f} {z:.7f}\n" for x, y, z in v[:g]]
    lines += [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f[:-2]]
    lines += ["o ground\n"] + [f"v {x} {y} {z}\n" for x, y, z in v[g:]]
    lines += [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f[-2:]]
    path.write_text("".join(lines))
    return path


def clad_wall(folder: Path) -> Path:
    """Cladding as BIM and CAD files carry it: an open panel standing off a closed wall by a batten's
    depth (0.004 of the scene's 2-unit span: 4 cm on a 20 m building), on a ground.  Light reaches
    the wall's face behind the panel through the gap's rim, so the reachable-sides flood keeps it;
    no camera fits in the gap."""
    scene = trimesh.Scene()
    scene.add_geometry(box((-1.5, 0, -0.1), (1.5, 1.5, 0.1)), node_name="wall")
    z = -0.1 - 0.008  # source units: the ground's 4-unit side is the 2-unit span
    panel = trimesh.Trimesh([[-1, 0.2, z], [1, 0.2, z], [1, 1.2, z], [-1, 1.2, z]], [[0, 2, 1], [0, 3, 2]], process=False)
    scene.add_geometry(panel, node_name="panel")
    scene.add_geometry(ground(0.0, 2.0), node_name="ground")
    return _write(scene, Path(folder) / "clad_wall.glb")
