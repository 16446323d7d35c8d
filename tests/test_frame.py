"""The ONNX backend's fast frame against its plain twins (issue 18).

- :func:`segment_sort` (counting sort) lists exactly what :func:`segment_sort_reference` (one pass
  per segment) lists;
- :meth:`OnnxTransfer.compute` (counting sort, packed inference, one scatter) equals
  :meth:`OnnxTransfer.compute_reference` (the pre-issue path) bit for bit;
- a Renderer frame (targets read as they are, packed transfer, shaded rows scattered once) equals
  the frame built the old way (interleaved ``read_packed``, ``compute_reference``, pixel-ordered
  shading), bit for bit, diffuse and glossy;
- back-face culling of a mesh without two-sided faces draws the same G-buffer as the shader's discard.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from prt.runtime import InputError
from prt.runtime.backends.onnx import OnnxTransfer, segment_sort, segment_sort_reference
from prt.runtime.gbuffer import PACKED_COLUMNS, PACKED_SEGMENT
from prt.runtime.renderer import Renderer, Scene, demo_scene_path
from prt.runtime.shading import shade

SIZE = 80


@pytest.mark.parametrize("n_segments", [1, 4, 300, 70000])
def test_segment_sort_equals_its_reference(n_segments):
    rng = np.random.default_rng(n_segments)
    for pixels in (0, 1, 257, 5000):
        segment = rng.integers(-1, n_segments, pixels)
        segment[rng.random(pixels) < 0.3] = -1
        for dtype in (np.int16, np.int32, np.int64):
            if n_segments >= np.iinfo(dtype).max:
                continue
            got, want = segment_sort(segment.astype(dtype), n_segments), segment_sort_reference(segment.astype(dtype), n_segments)
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
            assert got[1][-1] == np.count_nonzero(segment >= 0)


def test_segment_sort_refuses_unknown_segments():
    with pytest.raises(InputError, match="segment 4 appears in the G-buffer"):
        segment_sort(np.array([0, 4, -1], dtype=np.int16), 4)
    with pytest.raises(InputError, match="segment 4 appears in the G-buffer"):
        segment_sort_reference(np.array([0, 4, -1], dtype=np.int16), 4)


@pytest.fixture(scope="module")
def demo():
    return Scene.load()


@pytest.fixture(scope="module")
def closed_spot(tmp_path_factory):
    """The demo without its ground disc (an open, two-sided surface): Spot alone, a closed mesh."""
    folder = tmp_path_factory.mktemp("spot") / "demo"
    shutil.copytree(demo_scene_path().parent, folder)
    with np.load(folder / "geometry.npz") as g:
        mesh = dict(g)
    keep = mesh["object_ids"] == 0
    assert not mesh["two_sided"][keep].any()
    np.savez(folder / "geometry.npz", **{k: mesh[k][keep] if k in ("faces", "object_ids", "two_sided") else mesh[k] for k in mesh})
    return Scene.load(folder)


def _old_frame(r: Renderer, engine: OnnxTransfer, material):
    """The frame as the renderer made it before issue 18: from the interleaved G-buffer, pixel order."""
    r.gbuffer.render(r.camera)
    r.ctx.finish()
    packed = r.gbuffer.read_packed().copy()
    covered, transfer = engine.compute_reference(packed, packed[:, PACKED_SEGMENT].astype(np.int32), columns=PACKED_COLUMNS)
    if material.kind == "diffuse":
        light = (r.lighting.sh * np.asarray(material.albedo)).astype(np.float32)
        radiance = np.maximum(transfer @ light, 0.0)
    else:
        rows = packed[covered]
        radiance = shade(transfer, rows[:, 4:7], r.camera.eye[None, :] - rows[:, 0:3], r.lighting, material)
    image = np.zeros((r.height * r.width, 3), dtype=np.float32)
    image[covered] = radiance
    full = np.zeros((r.height * r.width, transfer.shape[1]), dtype=np.float32)
    full[covered] = transfer
    return image.reshape(r.height, r.width, 3), full.reshape(r.height, r.width, -1), packed, covered, transfer


def test_compute_equals_the_reference_path(gl_ctx, demo):
    with Renderer(demo, SIZE, SIZE, backend="onnx", ctx=gl_ctx) as r:
        engine = r._backend().engine
        r.gbuffer.render(r.camera)
        packed = r.gbuffer.read_packed().copy()
        segment = packed[:, PACKED_SEGMENT].astype(np.int32)
        covered, transfer = engine.compute(packed, segment, columns=PACKED_COLUMNS)
        ref_covered, ref_transfer = engine.compute_reference(packed, segment, columns=PACKED_COLUMNS)
        assert len(covered) > 100
        assert np.array_equal(covered, ref_covered) and np.array_equal(transfer, ref_transfer)
        assert set(engine.timings) == {"pack", "inference", "scatter"}


@pytest.mark.parametrize("threads", [1, 2])
def test_frames_equal_the_pre_issue_path(gl_ctx, demo, threads):
    with Renderer(demo, SIZE, SIZE + 7, backend="onnx", threads=threads, ctx=gl_ctx) as r:
        r.set_background(False)  # the pre-issue frame drew no env-map background
        engine = r._backend().engine
        engine.slice_rows = 700  # several slices per segment, as at full size
        for step, glossy in enumerate([False, True, False]):
            r.set_camera_object(r.camera.orbit(0.7 * step))
            if glossy:
                r.set_material("glossy", albedo=(0.5, 0.5, 0.5), specular=(0.4, 0.4, 0.4), exponent=16)
            else:
                r.set_material("diffuse", albedo=(0.6, 0.7, 0.8))
            image = r.render()
            assert set(r.timings) >= {"gbuffer", "readback", "pack", "inference", "shade", "readout", "frame"}
            ref_image, ref_transfer, packed, covered, _ = _old_frame(r, engine, r.material)
            assert np.array_equal(image, ref_image)
            assert np.array_equal(r.render_transfer(), ref_transfer)
            # The packed rows are the covered pixels, their inputs and segments.
            assert np.array_equal(np.sort(r._covered), covered)
            assert np.array_equal(r._inputs, packed[r._covered][:, list(PACKED_COLUMNS)])


def test_culling_draws_the_same_gbuffer(gl_ctx, demo, closed_spot):
    with Renderer(demo, SIZE, SIZE, ctx=gl_ctx) as r:
        assert not r.gbuffer._cull  # the demo's ground disc is two-sided: no culling
    with Renderer(closed_spot, SIZE, SIZE, ctx=gl_ctx) as r:
        gpass = r.gbuffer
        assert gpass._cull  # Spot alone is closed
        for angle in (0.0, 2.0, 4.0):
            camera = r.camera.orbit(angle)
            gpass.render(camera)
            culled = gpass.read_packed().copy()
            gpass._cull = False
            try:
                gpass.render(camera)
                assert np.array_equal(gpass.read_packed(), culled)
            finally:
                gpass._cull = True


def test_compute_refuses_unknown_segments(gl_ctx, demo):
    with Renderer(demo, 8, 8, ctx=gl_ctx) as r:
        engine = r._backend().engine
        inputs = np.zeros((3, 6), dtype=np.float32)
        for method in (engine.compute, engine.compute_reference):
            with pytest.raises(InputError, match="appears in the G-buffer but the scene has no such segment"):
                method(inputs, np.array([0, 10**9, -1]))
