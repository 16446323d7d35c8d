"""The web page of a built scene (hundreds of segments and objects) in headless Chromium (issue 44).

usage: python studies/web_scene_bench.py SCENE_DIR [--cameras VIEWS.json] [--size 512] [--rounds 3]
                                         [--json OUT.json] [--md OUT.md]

``prt-web SCENE -o TMP``; then, on this machine (Debian's chromium, software WebGL2 through
SwiftShader; the Python renderer on Mesa llvmpipe): the payload (geometry, weights, code; env
maps apart), the segments, objects and materials the page carries, the page loaded cold (a fresh
browser) at 256 and ``--size`` (files fetched and programs linked, first frame drawn, from
navigation start), the page's frame against ``Renderer(backend="glsl")`` at the scene's first
camera view (PSNR over covered pixels, same exposure), and full frames of the page and of the Python
GLSL backend interleaved in ``--rounds`` rounds (medians).  The machine is shared: the other
processes' share of the cores is recorded.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from web_bench import frame_times, same_pixels  # noqa: E402

from prt.bench.browser import chromium, load_page, missing_browser, serve  # noqa: E402
from prt.bench.machine import busy_seconds, other_cpu_share  # noqa: E402
from prt.bench.provenance import cpu_label, provenance  # noqa: E402
from prt.export.web import write_web  # noqa: E402
from prt.runtime.files import atomic_write_bytes, atomic_write_json  # noqa: E402
from prt.runtime.renderer import Scene  # noqa: E402


def markdown(fig: dict) -> str:
    prov = fig["provenance"]
    s = fig["scene"]
    lines = [f"Made by `{prov.get('command')}` ({prov.get('date')}, {fig['cpu']}, Chromium {fig.get('chromium')}, software WebGL2).", "",
             f"Scene `{s['name']}`: {s['segments']} segments, {s['objects']} objects, {s['materials']} materials; payload "
             f"{fig['payload']['geometry_weights_code_bytes'] / 1e6:.2f} MB (geometry, weights, code) + {fig['payload']['envmap_bytes'] / 1e6:.2f} MB env maps.", "",
             "| size | files fetched + programs linked (ms) | first frame (ms) | frame (ms) |", "|---:|---:|---:|---:|"]  # fmt: skip
    for r in fig["load"]:
        lines.append(f"| {r['size']} | {r['load_ms']} | {r['first_frame_ms']} | {r['frame_ms']} |")
    if fig.get("same_pixels"):
        p = fig["same_pixels"]
        lines += ["", f"Same pixels at {p['size']}x{p['size']} (first camera view): {p['psnr_db']} dB against the Python GLSL backend "
                  f"({p['psnr_db_away_from_edges']} dB away from edges)."]  # fmt: skip
    if fig.get("frame_time"):
        f = fig["frame_time"]
        lines += ["", f"Full frames at {f['size']}: page {f['web_frame_ms']} ms, Python GLSL {f['python_glsl_frame_ms']} ms "
                  f"(ratio {f['web_over_python_frame']}); relight {f['web_relight_ms']} / {f['python_glsl_relight_ms']} ms."]  # fmt: skip
    lines += ["", f"Other processes' share of the cores: {fig.get('other_cpu_share_before')} before, {fig.get('other_cpu_share_during')} during.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--cameras", type=Path, default=None)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None)
    args = ap.parse_args(argv)
    reason = missing_browser()
    if reason:
        raise SystemExit(f"web_scene_bench: {reason}")
    before = busy_seconds()
    time.sleep(3.0)
    scene = Scene.load(args.scene)
    m = scene.manifest
    fig: dict = {"provenance": provenance(), "other_cpu_share_before": other_cpu_share(before, 3.0),
                 "scene": {"name": m.name, "segments": len(m.segments), "objects": len(m.geometry.objects or []),
                           "materials": len((m.raw or {}).get("materials") or [])}}  # fmt: skip
    start, t0 = busy_seconds(), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "page"
        report = write_web(scene.path, out)
        files = report["files"]
        envmaps = sum(v for k, v in files.items() if k.startswith("envmaps/"))
        fig["payload"] = {"payload_bytes": report["payload_bytes"], "envmap_bytes": envmaps,
                          "geometry_weights_code_bytes": report["payload_bytes"] - envmaps}  # fmt: skip
        fig["load"] = []
        with serve(out) as url:
            for size in sorted({256, args.size}):
                with chromium() as driver:
                    page = load_page(driver, url + "index.html" + f"?size={size}", timeout=900)
                if page["state"] != "ready":
                    raise SystemExit(f"web_scene_bench: the page failed: {page['error']}")
                fig["load"].append({"size": size, "load_ms": page["load_ms"], "first_frame_ms": page["first_frame_ms"], "frame_ms": page["frame_ms"]})
            with chromium() as driver:
                fig["chromium"] = driver.capabilities.get("browserVersion")
                if args.cameras is not None:
                    view = json.loads(args.cameras.read_text())["views"][0]
                    eye, target, fov = view["eye"], view["target"], float(view.get("fov", 45.0))
                else:
                    eye, target, fov = m.camera.eye, m.camera.target, m.camera.fov
                fig["same_pixels"] = same_pixels(driver, url, scene, 256, eye, target, fov, "potsdamer")
                fig["frame_time"] = frame_times(driver, url, scene, args.size, args.rounds)
    fig["other_cpu_share_during"] = other_cpu_share(start, time.perf_counter() - t0)
    fig["cpu"] = cpu_label(fig["provenance"].get("machine"))
    print(json.dumps({k: v for k, v in fig.items() if k != "provenance"}, indent=1))
    if args.json:
        atomic_write_json(args.json, fig)
    if args.md:
        atomic_write_bytes(args.md, markdown(fig).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
