"""The prepared GPU check (issue 36): what our scenes cost on a GPU, in one run of at most 8 minutes.

usage: python studies/gpu_check.py [--json docs/benchmarks/gpu.json] [--md docs/benchmarks/gpu.md]
                                   [--bounce SCENE] [--gl-device NAME|INDEX] [--views 12] [--fit-steps 1000]
                                   [--reduced]

Run on a machine with an NVIDIA GPU by ``scripts/gpu_check.sh`` (which sets up EGL and the carried
wheels there; ``docs/guides/gpu.md`` says how).  Nothing is downloaded.  Measured, per scene (the
bundled demo: k = 64, l = 4, direct; ``--bounce``: a default build with bounces, 64-wide, committed
in ``studies/data/spot_bounces``) and per size (512x512, 1024x1024, 1920x1080):

- **GLSL** (:class:`prt.runtime.renderer.Renderer`, ``draw()``): the frame as a user of the GPU sees it
  (G-buffer, transfer, shading, background, finished with glFinish), its stages, FPS; the relight-only
  frame (the light turned, no network); the read-back of the pixels, apart.
- **ONNX**: with ONNX Runtime's CUDA provider where this onnxruntime has it (the renderer's ``onnx``
  backend, I/O binding); where it has not (the lent H200's image carries the CPU build, and the
  GPU build does not fit the 64 MiB that can travel), the same batched inference (the view's covered
  pixels packed by segment, each segment's rows in one batch) with the GPU engine the machine has:
  torch on CUDA, on the same weights (read from the ONNX files; checked against ONNX Runtime on the
  CPU, in dB), eager and replayed as a CUDA graph, in float32 and float16.  Every figure names its engine.
- **Network stage against the device's limit**: the FLOPs of the covered pixels' networks over the
  stage's time, against the measured float32 matrix-product rate (and float16's).
- **Fitting**: one segment of the bounce build (its architecture, its sample count; samples drawn on its
  surface, the committed network as the target) fitted for ``--fit-steps`` steps on the GPU and on the
  CPU (``prt.train.networks.fit.fit_segment``, ``device`` cuda / cpu).

``--reduced`` runs every part at toy sizes (tests, a machine without a GPU: llvmpipe, torch on the
CPU) to show the script works before a GPU task runs it.  Writing ``docs/benchmarks/gpu.json`` from a
run that had no GPU (GL on a software rasteriser and torch without CUDA) is refused (exit 2); where GL
fell back to a software rasteriser but torch sees the GPU, the GLSL rows are skipped and the record
says so (``skipped``).  No configuration starts after ``--budget`` seconds (400): the record is
written with what was measured.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "docs" / "benchmarks" / "gpu.json"
BOUNCE_SCENE = ROOT / "studies" / "data" / "spot_bounces" / "scene.json"
SIZES = ((512, 512), (1024, 1024), (1920, 1080))
REDUCED_SIZES = ((24, 24), (32, 32), (40, 24))
SOFTWARE = ("llvmpipe", "softpipe", "swrast", "software")


def log(text: str) -> None:
    print(text, flush=True)


# ------------------------------------------------------------------ the machine


def environment(ctx) -> dict:
    """What ran: GL renderer, EGL devices, torch and CUDA, ONNX Runtime's providers, nvidia-smi."""
    import onnxruntime as ort
    import torch

    from prt.runtime.gl import context_info, list_devices

    out = {"gl": context_info(ctx), "egl_devices": list_devices(), "torch": torch.__version__,
           "cuda": torch.cuda.is_available(), "onnxruntime": ort.__version__, "onnxruntime_providers": ort.get_available_providers()}  # fmt: skip
    if out["cuda"]:
        props = torch.cuda.get_device_properties(0)
        out["gpu"] = {"name": props.name, "multiprocessors": props.multi_processor_count, "memory_gib": round(props.total_memory / 2**30, 1)}
    try:
        smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,clocks.sm,clocks.max.sm", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20)  # fmt: skip
        out["nvidia_smi"] = smi.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        out["nvidia_smi"] = None
    return out


