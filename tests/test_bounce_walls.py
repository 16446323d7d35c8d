"""Bounce lookups stay on their side of walls (issue 43): a hit takes a sample only where the segment
between them is clear, and the training targets' smoothing averages only such neighbours.

A sealed room of thin walls on a sunlit ground receives no light at all, so every bounce inside it
is exactly zero; before the rule, hits on the room's floor, walls and ceiling near a wall took
samples of the ground or the wall faces outside.  With a door, the room's floor is judged against
the benchmark's per-pixel reference (the direct transfer traced at every hit)."""

from __future__ import annotations

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from scipy.spatial import cKDTree  # noqa: E402

from prt.train.transport.interreflection import (  # noqa: E402
    NORMAL_WEIGHT, clear_between, interreflect, nearest_on_plane, nearest_visible, nearest_visible_reference, trace_bounce_rays,
)  # fmt: skip
from prt.train.transport.smoothing import smooth_indirect, smooth_indirect_reference  # noqa: E402
from prt.train.transport.transfer import EmbreeTracer, compute_transfer  # noqa: E402

HALF, WALL, HEIGHT, FLOOR = 0.3, 0.006, 0.4, 0.01  # the room: 0.6 wide, walls 0.006 thick (a quarter of the sample spacing)
SKY = np.zeros(16)
SKY[0] = np.sqrt(4 * np.pi)  # a constant white sky of radiance 1


class _Geometry:  # what compute_transfer needs of a Geometry
    sdf = None

    def __init__(self, mesh):
        self.mesh = mesh


def _room(door: bool):
    """Ground slab, four thin walls (a door gap in the +x wall when ``door``), a roof; the parts."""
    parts = [trimesh.creation.box(extents=(2.0, 2 * FLOOR, 2.0))]

    def box(extents, centre):
        b = trimesh.creation.box(extents=extents)
        b.apply_translation(centre)
        parts.append(b)

    y = FLOOR + HEIGHT / 2
    for z in (-1, 1):
        box((2 * HALF + 2 * WALL, HEIGHT, WALL), (0, y, z * (HALF + WALL / 2)))
    box((WALL, HEIGHT, 2 * HALF), (-HALF - WALL / 2, y, 0))
    if door:
        gap = 0.1
        for z in (-1, 1):
            box((WALL, HEIGHT, HALF - gap), (HALF + WALL / 2, y, z * (HALF + gap) / 2))
    else:
        box((WALL, HEIGHT, 2 * HALF), (HALF + WALL / 2, y, 0))
    box((2 * HALF + 2 * WALL, WALL, 2 * HALF + 2 * WALL), (0, FLOOR + HEIGHT + WALL / 2, 0))
    return trimesh.util.concatenate(parts), parts


def _samples(mesh, parts, count: int = 20000, seed: int = 1):
    """Samples on the faces a camera can see: those on or inside another part (coincident and covered
    faces: the build's sampling leaves them out) are dropped.  (points, normals, faces)"""
    points, faces = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    owner = np.searchsorted(np.cumsum([len(p.faces) for p in parts]), faces, side="right")
    covered = np.zeros(len(points), dtype=bool)
    for k, part in enumerate(parts):
        lo, hi = part.bounds
        covered |= (owner != k) & np.all((points >= lo - 1e-9) & (points <= hi + 1e-9), axis=1)
    keep = ~covered
    return points[keep], mesh.face_normals[faces[keep]], faces[keep]


def _inside(points) -> np.ndarray:
    return (np.abs(points[:, 0]) <= HALF + 1e-6) & (np.abs(points[:, 2]) <= HALF + 1e-6) & (np.abs(points[:, 1] - FLOOR - HEIGHT / 2) <= HEIGHT / 2 + 1e-6)


@pytest.fixture(scope="module")
def sealed():
    mesh, parts = _room(door=False)
    points, normals, faces = _samples(mesh, parts)
    direct = compute_transfer(_Geometry(mesh), points, normals, rays=64, progress=False)
    return mesh, points, normals, faces, direct


def test_a_sealed_room_gets_no_light_from_beyond_its_walls(sealed):
    mesh, points, normals, faces, direct = sealed
    inside = _inside(points)
    assert inside.sum() > 2000 and np.abs(direct[inside]).max() == 0.0  # sealed: no sky inside
    rays = trace_bounce_rays(mesh, points, normals, faces, rays=32, seed=2)
    landed = rays.nearest[inside]
    assert not (~inside[landed[landed >= 0]]).any()  # no hit inside takes a sample outside
    albedo = np.full((len(mesh.faces), 3), 0.8)
    indirect = np.einsum("snc,n->sc", interreflect(direct, rays, albedo, 3) - direct[:, :, None], SKY)
    assert np.abs(indirect[inside]).max() == 0.0
    assert indirect[~inside, 0].mean() > 0.01  # outside, the ground and walls do light each other
    # The case does exercise the rule: hits on the room's floor a millimetre from a wall, unchecked,
    # take the ground beyond it.
    tracer = EmbreeTracer(mesh)
    z = np.linspace(-HALF + 0.01, HALF - 0.01, 200)
    q = np.stack([np.full_like(z, HALF - 0.001), np.full_like(z, FLOOR), z], axis=1)
    key = np.concatenate([q, NORMAL_WEIGHT * np.tile([0.0, 1.0, 0.0], (len(q), 1))], axis=1)
    tree = cKDTree(np.concatenate([points, NORMAL_WEIGHT * normals], axis=1))
    unchecked = nearest_on_plane(tree, key, workers=1)
    assert (~inside[unchecked[unchecked >= 0]]).sum() > 20
    checked = nearest_visible(tree, key, tracer, workers=1)
    assert (checked >= 0).all() and inside[checked].all()


