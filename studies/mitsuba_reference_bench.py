"""Our reference against Mitsuba 3 on built scenes, under a sky 16 SH coefficients represent exactly (issue 38).

usage: python studies/mitsuba_reference_bench.py BUILD [BUILD ...] [--work DIR] [--sky potsdamer] [--window 5]
                                                 [--json docs/benchmarks/mitsuba_reference.json] [--md ...md]
                                                 [--figure-dir docs/benchmarks] [-- PRT-BENCH OPTIONS]

For each build (a ``prt-train`` output folder or its ``scene.json``) a copy whose manifest's
lighting is ``--sky``'s 4-band SH projection, Hanning-windowed (``--window``, Sloan 2008) until its
band-limited radiance is non-negative (the copy is refused otherwise: clamping would make
Mitsuba's light differ from ours), goes under ``--work``; then ``prt-bench --reference mitsuba``
measures all of them (the options after ``--`` are passed on).  Writes the JSON (the prt-bench
report under ``report``, a ``summary`` per scene and size: our reference's PSNR against Mitsuba,
the joint noise, ``mse_ratio``, mean bias and its standard error, the verdicts; each other
configuration's PSNR and bias), a Markdown table and the side-by-side figures (copied next to the
JSON), each with ``provenance``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from prt.bench import cli as bench_cli
from prt.bench.mitsuba_reference import band_limited_envmap
from prt.bench.provenance import cpu_label, provenance
from prt.runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.shading import Lighting

ROOT = Path(__file__).resolve().parents[1]


def sky(name: str, window: float | None):
    """The 4-band SH of a bundled or shared env map, windowed; refused when its radiance goes negative."""
    path = bundled_envmap_path(name) if name in BUNDLED_ENVMAPS else Path(name)
    lighting = Lighting.from_envmap(path, window=("hanning", window) if window else None)
    _, info = band_limited_envmap(lighting.sh, 128)
    if info["clamped"]:
        raise SystemExit(f"{name} (window {window}): its band-limited radiance is negative ({info['min_radiance']}); use a narrower --window")
    return lighting.sh, info


def relit_copy(build: Path, coeffs, work: Path, label: str) -> Path:
    """A copy of ``build``'s scene folder lit by SH ``coeffs`` (no background map)."""
    manifest = json.loads((build / "scene.json").read_text())
    out = work / f"{manifest['name']}-{label}"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for item in ("build.json", "geometry.npz", "segments", "precompute"):
        src = build / item
        if src.is_dir():
            shutil.copytree(src, out / item)
        elif src.is_file():
            shutil.copy2(src, out / item)
    manifest["name"] = f"{manifest['name']}-{label}"
    manifest["lighting"] = {"envmap": None, "sh": [[float(v) for v in row] for row in coeffs]}
    (out / "scene.json").write_text(json.dumps(manifest, indent=1))
    return out / "scene.json"


def summary(report: dict) -> dict:
    """{scene: {size: our reference against Mitsuba, the verdicts, and every configuration's PSNR and bias}}."""
    out = {}
    for scene in report["scenes"]:
        mi = scene.get("mitsuba") or {}
        for resolution, size in mi.get("sizes", {}).items():
            ours = size["rows"][0]
            conv = scene["reference"]["convergence"][resolution]
            out.setdefault(scene["scene"], {})[resolution] = {
                "mitsuba_spp": mi["spp"], "variant": mi["variant"], "views": mi["views"], "pixels": size["pixels"],
                "reference_rays": size["rays"], "reference_hit_rays": size["hit_rays"], "envmap_clamped": mi["envmap"]["clamped"],
                "psnr_db": ours["psnr"], "joint_noise_psnr_db": ours["joint_noise_psnr"], "mitsuba_noise_psnr_db": ours["mitsuba_noise_psnr"],
                "ours_noise_psnr_db": ours["ours_noise_psnr"], "mse_ratio": ours["mse_ratio"], "bias": ours["bias"], "bias_se": ours["bias_se"],
                "within_noise": ours["within_noise"], "bias_within": ours["bias_within"],
                "quiet_reference": {"floor": conv["floor"], "reason": conv.get("reason"), "noise_psnr_db": conv["noise_psnr"],
                                    "best_psnr_db": conv["best_psnr"]},
                "configurations": {r["label"]: {"transfer": r["transfer"], "psnr_db": r["psnr"], "bias": r["bias"], "bias_se": r["bias_se"],
                                                "psnr_vs_ours_db": r["psnr_vs_ours"]} for r in size["rows"][1:]},
            }  # fmt: skip
    return out