def flops_limits(device, size: int) -> dict:
    """Measured matrix-product rates (GFLOP/s) on ``device``: float32 without TF32 (the rate a
    fragment shader's float32 arithmetic and an fp32 network run against) and float16."""
    import torch

    out = {}
    gen = torch.Generator(device=device).manual_seed(0)
    for name, dtype in (("fp32", torch.float32), ("fp16", torch.float16)):
        if device.type == "cpu" and dtype == torch.float16:
            continue
        a = torch.randn(size, size, device=device, dtype=dtype, generator=gen)  # random data: zeros run faster
        b = torch.randn(size, size, device=device, dtype=dtype, generator=gen)
        previous = torch.backends.cuda.matmul.allow_tf32
        torch.backends.cuda.matmul.allow_tf32 = False
        try:
            out[f"{name}_gflops"] = round(2 * size**3 / _median_seconds(lambda: a @ b, device, 3, 10) / 1e9, 1)
        finally:
            torch.backends.cuda.matmul.allow_tf32 = previous
    out["matrix_size"] = size
    return out


def _median_seconds(fn, device, warmup: int, repeats: int) -> float:
    """Median seconds of ``fn()``: CUDA events on a GPU, the wall clock on the CPU."""
    import torch

    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end) / 1e3)
        else:
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


# ------------------------------------------------------------------ GLSL and ONNX frames


def views_of(camera, count: int) -> list:
    return [camera.orbit(2 * np.pi * i / count) for i in range(count)]


def renderer_frames(scene, size, ctx, views: int, backend: str, providers=None, standin=None) -> dict:
    """``draw()`` frames on ``views`` orbit views (after 2 warm-up views): medians of the frame and its
    stages; then per view the relight-only frame (the light turned) and the read-back of its pixels.
    ``standin``: (torch device) the ONNX backend's engine runs its packed batches in torch there instead
    of ONNX Runtime (:func:`torch_engine`); the rest of the frame is the backend's own."""
    from prt.runtime.renderer import Renderer

    width, height = size
    with Renderer(scene, width, height, backend=backend, ctx=ctx, providers=providers) as r:
        if standin is not None:
            r.draw()  # creates the backend
            torch_engine(r._backends["onnx"].engine, scene, standin)
        cams = views_of(r.camera, views)
        stages: dict[str, list[float]] = {}
        relight, readback, flops = [], [], []
        lighting = r.lighting
        for i, camera in enumerate([cams[0].orbit(-0.02), cams[0].orbit(-0.01), *cams]):
            r.set_camera_object(camera)
            r.lighting = lighting  # the light as the scene has it (the relight frame below turned it)
            r.draw()
            if i < 2:
                continue
            for k, v in r.timings.items():
                stages.setdefault(k, []).append(v)
            r.lighting = type(lighting).from_sh(lighting.sh, rotation=_rotation_y(0.3 + 0.1 * i))  # what set_envmap(rotation=) sets
            runs = r.stats["network_runs"]
            r.draw()
            assert r.stats["network_runs"] == runs  # relighting ran no network
            relight.append(r.timings["frame"])
            r.read_frame()
            readback.append(r.timings.get("frame_readback", 0.0))
            flops.append(covered_flops(scene, r.gbuffer.read_packed())[0])  # after the timings: the view's network FLOPs
        engine = backend
        if backend == "onnx":
            engine = f"onnxruntime {next(iter(r._backends['onnx'].engine.sessions.values())).get_providers()[0]}"
            if standin is not None:
                engine = f"onnx backend, engine torch on {standin.type} (stand-in for onnxruntime CUDA)"
        med = {k: round(float(np.median(v)), 4) for k, v in stages.items()}
        return {"engine": engine, "renderer": r.gl_renderer, "frame_ms": med["frame"], "fps": round(1e3 / med["frame"], 2),
                "stages_ms": med, "relight_ms": round(float(np.median(relight)), 4),
                "readback_ms": round(float(np.median(readback)), 4), "flops": int(np.median(flops)), "views": views}  # fmt: skip


def _rotation_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def covered_flops(scene, packed: np.ndarray) -> tuple[int, int]:
    """(FLOPs of the view's networks, covered pixels): each covered pixel's segment's FLOPs per fragment."""
    segment = packed[:, 7].astype(np.int64)
    covered = packed[:, 3] > 0.5
    per = np.array([s.flops_per_fragment or 0 for s in scene.manifest.segments], dtype=np.float64)
    return int(per[segment[covered]].sum()), int(covered.sum())


