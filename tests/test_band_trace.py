"""The band tracer against its reference twin, the plain sphere tracer, on the same rays.

Analytic SDFs (exact distances) and a fitted neural SDF (a slow field, as every neural SDF is
after its Lipschitz division); the hard cases: thin shells, grazing rays, origins on the
surface or inside, concave corners, candidates the field does not confirm.  Where the two
disagree, the plain tracer has spent its step budget on a grazing ray (it then reports a hit):
the plain tracer with 16x the budget settles those rays, and it agrees with the band tracer.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from prt.runtime.errors import SpecError  # noqa: E402
from prt.train.sdf import SDF, Box, Sphere, Subtraction, Union  # noqa: E402
from prt.train.sdf.band import build_band  # noqa: E402
from prt.train.sdf.band_trace import BandTracer  # noqa: E402
from prt.train.transport.precompute import PrecomputeSettings, check_settings  # noqa: E402
from prt.train.transport.transfer import SDFTracer, TransferIntegrator, cosine_directions, orthonormal_frames  # noqa: E402

RESOLUTION = 64  # the tests' bands: a coarser grid than a build's 128, to stay quick


def _surface_rays(sdf, count: int, rays: int, seed: int = 0, where=None):
    """Cosine rays from projected surface points, with the precompute's origin rule (SDFTracer.origins)."""
    rng = np.random.default_rng(seed)
    verts = sdf.to_mesh(resolution=48).vertices
    if where is not None:
        verts = verts[where(verts)]
    p = sdf.project_to_surface(verts[rng.integers(0, len(verts), count)])
    n = sdf.normals(p)
    frames = orthonormal_frames(n, rng.uniform(0.0, 2.0 * np.pi, count))
    dirs = np.matmul(cosine_directions(rays)[None], frames.transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(SDFTracer(sdf).origins(p, n), rays, axis=0)
    return origins.astype(np.float32), dirs.astype(np.float32)


def _compare(sdf, tracer, origins, dirs, most_disagreeing: float = 0.0):
    """Band and plain hits on the same rays; every disagreement is a ray the plain tracer ran out of steps on."""
    band = tracer.occluded(origins, dirs)
    plain = sdf.sphere_trace(origins, dirs)
    differ = np.flatnonzero(band != plain)
    assert len(differ) <= most_disagreeing * len(origins) + 1e-9, (len(differ), len(origins))
    if len(differ):  # the plain tracer's budget ran out there (a hit by its rule): with 16x the budget it agrees
        patient = sdf.sphere_trace(origins[differ], dirs[differ], max_steps=4096)
        np.testing.assert_array_equal(patient, band[differ])
    return band, plain


@pytest.fixture(scope="module")
def shell():
    """A spherical shell 0.012 thick (radius 0.5): thinner than a coarse cell (0.019), the wall a ray must not pass."""
    sdf = SDF("shell", Subtraction(Sphere((0.0, 0.0, 0.0), 0.506), Sphere((0.0, 0.0, 0.0), 0.494)))
    return sdf, BandTracer(sdf, build_band(sdf, resolution=RESOLUTION))


@pytest.fixture(scope="module")
def corner():
    """Two boxes meeting at a right angle (an L): concave, every sample near the corner shadows itself."""
    sdf = SDF("corner", Union((Box((0.0, -0.4, 0.0), (0.6, 0.1, 0.6)), Box((-0.4, 0.1, 0.0), (0.1, 0.4, 0.6)))))
    return sdf, BandTracer(sdf, build_band(sdf, resolution=RESOLUTION))


@pytest.fixture(scope="module")
def ball():
    sdf = SDF("ball", Sphere((0.0, 0.0, 0.0), 0.5))
    return sdf, BandTracer(sdf, build_band(sdf, resolution=RESOLUTION))


def test_the_shells_bracket_the_zero_set(ball, shell):
    for sdf, tracer in (ball, shell):
        band = tracer.band
        assert band.delta > 0 and band.stats["delta"] == band.delta
        for (verts, faces), sign in ((band.inner, -1.0), (band.outer, 1.0)):
            centres = verts[faces].mean(axis=1).astype(np.float64)
            f = sdf.evaluate(centres)
            assert (sign * f > 2e-4).all(), (sdf.name, sign, f.min(), f.max())  # clear of the hit threshold
            if sdf.name != "ball":  # the shell's inner level is a sliver along its medial ridge: its normals are noise
                continue
            # wound outwards: the face normal follows the field's gradient
            normal = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
            area = np.linalg.norm(normal, axis=1)
            solid = area > 1e-3 * area.max()  # marching cubes leaves slivers whose normals are noise
            assert (np.einsum("ij,ij->i", normal, sdf.gradient(centres))[solid] > 0).all()


def test_convex_ball_from_its_surface_and_from_outside(ball):
    sdf, tracer = ball
    origins, dirs = _surface_rays(sdf, 200, 32)
    band, _ = _compare(sdf, tracer, origins, dirs)
    assert not band.any()  # nothing shadows a convex ball
    rng = np.random.default_rng(1)
    o = rng.normal(size=(2000, 3))
    o = (0.9 * o / np.linalg.norm(o, axis=1, keepdims=True)).astype(np.float32)
    aim = (rng.uniform(-0.7, 0.7, (2000, 3)) - o).astype(np.float32)  # some rays through the ball, some past it
    band, _ = _compare(sdf, tracer, o, aim)
    assert 0.2 < band.mean() < 0.8


def test_grazing_rays_and_origins_on_or_inside_the_surface(ball):
    sdf, tracer = ball
    # rays tangent to the ball at heights just above and below its surface: miss above, hit below
    heights = np.array([-3e-3, -1e-3, -3e-4, 3e-4, 1e-3, 3e-3, 1e-2], dtype=np.float32)
    o = np.stack([np.full_like(heights, -0.9), 0.5 + heights, np.zeros_like(heights)], axis=1)
    d = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (len(heights), 1))
    band, plain = _compare(sdf, tracer, o, d)
    assert band.tolist() == [True, True, True, False, False, False, False]
    # origins exactly on the surface, and inside the solid: blocked at once, whichever way they look
    rng = np.random.default_rng(2)
    n = rng.normal(size=(300, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    for radius in (0.5, 0.49, 0.3):
        band, _ = _compare(sdf, tracer, (radius * n).astype(np.float32), rng.normal(size=(300, 3)).astype(np.float32))
        assert band.all(), radius


def test_a_shell_thinner_than_a_grid_cell_is_not_passed_through(shell):
    sdf, tracer = shell
    rng = np.random.default_rng(3)
    d = rng.normal(size=(3000, 3)).astype(np.float32)
    inside = np.zeros_like(d)  # from the centre: every ray meets the wall
    band, _ = _compare(sdf, tracer, inside, d)
    assert band.all()
    o = (0.95 * d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)  # from outside, towards and past it
    band, plain = _compare(sdf, tracer, o, (rng.uniform(-0.9, 0.9, (3000, 3)) - o).astype(np.float32))
    assert 0.3 < band.mean() < 0.95
    origins, dirs = _surface_rays(sdf, 200, 32, seed=4)  # the shell's own samples, outer and inner face
    band, _ = _compare(sdf, tracer, origins, dirs, most_disagreeing=1e-3)
    assert 0.2 < band.mean() < 0.8  # the inner face's rays are all blocked, the outer face's free


def test_concave_corner_shadows_itself_alike(corner):
    sdf, tracer = corner
    near_corner = lambda v: (np.abs(v[:, 0] + 0.3) < 0.15) & (np.abs(v[:, 1] + 0.3) < 0.15)  # noqa: E731
    origins, dirs = _surface_rays(sdf, 300, 64, seed=5, where=near_corner)
    band, plain = _compare(sdf, tracer, origins, dirs, most_disagreeing=1e-3)
    assert band.mean() > 0.1  # the other wall blocks a share of each hemisphere
    integ = TransferIntegrator(SDFTracer(sdf), rays=64)
    frames = np.tile(np.eye(3), (300, 1, 1))
    diff = np.abs(integ.integrate(band, frames) - integ.integrate(plain, frames))
    flipped = (band != plain).reshape(300, 64).sum(axis=1)  # each flipped ray moves a coefficient by |Y| / 64 < 1 / 64
    assert (diff.max(axis=1) <= flipped / 64 + 1e-6).all() and diff.mean() < 1e-3


def test_candidates_the_field_does_not_confirm_are_traced_plainly(ball):
    """An inner shell that lies outside the surface (a proxy hit the field says is not there)."""
    sdf, tracer = ball
    verts, faces = tracer.band.inner
    wrong = build_band(sdf, resolution=RESOLUTION)
    wrong.inner = (verts * np.float32(1.02), faces)  # 1 % outside the ball's surface
    off = BandTracer(sdf, wrong)
    rng = np.random.default_rng(6)
    o = (0.9 * np.tile([[1.0, 0.0, 0.0]], (500, 1)) + rng.normal(scale=0.05, size=(500, 3))).astype(np.float32)
    d = (rng.uniform(-0.6, 0.6, (500, 3)) - o).astype(np.float32)
    band, _ = _compare(sdf, off, o, d)
    assert off.counts["plain"] > 0 and band.any() and not band.all()


def test_the_tracer_pickles_for_a_cluster(ball):
    sdf, tracer = ball
    again = pickle.loads(pickle.dumps(tracer))
    origins, dirs = _surface_rays(sdf, 50, 16, seed=7)
    np.testing.assert_array_equal(again.occluded(origins, dirs), tracer.occluded(origins, dirs))


def test_sdf_trace_setting_is_checked_and_resolved():
    with pytest.raises(SpecError, match="sdf_trace"):
        check_settings(PrecomputeSettings(sdf_trace="fast"))
    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.transfer import sdf_trace_for

    assert sdf_trace_for(load_geometry("sphere_plane")) == "sphere"  # analytic: the plain tracer is the faster
    assert sdf_trace_for(load_geometry("sphere_plane"), "band") == "band"
    with pytest.raises(ValueError, match="sdf_trace"):
        sdf_trace_for(load_geometry("sphere_plane"), "fast")


# ----- a neural SDF ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """A 32x2 network fitted to two balls side by side: they shadow each other (a few seconds)."""
    from prt.train.sdf.neural import fit_neural_sdf, load_neural_sdf

    path = tmp_path_factory.mktemp("band_trace") / "twins.sdf.onnx"
    left = trimesh.creation.icosphere(subdivisions=3, radius=0.35)
    right = left.copy()
    left.apply_translation((-0.42, 0.0, 0.0))
    right.apply_translation((0.42, 0.0, 0.0))
    fit_neural_sdf(trimesh.util.concatenate([left, right]), path, size=(32, 2), samples=30_000, steps=800, batch=2048,
                   lr=1e-2, log=lambda *a: None)  # fmt: skip
    sdf = load_neural_sdf(path)
    return sdf, BandTracer(sdf, build_band(sdf, resolution=RESOLUTION)), path


def test_neural_sdf_traces_like_the_sphere_tracer(twins):
    sdf, tracer, _ = twins
    origins, dirs = _surface_rays(sdf, 400, 64, seed=8)
    band, plain = _compare(sdf, tracer, origins, dirs, most_disagreeing=2e-3)
    assert band.mean() > 0.03  # the facing sides shadow each other
    per_sample = lambda hit: hit.reshape(400, 64).mean(axis=1)  # noqa: E731
    assert np.abs(per_sample(band) - per_sample(plain)).mean() < 1e-3
    # the band tracer evaluates the network a few times per ray; the plain one tens of times
    assert tracer.counts["evaluations"] < 6 * tracer.counts["rays"]


def test_slope_table_bounds_the_networks_slope_near_its_surface(twins):
    sdf, tracer, _ = twins
    rng = np.random.default_rng(9)
    verts = sdf.to_mesh(resolution=48).vertices
    p = verts[rng.integers(0, len(verts), 20_000)] + rng.normal(scale=0.01, size=(20_000, 3))
    p = p[np.abs(sdf.evaluate(p)) < 2 * tracer.band.delta]
    slope = np.linalg.norm(sdf.gradient(p, eps=1e-5), axis=1)
    assert len(p) > 1000 and (slope <= tracer.band.slope_at(p)).all()


def test_neural_evaluation_matches_a_plain_forward_pass(twins):
    """The chunked, in-place network evaluation against the layers written out once, whole batch."""
    sdf, _, _ = twins
    node = sdf.root
    a, arch = node.arrays, node.arch
    p = np.random.default_rng(10).uniform(-1.2, 1.2, (10_001, 3))
    q = np.clip((p - a["enc_centre"]) * a["enc_inv_half"], -2.0, 2.0)
    h = q @ a["layer0_weight"][:3] + a["layer0_bias"]
    h = np.where(h > 0, h, 0.01 * h)
    for i in range(1, int(arch["layers"])):
        h = h @ a[f"layer{i}_weight"] + a[f"layer{i}_bias"]
        h = np.where(h > 0, h, 0.01 * h)
    expected = (np.tanh(h @ a["out_weight"] + a["out_bias"]) * a["out_scale"] + a["out_offset"])[:, 0]
    np.testing.assert_allclose(sdf.evaluate(p), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sdf.evaluate(p.astype(np.float32)), expected, rtol=0, atol=2e-6)


def test_mixed_scene_traces_its_sdf_objects_through_the_band(twins, tmp_path):
    from pathlib import Path

    from prt.train.inputs.mixed import compose_objects, parse_objects
    from prt.train.inputs.sampling import sample_surface
    from prt.train.transport.transfer import make_tracer

    ground = Path(__file__).parent / "data" / "ground_quad.obj"
    objects = parse_objects([{"mesh": str(ground), "translate": [0, -0.6, 0]},
                             {"neural_sdf": str(twins[2]), "scale": 0.6, "translate": [0, -0.1, 0]},
                             {"sdf": "sphere", "scale": 0.2, "translate": [0.5, 0.3, 0.2]}], "objects")  # fmt: skip
    geometry = compose_objects(objects, sdf_resolution=32)
    band, plain = make_tracer(geometry), make_tracer(geometry, "sphere")
    assert band.trace_rule and not plain.trace_rule and band.identity != plain.identity
    s = sample_surface(geometry, 300, seed=11)
    integ = TransferIntegrator(band, rays=32)
    origins, dirs, _ = integ.chunk_rays(s.points, s.normals, 0)
    hit_band, hit_plain = band.occluded(origins, dirs), plain.occluded(origins, dirs)
    differ = np.flatnonzero(hit_band != hit_plain)
    assert len(differ) <= 2e-3 * len(origins)
    assert hit_band.mean() > 0.05


def test_precompute_key_changes_only_where_the_band_tracer_traces(twins):
    """Mesh scenes and the sphere tracer keep the keys older builds have; the band tracer gets its own."""
    import hashlib
    import json
    from dataclasses import asdict
    from pathlib import Path

    from prt.train.inputs.geometry import load_geometry
    from prt.train.transport.precompute import FORMAT_VERSION, _geometry_key, precompute_key

    from prt.train.networks.segments import MARGIN_RULE, MERGE_RULE

    def before(geometry, settings):  # the key as it was computed before the setting existed (the margin's rule keyed since)
        keyed = {k: v for k, v in asdict(settings).items() if k not in ("adaptive", "split", "sdf_trace")} | {"margin": MARGIN_RULE, "merge": MERGE_RULE}
        return hashlib.sha1(json.dumps([_geometry_key(geometry), keyed, FORMAT_VERSION]).encode()).hexdigest()[:16]

    mesh = load_geometry(str(Path(__file__).parent / "data" / "ground_quad.obj"))
    analytic = load_geometry("sphere_plane")
    neural = load_geometry(str(twins[2]))
    settings = PrecomputeSettings(samples=5000, rays=32)
    for geometry in (mesh, analytic):
        assert precompute_key(geometry, settings) == before(geometry, settings)
    sphere = PrecomputeSettings(samples=5000, rays=32, sdf_trace="sphere")
    assert precompute_key(neural, sphere) == before(neural, sphere)
    assert precompute_key(neural, settings) != before(neural, settings)  # auto: the band tracer
    band = PrecomputeSettings(samples=5000, rays=32, sdf_trace="band")
    assert precompute_key(analytic, band) != precompute_key(analytic, settings)


def test_the_commands_take_sdf_trace():
    from prt.train import precompute_cli, train_cli
    from prt.train.build import spec_from_dict

    args = precompute_cli.build_parser().parse_args(["creature", "-o", "x", "--sdf-trace", "band"])
    assert precompute_cli.settings_from_args(args).sdf_trace == "band"
    assert precompute_cli.settings_from_args(precompute_cli.build_parser().parse_args(["creature", "-o", "x"])).sdf_trace == "auto"
    with pytest.raises(SystemExit) as exc:
        precompute_cli.build_parser().parse_args(["creature", "-o", "x", "--sdf-trace", "fast"])
    assert exc.value.code == 2
    assert train_cli.build_parser().parse_args(["creature", "-o", "x", "--sdf-trace", "sphere"]).sdf_trace == "sphere"
    assert spec_from_dict({"geometry": "creature", "sdf_trace": "band"}).precompute.sdf_trace == "band"
