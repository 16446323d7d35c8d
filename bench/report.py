"""The benchmark's outputs: JSON report, Markdown table, plot, error-map figures, scene checkpoints.

JSON report (``--json``)
    ``tool``, ``created`` (ISO time), ``settings`` (the arguments), ``failed`` (the scenes
    left out: each ``scene`` and ``error``, the one-line reason; they failed the check made
    before anything is measured, or while being measured), ``machine``: ``cpu``,
    ``cores``, ``gl_renderer``, ``onnxruntime``, ``numpy``, ``gemm_size``, ``gemm_numpy_gflops``
    and ``gemm_onnxruntime_gflops`` (float32 n x n GEMM through numpy's BLAS and through ONNX
    Runtime's MatMul on all cores, medians of 3), ``machine_gflops`` (the higher of the two: the
    machine's limit), ``resumed`` (the scenes taken from checkpoints of an earlier run, each
    with ``scene`` and ``measured``: their records keep that run's ``machine_gflops``; empty
    when every scene was measured in this run), ``load_average`` (1-minute load at the start),
    ``other_cpu_share`` (CPU time other processes used during the run, as a share of all
    cores' time; Linux only, else None): other work makes every timing slower and noisier.

    ``scenes``: one entry per scene: ``scene``, ``path``, ``geometry`` (``type``, ``source``
    used, ``checksum``, ``matches_build_source``: the vertex checksum of ``build.json``'s
    source re-loaded against ``geometry.npz``, or None), ``networks``, ``weight_bytes``,
    ``reference`` (``rays`` asked for, ``seed``, ``cache``, ``noise_psnr``: {size: {material: dB}},
    ``noise_note``, ``rays_max``, ``hit_rays_max``, ``budget_s`` (the limits of the quiet reference,
    :mod:`prt.bench.quiet_reference`), ``rays_by_size`` and ``hit_rays_by_size``: {size: direct rays
    and bounce rays per pixel used (None without bounces), raised where the noise was not 6 dB
    above the pilot's best PSNR}, ``bounce_noise_psnr``: {size: {material: dB}} the two-seed PSNR of
    the indirect part alone (scenes with bounces), ``plan``: {size: the last plan: ``rays``,
    ``hit_rays``, ``met``, ``reason``, ``predicted_noise_psnr``, ``seconds``, ``needs``,
    ``pilot_psnr``, ``noise_psnr``, ``bounce_noise_psnr``}, ``convergence``: {size: ``rays``,
    ``hit_rays``, ``noise_psnr``, ``best_psnr``, ``margin_db`` per material, ``required_db``,
    ``floor``: True when the reference is not 6 dB above the best PSNR measured, so it bounds what
    is measured; then ``reason``: ``caps``, ``budget`` or ``pilot`` (the views' mean PSNR beat view
    0's pilot) and ``needs``: what the cheapest plan that clears it would take}), ``mitsuba``
    (with ``--reference mitsuba``: every configuration against Mitsuba 3, keys in
    :mod:`prt.bench.mitsuba_bench`), ``packing``: one entry per size with ``resolution``, ``all_pixels``,
    ``covered_pixels`` (median), ``network_segments``, ``naive_rows_per_segment``
    ({segment: rows}, each H*W),
    ``naive_total_rows``, ``naive_inference_ms``, ``packed_inference_ms`` (medians over
    the views, or ``--packing-views`` of them spread over the orbit), ``packing_views``, ``packing_speedup`` (naive / packed), ``pixel_ratio`` (all / covered pixels),
    ``work_ratio`` (naive rows / covered pixels), ``naive_max_abs_diff`` (naive vs packed
    transfer on covered pixels), ``network_profile`` (ONNX Runtime's profiler on one slice of
    the largest network segment of the first view, one thread: ``segment``, ``rows``,
    ``run_us``, ``op_us`` per op type, ``gemm_share``: the share of the run in the MLP's
    Gemms; the rest is the encoding and element-wise ops); ``vertex_baseline`` (``vertices``, ``back_vertices``,
    ``weight_bytes``, ``rays`` (per vertex: ``--baseline-rays``, default ``--ref-rays``), ``coverage_agreement``, and for a scene built with ``--bounces N``
    ``bounces``: the interreflected vertex transfer's ``bounces``, ``rays``, ``estimator``,
    ``weight_bytes``, ``seconds``; or ``note`` when skipped), ``texture_baseline``
    (``bounces`` its textures carry, the scene's N or 0; ``sizes``: per ``--texture-size``, the bake's texel counts, ``bytes``, ``precompute_s``,
    ``timings_s``, UV source and note, float16-vs-float32 error, ``cached``; or ``note``), ``error_images``
    (the ``--images`` figures of this scene, one per size: view 0's reference and each
    configuration's error map; empty without ``--images``), ``measured`` (ISO time
    the scene was measured) and ``checkpoint`` (where its measurement is kept: a later run with
    the same scene files and settings takes it from there instead of measuring again, unless
    ``--fresh``; its records then keep the ``machine_gflops`` of the run that measured them),
    ``views_from`` (``orbit``, or the ``--cameras`` file), ``exposure``, ``probe_grid``
    (``--backends probes``: :mod:`prt.bench.probe_bench`), and in ``reference`` ``leak``: {size:
    {material: ``leak``, ``leak_error``}} of the reference's second seed against its first at view 0
    (the leak figure's noise floor).

    ``records``: one per configuration, with ``scene``, ``backend`` (onnx, glsl, vertex, texture;
    texture records add ``texture_size`` and ``precompute_s``, and their ``network_ms`` is the fetch pass),
    ``transfer`` (what the transfer carries: ``direct``, or ``N bounces`` of interreflection, ``1 bounce``
    for one; the scene's for networks, texture and reference; a scene with bounces has vertex records of
    both: direct-only and with the same N bounces, :mod:`prt.bench.vertex_prt`),
    ``precision`` (fp32, fp16, fp16-mlp, int8), ``interpolate`` (the ONNX rows' screen-space interpolation tolerance,
    ``--interpolate``; None: every pixel ran its network), ``network_fraction`` (median share of the covered
    pixels that ran a network), ``material``, ``resolution`` (``"WxH"``),
    ``width``, ``height``, ``views``, ``fps`` (1000 / median frame ms), ``frame_ms``,
    ``stages_ms`` (median per stage), ``network_ms`` (inference / network stage; 0 for
    vertex), ``mae``, ``psnr``, ``ssim``, ``psnr_whole``, ``weight_bytes`` (ONNX initialiser
    bytes of the models run; the fp32 models' for glsl; 16 float32 per vertex for vertex, 64 with bounces; the
    float16 texture plus its per-corner UVs for texture),
    ``flops_per_fragment`` (manifest FLOPs, weighted by the covered pixels of each segment;
    the manifest counts a multiply-add as 2 and each sin, cos or tanh as about 20),
    ``covered_pixels`` (median), ``achieved_gflops`` (FLOPs of the covered pixels that ran a
    network / network seconds, median over views; with ``interpolate``, the covered pixels' FLOPs x
    the network fraction), ``machine_gflops``, ``machine_percent``,
    ``transfer_max_abs_diff`` (transfer against the fp32 ONNX path at view 0, covered pixels),
    ``ref_rays``, ``ref_noise_psnr``, ``label`` (vertex and texture records name a transfer other than
    direct: ``vertex 2 bounces diffuse``), ``pareto`` (on the FPS-PSNR Pareto front of
    its scene, resolution and material), ``leak`` and ``leak_error`` (light leaking,
    :mod:`prt.bench.leak`: the share of the reference's dark pixels the configuration lights, and the
    mean excess light there in units of the frame's key; means over the views with dark pixels,
    None when none has).  Probe-grid records (backend ``probes``, ``--backends probes``, diffuse
    only) add ``probe_grid`` (``density``: ``equal-bytes`` or ``engine``, ``dims``, ``probes``,
    ``spacing``, ``invalid``, ``rays``, ``weight_bytes``, ``seconds``; :mod:`prt.bench.probe_bench`);
    their ``network_ms`` is the probe lookup.  Every PSNR, SSIM and MAE is of images tone-mapped at
    the scene entry's ``exposure`` (``--exposure``: a number, or ``auto``, the reference frame's own
    auto exposure per view and material, :mod:`prt.bench.exposure`).

    ``pareto``: {``"scene WxH material"``: [labels on the front, by increasing FPS]}: only
    configurations with the same reference image compete.

Markdown (``--md``): the records as a table (with a ``transfer`` column), then the reference's
noise against the best PSNR (and, where it is the floor, why), the comparison with Mitsuba 3
(``--reference mitsuba``: a table per size), packing and machine lines.
Plot (``--plot``): FPS (log) against PSNR, one panel per scene and resolution, one labelled
point per configuration, the Pareto front of each material ringed and connected.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections import defaultdict
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np

from prt.bench.bounce_reference import HIT_RAYS, HIT_TRANSFER_RAYS
from prt.bench.metrics import image_metrics, pareto_front
from prt.runtime.files import atomic_write_bytes
from prt.runtime.manifest import load_manifest

__all__ = [
    "REPORT_KEYS", "MACHINE_KEYS", "SCENE_KEYS", "PACKING_KEYS", "RECORD_KEYS", "RECORD_FORMAT", "ERROR_MAP_MAX",
    "markdown", "plot", "error_figure", "scene_checkpoint", "save_figure", "transfer_label",
]  # fmt: skip

# Raised when records change (2: ``transfer``, the vertex baseline with bounces; 3: the quiet reference's
# bounce rays and plan, ``mitsuba``; 4: ``leak``, ``leak_error``): older checkpoints are measured again.
RECORD_FORMAT = 4
# The report's keys (documented in the module docstring; the tests hold the output to them).
REPORT_KEYS = ("tool", "created", "settings", "machine", "scenes", "records", "pareto", "failed")
MACHINE_KEYS = ("cpu", "cores", "gl_renderer", "onnxruntime", "numpy", "gemm_size", "gemm_numpy_gflops",
                "gemm_onnxruntime_gflops", "machine_gflops", "resumed", "load_average", "other_cpu_share")
SCENE_KEYS = ("scene", "path", "geometry", "networks", "weight_bytes", "reference", "packing", "vertex_baseline",
              "error_images", "measured", "checkpoint", "views_from", "exposure")  # fmt: skip
PACKING_KEYS = (
    "resolution", "all_pixels", "covered_pixels", "network_segments", "naive_rows_per_segment", "naive_total_rows",
    "naive_inference_ms", "packed_inference_ms", "packing_speedup", "pixel_ratio", "work_ratio", "naive_max_abs_diff",
    "packing_views", "network_profile",
)  # fmt: skip
RECORD_KEYS = (
    "scene", "backend", "transfer", "precision", "material", "resolution", "width", "height", "views", "fps", "frame_ms",
    "stages_ms", "network_ms", "mae", "psnr", "ssim", "psnr_whole", "weight_bytes", "flops_per_fragment",
    "covered_pixels", "achieved_gflops", "machine_gflops", "machine_percent", "transfer_max_abs_diff", "ref_rays",
    "ref_noise_psnr", "label", "pareto", "leak", "leak_error",
)  # fmt: skip


def _pyplot():
    """matplotlib's pyplot on the Agg backend.

    matplotlib is imported here, on first use, not at module top: only ``--plot`` and
    ``--images`` draw, it is slow to import, and choosing its backend at import time would
    change it for everything else in a process that merely imports :mod:`prt.bench`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _backend_cell(record: dict) -> str:
    """The backend column: the texture baseline names its texture size, the equal-bytes vertex baseline its vertices."""
    if record.get("equal_bytes"):
        return f"vertex at equal bytes ({record['equal_bytes']['vertices']:,} vertices)"
    if "probe_grid" in record:
        g = record["probe_grid"]
        return f"probes {g['density']} ({'x'.join(map(str, g['dims']))})"
    if "texture_size" in record:
        return f"texture {record['texture_size']}^2"
    if record.get("interpolate"):  # screen-space interpolation: its tolerance and the share of pixels that ran a network
        return f"{record['backend']} interpolate {record['interpolate']:g} ({100 * record.get('network_fraction', 1.0):.0f} % inferred)"
    return record["backend"]


