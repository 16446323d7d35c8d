"""prt scenes inside three.js (issue 45): ``prt-three.js``, ``three.html`` and the three.js that
``prt-web`` ships, tested in headless Chromium as the page is (``tests/test_web.py``: Debian's
``chromium`` + ``chromedriver``, software WebGL2 through SwiftShader, the folder served from
127.0.0.1).

Without a browser: the files prt-web writes for three.js (the pinned three.js, its licence, the
material's programs with the scene's own network GLSL, nothing from a CDN, the payload figure).
In a browser: ``three.html``'s capture against ``index.html``'s at the same view (the same
SwiftShader, so the same rasterisation: the only differences are three.js's matrices and the
forward material's order of operations) on the demo and on a build with bounces; a plain three.js
mesh and light beside the prt object; the light turned into a rotated object's frame; broken
folders and a bad query shown in ``#prt-error``.  Pages are 128 x 128 (a network frame of
SwiftShader takes seconds here).
"""

from __future__ import annotations

import base64
import json
import math
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from prt.bench.browser import chromium, covered_psnr, decode_png_data_url, load_page, missing_browser, page_query, serve
from prt.export.web import THREE_FILES, THREE_VERSION, VENDOR_FILES, page_file, write_web
from prt.runtime import sh
from prt.runtime.renderer import demo_scene_path
from prt.runtime.shading import TONEMAP_MAX

SIZE = 128
CORNELL_VIEW = ((0.3, 0.6, 1.8), (0.0, -0.5, -0.2), 40.0)  # test_web.py's view into the box


@pytest.fixture(scope="module")
def demo_web(tmp_path_factory):
    out = tmp_path_factory.mktemp("three") / "demo"
    write_web(demo_scene_path(), out)
    return out


# --------------------------------------------------------------------------- no browser


def test_prt_web_writes_the_three_module_and_a_pinned_three(demo_web):
    out = demo_web
    web = json.loads((out / "web.json").read_text())
    three = web["three"]
    assert three["version"] == THREE_VERSION and (three["page"], three["module"]) == THREE_FILES
    version = json.loads((out / "vendor/three/VERSION.json").read_text())
    assert version["version"] == THREE_VERSION and version["package"] == "three"
    core = (out / "vendor/three/three.core.min.js").read_text()
    assert re.search(r"\*/\s*const \w+=\"(\d+)\"", core).group(1) == THREE_VERSION.split(".")[1]  # REVISION, the first statement
    assert "The MIT License" in (out / "vendor/three/LICENSE").read_text()
    for name in VENDOR_FILES:  # the package data as it is, every file listed with its size
        assert (out / "vendor/three" / name).read_bytes() == page_file(f"vendor/three/{name}")
        assert web["files"][f"vendor/three/{name}"] == (out / "vendor/three" / name).stat().st_size
    # Minified three.js: the module and the core it imports, under 1 MB with the controls.
    assert sum((out / "vendor/three" / n).stat().st_size for n in VENDOR_FILES) < 1_000_000
    assert 'from"./three.core.min.js"' in (out / "vendor/three/three.module.min.js").read_text()
    # Nothing from a CDN: the import map names the folder's own copy.
    html = (out / "three.html").read_text()
    imports = json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1))["imports"]
    assert all(v.startswith("./vendor/three/") and (out / v).is_file() for v in imports.values()), imports
    module = (out / "prt-three.js").read_text()
    assert "http://" not in (html + module).replace("http://127.0.0.1:8000/", "") and "https://" not in html + module
    # The material runs the scene's own generated network GLSL, after the runtime's shading.
    frag = (out / three["programs"]["three.frag"]).read_text()
    seg = (demo_scene_path().parent / "segments" / "seg000.glsl").read_text()
    assert seg[seg.index("vec4 prt_freq_"):] in frag and "vec3 prt_shade_with_indirect(" in frag
    assert not frag.startswith(("#version", "precision")) and "#include <tonemapping_fragment>" in frag  # three.js prepends its prefix
    assert frag.count("#define PRT_SEGMENTS ") == 1
    # The payload three.html loads: the shared arrays, its own files, web.json.
    shared = [web["geometry"]["file"], web["weights"]["file"], *(e["image"]["file"] for e in web["lighting"]["envmaps"].values() if e["image"])]
    own = [*THREE_FILES, *(f"vendor/three/{n}" for n in VENDOR_FILES if n not in ("LICENSE", "VERSION.json", "LightProbeGrid.js")),
           *three["programs"].values()]  # fmt: skip
    assert three["payload_bytes"] == sum((out / n).stat().st_size for n in [*shared, *own, "web.json"])
    # The page's tone curve in three.js has the runtime's ceiling.
    assert float(re.search(r"export const TONEMAP_MAX = ([0-9.e+]+);", module).group(1)) == TONEMAP_MAX


