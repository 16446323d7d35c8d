"""Headless Chromium for the web page's tests and benchmark (``prt-web``'s output, issue 37).

Debian's ``chromium``, driven by Debian's ``chromedriver`` through selenium (both installed by
``scripts/bootstrap.sh``; the driver is built from the same source as the browser, so their
versions always match), with software WebGL2 (SwiftShader through ANGLE) and no network but the
page's own server: a :func:`serve` of the folder on 127.0.0.1, in a thread of this process.

Nothing here downloads anything: the browser and the driver are given by path, so selenium's
driver manager is never asked.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import http.server
import io
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["CHROMIUM", "CHROMEDRIVER", "CHROMIUM_FLAGS", "missing_browser", "serve", "chromium", "load_page", "decode_png_data_url",
           "page_query", "python_frame", "covered_psnr", "interior_pixels"]

CHROMIUM = os.environ.get("PRT_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("PRT_CHROMEDRIVER", "/usr/bin/chromedriver")
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-dev-shm-usage",
)  # fmt: skip
"""Software WebGL2 (SwiftShader), nothing fetched from the network, no first-run dialogs."""


def missing_browser() -> str | None:
    """Why the browser tests cannot run here (None: they can)."""
    for path, package in ((CHROMIUM, "chromium"), (CHROMEDRIVER, "chromium-driver")):
        if not (Path(path).is_file() and os.access(path, os.X_OK)):
            return f"{path} missing (apt package {package}; scripts/bootstrap.sh installs it)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium missing (pip install -e .[dev])"
    return None


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # the tests' output stays readable
        pass


@contextlib.contextmanager
def serve(folder):
    """Serve ``folder`` on 127.0.0.1 (a free port) while the block runs; yields the base URL."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@contextlib.contextmanager
def chromium(window: int = 1200):
    """A headless Chromium with a fresh profile (removed afterwards), driven by selenium."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="prt-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={window},{window}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=options)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def load_page(driver, url: str, timeout: float = 60.0) -> dict:
    """Open ``url`` and wait until the page is ready or failed; what it shows.

    Returns
    -------
    dict
        ``state`` ("ready" or "error"; "loading" after ``timeout`` s), ``error`` (the text of
        ``#prt-error``), ``capture`` (the text of ``#prt-capture``), ``first_frame_ms`` (the page's
        clock at its first frame, from navigation start), ``frame_ms`` (the frame time it shows),
        ``stats`` (the text it shows), ``load_ms`` (the page's clock when its files were fetched and
        its programs linked) and ``wall_s`` (this call's time).
    """
    t0 = time.perf_counter()
    driver.get(url)
    script = ("const b = document.body; const s = document.getElementById('prt-stats');"
              "return b ? [b.dataset.prtState, document.getElementById('prt-error').textContent,"
              " (document.getElementById('prt-capture') || {}).textContent || '', b.dataset.firstFrameMs || null,"
              " s ? (s.dataset.frameMs || null) : null, s ? s.textContent : '', b.dataset.loadMs || null] : ['loading', '', '', null, null, '', null];")  # fmt: skip
    while True:
        state, error, capture, first, frame, stats, load = driver.execute_script(script)
        if state != "loading" or time.perf_counter() - t0 > timeout:
            break
        time.sleep(0.05)
    return {"state": state, "error": error, "capture": capture, "first_frame_ms": None if first is None else float(first),
            "frame_ms": None if frame is None else float(frame), "stats": stats, "wall_s": time.perf_counter() - t0,
            "load_ms": None if load is None else float(load)}  # fmt: skip


def decode_png_data_url(text: str) -> np.ndarray:
    """A ``data:image/png;base64,...`` URL as an (H, W, 3) uint8 image."""
    import imageio.v3 as iio

    prefix = "data:image/png;base64,"
    if not text.startswith(prefix):
        raise ValueError(f"not a PNG data URL: {text[:40]!r}")
    image = iio.imread(io.BytesIO(base64.b64decode(text[len(prefix):])), extension=".png")
    return np.asarray(image)[..., :3]


def page_query(eye, target, fov: float, size: int, envmap: str, *, exposure: float = 1.0, background: str = "black",
               capture: bool = True, **extra) -> str:
    """The page's query string (docs/guides/web.md): the view, and ``extra`` parameters as they are
    (``rotation``, ``material``, ``exponent``, ``frame``)."""
    vec = lambda v: ",".join(repr(float(x)) for x in v)  # noqa: E731
    parts = [f"eye={vec(eye)}", f"target={vec(target)}", f"fov={float(fov)!r}", f"size={int(size)}", f"envmap={envmap}",
             f"exposure={float(exposure)!r}", f"background={background}"]  # fmt: skip
    parts += [f"{k}={v}" for k, v in extra.items()]
    return "?" + "&".join(parts + (["capture=1"] if capture else []))


def python_frame(scene, size: int, eye, target, fov: float, envmap: str, *, exposure: float = 1.0, rotation: float = 0.0,
                 material: str = "scene", exponent: float = 16.0, frame: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The same view rendered by ``Renderer(backend="glsl")`` (llvmpipe here), as the page draws it
    with these query parameters: the tone-mapped sRGB image (H, W, 3) uint8 and the covered pixels
    (H, W) bool.  ``rotation``: degrees about +Y (the viewer's light rotation)."""
    import math

    from ..export.web_assets import GLOSSY_SPECULAR
    from ..runtime.renderer import Renderer

    a = math.radians(rotation)
    turn = [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]]
    with Renderer(scene, size, size, backend="glsl") as r:
        r.set_camera(eye=eye, target=target, fov=fov)
        r.set_envmap(envmap, rotation=turn)
        r.set_background(False)
        if material == "glossy":
            r.set_material("glossy", albedo=r.material.albedo, specular=GLOSSY_SPECULAR, exponent=exponent)
        elif material == "diffuse":
            r.set_material("diffuse", albedo=r.material.albedo)
        if frame is not None:
            r.set_deformation(frame=frame)
        image = r.render_srgb(exposure)
        covered = r.gbuffer_image().covered
    return image, covered


def covered_psnr(image: np.ndarray, reference: np.ndarray, covered: np.ndarray) -> float:
    """PSNR in dB of two tone-mapped uint8 images over the covered pixels (on [0, 1])."""
    from .metrics import psnr_from_mse

    diff = (image.astype(np.float64) - reference.astype(np.float64))[covered] / 255.0
    return psnr_from_mse(float(np.mean(diff**2)))


def interior_pixels(covered: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Covered pixels whose 3 x 3 neighbourhood is covered and has no crease (normals within 0.1):
    where two rasterisers agree on the surface, away from silhouettes and edges (SwiftShader and
    llvmpipe snap vertices to different sub-pixel grids, so an edge pixel may take the other surface)."""
    pad, npad = np.pad(covered, 1), np.pad(normal, ((1, 1), (1, 1), (0, 0)))
    h, w = covered.shape
    keep = covered.copy()
    for dy in range(3):
        for dx in range(3):
            keep &= pad[dy : dy + h, dx : dx + w] & (np.abs(npad[dy : dy + h, dx : dx + w] - normal).max(axis=2) < 0.1)
    return keep
