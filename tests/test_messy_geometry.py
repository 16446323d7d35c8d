"""Geometry as real scene files have it (issue 43): the samples' transfer must agree with what a
camera sees.

Each synthetic case (tests/messy_scenes.py: BIM layer walls with coincident faces,
interpenetrating solids, inconsistent winding, a mirrored instance, slivers) is precomputed as a
build precomputes it; then every pixel a camera outside sees is looked up in the training samples
(the mean of its nearest samples by position and normal, the least a network fitted to them can
do) and compared with transfer ray-traced at that pixel with the side the camera sees: the
per-pixel reference.  Before the reachable-sides rule (prt.train.inputs.visibility) the BIM wall
failed this by a factor of ten (its facade's samples were mostly dark ones from between the layers);
before its gap rule the doubled petals failed it, 17 % off against 2 % with it (dark samples on the
inner sides, a hair from the lit outer ones with the same normal; one scratch run).  A panel stood
off a wall by 0.004 (cladding on battens) is 27 % off with the rule's first width (0.002) and 10 %
with its width now (0.006; one scratch run, the tests below hold both sides): the wall's samples
near the gap's rim, which light reaches through it, stay (its tolerance below is wider for that).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.sampling import sample_surface
from prt.train.inputs.visibility import surface_sides
from prt.train.transport.precompute import PrecomputeSettings, load_precompute, run_precompute
from prt.train.transport.transfer import compute_transfer

import messy_scenes

# Relative mean error of the DC coefficient at the camera's pixels, nearest samples vs reference.
TOLERANCE = 0.05
CASE_TOLERANCE = {"clad_wall": 0.15}  # the samples near the rim of the gap behind the panel stay (module docstring)


def _camera_points(geometry, eye, target, size=48, fov=50.0):
    """What a rasteriser shows: first hits of primary rays (one-sided back faces are culled, so such
    pixels are left out), with the normal of the side facing the camera."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    v = np.asarray(geometry.mesh.vertices, np.float64)
    f = np.asarray(geometry.mesh.faces, np.int64)
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(v[f], np.float32))
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 1, 0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    t = np.tan(np.radians(fov) / 2)
    u, w = np.meshgrid(np.linspace(-t, t, size), np.linspace(-t, t, size))
    dirs = forward + u.reshape(-1, 1) * right + w.reshape(-1, 1) * up
    dirs = (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)
    origins = np.repeat(eye[None].astype(np.float32), len(dirs), axis=0)
    out = scene.run(origins, dirs, query="INTERSECT", output=1)
    hit, dist = np.asarray(out["primID"]), np.asarray(out["tfar"])
    ok = hit >= 0
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    normal = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-30)
    n = normal[np.maximum(hit, 0)]
    facing = np.einsum("kc,kc->k", n, dirs) < 0
    two = np.asarray(geometry.two_sided)[np.maximum(hit, 0)]
    keep = ok & (facing | two)
    n = np.where(facing[:, None], n, -n)
    points = origins + dist[:, None] * dirs
    return points[keep].astype(np.float64), n[keep]


def _agreement(geometry, samples_points, samples_normals, samples_transfer, views) -> float:
    """Relative mean |DC error| of the nearest-samples lookup against the per-pixel reference."""
    tree = cKDTree(np.hstack([samples_points, 0.05 * samples_normals]))
    errors, scale = [], []
    for eye, target in views:
        points, normals = _camera_points(geometry, eye, target)
        reference = compute_transfer(geometry, points.astype(np.float32), normals.astype(np.float32), rays=256, progress=False)
        _, index = tree.query(np.hstack([points, 0.05 * normals]), k=8)
        predicted = samples_transfer[index, 0].mean(axis=1)
        errors.append(np.abs(predicted - reference[:, 0]))
        scale.append(np.abs(reference[:, 0]))
    return float(np.concatenate(errors).mean() / max(np.concatenate(scale).mean(), 1e-9))


def _precomputed(path, tmp_path):
    geometry = load_geometry(path)
    settings = PrecomputeSettings(samples=30000, rays=64, segments=2, validation=1000)
    run_precompute(geometry, tmp_path / "pre", settings, progress=False, log=lambda *_: None)
    data = load_precompute(tmp_path / "pre")
    return geometry, data["samples"]


