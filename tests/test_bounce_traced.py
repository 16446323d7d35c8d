"""The bounce stage's first bounce reads the direct transfer traced at a hit where no sample stands for
it (issue 43): no clear candidate, or the clear one farther than TRACE_FAR sample spacings.

A wall stands on a ground lit by a low sun; the ground in the wall's shadow has no samples (as where
the build's sampling leaves a place out).  The rays of the wall's shaded face hit that strip: most of
those hits find no sample of their side within the search's reach and carry nothing, the others read
ground in the sun beyond the shadow (measured once: 63 % and 37 % of them), and the wall's first bounce
came out 32 % low.  Traced there, it matches the per-pixel reference.  The sparse product of
the stage (:func:`bounce_terms`) is checked against a plain loop over the rays."""

from __future__ import annotations

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from prt.runtime import sh  # noqa: E402
from prt.train.transport.interreflection import (  # noqa: E402
    TRACE_FAR, BounceJob, bounce_terms, interreflect, sample_spacing, trace_bounce_rays, trace_stage,
)  # fmt: skip
from prt.train.transport.transfer import EmbreeTracer, compute_transfer  # noqa: E402

HEIGHT, SHADOW = 0.3, 0.3  # the wall's height, its shadow's length (sun at 45 degrees)
SUN = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)  # from +x: the wall's -x face and the ground behind it are in shadow


class _Geometry:  # what compute_transfer and the reference need of a Geometry
    sdf = None

    def __init__(self, mesh):
        self.mesh = mesh


def _light() -> np.ndarray:
    """(16,) a sun lobe from SUN (band-limited, windowed) over a dim sky."""
    return sh.basis(SUN[None], 4)[0] * np.repeat([1.0, 0.8, 0.5, 0.2], [1, 3, 5, 7]) * 4.0 + np.eye(16)[0] * 0.3


@pytest.fixture(scope="module")
def scene():
    ground = trimesh.creation.box(extents=(2.0, 0.02, 2.0))
    ground.apply_translation((0.0, -0.01, 0.0))
    wall = trimesh.creation.box(extents=(0.02, HEIGHT, 1.0))
    wall.apply_translation((0.01, HEIGHT / 2, 0.0))
    mesh = trimesh.util.concatenate([ground, wall])
    points, faces = trimesh.sample.sample_surface_even(mesh, 12000, seed=1)
    normals = mesh.face_normals[faces]
    on_ground = points[:, 1] > -1e-6
    strip = on_ground & (points[:, 0] < 0.0) & (points[:, 0] > -SHADOW - 0.05) & (np.abs(points[:, 2]) < 0.5)
    under = points[:, 1] < -0.01 + 1e-6  # the slab's underside and the wall's foot, never seen
    keep = ~strip & ~under & ~((points[:, 1] < 1e-6) & (np.abs(points[:, 0] - 0.01) < 0.011))
    points, normals, faces = points[keep], normals[keep], faces[keep]
    direct = compute_transfer(_Geometry(mesh), points, normals, rays=64, progress=False)
    return mesh, points, normals, faces, direct


def _stage(mesh, folder, points, normals, faces, direct, rays=64):
    train = {"points": points, "normals": normals, "face_index": faces, "transfer": direct}
    valid = {k: v[:40] for k, v in train.items()}
    return trace_stage(mesh, folder, train, valid, rays=rays, seed=2, threads=2, progress=False, log=lambda line: None)


