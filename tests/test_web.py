"""prt-web (issue 37): a built scene as a static WebGL2 page, tested in a real browser.

Without a browser: the folder prt-web writes (files, marker, payload), its refusals (exit 2, one
line), the lighting data against the runtime's own (SH rotation, RGBE texels).  In a browser:
Debian's ``chromium`` driven headless by Debian's ``chromedriver`` through selenium
(``prt.bench.browser``), software WebGL2 (SwiftShader), the folder served from 127.0.0.1: the
page's frame against ``Renderer(backend="glsl")`` (llvmpipe) on the bundled demo and on a build
with bounces, the frame time it shows, relighting without the networks, the error pages.  A
network frame of SwiftShader takes seconds on this machine, so the pages are 256 x 256 and load once.

Silhouettes: SwiftShader and llvmpipe snap vertices to different sub-pixel grids, so a few pixels
on edges take the other surface (and grazing surfaces interpolate positions a little apart); the
covered-pixel PSNR includes them (docs/guides/web.md).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.bench.browser import (
    chromium, covered_psnr, decode_png_data_url, interior_pixels, load_page, missing_browser, page_query, python_frame, serve,
)  # fmt: skip
from prt.export.web import MARKER, main as web_main, write_web
from prt.export.web_assets import gaunt_entries, rgbe_bytes, rotation_fourier, rotation_from_fourier
from prt.runtime import sh
from prt.runtime.envmap import read_envmap
from prt.runtime.envmaps import bundled_envmap_path
from prt.runtime.renderer import Scene, demo_scene_path

SIZE = 256
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def demo_web(tmp_path_factory):
    out = tmp_path_factory.mktemp("web") / "demo"
    report = write_web(demo_scene_path(), out)
    return out, report


# --------------------------------------------------------------------------- no browser


def test_prt_web_writes_a_static_folder(demo_web, tmp_path, capsys):
    out, report = demo_web
    web = json.loads((out / "web.json").read_text())
    assert (web["format"], web["version"]) == ("prt-web", 1) and json.loads((out / MARKER).read_text())["format"] == "prt-web"
    for name, size in web["files"].items():  # the file table the page checks sizes against
        assert (out / name).stat().st_size == size, name
    assert {"index.html", "prt-web.js", "geometry.bin", "weights.bin"} <= set(web["files"])
    # Target: the demo's payload (geometry + weights + code + the env maps' texels) <= 2 MB: every
    # file but the marker and what only three.html loads (tests/test_three.py).
    three = {web["three"]["page"], web["three"]["module"], *web["three"]["vendor"].values(), *web["three"]["programs"].values()}
    payload = sum(p.stat().st_size for p in out.rglob("*") if p.is_file() and p.name != MARKER and p.relative_to(out).as_posix() not in three)
    assert payload == web["scene"]["payload_bytes"] == report["payload_bytes"] and payload <= 2_000_000, payload
    for name in web["programs"].values():  # GLSL ES 3.00, no CDN, nothing outside the folder
        assert (out / name).read_text().startswith("#version 300 es\nprecision highp float;")
    html = (out / "index.html").read_text() + (out / "prt-web.js").read_text()
    assert "http://" not in html.replace("http://127.0.0.1:8000/", "") and "https://" not in html
    # The networks are the scene's own generated GLSL (the same generator as the desktop's).
    seg = (demo_scene_path().parent / "segments" / "seg000.glsl").read_text()
    body = seg[seg.index("vec4 prt_freq_"):]
    assert body in (out / web["programs"]["transfer4.frag"]).read_text()
    # An earlier output is ours: written again; a folder of someone else's is refused, untouched.
    assert web_main([str(demo_scene_path()), "-o", str(out)]) == 0
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    capsys.readouterr()
    assert web_main([str(demo_scene_path()), "-o", str(other)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a prt-web output" in err and sorted(p.name for p in other.iterdir()) == ["notes.txt"]


def test_prt_web_rejects_bad_scenes_with_one_line(tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(demo_scene_path().parent, scene)
    newer = json.loads((scene / "scene.json").read_text())
    newer["version"] = 99
    (scene / "scene.json").write_text(json.dumps(newer))
    broken = tmp_path / "broken"
    shutil.copytree(demo_scene_path().parent, broken)
    (broken / "segments" / "seg001_weights.npy").write_bytes(b"not an array")
    corrupt = tmp_path / "corrupt.json"
    corrupt.write_text('{"format": "prt-scene"')
    sdf = tmp_path / "sdf"  # an SDF scene (the demo's networks over a sphere): the page rasterises meshes only
    shutil.copytree(demo_scene_path().parent, sdf)
    data = json.loads((sdf / "scene.json").read_text())
    data["geometry"] = {"type": "sdf", "name": "sphere", "glsl": "scene.glsl", "to_source": data["geometry"]["to_source"]}
    data["segmentation"]["roots"] = {"0": 0}
    (sdf / "scene.json").write_text(json.dumps(data))
    (sdf / "scene.glsl").write_text("float scene_sdf(vec3 p) { return length(p) - 0.5; }\n")
    cases = [(tmp_path / "nothing", "nothing"), (scene, "version"), (broken, "seg001_weights.npy"), (corrupt, "corrupt.json"),
             (sdf, "an SDF scene")]  # fmt: skip
    for path, words in cases:
        out = tmp_path / f"out_{path.name}"
        proc = subprocess.run([sys.executable, "-m", "prt.export.web", str(path), "-o", str(out)], capture_output=True, text=True)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and words in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert not out.exists()  # nothing half-written
    proc = subprocess.run([sys.executable, "-m", "prt.export.web", "-o", str(tmp_path / "x")], capture_output=True, text=True)
    assert proc.returncode == 2 and "usage: prt-web" in proc.stderr


NO_TORCH = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "onnx", "trimesh", "embreex", "scipy"):
            raise ModuleNotFoundError("No module named " + repr(name), name=name)
sys.meta_path.insert(0, Block())
from prt.export.web import main
sys.exit(main(sys.argv[1:]))
"""


