"""Segments: object and spatial split, CPCA-style merging, seam margins, point assignment."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.sampling import sample_surface
from prt.train.networks.segments import segment_samples
from prt.train.transport.transfer import compute_transfer

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def cornell():
    geometry = load_geometry(str(DATA / "CornellBox-Original.obj"))
    s = sample_surface(geometry, 6000, seed=0)
    t = compute_transfer(geometry, s.points, s.normals, rays=64)
    return geometry, s, t


def test_every_sample_has_one_segment_and_segments_respect_objects(cornell):
    geometry, s, t = cornell
    seg = segment_samples(s.points, s.object_ids, t, normals=s.normals, max_segments=12, merge=False, min_samples=50)
    assert seg.count == 12
    assert seg.home.shape == (len(s),) and seg.home.min() == 0 and seg.home.max() == seg.count - 1
    for k in range(seg.count):
        assert len(np.unique(s.object_ids[seg.home == k])) == 1  # no cell spans two objects
    # the rule the runtime will use reproduces every sample's segment
    assert np.array_equal(seg.assign(s.points, s.object_ids), seg.home)


def test_margins_hold_neighbours_within_delta_and_nothing_farther(cornell):
    geometry, s, t = cornell
    delta = 0.05
    seg = segment_samples(s.points, s.object_ids, t, normals=s.normals, max_segments=12, merge=False, delta=delta, min_samples=50)
    for k in range(seg.count):
        own = np.flatnonzero(seg.home == k)
        members = seg.members[k]
        assert np.isin(own, members).all()
        extra = np.setdiff1d(members, own)
        if len(extra):
            gaps = np.linalg.norm(s.points[extra][:, None] - s.points[own][None], axis=2).min(axis=1)
            assert gaps.max() <= delta + 1e-6
    # the floor meets the walls, so somebody has margin samples
    assert sum(len(m) for m in seg.members) > len(s)


def _thin_wall(rng, n=3000):
    """A wall 0.02 thick lying in y (its lit outer face, object 0, normal +y; its inner face, object 1,
    normal -y: the layers of a BIM wall) and a partition standing on it at x = 0.3 (object 2, normal -x)."""
    top = np.column_stack([rng.uniform(-1, 1, n), np.full(n, 0.01), rng.uniform(-1, 1, n)])
    bottom = top * [1, -1, 1]
    side = np.column_stack([np.full(n // 2, 0.3), rng.uniform(0.01, 0.5, n // 2), rng.uniform(-1, 1, n // 2)])
    points = np.concatenate([top, bottom, side])
    normals = np.concatenate([np.tile([0.0, 1, 0], (n, 1)), np.tile([0.0, -1, 0], (n, 1)), np.tile([-1.0, 0, 0], (n // 2, 1))])
    return points, normals, np.repeat([0, 1, 2], [n, n, n // 2])


def test_a_margin_continues_its_own_surface_and_leaves_the_far_face_of_a_thin_wall_out():
    """A segment of a wall's outer face trained on the inner face's samples 2 cm away (the dark room
    behind a lit facade) and on the partition standing on it: capacity spent on what its pixels never
    show.  Its margin holds the samples of its own face across the cut, and only those."""
    from prt.train.networks.segments import MARGIN_RULE

    rng = np.random.default_rng(5)
    points, normals, ids = _thin_wall(rng)
    transfer = rng.normal(size=(len(points), 4))
    delta = 0.05
    seg = segment_samples(points, ids, transfer, normals=normals, max_segments=8, merge=False, delta=delta, min_samples=50)
    plain = segment_samples(points, ids, transfer, normals=None, max_segments=8, merge=False, delta=delta, min_samples=50)
    assert np.array_equal(seg.home, plain.home)  # the rule changes margins only
    outer = [k for k in range(seg.count) if ids[seg.home == k][0] == 0]
    assert len(outer) >= 2  # the outer face is cut, so its segments meet on it
    for k in range(seg.count):
        own = seg.home == k
        extra = np.setdiff1d(seg.members[k], np.flatnonzero(own))
        face = ids[own][0]
        assert set(ids[extra]) <= {face}, (k, MARGIN_RULE)  # nothing across the wall, nothing round the corner
        if len(extra):
            gaps = np.linalg.norm(points[extra][:, None] - points[own][None], axis=2).min(axis=1)
            assert gaps.max() <= delta + 1e-9
    for k in outer:
        extra = np.setdiff1d(seg.members[k], np.flatnonzero(seg.home == k))
        plain_extra = np.setdiff1d(plain.members[k], np.flatnonzero(plain.home == k))
        assert (ids[extra] == 0).sum() > 0  # its own face beyond the cut: the seam
        assert (ids[plain_extra] == 0).sum() == (ids[extra] == 0).sum()  # all of it, as by distance alone
        assert (ids[plain_extra] == 1).sum() > (ids[plain_extra] == 0).sum()  # by distance alone, mostly the far face
    # a curved surface keeps its margin: a sphere cut in 8, by distance alone and by this rule alike
    v = rng.normal(size=(6000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    t = rng.normal(size=(len(v), 4))
    sphere = segment_samples(v, np.zeros(len(v), int), t, normals=v, max_segments=8, merge=False, min_samples=50)
    sphere_plain = segment_samples(v, np.zeros(len(v), int), t, normals=None, max_segments=8, merge=False, min_samples=50)
    assert all(np.array_equal(a, b) for a, b in zip(sphere.members, sphere_plain.members))


def test_unshadowed_plane_merges_into_one_segment_but_shadowed_regions_stay_apart(tmp_path):
    plane = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]])
    plane.export(tmp_path / "plane.ply")
    geometry = load_geometry(str(tmp_path / "plane.ply"))
    s = sample_surface(geometry, 4000, seed=1)
    up = s.normals[:, 1] > 0
    s = s.subset(np.flatnonzero(up))
    t = compute_transfer(geometry, s.points, s.normals, rays=64)
    seg = segment_samples(s.points, s.object_ids, t, normals=s.normals, max_segments=8, min_samples=50)
    assert seg.leaves_before_merge == 8
    assert seg.count == 1  # identical transfer everywhere: one network is enough

    # a plane with a wall standing on half of it: the shadowed half is not "simple"
    wall = trimesh.creation.box(extents=(0.05, 1.0, 2.0))
    wall.apply_translation((0.0, 0.5, 0.0))
    scene = trimesh.util.concatenate([plane, wall])
    scene.export(tmp_path / "wall.ply")
    geometry = load_geometry(str(tmp_path / "wall.ply"))
    s = sample_surface(geometry, 6000, seed=1)
    t = compute_transfer(geometry, s.points, s.normals, rays=64)
    merged = segment_samples(s.points, s.object_ids, t, normals=s.normals, max_segments=8, min_samples=50, by_object=False)
    assert 1 < merged.count < merged.leaves_before_merge
    assert (merged.residual_rms <= 0.01 + 1e-12).sum() >= 1


def test_dim_complex_objects_do_not_merge_past_twice_the_budgets_share():
    """Rooms of a building: many objects whose transfer is dim, so the PCA residual of any union is
    under the absolute tolerance, yet not explained by the subspace relative to its size.  Without
    the share limit they all merge into one segment; with it a union holds at most MERGE_SHARE x
    samples / budget samples (an unshadowed plane, explained exactly, still merges whole: above)."""
    from prt.train.networks.segments import MERGE_EXACT, MERGE_SHARE, _Moments

    rng = np.random.default_rng(3)
    per, objects, budget = 200, 16, 8
    ids = np.repeat(np.arange(objects), per)
    points = np.column_stack([ids * 0.1 + rng.uniform(0, 0.1, len(ids)), rng.uniform(0, 0.1, (len(ids), 2))])  # a row of touching boxes
    transfer = 0.002 * rng.standard_normal((len(ids), 16))
    transfer[:, 0] += 0.01
    everything = _Moments.of(transfer)
    assert everything.residual_rms(8) < 0.01  # the absolute test alone passes the whole row
    assert everything.residual_rms(8) > MERGE_EXACT * everything.rms()
    seg = segment_samples(points, ids, transfer, normals=None, max_segments=budget, delta=0.02, min_samples=50)
    counts = np.bincount(seg.home)
    assert counts.max() <= MERGE_SHARE * len(ids) / budget
    assert len(ids) / (MERGE_SHARE * len(ids) / budget) <= seg.count < seg.leaves_before_merge  # merges, up to the share (the old rule: 1)


def test_an_object_without_samples_still_gets_a_segment(cornell):
    geometry, s, t = cornell
    light = geometry.object_names.index("light")
    keep = s.object_ids != light  # as if the small light had received no samples
    seg = segment_samples(s.points[keep], s.object_ids[keep], t[keep], normals=s.normals[keep], max_segments=6, min_samples=50)
    assert all(len(m) > 0 for m in seg.members)
    probe = np.array([[0.0, 0.99, 0.0]])
    got = seg.assign(probe, np.array([light]))
    assert 0 <= got[0] < seg.count


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError, match="no samples"):
        segment_samples(np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 16)), normals=np.zeros((0, 3)))
    with pytest.raises(ValueError, match="NaN"):
        segment_samples(np.full((4, 3), np.nan), np.zeros(4, int), np.zeros((4, 16)), normals=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        segment_samples(np.zeros((4, 3)), np.zeros(4, int), np.zeros((4, 16)), normals=np.full((4, 3), np.nan))
    with pytest.raises(ValueError, match="differ in length"):
        segment_samples(np.zeros((4, 3)), np.zeros(4, int), np.zeros((4, 16)), normals=np.zeros((3, 3)))


def _floor_and_column(rng, n_floor=6000, n_column=4000):
    """A square floor at y = -0.5 (1 wide) holding most samples, and a column 2 tall standing on it:
    y is the longest side and the y-median of the samples lies on the floor (a creature on a slab)."""
    floor = np.column_stack([rng.uniform(-0.5, 0.5, n_floor), np.full(n_floor, -0.5), rng.uniform(-0.5, 0.5, n_floor)])
    angle = rng.uniform(0.0, 2 * np.pi, n_column)
    column = np.column_stack([0.2 * np.cos(angle), rng.uniform(-0.5, 1.5, n_column), 0.2 * np.sin(angle)])
    return np.concatenate([floor, column])


def test_split_value_is_the_median_unless_a_plane_of_samples_lies_there():
    from prt.train.networks.segments import PLANE_TOLERANCE, split_value

    rng = np.random.default_rng(0)
    smooth = rng.uniform(-1.0, 1.0, 10001)
    assert split_value(smooth) == np.median(smooth)
    plane = np.concatenate([np.full(3000, 0.25), rng.uniform(-1.0, 1.0, 4000)])
    assert np.median(plane) == 0.25  # the plain median cuts through the plane
    cut = split_value(plane)
    tol = PLANE_TOLERANCE * (plane.max() - plane.min())
    assert abs(cut - 0.25) >= tol * 0.999  # off the plane by the tolerance
    assert 0 < np.count_nonzero(plane <= cut) < len(plane)


def test_fragments_a_hair_off_a_floor_take_the_floor_samples_segment():
    """A kd cut through the floor put its samples in one segment and the runtime's fragments,
    1e-4 above it (sphere tracing stops short), in another: the creature's floor rendered at 26 dB."""
    rng = np.random.default_rng(1)
    points = _floor_and_column(rng)
    transfer = rng.normal(size=(len(points), 4))
    seg = segment_samples(points, np.zeros(len(points), np.int64), transfer, normals=None, max_segments=2, merge=False, min_samples=50)
    assert seg.nodes[0]["axis"] == 1  # the cut is along y, the longest side
    on_floor = points[:, 1] == -0.5
    home = np.unique(seg.home[on_floor])
    assert len(home) == 1  # the floor's samples sit in one segment
    zero = np.zeros(int(on_floor.sum()), np.int64)
    for lift in (1e-4, -1e-4, 1e-6, -1e-6):
        assert np.array_equal(seg.assign(points[on_floor] + [0.0, lift, 0.0], zero), np.full(len(zero), home[0])), lift


