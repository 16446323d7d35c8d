"""Screen-space transfer interpolation (runtime/interpolation.py): the numba path against its numpy twin, the
interpolation's error bounds on synthetic G-buffers with known transfer, and the renderer with it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from prt.runtime import Renderer, Scene
from prt.runtime.interpolation import (
    NORMAL_COS,
    STRIDES,
    TRANSFER_FLOOR,
    TransferInterpolator,
    interpolate_transfer,
    interpolate_transfer_reference,
    check_tolerance,
)
from prt.runtime.errors import ArgumentTypeError, InputError

N = 16


def gbuffer(position, normal, segment):
    """(H, W, 4) position and normal targets as the G-buffer has them (segment id in normal.w, -1 off)."""
    h, w = segment.shape
    pos = np.zeros((h, w, 4), np.float32)
    nrm = np.zeros((h, w, 4), np.float32)
    pos[..., :3] = position
    nrm[..., :3] = normal
    nrm[..., 3] = segment
    off = segment < 0
    pos[off, :3] = 0.0
    nrm[off, :3] = 0.0
    return pos, nrm


def plane(h=64, w=80, depth=None):
    """A plane facing the camera: position (x, y, depth), normal +z, one segment."""
    y, x = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1.2, 1.2, w), indexing="ij")
    z = np.zeros_like(x) if depth is None else depth(x, y)
    position = np.stack([x, y, z], axis=-1)
    normal = np.broadcast_to(np.array([0, 0, 1.0]), position.shape)
    return position, normal, np.zeros((h, w), np.int32)


class Field:
    """A known transfer field f(position, normal, segment) playing the network; counts the rows it gets."""

    def __init__(self, fn):
        self.fn, self.rows = fn, 0

    def __call__(self, inputs, offsets):
        assert inputs.dtype == np.float32 and inputs.shape[1] == 6 and offsets[0] == 0 and offsets[-1] == len(inputs)
        assert np.all(np.diff(offsets) >= 0)
        segment = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))  # the rows come grouped by segment
        self.rows += len(inputs)
        return self.fn(inputs[:, 0:3].astype(np.float64), inputs[:, 3:6].astype(np.float64), segment).astype(np.float32)


def linear(p, n, segment):
    """Transfer linear in position (every coefficient a different plane), offset by segment."""
    k = np.arange(N)
    return 1.0 + 0.1 * k + 0.3 * p[:, 0:1] * np.cos(k) + 0.2 * p[:, 1:2] * np.sin(k) + 0.1 * p[:, 2:3] + 2.0 * segment[:, None]


def both(pos, nrm, tol, fn, n=N):
    """The fast path and the twin on one G-buffer (``n`` coefficients a row); they must agree exactly."""
    fa, fb = Field(fn), Field(fn)
    a = interpolate_transfer(pos, nrm, tol, fa, n)
    b = interpolate_transfer_reference(pos, nrm, tol, fb, n)
    np.testing.assert_array_equal(a.covered, b.covered)
    np.testing.assert_array_equal(a.inferred, b.inferred)
    # the same decisions; values to float32 rounding (each path has its own unshadowed transfer)
    np.testing.assert_allclose(a.transfer, b.transfer, rtol=0, atol=2e-6)
    np.testing.assert_array_equal(a.transfer[a.inferred], b.transfer[b.inferred])
    np.testing.assert_array_equal(a.inputs, b.inputs)
    assert fa.rows == fb.rows == int(a.inferred.sum()), "the network sees exactly the inferred rows"
    return a


def truth(result, fn):
    p, n = result.inputs[:, 0:3].astype(np.float64), result.inputs[:, 3:6].astype(np.float64)
    return fn(p, n, result.segment)


def test_linear_field_is_interpolated_exactly():
    pos, nrm = gbuffer(*plane())
    r = both(pos, nrm, 0.05, linear)
    # Only the coarse grid and the last rows and columns (no neighbour beyond the edge) run the network.
    h, w = 64, 80
    assert r.fraction < 0.2, r.fraction
    y, x = np.divmod(r.covered, w)
    grid = (y % STRIDES[0] == 0) & (x % STRIDES[0] == 0)
    assert r.inferred[grid].all()
    assert not r.inferred[(~grid) & (y < h - 4) & (x < w - 4)].any()
    np.testing.assert_allclose(r.transfer, truth(r, linear), atol=2e-5)


def test_depth_step_is_not_interpolated_across():
    """Two surfaces of one segment with a depth step: no pixel takes a mean across the step."""
    pos, nrm = gbuffer(*plane(depth=lambda x, y: np.where(x > 0.13, -3.0, 0.0)))
    r = both(pos, nrm, 1.0, linear)  # the transfer test accepts anything: the position test must act
    np.testing.assert_allclose(r.transfer, truth(r, linear), atol=2e-5)
    y, x = np.divmod(r.covered, 80)
    step = np.flatnonzero(np.diff(pos[0, :, 2]))[0]  # last column before the step
    assert r.inferred[(x == step) | (x == step + 1)].mean() > 0.4  # the step's sides run the network


def test_segments_and_creases_are_not_interpolated_across():
    position, normal, segment = plane()
    segment = np.where(position[..., 0] > 0.07, 1, 0).astype(np.int32)  # two networks meet at x = 0.07
    normal = normal.copy()
    crease = position[..., 1] > 0.21  # and the normal turns by 60 degrees at y = 0.21
    normal[crease] = [np.sin(np.pi / 3), 0.0, np.cos(np.pi / 3)]
    assert np.cos(np.pi / 3) < NORMAL_COS
    pos, nrm = gbuffer(position, normal, segment)

    def fn(p, n, seg):  # depends on the segment and the normal: a mean across either would be off
        return linear(p, n, seg) + 5.0 * n[:, 0:1]

    r = both(pos, nrm, 1.0, fn)
    np.testing.assert_allclose(r.transfer, truth(r, fn), atol=2e-5)


def test_shadow_edge_error_is_bounded_by_the_tolerance():
    """A soft shadow (a tanh ramp in transfer): every interpolated pixel is within the bound of the
    neighbours' spread, and a tighter tolerance runs more networks."""

    def shadow(p, n, seg):
        k = np.arange(N)
        visible = 0.5 + 0.5 * np.tanh((p[:, 0:1] - 0.2 * p[:, 1:2]) / 0.05)
        return (1.0 + 0.05 * k) * visible + 0.02 * np.cos(7 * p[:, 1:2] + k)

    pos, nrm = gbuffer(*plane(96, 96))
    fractions = []
    for tol in (0.01, 0.05, 0.2):
        r = both(pos, nrm, tol, shadow)
        t = truth(r, shadow)
        err = np.linalg.norm(r.transfer - t, axis=1)
        bound = tol * (np.linalg.norm(t, axis=1) + TRANSFER_FLOOR)
        # the mean of neighbours within tol of each other lies within about tol of the truth between them
        assert np.all(err[~r.inferred] <= 1.5 * bound[~r.inferred] + 1e-5), (tol, float((err / bound).max()))
        np.testing.assert_array_equal(r.transfer[r.inferred], t[r.inferred].astype(np.float32))
        fractions.append(r.fraction)
    assert fractions[0] > fractions[1] > fractions[2], fractions