def test_prt_web_runs_without_the_train_extra(tmp_path):
    """A deployment machine has the runtime only: prt-web imports neither torch nor onnx."""
    proc = subprocess.run([sys.executable, "-c", NO_TORCH, str(demo_scene_path()), "-o", str(tmp_path / "page")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "python3 -m http.server -d" in proc.stdout and (tmp_path / "page" / "web.json").is_file()


def test_rotation_polynomial_is_the_sh_rotation():
    fourier = rotation_fourier(4)
    for theta in (0.0, 0.3, -1.7, 2.9, 5.5):
        c, s = math.cos(theta), math.sin(theta)
        exact = sh.rotation_matrices(np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]), 4)
        assert np.abs(rotation_from_fourier(fourier, theta) - exact).max() < 1e-12
    g = np.zeros((16, 16, 16))
    for i, j, k, v in gaunt_entries(4):
        g[i, j, k] = v
    assert np.abs(g - sh.gaunt(4)).max() < 1e-14


def test_rgbe_texels_give_back_the_hdr_values():
    image = read_envmap(bundled_envmap_path("studio"))
    texels = np.frombuffer(rgbe_bytes(image), np.uint8).reshape(image.shape[0], image.shape[1], 4).astype(np.float64)
    decoded = texels[..., :3] * np.where(texels[..., 3:] > 0, 2.0 ** (texels[..., 3:] - 136), 0.0)  # as prt-web.js decodes
    assert np.array_equal(decoded.astype(np.float32), image.astype(np.float32))


# --------------------------------------------------------------------------- in a browser


@pytest.fixture(scope="module")
def browser():
    reason = missing_browser()
    if reason is not None:
        pytest.skip(f"no headless browser: {reason}")
    with chromium() as driver:
        yield driver


def _canvas(driver) -> np.ndarray:
    return decode_png_data_url(driver.execute_script("return document.getElementById('prt-canvas').toDataURL('image/png')"))