def transfer_label(bounces: int) -> str:
    """What a record's transfer carries (its ``transfer``): ``"direct"``, ``"1 bounce"`` or ``"N bounces"``."""
    bounces = int(bounces)
    return "direct" if bounces <= 0 else f"{bounces} bounce{'s' if bounces > 1 else ''}"


def _texture_lines(scene: dict) -> list[str]:
    """The texture baseline's bake per size: texels, bytes, precompute time, UVs, float16 error."""
    tb = scene.get("texture_baseline") or {}
    if "note" in tb:
        return [f"- texture baseline: {tb['note']}"]
    return [
        f"- texture baseline {size}x{size} ({transfer_label(tb.get('bounces', 0))}): {t['atlases']} atlas(es), {t['texels_covered']:,} texels covered "
        f"({t['texel_utilisation']:.0%}), {t['rays']} rays, {t['bytes']:,} bytes (float16 + corner UVs), precompute "
        f"{t['precompute_s']:.1f} s (atlas {t['timings_s']['atlas_s']:.1f} s){' (cached)' if t['cached'] else ''}; "
        f"float16 vs float32: max |error| {t['float16_max_abs_error']:.2g}, RMS {t['float16_rms_error_relative']:.2g} of the RMS transfer; "
        f"UVs: {t['uv_note']}"
        for size, t in tb.get("sizes", {}).items()
    ]


