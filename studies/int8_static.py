"""Does static int8 (QDQ, calibrated activations) make the ONNX network stage faster?

usage: python studies/int8_static.py SCENE.json [--rows 4096] [--repeats 30] [--json out.json]

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

import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static

from prt.bench.segment_study import StudyError, study_parser, interleaved_ms, network_segments, session, write_report
from prt.export.precision import build_variant


def static_int8(source: Path, calibration: np.ndarray, path: Path) -> Path:
    """Write a QDQ static int8 copy of ``source`` (MLP Gemms and LeakyRelus only) to ``path``."""
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


def main(argv=None) -> int:
    p = study_parser(__doc__.splitlines()[0])
    p.add_argument("--calibration", type=int, default=4096, help="training samples that calibrate the activation ranges")
    args = p.parse_args(argv)

    try:
        segments = network_segments(args.scene)
    except StudyError as exc:
        print(f"int8_static: error: {exc}", file=sys.stderr)
        return 2
    rng = np.random.default_rng(0)
    variants = ("fp32", "int8-dynamic", "int8-static")
    rows = []
    with tempfile.TemporaryDirectory(prefix="prt_int8_") as folder:
        for item in segments:
            seg = item.segment
            calibration = item.train[rng.choice(len(item.train), min(args.calibration, len(item.train)), replace=False)]
            paths = {
                "fp32": seg.model,
                "int8-dynamic": build_variant(seg.model, "int8", Path(folder) / f"seg{seg.id}-dyn.onnx"),
                "int8-static": static_int8(seg.model, calibration, Path(folder) / f"seg{seg.id}-static.onnx"),
            }
            sessions = {k: session(v) for k, v in paths.items()}
            mae = {k: float(np.abs(s.run(None, {"x": item.held})[0] - item.held_transfer).mean()) for k, s in sessions.items()}
            x = item.train[rng.choice(len(item.train), args.rows, replace=len(item.train) < args.rows)]
            ms = interleaved_ms(sessions, x, args.repeats)
            row = {"segment": seg.id, "arch": seg.architecture, "ms": ms, "speedup": {k: ms["fp32"] / ms[k] for k in variants}, "mae": mae}
            rows.append(row)
            print(f"segment {seg.id}: " + ", ".join(f"{k} {ms[k]:.2f} ms ({row['speedup'][k]:.2f}x, MAE {mae[k]:.5f})" for k in variants))
    summary = {k: {"speedup": float(np.median([r["speedup"][k] for r in rows])), "mae": float(np.median([r["mae"][k] for r in rows]))} for k in variants}
    print("median over segments: " + ", ".join(f"{k} {v['speedup']:.2f}x, MAE {v['mae']:.5f}" for k, v in summary.items()))
    write_report(args.json, args.scene, args.rows, args.repeats, rows, summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
