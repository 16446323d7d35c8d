"""Adaptive sampling (prt.train.inputs.adaptive): the variation score against its brute-force twin, points
put back exactly on the surface, draws concentrated at a contact shadow, and the precompute's
second pass (deterministic, resumable, validation still uniform)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from prt.runtime.errors import SpecError
from prt.train.inputs.adaptive import adaptive_samples, closest_on_triangles, transfer_variation, transfer_variation_reference
from prt.train.inputs.geometry import load_geometry
from prt.train.transport.precompute import PrecomputeSettings, check_settings, load_precompute, run_precompute
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.transfer import compute_transfer


@pytest.fixture(scope="module")
def box_on_floor(tmp_path_factory):
    """A unit cube resting on a large open quad: transfer changes fast along the contact line."""
    box = trimesh.creation.box((0.6, 0.6, 0.6))
    box.apply_translation((0.0, 0.3, 0.0))
    quad = trimesh.Trimesh([(-2, 0, -2), (2, 0, -2), (2, 0, 2), (-2, 0, 2)], [(0, 2, 1), (0, 3, 2)], process=False)
    path = tmp_path_factory.mktemp("adaptive") / "scene.obj"
    trimesh.util.concatenate([box, quad]).export(path)
    return load_geometry(path)


def test_the_variation_score_matches_its_brute_force_twin():
    rng = np.random.default_rng(4)
    points, normals = rng.normal(size=(150, 3)), rng.normal(size=(150, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    transfer = rng.normal(size=(150, 16))
    fast, reference = transfer_variation(points, normals, transfer), transfer_variation_reference(points, normals, transfer)
    np.testing.assert_allclose(fast[0], reference[0], rtol=1e-9)
    np.testing.assert_allclose(fast[1], reference[1], rtol=1e-9)


def test_closest_points_on_triangles_beat_a_dense_barycentric_search():
    rng = np.random.default_rng(1)
    a, b, c = (rng.normal(size=(200, 3)) for _ in range(3))
    points = rng.normal(size=(200, 3)) * 2.0
    closest, weights = closest_on_triangles(points, a, b, c)
    assert np.all(weights >= -1e-12) and np.allclose(weights.sum(axis=1), 1.0)
    np.testing.assert_allclose(closest, weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c, atol=1e-12)
    grid = np.array([(i, j) for i in range(61) for j in range(61 - i)], dtype=np.float64) / 60.0
    u, v = grid[:, 0], grid[:, 1]
    dense = (1 - u - v)[None, :, None] * a[:, None] + u[None, :, None] * b[:, None] + v[None, :, None] * c[:, None]
    best = np.linalg.norm(dense - points[:, None], axis=2).min(axis=1)
    ours = np.linalg.norm(closest - points, axis=1)
    assert np.all(ours <= best + 1e-9)  # never farther than the best grid point
    assert np.all(best - ours < 0.1)  # and the grid's spacing bounds how much closer


def test_adaptive_samples_lie_on_the_surface_and_crowd_the_contact_line(box_on_floor):
    geometry = box_on_floor
    first = sample_surface(geometry, 3000, seed=0)
    transfer = compute_transfer(geometry, first.points, first.normals, rays=64, seed=0)
    extra, stats = adaptive_samples(geometry, first, transfer, 3000, seed=0)
    again, _ = adaptive_samples(geometry, first, transfer, 3000, seed=0)
    assert np.array_equal(extra.points, again.points)  # deterministic in the seed
    tri = np.asarray(geometry.mesh.vertices)[np.asarray(geometry.mesh.faces)[extra.face_index]]
    on_face, _ = closest_on_triangles(extra.points.astype(np.float64), tri[:, 0], tri[:, 1], tri[:, 2])
    assert np.abs(on_face - extra.points).max() < 1e-5
    assert np.allclose(np.linalg.norm(extra.normals, axis=1), 1.0, atol=1e-5)
    # The floor next to the box (a band of half the box's width around its footprint) is where the
    # shadow changes fastest.  Scene units: the floor at the bottom of the bounds, the box centred.
    floor = geometry.mesh.bounds[0][1]
    half = np.abs(geometry.mesh.vertices[np.asarray(geometry.mesh.vertices)[:, 1] > floor + 1e-6][:, 0]).max()

    def near_contact(points):
        y, reach = points[:, 1], np.maximum(np.abs(points[:, 0]), np.abs(points[:, 2]))
        return (np.abs(y - floor) < 1e-5) & (reach > half) & (reach < 1.5 * half)

    share_uniform, share_adaptive = near_contact(first.points).mean(), near_contact(extra.points).mean()
    assert share_adaptive > 1.6 * share_uniform, (share_uniform, share_adaptive)  # 2.1x measured
    assert stats["favoured"] > 1.5 and stats["unplaced"] == 0


def test_the_precompute_second_pass_is_deterministic_and_keeps_validation_uniform(box_on_floor, tmp_path):
    settings = PrecomputeSettings(samples=2000, validation=500, rays=16, segments=2, adaptive=0.5)
    first = run_precompute(box_on_floor, tmp_path / "a", settings, progress=False, log=lambda *a: None)
    run_precompute(box_on_floor, tmp_path / "b", settings, progress=False, log=lambda *a: None)
    a, b = load_precompute(tmp_path / "a"), load_precompute(tmp_path / "b")
    assert len(a["samples"]["points"]) == 2000 and len(a["validation"]["points"]) == 500
    assert np.array_equal(a["samples"]["transfer"], b["samples"]["transfer"])
    assert "adaptive" in first["timings"]
    uniform = run_precompute(box_on_floor, tmp_path / "u", PrecomputeSettings(samples=2000, validation=500, rays=16, segments=2),
                             progress=False, log=lambda *a: None)  # fmt: skip
    u = load_precompute(tmp_path / "u")
    assert np.array_equal(u["validation"]["points"], a["validation"]["points"])  # the held-out set does not move
    assert uniform["key"] != first["key"]
    lines = []
    again = run_precompute(box_on_floor, tmp_path / "a", settings, progress=False, log=lines.append)
    assert again["key"] == first["key"] and any("up to date" in line for line in lines)


@pytest.mark.parametrize("share", [-0.1, 0.95, True, "half", float("nan")])
def test_a_bad_adaptive_share_is_one_spec_error(share):
    with pytest.raises(SpecError, match=r"^--adaptive: expected a share of the samples in 0 \.\. 0\.9"):
        check_settings(PrecomputeSettings(samples=1000, adaptive=share), flags=True)


def test_in_a_mixed_scene_each_point_goes_back_onto_its_own_object():
    from pathlib import Path

    from prt.train.inputs.mixed import ObjectSpec, compose_objects

    quad = Path(__file__).parent / "data" / "ground_quad.obj"
    geometry = compose_objects([
        ObjectSpec("mesh", str(quad), "ground", translate=(0.0, -0.5, 0.0)),
        ObjectSpec("sdf", "sphere", "ball", scale=0.3, translate=(0.0, -0.2, 0.0)),
    ], sdf_resolution=40)  # fmt: skip
    first = sample_surface(geometry, 2000, seed=0)
    transfer = compute_transfer(geometry, first.points, first.normals, rays=32, seed=0)
    extra, _ = adaptive_samples(geometry, first, transfer, 1000, seed=0)
    ball = extra.object_ids == 1
    assert 0 < ball.sum() < len(extra)
    sdf = geometry.mixed.sdfs[1]
    assert np.abs(sdf.evaluate(extra.points[ball].astype(np.float64))).max() < 1e-4  # on the sphere's zero set
    ground = extra.object_ids == 0
    assert np.ptp(extra.points[ground, 1]) < 1e-6  # on the (flat) ground, never on the ball's proxy faces
    assert not geometry.mixed.proxy_faces[extra.face_index[ground]].any()
