"""The interreflection operator (train/transport/interreflection.py) against analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from prt.train.transport.interreflection import interreflect, trace_bounce_rays  # noqa: E402
from prt.train.transport.transfer import compute_transfer  # noqa: E402


def _inside_of_a_box(n: int = 600):
    """Samples on the inner faces of a closed cube, normals pointing in."""
    box = trimesh.creation.box(extents=(1.6, 1.6, 1.6))
    points, faces = trimesh.sample.sample_surface_even(box, n, seed=3)
    return box, points, -box.face_normals[faces], faces


@pytest.mark.parametrize("bounces", [0, 1, 2, 5])
def test_white_furnace_inside_a_closed_box_sums_the_albedo_powers(bounces):
    box, points, normals, faces = _inside_of_a_box()
    rays = trace_bounce_rays(box, points, normals, faces, rays=64, seed=1)
    assert (rays.nearest >= 0).all()  # closed: every ray hits a wall facing it
    constant = np.zeros((len(points), 16))
    constant[:, 0] = 1.0  # T_0 = the same vector everywhere (the env light seen through the walls)
    albedo = np.tile([0.5, 0.25, 0.8], (len(box.faces), 1))
    total = interreflect(constant, rays, albedo, bounces)
    expected = sum(albedo[0] ** k for k in range(bounces + 1))
    assert np.allclose(total[:, 0, :], expected, atol=1e-12) and np.allclose(total[:, 1:, :], 0)


def test_open_floor_under_a_red_wall_turns_red():
    """A floor next to a red wall: the bounce adds red light only, more the closer to the wall."""
    floor = trimesh.creation.box(extents=(2.0, 0.02, 2.0))
    wall = trimesh.creation.box(extents=(0.02, 2.0, 2.0))
    wall.apply_translation([1.0, 1.0, 0.0])
    scene = trimesh.util.concatenate([floor, wall])
    xs = np.linspace(-0.9, 0.9, 10)
    points = np.stack([xs, np.full_like(xs, 0.0101), np.zeros_like(xs)], axis=1)
    normals = np.tile([0.0, 1.0, 0.0], (len(xs), 1))
    wall_points = np.stack([np.full(200, 0.989), np.random.default_rng(0).uniform(0, 2, 200), np.random.default_rng(1).uniform(-1, 1, 200)], axis=1)
    all_points = np.concatenate([points, wall_points])
    all_normals = np.concatenate([normals, np.tile([-1.0, 0.0, 0.0], (200, 1))])

    class Geo:  # what compute_transfer needs of a Geometry
        sdf = None
        mesh = scene

    direct = compute_transfer(Geo(), all_points, all_normals, rays=256, progress=False)
    rays = trace_bounce_rays(scene, all_points, all_normals, rays=256, seed=2)
    albedo = np.zeros((len(scene.faces), 3))
    albedo[len(floor.faces):] = [0.8, 0.0, 0.0]  # the wall is red, the floor black
    total = interreflect(direct, rays, albedo, 2)
    light = np.zeros(16)
    light[0] = np.sqrt(4 * np.pi)  # constant white sky of radiance 1
    indirect = np.einsum("snc,n->sc", total[: len(xs)] - direct[: len(xs), :, None], light)
    assert np.allclose(indirect[:, 1:], 0) and (indirect[:, 0] > 0).all()
    assert indirect[-1, 0] > 2 * indirect[0, 0]  # nearer the wall, redder


def test_sparse_bounces_equal_the_plain_gather():
    box, points, normals, faces = _inside_of_a_box(300)
    rays = trace_bounce_rays(box, points, normals, rays=32, seed=4)
    rng = np.random.default_rng(5)
    direct = rng.normal(size=(len(points), 16))
    albedo = rng.uniform(0, 1, size=(len(box.faces), 3))
    fast = interreflect(direct, rays, albedo, 3)
    plain = interreflect(direct, rays, albedo, 3, transfer_at=lambda index, previous: previous[index])
    assert np.allclose(fast, plain, atol=1e-12)
