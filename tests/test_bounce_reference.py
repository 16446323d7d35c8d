"""The benchmark's interreflected reference against the integrating sphere (an analytic case).

Inside a sphere every surface point sees any region with the same cosine-weighted form factor,
area / (4 pi R^2) (the principle of the integrating sphere).  A sphere of radius 1 with the cap
above y = h removed, under a constant sky of radiance 1, therefore gives at every interior point
direct light f = (1 - h) / 2 (the cap's share of the sphere's area) and bounce k
(a (1 - f))^k f: each bounce is the fraction of rays landing on the wall times the albedo times
the previous bounce, the same everywhere.
"""

import numpy as np
import pytest
import trimesh

from prt.bench.bounce_reference import face_albedo, higher_bounce_samples, indirect_transfer
from prt.train import compute_transfer
from prt.train.inputs.geometry import Geometry
from prt.train.transport.transfer import make_tracer

H = 0.3
F_OPEN = (1 - H) / 2
ALBEDO = np.array([0.8, 0.5, 0.2])
DC = np.sqrt(4 * np.pi)  # SH coefficient of a constant radiance of 1


@pytest.fixture(scope="module")
def bowl():
    sphere = trimesh.creation.icosphere(subdivisions=4)
    mesh = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 1] < H], process=False)
    mesh.remove_unreferenced_vertices()
    n = len(mesh.faces)
    geometry = Geometry(mesh=mesh, object_ids=np.zeros(n, np.int64), object_names=["bowl"], two_sided=np.ones(n, bool),
                        to_source=np.eye(4), source="bowl", sdf=None)  # fmt: skip
    rng = np.random.default_rng(1)
    faces = rng.integers(0, n, 150)
    points = np.einsum("nk,nkc->nc", rng.dirichlet([1, 1, 1], 150), mesh.triangles[faces]).astype(np.float32)
    inward = -(points / np.linalg.norm(points, axis=1, keepdims=True)).astype(np.float32)
    return geometry, make_tracer(geometry), points, inward


def test_direct_light_is_the_open_share(bowl):
    geometry, tracer, points, normals = bowl
    direct = compute_transfer(geometry, points, normals, rays=256, seed=0, tracer=tracer)
    assert abs((direct[:, 0] * DC).mean() - F_OPEN) < 0.01


@pytest.mark.parametrize("bounces", [1, 2])
def test_bounces_match_the_integrating_sphere(bowl, bounces):
    geometry, tracer, points, normals = bowl
    albedo = face_albedo({"bowl": ALBEDO}, geometry)
    higher = higher_bounce_samples(geometry, tracer, albedo, bounces, rays=128, count=4000, log=lambda *_: None)
    indirect = indirect_transfer(geometry, tracer, points, normals, albedo, bounces, higher=higher, seed=3)
    r = ALBEDO * (1 - F_OPEN)
    exact = F_OPEN * sum(r**k for k in range(1, bounces + 1))
    measured = indirect[:, 0, :].mean(axis=0) * DC
    np.testing.assert_allclose(measured, exact, rtol=0.03)
    # Constant light: only the DC coefficient carries it, and the bounce is the same at every point.
    assert np.std(indirect[:, 0, 0] * DC) < 0.1 * exact[0]


def test_no_bounce_is_zero_and_albedos_must_name_every_object(bowl):
    geometry, tracer, points, normals = bowl
    albedo = face_albedo({"bowl": ALBEDO}, geometry)
    assert not indirect_transfer(geometry, tracer, points, normals, albedo, 0).any()
    with pytest.raises(ValueError, match="bowl"):
        face_albedo({"floor": [1, 1, 1]}, geometry)
    with pytest.raises(ValueError, match="higher-bounce"):
        indirect_transfer(geometry, tracer, points, normals, albedo, 2)


def test_more_hit_rays_with_fewer_rays_each_is_less_noisy_at_the_same_cost(bowl):
    """The spread of the indirect DC over points that all see the same light (the integrating
    sphere): 512 hits x 16 rays is below 64 x 128 (prt-bench --ref-hit-rays / --ref-hit-transfer-rays)."""
    geometry, tracer, points, normals = bowl
    albedo = face_albedo({"bowl": ALBEDO}, geometry)
    higher = higher_bounce_samples(geometry, tracer, albedo, 1, rays=64, count=2000, log=lambda *_: None)
    spread = {}
    for hits, rays in ((64, 128), (512, 16)):
        indirect = indirect_transfer(geometry, tracer, points, normals, albedo, 1, higher=higher, seed=5, hit_rays=hits, rays=rays)
        spread[hits] = float(indirect[:, 0, 0].std())
    assert spread[512] < 0.8 * spread[64], spread