def test_precompute_key_changes_only_where_the_off_plane_rule_moves_a_cut(tmp_path):
    """A build whose cuts the rule leaves alone keeps its key (and so its cached fits), also when its
    folder predates the rule; the creature, whose y-median lies on its ground slab, gets a new one."""
    import json

    from prt.train.transport.precompute import PrecomputeSettings, run_precompute
    from prt.train.networks.segments import SPLIT_RULE

    settings = PrecomputeSettings(samples=4000, validation=500, rays=16)
    keys = {}
    for name, source in (("cornell", str(DATA / "CornellBox-Original.obj")), ("creature", "creature")):
        geometry, out, logs = load_geometry(source), tmp_path / name, []
        first = run_precompute(geometry, out, settings, progress=False, log=logs.append)
        assert first["split_rule"] == SPLIT_RULE
        moved = [line for line in logs if "moved off a plane" in line]
        # a folder from before the rule (no split_rule recorded) is segmented again, not trusted
        old = json.loads((out / "precompute.json").read_text())
        old.pop("split_rule")
        (out / "precompute.json").write_text(json.dumps(old))
        logs.clear()
        again = run_precompute(geometry, out, settings, progress=False, log=logs.append)
        assert not any("up to date" in line for line in logs) and again["key"] == first["key"]
        logs.clear()
        assert run_precompute(geometry, out, settings, progress=False, log=logs.append)["key"] == first["key"]
        assert any("up to date" in line for line in logs)
        keys[name] = (first["key"], bool(moved))
    assert keys["cornell"][1] is False and keys["creature"][1] is True
    # the unmoved build's key is the one made before the off-plane rule: sha1 of geometry, settings, the margin's rule, format
    from dataclasses import asdict
    import hashlib

    from prt.train.transport.precompute import FORMAT_VERSION, _geometry_key

    from prt.train.networks.segments import MARGIN_RULE, MERGE_RULE

    keyed = {k: v for k, v in asdict(settings).items() if k not in ("adaptive", "split", "sdf_trace")}
    plain = hashlib.sha1(json.dumps([_geometry_key(load_geometry(str(DATA / "CornellBox-Original.obj"))),
                                     {**keyed, "margin": MARGIN_RULE, "merge": MERGE_RULE}, FORMAT_VERSION]).encode()).hexdigest()[:16]  # fmt: skip
    # the margin's and the merge's rules are keyed: fits made on the segments of an older rule are not reused
    for older_keyed in (keyed, {**keyed, "margin": MARGIN_RULE}):
        older = hashlib.sha1(json.dumps([_geometry_key(load_geometry(str(DATA / "CornellBox-Original.obj"))), older_keyed, FORMAT_VERSION]).encode()).hexdigest()[:16]
        assert older != plain
    from prt.train.transport.precompute import precompute_key, scene_sides

    cornell = load_geometry(str(DATA / "CornellBox-Original.obj"))
    assert precompute_key(cornell, settings) == plain
    # samples on reachable sides only (prt.train.inputs.visibility): keyed where the sides change
    sides = scene_sides(cornell, seed=settings.seed, log=lambda *_: None)
    assert keys["cornell"][0] == (precompute_key(cornell, settings, sides) if sides.changed else plain) and keys["creature"][0] != plain


