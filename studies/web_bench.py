"""The web page (prt-web, issue 37) in headless Chromium against the Python GLSL backend.

usage: python studies/web_bench.py [--size 512] [--rounds 5] [--json docs/benchmarks/web.json]

Measures, on this machine (Debian's chromium with software WebGL2, SwiftShader; the Python
renderer on Mesa llvmpipe; both on the CPU):

- payload of the demo page (geometry + weights + code, and the env maps' texels);
- load: the page's clock when its files are fetched and programs linked, and when its first
  frame is drawn, from navigation start, in a fresh browser each (cold caches), at 128, 256 and
  the page's default 512;
- same pixels: the page's frame against ``Renderer(backend="glsl")`` tone-mapped, PSNR over the
  covered pixels (and over the pixels away from silhouettes and creases), on the demo and on a
  Cornell box built with 2 bounces (built once into ``docs/benchmarks/web_cache/``);
- frame time: full frames (G-buffer, networks, shading, to the GPU's finish) of the page and of
  the Python GLSL backend, interleaved in ``--rounds`` rounds (medians), and their ratio.

Targets: >= 40 dB on two scenes; payload <= 2 MB; loaded and first frame drawn within 3 s.
The machine is shared: ``other_cpu_share_before`` is the other processes' share of the cores in
the 3 s before the run; the browser's own processes count as "others" during it.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import ROOT, write_figures  # beside this script (its folder is sys.path[0])

from prt.bench.browser import (
    chromium, covered_psnr, decode_png_data_url, interior_pixels, load_page, missing_browser, page_query, python_frame, serve,
)  # fmt: skip
from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import cpu_label, provenance
from prt.export.web import write_web
from prt.runtime.renderer import Renderer, Scene, demo_scene_path

CACHE = ROOT / "docs" / "benchmarks" / "web_cache"
CORNELL_VIEWS = {"into the box": ((0.3, 0.6, 1.8), (0.0, -0.5, -0.2)), "manifest camera": ((0.0, 0.6, 3.2), (0.0, 0.0, 0.0))}


def cornell_scene() -> Path:
    """The Cornell box with 2 bounces (tests/conftest.py's build), built once into the cache."""
    out = CACHE / "cornell_rgb"
    if not (out / "scene.json").is_file():
        cmd = [sys.executable, "-m", "prt.train.train_cli", str(ROOT / "tests" / "data" / "CornellBox-Original.obj"), "-o", str(out),
               "--samples", "2500", "--validation", "600", "--rays", "32", "--segments", "1", "--hidden", "16", "--layers", "2",
               "--steps", "200", "--bounces", "2", "--bounce-rays", "32", "--no-analytic", "--no-progress", "--threads", "1"]  # fmt: skip
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out / "scene.json"


def same_pixels(driver, url: str, scene: Scene, size: int, eye, target, fov: float, envmap: str) -> dict:
    page = load_page(driver, url + "index.html" + page_query(eye, target, fov, size, envmap), timeout=600)
    if page["state"] != "ready":
        raise SystemExit(f"the page failed: {page['error']}")
    image = decode_png_data_url(page["capture"])
    reference, covered = python_frame(scene, size, eye, target, fov, envmap)
    with Renderer(scene, size, size, backend="glsl") as r:
        r.set_camera(eye=eye, target=target, fov=fov)
        normal = r.gbuffer_image().normal
    flips = int(np.count_nonzero(np.abs(image.astype(int) - reference).max(axis=2)[covered] > 10))
    return {"size": size, "eye": list(eye), "target": list(target), "fov": fov, "envmap": envmap, "covered_pixels": int(covered.sum()),
            "psnr_db": round(covered_psnr(image, reference, covered), 2),
            "psnr_db_away_from_edges": round(covered_psnr(image, reference, interior_pixels(covered, normal)), 2),
            "pixels_off_by_more_than_10": flips}  # fmt: skip


def frame_times(driver, url: str, scene: Scene, size: int, rounds: int) -> dict:
    """Full frames of the page and of the Python GLSL backend, interleaved; medians and the ratio."""
    cam = scene.manifest.camera
    page = load_page(driver, url + "index.html" + page_query(cam.eye, cam.target, cam.fov, size, "potsdamer", capture=False), timeout=600)
    if page["state"] != "ready":
        raise SystemExit(f"the page failed: {page['error']}")
    web, python = [], []
    with Renderer(scene, size, size, backend="glsl") as r:
        r.set_envmap("potsdamer")
        start = r.camera
        r.render()  # warm-up: compile
        for i in range(rounds):
            web += driver.execute_script("return window.prtWeb.benchmark(1, true)")
            r.set_camera_object(start.orbit(0.001 * (i + 1)))  # a new view: the networks run
            t0 = time.perf_counter()
            r.render()
            python.append(1e3 * (time.perf_counter() - t0))
        relight_web = driver.execute_script("return window.prtWeb.benchmark(5, false)")
        relight_python = []
        for i in range(5):
            r.set_envmap("potsdamer", rotation=[[np.cos(0.1 * i), 0, np.sin(0.1 * i)], [0, 1, 0], [-np.sin(0.1 * i), 0, np.cos(0.1 * i)]])
            t0 = time.perf_counter()
            r.render()
            relight_python.append(1e3 * (time.perf_counter() - t0))
    out = {"size": size, "rounds": rounds, "web_frame_ms": round(float(np.median(web)), 1), "python_glsl_frame_ms": round(float(np.median(python)), 1),
           "web_relight_ms": round(float(np.median(relight_web)), 1), "python_glsl_relight_ms": round(float(np.median(relight_python)), 1),
           "web_frames_ms": [round(v, 1) for v in web], "python_glsl_frames_ms": [round(v, 1) for v in python]}  # fmt: skip
    out["web_over_python_frame"] = round(out["web_frame_ms"] / out["python_glsl_frame_ms"], 2)
    out["fps_web"] = round(1e3 / out["web_frame_ms"], 2)
    out["fps_python_glsl"] = round(1e3 / out["python_glsl_frame_ms"], 2)
    return out


def markdown(fig: dict) -> str:
    p, t = fig["payload"], fig["frame_time"]
    lines = [
        "# The web page in headless Chromium (issue 37)", "",
        f"`{fig['provenance']['command']}`, {fig['provenance']['date']}, {fig['cpu']}; other processes' share of the cores "
        f"before the run {fig['other_cpu_share_before']}.  Chromium {fig['chromium']} with SwiftShader (software WebGL2); "
        "the Python GLSL backend on Mesa llvmpipe.", "",
        "| scene, view | size | covered px | PSNR dB (covered) | PSNR dB (away from edges) | px off by > 10 |",
        "|---|---|---|---|---|---|",
    ]  # fmt: skip
    for name, r in fig["same_pixels"].items():
        lines.append(f"| {name} | {r['size']} | {r['covered_pixels']} | {r['psnr_db']} | {r['psnr_db_away_from_edges']} | {r['pixels_off_by_more_than_10']} |")
    lines += ["", f"Demo payload: {p['payload_bytes'] / 1e6:.2f} MB in all; geometry + weights + code {p['geometry_weights_code_bytes'] / 1e6:.2f} MB "
              f"(target <= 2 MB), env maps {p['envmap_bytes'] / 1e6:.2f} MB.", ""]  # fmt: skip
    lines += ["| load (demo) | size | files fetched, programs linked (ms) | first frame drawn (ms) |", "|---|---|---|---|"]
    for r in fig["load"]:
        lines.append(f"| cold browser, navigation start -> | {r['size']} | {r['load_ms']} | {r['first_frame_ms']} |")
    lines += ["", f"Frame time at {t['size']} x {t['size']} (demo, full frames: G-buffer, networks, shading; medians of {t['rounds']} "
              f"interleaved rounds): page {t['web_frame_ms']} ms ({t['fps_web']} FPS), Python GLSL backend {t['python_glsl_frame_ms']} ms "
              f"({t['fps_python_glsl']} FPS): ratio {t['web_over_python_frame']}.  Relight (no network): page {t['web_relight_ms']} ms, "
              f"Python {t['python_glsl_relight_ms']} ms.", ""]  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    reason = missing_browser()
    if reason:
        raise SystemExit(f"web_bench: {reason}")
    before = busy_seconds()
    time.sleep(3.0)
    background = other_cpu_share(before, 3.0)
    demo = Scene.load(demo_scene_path())
    cornell = Scene.load(cornell_scene())
    figures: dict = {"provenance": provenance(), "other_cpu_share_before": background}
    with tempfile.TemporaryDirectory() as tmp:
        demo_out, cornell_out = Path(tmp) / "demo", Path(tmp) / "cornell"
        report = write_web(demo_scene_path(), demo_out)
        write_web(cornell.path, cornell_out)
        files = report["files"]
        envmaps = sum(v for k, v in files.items() if k.startswith("envmaps/"))
        figures["payload"] = {"payload_bytes": report["payload_bytes"], "envmap_bytes": envmaps,
                              "geometry_weights_code_bytes": report["payload_bytes"] - envmaps, "files": files}  # fmt: skip
        start = busy_seconds()
        t0 = time.perf_counter()
        figures["load"] = []
        with serve(demo_out) as url:
            for size in sorted({128, 256, 512, args.size}):  # cold: a fresh browser (profile, caches) each time
                with chromium() as driver:
                    page = load_page(driver, url + "index.html" + f"?size={size}", timeout=600)
                figures["load"].append({"size": size, "load_ms": page["load_ms"], "first_frame_ms": page["first_frame_ms"], "frame_ms": page["frame_ms"]})
        with chromium() as driver:
            figures["chromium"] = driver.capabilities.get("browserVersion")
            with serve(demo_out) as url:
                cam = demo.manifest.camera
                figures["same_pixels"] = {"demo, manifest camera": same_pixels(driver, url, demo, args.size, cam.eye, cam.target, cam.fov, "potsdamer")}
                figures["frame_time"] = frame_times(driver, url, demo, args.size, args.rounds)
            with serve(cornell_out) as url:
                for name, (eye, target) in CORNELL_VIEWS.items():
                    figures["same_pixels"][f"Cornell, 2 bounces, {name}"] = same_pixels(driver, url, cornell, args.size, eye, target, 40.0, "interior")
        figures["other_cpu_share_during"] = other_cpu_share(start, time.perf_counter() - t0)
    figures["cpu"] = cpu_label(figures["provenance"].get("machine"))
    figures["targets"] = {
        "psnr_db_two_scenes_at_least_40": min(figures["same_pixels"]["demo, manifest camera"]["psnr_db"],
                                              figures["same_pixels"]["Cornell, 2 bounces, into the box"]["psnr_db"]) >= 40.0,
        "payload_at_most_2mb": figures["payload"]["geometry_weights_code_bytes"] <= 2_000_000,
        "first_frame_within_3s_at_512": next(r for r in figures["load"] if r["size"] == 512)["first_frame_ms"] <= 3000.0,
    }  # fmt: skip
    print(json.dumps({k: v for k, v in figures.items() if k != "provenance"}, indent=1))
    write_figures(args.json, figures)
    if args.json is not None:
        args.json.with_suffix(".md").write_text(markdown(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
