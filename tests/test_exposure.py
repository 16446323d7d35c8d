"""Auto exposure (prt.runtime.exposure): the log-average rule, its mask, and temporal adaptation."""

import math

import numpy as np
import pytest

from prt.runtime.errors import InputError
from prt.runtime.exposure import (EPS, EXPOSURE_RANGE, KEY, ExposureAdapter, auto_exposure, log_average_luminance,
                                  parse_exposure)


def test_uniform_grey_maps_to_key():
    img = np.full((8, 8, 3), 0.02, dtype=np.float32)
    e = auto_exposure(img)
    assert e == pytest.approx(KEY / (0.02 + EPS), rel=1e-5)


def test_log_average_is_geometric_mean():
    rng = np.random.default_rng(1)
    lum = rng.uniform(0.01, 3.0, size=(16, 16))
    img = np.repeat(lum[..., None], 3, axis=-1)  # grey: luminance = value (weights sum to 1)
    want = math.exp(np.mean(np.log(EPS + lum)))
    assert log_average_luminance(img) == pytest.approx(want, rel=1e-9)
    assert auto_exposure(img) == pytest.approx(KEY / want, rel=1e-9)


def test_mask_excludes_background_and_scale_invariance():
    img = np.zeros((4, 4, 3))
    img[:2] = 0.5
    img[2:] = 50.0  # background: bright sky, not covered
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    assert auto_exposure(img, mask) == pytest.approx(KEY / (0.5 + EPS))
    # ten times darker frame, ten times the exposure (away from EPS and the clip)
    assert auto_exposure(img * 0.1, mask) == pytest.approx(10 * auto_exposure(img, mask), rel=5e-3)


def test_empty_black_and_clip():
    img = np.ones((4, 4, 3))
    assert auto_exposure(img, np.zeros((4, 4), bool)) == 1.0
    assert auto_exposure(np.zeros((4, 4, 3))) == 1.0
    assert auto_exposure(np.full((2, 2, 3), 1e-3)) == pytest.approx(KEY / (1e-3 + EPS))
    assert auto_exposure(np.full((2, 2, 3), 1e-5)) == EXPOSURE_RANGE[1]  # nearly black: the clip
    assert auto_exposure(np.full((2, 2, 3), 1e6)) == EXPOSURE_RANGE[0]
    bad = np.full((2, 2, 3), 0.5)
    bad[0, 0] = np.nan
    assert math.isfinite(auto_exposure(bad))
    with pytest.raises(InputError, match="covered_mask"):
        auto_exposure(img, np.ones((3, 3), bool))


def test_adapter_first_frame_exact_then_smooth():
    a = ExposureAdapter(tau=0.5)
    assert a.update(4.0, 1 / 30) == 4.0
    v = a.update(16.0, 1 / 30)
    assert 4.0 < v < 16.0
    # log-space step: fraction 1 - exp(-dt/tau)
    frac = 1 - math.exp(-(1 / 30) / 0.5)
    assert math.log(v) == pytest.approx(math.log(4) + (math.log(16) - math.log(4)) * frac)
    for _ in range(300):
        v = a.update(16.0, 1 / 30)
    assert v == pytest.approx(16.0, rel=1e-6)
    # steady target, steady exposure
    assert a.update(16.0, 1 / 30) == pytest.approx(v)


def test_parse_exposure():
    assert parse_exposure("auto") == "auto"
    assert parse_exposure("AUTO") == "auto"
    assert parse_exposure("2.5") == 2.5
    for bad in ("-1", "nan", "bright"):
        with pytest.raises(InputError, match="--exposure"):
            parse_exposure(bad)


# --------------------------------------------------------------------------- on a renderer's frame


@pytest.mark.parametrize("background", [False, True])
def test_gpu_log_average_matches_the_numpy_twin(gl_ctx, background):
    """The glsl backend's frame stays on the GPU: its tiles' log-luminance sums (shaders/log_luminance.frag)
    give the exposure numpy gives on the same frame read back, over the same covered pixels."""
    from prt.runtime import Renderer, Scene
    from prt.runtime.exposure_gl import LogLuminanceReduction

    with Renderer(Scene.load(), 72, 56, backend="glsl", ctx=gl_ctx) as r:  # not a multiple of the 16-pixel tile
        r.set_background(background)
        image = r.render()
        mask = r.covered_mask()
        assert 0 < mask.sum() < mask.size and (image[~mask].sum() > 0) == background
        gpu = r.frame_exposure()
        assert gpu == pytest.approx(auto_exposure(image, mask), rel=1e-5)
        assert gpu != pytest.approx(auto_exposure(image), rel=1e-3)  # the mask matters
        s, n = LogLuminanceReduction(gl_ctx, 72, 56).sums(r.frame_texture, r.gbuffer.depth_texture)
        lum = np.maximum(image[mask] @ np.array([0.2126, 0.7152, 0.0722]), 0)
        assert n == mask.sum() and s == pytest.approx(np.log(EPS + lum).sum(), rel=1e-5)


def test_renderer_exposure_api(gl_ctx):
    from prt.runtime import Renderer, Scene
    from prt.runtime.shading import to_srgb8

    with Renderer(Scene.load(), 40, 32, ctx=gl_ctx) as r:
        assert r.exposure == 1.0  # the demo is one object seen from outside: its images do not change
        image = r.render()
        cpu = r.frame_exposure()
        assert cpu == pytest.approx(auto_exposure(image, r.covered_mask()), rel=1e-12)
        np.testing.assert_array_equal(r.render_srgb(), to_srgb8(image, 1.0))
        r.set_exposure("auto")
        np.testing.assert_array_equal(r.render_srgb(), to_srgb8(image, cpu))
        with pytest.raises(InputError, match="set_exposure"):
            r.set_exposure(-2)
    with Renderer(Scene.load(), 40, 32, ctx=gl_ctx, exposure="auto") as r:
        assert r.exposure == "auto"


def test_cost_study_runs(bench_module, tmp_path):
    """studies/auto_exposure_cost.py (docs/benchmarks/runtime_auto_exposure.json) on a tiny frame."""
    import json

    study = bench_module("auto_exposure_cost")
    assert study.main(["--size", "32", "--views", "2", "--json", str(tmp_path / "r.json")]) == 0
    result = json.loads((tmp_path / "r.json").read_text())
    glsl = result["backends"]["glsl"]
    assert glsl["max_rel_diff"] < 1e-4 and glsl["exposure_ms"] > 0 and result["backends"]["onnx"]["exposure_share"] > 0


def test_before_a_frame_and_after_close_are_state_errors(gl_ctx):
    from prt.runtime import Renderer, Scene
    from prt.runtime.errors import RendererStateError

    r = Renderer(Scene.load(), 16, 16, ctx=gl_ctx)
    for call in (r.frame_exposure, r.covered_mask):
        with pytest.raises(RendererStateError, match="no frame drawn yet"):
            call()
    r.render()
    r.close()
    with pytest.raises(RendererStateError):
        r.frame_exposure()
