"""The ``"onnx"`` backend: transfer per pixel with ONNX Runtime (pack covered fragments by
segment, infer, scatter back), the analogue of the paper's CUDA path.

Readback: the G-buffer comes back to the CPU as one packed array (:meth:`GBufferPass.read_packed`).

Packing: the segment id of every pixel comes from the G-buffer; one pass per segment over the
covered pixels (``flatnonzero``, no argsort), then one gather of the six input floats.
Inference: each network segment's batch is cut into cache-sized slices that a small pool of
threads feeds to the segment's session concurrently (one intra-op thread per call, spinning
off), which keeps two cores busy without thread pools fighting each other.  Analytic
(unshadowed) segments skip the network: their transfer is :func:`prt.runtime.sh.unshadowed_transfer`
(in float32).  The result is one transfer row per covered pixel, in pixel order.

:class:`OnnxTransfer` is the engine (sessions and packed inference, no OpenGL); :class:`OnnxBackend`
puts it behind :class:`prt.runtime.backends.TransferBackend`.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .. import sh
from ..checks import positive_int
from ..errors import InputError
from ..gbuffer import PACKED_COLUMNS, PACKED_SEGMENT
from ..onnxfile import read_model
from .base import CpuTransfer, TransferBackend

__all__ = ["OnnxBackend", "OnnxTransfer", "default_providers"]


def default_providers() -> list[str]:
    """CUDA first where onnxruntime has it, then CPU."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


class OnnxTransfer:
    """The networks of a scene as ONNX Runtime sessions.

    Parameters
    ----------
    manifest : prt.runtime.manifest.Manifest
    providers : execution providers in order of preference (default: CUDA if present, CPU)
    threads : concurrent inference calls (default: all cores)
    slice_rows : rows per inference call (small enough that activations stay in cache)
    """

    def __init__(self, manifest, providers=None, threads: int | None = None, slice_rows: int = 4096):
        import onnxruntime as ort

        self.bands = manifest.sh_bands
        self.n = self.bands * self.bands
        self.providers = list(providers) if providers else default_providers()
        self.threads = positive_int(threads, "threads") if threads is not None else (os.cpu_count() or 1)
        self.slice_rows = int(slice_rows)
        self.sessions: dict[int, object] = {}
        self.input_names: dict[int, str] = {}
        self.models: dict[int, object] = {}  # segment id -> model path, for messages
        self.analytic: set[int] = set()
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.intra_op_num_threads = 1  # parallelism comes from concurrent slices
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
        for seg in manifest.segments:
            if seg.kind == "analytic":
                self.analytic.add(seg.id)
                continue
            model = read_model(seg.model)  # refuses external data (files outside the scene folder)
            try:
                sess = ort.InferenceSession(model, opts, providers=self.providers)
            except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph types
                msg = " ".join(str(exc).split())[:200]
                raise InputError(f"{seg.model}: cannot load ONNX model ({msg})") from None
            self.input_names[seg.id] = _check_signature(sess, seg.model, self.n)
            self.sessions[seg.id] = sess
            self.models[seg.id] = seg.model
        self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="ort") if self.threads > 1 else None
        self.calls = 0  # network invocations so far (tests check relighting makes none)
        self.timings: dict[str, float] = {}

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.sessions.clear()

    def compute(self, inputs: np.ndarray, segment: np.ndarray, columns=(0, 1, 2, 3, 4, 5)):
        """Transfer of every covered pixel.

        Parameters
        ----------
        inputs : (P, C) float32 per-pixel data (e.g. the packed G-buffer)
        segment : (P,) int, segment id per pixel, -1 for background
        columns : the six columns of ``inputs`` holding position xyz and normal xyz

        Returns
        -------
        covered : (M,) int64, indices of the covered pixels (segment >= 0), ascending
        transfer : (M, n) float32, the transfer of each covered pixel
        Timings (ms) of the last call are in ``self.timings``: pack, inference, scatter.
        """
        t0 = time.perf_counter()
        covered = np.flatnonzero(segment >= 0)
        seg_cov = segment[covered]
        cols = np.asarray(columns, dtype=np.intp)[None, :]
        batches = []
        for s in np.unique(seg_cov):
            rows = np.flatnonzero(seg_cov == s)  # positions within ``covered``
            x = inputs[covered[rows][:, None], cols]  # one gather, contiguous (len, 6)
            batches.append((int(s), rows, x))
        t1 = time.perf_counter()
        jobs = []
        for s, rows, x in batches:
            if s in self.analytic:
                continue
            if s not in self.sessions:
                raise InputError(f"segment {s} appears in the G-buffer but the scene has no such segment")
            for a in range(0, len(x), self.slice_rows):
                jobs.append((s, rows, x, a))
        results = self._run(jobs)
        t2 = time.perf_counter()
        transfer = np.empty((len(covered), self.n), dtype=np.float32)
        for (s, rows, x, a), y in zip(jobs, results):
            transfer[rows[a : a + self.slice_rows]] = y
        for s, rows, x in batches:
            if s in self.analytic:
                transfer[rows] = sh.unshadowed_transfer(x[:, 3:6], self.bands, dtype=np.float32)
        t3 = time.perf_counter()
        self.timings = {"pack": 1e3 * (t1 - t0), "inference": 1e3 * (t2 - t1), "scatter": 1e3 * (t3 - t2)}
        return covered, transfer

    def _run(self, jobs):
        if not jobs:
            return []
        self.calls += 1

        def run(job):
            s, _, x, a = job
            rows = x[a : a + self.slice_rows]
            try:
                y = self.sessions[s].run(None, {self.input_names[s]: rows})[0]
            except Exception as exc:  # onnxruntime's own error types
                raise InputError(f"{self.models[s]}: inference failed ({' '.join(str(exc).split())[:200]})") from None
            if not isinstance(y, np.ndarray) or y.shape != (len(rows), self.n) or y.dtype != np.float32:
                what = f"{getattr(y, 'shape', '?')} {getattr(y, 'dtype', type(y).__name__)}"
                raise InputError(f"{self.models[s]}: the model gave {what} for {len(rows)} rows, expected ({len(rows)}, {self.n}) float32")
            return y

        if self._pool is None:
            return [run(j) for j in jobs]
        return list(self._pool.map(run, jobs))