VIEWS = {  # (eye, target) in the normalised scene
    "layered_wall": [((0.2, 0.35, -1.6), (0, 0.3, 0)), ((-0.3, 0.4, 1.6), (0, 0.3, 0))],
    "interpenetrating": [((1.2, 0.9, -1.5), (0, 0.1, 0)), ((-1.4, 0.8, 1.2), (0, 0.1, 0))],
    "flipped": [((1.3, 1.0, -1.4), (0, 0.2, 0)), ((-1.2, 1.2, 1.3), (0, 0.2, 0))],
    "mirrored_instances": [((0.3, 1.0, 1.8), (0, 0.1, 0)), ((-0.4, 1.2, -1.6), (0, 0.1, 0))],
    "slivers": [((1.5, 1.2, -1.5), (0, 0, 0))],
    "doubled_sheets": [((1.2, 1.6, -1.4), (0, 0.5, 0)), ((-1.5, 1.3, 0.9), (0, 0.5, 0))],
    "clad_wall": [((0.3, 0.5, -1.6), (0, 0.35, 0)), ((-0.8, 0.7, -1.2), (0, 0.35, 0))],
}


@pytest.mark.parametrize("case", sorted(VIEWS))
def test_samples_agree_with_what_the_camera_sees(case, tmp_path):
    path = getattr(messy_scenes, case)(tmp_path)
    geometry, samples = _precomputed(path, tmp_path)
    error = _agreement(geometry, samples["points"], samples["normals"], samples["transfer"], VIEWS[case])
    assert error < CASE_TOLERANCE.get(case, TOLERANCE), f"{case}: nearest samples off the per-pixel reference by {100 * error:.1f} %"


def test_without_the_rule_the_layered_wall_fails(tmp_path):
    """The check above can fail: the samples drawn on the geometry's own sides disagree."""
    geometry = load_geometry(messy_scenes.layered_wall(tmp_path))
    samples = sample_surface(geometry, 30000, seed=0)
    transfer = compute_transfer(geometry, samples.points, samples.normals, rays=64, progress=False)
    error = _agreement(geometry, samples.points, samples.normals, transfer, VIEWS["layered_wall"])
    assert error > 4 * TOLERANCE


def test_without_the_gap_rule_doubled_sheets_fail(tmp_path, monkeypatch):
    """Light reaches the inner sides of a doubled petal (grazing rays leave at its rim), so the
    reachable-sides flood keeps them; the lower sheet's inner side then sits a hair below the upper
    sheet's outer side with the same normal, dark where the camera's pixel is lit."""
    from prt.train.inputs import visibility

    monkeypatch.setattr(visibility, "GAP", 0.0)
    geometry, samples = _precomputed(messy_scenes.doubled_sheets(tmp_path), tmp_path)
    error = _agreement(geometry, samples["points"], samples["normals"], samples["transfer"], VIEWS["doubled_sheets"])
    assert error > 3 * TOLERANCE


def test_with_the_narrow_gap_the_clad_wall_fails(tmp_path, monkeypatch):
    """The wall's face behind a panel stood off it by 0.004 lies beyond a gap of 0.002 (the rule's
    width before): its dark samples, with the panel's normal, are then nearer the panel's pixels than
    most of the panel's own."""
    from prt.train.inputs import visibility

    monkeypatch.setattr(visibility, "GAP", 0.002)
    geometry, samples = _precomputed(messy_scenes.clad_wall(tmp_path), tmp_path)
    error = _agreement(geometry, samples["points"], samples["normals"], samples["transfer"], VIEWS["clad_wall"])
    assert error > 1.5 * CASE_TOLERANCE["clad_wall"]


