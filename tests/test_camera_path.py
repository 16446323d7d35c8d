"""Camera paths (runtime/camera_path.py) and their headless rendering (runtime/orbit.py): the
JSON round trip, interpolation, one-line errors, PNG / EXR / MP4 output written whole or not at all."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.runtime import Renderer, Scene
from prt.runtime.camera import Camera, orbit_views
from prt.runtime.camera_path import (
    CameraPath,
    PathRecorder,
    camera_path_from_dict,
    load_camera_path,
    orbit_path,
    save_camera_path,
)
from prt.runtime.cli import main as prt_runtime
from prt.runtime.errors import InputError
from prt.runtime.orbit import render_camera_path

START = Camera([0.0, 0.6, 3.2], [0.0, 0.0, 0.0])


def _same(a: Camera, b: Camera) -> bool:
    return all(np.allclose(getattr(a, k), getattr(b, k), atol=1e-12) for k in ("eye", "target", "up", "fov_y"))


def test_orbit_path_round_trips_through_json(tmp_path):
    path = orbit_path(START, 12)
    saved = save_camera_path(tmp_path / "orbit.json", path)
    data = json.loads(saved.read_text())
    assert data["format"] == "prt-camera-path" and data["version"] == 1 and data["frames"] == 12
    assert set(data["keyframes"][0]) == {"eye", "target", "up", "fov"}
    loaded = load_camera_path(saved)
    assert loaded.frames == 12 and loaded.interpolation == "linear" and not loaded.loop
    for got, want in zip(loaded.cameras(), orbit_views(START, 12), strict=True):
        assert _same(got, want)
    assert [p.name for p in tmp_path.iterdir()] == ["orbit.json"]  # no temporary left


def test_interpolation_passes_through_keyframes():
    keys = (START, START.orbit(1.0), START.orbit(2.0))
    linear = CameraPath(keys, 5).cameras()  # frames 0, 2, 4 are the keyframes
    for frame, key in ((0, 0), (2, 1), (4, 2)):
        assert _same(linear[frame], keys[key])
    np.testing.assert_allclose(linear[1].eye, (keys[0].eye + keys[1].eye) / 2)
    smooth = CameraPath(keys, 5, "smooth").cameras()
    for frame, key in ((0, 0), (2, 1), (4, 2)):
        assert _same(smooth[frame], keys[key])
    # a loop covers the closed path and stops short of the start: 3 keyframes, 6 frames
    looped = CameraPath(keys, 6, loop=True).cameras()
    assert _same(looped[0], keys[0]) and _same(looped[2], keys[1]) and _same(looped[4], keys[2])
    np.testing.assert_allclose(looped[5].eye, (keys[2].eye + keys[0].eye) / 2)
    # a single keyframe is a still
    assert all(_same(c, START) for c in CameraPath((START,), 3).cameras())


def test_defaults_and_optional_fields():
    path = camera_path_from_dict({"format": "prt-camera-path", "version": 1, "keyframes": [{"eye": [0, 0, 2], "target": [0, 0, 0]}]})
    assert path.frames == 1 and path.cameras()[0].fov_y == 40.0
    np.testing.assert_array_equal(path.cameras()[0].up, [0.0, 1.0, 0.0])


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"format": "x"}, r"^p\.json: format: expected 'prt-camera-path'"),
        ({"version": 1.0}, r"^p\.json: version: expected 1"),
        ({"frames": True}, r"^p\.json: frames: expected an integer"),
        ({"keyframes": {}}, r"^p\.json: keyframes: expected a non-empty list"),
        ({"keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0], "roll": 3}]}, r"^p\.json: keyframes\[0\]\.roll: unknown field"),
        ({"keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0], "fov": "wide"}]}, r"^p\.json: keyframes\[0\]\.fov: expected a number"),
        ({"keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0], "up": [0, 0, 1]}]}, r"^p\.json: keyframes\[0\]: up .* parallel"),
        ({"keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 2e39]}]}, r"^p\.json: keyframes\[0\]\.target\[2\]: number"),
    ],
)
def test_bad_fields_are_one_line_errors_naming_the_field(change, message):
    data = {"format": "prt-camera-path", "version": 1, "keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0]}], **change}
    with pytest.raises(InputError, match=message) as info:
        camera_path_from_dict(data, "p.json")
    assert "\n" not in str(info.value)


def test_recorder_skips_repeats():
    rec = PathRecorder(limit=3)
    assert rec.path() is None
    for cam in (START, START, START.orbit(0.1), START.orbit(0.2), START.orbit(0.3)):
        rec.add(cam)
    path = rec.path()
    assert path.frames == 3 and len(path.keyframes) == 3 and _same(path.keyframes[1], START.orbit(0.1))


@pytest.fixture(scope="module")
def renderer(gl_ctx):
    with Renderer(Scene.load(), 40, 32, ctx=gl_ctx) as r:
        yield r


def test_png_and_exr_frames(renderer, tmp_path):
    path = CameraPath((START, START.orbit(0.5)), 3)
    summary = render_camera_path(renderer, path, tmp_path / "png", warmup=0)
    assert summary.frames == 3 and sorted(p.name for p in (tmp_path / "png").iterdir()) == [f"frame_00{i}.png" for i in range(3)]
    render_camera_path(renderer, path, tmp_path / "exr", fmt="exr", exposure=2.0, warmup=0)
    renderer.set_camera_object(path.cameras()[2])
    expected = renderer.render() * 2.0
    got = read_envmap_like(tmp_path / "exr" / "frame_002.exr")
    assert got.shape == (32, 40, 3)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)  # linear radiance, float32


def test_frames_held_then_written_match_each_view(renderer, tmp_path, monkeypatch):
    """Frames held in memory and written in batches (a budget below one frame: one at a time)
    are the views' own images, in order, losslessly: the PNG pixels are to_srgb8 of each render."""
    import imageio.v3 as iio

    import prt.runtime.orbit as orbit
    from prt.runtime.shading import to_srgb8

    path = CameraPath((START, START.orbit(0.7)), 4)
    frame_bytes = 32 * 40 * 3 * 4
    for budget, folder in ((1, "one"), (2 * frame_bytes + 1, "two"), (orbit.HOLD_BYTES, "all")):
        monkeypatch.setattr(orbit, "HOLD_BYTES", budget)
        summary = render_camera_path(renderer, path, tmp_path / folder, warmup=0)
        assert summary.write_s > 0 and " in " in str(summary)
    for i, camera in enumerate(path.cameras()):
        renderer.set_camera_object(camera)
        expected = to_srgb8(renderer.render())
        for folder in ("one", "two", "all"):
            np.testing.assert_array_equal(iio.imread(tmp_path / folder / f"frame_{i:03d}.png"), expected)