_FLOOR_REASONS = {
    "caps": "the ray limits (--ref-rays-max, --ref-hit-rays-max) stopped it",
    "budget": "the time budget (--ref-budget) stopped it",
    "pilot": "the views' mean PSNR beat view 0's pilot, which the rays were chosen for",
}


def _floor_reason(convergence: dict) -> str:
    """Why the reference could not be made quieter (bench/quiet_reference.py), and what it would need."""
    reason = convergence.get("reason")
    if not reason:
        return ""
    needs = convergence.get("needs") or {}
    more = (f"; it would need {needs['rays']} rays x {needs['hit_rays']} bounce rays"
            + (f", about {needs['seconds']:.0f} s" if needs.get("seconds") is not None else "")) if needs else ""  # fmt: skip
    return f" ({_FLOOR_REASONS.get(reason, reason)}{more})"


def _mitsuba_lines(scene: dict) -> list[str]:
    """The scene's comparison with Mitsuba 3 (``prt-bench --reference mitsuba``), one table per size."""
    mi = scene.get("mitsuba")
    if not mi:
        return []
    env = mi["envmap"]
    shares = ", ".join(f"{100 * c:.2f}" for c in env["clamp_share"]) if env["clamped"] else ""
    clamp = ("non-negative, nothing clamped" if not env["clamped"] else
             f"negative in places ({shares} % of the energy, R, G, B): that part rendered apart and subtracted" if env.get("negative_part") else
             f"clamping its negative radiance removed {shares} % of the energy (R, G, B)")  # fmt: skip
    lines = [f"- **against Mitsuba 3** {mi['mitsuba']} ({mi['variant']}, {mi['spp']} paths per pixel, max_depth {mi['max_depth']}, "
             f"views {mi['views']}); the band-limited sky is {clamp}; diffuse, per-object albedos; PSNR and bias over the "
             f"compared pixels of those views pooled (the hardest view weighs most, unlike the mean of per-view PSNRs above):"]  # fmt: skip
    for res, size in mi["sizes"].items():
        lines += ["", f"| {scene['scene']} {res} | transfer | PSNR vs Mitsuba | mean bias (se) | PSNR vs our reference |", "|---|---|---:|---:|---:|"]
        for r in size["rows"]:
            vs_ours = "-" if r.get("psnr_vs_ours") is None else f"{r['psnr_vs_ours']:.2f}"
            lines.append(f"| {r['label']} | {r['transfer']} | {r['psnr']:.2f} | {100 * r['bias']:+.2f} % ({100 * r['bias_se']:.2f} %) | {vs_ours} |")
        ours = size["rows"][0]
        lines += ["", f"  {size['pixels']:,} pixels compared; Mitsuba's noise {size['mitsuba_noise_psnr']:.1f} dB, ours "
                  f"{ours['ours_noise_psnr']:.1f} dB (two-seed PSNRs): together {ours['joint_noise_psnr']:.1f} dB expected, "
                  f"{ours['psnr']:.1f} dB measured (squared error {ours['mse_ratio']:.2f}x the noise's: "
                  f"{'within' if ours['within_noise'] else '**not within**'} the joint noise); mean bias "
                  f"{100 * ours['bias']:+.2f} % ({'within' if ours['bias_within'] else '**beyond**'} 0.3 %)."]  # fmt: skip
        if size.get("figure"):
            lines.append(f"  Side by side: {size['figure']}")
    return lines