def test_demo_page_draws_the_glsl_backends_frame(browser, demo_web, record_property):
    out, _ = demo_web
    scene = Scene.load(demo_scene_path())
    cam = scene.manifest.camera
    view = (cam.eye, cam.target, cam.fov)
    with serve(out) as url:
        page = load_page(browser, url + "index.html" + page_query(*view, SIZE, "potsdamer"))
        assert page["state"] == "ready", page["error"]
        image = decode_png_data_url(page["capture"])
        # The frame time the page shows, read back (a full frame: G-buffer, networks, shading, to the GPU's finish).
        assert page["frame_ms"] > 0 and f"{page['frame_ms']:.1f} ms a frame" in page["stats"]
        record_property("web_demo", {k: page[k] for k in ("first_frame_ms", "load_ms", "frame_ms")})
        if os.environ.get("PRT_WEB_SCREENSHOT"):  # docs/images/web_demo.png: the page as a person sees it
            shot = load_page(browser, url + "index.html" + page_query(*view, 512, "potsdamer", background="envmap", capture=False))
            assert shot["state"] == "ready", shot["error"]
            browser.set_window_size(900, 720)  # the canvas and the panel
            browser.save_screenshot(os.environ["PRT_WEB_SCREENSHOT"])
            browser.set_window_size(1200, 1200)
            assert load_page(browser, url + "index.html" + page_query(*view, SIZE, "potsdamer", capture=False))["state"] == "ready"
        reference, covered = python_frame(scene, SIZE, *view, "potsdamer")
        assert covered.sum() > 20_000 and covered_psnr(image, reference, covered) >= 40.0
        # Relighting in the page runs no network: glossy, the light turned by 40 degrees, against the
        # renderer set alike; and the uniforms the page computed against shading.shader_uniforms.
        frame = browser.execute_script("window.prtWeb.view.material = 'glossy'; window.prtWeb.view.rotation = 40;"
                                       "return window.prtWeb.frame(false);")  # fmt: skip
        assert frame["networks"] is False and frame["ms"] > 0
        glossy, covered = python_frame(scene, SIZE, *view, "potsdamer", rotation=40, material="glossy")
        assert covered_psnr(_canvas(browser), glossy, covered) >= 40.0
        uniforms = browser.execute_script("return window.prtWeb.uniforms();")
        # A drag orbits the camera (pointer events, as a finger's), the wheel zooms.
        from selenium.webdriver.common.action_chains import ActionChains

        canvas = browser.find_element("id", "prt-canvas")
        ActionChains(browser).move_to_element(canvas).click_and_hold().move_by_offset(40, 15).release().perform()
        browser.execute_script("document.getElementById('prt-canvas').dispatchEvent(new WheelEvent('wheel', {deltaY: 200, cancelable: true}));")
        orbit = browser.execute_script("return window.prtWeb.view.orbit;")
        assert orbit["yaw"] < 0 and orbit["pitch"] > 0 and orbit["zoom"] > 1.1, orbit
    from prt.export.web_assets import GLOSSY_SPECULAR
    from prt.runtime.shading import Lighting, Material, shader_uniforms

    c, s = math.cos(math.radians(40)), math.sin(math.radians(40))
    lighting = Lighting.from_envmap(bundled_envmap_path("potsdamer"), rotation=[[c, 0, s], [0, 1, 0], [-s, 0, c]])
    expected = shader_uniforms(lighting, Material("glossy", albedo=scene.manifest.material.albedo, specular=GLOSSY_SPECULAR, exponent=16))
    for name in ("u_light", "u_light_matrix", "u_lobe"):
        got, want = np.asarray(uniforms[name]), expected[name].reshape(-1)
        assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max(), name


def test_bounce_page_draws_the_glsl_backends_frame(browser, cornell_rgb, tmp_path):
    """Interreflection: 16 transfer blocks, drawn 4 targets at a time (SwiftShader offers 6 draw
    buffers), per-object materials (the box's MTL colours).  A view into the box that sees no
    surface edge-on (the manifest's camera sees the ceiling at a grazing angle, where the tiny,
    noisy test networks turn the two rasterisers' position differences into ~37 dB at 256 x 256;
    docs/benchmarks/web.md has both views at 512)."""
    out = tmp_path / "cornell"
    write_web(cornell_rgb, out)
    web = json.loads((out / "web.json").read_text())
    assert web["transfer"]["blocks"] == 16 and web["material"]["per_object"] and "shade_materials.frag" in web["programs"]
    view = ((0.3, 0.6, 1.8), (0.0, -0.5, -0.2), 40.0)
    with serve(out) as url:
        page = load_page(browser, url + "index.html" + page_query(*view, SIZE, "interior"))
    assert page["state"] == "ready", page["error"]
    reference, covered = python_frame(Scene.load(cornell_rgb), SIZE, *view, "interior")
    assert covered_psnr(decode_png_data_url(page["capture"]), reference, covered) >= 40.0