# ------------------------------------------------------------------ the stand-in engine: torch


def torch_networks(scene, device):
    """Per network segment, a callable (R, 6) -> (R, outputs) in torch on ``device`` with the weights of
    its ONNX file (the graph's function, as ``prt.train.networks.network.evaluate_numpy``); and one for
    float16 (encoding in float32: sin / cos of 2^k pi x need it, then the MLP in float16)."""
    import torch

    from prt.export.onnx_model import LEAKY_SLOPE, NORMAL_EPS, POSITION_CLIP, read_arrays

    def normal_quadratic(n):  # prt.train.networks.network's, without list indexing (a host copy a CUDA graph cannot capture)
        return torch.cat([n, n * n, n * torch.cat([n[:, 1:], n[:, :1]], dim=1)], dim=1)

    nets = {}
    for seg in scene.manifest.segments:
        if seg.kind != "network":
            continue
        arrays, arch = read_arrays(seg.model)
        if arch.get("encoding", "freq") != "freq" or "code_weight" in arrays:
            raise ValueError(f"{seg.model}: the stand-in evaluates static frequency networks only")
        t = {k: torch.from_numpy(np.asarray(v, np.float32)).to(device) for k, v in arrays.items()}
        layers = sum(1 for k in t if k.startswith("layer") and k.endswith("_weight"))

        def run(x, t=t, layers=layers, half=False):
            p = torch.clamp((x[:, :3] - t["enc_centre"]) * t["enc_inv_half"], -POSITION_CLIP, POSITION_CLIP)
            n = x[:, 3:6] / torch.clamp(torch.linalg.vector_norm(x[:, 3:6], dim=1, keepdim=True), min=NORMAL_EPS)
            ap, an = p @ t["enc_pos_freq"], n @ t["enc_normal_freq"]
            h = torch.cat([p, torch.sin(ap), torch.cos(ap), n, torch.sin(an), torch.cos(an)], dim=1)
            w = (lambda k: t[k].half()) if half else (lambda k: t[k])
            h = h.half() if half else h
            for i in range(layers):
                h = torch.nn.functional.leaky_relu(h @ w(f"layer{i}_weight") + w(f"layer{i}_bias"), LEAKY_SLOPE)
            out = torch.tanh((h @ w("out_weight") + w("out_bias")).float()) * t["out_scale"] + t["out_offset"]
            if "out_normal_quad" in t:
                out = out + normal_quadratic(n) @ t["out_normal_quad"]
            return out

        nets[seg.id] = run
    return nets


def torch_engine(engine, scene, device) -> None:
    """Replace ``engine.infer_sorted`` (an :class:`~prt.runtime.backends.onnx.OnnxTransfer`) by the same
    batched inference in torch on ``device``: the packed rows copied there once, each network segment's
    block one batch, the transfer copied back; analytic segments as the engine computes them."""
    import torch

    nets = torch_networks(scene, device)

    def infer_sorted(x, offsets):
        t0 = time.perf_counter()
        transfer = np.empty((len(x), engine.n), dtype=np.float32)
        with torch.inference_mode():
            xd = torch.from_numpy(x).to(device, non_blocking=False)
            parts = []
            for s in range(len(offsets) - 1):
                lo, hi = int(offsets[s]), int(offsets[s + 1])
                if hi == lo:
                    continue
                if s in engine.analytic:
                    engine._analytic(transfer, slice(lo, hi), x[lo:hi, 3:6])
                else:
                    parts.append((lo, hi, nets[s](xd[lo:hi])))
            for lo, hi, y in parts:
                transfer[lo:hi] = y.cpu().numpy()
        engine.calls += 1
        engine.timings = {"inference": 1e3 * (time.perf_counter() - t0)}
        return transfer

    engine.infer_sorted = infer_sorted


def packed_view(scene, size, ctx, camera) -> np.ndarray:
    """The G-buffer of a view, packed (:meth:`prt.runtime.gbuffer.GBufferPass.read_packed`)."""
    from prt.runtime.gbuffer import GBufferPass

    gbuffer = GBufferPass(ctx, scene.manifest, *size)
    try:
        gbuffer.render(camera)
        return gbuffer.read_packed()
    finally:
        gbuffer.release()


