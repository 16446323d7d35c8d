"""The ONNX backend's fast frame against its plain twins (issue 18).

- :func:`segment_sort` (counting sort) lists exactly what :func:`segment_sort_reference` (one pass
  per segment) lists;
- :meth:`OnnxTransfer.compute` (counting sort, packed inference, one scatter) equals
  :meth:`OnnxTransfer.compute_reference` (the pre-issue path) bit for bit;
- a Renderer frame (targets read as they are, packed transfer, shaded rows scattered once) equals
  the frame built the old way (interleaved ``read_packed``, ``compute_reference``, pixel-ordered
  shading), bit for bit, diffuse and glossy;
- back-face culling of closed faces (their own draw, two-sided faces in a second one without
  culling) draws the same G-buffer as one draw with the shader's discard alone, whatever the
  order of the faces in the file;
- the triangles that lie wholly in one k-d leaf, drawn with their segment as an attribute (no
  descent per fragment), draw the same G-buffer as every fragment descending the tree; every point
  of such a triangle has that segment by :func:`segment_of`;
- the env-map background drawn only where the G-buffer's depth says no geometry is equals the
  full-screen layer there, and a frame built on it equals the frame composited the old way;
- ``all_finite``, ``scatter_rows`` and ``take_rows`` equal ``np.isfinite(...).all()``, ``image[rows] = values`` and ``array[rows]``.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from prt.runtime import InputError
from prt.runtime.camera import Camera
from prt.runtime.backends.onnx import OnnxTransfer, segment_sort, segment_sort_reference
from prt.runtime.gbuffer import PACKED_COLUMNS, PACKED_SEGMENT
from prt.runtime.renderer import Renderer, Scene, all_finite, demo_scene_path
from prt.runtime.segmentation import scatter_rows, take_rows
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
        engine.batched = False  # the per-segment sessions, bit for bit (the stacked models: tests/test_onnx_stack.py)
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
        engine.batched = False  # the per-segment sessions, bit for bit (the stacked models: tests/test_onnx_stack.py)
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


@pytest.fixture(scope="module")
def shuffled_demo(tmp_path_factory):
    """The demo with its faces shuffled: two-sided (ground) faces among and before the closed ones."""
    folder = tmp_path_factory.mktemp("shuffled") / "demo"
    shutil.copytree(demo_scene_path().parent, folder)
    with np.load(folder / "geometry.npz") as g:
        mesh = dict(g)
    order = np.random.default_rng(3).permutation(len(mesh["faces"]))
    assert mesh["two_sided"][order][:100].any()  # some two-sided face comes early
    np.savez(folder / "geometry.npz", **{k: mesh[k][order] if k in ("faces", "object_ids", "two_sided") else mesh[k] for k in mesh})
    return Scene.load(folder)


def _targets(gpass, camera):
    gpass.render(camera)
    return gpass.read_packed().copy(), gpass.read(depth=True).depth


@pytest.mark.parametrize("scene", ["demo", "closed_spot", "shuffled_demo"])
def test_culling_draws_the_same_gbuffer(gl_ctx, scene, request):
    with Renderer(request.getfixturevalue(scene), SIZE, SIZE + 5, ctx=gl_ctx) as r:
        gpass = r.gbuffer
        assert gpass.cull and gpass._closed_vertices == 3 * 5856  # Spot's faces, culled in their own draw
        two_sided = gpass._vertices - gpass._closed_vertices
        assert two_sided == (0 if scene == "closed_spot" else 3 * 48)
        for angle in (0.0, 2.0, 4.0):
            # from above and from below the ground disc (its back side)
            for camera in (r.camera.orbit(angle), Camera(eye=(2.5 * np.sin(angle), -1.2, 2.5 * np.cos(angle)), target=(0, 0, 0))):
                culled, culled_depth = _targets(gpass, camera)
                gpass.cull = False  # the reference twin: one draw, the shader's discard alone
                try:
                    plain, plain_depth = _targets(gpass, camera)
                finally:
                    gpass.cull = True
                assert (culled[:, 3] > 0.5).sum() > 100
                assert np.array_equal(culled, plain) and np.array_equal(culled_depth, plain_depth)


@pytest.mark.parametrize("scene", ["demo", "closed_spot", "shuffled_demo"])
def test_known_segments_draw_the_same_gbuffer(gl_ctx, scene, request):
    with Renderer(request.getfixturevalue(scene), SIZE, SIZE + 5, ctx=gl_ctx) as r:
        gpass = r.gbuffer
        assert gpass.known_segments
        known = sum(count for _, count, _, has in gpass._ranges if has)
        assert 0 < gpass._vertices - known < known  # most triangles take their segment along
        for angle in (0.0, 2.0, 4.0):
            for camera in (r.camera.orbit(angle), Camera(eye=(2.5 * np.sin(angle), -1.2, 2.5 * np.cos(angle)), target=(0, 0, 0))):
                fast, fast_depth = _targets(gpass, camera)
                gpass.known_segments = False  # the reference twin: every fragment descends the tree
                try:
                    plain, plain_depth = _targets(gpass, camera)
                finally:
                    gpass.known_segments = True
                assert len(np.unique(fast[fast[:, 3] > 0.5, PACKED_SEGMENT])) >= 2
                assert np.array_equal(fast, plain) and np.array_equal(fast_depth, plain_depth)


def test_face_segments_follow_the_rule(demo):
    from prt.runtime.gbuffer import segment_tables
    from prt.runtime.segmentation import face_segments, segment_of

    manifest = demo.manifest
    tables = segment_tables(manifest, np.array([0, 1]))
    rng = np.random.default_rng(5)
    # Triangles of every size around the demo's splits (z = -0.0799 for Spot, x = -0.0033 for the ground).
    centre = rng.uniform(-0.3, 0.3, (4000, 1, 3))
    corners = (centre + rng.normal(size=(4000, 3, 3)) * np.exp(rng.uniform(-9, -1, (4000, 1, 1)))).astype(np.float32)
    ids = rng.integers(0, 3, 4000)  # object 2 has no root: the nearest-box rule, never known
    known = face_segments(corners, ids, tables["nodes"], tables["roots"][:2])
    assert (known[ids == 2] == -1).all()
    assert (known[ids == 1] == 1).all()  # both sides of the ground's split are segment 1
    spot = ids == 0
    assert 100 < (known[spot] == -1).sum() < spot.sum() - 100  # across the split, and not
    w = rng.dirichlet(np.ones(3), (4000, 16))  # points inside each triangle, corners included
    w[:, :3] = np.eye(3)
    points = np.einsum("fkc,fcd->fkd", w, corners.astype(np.float64)).astype(np.float32)
    rule = segment_of(manifest, points.reshape(-1, 3), np.repeat(ids, 16)).reshape(-1, 16)
    has = known >= 0
    assert (rule[has] == known[has, None]).all()


def test_face_order_does_not_change_the_gbuffer(gl_ctx, demo, shuffled_demo):
    with Renderer(demo, SIZE, SIZE, ctx=gl_ctx) as a, Renderer(shuffled_demo, SIZE, SIZE, ctx=gl_ctx) as b:
        for angle in (0.5, 3.0):
            camera = a.camera.orbit(angle)
            assert np.array_equal(_targets(a.gbuffer, camera)[0], _targets(b.gbuffer, camera)[0])


def test_background_drawn_only_where_nothing_is_covered(gl_ctx, demo):
    with Renderer(demo, SIZE, SIZE + 3, ctx=gl_ctx) as r:
        r.set_background(True)
        for step in range(3):
            r.set_camera_object(r.camera.orbit(1.3 * step))
            r.render()
            covered = r.gbuffer_image().covered
            assert covered.any() and (~covered).any()
            background = r._background
            full = background.image(r.camera, r._envmap_rotation).copy()  # the reference: every pixel
            assert full.min() > 0  # the map is positive everywhere
            sentinel = np.full((r.height, r.width, 3), -1.0, dtype=np.float32)
            background.target.write(sentinel.tobytes())
            layer = background.image(r.camera, r._envmap_rotation, r.gbuffer.depth_texture)
            assert np.array_equal(layer[~covered], full[~covered])
            assert (layer[covered] == -1).all()  # nothing drawn (nor cleared) under geometry
            assert np.array_equal(r._background_layer()[~covered], full[~covered])  # what the renderer uses


def test_background_drawn_with_the_gbuffer_is_read_back_once_and_redrawn_for_a_new_gbuffer(gl_ctx, demo, monkeypatch):
    """An ONNX frame draws the layer right after the G-buffer's pass and reads it back when it is assembled:
    one draw per G-buffer, the same pixels as drawing at assembly; a new G-buffer (a deformed pose behind the
    same camera) is drawn again, never a stale layer."""
    with Renderer(demo, SIZE, SIZE, ctx=gl_ctx) as r:
        r.set_background(True)
        background_draws, events = [], []
        r.render()
        background, backend = r._background, r._backend()
        original, run = background._draw_behind, backend.run
        monkeypatch.setattr(background, "_draw_behind", lambda fbo: (background_draws.append(1), events.append("background"), original(fbo)))
        monkeypatch.setattr(backend, "run", lambda *a: (events.append("network"), run(*a))[1])
        for step in range(2):
            r.set_camera_object(r.camera.orbit(0.9 + step))
            before = len(background_draws)
            events.clear()
            image = r.render()
            assert events == ["background", "network"]  # drawn with the G-buffer, before the networks run
            assert len(background_draws) == before + 1  # read back without a second draw
            covered = r.gbuffer_image().covered
            full = background.image(r.camera, r._envmap_rotation).copy()
            assert np.array_equal(image[~covered], full[~covered])
        view = (r.camera, r._envmap_rotation, r.gbuffer.depth_texture)
        before = len(background_draws)
        background.draw_layer(*view, generation=99)
        background.draw_layer(*view, generation=99)  # drawn already: nothing
        first = background.image(*view, generation=99).copy()
        assert len(background_draws) == before + 1
        background.image(*view, generation=100)  # the same camera, a new G-buffer: drawn again
        assert len(background_draws) == before + 2
        assert np.array_equal(background.image(*view, generation=99), first)  # and back


@pytest.mark.parametrize("backend", ["onnx", "glsl"])
def test_frame_with_background_equals_the_old_composite(gl_ctx, demo, backend):
    with Renderer(demo, 40, 36, backend=backend, ctx=gl_ctx) as r:
        for step in range(2):
            r.set_camera_object(r.camera.orbit(2.1 * step))
            r.set_background(False)
            black = r.render()
            r.set_background(True)
            image = r.render()  # relit: the cached transfer, the background added
            covered = r.gbuffer_image().covered
            layer = r._background.image(r.camera, r._envmap_rotation)  # full-screen reference
            want = black.copy()
            np.copyto(want, layer, where=~covered[..., None])
            assert np.array_equal(image, want)
            assert "background" in r.timings


def test_all_finite_equals_isfinite_all():
    rng = np.random.default_rng(0)
    for shape in [(0, 16), (1, 16), (1000, 16), (7, 3)]:
        base = rng.standard_normal(shape).astype(np.float32)
        assert all_finite(base) == bool(np.isfinite(base).all())
        for bad in (np.nan, np.inf, -np.inf):
            for _ in range(3):
                if not base.size:
                    continue
                a = base.copy()
                a.reshape(-1)[rng.integers(a.size)] = bad
                assert all_finite(a) is False and not np.isfinite(a).all()
    assert all_finite(np.array([3e38, -3e38], np.float32))


def test_scatter_rows_equals_fancy_assignment():
    rng = np.random.default_rng(1)
    for pixels, m, c in [(1000, 300, 3), (64, 0, 3), (500, 500, 4), (100, 10, 16)]:
        rows = rng.choice(pixels, m, replace=False)
        values = rng.standard_normal((m, c)).astype(np.float32)
        for vals in (values, values.astype(np.float64), np.asfortranarray(values)):
            got, want = np.zeros((pixels, c), np.float32), np.zeros((pixels, c), np.float32)
            scatter_rows(got, rows, vals)
            want[rows] = vals
            assert np.array_equal(got, want)


def test_take_rows_equals_fancy_take():
    rng = np.random.default_rng(2)
    for pixels, m, c in [(1000, 300, 6), (64, 0, 6), (500, 500, 64), (100, 10, 1)]:
        rows = rng.integers(0, pixels, m)  # repeats allowed, any order
        for array in (rng.standard_normal((pixels, c)).astype(np.float32), rng.standard_normal((pixels, c)),
                      np.asfortranarray(rng.standard_normal((pixels, c)).astype(np.float32)), rng.standard_normal((pixels, 2 * c))[:, ::2]):
            got = take_rows(array, rows)
            assert got.dtype == array.dtype and got.shape == (m, c) and np.array_equal(got, array[rows])
            if m:
                got[0] += 1.0  # a copy: the array is not touched
                assert not np.array_equal(got[0], array[rows[0]])


def test_compute_refuses_unknown_segments(gl_ctx, demo):
    with Renderer(demo, 8, 8, ctx=gl_ctx) as r:
        engine = r._backend().engine
        inputs = np.zeros((3, 6), dtype=np.float32)
        for method in (engine.compute, engine.compute_reference):
            with pytest.raises(InputError, match="appears in the G-buffer but the scene has no such segment"):
                method(inputs, np.array([0, 10**9, -1]))