def _broken(demo: Path, tmp_path: Path, name: str, change) -> Path:
    folder = tmp_path / name
    shutil.copytree(demo, folder)
    change(folder)
    return folder


def _edit_web(folder: Path, change) -> None:
    web = json.loads((folder / "web.json").read_text())
    change(web)
    (folder / "web.json").write_text(json.dumps(web))


def test_bad_folders_show_one_line_in_the_page(browser, demo_web, tmp_path):
    demo, _ = demo_web
    with serve(demo) as url:  # the browser's texture limit, from a page that works
        browser.get(url + "index.html?size=8")
        assert load_page(browser, browser.current_url)["state"] == "ready"
        limit = browser.execute_script("return window.prtWeb.limits.MAX_TEXTURE_SIZE")

    def too_large(folder):  # weights one row past the limit (a sparse file: the page refuses before fetching it)
        size = (limit + 1) * 1024 * 16
        with open(folder / "weights.bin", "r+b") as f:
            f.truncate(size)
        _edit_web(folder, lambda w: (w["weights"].update(height=limit + 1), w["files"].update({"weights.bin": size})))

    def bad_shader(folder):  # a program that does not compile (its size as web.json lists it)
        text = "#version 300 es\nvoid main() { oops; }\n"
        (folder / "shaders" / "shade.frag").write_text(text)
        _edit_web(folder, lambda w: w["files"].update({"shaders/shade.frag": len(text)}))

    cases = {
        "missing": (lambda f: (f / "weights.bin").unlink(), "", "weights.bin: HTTP 404"),
        "truncated": (lambda f: (f / "geometry.bin").write_bytes((f / "geometry.bin").read_bytes()[:1000]), "", "geometry.bin: 1000 bytes"),
        "not_json": (lambda f: (f / "web.json").write_text("{oops"), "", "web.json: not valid JSON"),
        "newer": (lambda f: _edit_web(f, lambda w: w.update(version=2)), "", "web.json: format version 2 is newer"),
        "shader": (bad_shader, "", "shaders/shade.frag: does not compile in this browser's WebGL2"),
        "too_large": (too_large, "", f"over this browser's limit of {limit} x {limit}"),
        "query": (lambda f: None, "?envmap=nowhere", 'query: envmap must be one of'),
    }  # fmt: skip
    for name, (change, query, words) in cases.items():
        folder = _broken(demo, tmp_path, name, change)
        with serve(folder) as url:
            page = load_page(browser, url + "index.html" + query, timeout=30)
        assert page["state"] == "error" and words in page["error"] and "\n" not in page["error"], (name, page["error"])
        assert browser.execute_script("return document.getElementById('prt-canvas').offsetParent") is None  # no blank canvas shown
    # Opened from the disk: browsers block the module and its fetches; the page says how to serve it.
    page = load_page(browser, (demo / "index.html").as_uri(), timeout=30)
    assert page["state"] == "error" and "python3 -m http.server" in page["error"]