def standin_stage(scene, size, ctx, device, views: int) -> dict:
    """The batched network stage with torch on ``device``: each view's covered pixels packed by segment,
    resident on the device, every segment's rows one batch; eager and CUDA-graph replay, fp32 and fp16."""
    import onnxruntime as ort
    import torch

    from prt.runtime.camera import Camera
    from prt.runtime.segmentation import segment_sort

    nets = torch_networks(scene, device)
    camera = Camera.from_manifest(scene.manifest.camera)
    rows = {"fp32_eager": [], "fp16_eager": [], "fp32_graph": [], "fp16_graph": []}
    agreement, fp16_db, flops, pixels = [], [], [], []
    for k, view in enumerate(views_of(camera, views)):
        packed = packed_view(scene, size, ctx, view)
        segment = np.where(packed[:, 3] > 0.5, packed[:, 7], -1).astype(np.int32)
        order, offsets = segment_sort(segment, len(scene.manifest.segments))
        x = np.ascontiguousarray(packed[order][:, [0, 1, 2, 4, 5, 6]], dtype=np.float32)
        blocks = [(s, int(offsets[s]), int(offsets[s + 1])) for s in nets if offsets[s + 1] > offsets[s]]
        f, p = covered_flops(scene, packed)
        flops.append(f)
        pixels.append(p)
        xd = torch.from_numpy(x).to(device)
        outputs = {}

        def stage(half, xd=xd, blocks=blocks):
            return [nets[s](xd[lo:hi], half=half) for s, lo, hi in blocks]

        with torch.inference_mode():
            for half in (False, True):
                name = "fp16" if half else "fp32"
                rows[f"{name}_eager"].append(_median_seconds(lambda: stage(half), device, 2, 5) * 1e3)
                outputs[name] = torch.cat(stage(half)).float().cpu().numpy() if blocks else np.zeros((0, 1), np.float32)
                if device.type == "cuda" and blocks:
                    graph = torch.cuda.CUDAGraph()
                    stream = torch.cuda.Stream()
                    stream.wait_stream(torch.cuda.current_stream())
                    with torch.cuda.stream(stream):
                        stage(half)  # warm-up outside the capture
                    torch.cuda.current_stream().wait_stream(stream)
                    with torch.cuda.graph(graph):
                        stage(half)
                    rows[f"{name}_graph"].append(_median_seconds(graph.replay, device, 3, 20) * 1e3)
        if k == 0 and blocks:  # the stand-in computes the ONNX files' function: ONNX Runtime on the CPU, same rows
            reference = np.concatenate([ort.InferenceSession(str(scene.manifest.segments[s].model), providers=["CPUExecutionProvider"])
                                        .run(None, {"x": x[lo:hi]})[0] for s, lo, hi in blocks])  # fmt: skip
            agreement.append(_db(reference, outputs["fp32"]))
            fp16_db.append(_db(outputs["fp32"], outputs["fp16"]))
    med = {k: round(float(np.median(v)), 4) for k, v in rows.items() if v}
    return {"engine": f"torch {torch.__version__} on {device.type}" + (f" ({torch.cuda.get_device_name(0)})" if device.type == "cuda" else ""),
            "network_ms": med, "flops": int(np.median(flops)), "covered_pixels": int(np.median(pixels)),
            "fp32_vs_onnxruntime_db": round(agreement[0], 2) if agreement else None,
            "fp16_vs_fp32_db": round(fp16_db[0], 2) if fp16_db else None, "views": views}  # fmt: skip