def markdown(data: dict) -> str:
    prov = data["provenance"]
    lines = [f"# Our reference against Mitsuba 3 ({prov['date'][:10]})", "",
             f"Command: `{prov['command']}`  ", f"Machine: {cpu_label(prov['machine'])}; commit {prov['commit']}; sky: {data['sky']}.", "",
             "| scene | size | Mitsuba spp (variant) | reference rays (bounce) | PSNR vs Mitsuba | joint noise | squared error / noise | mean bias (se) | verdict |",
             "|---|---|---|---|---:|---:|---:|---:|---|"]  # fmt: skip
    for scene, sizes in data["summary"].items():
        for res, s in sizes.items():
            verdict = ("within the joint noise" if s["within_noise"] else "**not within the joint noise**") + ", " + (
                "mean bias within 0.3 %" if s["bias_within"] else "**mean bias beyond 0.3 %**")  # fmt: skip
            lines.append(f"| {scene} | {res} | {s['mitsuba_spp']} ({s['variant']}) | {s['reference_rays']} ({s['reference_hit_rays']}) "
                         f"| {s['psnr_db']:.2f} | {s['joint_noise_psnr_db']:.2f} | {s['mse_ratio']:.3f} "
                         f"| {100 * s['bias']:+.3f} % ({100 * s['bias_se']:.3f} %) | {verdict} |")  # fmt: skip
    lines += ["", "Every configuration against Mitsuba (diffuse, per-object albedos; PSNR in dB and mean bias over the compared pixels of "
              "the views pooled):", "",
              "| scene | size | configuration | transfer | PSNR vs Mitsuba | mean bias (se) | PSNR vs our reference |", "|---|---|---|---|---:|---:|---:|"]
    for scene, sizes in data["summary"].items():
        for res, s in sizes.items():
            for label, c in s["configurations"].items():
                lines.append(f"| {scene} | {res} | {label} | {c['transfer']} | {c['psnr_db']:.2f} | {100 * c['bias']:+.2f} % "
                             f"({100 * c['bias_se']:.2f} %) | {c['psnr_vs_ours_db']:.2f} |")  # fmt: skip
    if data.get("figures"):
        lines += ["", "Side by side (ours, Mitsuba, 10x their difference):", ""] + [f"- [{Path(f).name}]({Path(f).name})" for f in data["figures"]]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    bench_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("builds", nargs="+", type=Path)
    p.add_argument("--work", type=Path, default=Path("/tmp/mitsuba_reference_bench"))
    p.add_argument("--sky", default="potsdamer")
    p.add_argument("--window", type=float, default=5.0, help="Hanning window width on the sky's bands (0: none)")
    p.add_argument("--json", type=Path, default=ROOT / "docs" / "benchmarks" / "mitsuba_reference.json")
    p.add_argument("--md", type=Path, default=None)
    args = p.parse_args(argv)
    coeffs, info = sky(args.sky, args.window or None)
    label = f"{args.sky}-w{args.window:g}"
    scenes = [relit_copy(b if b.is_dir() else b.parent, coeffs, args.work, label) for b in args.builds]
    images = args.work / "images"
    report_path = args.work / "report.json"
    code = bench_cli.main([*map(str, scenes), "--reference", "mitsuba", "--images", str(images), "--json", str(report_path),
                           "--cache", str(args.work / "cache"), *bench_args])  # fmt: skip
    if code != 0:
        return code
    report = json.loads(report_path.read_text())
    figures = []
    for scene in report["scenes"]:
        for size in (scene.get("mitsuba") or {}).get("sizes", {}).values():
            if size.get("figure"):
                target = args.json.parent / f"mitsuba_reference_{Path(size['figure']).name}"
                shutil.copy2(size["figure"], target)
                figures.append(str(target.relative_to(ROOT)) if target.is_relative_to(ROOT) else str(target))
    data = {"provenance": provenance(), "sky": f"{args.sky}, 4-band SH, Hanning window {args.window:g}: non-negative ({info['min_radiance']})",
            "summary": summary(report), "figures": figures, "report": report}  # fmt: skip
    atomic_write_json(args.json, data)
    atomic_write_bytes(args.md or args.json.with_suffix(".md"), markdown(data).encode())
    print(markdown(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
