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

__all__ = ["CHROMIUM", "CHROMEDRIVER", "CHROMIUM_FLAGS", "missing_browser", "serve", "chromium", "load_page", "decode_png_data_url"]

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
