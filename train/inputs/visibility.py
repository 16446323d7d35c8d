"""Which side of each face a sample may stand for: the sides that light and eyes can reach.

Real scene files put surfaces where nobody can see them: the faces between the layers of a BIM
wall (stacks of closed solids sharing coincident faces), the parts of CAD solids inside other
solids, the inner side of an open surface glued against a wall.  The orientation stage
(:mod:`prt.train.inputs.geometry`) cannot tell those apart from real surfaces: a stack of layer
solids welds into non-manifold edges and is judged open, so every face of it is two-sided.  A
sample on such a hidden side is dark (its rays hit the solid it sits in within a hair's breadth),
and it sits next to the visible side's bright samples with the same normal: a network fitted to
both learns their average, and the facade the camera sees renders black.

The rule here is topological only in the sense of light: a face side is **reachable** when some
ray leaving the environment can arrive at it, followed from side to side.  Face sides whose
rays escape the scene see the environment; the sides their rays hit are reachable too; and so
on (a breadth-first search over a graph of face sides whose edges are traced rays, as a level
compiler floods the outside of a map to find what is inside solids).  Winding, manifoldness,
coincident faces and the two-sided flag play no part.  Samples are then drawn only on reachable
sides (:func:`prt.train.inputs.sampling.sample_surface`'s ``sides``):

- a one-sided face (a closed component, outward) keeps its front side where that is reachable;
  where only its back is (a room modelled as a closed box seen from inside through a hole, say)
  it becomes two-sided, so that the G-buffer shows the side that can be seen;
- a two-sided face keeps the sides that are reachable;
- a face no light reaches on either side gets no samples (the G-buffer never shows it from a
  reachable place).

A scene whose surfaces see no environment at all (a sealed box) keeps its sides as they are.
Points are then checked one by one (:func:`hidden_points`): a sample all of whose rays end on
sides that are not reachable sits inside a solid (interpenetrating CAD parts) and is dropped.

Light reaching a side is not yet an eye reaching it.  A plant's petal modelled as two sheets a
hair apart (the orchids' petals: 0.0006 normalised units), a panel glued 1 cm off a wall, the
underside of a rug: the inner sides are reachable (a few grazing rays leave the gap at its rim),
but no camera fits in the gap, so the G-buffer never shows them.  Their samples are nearly black,
and the lower sheet's inner side lies a hair below the upper sheet's lit outer side with the same
normal; a network fitted to both blurs the two, and the petals the camera sees render at about half their
brightness (two of the orchids' flower segments refitted on their outer sides' samples alone:
+8 and +10 dB held out).  So a side is **in a gap** when at least
:data:`GAP_SHARE` of its pilot rays hit a surface less than :data:`GAP` (normalised scene units:
the scene spans about 2) above the side's plane -- the height of the hit over the side, not the
ray's length, which grazing rays stretch -- and such a side gets no samples.  A concave corner
(a floor meeting a wall) hides at most about half its hemisphere that way, far below the bar.
The point check drops a sample whose every ray hits that close too (a floor under a cabinet).

How close is close: :data:`GAP` is 0.3 % of the scene's span (5 cm on a 20 m house, 3 mm on a 1 m
plant).  A BIM wall's finish, cladding and lining layers stand 2 to 10 cm apart: at 0.1 % (the
rule's first width) the Duplex house kept samples on the faces a layer or two behind the room
sides the camera sees, 0.002-0.005 behind them with the same normal and mostly dark (4,552 of them
within 0.03 of the samples one inside view sees: a scratch count), and its networks drew blotches
over the rooms' walls and floors.  At 0.3 % the house's inside views went from 19.3 to 21.4 dB and
its outside views from 27.2 to 30.7 dB, its leak figure inside from 16 % to 0.8 %
(``docs/benchmarks/scenes_real.json`` and ``scenes_real_before_gap6.json``, ``studies/scenes_real.py``);
at 0.5 % (one scratch build) it was at 20.8 / 29.9 dB: wider is not better.  A corridor, a room, the space under a
table are far wider than that in any scene a camera walks through; a gap a camera could enter
at 0.3 % of the span would need a level about 300 times a person's width across.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

__all__ = ["SIDE_RULE", "SurfaceSides", "surface_sides", "hidden_points", "PILOT_RAYS", "GAP", "GAP_SHARE"]

# Part of the precompute key of builds whose sides differ from the geometry's own.
SIDE_RULE = "reach-v3"  # v2: sides and points in gaps no camera enters get no samples; v3: the gap 0.3 % of the span
# Rays per pilot point; pilot points per face side (fewer on very large meshes, at least 1).
PILOT_RAYS = 12
PILOT_POINTS = 2
PILOT_BUDGET = 250_000  # pilot points in all (both sides of every face)
# Rays per sample of the point check.
POINT_RAYS = 8
# A side in a gap: this share of its pilot rays hit a surface less than GAP above its plane
# (normalised scene units, the scene spans about 2: 0.3 % of it; the module docstring says why).
GAP = 6e-3
GAP_SHARE = 0.9


@dataclass
class SurfaceSides:
    """The sides of each face that samples may stand for.

    Attributes
    ----------
    allowed : (F, 2) bool
        Side 0 lies along the face's geometric normal (its winding), side 1 against it.
    reachable : (F, 2) bool
        Sides some ray from the environment can arrive at.
    two_sided : (F,) bool
        Sidedness after the rule (one-sided faces seen only from behind become two-sided).
    changed : bool
        False when ``allowed`` and ``two_sided`` are the geometry's own (samples are then drawn as
        before, bit for bit).
    notes : list of str
        What the rule did, one line each.
    stats : dict
        Counts (faces without a reachable side, and so on) and the time taken.
    """

    allowed: np.ndarray
    reachable: np.ndarray
    two_sided: np.ndarray
    changed: bool
    notes: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)


def _hemisphere(normals: np.ndarray, rays: int, rng: np.random.Generator) -> np.ndarray:
    """(N * rays, 3) float32 directions, uniform over the hemisphere about each unit normal."""
    n = len(normals)
    d = rng.normal(size=(n, rays, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True) + 1e-30
    flip = np.einsum("nrc,nc->nr", d, normals) < 0
    d[flip] *= -1.0
    return d.reshape(-1, 3).astype(np.float32)


def _trace(scene, origins: np.ndarray, dirs: np.ndarray, face_normal: np.ndarray, chunk: int = 1 << 18):
    """Hit face (-1: escaped), the side of it each ray arrives at (0: its front) and the distance
    travelled (inf where it escaped)."""
    import os
    from concurrent.futures import ThreadPoolExecutor

    hit = np.empty(len(dirs), dtype=np.int64)
    distance = np.empty(len(dirs), dtype=np.float64)

    def run(start: int) -> None:  # Embree releases the GIL while it traces
        stop = start + chunk
        out = scene.run(origins[start:stop], dirs[start:stop], query="INTERSECT", output=1)
        hit[start:stop] = np.where(np.asarray(out["geomID"]) != -1, np.asarray(out["primID"]), -1)
        distance[start:stop] = out["tfar"]

    with ThreadPoolExecutor(max_workers=max(1, min(8, os.cpu_count() or 1))) as pool:
        list(pool.map(run, range(0, len(dirs), chunk)))
    side = np.zeros(len(dirs), dtype=np.int64)
    ok = hit >= 0
    side[ok] = (np.einsum("kc,kc->k", dirs[ok].astype(np.float64), face_normal[hit[ok]]) > 0).astype(np.int64)
    distance[~ok] = np.inf
    return hit, side, distance


def _in_gap(dirs: np.ndarray, normals: np.ndarray, distance: np.ndarray, rays: int) -> np.ndarray:
    """(K,) bool per ray: it hits a surface less than :data:`GAP` above its origin's plane.

    dirs : (K * rays, 3); normals : (K, 3) unit normals of the origins' sides; distance : (K * rays,)
    """
    height = distance.reshape(-1, rays) * np.einsum("krc,kc->kr", dirs.reshape(-1, rays, 3).astype(np.float64), normals)
    return (height < GAP).reshape(-1)


def _embree(vertices: np.ndarray, faces: np.ndarray):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
    return scene


def surface_sides(geometry, *, rays: int = PILOT_RAYS, points: int = PILOT_POINTS, seed: int = 0,
                  offset: float = 1e-4, budget: int = PILOT_BUDGET) -> SurfaceSides:
    """Reachable face sides of a mesh geometry and the sides samples may take.

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
        A mesh scene (``kind == "mesh"``).
    rays : int
        Rays per pilot point, uniform over its side's hemisphere.
    points : int
        Pilot points per face side (uniform in the triangle); fewer where the mesh has more
        than ``budget / 2`` faces' worth (at least one per side).
    seed : int
    offset : float
        How far a pilot ray's origin leaves the face along the side's normal (scene units): the
        mesh tracer's offset, so coincident faces are told apart as its rays tell them.
    budget : int
        Pilot points in all.

    Returns
    -------
    SurfaceSides
    """
    import time

    t0 = time.perf_counter()
    vertices = np.asarray(geometry.mesh.vertices, dtype=np.float64)
    faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
    two_sided = np.asarray(geometry.two_sided, dtype=bool)
    n_faces = len(faces)
    normal = _face_normals(vertices, faces)
    own = np.stack([np.ones(n_faces, bool), two_sided], axis=1)
    per_side = int(max(1, min(points, budget // max(2 * n_faces, 1))))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x51DE]))

    # Pilot points: per_side uniform points on each side of every face.
    face = np.repeat(np.arange(n_faces), 2 * per_side)
    side = np.tile(np.repeat([0, 1], per_side), n_faces)
    r1, r2 = np.sqrt(rng.random(len(face))), rng.random(len(face))
    tri = vertices[faces[face]]
    pts = (1 - r1)[:, None] * tri[:, 0] + (r1 * (1 - r2))[:, None] * tri[:, 1] + (r1 * r2)[:, None] * tri[:, 2]
    side_normal = normal[face] * np.where(side == 1, -1.0, 1.0)[:, None]
    valid = np.linalg.norm(normal[face], axis=1) > 0
    face, side, pts, side_normal = face[valid], side[valid], pts[valid], side_normal[valid]

    scene = _embree(vertices, faces)
    origins = np.repeat((pts + offset * side_normal).astype(np.float32), rays, axis=0)
    dirs = _hemisphere(side_normal, rays, rng)
    hit, hit_side, distance = _trace(scene, origins, dirs, normal)
    gap_ray = _in_gap(dirs, side_normal, distance, rays)

    node = np.repeat(2 * face + side, rays)
    # A pilot point whose origin starts inside a closed solid (parts that overlap by less than the
    # offset, at edges) sees that solid's back faces: its rays would leak reach into the solid.
    on_closed = (hit >= 0) & ~two_sided[np.maximum(hit, 0)]
    closed_hits = on_closed.reshape(-1, rays).sum(axis=1)
    back_hits = (on_closed & (hit_side == 1)).reshape(-1, rays).sum(axis=1)
    inside = (closed_hits >= rays // 4) & (2 * back_hits > closed_hits)
    usable = ~np.repeat(inside, rays)
    hit, hit_side, node, gap_ray = hit[usable], hit_side[usable], node[usable], gap_ray[usable]
    traced = np.bincount(node, minlength=2 * n_faces)
    in_gap = (traced > 0) & (np.bincount(node, weights=gap_ray, minlength=2 * n_faces) >= GAP_SHARE * np.maximum(traced, 1))
    in_gap = in_gap.reshape(n_faces, 2)
    escaped = np.zeros(2 * n_faces, dtype=bool)
    escaped[node[hit < 0]] = True
    reach = np.zeros(2 * n_faces + 1, dtype=bool)
    if escaped.any():
        ok = hit >= 0
        root = 2 * n_faces
        rows = np.r_[node[ok], np.full(int(escaped.sum()), root)]
        cols = np.r_[2 * hit[ok] + hit_side[ok], np.flatnonzero(escaped)]
        graph = scipy.sparse.coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(root + 1, root + 1)).tocsr()
        order = scipy.sparse.csgraph.breadth_first_order(graph, root, directed=True, return_predecessors=False)
        reach[order] = True
    reachable = reach[: 2 * n_faces].reshape(n_faces, 2)
    stats = {"pilot_points": int(len(pts)), "pilot_rays": int(len(dirs)), "faces": n_faces,
             "pilot_points_inside_solids": int(inside.sum())}
    notes: list[str] = []
    if not reachable.any():
        stats["seconds"] = time.perf_counter() - t0
        notes.append("no face side sees the environment (a sealed scene): every side kept as the file has it")
        return SurfaceSides(own.copy(), reachable, two_sided.copy(), False, notes, stats)

    allowed = own & reachable
    new_two_sided = two_sided.copy()
    back_only = ~two_sided & ~reachable[:, 0] & reachable[:, 1]
    new_two_sided[back_only] = True
    allowed[back_only] = (False, True)
    gapped = allowed & in_gap
    allowed &= ~in_gap
    hidden = ~allowed.any(axis=1)
    dropped_side = two_sided & (allowed.sum(axis=1) == 1)
    stats.update(hidden_faces=int(hidden.sum()), one_side_kept=int(dropped_side.sum()), seen_from_behind=int(back_only.sum()),
                 sides_in_gaps=int(gapped.sum()),
                 hidden_area=float(np.asarray(geometry.mesh.area_faces)[hidden].sum() / max(geometry.mesh.area, 1e-30)))
    changed = bool((allowed != own).any() or (new_two_sided != two_sided).any())
    if changed:
        names = geometry.object_names
        objects = np.asarray(geometry.object_ids)
        if hidden.any():
            notes.append(f"{int(hidden.sum()):,} of {n_faces:,} triangles ({100 * stats['hidden_area']:.1f} % of the area) "
                         f"are seen from no reachable place (inside solids, between coincident faces): no samples there")
        if gapped.any():
            who = sorted({names[i] for i in np.unique(objects[gapped.any(axis=1)])})
            shown = ", ".join(who[:5]) + (f" and {len(who) - 5} more" if len(who) > 5 else "")
            notes.append(f"{int(gapped.sum()):,} triangle sides face another surface closer than {GAP:g} (doubled sheets, "
                         f"layers, parts resting on others) and no camera fits there: no samples on them ({shown})")
        if dropped_side.any():
            notes.append(f"{int(dropped_side.sum()):,} two-sided triangles are reachable from one side only: samples on that side")
        if back_only.any():
            who = sorted({names[i] for i in np.unique(objects[back_only])})
            shown = ", ".join(who[:5]) + (f" and {len(who) - 5} more" if len(who) > 5 else "")
            notes.append(f"{int(back_only.sum()):,} closed-surface triangles are seen only from behind (inside-out or enclosing "
                         f"rooms): made two-sided ({shown})")
    stats["seconds"] = time.perf_counter() - t0
    return SurfaceSides(allowed, reachable, new_two_sided, changed, notes, stats)


def hidden_points(geometry, sides: SurfaceSides, points: np.ndarray, normals: np.ndarray, *, rays: int = POINT_RAYS,
                  seed: int = 0, offset: float = 1e-4) -> np.ndarray:
    """(N,) bool: samples whose every ray ends on a side no light reaches (points inside solids),
    or whose every ray hits a surface less than :data:`GAP` above it (in a gap no camera enters).

    A sample on a reachable face side can still sit inside another solid where two parts
    interpenetrate; its rays then all hit that solid from inside.  One escaping ray, or one hit
    on a reachable side, keeps it, unless all its rays stay in a gap (a floor under a cabinet).
    """
    vertices = np.asarray(geometry.mesh.vertices, dtype=np.float64)
    faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
    normal = _face_normals(vertices, faces)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x9017]))
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    origins = np.repeat((np.asarray(points, np.float64) + offset * n).astype(np.float32), rays, axis=0)
    dirs = _hemisphere(n, rays, rng)
    hit, hit_side, distance = _trace(_embree(vertices, faces), origins, dirs, normal)
    seen = np.where(hit >= 0, sides.reachable.reshape(-1)[2 * np.maximum(hit, 0) + hit_side], True)
    in_gap = _in_gap(dirs, n, distance, rays).reshape(-1, rays).all(axis=1)
    return ~seen.reshape(-1, rays).any(axis=1) | in_gap
