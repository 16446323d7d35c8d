"""The bounce stage's indirect targets averaged over neighbours on the same side
(train/transport/smoothing.py: smooth_indirect) against its plain twin, and what the mean
must and must not do: take out noise, keep the two sides of a sheet and an isolated sample apart."""

from __future__ import annotations

import numpy as np

from prt.train.transport.smoothing import SMOOTH_NEIGHBOURS, smooth_indirect, smooth_indirect_reference


def sheet(count, rng, z=0.0, normal=(0.0, 0.0, 1.0)):
    points = np.column_stack([rng.uniform(0, 1, count), rng.uniform(0, 1, count), np.full(count, z)])
    return points, np.tile(np.asarray(normal, np.float64), (count, 1))


def test_fast_path_equals_the_twin():
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (400, 3))
    normals = rng.normal(size=(400, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    indirect = rng.normal(size=(400, 16, 3)).astype(np.float32)
    for k in (1, 2, SMOOTH_NEIGHBOURS, 20):
        fast = smooth_indirect(points, normals, indirect, k, chunk=97)  # several chunks
        np.testing.assert_allclose(fast, smooth_indirect_reference(points, normals, indirect, k), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(smooth_indirect(points, normals, indirect, 1), indirect)


def test_noise_is_taken_out_and_the_field_kept():
    """A smooth field plus noise on a dense sheet: the mean is closer to the field, by about the
    square root of the neighbours, and no farther from it on average (no bias)."""
    rng = np.random.default_rng(0)
    points, normals = sheet(20000, rng)
    field = (0.2 + 0.1 * np.sin(3 * points[:, 0]) * np.cos(2 * points[:, 1]))[:, None, None] * np.ones((1, 16, 3))
    noisy = (field + rng.normal(0, 0.05, field.shape)).astype(np.float32)
    smooth = smooth_indirect(points, normals, noisy)
    raw_rms = np.sqrt(np.mean((noisy - field) ** 2))
    smooth_rms = np.sqrt(np.mean((smooth - field) ** 2))
    assert smooth_rms < 0.45 * raw_rms, (smooth_rms, raw_rms)  # 1/sqrt(8) = 0.35 for pure noise
    assert abs(float(np.mean(smooth - field))) < 1e-3


def test_sides_of_a_sheet_and_isolated_samples_stay_apart():
    """Two sides of a thin sheet (opposite normals, 1e-4 apart: the lit top, the dark underside) do
    not mix; a sample far from all others keeps its own value."""
    rng = np.random.default_rng(1)
    top, up = sheet(3000, rng, z=1e-4)
    bottom, down = sheet(3000, rng, z=0.0, normal=(0.0, 0.0, -1.0))
    lone = np.array([[5.0, 5.0, 5.0]])
    points = np.vstack([top, bottom, lone])
    normals = np.vstack([up, down, [[0.0, 1.0, 0.0]]])
    indirect = np.zeros((len(points), 16, 3), np.float32)
    indirect[:3000] = 1.0
    indirect[-1] = 7.0
    smooth = smooth_indirect(points, normals, indirect)
    np.testing.assert_array_equal(smooth[:3000], 1.0)
    np.testing.assert_array_equal(smooth[3000:-1], 0.0)
    np.testing.assert_array_equal(smooth[-1], 7.0)
