"""Does static int8 (QDQ, calibrated activations) make the ONNX network stage faster?

usage: python bench/int8_static.py SCENE.json [--rows 4096] [--repeats 30] [--json out.json]

For every network segment of a scene built by ``prt-train`` (its ``precompute/`` beside
``scene.json``), three versions of the model run one slice of ``--rows`` held-out surface
points on one thread, alternating so that machine noise hits them alike:

- ``fp32``: the exported model (ONNX Runtime fuses Gemm + LeakyRelu into FusedGemm);
- ``int8-dynamic``: what ``prt-bench`` calls int8 (weights int8, activations quantised per
  call by DynamicQuantizeLinear, MatMulInteger);
- ``int8-static``: weights int8 per channel, activations uint8 with ranges calibrated on the
  segment's training samples (QDQ format; ONNX Runtime runs QGemm and QLinearLeakyRelu), the
  encoding kept in float32.

It reports the median time per call (and the speed-up over fp32) and the validation MAE of
the transfer coefficients against the ray-traced ground truth, per segment and as medians.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT.parent))  # run from a checkout without installing


def static_int8(source: Path, calibration: np.ndarray, path: Path) -> Path:
    """Write a QDQ static int8 copy of ``source`` (MLP Gemms and LeakyRelus only) to ``path``."""
    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.batches = iter([{"x": calibration[i : i + 512]} for i in range(0, len(calibration), 512)])

        def get_next(self):
            return next(self.batches, None)

    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the quantiser's advice to pre-process is noise here
    try:
        quantize_static(
            str(source), str(path), Reader(), quant_format=QuantFormat.QDQ, op_types_to_quantize=["Gemm", "LeakyRelu"],
            per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
            calibrate_method=CalibrationMethod.MinMax,
        )  # fmt: skip
    finally:
        root.setLevel(level)
    return path


def session(path: Path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path)
    p.add_argument("--rows", type=int, default=4096, help="rows per call (the runtime's slice)")
    p.add_argument("--calibration", type=int, default=4096, help="training samples that calibrate the activation ranges")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)

    from prt.runtime.errors import PRTError
    from prt.runtime.manifest import load_manifest
    from prt.train.benchmark import build_variant

    try:
        manifest = load_manifest(args.scene)
    except PRTError as exc:
        print(f"int8_static: error: {exc}", file=sys.stderr)
        return 2
    pre = args.scene.parent / "precompute"
    if not (pre / "samples.npz").is_file():
        print(f"int8_static: error: {pre}/samples.npz: not found (a scene built by prt-train keeps it)", file=sys.stderr)
        return 2
    samples, valid = np.load(pre / "samples.npz"), np.load(pre / "validation.npz")
    x_train = np.concatenate([samples["points"], samples["normals"]], axis=1).astype(np.float32)
    x_valid = np.concatenate([valid["points"], valid["normals"]], axis=1).astype(np.float32)
    rng = np.random.default_rng(0)
    variants = ("fp32", "int8-dynamic", "int8-static")
    rows = []
    with tempfile.TemporaryDirectory(prefix="prt_int8_") as folder:
        for seg in manifest.segments:
            if seg.kind != "network":
                continue
            own = np.flatnonzero(samples["segment"] == seg.id)
            held = np.flatnonzero(valid["segment"] == seg.id)
            if len(own) == 0 or len(held) == 0:
                continue
            calibration = x_train[rng.choice(own, min(args.calibration, len(own)), replace=False)]
            paths = {
                "fp32": seg.model,
                "int8-dynamic": build_variant(seg.model, "int8", Path(folder) / f"seg{seg.id}-dyn.onnx"),
                "int8-static": static_int8(seg.model, calibration, Path(folder) / f"seg{seg.id}-static.onnx"),
            }
            sessions = {k: session(v) for k, v in paths.items()}
            xs = x_valid[held]
            mae = {k: float(np.abs(s.run(None, {"x": xs})[0] - valid["transfer"][held]).mean()) for k, s in sessions.items()}
            x = x_train[rng.choice(own, args.rows, replace=len(own) < args.rows)]
            times = {k: [] for k in variants}
            for k, s in sessions.items():
                s.run(None, {"x": x})  # warm-up
            for _ in range(args.repeats):  # interleaved: noise hits every variant alike
                for k, s in sessions.items():
                    t0 = time.perf_counter()
                    s.run(None, {"x": x})
                    times[k].append(time.perf_counter() - t0)
            ms = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
            row = {"segment": seg.id, "arch": seg.architecture, "ms": ms, "speedup": {k: ms["fp32"] / ms[k] for k in variants}, "mae": mae}
            rows.append(row)
            print(f"segment {seg.id}: " + ", ".join(f"{k} {ms[k]:.2f} ms ({row['speedup'][k]:.2f}x, MAE {mae[k]:.5f})" for k in variants))
    if not rows:
        print("int8_static: error: the scene has no network segment with samples", file=sys.stderr)
        return 2
    summary = {k: {"speedup": float(np.median([r["speedup"][k] for r in rows])), "mae": float(np.median([r["mae"][k] for r in rows]))} for k in variants}
    print("median over segments: " + ", ".join(f"{k} {v['speedup']:.2f}x, MAE {v['mae']:.5f}" for k, v in summary.items()))
    if args.json is not None:
        import onnxruntime

        from prt.runtime.files import atomic_write_json

        atomic_write_json(args.json, {"scene": str(args.scene), "rows": args.rows, "repeats": args.repeats, "threads": 1,
                                      "onnxruntime": onnxruntime.__version__, "segments": rows, "median": summary})  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
