"""prt scenes inside three.js (issue 45): three.html against index.html in headless Chromium.

usage: python studies/three_bench.py [--size 256] [--rounds 3] [--json docs/benchmarks/three.json]

Measures, on this machine (Debian's chromium with software WebGL2, SwiftShader, on the CPU):

- same pixels: ``three.html``'s capture (prt-three.js's ShaderMaterial in three.js, forward)
  against ``index.html``'s (the page's deferred passes) at the same view, PSNR over the covered
  pixels of the tone-mapped sRGB frames, on the demo and on a Cornell box built with 2 bounces
  (``web_bench.py``'s build, cached in ``docs/benchmarks/web_cache/``);
- sizes: ``prt-three.js``, ``three.html``, the vendored three.js (minified module + core +
  OrbitControls) and everything three.html loads;
- first frame: each page in a fresh browser (cold caches), the page's clock from navigation start
  when its files are fetched, how long three.html's ``renderer.compile`` takes (the material's
  program, with the networks) and when its first frame is drawn;
- against the ray-traced reference (the demo, ``--ref-size``): the page, three.html, and three.js's
  own LightProbeGrid baked on the same scene (three.html?grid=...);
- frame time: full frames (every network runs) of index.html, of three.html and of three.html
  without the depth pre-pass, interleaved in ``--rounds`` rounds (three tabs of one browser),
  medians and ratios.

The machine is shared: ``other_cpu_share_before`` is the other processes' share of the cores in
the 3 s before the run.
"""

from __future__ import annotations

import argparse
import base64
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import write_figures  # beside this script (its folder is sys.path[0])
from web_bench import CORNELL_VIEWS, cornell_scene

from prt.bench.browser import chromium, covered_psnr, decode_png_data_url, load_page, missing_browser, page_query, serve
from prt.bench.machine import busy_seconds, other_cpu_share
from prt.bench.provenance import cpu_label, provenance
from prt.export.web import THREE_VERSION, VENDOR_FILES, write_web
from prt.runtime.renderer import demo_scene_path


def _ready(page: dict, what: str) -> dict:
    if page["state"] != "ready":
        raise SystemExit(f"{what} failed: {page['error']}")
    return page


def same_pixels(driver, url: str, size: int, eye, target, fov: float, envmap: str) -> dict:
    query = page_query(eye, target, fov, size, envmap)
    index = _ready(load_page(driver, url + "index.html" + query, timeout=600), "index.html")
    position = np.frombuffer(base64.b64decode(driver.execute_script("return window.prtWeb.read('position')")), np.float32)
    covered = position.reshape(size, size, 4)[::-1, :, 3] >= 0.5
    three = _ready(load_page(driver, url + "three.html" + query, timeout=600), "three.html")
    a, b = decode_png_data_url(index["capture"]), decode_png_data_url(three["capture"])
    diff = np.abs(a.astype(int) - b).max(axis=2)
    return {"size": size, "eye": list(map(float, eye)), "target": list(map(float, target)), "fov": float(fov), "envmap": envmap,
            "covered_pixels": int(covered.sum()), "psnr_db": round(covered_psnr(b, a, covered), 2),
            "max_abs_diff_8bit": int(diff[covered].max()), "pixels_off_by_more_than_2": int((diff[covered] > 2).sum())}  # fmt: skip


