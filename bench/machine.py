"""The machine the benchmark runs on: its float32 GEMM limit, CPU, load, and a network's op profile.

- :func:`machine_gemm`     float32 n x n GEMM through numpy's BLAS and through ONNX Runtime's
                           MatMul on all cores (medians of 3); the higher is the machine's limit
- :func:`busy_seconds`, :func:`other_cpu_share`   CPU time other processes take during a run
- :func:`cpu_name`
- :func:`profile_network`  where one network's time goes (ONNX Runtime's profiler, one thread)
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

__all__ = ["gemm_gflops", "ort_gemm_gflops", "machine_gemm", "busy_seconds", "other_cpu_share", "cpu_name", "profile_network"]


def _gemm_rate(product, n: int, repeats: int) -> float:
    """GFLOP/s of ``product()``, an n x n x n GEMM: median of ``repeats`` after one warm-up."""
    product()  # warm-up: thread pool start, page faults of the output
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        product()
        times.append(time.perf_counter() - t0)
    return float(2.0 * n**3 / np.median(times) / 1e9)


def gemm_gflops(n: int = 4096, repeats: int = 3) -> float:
    """Single-precision GEMM throughput of numpy's BLAS: median GFLOP/s of ``repeats`` n x n products."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    return _gemm_rate(lambda: a @ b, n, repeats)


def ort_gemm_gflops(n: int = 4096, repeats: int = 3, threads: int | None = None) -> float:
    """Single-precision GEMM throughput of ONNX Runtime's CPU MatMul (MLAS) on all cores.

    The same library and kernels family the network stage runs on; on CPUs whose numpy BLAS
    picks an older kernel (OpenBLAS uses its AVX2 kernels on some AVX-512 parts) this is the
    higher of the two, so the honest machine limit is the maximum (``machine_gemm``).
    """
    rng = np.random.default_rng(1)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["a", "b"], ["c"])], "gemm",
        [helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])],
        [helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])],
        [numpy_helper.from_array(b, "b")],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads or os.cpu_count() or 1
    sess = ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    return _gemm_rate(lambda: sess.run(None, {"a": a}), n, repeats)


def machine_gemm(n: int = 4096, repeats: int = 3) -> dict:
    """The machine's float32 GEMM limit: numpy's BLAS and ONNX Runtime's MLAS, and the higher one.

    Returns ``{"numpy": GFLOP/s, "onnxruntime": GFLOP/s, "best": max of the two}``.
    """
    measured = {"numpy": gemm_gflops(n, repeats), "onnxruntime": ort_gemm_gflops(n, repeats)}
    return {**{k: round(v, 2) for k, v in measured.items()}, "best": round(max(measured.values()), 2)}


def busy_seconds():
    """(CPU seconds all processes have been busy, CPU seconds of this process), or None off Linux."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:9]]
    except (OSError, ValueError, IndexError):
        return None
    idle = fields[3] + fields[4]  # idle and iowait
    own = os.times()
    return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK"), own.user + own.system


def other_cpu_share(start, wall: float):
    """Share of all cores' time that other processes were busy since ``start`` (see busy_seconds)."""
    end = busy_seconds()
    if start is None or end is None or wall <= 0:
        return None
    others = (end[0] - start[0]) - (end[1] - start[1])
    return round(max(others, 0.0) / (wall * (os.cpu_count() or 1)), 3)


def cpu_name() -> str:
    """The CPU's model name (Linux), else what :mod:`platform` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def profile_network(model_path, x: np.ndarray, repeats: int = 30) -> dict:
    """Where one network's time goes: ONNX Runtime's own profiler, one thread, ``x`` as one call.

    Returns ``{"rows", "run_us"`` (median model run), ``"op_us"`` ({op type: median microseconds
    per run}), ``"gemm_share"`` (share of the run spent in the MLP's matrix products: Gemm and
    the FusedGemm ORT makes of Gemm + LeakyRelu; the encoding's tiny MatMuls are not counted)``}``.
    """
    with tempfile.TemporaryDirectory(prefix="prt_profile_") as folder:
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.intra_op_num_threads = 1
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(folder) / "profile")
        sess = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
        feed = {"x": np.ascontiguousarray(x, dtype=np.float32)}
        for _ in range(3):
            sess.run(None, feed)  # warm-up runs are profiled too; dropped below by run index
        for _ in range(repeats):
            sess.run(None, feed)
        events = json.loads(Path(sess.end_profiling()).read_text())
    runs = sorted((e for e in events if e.get("name") == "model_run"), key=lambda e: e["ts"])
    kept = runs[3:]
    nodes = [e for e in events if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time")]
    per_run = []  # {op type: microseconds} of each kept run: medians resist a preempted op or two
    for run in kept:
        ops: dict[str, float] = {}
        for e in nodes:
            if run["ts"] <= e["ts"] <= run["ts"] + run["dur"]:
                op = e.get("args", {}).get("op_name", "?")
                ops[op] = ops.get(op, 0.0) + e["dur"]
        per_run.append(ops)
    names = {op for ops in per_run for op in ops}
    op_us = {op: float(np.median([ops.get(op, 0.0) for ops in per_run])) for op in names}
    run_us = float(np.median([e["dur"] for e in kept])) if kept else 0.0
    gemm = sum(v for k, v in op_us.items() if k in ("Gemm", "FusedGemm"))
    return {
        "rows": int(len(x)),
        "run_us": round(run_us, 1),
        "op_us": {k: round(v, 1) for k, v in sorted(op_us.items(), key=lambda kv: -kv[1])},
        "gemm_share": round(gemm / run_us, 3) if run_us else None,
    }