def read_envmap_like(path):
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels, dtype=np.float32)


def test_mp4(renderer, tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason="the [video] extra (imageio-ffmpeg) is not installed")
    out = tmp_path / "a" / "turn.mp4"
    summary = render_camera_path(renderer, orbit_path(START, 4), out, fmt="mp4", warmup=0)
    assert summary.wrote == str(out) and out.stat().st_size > 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["turn.mp4"]  # the temporary was renamed
    assert out.read_bytes()[4:8] == b"ftyp"  # an MP4 container


@pytest.mark.parametrize("fmt", ["png", "mp4"])
def test_a_failed_frame_leaves_nothing(renderer, tmp_path, monkeypatch, fmt):
    if fmt == "mp4":
        pytest.importorskip("imageio_ffmpeg", reason="the [video] extra (imageio-ffmpeg) is not installed")
    calls = {"n": 0}
    real = renderer.render

    def failing():
        calls["n"] += 1
        if calls["n"] == 3:
            raise InputError("boom")
        return real()

    monkeypatch.setattr(renderer, "render", failing)
    out = tmp_path / "new" / "deeper" / ("v.mp4" if fmt == "mp4" else "frames")
    with pytest.raises(InputError, match="boom"):
        render_camera_path(renderer, orbit_path(START, 4), out, fmt=fmt, warmup=0)
    assert list(tmp_path.iterdir()) == []


def test_cli_renders_a_path_and_refuses_a_bad_one(tmp_path, capsys):
    good = save_camera_path(tmp_path / "good.json", CameraPath((START, START.orbit(0.3)), 2))
    # in a process of its own: the command makes its own GL context current, which gl_ctx's tests must not inherit
    argv = ["--headless", "--size", "16", "--camera-path", str(good), "--out", str(tmp_path / "frames")]
    run = subprocess.run([sys.executable, "-m", "prt.runtime.cli", *argv], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-1000:]
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["frame_000.png", "frame_001.png"]
    assert "2 frames 16x16" in run.stdout
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "prt-camera-path", "version": 1, "keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 1]}]}))
    assert prt_runtime(["--headless", "--size", "16", "--camera-path", str(bad), "--out", str(tmp_path / "never")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.json: keyframes[0]: eye and target coincide" in err[0]
    assert not (tmp_path / "never").exists()


def test_demo_frame_rate_study_runs_every_configuration(tmp_path):
    """studies/demo_fps.py: six configurations (tolerance x held / written each, and the default with
    the G-buffer's reference twin or with the background drawn at assembly), each with its rounds and its
    share outside the network, the HOLD_BYTES default restored, and the PNG levels' timings."""
    root = Path(__file__).resolve().parents[1]
    out, md = tmp_path / "fps.json", tmp_path / "fps.md"
    proc = subprocess.run([sys.executable, str(root / "studies" / "demo_fps.py"), "--size", "40", "--frames", "3",
                           "--rounds", "2", "--json", str(out), "--md", str(md)], capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out.read_text())
    twin = "interpolate 0.1 / held / G-buffer twin (per-fragment segments)"
    late = "interpolate 0.1 / held / background drawn at assembly"
    assert sorted(data["rows"]) == sorted(["interpolate 0 / each", "interpolate 0 / held", "interpolate 0.1 / each", "interpolate 0.1 / held", late, twin])
    assert data["rows"][late]["stages_ms"]["background"] > data["rows"]["interpolate 0.1 / held"]["stages_ms"]["background"]  # its pass timed there
    assert all(len(r["rounds"]) == 2 and r["fps"] > 0 and r["write_s"] > 0 for r in data["rows"].values())
    assert all(0 < r["outside_share"] < 1 for r in data["rows"].values())
    assert "Targets (issue 44)" in md.read_text()
    assert "interpolate" in data["rows"]["interpolate 0.1 / held"]["stages_ms"]
    prov = data["provenance"]  # the machine beside the figures
    assert prov["machine"]["cpu"] and prov["machine"]["gl_renderer"] and "demo_fps.py" in prov["command"]
    assert "interpolate" not in data["rows"]["interpolate 0 / held"]["stages_ms"]
    assert set(data["png"]) == {"1", "6"} and data["png"]["1"]["bytes"] >= data["png"]["6"]["bytes"] * 0.9
    assert "| interpolate 0.1 / held |" in md.read_text()