# --------------------------------------------------------------------------- in a browser


@pytest.fixture(scope="module")
def browser():
    reason = missing_browser()
    if reason is not None:
        pytest.skip(f"no headless browser: {reason}")
    with chromium() as driver:
        yield driver


def _index_frame(driver, url: str, query: str) -> tuple[np.ndarray, np.ndarray]:
    """index.html's capture and its covered pixels (the G-buffer's position target, top row first)."""
    page = load_page(driver, url + "index.html" + query)
    assert page["state"] == "ready", page["error"]
    n = int(re.search(r"size=(\d+)", query).group(1))
    position = np.frombuffer(base64.b64decode(driver.execute_script("return window.prtWeb.read('position')")), np.float32)
    return decode_png_data_url(page["capture"]), position.reshape(n, n, 4)[::-1, :, 3] >= 0.5


def _three_frame(driver, url: str, query: str) -> tuple[np.ndarray, dict]:
    page = load_page(driver, url + "three.html" + query)
    assert page["state"] == "ready", page["error"]
    assert page["first_frame_ms"] > 0 and page["frame_ms"] > 0
    return decode_png_data_url(page["capture"]), page


def test_three_page_draws_the_pages_frame_on_the_demo(browser, demo_web, record_property):
    cam = json.loads((demo_web / "web.json").read_text())["camera"]
    query = page_query(cam["eye"], cam["target"], cam["fov"], SIZE, "potsdamer")
    with serve(demo_web) as url:
        reference, covered = _index_frame(browser, url, query)
        image, page = _three_frame(browser, url, query)
        assert browser.execute_script("return window.prtThree.THREE.REVISION") == THREE_VERSION.split(".")[1]
        # Glossy, the light turned by 40 degrees, exposure 1.5: uniforms only, against the page alike.
        extra = "&material=glossy&rotation=40&exposure=1.5"
        glossy_ref, _ = _index_frame(browser, url, query + extra)
        glossy, _ = _three_frame(browser, url, query + extra)
    record_property("three_demo", {k: page[k] for k in ("first_frame_ms", "load_ms", "frame_ms")})
    assert covered.sum() > 5000 and covered_psnr(image, reference, covered) >= 40.0
    assert np.abs(image[~covered].astype(int)).max() <= 1  # background black, as the page's
    assert covered_psnr(glossy, glossy_ref, covered) >= 40.0 and np.abs(glossy.astype(int) - image).mean() > 2.0


def test_three_page_draws_the_pages_frame_with_bounces(browser, cornell_rgb, tmp_path):
    """Interreflection (16 transfer blocks in one forward fragment) and per-object materials."""
    out = tmp_path / "cornell"
    write_web(cornell_rgb, out)
    web = json.loads((out / "web.json").read_text())
    assert web["transfer"]["blocks"] == 16 and "three_materials.frag" in web["three"]["programs"]
    query = page_query(*CORNELL_VIEW, SIZE, "interior")
    with serve(out) as url:
        reference, covered = _index_frame(browser, url, query)
        image, _ = _three_frame(browser, url, query)
    assert covered.sum() > 5000 and covered_psnr(image, reference, covered) >= 40.0


