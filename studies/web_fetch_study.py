"""Where the web page's frame goes in software WebGL (SwiftShader): the networks' weight fetches.

usage: python studies/web_fetch_study.py [--scene runtime/data/demo] [--size 512] [--rounds 3] [--json docs/benchmarks/web_fetch.json]

The page's first frame at 512 x 512 is one evaluation of the networks (issue 37's target: loaded and
drawn within 3 s).  This study builds the scene's page once, then variants of its transfer shader
(and, where a variant needs it, of the weight texture's upload), and times each in the same headless
Chromium, interleaved in rounds (medians of ``prtWeb.benchmark`` full frames):

- ``page``: the page as ``prt-web`` writes it;
- ``computed weights``: ``prt_weight(i)`` computed from ``i`` instead of fetched (a wrong image: the
  cost of everything but the fetches);
- ``half the fetches``: each 4x4 block built from two fetched texels instead of four (a wrong image:
  what halving the fetches would buy);
- ``constant loop bounds``: the layers' loops bounded by the architecture's literal sizes (the
  compiler may unroll them), same image;
- ``integer texture``: the weights as RGBA32UI read through ``uintBitsToFloat``, same image;
- ``fp16 pairs``: two texels' weights as halves in one RGBA32UI texel (``unpackHalf2x16``), half the
  fetches and fp16 weights: its image against the page's.

Every variant's image is compared with the page's (PSNR over the canvas).  The scene must have one
network architecture (its segments share one network function), as the bundled demo has.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from common import ROOT, write_figures  # beside this script (its folder is sys.path[0])

from prt.bench.browser import chromium, decode_png_data_url, load_page, missing_browser, serve
from prt.bench.provenance import cpu_label, provenance
from prt.export.web import write_web

FETCH = "vec4 prt_weight(int i) { return texelFetch(prt_weights, ivec2(i % PRT_WEIGHTS_WIDTH, i / PRT_WEIGHTS_WIDTH), 0); }"
SAMPLER = "uniform sampler2D prt_weights;"
BLOCK = "z += mat4(prt_weight(k), prt_weight(k + 1), prt_weight(k + 2), prt_weight(k + 3)) * x[i];"
UPLOAD = "this.weights = texture2D(gl, gl.RGBA32F, web.weights.width, web.weights.height, this.weightData);"
UPLOAD_UINT = """this.weights = gl.createTexture(); gl.bindTexture(gl.TEXTURE_2D, this.weights);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32UI, web.weights.width, web.weights.height);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, web.weights.width, web.weights.height, gl.RGBA_INTEGER, gl.UNSIGNED_INT,
                       new Uint32Array(this.weightData.buffer));"""
HALF = """uniform highp usampler2D prt_weights;
uvec4 prt_fetch16(int j) { return texelFetch(prt_weights, ivec2(j % PRT_WEIGHTS_WIDTH, j / PRT_WEIGHTS_WIDTH), 0); }
vec4 prt_lo(uvec4 u) { return vec4(unpackHalf2x16(u.x), unpackHalf2x16(u.y)); }
vec4 prt_hi(uvec4 u) { return vec4(unpackHalf2x16(u.z), unpackHalf2x16(u.w)); }
vec4 prt_weight(int i) { uvec4 u = prt_fetch16(i >> 1); return (i & 1) == 0 ? prt_lo(u) : prt_hi(u); }
mat4 prt_mat4(int k) {
    if ((k & 1) != 0) return mat4(prt_weight(k), prt_weight(k + 1), prt_weight(k + 2), prt_weight(k + 3));
    uvec4 a = prt_fetch16(k >> 1), b = prt_fetch16((k >> 1) + 1);
    return mat4(prt_lo(a), prt_hi(a), prt_lo(b), prt_hi(b));
}"""


def _replace(text: str, old: str, new: str, what: str) -> str:
    if old not in text:
        raise SystemExit(f"web_fetch_study: the generated transfer shader has no {what}; the study follows the compact GLSL of prt.export")
    return text.replace(old, new)


def _sizes(page: Path) -> tuple[int, int, int]:
    """(feature groups, hidden blocks, output blocks) of the scene's one architecture (the weight header)."""
    web = json.loads((page / "web.json").read_text())
    nets = web["uniforms"]["transfer"]["u_segment_net"]
    if len({n for n in nets if n >= 0}) != 1:
        raise SystemExit("web_fetch_study: the scene must have one network architecture (the demo's kind)")
    base = next(b for b, n in zip(web["uniforms"]["transfer"]["u_segment_base"], nets) if n >= 0)
    weights = np.frombuffer((page / web["weights"]["file"]).read_bytes(), dtype="<f4").reshape(-1, 4)
    groups, hidden, outputs = (int(v) for v in weights[base][:3])
    return groups, hidden, outputs


