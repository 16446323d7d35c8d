"""The bounce stage's nearest-sample rule near parallel sheets (issue #13: the Cornell box's light
quad 0.01 below the ceiling), and its fast search against the plain twin."""

from __future__ import annotations

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from scipy.spatial import cKDTree  # noqa: E402

from prt.train.transport.interreflection import NORMAL_WEIGHT, nearest_on_plane, trace_bounce_rays  # noqa: E402
from prt.train.transport.interreflection import nearest_on_plane_reference  # noqa: E402


def test_nearest_on_plane_equals_the_plain_twin():
    rng = np.random.default_rng(0)
    points = rng.uniform(-1, 1, (400, 3))
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    data = np.concatenate([points, NORMAL_WEIGHT * normals], axis=1)
    q = rng.uniform(-1.2, 1.2, (300, 3))
    n = rng.normal(size=(300, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    key = np.concatenate([q, NORMAL_WEIGHT * n], axis=1)
    for bound, options in ((0.3, {}), (np.inf, {}), (0.3, {"candidates": 16, "plane_weight": 16.0})):
        fast = nearest_on_plane(cKDTree(data), key, bound=bound, workers=1, **options)
        plain = nearest_on_plane_reference(data, key, bound=bound, **options)
        assert (fast == plain).all()
    assert (nearest_on_plane(cKDTree(data), key, bound=0.3, workers=1) == -1).any()  # some hits have no sample that near


def _ceiling_and_light(gap: float = 0.01):
    """A two-sided ceiling quad at y = 1 and a smaller two-sided 'light' quad ``gap`` below it, with
    samples on both sides of both, about 0.02 apart (the Cornell box's spacing)."""
    ceiling = trimesh.Trimesh([[-1, 1, -1], [1, 1, -1], [1, 1, 1], [-1, 1, 1]], [[0, 1, 2], [0, 2, 3]], process=False)
    y = 1.0 - gap
    light = trimesh.Trimesh([[-0.3, y, -0.3], [0.3, y, -0.3], [0.3, y, 0.3], [-0.3, y, 0.3]], [[0, 1, 2], [0, 2, 3]], process=False)
    scene = trimesh.util.concatenate([ceiling, light])
    rng = np.random.default_rng(1)
    parts = []
    for height, half, count in ((1.0, 1.0, 20000), (y, 0.3, 1800)):
        xz = rng.uniform(-half, half, (count, 2))
        pts = np.stack([xz[:, 0], np.full(count, height), xz[:, 1]], axis=1)
        side = np.where(np.arange(count) % 2 == 0, 1.0, -1.0)  # both sides at the same places
        parts.append((pts, np.stack([np.zeros(count), side, np.zeros(count)], axis=1)))
    points = np.concatenate([p for p, _ in parts])
    normals = np.concatenate([n for _, n in parts])
    return scene, points, normals, y


def test_hits_on_the_light_underside_take_a_light_sample_not_the_ceiling_above():
    """Before the fix 23 % of these hits took a ceiling sample (inside the gap); now none."""
    scene, points, normals, y = _ceiling_and_light()
    xs = np.linspace(-0.25, 0.25, 12)
    floor = np.stack([np.repeat(xs, len(xs)), np.zeros(len(xs) ** 2), np.tile(xs, len(xs))], axis=1)
    up = np.tile([0.0, 1.0, 0.0], (len(floor), 1))
    found = trace_bounce_rays(scene, floor, up, rays=32, seed=3, targets=(points, normals))
    light_faces = found.hit_face >= 2  # the light's two triangles come after the ceiling's
    assert light_faces.sum() > 300
    chosen = found.nearest[light_faces]
    wrong = (np.abs(points[chosen, 1] - y) > 1e-9) | (normals[chosen, 1] > 0)
    assert wrong.mean() < 0.005


def test_hits_on_the_light_top_take_the_light_not_the_roof():
    """From inside the gap (the ceiling's underside above the light) rays hit the light's top: the
    sample must be the light's top, not the ceiling's roof side 0.01 above (which sees the sky):
    25 % of them took the roof before the fix, 0.3 % now (hits near the light's edge)."""
    scene, points, normals, y = _ceiling_and_light()
    xs = np.linspace(-0.2, 0.2, 10)
    gap = np.stack([np.repeat(xs, len(xs)), np.ones(len(xs) ** 2), np.tile(xs, len(xs))], axis=1)
    down = np.tile([0.0, -1.0, 0.0], (len(gap), 1))
    found = trace_bounce_rays(scene, gap, down, rays=32, seed=4, targets=(points, normals))
    on_light = found.hit_face >= 2
    assert on_light.mean() > 0.8
    chosen = found.nearest[on_light]
    wrong = (np.abs(points[chosen, 1] - y) > 1e-9) | (normals[chosen, 1] < 0)
    assert wrong.mean() < 0.01