def _unexplained(points, transfer, seg, rank=8):
    """Sum over leaves of count x RMS residual^2 of a rank-``rank`` PCA: what per-leaf fits must explain beyond it."""
    from prt.train.networks.segments import _Moments

    leaves = [seg.assign(points, np.zeros(len(points), int)) == k for k in range(seg.count)]
    return sum(m.sum() * _Moments.of(transfer[m]).residual_rms(rank) ** 2 for m in leaves)


def test_residual_split_puts_leaves_where_the_transfer_is_complex(tmp_path):
    """A plane with a small box standing near one corner (real ray-traced transfer): cutting the leaf
    with the most unexplained transfer leaves less unexplained in all than cutting the biggest, its
    small leaves crowd round the box, and the open plane, which only sees the sky, stays one big leaf."""
    plane = trimesh.Trimesh([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 2, 1], [0, 3, 2]])
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    box.apply_translation((0.6, 0.15, 0.6))  # x and z keep their scale in the loaded geometry
    trimesh.util.concatenate([plane, box]).export(tmp_path / "box.ply")
    geometry = load_geometry(str(tmp_path / "box.ply"))
    s = sample_surface(geometry, 8000, seed=2)
    t = compute_transfer(geometry, s.points, s.normals, rays=64)
    ids = np.zeros(len(s), int)
    common = dict(max_segments=8, min_samples=50, by_object=False, merge=False)
    plain = segment_samples(s.points, ids, t, normals=s.normals, split="samples", **common)
    complex_first = segment_samples(s.points, ids, t, normals=s.normals, split="residual", **common)
    assert plain.count == complex_first.count == 8
    assert np.array_equal(complex_first.assign(s.points, ids), complex_first.home)  # the runtime's rule still holds
    assert _unexplained(s.points, t, complex_first) < 0.5 * _unexplained(s.points, t, plain)
    sizes = np.bincount(complex_first.home)
    assert np.bincount(plain.home).max() <= 1.2 * np.bincount(plain.home).min()  # equal areas
    assert sizes.max() >= 8 * sizes.min()
    near_box = [k for k in range(8) if complex_first.bounds[k, 1, 0] >= 0.45 and complex_first.bounds[k, 1, 2] >= 0.45]
    far = int(np.argmax(sizes))
    assert len(near_box) >= 5 and far not in near_box and sizes[far] >= 0.4 * len(s)
    # its dim weight is the relative loss's (segments.py keeps its own copy to stay free of torch)
    from prt.train.networks.fit import RELATIVE_FLOOR
    from prt.train.networks.segments import DIM_FLOOR

    assert DIM_FLOOR == RELATIVE_FLOOR
    # the default is the equal-area split, and an unknown rule is refused
    assert np.array_equal(segment_samples(s.points, ids, t, normals=s.normals, **common).home, plain.home)
    with pytest.raises(ValueError, match="split: expected one of samples, residual"):
        segment_samples(s.points, ids, t, normals=s.normals, split="area", **common)