def test_doubled_sheets_keep_only_their_outer_sides(tmp_path):
    geometry = load_geometry(messy_scenes.doubled_sheets(tmp_path))
    sides = surface_sides(geometry)
    v, f = np.asarray(geometry.mesh.vertices), np.asarray(geometry.mesh.faces)
    petals = np.asarray(geometry.object_ids) == geometry.object_names.index("petals")
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    # A face's twin on the other sheet is the nearest other face; its outer side faces away from it.
    index = np.flatnonzero(petals)
    centroid = v[f[index]].mean(axis=1)
    _, near = cKDTree(centroid).query(centroid, k=2)
    away = centroid - centroid[near[:, 1]]
    outer = np.where(np.einsum("kc,kc->k", normal[index], away) > 0, 0, 1)
    allowed = sides.allowed[index]
    inner_allowed = allowed[np.arange(len(index)), 1 - outer]
    outer_allowed = allowed[np.arange(len(index)), outer]
    assert inner_allowed.mean() < 0.02, f"{inner_allowed.sum()} of {len(index)} inner sides keep samples"
    assert outer_allowed.mean() > 0.9
    assert sides.stats["sides_in_gaps"] > 0 and any("no camera fits there" in n and "petals" in n for n in sides.notes)


def test_layer_faces_get_no_samples_and_facades_keep_theirs(tmp_path):
    geometry = load_geometry(messy_scenes.layered_wall(tmp_path))
    assert geometry.two_sided[np.asarray(geometry.object_ids) == geometry.object_names.index("wall")].all()
    sides = surface_sides(geometry)
    assert sides.changed
    v, f = np.asarray(geometry.mesh.vertices), np.asarray(geometry.mesh.faces)
    wall = np.asarray(geometry.object_ids) == geometry.object_names.index("wall")
    z = v[f][:, :, 2]
    flat_z = np.ptp(z, axis=1) < 1e-9
    outer = wall & flat_z & ((np.abs(z[:, 0] - z[wall].min()) < 1e-9) | (np.abs(z[:, 0] - z[wall].max()) < 1e-9))
    inner = wall & flat_z & ~outer
    assert outer.any() and inner.any()
    assert sides.allowed[outer].sum(axis=1).min() == 1  # the facades: the outside only
    assert not sides.allowed[inner].any()  # between the layers: nothing


def test_a_sealed_scene_keeps_its_sides(tmp_path):
    path = tmp_path / "sealed.glb"
    import trimesh

    scene = trimesh.Scene()
    outer = messy_scenes.box((-1, -1, -1), (1, 1, 1))
    scene.add_geometry(outer, node_name="shell")
    scene.export(path)
    geometry = load_geometry(path)
    sides = surface_sides(geometry)
    assert sides.reachable[:, 0].all() and not sides.reachable[:, 1].any()
    assert not sides.changed  # a closed convex object: nothing to change, samples as before


def test_sides_are_deterministic(tmp_path):
    geometry = load_geometry(messy_scenes.interpenetrating(tmp_path))
    a, b = surface_sides(geometry, seed=3), surface_sides(geometry, seed=3)
    assert np.array_equal(a.allowed, b.allowed) and np.array_equal(a.two_sided, b.two_sided)


def test_glass_is_left_out_and_named(tmp_path):
    """Glass (a blended, mostly transparent glTF material) lets light in: a room behind a pane is lit."""
    import trimesh
    from prt.train.inputs.gltf_scene import is_see_through

    assert is_see_through({"alphaMode": "BLEND", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.9, 1.0, 0.1]}})
    assert not is_see_through({"alphaMode": "OPAQUE", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.9, 1.0, 0.1]}})
    assert not is_see_through({"alphaMode": "BLEND", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.9, 1.0, 0.9]}})
    assert is_see_through({"extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}}})
    scene = trimesh.Scene()
    pane = messy_scenes.box((-1, 0, 0), (1, 1, 0.01))
    pane.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(
        baseColorFactor=[200, 220, 255, 25], alphaMode="BLEND"))
    scene.add_geometry(pane, node_name="pane")
    scene.add_geometry(messy_scenes.box((-1, 0, 0.5), (1, 1, 0.6)), node_name="wall")
    path = tmp_path / "glass.glb"
    scene.export(path)
    geometry = load_geometry(path)
    assert geometry.object_names == ["wall"] and geometry.see_through == ["pane"]
    assert "1 see-through (glass) parts left out" in geometry.summary() and "pane" in geometry.summary()