def test_a_plain_three_mesh_beside_the_prt_object(browser, demo_web):
    query = page_query(*_demo_view(demo_web), SIZE, "potsdamer")
    with serve(demo_web) as url:
        alone, _ = _three_frame(browser, url, query)
        both, _ = _three_frame(browser, url, query + "&extra=1")
        names = browser.execute_script("return window.prtThree.scene.children.map((o) => o.type + ':' + o.name)")
    assert any(n.startswith("Mesh:extra") for n in names) and any(n.startswith("DirectionalLight") for n in names), names
    rgb = both.astype(int)
    ball = (rgb[..., 0] > 60) & (rgb[..., 0] > 2 * rgb[..., 1] + 10) & (rgb[..., 0] > 2 * rgb[..., 2] + 10)  # the red ball, lit
    assert ball.sum() > 100 and np.any(rgb[ball, 0] > 150), ball.sum()  # its lit side is bright
    # The prt object is drawn as before wherever the ball does not cover it (one depth buffer).
    grey = alone.astype(int)
    prt_pixels = (grey.max(axis=2) > 10) & ~ball
    assert prt_pixels.sum() > 3000 and covered_psnr(both, alone, prt_pixels) >= 40.0


def test_three_js_light_probe_grid_on_the_same_scene(browser, demo_web):
    """three.html?grid=...: three.js's own baked light (a LightProbeGrid over the scene's box, the
    same triangles with a MeshLambertMaterial) in place of the prt material; the study compares it
    with the ray-traced reference (docs/benchmarks/three.md)."""
    query = page_query(*_demo_view(demo_web), 64, "potsdamer")
    with serve(demo_web) as url:
        prt, _ = _three_frame(browser, url, query)
        grid, _ = _three_frame(browser, url, query + "&grid=4,2,4")
        kinds = browser.execute_script("return window.prtThree.scene.children.map((o) => o.isLightProbeGrid ? 'grid' : o.name)")
        bake_ms = float(browser.execute_script("return document.body.dataset.bakeMs"))
    assert "grid" in kinds and "lambert" in kinds and bake_ms > 0, kinds
    covered = prt.max(axis=2) > 10
    assert grid[covered].mean() > 60 and np.abs(grid.astype(int) - prt)[covered].mean() > 3  # lit by the probes, and not the prt frame


def _demo_view(out: Path):
    cam = json.loads((out / "web.json").read_text())["camera"]
    return cam["eye"], cam["target"], cam["fov"]


def test_the_light_follows_the_objects_rotation(browser, demo_web):
    """The networks see the scene's own frame: a rotated object is lit in it.  The object, the
    camera and the light turned together about +Y give the unturned frame; and the module's SH
    rotation for any rotation is numpy's (g(w) = f(M w))."""
    eye, target, fov = _demo_view(demo_web)
    a = math.radians(35.0)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])  # R_y as three's makeRotationY
    with serve(demo_web) as url:
        straight, _ = _three_frame(browser, url, page_query(eye, target, fov, SIZE, "potsdamer"))
        # The light turned by the same rotation (the page's rotation: sh.rotation_matrices(R_y), g(w) = f(R_y^T w)).
        _three_frame(browser, url, page_query(turn @ eye, turn @ target, fov, SIZE, "potsdamer", rotation=35.0))
        turned = decode_png_data_url(browser.execute_script(
            "const t = window.prtThree; t.prt.object.rotation.y = arguments[0]; t.prt.object.updateMatrixWorld(); t.frame();"
            "return t.renderer.domElement.toDataURL('image/png');", a))  # fmt: skip
        m = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
        d = np.array(browser.execute_async_script(
            "const done = arguments[1]; import('./prt-three.js').then((mod) => done(mod.shRotation(arguments[0])));", m.tolist()))  # fmt: skip
    covered = straight.max(axis=2) > 10
    assert covered.sum() > 5000 and covered_psnr(turned, straight, covered) >= 40.0
    dirs = np.random.default_rng(4).normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    c = np.random.default_rng(5).normal(size=16)
    assert np.abs(sh.basis(dirs, 4) @ (d @ c) - sh.basis(dirs @ m.T, 4) @ c).max() < 1e-9


