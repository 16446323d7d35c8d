"""Ground-truth transfer: analytic cases, hard geometry, determinism and resume."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from prt.runtime import sh
from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.transfer import compute_transfer, cosine_directions, orthonormal_frames

Y00 = 0.5 / np.sqrt(np.pi)


def unoccluded_transfer(normals: np.ndarray, bands: int = 4) -> np.ndarray:
    """Analytic transfer of an unshadowed point: the clamped cosine / pi rotated to n."""
    lam = sh.zonal_to_band_factors(sh.clamped_cosine(bands)) / np.pi
    return sh.basis(normals, bands) * sh.band_factors_to_coeff_scale(lam)


def load_mesh(tmp_path, mesh: trimesh.Trimesh, name: str = "scene.ply"):
    path = tmp_path / name
    mesh.export(path)
    return load_geometry(str(path))


def test_cosine_directions_are_a_cosine_weighted_hemisphere():
    d = cosine_directions(4096)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert (d[:, 2] > 0).all()
    # E[cos] under the pdf cos/pi is 2/3; E[x] = E[y] = 0
    assert abs(d[:, 2].mean() - 2 / 3) < 2e-3
    assert abs(d[:, 0].mean()) < 2e-3 and abs(d[:, 1].mean()) < 2e-3


def test_frames_are_rotations_with_the_normal_as_z():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(500, 3))
    n[:3] = [[0, 0, 1], [0, 0, -1], [0, 0, -1 + 1e-9]]  # the branch point of the construction
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    f = orthonormal_frames(n, rng.uniform(0, 2 * np.pi, len(n)))
    assert np.allclose(f @ f.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(f), 1.0)
    assert np.allclose(f[:, :, 2], n)


def test_unoccluded_sphere_matches_the_analytic_transfer(tmp_path):
    geometry = load_mesh(tmp_path, trimesh.creation.icosphere(subdivisions=4))
    s = sample_surface(geometry, 300, seed=3)
    t = compute_transfer(geometry, s.points, s.normals, rays=1024)
    expected = unoccluded_transfer(s.normals.astype(np.float64))
    assert np.abs(t - expected).max() < 4e-3
    # white furnace: a constant environment of radiance 1 gives exactly 1
    light = np.zeros(16)
    light[0] = np.sqrt(4 * np.pi)
    assert np.allclose(t @ light, 1.0, atol=1e-6)


def test_point_below_a_sphere_sees_the_analytic_cone(tmp_path):
    """A point on a plane under a sphere of radius r at height d loses sin^2(a) = (r/d)^2."""
    r, d = 0.3, 0.6
    plane = trimesh.creation.box(extents=(4.0, 0.02, 4.0))
    plane.apply_translation((0, -0.01, 0))
    ball = trimesh.creation.icosphere(subdivisions=5, radius=r)
    ball.apply_translation((0, d, 0))
    # normalise=False keeps the analytic set-up in its own units
    path = tmp_path / "ball.ply"
    trimesh.util.concatenate([plane, ball]).export(path)
    geometry = load_geometry(str(path), normalise=False)
    t = compute_transfer(geometry, np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]), rays=4096)
    assert t[0, 0] == pytest.approx(Y00 * (1 - (r / d) ** 2), abs=2e-3)
    # symmetric about the vertical: the band-1 x and z parts (i = 3, 2) vanish, and the y part
    # (i = 1) integrates c*cos^2/pi over the open ring only: (2c/3) * cos^3(a)
    c1 = np.sqrt(3 / (4 * np.pi))
    assert abs(t[0, 2]) < 2e-3 and abs(t[0, 3]) < 2e-3
    assert t[0, 1] == pytest.approx(2 * c1 / 3 * (1 - (r / d) ** 2) ** 1.5, abs=2e-3)


def test_open_bowl_lets_rays_escape_through_the_hole(tmp_path):
    """Inside a hemispherical bowl, the bottom point sees the sky through a 45 degree cone."""
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    keep = sphere.triangles_center[:, 1] < 0
    bowl = trimesh.Trimesh(sphere.vertices, sphere.faces[keep], process=False)
    path = tmp_path / "bowl.ply"
    bowl.export(path)
    geometry = load_geometry(str(path), normalise=False)
    assert geometry.two_sided.all()
    t = compute_transfer(geometry, np.array([[0.0, -0.999, 0.0]]), np.array([[0.0, 1.0, 0.0]]), rays=4096)
    assert t[0, 0] == pytest.approx(0.5 * Y00, abs=1e-2)


def test_coplanar_and_thin_geometry_do_not_shadow_themselves(tmp_path):
    # a slab 1e-3 thick plus a duplicate of its top face (coplanar, z-fighting geometry)
    slab = trimesh.creation.box(extents=(2.0, 1e-3, 2.0))
    top = trimesh.Trimesh([[-1, 5e-4, -1], [1, 5e-4, -1], [1, 5e-4, 1], [-1, 5e-4, 1]], [[0, 2, 1], [0, 3, 2]])
    path = tmp_path / "slab.ply"
    trimesh.util.concatenate([slab, top]).export(path)
    geometry = load_geometry(str(path), normalise=False)
    rng = np.random.default_rng(0)
    xz = rng.uniform(-0.9, 0.9, size=(200, 2))
    up = np.column_stack([xz[:, 0], np.full(200, 5e-4), xz[:, 1]])
    down = up * [1, -1, 1]
    normals = np.repeat([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], 200, axis=0)
    t = compute_transfer(geometry, np.vstack([up, down]), normals, rays=256)
    assert np.allclose(t[:, 0], Y00, atol=1e-6)  # every ray escapes, grazing ones included


def test_scale_does_not_change_transfer(tmp_path):
    base = trimesh.creation.torus(0.6, 0.25)
    results = []
    for i, scale in enumerate((1e-6, 1.0, 1e6)):
        mesh = base.copy()
        mesh.apply_scale(scale)
        geometry = load_mesh(tmp_path, mesh, f"torus{i}.ply")
        s = sample_surface(geometry, 200, seed=0)
        results.append(compute_transfer(geometry, s.points, s.normals, rays=128))
    assert np.abs(results[0] - results[1]).max() < 1e-3
    assert np.abs(results[2] - results[1]).max() < 1e-3


def test_rotating_the_scene_rotates_the_transfer(tmp_path):
    torus = trimesh.creation.torus(0.6, 0.25)
    R = trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])
    torus.export(tmp_path / "a.ply")
    torus.copy().apply_transform(R).export(tmp_path / "b.ply")
    geometry = load_geometry(str(tmp_path / "a.ply"), normalise=False)
    geometry_r = load_geometry(str(tmp_path / "b.ply"), normalise=False)
    R = R[:3, :3]
    s = sample_surface(geometry, 64, seed=0)
    t = compute_transfer(geometry, s.points, s.normals, rays=2048)
    t_r = compute_transfer(geometry_r, s.points @ R.T, s.normals @ R.T, rays=2048)
    expected = sh.rotate(t.astype(np.float64).T, R).T
    assert np.abs(t_r - expected).max() < 3e-2  # two independent low-discrepancy estimates
    assert np.abs(t_r - expected).mean() < 4e-3


def test_results_are_deterministic_and_resume_bit_identically(tmp_path):
    geometry = load_mesh(tmp_path, trimesh.creation.torus(0.6, 0.25))
    s = sample_surface(geometry, 1000, seed=0)
    kwargs = dict(rays=64, chunk_size=128)
    reference = compute_transfer(geometry, s.points, s.normals, threads=1, **kwargs)
    cache = tmp_path / "cache"
    first = compute_transfer(geometry, s.points, s.normals, threads=2, cache_dir=cache, **kwargs)
    assert np.array_equal(first, reference)
    chunks = sorted(cache.glob("*/chunk_*.npy"))
    assert len(chunks) == 8
    for c in chunks[::2]:
        c.unlink()
    # a finished chunk that would differ proves it is reused rather than recomputed
    np.save(chunks[1], np.full((128, 16), 7.0, dtype=np.float32))
    resumed = compute_transfer(geometry, s.points, s.normals, threads=2, cache_dir=cache, **kwargs)
    assert np.array_equal(resumed[:128], reference[:128])
    assert (resumed[128:256] == 7.0).all()
    assert np.array_equal(resumed[256:], reference[256:])


def test_bad_points_are_rejected(tmp_path):
    geometry = load_mesh(tmp_path, trimesh.creation.icosphere())
    with pytest.raises(ValueError, match="NaN"):
        compute_transfer(geometry, np.array([[np.nan, 0, 0]]), np.array([[0, 1.0, 0]]))
    with pytest.raises(ValueError, match="differ"):
        compute_transfer(geometry, np.zeros((2, 3)), np.zeros((3, 3)))


def test_normals_of_any_length_are_normalised(tmp_path):
    geometry = load_mesh(tmp_path, trimesh.creation.icosphere(subdivisions=3))
    s = sample_surface(geometry, 50, seed=0)
    a = compute_transfer(geometry, s.points, s.normals, rays=64)
    b = compute_transfer(geometry, s.points, s.normals * 3.5, rays=64)
    assert np.abs(a - b).max() < 1e-5


def test_sdf_sphere_tracing_agrees_with_embree_on_its_own_mesh():
    """The same scene two ways: sphere traced SDF vs Embree on its marching-cubes mesh."""
    from prt.train.transport.transfer import EmbreeTracer, SDFTracer

    geometry = load_geometry("sphere_plane")
    assert geometry.kind == "sdf"
    s = sample_surface(geometry, 400, seed=2)
    assert np.abs(geometry.sdf.evaluate(s.points.astype(np.float64))).max() < 1e-4  # on the zero set
    by_sdf = compute_transfer(geometry, s.points, s.normals, rays=256, tracer=SDFTracer(geometry.sdf))
    by_mesh = compute_transfer(geometry, s.points, s.normals, rays=256, tracer=EmbreeTracer(geometry.mesh))
    assert np.isfinite(by_sdf).all()
    # the two tracers differ only by the mesh's facets and their ray offsets
    assert np.abs(by_sdf[:, 0] - by_mesh[:, 0]).mean() < 2e-3
    assert np.abs(by_sdf - by_mesh).max() < 0.05
    # contact shadow: the lowest samples on the sphere are darker than its top
    ball = s.points[:, 1] > geometry.sdf.bounds[0][1] + 0.2
    low = ball & (s.points[:, 1] < np.quantile(s.points[ball, 1], 0.1))
    high = ball & (s.points[:, 1] > np.quantile(s.points[ball, 1], 0.9))
    assert by_sdf[low, 0].mean() < 0.7 * by_sdf[high, 0].mean()