def _probe_lines(scene: dict) -> list[str]:
    """The probe-grid baseline's grids and leak mitigation (``--backends probes``)."""
    pg = scene.get("probe_grid")
    if not pg:
        return []
    if "note" in pg:
        return [f"- probe grid: {pg['note']}"]
    grids = "; ".join(f"{d}: {'x'.join(map(str, g['dims']))} = {g['probes']:,} probes ({g['invalid']} invalid), spacing "
                      f"{g['spacing']:.4g} scene units, {g['weight_bytes']:,} bytes" for d, g in pg["grids"].items())  # fmt: skip
    engine = f"engine density {pg['engine_spacing_m']:g} m in the source's units" + (" (clamped to the probe limits)" if pg["engine_clamped"] else "")
    return [f"- probe grid (L2 SH irradiance, 27 float32 per probe, trilinear): {grids}; {engine}; leak mitigation: {pg['mitigation']}; "
            f"{pg['radiance']}"]


def _leak_lines(scene: dict, records: list) -> list[str]:
    """Light leaking per configuration (:mod:`prt.bench.leak`), with the reference's second seed as its floor."""
    rows = [r for r in records if r.get("leak") is not None]
    floor = scene["reference"].get("leak") or {}
    if not rows and not floor:
        return []
    lines = ["- light leaking (share of the reference's dark pixels, under 1/8 of the frame's key, lit above 1/2 of it; "
             "mean excess there in key units):"]
    for res, per in floor.items():
        cells = ", ".join(f"{m} {100 * f['leak']:.2f} % / {f['leak_error']:.4f}" for m, f in per.items() if f["leak"] is not None)
        lines.append(f"  - reference, second seed at view 0, {res}: {cells or 'no dark pixels'}")
    for r in rows:
        lines.append(f"  - {r['resolution']} {r['label']}: {100 * r['leak']:.2f} % / {r['leak_error']:.4f}")
    return lines