class OnnxBackend(TransferBackend):
    """:class:`OnnxTransfer` on the packed G-buffer: the transfer comes back on the CPU.

    Timings: ``readback`` (the packed G-buffer), ``pack``, ``inference``, ``scatter``.
    """

    name = "onnx"

    def __init__(self, ctx, manifest, *, providers=None, threads: int | None = None):
        super().__init__(ctx, manifest)
        self.engine = OnnxTransfer(manifest, providers=providers, threads=threads)

    def run(self, gbuffer, target) -> CpuTransfer:
        t0 = time.perf_counter()
        packed = gbuffer.read_packed()
        t1 = time.perf_counter()
        segment = packed[:, PACKED_SEGMENT].astype(np.int32)
        covered, transfer = self.engine.compute(packed, segment, columns=PACKED_COLUMNS)
        t2 = time.perf_counter()
        self.timings = {"readback": 1e3 * (t1 - t0), **self.engine.timings}
        self.timings["pack"] += 1e3 * (t2 - t1) - sum(self.engine.timings.values())  # the segment-id column
        return CpuTransfer(covered, transfer, packed)

    def release(self) -> None:
        self.engine.close()


def _check_signature(sess, path, n_out: int) -> str:
    """The name of the model's one input, after checking it is float32 [N, 6] and its one output float32 [N, n_out]."""
    inputs, outputs = sess.get_inputs(), sess.get_outputs()

    def fits(args, width):
        a = args[0]
        return len(args) == 1 and a.type == "tensor(float)" and len(a.shape) == 2 and a.shape[1] == width

    if not fits(inputs, 6):
        got = [(i.name, i.type, i.shape) for i in inputs]
        raise InputError(f"{path}: model input must be one float32 tensor [N, 6] (position, normal), got {got}")
    if not fits(outputs, n_out):
        got = [(o.name, o.type, o.shape) for o in outputs]
        raise InputError(f"{path}: model output must be one float32 tensor [N, {n_out}], got {got}")
    return inputs[0].name