def test_split_rule_is_keyed_only_when_not_the_default_and_reuses_the_ray_traced_transfer(tmp_path):
    from prt.runtime.errors import SpecError
    from prt.train.transport.precompute import PrecomputeSettings, check_settings, run_precompute

    geometry = load_geometry(str(DATA / "CornellBox-Original.obj"))
    out, logs = tmp_path / "pre", []
    plain = run_precompute(geometry, out, PrecomputeSettings(samples=4000, validation=500, rays=16), progress=False, log=logs.append)
    cache = sorted(p.name for p in (out / "cache").rglob("*") if p.is_file())
    residual = run_precompute(geometry, out, PrecomputeSettings(samples=4000, validation=500, rays=16, split="residual"),
                              progress=False, log=logs.append)  # fmt: skip
    assert residual["key"] != plain["key"] and residual["settings"]["split"] == "residual"
    assert sorted(p.name for p in (out / "cache").rglob("*") if p.is_file()) == cache  # no new ray tracing
    with pytest.raises(SpecError, match="--split: expected one of samples, residual"):
        check_settings(PrecomputeSettings(split="area"), flags=True)


def test_a_build_spec_names_a_bad_split_rule():
    from prt.runtime.errors import SpecError
    from prt.train.build import spec_from_dict

    assert spec_from_dict({"geometry": "creature", "split": "residual"}).precompute.split == "residual"
    with pytest.raises(SpecError, match=r"^split: expected one of samples, residual, got 'area'$"):
        spec_from_dict({"geometry": "creature", "split": "area"})
    with pytest.raises(SpecError, match=r"^split: expected str, got int 3$"):
        spec_from_dict({"geometry": "creature", "split": 3})
