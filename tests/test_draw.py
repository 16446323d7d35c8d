"""A frame drawn where it is shaded, read back only when pixels are asked for (issue 36).

- ``Renderer.draw()`` leaves a GPU-shaded frame (``glsl``) in ``frame_texture``, the background
  composited there, its pixels not read: timings have ``frame`` (and the occlusion-query ``check``),
  no ``frame_readback``; ``read_frame()`` then gives exactly what ``render()`` gives for that view;
- a CPU-shaded frame (``onnx``) has no texture; ``read_frame()`` is its image;
- ``render()`` times the read-back apart from ``frame``;
- every report names the GL renderer (``Renderer.gl_renderer``, the orbit's summary).
"""

from __future__ import annotations

import numpy as np
import pytest

from prt.runtime.errors import RendererStateError
from prt.runtime.orbit import render_orbit
from prt.runtime.renderer import Renderer, Scene


@pytest.fixture(scope="module")
def demo():
    return Scene.load()


def test_glsl_frame_stays_on_the_gpu_until_pixels_are_asked_for(gl_ctx, demo):
    with Renderer(demo, 40, 36, backend="glsl", ctx=gl_ctx) as r:
        with pytest.raises(RendererStateError, match="no frame drawn yet"):
            r.read_frame()
        assert r.frame_texture is None  # nothing drawn yet
        for step in range(2):
            r.set_camera_object(r.camera.orbit(1.7 * step))
            r.draw()
            assert r.frame_texture is not None
            assert {"gbuffer", "network", "shade", "background", "check", "frame"} <= set(r.timings)
            assert "frame_readback" not in r.timings
            drawn = r.read_frame()
            assert "frame_readback" in r.timings
            texture = np.frombuffer(r.frame_texture.read(), np.float32).reshape(36, 40, 4)[::-1]
            assert np.array_equal(texture[..., :3], drawn)  # GL's row order, the background in it
            again = r.render()  # the cached transfer shaded again, then read back
            assert np.array_equal(again, drawn)
            assert r.timings["frame_readback"] > 0 and r.timings["frame"] > 0
        assert "llvmpipe" in r.gl_renderer


def test_onnx_frame_is_on_the_cpu(gl_ctx, demo):
    with Renderer(demo, 40, 36, backend="onnx", ctx=gl_ctx) as r:
        r.draw()
        assert r.frame_texture is None and "frame_readback" not in r.timings
        image = r.read_frame()
        assert np.array_equal(image, r.render())


def test_orbit_summary_names_the_renderer_and_reads_back_apart(gl_ctx, demo, tmp_path):
    with Renderer(demo, 24, 24, backend="glsl", ctx=gl_ctx) as r:
        summary = render_orbit(r, 2, tmp_path / "frames", warmup=0)
    assert summary.renderer == r.gl_renderer
    assert "frame_readback" in summary.median_ms
    text = str(summary)
    assert f"on {summary.renderer}" in text and "read back" in text and "frame_readback" not in text.split("read back")[0]


def test_viewer_title_and_stage_line_name_the_renderer():
    from prt.runtime.viewer import stage_text, title_text

    title = title_text("spot", "glsl", "diffuse", "studio", fps=30.0, size=(512, 512), renderer="NVIDIA H200/PCIe/SSE2")
    assert title.endswith("| NVIDIA H200") and "30.0 FPS" in title
    assert title_text("spot", "onnx", "diffuse", "studio", fps=None, size=None, renderer="llvmpipe (LLVM 15.0.6, 256 bits)").endswith("| llvmpipe")
    assert "on llvmpipe (LLVM" in stage_text(30.0, (64, 64), {"frame": 33.0, "network": 20.0}, "llvmpipe (LLVM 15.0.6, 256 bits)")