def variant(page: Path, out: Path, name: str) -> None:
    """``out``: a copy of ``page`` with the variant ``name`` applied (web.json's file table follows)."""
    shutil.copytree(page, out)
    shader, script = out / "shaders" / "transfer4.frag", out / "prt-web.js"
    text, js = shader.read_text(), script.read_text()
    if name == "computed weights":
        text = _replace(text, FETCH, "vec4 prt_weight(int i) { float x = float(i) * 1e-5; return vec4(x, -x, 0.5 * x, 0.01); }", "prt_weight")
    elif name == "half the fetches":
        text = _replace(text, BLOCK, "vec4 a = prt_weight(k), b = prt_weight(k + 1); z += mat4(a, b, a.yzwx, b.yzwx) * x[i];", "4x4 block")
    elif name == "constant loop bounds":
        groups, hidden, outputs = _sizes(page)
        for suffix, n_in, n_out in (("first", groups, hidden), ("hidden", hidden, hidden), ("out", hidden, outputs)):
            pattern = re.compile(r"(void \w+_" + suffix + r"\(int w, int n_in, int n_out[^{]*\{.*?\n\})", re.S)
            found = pattern.search(text)
            if found is None:
                raise SystemExit(f"web_fetch_study: no {suffix} layer in the generated transfer shader")
            body = found.group(1).replace("o < n_out", f"o < {n_out}").replace("i < n_in", f"i < {n_in}")
            text = text[: found.start()] + body + text[found.end():]
    elif name == "integer texture":
        text = _replace(text, SAMPLER, "uniform highp usampler2D prt_weights;", "weight sampler")
        text = _replace(text, FETCH, FETCH.replace("return texelFetch(", "return uintBitsToFloat(texelFetch(").replace("0); }", "0)); }"), "prt_weight")
        js = _replace(js, UPLOAD, UPLOAD_UINT, "weight upload")
    elif name == "fp16 pairs":
        text = _replace(text, SAMPLER + "\n\n" + FETCH, HALF, "weight fetch")
        text = _replace(text, BLOCK, "z += prt_mat4(k) * x[i];", "4x4 block")
        js = _replace(js, UPLOAD, UPLOAD_UINT, "weight upload")
        web = json.loads((out / "web.json").read_text())
        texels = np.frombuffer((out / web["weights"]["file"]).read_bytes(), dtype="<f4").reshape(-1, 4)
        if len(texels) % 2:
            texels = np.vstack([texels, np.zeros((1, 4), "<f4")])
        halves = texels.astype("<f2").reshape(-1, 8).view("<u2").astype("<u4")
        packed = halves[:, 0::2] | (halves[:, 1::2] << 16)
        width = web["weights"]["width"]
        height = -(-len(packed) // width)
        table = np.zeros((height * width, 4), "<u4")
        table[: len(packed)] = packed
        (out / web["weights"]["file"]).write_bytes(table.tobytes())
        web["weights"]["height"] = height
        (out / "web.json").write_text(json.dumps(web, separators=(",", ":")))
    elif name != "page":
        raise ValueError(name)
    shader.write_text(text)
    script.write_text(js)
    web = json.loads((out / "web.json").read_text())
    for rel in list(web["files"]):
        web["files"][rel] = (out / rel).stat().st_size
    (out / "web.json").write_text(json.dumps(web, separators=(",", ":")))


VARIANTS = ("page", "computed weights", "half the fetches", "constant loop bounds", "integer texture", "fp16 pairs")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ROOT / "runtime" / "data" / "demo")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=2, help="full frames per variant and round")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    reason = missing_browser()
    if reason:
        raise SystemExit(f"web_fetch_study: {reason}")
    figures: dict = {"provenance": provenance(), "scene": str(args.scene), "size": args.size, "rounds": args.rounds}
    times = {v: [] for v in VARIANTS}
    images, states = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        write_web(args.scene, Path(tmp) / "page-src")
        folders = {}
        for i, name in enumerate(VARIANTS):
            folders[name] = Path(tmp) / f"v{i}"
            variant(Path(tmp) / "page-src", folders[name], name)
        with chromium() as driver:
            figures["chromium"] = driver.capabilities.get("browserVersion")
            for r in range(args.rounds):
                for name in VARIANTS:
                    with serve(folders[name]) as url:
                        page = load_page(driver, url + f"index.html?size={args.size}&capture=1", timeout=600)
                        if page["state"] != "ready":
                            raise SystemExit(f"web_fetch_study: {name}: the page failed: {page['error']}")
                        if r == 0:
                            images[name] = decode_png_data_url(page["capture"]).astype(np.float64)
                            states[name] = page["first_frame_ms"]
                        times[name] += driver.execute_script(f"return window.prtWeb.benchmark({args.frames}, true)")
                    print(f"round {r + 1}/{args.rounds} {name}: {times[name][-1]:.0f} ms", flush=True)
    base = statistics.median(times["page"])
    rows = {}
    for name in VARIANTS:
        mse = float(np.mean((images[name] - images["page"]) ** 2))
        rows[name] = {"frame_ms": round(statistics.median(times[name]), 1), "frames_ms": [round(t, 1) for t in times[name]],
                      "over_page": round(statistics.median(times[name]) / base, 3),
                      "psnr_db_vs_page": None if mse == 0 else round(10 * np.log10(255.0**2 / mse), 2),
                      "first_frame_ms_warm_browser": states[name]}  # fmt: skip
    figures["variants"] = rows
    figures["cpu"] = cpu_label(figures["provenance"].get("machine"))
    print(json.dumps(rows, indent=1))
    write_figures(args.json, figures)
    if args.json is not None:
        lines = ["# Where the web page's frame goes in SwiftShader: weight fetches", "",
                 f"`{figures['provenance']['command']}`, {figures['provenance']['date']}, {figures['cpu']}; Chromium {figures['chromium']} "
                 f"with SwiftShader; {args.scene.name} at {args.size} x {args.size}; full frames (G-buffer, networks, shading), medians of "
                 f"{args.rounds} interleaved rounds of {args.frames}.", "",
                 "| variant | frame ms | / page | image vs page (PSNR dB; - identical) |", "|---|---:|---:|---:|"]  # fmt: skip
        for name, r in rows.items():
            lines.append(f"| {name} | {r['frame_ms']} | {r['over_page']} | {'-' if r['psnr_db_vs_page'] is None else r['psnr_db_vs_page']} |")
        lines += ["", "`computed weights` and `half the fetches` draw wrong images on purpose: they bound what the fetches cost.", ""]
        args.json.with_suffix(".md").write_text("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
