"""Tests of prt.runtime.envmap: HDR round trips, the real sample file, error messages."""

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from prt.runtime import envmap, sh
from prt.runtime.errors import EnvmapError

STUDIO = Path("/work/shared/data/envmaps/studio_small_03_1k.hdr")


def assert_one_line_naming(excinfo, path):
    message = str(excinfo.value)
    assert Path(path).name in message
    assert "\n" not in message


def test_hdr_round_trip_within_rgbe_precision(tmp_path):
    rng = np.random.default_rng(0)
    image = np.exp(rng.uniform(-4, 6, size=(16, 32, 3))).astype(np.float32)
    path = tmp_path / "random.hdr"
    envmap.write_hdr(path, image)
    back = envmap.read_envmap(path)
    assert back.shape == (16, 32, 3) and back.dtype == np.float32
    # RGBE shares one exponent per texel: error is relative to the texel's largest channel.
    scale = image.max(axis=-1, keepdims=True)
    assert np.abs(back - image).max(axis=None) <= 0.01 * scale.max()
    assert np.all(np.abs(back - image) <= 0.01 * scale)
    assert [p.name for p in tmp_path.iterdir()] == ["random.hdr"]  # no temporary left


def test_channel_order_is_rgb(tmp_path):
    red = np.zeros((8, 16, 3), np.float32)
    red[..., 0] = 5.0
    path = tmp_path / "red.HDR"
    envmap.write_hdr(path, red)
    back = envmap.read_envmap(path)
    np.testing.assert_allclose(back[..., 0], 5.0, rtol=0.01)
    assert np.all(back[..., 1:] == 0.0)


def test_write_overwrites_and_validates(tmp_path):
    path = tmp_path / "env.hdr"
    envmap.write_hdr(path, np.ones((4, 8, 3)))
    envmap.write_hdr(path, np.full((4, 8, 3), 2.0))
    np.testing.assert_allclose(envmap.read_envmap(path), 2.0, rtol=0.01)
    for bad in [np.ones((4, 8)), np.full((4, 8, 3), np.nan), -np.ones((4, 8, 3))]:
        with pytest.raises(EnvmapError) as excinfo:
            envmap.write_hdr(path, bad)
        assert_one_line_naming(excinfo, path)
    with pytest.raises(EnvmapError):
        envmap.write_hdr(tmp_path / "env.png", np.ones((4, 8, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["env.hdr"]


@pytest.mark.skipif(not STUDIO.is_file(), reason=f"{STUDIO} not present")
def test_real_studio_envmap():
    image = envmap.read_envmap(STUDIO)
    assert image.shape == (512, 1024, 3) and image.dtype == np.float32
    assert image.max() > 1000.0 and image.min() >= 0.0
    coeffs = envmap.load_envmap_sh(STUDIO)
    assert coeffs.shape == (16, 3)
    # L00 / sqrt(4 pi) is the mean radiance over the sphere (solid-angle weighted).
    mean = (image * sh.texel_solid_angles(512, 1024)[..., None]).sum((0, 1)) / (4 * math.pi)
    np.testing.assert_allclose(coeffs[0] / math.sqrt(4 * math.pi), mean, rtol=1e-6)


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.hdr"
    with pytest.raises(EnvmapError, match="not found") as excinfo:
        envmap.read_envmap(path)
    assert_one_line_naming(excinfo, path)


def test_garbage_hdr(tmp_path):
    path = tmp_path / "garbage.hdr"
    path.write_bytes(b"this is not an image\n" * 20)
    with pytest.raises(EnvmapError, match="decode") as excinfo:
        envmap.read_envmap(path)
    assert_one_line_naming(excinfo, path)


def test_unknown_extension(tmp_path):
    path = tmp_path / "env.txt"
    path.write_text("hello")
    with pytest.raises(EnvmapError, match="extension") as excinfo:
        envmap.read_envmap(path)
    assert_one_line_naming(excinfo, path)
    assert isinstance(excinfo.value, ValueError)


def test_not_equirectangular(tmp_path):
    path = tmp_path / "square.hdr"
    envmap.write_hdr(path, np.ones((8, 8, 3)))
    with pytest.raises(EnvmapError, match="2 \\* height") as excinfo:
        envmap.read_envmap(path)
    assert_one_line_naming(excinfo, path)


def _fake_decoder(monkeypatch, bgr):
    """Make cv2.imread return ``bgr`` so that read_envmap's value checks can be exercised."""
    cv2 = envmap._cv2()
    monkeypatch.setattr(cv2, "imread", lambda *args, **kwargs: bgr.copy())


def test_nan_and_inf_rejected(tmp_path, monkeypatch):
    path = tmp_path / "nan.hdr"
    envmap.write_hdr(path, np.ones((4, 8, 3)))
    bad = np.ones((4, 8, 3), np.float32)
    bad[1, 2, 0] = np.nan
    bad[3, 3, 2] = np.inf
    _fake_decoder(monkeypatch, bad)
    with pytest.raises(EnvmapError, match="2 NaN or Inf") as excinfo:
        envmap.read_envmap(path)
    assert_one_line_naming(excinfo, path)


def test_negative_values_clamped(tmp_path, monkeypatch):
    path = tmp_path / "neg.hdr"
    envmap.write_hdr(path, np.ones((4, 8, 3)))
    tiny = np.ones((4, 8, 3), np.float32)
    tiny[0, 0, 0] = -1e-6
    _fake_decoder(monkeypatch, tiny)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert envmap.read_envmap(path).min() == 0.0
    large = np.ones((4, 8, 3), np.float32)
    large[0, 0, 0] = -0.5
    _fake_decoder(monkeypatch, large)
    with pytest.warns(UserWarning, match="neg.hdr"):
        assert envmap.read_envmap(path).min() == 0.0


def test_exr_round_trip(tmp_path):
    image = np.random.default_rng(1).uniform(0, 50, size=(8, 16, 3)).astype(np.float32)
    image[..., 1] = 0.0
    path = tmp_path / "env.exr"
    envmap.write_hdr(path, image)
    np.testing.assert_allclose(envmap.read_envmap(path), image, rtol=1e-6)


def test_exr_that_cannot_be_decoded(tmp_path):
    path = tmp_path / "broken.exr"
    path.write_bytes(bytes([0x76, 0x2F, 0x31, 0x01]) + b"\0" * 60)
    with pytest.raises(EnvmapError) as excinfo:
        envmap.read_envmap(path)
    assert_one_line_naming(excinfo, path)