def markdown(report: dict) -> str:
    """The report as Markdown: the configurations' table, then packing, reference and machine lines."""
    machine = report["machine"]
    lines = [
        "| scene | size | backend | transfer | precision | material | FPS | frame ms | network ms | PSNR (covered) "
        "| PSNR (whole) | SSIM | MAE | weights (bytes) | network GFLOP/s (% of GEMM) | Pareto |",
        "|---|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|:-:|",
    ]
    settings_views = report["settings"]["views"]
    for r in report["records"]:
        gflops = f"{r['achieved_gflops']:.1f} ({r['machine_percent']:.1f} %)" if r["achieved_gflops"] else "-"
        fps = f"{r['fps']:.1f}" + (f" ({r['views']} views)" if r["views"] != settings_views else "")
        lines.append(
            f"| {r['scene']} | {r['resolution']} | {_backend_cell(r)} | {r.get('transfer', '?')} | {r['precision']} | {r['material']} | {fps} "
            f"| {r['frame_ms']:.1f} | {r['network_ms']:.1f} | {r['psnr']:.2f} | {r['psnr_whole']:.2f} | {r['ssim']:.4f} "
            f"| {r['mae']:.4f} | {r['weight_bytes']:,} | {gflops} | {'*' if r.get('pareto') else ''} |"
        )
    lines.append("")
    for s in report["scenes"]:
        ref = s["reference"]
        used = sorted(set((ref.get("rays_by_size") or {}).values()) | ({ref["rays"]} if not ref.get("rays_by_size") else set()))
        rays = " / ".join(f"{r}" for r in used) + (f" (asked {ref['rays']}; raised for the noise margin)" if used != [ref["rays"]] else "")
        lines.append(f"**{s['scene']}**: reference {rays} rays per pixel; its noise (two seeds, view 0): "
                     + "; ".join(f"{res}: " + ", ".join(f"{m} {db:.1f} dB" for m, db in d.items()) for res, d in ref["noise_psnr"].items()))  # fmt: skip
        for res, c in ref.get("convergence", {}).items():
            gaps = ", ".join(f"{m} {c['noise_psnr'][m]:.1f} vs {c['best_psnr'][m]:.1f} dB ({c['margin_db'][m]:+.1f})" for m in c["margin_db"])
            rays = f"{c['rays']} rays" + (f" x {c['hit_rays']} bounce rays" if c.get("hit_rays") else "")
            verdict = (f"under {c['required_db']:g} dB apart at {rays}: **the reference is the floor** of these PSNRs"
                       f"{_floor_reason(c)}" if c["floor"] else f">= {c['required_db']:g} dB apart at {rays}: quiet enough")  # fmt: skip
            lines.append(f"- reference noise vs best PSNR {res}: {gaps}; {verdict}")
        lines += _mitsuba_lines(s)
        for p in s["packing"]:
            lines.append(
                f"- packing {p['resolution']} ({p.get('packing_views', '?')} views): naive {p['naive_inference_ms']:.1f} ms ({p['network_segments']} networks x "
                f"{p['all_pixels']:,} pixels) vs packed {p['packed_inference_ms']:.1f} ms ({p['covered_pixels']:,.0f} covered): "
                f"speed-up {p['packing_speedup']}x; all / covered pixels {p['pixel_ratio']}x, naive rows / covered {p['work_ratio']}x"
            )
            prof = p.get("network_profile")
            if prof:
                top = ", ".join(f"{op} {us / prof['run_us']:.0%}" for op, us in list(prof["op_us"].items())[:6])
                lines.append(f"- network profile (segment {prof['segment']}, {prof['rows']:,} rows, one thread): {prof['run_us']:.0f} us per call, "
                             f"{prof['gemm_share']:.0%} in the MLP's Gemms; {top}")  # fmt: skip
        lines += _texture_lines(s)
        vb = s["vertex_baseline"]
        if "note" in vb:
            lines.append(f"- vertex baseline: {vb['note']}")
        elif vb:
            lines.append(f"- vertex baseline: {vb['vertices']:,} vertices (+{vb['back_vertices']:,} back sides) x 16 float32 = "
                         f"{vb['weight_bytes']:,} bytes vs {s['weight_bytes']:,} bytes of network weights (fp32 ONNX initialisers); "
                         f"{vb.get('rays', '?')} rays per vertex")  # fmt: skip
            if "bounces" in vb:
                b = vb["bounces"]
                lines.append(f"- vertex baseline with {transfer_label(b['bounces'])}: x 64 float32 (direct + indirect RGB) = {b['weight_bytes']:,} "
                             f"bytes; {b['rays']} bounce rays per vertex sample; estimator: {b['estimator']}")  # fmt: skip
        lines += _probe_lines(s) + _leak_lines(s, [r for r in report["records"] if r["scene"] == s["scene"]])
    gemm = f"numpy {machine['gemm_numpy_gflops']:.1f}, onnxruntime {machine['gemm_onnxruntime_gflops']:.1f}" if "gemm_numpy_gflops" in machine else "numpy"
    if machine.get("resumed"):
        times = sorted(r["measured"] for r in machine["resumed"])
        lines.append(f"\n{len(times)} of {len(report['scenes'])} scenes taken from checkpoints of an earlier run "
                     f"(measured {times[0]} to {times[-1]}); their records keep that run's GEMM limit.")  # fmt: skip
    lines.append(f"\nMachine: {machine['cpu']}, {machine['cores']} cores, {machine['gl_renderer']}; float32 GEMM "
                 f"({machine['gemm_size']}^3; {gemm}): limit {machine['machine_gflops']:.1f} GFLOP/s.")  # fmt: skip
    settings = report["settings"]
    lines.append(f"Settings: {settings['views']} views, warm-up {settings['warmup']} frames, numpy BLAS threads while "
                 f"rendering: {settings['blas_threads'] or 'as found'}.")  # fmt: skip
    if machine.get("other_cpu_share") is not None:
        lines.append(f"Load: {machine['load_average']:.2f} at the start; other processes used "
                     f"{100 * machine['other_cpu_share']:.0f} % of the cores' time during the run.")  # fmt: skip
    for failure in report.get("failed", []):
        lines.append(f"\n**Not measured**: {failure['scene']}: {' '.join(failure['error'].split())}")
    return "\n".join(lines) + "\n"