def test_a_place_without_samples_reads_the_light_traced_there(scene, tmp_path):
    from prt.bench.bounce_reference import indirect_transfer

    mesh, points, normals, faces, direct = scene
    albedo = np.full((len(mesh.faces), 3), 0.8)
    light = _light()
    found = _stage(mesh, tmp_path, points, normals, faces, direct)
    traced = next(bounce_terms(found, albedo, direct, 1))[1].transpose(0, 2, 1) @ light
    clear = (interreflect(direct, trace_bounce_rays(mesh, points, normals, faces, rays=64, seed=2), albedo, 1) - direct[:, :, None])
    clear = clear.transpose(0, 2, 1) @ light
    shaded = np.flatnonzero((normals[:, 0] < -0.9) & (points[:, 1] < HEIGHT / 2) & (np.abs(points[:, 2]) < 0.3))  # the wall's lower shaded face
    assert len(shaded) > 60
    reference = indirect_transfer(_Geometry(mesh), EmbreeTracer(mesh), points[shaded], normals[shaded], albedo, 1, hit_rays=256, rays=64)
    expected = (reference.transpose(0, 2, 1) @ light)[:, 0].mean()
    assert expected > 0.0
    assert abs(clear[shaded, 0].mean() / expected - 1.0) > 0.2  # the case fails without tracing
    assert abs(traced[shaded, 0].mean() / expected - 1.0) < 0.06
    # Away from the strip the hits keep their samples: the open ground reads the same either way.
    far_ground = np.flatnonzero((normals[:, 1] > 0.9) & (points[:, 0] > 0.5))
    assert abs(traced[far_ground, 0].mean() / clear[far_ground, 0].mean() - 1.0) < 0.02


def test_bounce_terms_equal_a_plain_loop_over_the_rays(scene, tmp_path):
    mesh, points, normals, faces, direct = scene
    pick = np.random.default_rng(4).choice(len(points), 1500, replace=False)
    points, normals, faces, direct = points[pick], normals[pick], faces[pick], direct[pick]
    albedo = np.random.default_rng(5).uniform(0.2, 0.9, (len(mesh.faces), 3))
    found = _stage(mesh, tmp_path, points, normals, faces, direct, rays=16)
    rays = found["train"]
    assert (rays.traced >= 0).sum() > 100 and (rays.traced < 0).sum() > 100
    terms = list(bounce_terms(found, albedo, direct, 2))
    previous = np.repeat(direct[:, :, None].astype(np.float64), 3, axis=2)
    for b, term, valid_term in terms:
        for own, got in ((rays, term), (found["validation"], valid_term)):
            plain = np.zeros(got.shape)
            for s in range(len(got)):
                for j in range(own.nearest.shape[1]):
                    a = albedo[own.hit_face[s, j]] if own.hit_face[s, j] >= 0 else 0.0
                    if b == 1 and own.traced[s, j] >= 0:
                        plain[s] += a * own.traced_transfer[own.traced[s, j]][:, None]
                    elif own.nearest[s, j] >= 0:
                        plain[s] += a * previous[own.nearest[s, j]]
            np.testing.assert_allclose(got, plain / own.nearest.shape[1], rtol=1e-9, atol=1e-12)
        previous = term


def test_the_traced_hits_are_those_without_a_near_clear_sample(scene):
    mesh, points, normals, faces, direct = scene
    far = TRACE_FAR * sample_spacing(points, normals)
    job = BounceJob(EmbreeTracer(mesh), points, normals, rays=16, seed=2, workers=1, trace_far=far)
    rows = slice(0, 600)
    nearest, hit_face, traced, transfer = job.traced_chunk(points[rows], normals[rows], 3, faces[rows])
    again = job.chunk(points[rows], normals[rows], 3, faces[rows])  # the same rays, the same choices
    np.testing.assert_array_equal(nearest, again[0])
    np.testing.assert_array_equal(hit_face, again[1])
    _, q, ng = job.hits(points[rows], normals[rows], 3, faces[rows])
    hit = hit_face.reshape(-1) >= 0
    chosen = nearest.reshape(-1)[hit]
    gap = np.where(chosen >= 0, np.linalg.norm(points[np.maximum(chosen, 0)] - q, axis=1), np.inf)
    flagged = traced.reshape(-1)[hit]
    np.testing.assert_array_equal(flagged >= 0, gap > far)
    assert sorted(flagged[flagged >= 0]) == list(range(len(transfer)))
    # The traced transfer is the direct transfer at the hit, on its side: sunlit ground hits see the sky.
    expected = compute_transfer(_Geometry(mesh), q[flagged >= 0], ng[flagged >= 0], rays=512, progress=False)
    assert np.abs(transfer[flagged[flagged >= 0]][:, 0] - expected[:, 0]).mean() < 0.03
    # Deterministic: the same chunk traced again gives the same bytes.
    np.testing.assert_array_equal(job.traced_chunk(points[rows], normals[rows], 3, faces[rows])[3], transfer)