def test_nearest_visible_equals_the_plain_twin(sealed):
    mesh, points, normals, _, _ = sealed
    tracer = EmbreeTracer(mesh)
    rng = np.random.default_rng(3)
    pick = rng.choice(len(points), 150, replace=False)
    q = points[pick] + rng.normal(scale=0.01, size=(150, 3)) * (1 - np.abs(normals[pick]))  # moved within their planes
    key = np.concatenate([q, NORMAL_WEIGHT * normals[pick]], axis=1)
    data = np.concatenate([points, NORMAL_WEIGHT * normals], axis=1)
    for options in ({}, {"candidates": 16, "plane_weight": 16.0, "bound": np.inf}):
        fast = nearest_visible(cKDTree(data), key, tracer, workers=1, **options)
        plain = nearest_visible_reference(data, key, tracer, **options)
        assert (fast == plain).all()


def test_clear_between_blocks_a_wall_and_keeps_a_floor_and_a_curved_surface():
    mesh, _ = _room(door=False)
    tracer = EmbreeTracer(mesh)
    up = np.array([[0.0, 1.0, 0.0]] * 2)
    floor = np.array([[HALF - 0.004, FLOOR, 0.0], [HALF - 0.02, FLOOR, 0.0]])  # two points of the room's floor
    beyond = np.array([[HALF + WALL + 0.004, FLOOR, 0.0]] * 2)  # the ground just beyond the wall
    assert clear_between(tracer, floor[:1], up[:1], floor[1:], up[1:]).all()
    assert not clear_between(tracer, floor, up, beyond, up).any()
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.1)
    tracer = EmbreeTracer(sphere)
    rng = np.random.default_rng(4)
    a = rng.normal(size=(200, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = a + rng.normal(scale=0.08, size=(200, 3))  # chords up to about the radius
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    assert clear_between(tracer, 0.1 * a, a, 0.1 * b, b).all()


def test_the_room_behind_a_door_matches_the_per_pixel_reference():
    """The build's estimator (nearest clear sample's direct transfer) against the reference's (the
    direct transfer traced at each hit) on the floor of a room lit through its door: first bounce."""
    from prt.bench.bounce_reference import indirect_transfer

    mesh, parts = _room(door=True)
    points, normals, faces = _samples(mesh, parts)
    direct = compute_transfer(_Geometry(mesh), points, normals, rays=64, progress=False)
    rays = trace_bounce_rays(mesh, points, normals, faces, rays=64, seed=2)
    albedo = np.full((len(mesh.faces), 3), 0.8)
    indirect = np.einsum("snc,n->sc", interreflect(direct, rays, albedo, 1) - direct[:, :, None], SKY)[:, 0]
    floor = np.flatnonzero(_inside(points) & (normals[:, 1] > 0.9) & (points[:, 1] < FLOOR + 1e-6))
    pick = floor[:: max(1, len(floor) // 120)]
    reference = indirect_transfer(_Geometry(mesh), EmbreeTracer(mesh), points[pick], normals[pick], albedo, 1, hit_rays=256, rays=64)
    expected = np.einsum("snc,n->sc", reference, SKY)[:, 0]
    assert expected.mean() > 0.01
    assert abs(indirect[pick].mean() / expected.mean() - 1) < 0.05


def test_smoothing_keeps_to_its_side_of_a_wall(sealed):
    mesh, points, normals, _, _ = sealed
    inside = _inside(points)
    values = np.where(inside, 0.0, 1.0)[:, None, None] * np.ones((1, 4, 3))
    tracer = EmbreeTracer(mesh)
    smoothed = smooth_indirect(points, normals, values, tracer=tracer)
    assert smoothed[inside].max() == 0.0 and smoothed[~inside].min() == 1.0
    unchecked = smooth_indirect(points, normals, values)
    assert unchecked[inside].max() > 0.0  # the case crosses walls without the rule
    few = np.random.default_rng(5).choice(len(points), 400, replace=False)
    fast = smooth_indirect(points[few], normals[few], values[few], tracer=tracer)
    plain = smooth_indirect_reference(points[few], normals[few], values[few], tracer=tracer)
    assert np.allclose(fast, plain)