def against_reference(driver, url: str, size: int, camera: dict, grids: list[str], rays: int, strip: Path | None = None) -> dict:
    """The demo against the ray-traced reference (``prt.bench.reference``'s: transfer traced at every
    covered pixel of the renderer's G-buffer, shaded with the same SH light, tone-mapped): the page,
    three.html, and three.js's own LightProbeGrid (three.html?grid=...: a MeshLambertMaterial of
    the scene's albedo lit by L2 irradiance probes baked from the env map over the scene's box)."""
    from prt.bench.reference import load_scene_geometry, shade_image
    from prt.runtime.envmaps import bundled_envmap_path
    from prt.runtime.renderer import Renderer, Scene
    from prt.runtime.shading import Lighting, Material, to_srgb8
    from prt.train import compute_transfer
    from prt.train.transport.transfer import make_tracer

    scene = Scene.load(demo_scene_path())
    eye, target, fov = camera["eye"], camera["target"], camera["fov"]
    with Renderer(scene, size, size, backend="glsl") as r:
        r.set_camera(eye=eye, target=target, fov=fov)
        gbuffer = r.gbuffer_image()
    covered = gbuffer.covered
    geometry, _ = load_scene_geometry(scene.manifest)
    tracer = make_tracer(geometry)
    lighting = Lighting.from_envmap(bundled_envmap_path("potsdamer"))
    material = Material("diffuse", albedo=scene.manifest.material.albedo)
    refs = []
    for seed in (0, 1):  # the reference's own noise: a second seed
        transfer = compute_transfer(geometry, gbuffer.position[covered], gbuffer.normal[covered], rays=rays, seed=seed, tracer=tracer)
        refs.append(to_srgb8(shade_image(transfer, gbuffer, eye, lighting, material)))
    query = page_query(eye, target, fov, size, "potsdamer")
    rows = {"reference, second seed": refs[1]}
    rows["index.html (prt-web page)"] = decode_png_data_url(_ready(load_page(driver, url + "index.html" + query, timeout=600), "index.html")["capture"])
    rows["three.html (prt-three.js)"] = decode_png_data_url(_ready(load_page(driver, url + "three.html" + query, timeout=600), "three.html")["capture"])
    bake_ms = {}
    for grid in grids:
        page = _ready(load_page(driver, url + "three.html" + query + f"&grid={grid}", timeout=600), "three.html?grid")
        rows[f"three.js LightProbeGrid {grid.replace(',', ' x ')} (three.html?grid={grid})"] = decode_png_data_url(page["capture"])
        bake_ms[grid] = float(driver.execute_script("return document.body.dataset.bakeMs"))
    if strip is not None:  # reference | page | three.html | LightProbeGrid, side by side
        import imageio.v3 as iio

        iio.imwrite(strip, np.concatenate([refs[0], *(rows[k] for k in list(rows)[1:])], axis=1))
    out = {"size": size, "rays": rays, "covered_pixels": int(covered.sum()), "grids": grids, "grid_bake_ms": bake_ms,
           "psnr_db": {name: round(covered_psnr(image, refs[0], covered), 2) for name, image in rows.items()},
           "mean_signed_error_8bit": {name: round(float((image.astype(float) - refs[0])[covered].mean()), 2) for name, image in rows.items()}}  # fmt: skip
    return out


def frame_times(driver, url: str, size: int, rounds: int, eye, target, fov: float, envmap: str) -> dict:
    """Full frames of index.html (its networks rerun) and of three.html with and without the depth
    pre-pass (``prt.prepass.visible`` toggled in the same page), interleaved; medians and ratios."""
    query = page_query(eye, target, fov, size, envmap, capture=False)
    _ready(load_page(driver, url + "index.html" + query, timeout=600), "index.html")
    index_tab = driver.current_window_handle
    driver.switch_to.new_window("tab")
    _ready(load_page(driver, url + "three.html" + query, timeout=600), "three.html")
    three_tab = driver.current_window_handle
    times: dict[str, list] = {"index": [], "three": [], "three_no_prepass": []}
    for _ in range(rounds):
        driver.switch_to.window(index_tab)
        times["index"].append(float(driver.execute_script("return window.prtWeb.benchmark(1, true)[0]")))
        driver.switch_to.window(three_tab)
        for name, on in (("three", "true"), ("three_no_prepass", "false")):
            times[name].append(float(driver.execute_script(f"window.prtThree.prt.prepass.visible = {on}; return window.prtThree.frame();")))
    driver.close()
    driver.switch_to.window(index_tab)
    med = {k: round(float(np.median(v)), 1) for k, v in times.items()}
    return {"size": size, "rounds": rounds, "median_ms": med, "frames_ms": {k: [round(x, 1) for x in v] for k, v in times.items()},
            "three_over_index": round(med["three"] / med["index"], 2),
            "three_no_prepass_over_three": round(med["three_no_prepass"] / med["three"], 2)}  # fmt: skip


