"""The viewer's parts that need no window (dynamic resolution, the title, the env-map cycle), the
env-map background, and a smoke test of the window under Xvfb (skipped where Xvfb is absent)."""

import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from prt.runtime import Renderer, Scene
from prt.runtime.envmap import read_envmap
from prt.runtime.envmaps import DEFAULT_ENVMAP, bundled_envmap_path
from prt.runtime.sh import direction_to_equirect_uv
from prt.runtime.viewer import ENVMAPS, DynamicResolution, envmap_cycle, stage_text, title_text


def test_dynamic_resolution_policy():
    policy = DynamicResolution(target_ms=33.0)
    assert policy.choose(moving=False) == 1.0
    assert policy.choose(moving=True) == 1.0  # nothing measured yet
    policy.record(1.0, 60.0)  # full size is too slow: 0.75 would take ~34 ms, 0.5 ~15 ms
    assert policy.choose(moving=True) == 0.5
    assert policy.choose(moving=False) == 1.0  # still: full resolution again
    policy.record(0.5, 40.0)  # slower than predicted: measured times win
    assert policy.choose(moving=True) == 0.375
    for scale in DynamicResolution.SCALES:
        policy.record(scale, 500.0)
    assert policy.choose(moving=True) == 0.25  # nothing meets the target: the smallest
    assert DynamicResolution(None).choose(moving=True) == 1.0  # off
    assert DynamicResolution.size(0.375, 512, 300) == (192, 112)


def test_title_counts_network_frames_and_labels_relight():
    title = title_text("spot", "onnx", "diffuse", "potsdamer", fps=31.25, size=(512, 512), relight_ms=2.14)
    assert title == "spot | 31.2 FPS 512x512 | relight 2.1 ms | onnx diffuse potsdamer"
    moving = title_text("spot", "glsl", "glossy", "sky.hdr", fps=20.0, size=(256, 256), full=False)
    assert moving == "spot | 20.0 FPS 256x256 moving | glsl glossy sky.hdr"
    assert title_text("spot", "onnx", "diffuse", "studio", fps=None, size=None, relight_ms=1.0) == "spot | relight 1.0 ms | onnx diffuse studio"
    line = stage_text(31.25, (512, 512), {"gbuffer": 7.2, "inference": 14.5, "frame": 32.0})
    assert line == "31.2 FPS at 512x512: gbuffer 7.2, inference 14.5 ms"


def test_custom_envmap_stays_in_the_cycle(tmp_path):
    custom = tmp_path / "sky.hdr"
    custom.write_bytes(b"not read here")
    cycle, first = envmap_cycle(str(custom))
    assert cycle[: len(ENVMAPS)] == ENVMAPS and cycle[first] == str(custom) and len(cycle) == len(ENVMAPS) + 1
    # a copy of a bundled map (the demo's envmap.hdr) is that map, not a new entry
    copy = tmp_path / "envmap.hdr"
    shutil.copy(bundled_envmap_path("studio"), copy)
    cycle, first = envmap_cycle(None, copy)
    assert cycle == ENVMAPS and cycle[first] == "studio"
    cycle, first = envmap_cycle("interior", copy)  # the command line wins
    assert cycle[first] == "interior"
    assert envmap_cycle()[0][envmap_cycle()[1]] == DEFAULT_ENVMAP


@pytest.mark.parametrize("backend", ["onnx", "glsl"])
def test_background_is_the_envmap_where_no_geometry_is(gl_ctx, backend):
    with Renderer(Scene.load(), 48, 32, backend=backend, ctx=gl_ctx) as r:
        r.set_background(False)
        r.set_envmap("interior", rotation=np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
        black = r.render()
        runs = r.network_calls
        r.set_background(True)
        image = r.render()
        assert r.network_calls == runs  # drawing the background runs no network
        covered = r.gbuffer_image().covered
    assert covered.any() and (~covered).any()
    np.testing.assert_array_equal(image[covered], black[covered])
    assert (black[~covered] == 0).all()
    # the numpy reference: each uncovered pixel's ray, turned back by the light's rotation, looked up bilinearly
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    dirs = r.camera.ray_directions(48, 32) @ rot  # rot^T d per row vector
    uv = direction_to_equirect_uv(dirs)
    env = read_envmap(bundled_envmap_path("interior"))
    h, w = env.shape[:2]
    x, y = uv[..., 0] * w - 0.5, np.clip(uv[..., 1] * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    y1 = np.minimum(y0 + 1, h - 1)
    look = lambda yy, xx: env[yy, xx % w]  # noqa: E731
    expected = (look(y0, x0) * (1 - fx) + look(y0, x0 + 1) * fx) * (1 - fy) + (look(y1, x0) * (1 - fx) + look(y1, x0 + 1) * fx) * fy
    err = np.abs(image[~covered] - expected[~covered]).max(axis=1) / (expected[~covered].max(axis=1) + 1e-3)
    assert np.quantile(err, 0.99) < 0.02  # GPU filtering has 8-bit sub-texel weights


def test_background_follows_set_lighting_sh(gl_ctx):
    with Renderer(Scene.load(), 16, 16, ctx=gl_ctx) as r:
        r.set_background(True)
        r.set_lighting_sh(np.eye(16, 3))
        image = r.render()
        assert (image[~r.gbuffer_image().covered] == 0).all()  # SH light has no picture to draw


SMOKE = textwrap.dedent("""
    import pygame, sys, threading
    from prt.runtime import Scene
    from prt.runtime.viewer import ViewerOptions, run_window
    real_get, state = pygame.event.get, {"n": 0}
    def scripted():
        state["n"] += 1
        n, events = state["n"], real_get()
        if n == 2:
            events.append(pygame.event.Event(pygame.MOUSEBUTTONDOWN, button=1, pos=(10, 10)))
        elif 3 <= n < 8:
            events.append(pygame.event.Event(pygame.MOUSEMOTION, rel=(6, 1), pos=(10, 10), buttons=(1, 0, 0)))
        elif n == 8:
            events.append(pygame.event.Event(pygame.MOUSEBUTTONUP, button=1, pos=(10, 10)))
        elif n == 10:
            events.append(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_n, unicode="n", mod=0, scancode=0))
        elif n == 12:
            print("TITLE", pygame.display.get_caption()[0], flush=True)
            events.append(pygame.event.Event(pygame.QUIT))
        return events
    pygame.event.get = scripted
    sys.exit(run_window(Scene.load(), ViewerOptions(width=64, height=64, target_fps=30.0)))
""")


@pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="Xvfb is not installed (apt-get install xvfb)")
def test_viewer_window_smoke_under_xvfb(tmp_path):
    pytest.importorskip("pygame", reason="the [viewer] extra (pygame) is not installed")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    run = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 320x240x24", sys.executable, "-c", SMOKE], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
    title = [ln for ln in run.stdout.splitlines() if ln.startswith("TITLE ")][-1]
    after_n = ENVMAPS[(ENVMAPS.index(DEFAULT_ENVMAP) + 1) % len(ENVMAPS)]  # one "n" press from the demo's map
    assert "FPS 64x64 |" in title and "relight" in title and title.endswith(f"onnx diffuse {after_n}"), title