def test_bad_folders_show_one_line_in_the_three_page(browser, demo_web, tmp_path):
    def edit_web(folder, change):
        web = json.loads((folder / "web.json").read_text())
        change(web)
        (folder / "web.json").write_text(json.dumps(web))

    def bad_shader(folder):
        text = "void main() { oops; }\n"
        (folder / "shaders" / "three.frag").write_text(text)
        edit_web(folder, lambda w: w["files"].update({"shaders/three.frag": len(text)}))

    cases = {
        "missing": (lambda f: (f / "weights.bin").unlink(), "", "weights.bin: HTTP 404"),
        "truncated": (lambda f: (f / "geometry.bin").write_bytes((f / "geometry.bin").read_bytes()[:1000]), "", "geometry.bin: 1000 bytes"),
        "no_three": (lambda f: shutil.rmtree(f / "vendor"), "", "vendor/three: three.js could not be loaded"),
        "old_web": (lambda f: edit_web(f, lambda w: w.pop("three")), "", 'web.json: no "three"'),
        "shader": (bad_shader, "", "shaders/three.frag: does not compile in this browser's WebGL2"),
        "query": (lambda f: None, "?envmap=nowhere", "query: envmap must be one of"),
        "grid": (lambda f: None, "?grid=1,2", "query: grid must be three whole numbers"),
        "deformable": (lambda f: edit_web(f, lambda w: w.update(deformation={"frames": 2})), "", "a deformable scene; prt-three.js draws rigid"),
    }  # fmt: skip
    for name, (change, query, words) in cases.items():
        folder = tmp_path / name
        shutil.copytree(demo_web, folder)
        change(folder)
        with serve(folder) as url:
            page = load_page(browser, url + "three.html" + query, timeout=60)
        assert page["state"] == "error" and words in page["error"] and "\n" not in page["error"], (name, page["error"])
        assert browser.execute_script("return document.getElementById('prt-canvas').offsetParent") is None
    page = load_page(browser, (demo_web / "three.html").as_uri(), timeout=30)
    assert page["state"] == "error" and "python3 -m http.server" in page["error"]


def test_the_guides_ten_lines_draw_the_scene(browser, demo_web, tmp_path):
    """docs/guides/three.md's snippet, as it is, in an app page beside the folder (prt/)."""
    guide = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "three.md").read_text()
    snippet = re.search(r"## The ten lines an app needs\n\n```html\n(.*?)```", guide, re.S).group(1)
    assert len([line for line in snippet.splitlines() if line.strip() and not line.startswith("<")]) <= 10
    app = tmp_path / "app"
    shutil.copytree(demo_web, app / "prt")
    shim = ("<script>const getContext = HTMLCanvasElement.prototype.getContext;"  # keep the frame readable after it is drawn
            "HTMLCanvasElement.prototype.getContext = function (kind, options) {"
            " return getContext.call(this, kind, Object.assign({}, options, { preserveDrawingBuffer: true })); };</script>")  # fmt: skip
    (app / "index.html").write_text(f"<!doctype html><html><body><canvas width='96' height='96'></canvas>{shim}\n{snippet}</body></html>")
    with serve(app) as url:
        browser.get(url + "index.html")
        image = None
        for _ in range(600):
            text = browser.execute_script("const c = document.querySelector('canvas'); return c.toDataURL('image/png');")
            image = decode_png_data_url(text)
            if image.max() > 0:
                break
            time.sleep(0.1)
    assert image is not None and (image.max(axis=2) > 40).sum() > 500  # the cow and its floor, lit