@pytest.mark.slow  # a deformable build (~45 s); the page's other passes are covered above
def test_deformable_page_plays_the_recorded_poses(browser, tmp_path):
    from test_deformation import _box_arm

    from prt.runtime.renderer import Renderer
    from prt.train.deform.deform_build import DeformSpec, run_deform_build
    from prt.train.deform.deform_sources import procedural

    source = procedural("bend", np.linspace(0, 60, 7), mesh=_box_arm(), axis="z", path="bar")
    spec = DeformSpec(samples=1500, validation=200, rays=32, steps=80, hidden=16, layers=2, segments=2, pos_freqs=3)
    run_deform_build(source, tmp_path / "bar", spec, threads=2, progress=False, log=lambda *a: None)
    write_web(tmp_path / "bar", tmp_path / "web")
    scene = Scene.load(tmp_path / "bar")
    view = ((2.0, 1.4, 2.4), (0.0, 0.0, 0.0), 40.0)
    images = {}
    with serve(tmp_path / "web") as url:
        for frame in (0, 6):
            page = load_page(browser, url + "index.html" + page_query(*view, SIZE, "potsdamer", frame=frame))
            assert page["state"] == "ready", page["error"]
            images[frame] = decode_png_data_url(page["capture"])
            reference, covered = python_frame(scene, SIZE, *view, "potsdamer", frame=frame)
            with Renderer(scene, SIZE, SIZE, backend="glsl") as r:
                r.set_camera(eye=view[0], target=view[1], fov=view[2])
                r.set_deformation(frame=frame)
                normal = r.gbuffer_image().normal
            # Silhouettes and the box's edges differ by a few pixels (sub-pixel grids): ~36 dB on all
            # covered pixels at this size; away from them the frames agree.
            assert covered_psnr(images[frame], reference, covered) >= 30.0
            assert covered_psnr(images[frame], reference, interior_pixels(covered, normal)) >= 40.0
    assert np.abs(images[0].astype(int) - images[6]).mean() > 1.0  # the pose changed the frame


def test_page_walks_with_keys_and_exposes_automatically(browser, demo_web):
    """Walking in the page (issue 44): W held moves the eye along the level heading at the scene's
    speed, v switches back to the orbit; exposure=auto gives the first frame the exposure the
    runtime computes for the same view (the page reduces its shaded frame on the GPU, as the
    glsl backend does), and web.json carries the walk's figures from prt.runtime.camera."""
    from selenium.webdriver.common.action_chains import ActionChains
    from prt.runtime.camera import scene_box, walk_speed
    from prt.runtime.renderer import Renderer

    out, _ = demo_web
    web = json.loads((out / "web.json").read_text())
    scene = Scene.load(demo_scene_path())
    box = scene_box(scene.manifest)
    assert web["camera"]["walk_speed"] == pytest.approx(walk_speed(box)) and web["exposure"]["default"] == 1.0
    cam = scene.manifest.camera
    size = 64
    query = page_query(cam.eye, cam.target, cam.fov, size, "potsdamer", mode="walk").replace("exposure=1.0", "exposure=auto")
    with serve(out) as url:
        page = load_page(browser, url + "index.html" + query)
        assert page["state"] == "ready", page["error"]
        shown = browser.execute_script("return window.prtWeb.view.shownExposure;")
        with Renderer(scene, size, size, backend="glsl") as r:
            r.set_camera(eye=cam.eye, target=cam.target, fov=cam.fov)
            r.set_envmap("potsdamer")
            r.render()
            expected = r.frame_exposure()
        assert expected != pytest.approx(1.0, abs=0.1) and shown == pytest.approx(expected, rel=0.03)  # silhouettes differ by a few pixels
        before = np.array(browser.execute_script("return window.prtWeb.view.walk.eye;"))
        ActionChains(browser).key_down("w").pause(1.5).key_up("w").perform()
        after = np.array(browser.execute_script("return window.prtWeb.view.walk.eye;"))
        step = after - before
        heading = np.subtract(cam.target, cam.eye) * [1, 0, 1]
        heading /= np.linalg.norm(heading)
        assert np.linalg.norm(step) > 0.01 and abs(step[1]) < 1e-9 and step @ heading == pytest.approx(np.linalg.norm(step), rel=1e-6)
        assert np.linalg.norm(step) <= walk_speed(box) * 4.0  # at most the speed for the time held (plus slack)
        state = browser.execute_script("return [window.prtWeb.view.camera.eye, window.prtWeb.view.mode];")
        np.testing.assert_allclose(state[0], after)  # the frame drawn is from the walked eye
        ActionChains(browser).send_keys("v").perform()
        assert browser.execute_script("return window.prtWeb.view.mode;") == "orbit"