def plot(report: dict, path: Path) -> None:
    """FPS (log) against PSNR, one panel per scene and resolution, Pareto fronts connected."""
    plt = _pyplot()
    from matplotlib.ticker import FormatStrFormatter, NullFormatter  # lazy, as _pyplot says

    groups = defaultdict(list)
    for r in report["records"]:
        groups[f"{r['scene']} {r['resolution']}"].append(r)
    cols = min(3, len(groups))  # a grid, so a many-scene report stays readable
    rows = -(-len(groups) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(8.5 * cols, 6.0 * rows), squeeze=False)
    for ax in axes.flat[len(groups):]:
        ax.set_visible(False)
    colours = {"onnx": "tab:blue", "glsl": "tab:orange", "vertex": "tab:green", "texture": "tab:red"}
    markers = {"diffuse": "o", "glossy": "s"}
    for ax, (name, group) in zip(axes.flat, groups.items()):
        for r in group:
            ax.scatter(r["fps"], r["psnr"], c=colours.get(r["backend"], "grey"), marker=markers[r["material"]], s=36, zorder=3)
        for material, style in (("diffuse", "-"), ("glossy", "--")):
            same = [r for r in group if r["material"] == material]
            front = [same[i] for i in pareto_front([(r["fps"], r["psnr"]) for r in same])]
            ax.plot([r["fps"] for r in front], [r["psnr"] for r in front], style, color="crimson", lw=1.2, zorder=2)
            ax.scatter([r["fps"] for r in front], [r["psnr"] for r in front], s=150, facecolors="none", edgecolors="crimson", zorder=4)
        ax.set_xscale("log")
        ax.margins(x=0.25, y=0.2)  # room for the labels
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        fps = [r["fps"] for r in group if r["fps"] > 0]
        if fps and max(fps) / min(fps) < 20:  # minor labels only where they fit (one or two decades)
            ax.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
            ax.tick_params(axis="x", which="minor", labelsize=7)
        else:
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("FPS (log scale)")
        ax.set_ylabel("PSNR over covered pixels (dB)")
        ax.set_title(f"{name}: speed against error")
        ax.grid(True, which="both", alpha=0.3)
        handles = [plt.Line2D([], [], color=c, marker="o", ls="", label=b) for b, c in colours.items()]
        handles += [plt.Line2D([], [], color="k", marker=m, ls="", label=k) for k, m in markers.items()]
        handles.append(plt.Line2D([], [], color="crimson", marker="o", mfc="none", label="Pareto front, diffuse"))
        handles.append(plt.Line2D([], [], color="crimson", ls="--", marker="o", mfc="none", label="Pareto front, glossy"))
        ax.legend(handles=handles, fontsize=8, loc="best")
    fig.tight_layout()  # before the labels: they are placed in final display coordinates
    fig.canvas.draw()
    for ax, group in zip(axes.flat, groups.values()):
        _place_labels(fig, ax, [(r["fps"], r["psnr"], r["label"]) for r in group])
    save_figure(fig, path, dpi=120)


