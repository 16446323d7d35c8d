"""Real scenes built with the defaults and judged from their own cameras (issue 43's targets).

usage: python studies/scenes_real.py SCENE.glb[:CAMERAS.json] [...] --json OUT.json [--md OUT.md] [--work DIR]
           [--quality standard] [--size 192] [--ref-rays 512] [--mitsuba SCENE_NAME ...] [--extra FLAG ...]

For every scene file: ``prt-train SCENE -o WORK/NAME`` (``--quality``, nothing else; timed under
``nice`` with the load recorded, as ``studies/builds_vs_vertex.py`` times builds), the build's
own held-out figures (``build.json``'s ``sizing``: absolute PSNR, margin over vertex PRT) and any
"no material" line it printed; then ``prt-bench`` from the scene's cameras (``CAMERAS.json``,
default ``SCENE.cameras.json`` beside the file: ``{"views": [{"eye", "target", "fov"}]}`` in the
normalised space), the views split into those whose eye lies outside the scene's bounds and those
inside, each group at ``--exposure auto`` (scored at the exposure the reference frame gets):
the networks, per-vertex PRT with the same bounces, the L2 SH probe grid at equal bytes and at an
engine density, with the light-leak figure.  ``--mitsuba NAME ...`` adds Mitsuba 3 as the reference
for those scenes' outside views (:mod:`prt.bench.mitsuba_bench`; 2 views, ``--mitsuba-spp`` paths per pixel).

Scene files are not part of the repository (their licences, AGPL and GPL among them, are not the
package's): ``/work/scenes/SOURCES.md`` on the machine that made the record lists their origin,
and the record names each file with its sha1.  Resumable: a finished build or bench is read back.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from prt.bench.machine import cpu_name
from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_bytes, atomic_write_json

sys.path.insert(0, str(Path(__file__).resolve().parent))
from builds_vs_vertex import timed_build  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# Issue 43's bars: outside / inside views against the reference, over vertex PRT, over the probe grid at equal bytes.
BARS = {"outside_db": 35.0, "inside_db": 30.0, "over_vertex_db": 3.0, "over_probes_db": 6.0}


def split_views(cameras: Path, build: Path) -> dict[str, list]:
    """The cameras' views, as outside / inside the scene's bounds (normalised, from geometry.npz)."""
    views = json.loads(cameras.read_text())["views"]
    with np.load(build / "geometry.npz") as g:
        low, high = g["vertices"].min(axis=0), g["vertices"].max(axis=0)
    groups: dict[str, list] = {"outside": [], "inside": []}
    for view in views:
        eye = np.asarray(view["eye"], float)
        inside = bool(np.all(eye > low) and np.all(eye < high))
        groups["inside" if inside else "outside"].append({k: view[k] for k in ("eye", "target", "fov") if k in view})
    return {k: v for k, v in groups.items() if v}


def bench_group(build: Path, name: str, views: list, args, mitsuba: bool) -> dict:
    cams = build.parent / f"{build.name}-{name}.cameras.json"
    atomic_write_json(cams, {"views": views})
    report = build.parent / f"{build.name}-{name}.bench.json"
    if report.is_file():
        return json.loads(report.read_text())
    command = [sys.executable, "-m", "prt.bench.cli", str(build / "scene.json"), "--cameras", str(cams), "--exposure", "auto",
               "--size", str(args.size), "--ref-rays", str(args.ref_rays), "--ref-rays-max", str(4 * args.ref_rays),
               "--backends", "onnx", "vertex", "probes", "--precisions", "fp32", "--warmup", "1", "--packing-views", "1",
               "--gemm-size", "512", "--cache", str(build.parent / "bench_cache"), "--images", str(build.parent / f"{build.name}-{name}-images"),
               "--md", str(report.with_suffix(".md")), "--json", str(report)]  # fmt: skip
    if mitsuba:
        command += ["--reference", "mitsuba", "--mitsuba-views", str(min(2, len(views))), "--mitsuba-spp", str(args.mitsuba_spp)]
    print("==", " ".join(["prt-bench", *command[3:]]), flush=True)
    subprocess.run(["nice", "-n", "10", *command], check=True, stdout=subprocess.DEVNULL)
    out = json.loads(report.read_text())
    out["command"] = " ".join(["prt-bench", *command[3:]])
    atomic_write_json(report, out)
    return out


def summarise(report: dict, group: str) -> dict:
    """Diffuse covered PSNR (exposure matched) and leak of each configuration of one bench report."""
    recs = [r for r in report["records"] if r["material"] == "diffuse" and r.get("precision", "fp32") == "fp32"]
    out = {"views": report["settings"].get("views"), "configurations": {}}
    for r in recs:
        label = r["backend"] if r["backend"] != "probes" else r["label"].replace(" diffuse", "")
        out["configurations"][label] = {"psnr_db": r["psnr"], "ssim": r.get("ssim"), "bytes": r.get("weight_bytes"),
                                        "leak": r.get("leak"), "leak_error": r.get("leak_error")}  # fmt: skip
    scene = report["scenes"][0]
    out["reference_noise_db"] = next(iter(scene["reference"]["noise_psnr"].values()))["diffuse"]
    if "mitsuba" in scene:  # what it rendered and each configuration's figures against it (not the albedo table)
        out["mitsuba"] = {k: v for k, v in scene["mitsuba"].items() if k != "albedos"}
    return out


def mitsuba_line(name: str, group: str, m: dict) -> str:
    """One line of the record: our reference and the networks against Mitsuba 3."""
    rows = [(size, {r["label"]: r for r in s["rows"]}, s) for size, s in m["sizes"].items()]
    parts = []
    for size, by, s in rows:
        ours, nets = by.get("our reference", {}), by.get("onnx fp32", {})
        parts.append(f"{size}, {s['pixels']:,} pixels: our reference {ours.get('psnr')} dB against Mitsuba (joint noise "
                     f"{ours.get('joint_noise_psnr')} dB, MSE ratio {ours.get('mse_ratio')}: "
                     f"{'within' if ours.get('within_noise') else 'NOT within'} the joint noise; brightness bias "
                     f"{100 * ours.get('bias', 0):+.3f} % +- {100 * ours.get('bias_se', 0):.3f}), the networks {nets.get('psnr')} dB")
    return (f"- {name} {group}: Mitsuba 3 {m.get('mitsuba')} ({m.get('variant')}, {m.get('spp')} paths per pixel, max depth "
            f"{m.get('max_depth')}, views {m.get('views')}, negative light subtracted: {m.get('envmap', {}).get('negative_part')}); "
            + "; ".join(parts))


def verdicts(groups: dict) -> dict:
    result = {}
    for name, g in groups.items():
        conf = g["configurations"]
        net = conf.get("onnx", {}).get("psnr_db")
        vertex = conf.get("vertex", {}).get("psnr_db")
        probes = next((c["psnr_db"] for k, c in conf.items() if k.startswith("probes") and "equal" in k), None)
        bar = BARS["inside_db" if name == "inside" else "outside_db"]
        result[name] = {"psnr_db": net, "bar_db": bar, "met_bar": net is not None and net >= bar,
                        "over_vertex_db": None if vertex is None or net is None else round(net - vertex, 2),
                        "over_probes_equal_bytes_db": None if probes is None or net is None else round(net - probes, 2)}  # fmt: skip
        result[name]["met_over_vertex"] = result[name]["over_vertex_db"] is not None and result[name]["over_vertex_db"] >= BARS["over_vertex_db"]
        result[name]["met_over_probes"] = (result[name]["over_probes_equal_bytes_db"] is not None
                                           and result[name]["over_probes_equal_bytes_db"] >= BARS["over_probes_db"])  # fmt: skip
    return result


def markdown(result: dict) -> str:
    prov = result["provenance"]
    lines = [f"Made by `{prov.get('command')}` ({prov.get('date')}, {result['cpu']}, 2 cores). Scenes: "
             "/work/scenes/SOURCES.md on that machine (not in the repository; each file's sha1 is in the JSON).", "",
             "| scene | triangles / objects | build (min) | load | no-material line | held-out PSNR (margin over vertex PRT) | views | networks dB | vertex PRT dB | probes equal bytes dB | probes engine dB | leak networks / probes eq. / probes eng. | bars met |",
             "|---|---|---:|---:|---|---|---|---:|---:|---:|---:|---|---|"]  # fmt: skip
    for s in result["scenes"]:
        t = s["timing"]
        sizing = t.get("sizing") or {}
        held = sizing.get("absolute_psnr_db", sizing.get("psnr_db"))
        margin = sizing.get("margin_db")
        for group, g in s["groups"].items():
            c = g["configurations"]
            eq = next((v for k, v in c.items() if k.startswith("probes") and "equal" in k), {})
            en = next((v for k, v in c.items() if k.startswith("probes") and "engine" in k), {})
            v = s["verdicts"][group]
            leaks = " / ".join("-" if x.get("leak") is None else f"{100 * x['leak']:.1f} %" for x in (c.get("onnx", {}), eq, en))
            met = ", ".join(k for k in ("met_bar", "met_over_vertex", "met_over_probes") if v[k]) or "none"
            lines.append(f"| {s['name']} | {s['triangles']:,} / {s['objects']} | {t['wall_s'] / 60:.1f} | {t.get('other_cpu_share')} | "
                         f"{'yes' if s['no_material_line'] else 'no'} | {held} ({margin}) | {group} ({g['views']}) | "
                         f"{c.get('onnx', {}).get('psnr_db')} | {c.get('vertex', {}).get('psnr_db')} | {eq.get('psnr_db')} | {en.get('psnr_db')} | "
                         f"{leaks} | {met} |")  # fmt: skip
    judged = [mitsuba_line(s["name"], group, g["mitsuba"]) for s in result["scenes"] for group, g in s["groups"].items() if "mitsuba" in g]
    if judged:
        lines += ["", "Against Mitsuba 3 (diffuse, exposure matched, the pixels where both see the same point):", "", *judged]
    lines += ["", f"Bars (issue 43): outside >= {BARS['outside_db']} dB, inside >= {BARS['inside_db']} dB (exposure matched), "
              f">= vertex PRT + {BARS['over_vertex_db']} dB, >= probe grid at equal bytes + {BARS['over_probes_db']} dB; build <= 20 min; "
              "one scene against Mitsuba 3 within the joint noise.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+")
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--md", type=Path)
    p.add_argument("--work", type=Path, default=Path("scenes_real_work"))
    p.add_argument("--quality", default="standard")
    p.add_argument("--size", type=int, default=192)
    p.add_argument("--ref-rays", type=int, default=512)
    p.add_argument("--mitsuba", nargs="+", default=[], metavar="SCENE_NAME", help="the scenes (file stems) whose outside views Mitsuba 3 also judges")
    p.add_argument("--mitsuba-spp", type=int, default=256)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--extra", nargs="*", default=[])
    args = p.parse_args(argv)
    args.extra = [token for entry in args.extra for token in entry.split()]  # "--extra=--samples 20000 --bounces 1"
    args.work.mkdir(parents=True, exist_ok=True)
    result = {"provenance": provenance(), "cpu": cpu_name(), "bars": BARS, "scenes": []}
    for spec in args.scenes:
        path, _, cams = spec.partition(":")
        path = Path(path)
        if not path.is_file():
            print(f"scenes_real: {path}: not found (scenes live outside the repository), skipped", flush=True)
            continue
        cams = Path(cams) if cams else path.with_suffix(".cameras.json")
        if path.suffix == ".obj" and not cams.is_file():
            cams = path.parent.with_suffix(".cameras.json")
        out = args.work / path.stem
        timing = timed_build(path, args.quality, out, args.threads, args.extra)
        stdout = "\n".join(timing.get("summary", []))
        log = (out / "train.log").read_text() if (out / "train.log").is_file() else stdout
        with np.load(out / "geometry.npz") as g:
            triangles, objects = len(g["faces"]), int(g["object_ids"].max()) + 1
        groups = {}
        for name, views in split_views(cams, out).items():
            report = bench_group(out, name, views, args, mitsuba=path.stem in args.mitsuba and name == "outside")
            groups[name] = summarise(report, name)
            groups[name]["command"] = report.get("command")
        entry = {"name": path.stem, "file": path.name, "sha1": hashlib.sha1(path.read_bytes()).hexdigest(), "triangles": triangles,
                 "objects": objects, "timing": timing, "no_material_line": "no material for" in log, "groups": groups,
                 "verdicts": verdicts(groups), "build_within_20_min": timing["wall_s"] <= 1200}  # fmt: skip
        result["scenes"].append(entry)
        atomic_write_json(args.json, result)
        if args.md:
            atomic_write_bytes(args.md, markdown(result).encode())
    atomic_write_json(args.json, result)
    if args.md:
        atomic_write_bytes(args.md, markdown(result).encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
