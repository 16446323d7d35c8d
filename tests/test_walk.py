"""Walking through a scene: the first-person camera (prt.runtime.camera.walk), the viewer's walk
keys, interiors' near plane and auto exposure on camera paths, and the viewer recording a walk."""

import json
import math
import os
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

from prt.runtime import Renderer, Scene
from prt.runtime.camera import MAX_PITCH, WALK_NEAR, Camera, fit_near, inside_bounds, scene_box, walk, walk_speed
from prt.runtime.camera_path import CameraPath
from prt.runtime.exposure import SCENE_OBJECTS, auto_exposure, default_exposure
from prt.runtime.orbit import render_camera_path
from prt.runtime.viewer import WALK_FAST, walk_move

CAM = Camera((0.0, 0.2, 1.0), (0.0, 0.2, 0.0), (0.0, 1.0, 0.0), 50.0)  # looking down -Z


def test_walk_forward_right_up_and_turns():
    c = walk(CAM, (0.3, 0.0, 0.0))
    np.testing.assert_allclose(c.eye, [0.0, 0.2, 0.7], atol=1e-12)
    np.testing.assert_allclose(c.forward, CAM.forward, atol=1e-12)
    assert np.linalg.norm(c.target - c.eye) == pytest.approx(1.0) and c.fov_y == 50.0
    np.testing.assert_allclose(walk(CAM, (0.0, 0.25, 0.1)).eye, [0.25, 0.3, 1.0], atol=1e-12)  # right is +X here
    left = walk(CAM, yaw=math.pi / 2)  # positive yaw turns left: -Z -> -X
    np.testing.assert_allclose(left.forward, [-1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(left.eye, CAM.eye)
    up = walk(CAM, pitch=0.3)
    assert math.asin(up.forward[1]) == pytest.approx(0.3)
    # looking down, "forward" still walks level (the heading), not into the floor
    down = walk(CAM, pitch=-0.8)
    np.testing.assert_allclose(walk(down, (0.5, 0, 0)).eye, [0.0, 0.2, 0.5], atol=1e-12)


def test_walk_pitch_is_clamped_and_survives_a_vertical_view():
    c = walk(CAM, pitch=10.0)
    assert math.asin(c.forward[1]) == pytest.approx(MAX_PITCH)
    c = walk(c, pitch=10.0)  # stays at the clamp, stays a valid camera
    assert math.asin(c.forward[1]) == pytest.approx(MAX_PITCH)
    vertical = Camera((0, 0, 0), (0, -1, 0), (0, 1, 0.001), 40.0)  # nearly straight down
    w = walk(vertical, (0.1, 0, 0), yaw=0.2, pitch=0.1)
    up = vertical.up / np.linalg.norm(vertical.up)
    assert np.isfinite(w.eye).all() and abs(w.eye @ up) < 1e-12 and np.linalg.norm(w.eye) == pytest.approx(0.1)  # level


def test_walk_move_keys_speed_and_diagonals():
    assert walk_move(set(), 1.0, 0.1) is None
    assert walk_move({"forward", "back"}, 1.0, 0.1) is None
    np.testing.assert_allclose(walk_move({"forward"}, 2.0, 0.5), (1.0, 0.0, 0.0))
    diag = np.array(walk_move({"forward", "left"}, 1.0, 1.0))
    assert np.linalg.norm(diag) == pytest.approx(1.0) and diag[1] < 0 < diag[0]
    np.testing.assert_allclose(walk_move({"up", "fast"}, 1.0, 1.0), (0.0, 0.0, WALK_FAST))
    np.testing.assert_allclose(walk_move({"down"}, 1.0, 1.0), (0.0, 0.0, -1.0))


def test_held_keys_map_to_actions():
    pygame = pytest.importorskip("pygame", reason="the [viewer] extra (pygame) is not installed")
    from prt.runtime.viewer import held_actions

    class Pressed(dict):
        def __missing__(self, key):
            return False

    assert held_actions(Pressed()) == set()
    keys = Pressed({pygame.K_w: True, pygame.K_LSHIFT: True, pygame.K_SPACE: True, pygame.K_LEFT: True})
    assert held_actions(keys) == {"forward", "fast", "up", "left"}


def test_speed_from_the_scene_size():
    small, large = np.array([[0, 0, 0], [1, 1, 1.0]]), np.array([[0, 0, 0], [10, 10, 10.0]])
    assert walk_speed(large) == pytest.approx(10 * walk_speed(small)) and walk_speed(small) > 0


def test_interior_near_plane_and_the_default_exposure_rule():
    box = np.array([[-1, -1, -1], [1, 1, 1.0]])
    assert inside_bounds((0, 0, 0), box) and not inside_bounds((0, 0, 3), box)
    assert fit_near(CAM, box).near == WALK_NEAR
    outside = Camera((0, 0, 3), (0, 0, 0))
    assert fit_near(outside, box) is outside
    demo = Scene.load().manifest
    assert default_exposure(demo) == 1.0  # Spot on its ground disc: an object, exposure 1 as recorded
    stub = SimpleNamespace(geometry=SimpleNamespace(objects=["a", "b"]), camera=SimpleNamespace(eye=(0, 0, 0)), bounds=demo.bounds)
    assert default_exposure(stub) == "auto"  # camera inside: an interior
    stub.camera.eye = (0, 0, 5)
    assert default_exposure(stub) == 1.0
    stub.geometry.objects = [f"o{i}" for i in range(SCENE_OBJECTS)]
    assert default_exposure(stub) == "auto"  # a building, an assembly


@pytest.fixture(scope="module")
def renderer(gl_ctx):
    with Renderer(Scene.load(), 32, 32, ctx=gl_ctx) as r:
        r.set_background(False)
        yield r


def test_a_path_inside_the_bounds_is_not_clipped(renderer, tmp_path):
    """A view from 3 cm above the ground disc: the default near plane (0.05) clips the ground
    away; the path renders it with the interior near plane."""
    import imageio.v3 as iio

    low = Camera((0.5, -0.6165 + 0.03, 0.5), (0.5, -0.7, 0.52), (0, 1, 0), 40)
    renderer.set_camera_object(low)
    assert renderer.render().max() == 0  # the near plane cuts the ground
    render_camera_path(renderer, CameraPath((low,), 1), tmp_path, exposure=1.0, warmup=0)
    assert (iio.imread(tmp_path / "frame_000.png").sum(axis=2) > 0).all()


def test_path_frames_with_auto_exposure(renderer, tmp_path):
    """--exposure auto on a path: the first frame exactly at its own auto exposure, the next ones
    smoothed towards theirs (a dark stretch brightens gradually)."""
    import imageio.v3 as iio

    from prt.runtime.shading import to_srgb8

    start = Camera.from_manifest(renderer.scene.manifest)
    path = CameraPath((start, start.orbit(0.6)), 3)
    summary = render_camera_path(renderer, path, tmp_path, exposure="auto", warmup=0, fps=10)
    assert "exposure auto" in str(summary) and "exposure" in summary.median_ms
    renderer.set_camera_object(path.cameras()[0])
    image = renderer.render()
    e0 = auto_exposure(image, renderer.covered_mask())
    np.testing.assert_array_equal(iio.imread(tmp_path / "frame_000.png"), to_srgb8(image, e0))
    assert e0 != pytest.approx(1.0, abs=0.05)  # the check above would not tell exposure 1 apart


def test_cli_exposure_auto_and_a_bad_value(tmp_path, capsys):
    from prt.runtime.cli import main

    assert main(["--headless", "--frames", "2", "--size", "24", "--out", str(tmp_path / "a"), "--exposure", "auto"]) == 0
    assert "exposure auto" in capsys.readouterr().out
    assert main(["--headless", "--frames", "2", "--size", "24", "--out", str(tmp_path / "b"), "--exposure", "bright"]) == 2
    err = capsys.readouterr().err
    assert "--exposure" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "b").exists()


WALK = textwrap.dedent("""
    import json, sys
    import moderngl, pygame
    from prt.runtime import Scene
    from prt.runtime.gl import create_context
    from prt.runtime.viewer import ViewerOptions, run_window

    # No GL window under SDL's dummy driver: the window is a plain surface, the screen an offscreen
    # framebuffer of a headless context; the viewer's loop, keys and recorder run as they are.
    real_set_mode = pygame.display.set_mode
    pygame.display.set_mode = lambda size, flags=0: real_set_mode(size)
    ctx = create_context()
    screen = ctx.framebuffer([ctx.texture((48, 48), 4)])
    ctx.detect_framebuffer = lambda *a: screen
    moderngl.create_context = lambda *a, **k: ctx
    state = {"n": 0, "held": set()}
    real_get = pygame.event.get
    def key(k, u):
        return pygame.event.Event(pygame.KEYDOWN, key=k, unicode=u, mod=0, scancode=0)
    def scripted():
        state["n"] += 1
        n, events = state["n"], real_get()
        if n == 2:
            events.append(key(pygame.K_v, "v"))  # walk
        elif n == 3:
            state["held"] = {pygame.K_w}  # held down: forward every frame
            events.append(key(pygame.K_w, "w"))  # (its key-down is a move, not the orbit's key)
        elif n == 9:
            state["held"] = set()
            events.append(pygame.event.Event(pygame.MOUSEBUTTONDOWN, button=1, pos=(5, 5)))
        elif 10 <= n < 13:
            events.append(pygame.event.Event(pygame.MOUSEMOTION, rel=(8, 0), pos=(5, 5), buttons=(1, 0, 0)))
        elif n == 13:
            events.append(pygame.event.Event(pygame.MOUSEBUTTONUP, button=1, pos=(5, 5)))
        elif n == 15:
            events.append(key(pygame.K_c, "c"))  # save the recorded walk
        elif n == 17:
            events.append(pygame.event.Event(pygame.QUIT))
        return events
    class Pressed:
        def __getitem__(self, k):
            return k in state["held"]
    pygame.event.get = scripted
    pygame.key.get_pressed = lambda: Pressed()
    sys.exit(run_window(Scene.load(), ViewerOptions(width=48, height=48, target_fps=0, exposure="auto")))
""")


def test_viewer_walks_and_records_the_walk(tmp_path):
    pytest.importorskip("pygame", reason="the [viewer] extra (pygame) is not installed")
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
    run = subprocess.run([sys.executable, "-c", WALK], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "walk: W A S D" in run.stdout
    saved = list(tmp_path.glob("prt_camera_path_*.json"))
    assert len(saved) == 1, run.stdout[-2000:]
    keys = json.loads(saved[0].read_text())["keyframes"]
    eyes = np.array([k["eye"] for k in keys])
    start = Camera.from_manifest(Scene.load().manifest)
    heading = start.forward * np.array([1, 0, 1])
    heading /= np.linalg.norm(heading)
    steps = np.diff(eyes, axis=0)
    moved = steps[np.linalg.norm(steps, axis=1) > 0]
    assert len(moved) >= 3  # one recorded view per frame while W was held
    for s in moved:  # level, along the heading
        assert abs(s[1]) < 1e-12 and s @ heading == pytest.approx(np.linalg.norm(s), rel=1e-9)
    looks = [np.subtract(k["target"], k["eye"]) for k in keys[-3:]]  # the drag turned the view, not the eye
    assert np.allclose(eyes[-1], eyes[-3]) and not np.allclose(looks[0], looks[-1])
    assert np.cross(looks[0], looks[-1])[1] < 0  # the mouse moved right: the view turned right (clockwise from above)


def test_set_camera_inside_gets_the_interior_near_plane(renderer):
    renderer.set_camera(eye=(0.5, -0.6165 + 0.03, 0.5), target=(0.5, -0.7, 0.52))
    assert renderer.camera.near == WALK_NEAR and (renderer.render().sum(axis=2) > 0).all()
    renderer.set_camera(eye=(1.45, 0.55, -2.1), target=(0, -0.12, 0))
    assert renderer.camera.near == 0.05  # outside: as before


def test_walkthrough_study_renders_a_walk_video(bench_module, tmp_path):
    """studies/walkthrough.py: the generated walk stays inside the box, renders to MP4 with auto exposure."""
    pytest.importorskip("imageio_ffmpeg", reason="the [video] extra (imageio-ffmpeg) is not installed")
    study = bench_module("walkthrough")
    manifest = Scene.load().manifest
    path = study.straight_walk(manifest, 4)
    box = scene_box(manifest)
    assert all(inside_bounds(c.eye, box) and abs(c.forward[1]) < 1e-12 for c in path.cameras())
    assert study.main([str(Scene.load().path), "--size", "32x24", "--frames", "4", "--json", str(tmp_path / "w.json"),
                       "--out", str(tmp_path / "w.mp4"), "--figure", str(tmp_path / "f.png")]) == 0  # fmt: skip
    result = json.loads((tmp_path / "w.json").read_text())
    assert result["frames"] == 4 and result["exposure"].startswith("auto") and (tmp_path / "w.mp4").stat().st_size > 0
    assert (tmp_path / "w.path.json").is_file()
    import imageio.v3 as iio

    figure = iio.imread(tmp_path / "f.png")
    assert figure.shape == (24, 64, 3)
    assert np.array_equal(figure[:, :32], figure[:, 32:]) == (result["figure_exposure"] == 1.0)  # exposure 1 | auto