def markdown(fig: dict) -> str:
    s = fig["sizes"]
    lines = [
        "# prt scenes inside three.js (issue 45)", "",
        f"`{fig['provenance']['command']}`, {fig['provenance']['date']}, {fig['cpu']}; other processes' share of the cores before the "
        f"run {fig['other_cpu_share_before']}.  Chromium {fig['chromium']} with SwiftShader (software WebGL2); three.js {fig['three_version']} "
        "(vendored from npm).", "",
        "`three.html` (prt-three.js's ShaderMaterial, forward) against `index.html` (the page's deferred passes) at the same view, "
        "tone-mapped sRGB:", "",
        "| scene, view | size | covered px | PSNR dB (covered) | max abs diff (8 bit) | px off by > 2 |", "|---|---|---|---|---|---|",
    ]  # fmt: skip
    for name, r in fig["same_pixels"].items():
        lines.append(f"| {name} | {r['size']} | {r['covered_pixels']} | {r['psnr_db']} | {r['max_abs_diff_8bit']} | {r['pixels_off_by_more_than_2']} |")
    lines += ["", f"Sizes: `prt-three.js` {s['prt_three_js_bytes']:,} bytes, `three.html` {s['three_html_bytes']:,} bytes, vendored three.js "
              f"(minified module + core + OrbitControls) {s['vendored_three_bytes']:,} bytes; three.html loads {s['three_payload_bytes'] / 1e6:.2f} MB "
              f"for the demo (index.html {s['index_payload_bytes'] / 1e6:.2f} MB).", ""]  # fmt: skip
    lines += ["| first frame (demo, cold browser) | size | files fetched (ms) | `renderer.compile` (ms) | first frame drawn (ms) |", "|---|---|---|---|---|"]
    for r in fig["first_frame"]:
        lines.append(f"| {r['page']} | {r['size']} | {r['load_ms']} | {r['three_compile_call_ms'] if r['three_compile_call_ms'] is not None else '-'} "
                     f"| {r['first_frame_ms']} |")  # fmt: skip
    ref = fig["reference"]
    lines += ["", f"The demo against the ray-traced reference ({ref['rays']} rays per pixel, shaded with the same SH light, tone-mapped; "
              f"{ref['size']} x {ref['size']}, {ref['covered_pixels']} covered pixels). three.js's LightProbeGrid: the same triangles with a "
              "MeshLambertMaterial of the scene's albedo, lit by L2 irradiance probes baked from the env map over the scene's box "
              f"(cube maps of 32 px; baked in {', '.join(f'{v:.0f} ms ({k})' for k, v in ref['grid_bake_ms'].items())}).  "
              f"Side by side in [`three_reference.png`](three_reference.png): reference, page, three.html, the grids.", "",
              "| image | PSNR dB against the reference (covered) | mean signed error (8 bit) |", "|---|---|---|"]  # fmt: skip
    for name, value in ref["psnr_db"].items():
        lines.append(f"| {name} | {value} | {ref['mean_signed_error_8bit'][name]:+.2f} |")
    t0 = next(iter(fig["frame_time"].values()))
    lines += ["", f"Full frames at {t0['size']} x {t0['size']} (every network runs; medians of {t0['rounds']} interleaved rounds; the pre-pass "
              "toggled in the same page):", "",
              "| scene | index.html (ms) | three.html (ms) | three / index | three.html without the depth pre-pass (ms) | without / with |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for name, t in fig["frame_time"].items():
        m = t["median_ms"]
        lines.append(f"| {name} | {m['index']} | {m['three']} | {t['three_over_index']} | {m['three_no_prepass']} | {t['three_no_prepass_over_three']} |")
    lines += ["", "The page caches the transfer between frames of one view (relighting runs no network); the three.js material is forward "
              "and runs the networks in every frame it draws, so a three.js app renders on demand.  SwiftShader compiles a program at its "
              "first draw, so `renderer.compile` returns at once and the compile lands in the first frame.", ""]  # fmt: skip
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--grid", nargs="+", default=["8,4,8", "16,8,16"], help="probes of three.js's LightProbeGrid along X, Y, Z (reference rows)")
    ap.add_argument("--ref-rays", type=int, default=1024, help="rays per pixel of the ray-traced reference")
    ap.add_argument("--ref-size", type=int, default=128)
    args = ap.parse_args(argv)
    reason = missing_browser()
    if reason:
        raise SystemExit(f"three_bench: {reason}")
    before = busy_seconds()
    time.sleep(3.0)
    figures: dict = {"provenance": provenance(), "other_cpu_share_before": other_cpu_share(before, 3.0), "three_version": THREE_VERSION}
    cornell = cornell_scene()
    with tempfile.TemporaryDirectory() as tmp:
        demo_out, cornell_out = Path(tmp) / "demo", Path(tmp) / "cornell"
        report = write_web(demo_scene_path(), demo_out)
        write_web(cornell, cornell_out)
        files = report["files"]
        figures["sizes"] = {"prt_three_js_bytes": files["prt-three.js"], "three_html_bytes": files["three.html"],
                            "vendored_three_bytes": sum(files[f"vendor/three/{n}"] for n in VENDOR_FILES if n.endswith(".js") and n != "LightProbeGrid.js"),
                            "vendored_light_probe_grid_bytes": files["vendor/three/LightProbeGrid.js"],
                            "three_payload_bytes": report["three_payload_bytes"], "index_payload_bytes": report["payload_bytes"]}  # fmt: skip
        web = json.loads((demo_out / "web.json").read_text())
        cam = web["camera"]
        start = busy_seconds()
        t0 = time.perf_counter()
        figures["first_frame"] = []
        with serve(demo_out) as url:
            for size in (128, args.size):
                for page in ("index.html", "three.html"):
                    with chromium() as driver:  # cold: a fresh browser (profile, caches) each time
                        p = _ready(load_page(driver, url + page + f"?size={size}", timeout=600), page)
                        compile_ms = driver.execute_script("return document.body.dataset.compileMs || null")
                    figures["first_frame"].append({"page": page, "size": size, "load_ms": p["load_ms"], "first_frame_ms": p["first_frame_ms"],
                                                   "three_compile_call_ms": None if compile_ms is None else float(compile_ms)})  # fmt: skip
        with chromium() as driver:
            figures["chromium"] = driver.capabilities.get("browserVersion")
            with serve(demo_out) as url:
                figures["same_pixels"] = {"demo, manifest camera": same_pixels(driver, url, args.size, cam["eye"], cam["target"], cam["fov"], "potsdamer")}
                figures["frame_time"] = {"demo, manifest camera": frame_times(driver, url, args.size, args.rounds, cam["eye"], cam["target"],
                                                                              cam["fov"], "potsdamer")}  # fmt: skip
                strip = None if args.json is None else args.json.with_name(args.json.stem + "_reference.png")
                figures["reference"] = against_reference(driver, url, args.ref_size, cam, args.grid, args.ref_rays, strip)
            with serve(cornell_out) as url:
                eye, target = CORNELL_VIEWS["into the box"]
                figures["same_pixels"]["Cornell, 2 bounces, into the box"] = same_pixels(driver, url, args.size, eye, target, 40.0, "interior")
                figures["frame_time"]["Cornell, 2 bounces, into the box"] = frame_times(driver, url, args.size, args.rounds, eye, target, 40.0, "interior")
        figures["other_cpu_share_during"] = other_cpu_share(start, time.perf_counter() - t0)
    figures["cpu"] = cpu_label(figures["provenance"].get("machine"))
    figures["targets"] = {"psnr_db_two_scenes_at_least_40": min(r["psnr_db"] for r in figures["same_pixels"].values()) >= 40.0}
    print(json.dumps({k: v for k, v in figures.items() if k != "provenance"}, indent=1))
    write_figures(args.json, figures)
    if args.json is not None:
        args.json.with_suffix(".md").write_text(markdown(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