def _place_labels(fig, ax, points) -> None:
    """Label each point at the nearby offset where its text covers the least of other labels and markers.

    Labels pushed beyond the first ring of offsets get a thin leader line to their point.
    """
    from matplotlib.transforms import Bbox  # lazy, as _pyplot says

    near = [(6, 4), (6, -11), (-6, 4), (-6, -11)]
    far = [(dx, dy) for dy in (16, -23, 28, -35, 40, -47) for dx in (10, -10)]
    renderer = fig.canvas.get_renderer()
    inside = ax.get_window_extent(renderer)
    placed = []
    for x, y, _ in points:  # markers count as occupied space
        px, py = ax.transData.transform((x, y))
        placed.append(Bbox([[px - 6, py - 6], [px + 6, py + 6]]))

    def cost(box) -> float:
        covered = sum(b.width * b.height for b in (Bbox.intersection(box, other) for other in placed) if b is not None)
        clipped = box.width * box.height - (lambda b: b.width * b.height if b is not None else 0.0)(Bbox.intersection(box, inside))
        return covered + 10.0 * clipped  # text outside the axes is worse than touching a neighbour

    for x, y, text in sorted(points, key=lambda p: (-p[1], p[0])):
        best = None
        for k, (dx, dy) in enumerate(near + far):
            leader = dict(arrowstyle="-", lw=0.5, color="grey", shrinkA=0, shrinkB=4) if k >= len(near) else None
            label = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=7,
                                ha="left" if dx > 0 else "right", arrowprops=leader)  # fmt: skip
            box = label.get_window_extent(renderer).expanded(1.02, 1.15)
            score = cost(box)
            if best is None or score < best[0]:
                if best is not None:
                    best[1].remove()
                best = (score, label, box)
            else:
                label.remove()
            if score == 0.0:
                break
        placed.append(best[2])


ERROR_MAP_MAX = 0.05  # |error| (tone-mapped, channel mean) at the top of the error maps' colour scale