def test_interreflected_layout_matches_twin():
    """64 coefficients a row (direct, indirect R, G, B): the fast path's two loops (the direct part's
    residuals, then the rest) against the twin, on a soft shadow that refuses some pixels."""

    def shadow64(p, n, seg):
        k = np.arange(64)
        visible = 0.5 + 0.5 * np.tanh((p[:, 0:1] - 0.2 * p[:, 1:2]) / 0.05)
        return (1.0 + 0.05 * k) * visible + 0.02 * np.cos(7 * p[:, 1:2] + k) + 0.1 * n[:, 2:3]

    pos, nrm = gbuffer(*plane(96, 96))
    r = both(pos, nrm, 0.05, shadow64, n=64)
    assert 0.1 < r.fraction < 0.9, r.fraction
    t = shadow64(r.inputs[:, 0:3].astype(np.float64), r.inputs[:, 3:6].astype(np.float64), r.segment)
    # the indirect part (no unshadowed residual) is interpolated too: close to the field where the mean was taken
    err = np.abs(r.transfer[~r.inferred, 16:] - t[~r.inferred, 16:]).max()
    assert err < 0.05 * np.abs(t[:, 16:]).max(), err


def test_bumpy_unoccluded_surface_is_interpolated_exactly():
    """Nothing occludes: the transfer is the unshadowed one of each normal, however the normals wander
    (within the crease angle); the residual is 0, so every interpolation is exact."""
    from prt.runtime.sh import unshadowed_transfer

    position, normal, segment = plane(64, 64)
    x, y = position[..., 0], position[..., 1]
    normal = np.stack([0.3 * np.sin(9 * x + 2 * y), 0.3 * np.cos(7 * y), np.ones_like(x)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    pos, nrm = gbuffer(position, normal, segment)

    def fn(p, n, seg):
        return unshadowed_transfer(n, 4, np.float64).astype(np.float64) * (1.0 + 0.0 * seg[:, None])

    r = both(pos, nrm, 0.01, fn)
    assert r.fraction < 0.12, r.fraction  # the grid and the last rows and columns
    np.testing.assert_allclose(r.transfer, truth(r, fn), rtol=0, atol=3e-6)


def test_silhouettes_and_holes_run_the_network():
    position, normal, segment = plane(48, 48)
    segment = segment.copy()
    segment[(position[..., 0] ** 2 + position[..., 1] ** 2) > 0.8] = -1  # a disc
    segment[20:23, 10:30] = -1  # with a slot
    pos, nrm = gbuffer(position, normal, segment)
    r = both(pos, nrm, 0.5, linear)
    assert len(r.covered) == int((segment >= 0).sum())
    np.testing.assert_allclose(r.transfer, truth(r, linear), atol=2e-5)
    y, x = np.divmod(r.covered, 48)
    next_to_slot = ((y == 19) | (y == 23)) & (x > 10) & (x < 29) & (x % 2 == 1)
    assert r.inferred[next_to_slot].all()


def test_every_row_is_written_after_a_previous_frame():
    """The fast path reuses its arrays between frames: a new frame leaves none of the old values."""
    sampler = TransferInterpolator(0.05, threads=2)
    try:
        big = gbuffer(*plane(64, 80, depth=lambda x, y: 0.3 * x))
        sampler.run(*big, Field(lambda p, n, s: np.full((len(p), N), 1e6)), N)
        sampler.run(*big, Field(lambda p, n, s: np.full((len(p), N), -1e6)), N)  # the other set of arrays
        position, normal, segment = plane(64, 80)
        segment[:, :7] = -1
        pos, nrm = gbuffer(position, normal, segment)
        a = sampler.run(pos, nrm, Field(linear), N)
    finally:
        sampler.close()
    b = interpolate_transfer_reference(pos, nrm, 0.05, Field(linear), N)
    np.testing.assert_array_equal(a.inferred, b.inferred)
    np.testing.assert_allclose(a.transfer, b.transfer, rtol=0, atol=2e-6)
    assert np.abs(a.transfer).max() < 100


def test_real_gbuffer_fast_path_matches_twin(demo_renderer_256):
    r = demo_renderer_256
    r.render()
    pos, nrm = (a.copy() for a in r.gbuffer.read_targets())
    infer = r._backend().engine.infer_sorted

    for tol in (0.02, 0.1):
        a = interpolate_transfer(pos, nrm, tol, infer, N)
        b = interpolate_transfer_reference(pos, nrm, tol, infer, N)
        np.testing.assert_array_equal(a.inferred, b.inferred)
        np.testing.assert_allclose(a.transfer, b.transfer, rtol=0, atol=2e-6)
        assert 0.1 < a.fraction < 0.9


@pytest.fixture(scope="module")
def demo_renderer_256():
    with Renderer(Scene.load(), 256, 256) as r:
        yield r


def psnr(a, b):
    return 10 * np.log10(float(b.max()) ** 2 / float(np.mean((a - b) ** 2)))


def test_renderer_adaptive_matches_exact_and_relights_without_networks(demo_renderer_256):
    exact = demo_renderer_256
    with Renderer(Scene.load(), 256, 256, interpolate=0.05) as r:
        for angle in (0.0, 1.3):
            camera = exact.camera.orbit(angle)
            exact.set_camera_object(camera)
            r.set_camera_object(camera)
            a, e = r.render(), exact.render()
            assert psnr(a, e) > 50, psnr(a, e)
            assert 0.2 < r.stats["network_fraction"] < 0.8
            assert exact.stats["network_fraction"] == 1.0
        runs = r.network_calls
        r.set_envmap("studio")
        exact.set_envmap("studio")
        relit = r.render()
        assert r.network_calls == runs, "relighting runs no network"
        assert psnr(relit, exact.render()) > 50
        exact.set_envmap("potsdamer_platz" if "potsdamer_platz" in r._envmap_sh else "interior")


def test_tolerance_checks():
    assert check_tolerance(None) is None and check_tolerance(0) is None and check_tolerance(0.05) == 0.05
    with pytest.raises(InputError, match="interpolate"):
        check_tolerance(1.5)
    with pytest.raises(InputError, match="interpolate"):
        check_tolerance(float("nan"))
    with pytest.raises(ArgumentTypeError, match="interpolate"):
        check_tolerance("0.05")
    with pytest.raises(InputError, match="Renderer: interpolate"):
        Renderer(Scene.load(), 16, 16, interpolate=-0.1)


def test_cli_refuses_a_bad_tolerance(tmp_path):
    out = subprocess.run([sys.executable, "-m", "prt.runtime.cli", "--headless", "--frames", "1", "--size", "32",
                          "--out", str(tmp_path / "f"), "--interpolate", "2"], capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0 and "--interpolate" in out.stderr, out.stderr
    assert not (tmp_path / "f").exists()


def test_frame_rate_study_compares_two_builds_in_one_run(tmp_path):
    """studies/interpolation_fps.py --against: both scenes' renderers take turns; one row per
    (scene, tolerance), speed-ups over the first scene's every-pixel frames, PSNR against each scene's own."""
    import json
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    demo = root / "runtime" / "data" / "demo" / "scene.json"
    out = tmp_path / "fps.json"
    proc = subprocess.run([sys.executable, str(root / "studies" / "interpolation_fps.py"), "--size", "48", "--views", "2",
                           "--rounds", "1", "--warmup", "1", "--tolerances", "0.1", "--against", str(demo), "--json", str(out)],
                          capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [(r["scene"] == str(demo), r["tolerance"]) for r in rows] == [(True, 0.0), (True, 0.1)] * 2
    assert rows[0]["speedup"] == 1.0 and all(r["speedup"] > 0 and r["fps"] > 0 for r in rows)
    assert rows[0]["psnr_vs_every_pixel_db"] is None and rows[2]["psnr_vs_every_pixel_db"] is None
    assert rows[1]["psnr_vs_every_pixel_db"] > 30 and rows[3]["psnr_vs_every_pixel_db"] > 30
    assert 0 < rows[1]["network_fraction"] <= 1 and rows[0]["network_fraction"] == 1.0
