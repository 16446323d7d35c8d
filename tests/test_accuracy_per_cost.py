"""Issue 12: the deringing window on the lighting and the reference's convergence logic (fast, synthetic)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prt.bench.quiet_reference import quiet_plan
from prt.bench.reference import REFERENCE_MARGIN_DB, convergence
from prt.runtime import sh
from prt.runtime.errors import InputError
from prt.runtime.shading import Lighting


def _step_light(bands: int = 4) -> np.ndarray:
    """A light that is 1 over the upper hemisphere and 0 below: its truncated SH rings below zero."""
    dirs = sh.envmap_directions(64, 128)
    image = np.repeat((dirs[..., 2:3] > 0).astype(np.float64), 3, axis=2)
    return sh.project_envmap(image, bands)


def test_the_window_lowers_the_negative_lobes_of_a_step_light():
    coeffs = _step_light()
    dirs = sh.envmap_directions(64, 128).reshape(-1, 3)
    plain = sh.evaluate(Lighting.from_sh(coeffs).sh[:, 0], dirs)
    assert plain.min() < -0.05  # the ringing the window is for
    for window in (("hanning", 6.0), ("hanning", 5.0), ("lanczos", 6.0)):
        lighting = Lighting.from_sh(coeffs, window=window)
        windowed = sh.evaluate(lighting.sh[:, 0], dirs)
        assert windowed.min() > 0.6 * plain.min(), window  # -0.114 -> -0.043 (hanning 6)
        assert lighting.sh[0, 0] == coeffs[0, 0]  # band 0 (the average) is untouched


def test_the_window_at_infinite_width_is_the_identity_and_commutes_with_rotation():
    coeffs = _step_light()
    for kind in ("hanning", "lanczos"):
        np.testing.assert_array_equal(Lighting.from_sh(coeffs, window=(kind, math.inf)).sh, Lighting.from_sh(coeffs).sh)
    c, s = math.cos(0.7), math.sin(0.7)
    rotation = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    a = Lighting.from_sh(coeffs, rotation=rotation, window=("hanning", 6.0)).sh
    b = sh.rotate(Lighting.from_sh(coeffs, window=("hanning", 6.0)).sh, rotation)
    np.testing.assert_allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("window", [("gauss", 4.0), ("hanning", 0.0), ("hanning",), "hanning"])
def test_a_bad_window_is_one_input_error(window):
    with pytest.raises(InputError, match="Lighting window"):
        Lighting.from_sh(_step_light(), window=window)


def test_reference_rays_grow_until_the_noise_clears_the_best_psnr_by_the_margin():
    """Direct rays only (no bounces, no budget): bench/quiet_reference.py's plan doubles as often as the worst material needs."""
    assert REFERENCE_MARGIN_DB == 6.0

    def rays(noise, best, start, most):
        return quiet_plan(noise, None, best, start, 64, rays_max=most, hit_rays_max=64, seconds_direct=None, seconds_bounce=None, views=1,
                          budget=None)["rays"]  # fmt: skip

    assert rays({"diffuse": 50.0}, {"diffuse": 40.0}, 512, 4096) == 512  # 10 dB apart: enough
    assert rays({"diffuse": 46.0}, {"diffuse": 40.0}, 512, 4096) == 512  # exactly 6 dB
    # 2 dB short: one doubling (+3 dB); 4 dB short: two; the worst material decides
    assert rays({"diffuse": 44.0, "glossy": 45.0}, {"diffuse": 40.0, "glossy": 40.0}, 512, 4096) == 1024
    assert rays({"diffuse": 46.0, "glossy": 42.0}, {"diffuse": 40.0, "glossy": 40.0}, 512, 4096) == 2048
    assert rays({"diffuse": 30.0}, {"diffuse": 40.0}, 512, 4096) == 4096  # capped
    assert rays({"diffuse": 30.0}, {"diffuse": 40.0}, 4096, 4096) == 4096
    assert rays({"diffuse": 30.0}, {}, 512, 4096) == 512  # nothing measured to compare with


def test_convergence_says_when_the_reference_is_the_floor():
    ok = convergence({"diffuse": 47.0, "glossy": 49.0}, {"diffuse": 40.0, "glossy": 42.5}, 1024)
    assert ok["floor"] is False and ok["margin_db"] == {"diffuse": 7.0, "glossy": 6.5} and ok["rays"] == 1024
    floor = convergence({"diffuse": 44.0, "glossy": 49.0}, {"diffuse": 40.0, "glossy": 30.0}, 4096)
    assert floor["floor"] is True and floor["best_psnr"] == {"diffuse": 40.0, "glossy": 30.0}


def test_auto_windows_only_a_light_that_rings_strongly():
    from prt.runtime.envmap import load_envmap_sh
    from prt.runtime.envmaps import bundled_envmap_path
    from prt.runtime.shading import DERING_AUTO_RINGING, DERING_WINDOW, lighting_ringing

    constant = np.zeros((16, 3))
    constant[0] = 1.0
    assert lighting_ringing(constant) == 0.0
    studio, potsdamer = (load_envmap_sh(bundled_envmap_path(n), 4) for n in ("studio", "potsdamer"))
    assert lighting_ringing(studio) > DERING_AUTO_RINGING > lighting_ringing(potsdamer)
    np.testing.assert_array_equal(Lighting.from_sh(studio, window="auto").sh, Lighting.from_sh(studio, window=DERING_WINDOW).sh)
    np.testing.assert_array_equal(Lighting.from_sh(potsdamer, window="auto").sh, Lighting.from_sh(potsdamer).sh)