def error_figure(view, images: dict, path: Path, title: str) -> None:
    """View 0's reference and each configuration's error map, one row per material (PNG).

    ``images``: material -> [(label, tone-mapped image)].  Every error map shares one colour
    scale (0 to :data:`ERROR_MAP_MAX`), so panels compare at a glance; each title gives the
    view's PSNR over covered pixels.
    """
    plt = _pyplot()
    covered = view.gbuffer.covered
    rows = [m for m in images if images[m]]
    cols = 1 + max((len(images[m]) for m in rows), default=0)
    panel = max(2.6, covered.shape[1] / 70)  # inches: about one image pixel per figure pixel or more, at 100 dpi
    fig, axes = plt.subplots(len(rows), cols, figsize=(panel * cols + 0.8, (panel + 0.3) * len(rows) + 0.3), squeeze=False,
                             layout="constrained")
    shown = None
    for i, material in enumerate(rows):
        reference = view.references[material]
        axes[i, 0].imshow(np.clip(reference, 0, 1))
        axes[i, 0].set_title(f"reference ({material})", fontsize=9)
        for j, (label, image) in enumerate(images[material], start=1):
            error = np.abs(image - reference).mean(axis=2)
            error[~covered] = np.nan
            shown = axes[i, j].imshow(error, cmap="magma", vmin=0.0, vmax=ERROR_MAP_MAX)
            axes[i, j].set_facecolor("#d0d0d0")
            psnr = image_metrics(image, reference, covered)["psnr"]
            axes[i, j].set_title(f"{label.replace(f' {material}', '')}: {psnr:.1f} dB", fontsize=9)
        for ax in axes[i]:
            ax.set_xticks([])
            ax.set_yticks([])
        for ax in axes[i, len(images[material]) + 1:]:
            ax.set_visible(False)
    fig.suptitle(f"{title}: |error| of tone-mapped images (grey: not covered)", fontsize=10)
    if shown is not None:
        fig.colorbar(shown, ax=axes, shrink=0.8, label="|error|")
    save_figure(fig, path, dpi=100)


# Settings that change what a scene's measurement is (the cache only says where things live).
_CHECKPOINT_SETTINGS = ("views", "sizes", "ref_rays", "ref_rays_max", "warmup", "config_budget", "packing_views", "precisions",
                        "backends", "gemm_size", "seed", "blas_threads")  # fmt: skip


def scene_checkpoint(scene_path, settings) -> Path:
    """Where one scene's finished measurement is kept, keyed by its files and the settings.

    The key covers ``scene.json`` and every file it names (models, generated GLSL, weight
    textures, geometry, environment map) plus ``geometry.npz``, so a rebuilt scene or other
    settings never reuse an old measurement.
    """
    manifest = load_manifest(scene_path)
    digest = hashlib.sha256()
    files = [manifest.path, manifest.geometry.path, manifest.lighting.envmap, manifest.root / "geometry.npz"]
    for segment in manifest.segments:
        files += [segment.model, segment.glsl, segment.glsl_weights]
    for f in dict.fromkeys(Path(f) for f in files if f is not None and Path(f).is_file()):
        digest.update(f.name.encode())
        digest.update(f.read_bytes())
    options = {k: getattr(settings, k) for k in _CHECKPOINT_SETTINGS}
    if settings.images is not None:  # (only then, so keys made before --images existed still match)
        options["images"] = str(settings.images)
    if "texture" in settings.backends:  # (likewise)
        options["texture_sizes"] = list(settings.texture_sizes)
    if getattr(settings, "interpolate", ()):  # (likewise)
        options["interpolate"] = list(settings.interpolate)
    for key, default in (("ref_hit_rays", HIT_RAYS), ("ref_hit_transfer_rays", HIT_TRANSFER_RAYS), ("ref_hit_rays_max", 1024),
                         ("ref_budget", 3600.0)):  # (likewise)
        if getattr(settings, key, default) != default:
            options[key] = getattr(settings, key)
    if getattr(settings, "baseline_rays", None) is not None:  # (likewise)
        options["baseline_rays"] = settings.baseline_rays
    if getattr(settings, "gl_device", None) is not None:  # (likewise)
        options["gl_device"] = settings.gl_device
    if getattr(settings, "cameras", None):  # (likewise)
        options["cameras"] = [list(c) for c in settings.cameras]
    if getattr(settings, "exposure", 1.0) != 1.0:  # (likewise)
        options["exposure"] = settings.exposure
    if getattr(settings, "reference", "ours") != "ours":  # (likewise)
        options.update(reference=settings.reference, mitsuba_spp=settings.mitsuba_spp, mitsuba_views=settings.mitsuba_views,
                       mitsuba_variant=settings.mitsuba_variant, mitsuba_light="signed")  # fmt: skip  # signed: its negative part subtracted
    options["prt"] = _prt_version()  # a new release measures again
    options["records"] = RECORD_FORMAT  # so does a new record format
    digest.update(json.dumps(options, sort_keys=True, default=list).encode())
    return settings.cache / "results" / f"{manifest.name}-{digest.hexdigest()[:16]}.json"


def _prt_version() -> str:
    try:
        return version("prt-runtime")
    except PackageNotFoundError:
        return "unknown"


def save_figure(fig, path, dpi: int) -> None:
    """PNG through a temporary file and a rename (an interrupted run leaves no half image)."""
    plt = _pyplot()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