def _db(reference: np.ndarray, other: np.ndarray) -> float:
    """Agreement in dB: peak of the reference over the RMS difference."""
    mse = float(np.mean((np.asarray(reference, np.float64) - np.asarray(other, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(float(np.abs(reference).max()) ** 2 / mse)


# ------------------------------------------------------------------ fitting


def fit_figures(scene, steps: int, devices: list[str], samples: int | None) -> dict:
    """One segment (the bounce build's largest network segment) fitted on each device: its architecture
    and sample count, samples drawn on its surface (area-uniform, face normals), the committed network's
    output as the target."""
    import torch

    from prt.export.onnx_model import read_arrays
    from prt.runtime.gbuffer import load_mesh
    from prt.runtime.segmentation import segment_of
    from prt.train.networks.fit import FitSettings, fit_segment
    from prt.train.networks.network import Architecture, evaluate_numpy

    m = scene.manifest
    seg = max((s for s in m.segments if s.kind == "network"), key=lambda s: s.samples or 0)
    arrays, arch_dict = read_arrays(seg.model)
    fields = {k: arch_dict[k] for k in ("hidden", "layers", "pos_freqs", "normal_freqs", "bands", "layout", "residual") if k in arch_dict}
    arch = Architecture(**fields)
    mesh = load_mesh(m.geometry.path)
    v, f = mesh["vertices"].astype(np.float64), mesh["faces"]
    tri = v[f]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(0)
    want = int(samples or seg.samples or 20000)
    points, normals = [], []
    while sum(len(p) for p in points) < want * 1.05:
        faces = rng.choice(len(f), size=want, p=area / area.sum())
        a, b = rng.random((2, want))
        flip = a + b > 1
        a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
        pts = tri[faces, 0] + a[:, None] * (tri[faces, 1] - tri[faces, 0]) + b[:, None] * (tri[faces, 2] - tri[faces, 0])
        keep = segment_of(m, pts.astype(np.float32), mesh["object_ids"][faces]) == seg.id
        points.append(pts[keep])
        normals.append((cross[faces] / np.maximum(area[faces], 1e-12)[:, None])[keep])
    p = np.concatenate(points)[: int(want * 1.05)].astype(np.float32)
    n = np.concatenate(normals)[: len(p)].astype(np.float32)
    t = evaluate_numpy(arrays, p, n)
    split = want
    out = {"segment": seg.id, "architecture": arch.label(), "samples": int(split), "validation": int(len(p) - split), "steps": steps, "runs": {}}
    for device in devices:
        settings = FitSettings(steps=steps, batch=8192, device=device)
        if device == "cuda":
            torch.cuda.synchronize()
        result = fit_segment(p[:split], n[:split], t[:split], p[split:], n[split:], t[split:], arch, np.asarray(seg.bounds), settings)
        out["runs"][device] = {"seconds": round(result.seconds, 3), "steps": result.steps, "val_mae": float(result.val_mae),
                               "threads": torch.get_num_threads() if device == "cpu" else None}  # fmt: skip
        log(f"  fit on {device}: {result.seconds:.1f} s, {result.steps} steps, val MAE {result.val_mae:.5f}")
    if {"cuda", "cpu"} <= set(out["runs"]):
        out["cpu_over_gpu"] = round(out["runs"]["cpu"]["seconds"] / out["runs"]["cuda"]["seconds"], 2)
    return out


# ------------------------------------------------------------------ report


def markdown(report: dict) -> str:
    env = report["environment"]
    lines = [f"# GPU check ({'reduced, ' if report['reduced'] else ''}{report['provenance']['date']})", "",
             f"GL renderer: {report['renderer']}; torch {env['torch']} (CUDA {'yes' if env['cuda'] else 'no'}"
             f"{', ' + env['gpu']['name'] if env.get('gpu') else ''}); onnxruntime {env['onnxruntime']} ({', '.join(env['onnxruntime_providers'])}).",
             f"Device limits: {', '.join(f'{k} {v}' for k, v in report['limits'].items())}.", "",
             "| scene | size | engine | frame ms | FPS | network ms | network GFLOP/s | share of fp32 limit | relight ms | read-back ms |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for row in report["frames"]:
        lines.append(f"| {row['scene']} | {row['size']} | {row['engine']} | {row.get('frame_ms', '-')} | {row.get('fps', '-')} | "
                     f"{row.get('network_ms', '-')} | {row.get('network_gflops', '-')} | {row.get('limit_share', '-')} | "
                     f"{row.get('relight_ms', '-')} | {row.get('readback_ms', '-')} |")  # fmt: skip
    fit = report.get("fit")
    if fit:
        runs = "; ".join(f"{d}: {r['seconds']} s, val MAE {r['val_mae']:.5f}" for d, r in fit["runs"].items())
        lines += ["", f"Fit of segment {fit['segment']} ({fit['architecture']}, {fit['samples']} samples, {fit['steps']} steps): {runs}"
                  + (f"; CPU / GPU {fit['cpu_over_gpu']}x" if "cpu_over_gpu" in fit else "") + "."]  # fmt: skip
    lines += ["", "| target | measured | met |", "|---|---|---|"]
    for name, t in report["targets"].items():
        lines.append(f"| {name} | {t['measured']} | {t['met']} |")
    lines += ["", f"Command: `{report['provenance']['command']}`, commit {report['provenance']['commit']}."]
    return "\n".join(lines) + "\n"


def targets(frames: list[dict], reduced: bool) -> dict:
    """The issue's H200 targets, read off the rows (at the full sizes; a reduced run marks them n/a)."""

    def row(scene, size, engine_prefix):
        return next((r for r in frames if r["scene"] == scene and r["size"] == size and r["engine"].startswith(engine_prefix)), None)

    out = {}
    glsl = row("demo", "1024x1024", "glsl")
    out["GLSL >= 500 FPS at 1024x1024, k = 64 direct (demo)"] = (glsl or {}).get("fps"), lambda v: v >= 500
    net = [r for r in frames if r["scene"] == "bounce" and r["size"] == "1920x1080" and "network_ms" in r and r["engine"] != "glsl"]
    best = min((r["network_ms"] for r in net), default=None)
    out["network stage <= 2 ms at 1920x1080, default build with bounces (best engine)"] = best, lambda v: v <= 2.0
    relight = [r["relight_ms"] for r in frames if r["engine"] == "glsl" and "relight_ms" in r]
    out["relight-only frame <= 0.3 ms (GLSL, largest over scenes and sizes)"] = (max(relight) if relight else None), lambda v: v <= 0.3
    return {k: {"measured": v, "met": "n/a (reduced run)" if reduced or v is None else bool(ok(v))} for k, (v, ok) in out.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", type=Path, default=None, help=f"the record (default: {RECORD.relative_to(ROOT)} on a GPU; required with --reduced)")
    p.add_argument("--md", type=Path, default=None, help="the Markdown table (default: beside --json)")
    p.add_argument("--bounce", type=Path, default=BOUNCE_SCENE, help="a default build with bounces")
    p.add_argument("--gl-device", default=None, help="EGL device (default: $PRT_GL_DEVICE, else auto)")
    p.add_argument("--views", type=int, default=12, help="orbit views per configuration")
    p.add_argument("--fit-steps", type=int, default=1000)
    p.add_argument("--reduced", action="store_true", help="toy sizes: shows the script works (no GPU needed)")
    p.add_argument("--budget", type=float, default=400.0, help="seconds after which no further configuration starts (the record is written)")
    args = p.parse_args(argv)
    import torch

    from prt.runtime.errors import PRTError
    from prt.runtime.files import atomic_write_bytes, atomic_write_json
    from prt.runtime.gl import create_context
    from prt.runtime.renderer import Scene

    out = args.json if args.json is not None else (None if args.reduced else RECORD)
    if out is None:
        print("gpu_check: error: --reduced needs --json (a trial run never writes the record)", file=sys.stderr)
        return 2
    try:
        ctx = create_context(device=args.gl_device, origin="--gl-device")
        scenes = {"demo": Scene.load(), "bounce": Scene.load(args.bounce)}
    except PRTError as exc:
        print(f"gpu_check: error: {exc}", file=sys.stderr)
        return 2
    renderer = ctx.info.get("GL_RENDERER", "")
    gpu_gl = not any(word in renderer.lower() for word in SOFTWARE)
    if out.resolve() == RECORD.resolve() and not (gpu_gl or torch.cuda.is_available()):  # a CPU-only run
        ctx.release()
        print(f"gpu_check: error: refusing to write {RECORD.relative_to(ROOT)} from a run without a GPU (GL renderer {renderer!r}, "
              f"torch CUDA {torch.cuda.is_available()}); pass --reduced --json DIR/gpu.json for a trial run", file=sys.stderr)  # fmt: skip
        return 2
    t_start = time.perf_counter()
    reduced = args.reduced
    sizes = REDUCED_SIZES if reduced else SIZES
    views = 1 if reduced else args.views
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    env = environment(ctx)
    log(f"GL renderer {renderer}; torch {torch.__version__} on {device}; onnxruntime providers {env['onnxruntime_providers']}")
    limits = flops_limits(device, 256 if reduced else 8192 if device.type == "cuda" else 2048)
    log(f"limits: {limits}")
    has_ort_cuda = "CUDAExecutionProvider" in env["onnxruntime_providers"]
    fit_devices = ["cuda", "cpu"] if device.type == "cuda" else ["cpu"]
    fit = fit_figures(scenes["bounce"], 5 if reduced else args.fit_steps, fit_devices, 800 if reduced else None)
    # GLSL on a software rasteriser at full sizes would take the whole budget: there only the GPU engine runs
    glsl_ok = gpu_gl or reduced
    frames, skipped = [], []
    for name, scene in scenes.items():
        for size in sizes:
            label = f"{size[0]}x{size[1]}"
            if time.perf_counter() - t_start > args.budget:  # write what was measured rather than be cut off
                skipped.append(f"{name} {label}: over the {args.budget:.0f} s budget")
                continue
            rows = []
            if glsl_ok:
                glsl = renderer_frames(scene, size, ctx, views, "glsl")
                rows.append({"scene": name, "size": label, **glsl, "network_ms": glsl["stages_ms"].get("network")})
            else:
                skipped.append(f"{name} {label} glsl: GL is a software rasteriser ({renderer})")
            if has_ort_cuda or reduced:  # onnxruntime's own engine (on the CPU only in a reduced run)
                onnx = renderer_frames(scene, size, ctx, views, "onnx", ["CUDAExecutionProvider", "CPUExecutionProvider"] if has_ort_cuda else None)
                rows.append({"scene": name, "size": label, **onnx, "network_ms": onnx["stages_ms"].get("inference")})
            if not has_ort_cuda or reduced:  # the same frames with torch as the engine, and the network stage resident
                onnx = renderer_frames(scene, size, ctx, views, "onnx", standin=device)
                rows.append({"scene": name, "size": label, **onnx, "network_ms": onnx["stages_ms"].get("inference")})
                standin = standin_stage(scene, size, ctx, device, 1 if reduced else 3)
                best = min(standin["network_ms"].values())
                rows.append({"scene": name, "size": label, "engine": standin["engine"] + " (stand-in: network stage only)",
                             "network_ms": best, "flops": standin["flops"], "standin": standin})  # fmt: skip
            for row in rows:
                if row.get("network_ms"):
                    row["network_gflops"] = round(row["flops"] / (row["network_ms"] * 1e-3) / 1e9, 1)
                    row["limit_share"] = round(row["network_gflops"] / limits["fp32_gflops"], 4)
                log(f"{name} {label} {row['engine']}: frame {row.get('frame_ms', '-')} ms, network {row.get('network_ms')} ms, "
                    f"relight {row.get('relight_ms', '-')} ms")  # fmt: skip
            frames += rows
    report = {
        "provenance": _provenance()(gl_renderer=renderer, gpu=(env.get("gpu") or {}).get("name")),
        "renderer": renderer, "reduced": reduced, "environment": env, "limits": limits, "frames": frames, "fit": fit,
        "targets": targets(frames, reduced), "skipped": skipped, "seconds": round(time.perf_counter() - t_start, 1),
    }  # fmt: skip
    ctx.release()
    text = markdown(report)
    atomic_write_json(out, report)
    atomic_write_bytes(args.md or out.with_suffix(".md"), text.encode())
    log(text)
    log(f"gpu_check: {report['seconds']} s; wrote {out}")
    return 0


def _provenance():
    """``prt.bench.provenance.provenance``, loaded from its file: the package ``prt.bench`` imports the
    benchmark (ray tracing: embreex, trimesh), which the GPU machine's image does not have."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("prt_bench_provenance", ROOT / "bench" / "provenance.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.provenance


def scene_camera(scene):
    from prt.runtime.camera import Camera

    return Camera.from_manifest(scene.manifest.camera)


if __name__ == "__main__":
    sys.exit(main())
