"""The ``"onnx"`` backend: transfer per pixel with ONNX Runtime (pack covered fragments by
segment, infer, no scatter), the analogue of the paper's CUDA path.

Readback: the G-buffer's two targets come back as they are (:meth:`GBufferPass.read_targets`,
two plain copies); no interleaved array is built.

Packing, O(N): the segment ids are small integers, so one stable counting sort
(:func:`segment_sort`: ``np.bincount`` for the segment sizes, NumPy's radix ``argsort`` on 16-bit
ids for the order) lists the covered pixels segment by segment, ascending within each segment;
one gather per target then builds the networks' input rows in that order
(:func:`segment_sort_reference` is the plain twin: one ``flatnonzero`` pass per segment).
Inference: each network segment's rows are one contiguous block, cut into cache-sized slices that
a small pool of threads feeds to the segment's session concurrently (one intra-op thread per
call, spinning off), which keeps two cores busy without thread pools fighting each other; each
slice's output is copied into its block (no scatter: the transfer stays in packed order and the
renderer shades packed rows, then scatters the radiance once).  Analytic (unshadowed) segments
skip the network: their transfer is :func:`prt.runtime.sh.unshadowed_transfer` (in float32).

Many segments, one cost: the network segments that share an architecture are also loaded as one
stacked model (:mod:`prt.runtime.onnx_stack`, built at load time from their files), which takes
blocks of 64 rows and each block's segment; a frame's rows of all those segments go to it in calls
of about ``slice_rows`` rows, so the number of calls follows the rows, not the segments (a segment
with ``stack_below`` rows or more in the frame keeps its own session: there a call's fixed cost is
small and the plain model a little faster per row).  Each stacked model is checked against its
segments' own sessions on probe rows at load (:data:`STACK_TOLERANCE`); those sessions stay the
reference path (``batched=False``) and run whatever does not stack.

:class:`OnnxTransfer` is the engine (sessions and packed inference, no OpenGL); :class:`OnnxBackend`
puts it behind :class:`prt.runtime.backends.TransferBackend`.  :meth:`OnnxTransfer.compute` keeps the
pixel-ordered contract for callers with their own arrays (benchmarks); :meth:`OnnxTransfer.compute_reference`
is the pre-counting-sort path it is tested against.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .. import sh
from ..checks import positive_int
from ..errors import ArgumentTypeError, InputError
from ..interpolation import TransferInterpolator, check_tolerance
from ..onnxfile import read_model
from ..onnx_stack import block_layout, read_network, stack_key, stacked_model
from ..segmentation import segment_sort, segment_sort_reference
from .base import CpuTransfer, TransferBackend

__all__ = ["OnnxBackend", "OnnxTransfer", "default_providers", "check_providers", "PROVIDERS_ENV", "segment_sort", "segment_sort_reference"]


PROVIDERS_ENV = "PRT_ONNX_PROVIDERS"
"""Environment variable with the ONNX Runtime providers of renderers that name none (comma-separated,
e.g. ``cuda,cpu``), for embedders."""

PROVIDER_NAMES = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider", "tensorrt": "TensorrtExecutionProvider",
                  "trt": "TensorrtExecutionProvider", "rocm": "ROCMExecutionProvider", "openvino": "OpenVINOExecutionProvider",
                  "dml": "DmlExecutionProvider", "coreml": "CoreMLExecutionProvider"}  # fmt: skip
"""Short names accepted for ONNX Runtime's execution providers (the full names are accepted too)."""

GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "ROCMExecutionProvider", "DmlExecutionProvider")
"""Providers that run the networks on a GPU: a segment's rows go in one call, bound in and out
(I/O binding), instead of the CPU's cache-sized slices on a pool of threads."""


def default_providers() -> list[str]:
    """CUDA first where onnxruntime has it, then CPU.  TensorRT is used only when asked for
    (``--onnx-providers tensorrt,cuda,cpu``): it builds an engine per new input shape, and a
    segment's row count changes with every view."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in available]


def check_providers(providers, origin: str = "providers") -> list[str] | None:
    """The providers to use: ``providers`` (a list of names, short or full; or one comma-separated
    string), else the environment variable :data:`PROVIDERS_ENV`, else None (:func:`default_providers`).

    Raises
    ------
    ArgumentTypeError
        Not a list of strings.
    InputError
        A provider this onnxruntime lacks (CUDA where there is none, say): one line naming it and
        the providers there are.
    """
    if providers is None:
        env = os.environ.get(PROVIDERS_ENV, "").strip()
        if not env:
            return None
        providers, origin = env, PROVIDERS_ENV
    if isinstance(providers, str):
        providers = [p.strip() for p in providers.split(",") if p.strip()]
    if not isinstance(providers, (list, tuple)) or not all(isinstance(p, str) for p in providers):
        raise ArgumentTypeError(f"{origin}: expected a list of provider names, got {providers!r}")
    import onnxruntime as ort

    available = ort.get_available_providers()
    names = [PROVIDER_NAMES.get(p.lower(), p) for p in providers]
    missing = [p for p in names if p not in available]
    if missing or not names:
        hint = "; install onnxruntime-gpu on a machine with a CUDA GPU" if any(p in GPU_PROVIDERS for p in missing) else ""
        raise InputError(f"{origin}: {', '.join(missing) or 'none given'} not available (this onnxruntime {ort.__version__} has "
                         f"{', '.join(available)}){hint}")  # fmt: skip
    return list(dict.fromkeys(names))


class OnnxTransfer:
    """The networks of a scene as ONNX Runtime sessions.

    Parameters
    ----------
    manifest : prt.runtime.manifest.Manifest
    providers : execution providers in order of preference (default: CUDA if present, CPU)
    threads : concurrent inference calls (default: all cores)
    slice_rows : rows per inference call (small enough that activations stay in cache)
    bound : run each segment's rows in one call with I/O binding (input bound from, output bound into
        the transfer array; no slices, no pool).  None (default): where the first provider runs on a
        GPU (:data:`GPU_PROVIDERS`), whose calls cost a launch and a copy each.  True on the CPU tests
        the path against the sliced one.
    batched : evaluate the segments of one architecture together, one stacked model per architecture
        (:mod:`prt.runtime.onnx_stack`: rows in blocks of ``block_rows``, a grouped GEMM), so a frame
        costs one call per architecture and slice, not per segment.  Default True; False (or a scene
        whose networks do not stack: grid, shape-conditioned, other formats) runs one session per
        segment, the reference path.  The attribute can be switched between frames.
    block_rows : rows per block of the stacked models (a segment's last block is padded)
    stack_below : a segment with at least this many rows in a frame runs its own session even when
        stacked (a call's fixed cost is small beside its rows, and the plain Gemm model is a little
        faster per row than the stacked one); the rest of its stack runs in the stacked calls
    """

    def __init__(self, manifest, providers=None, threads: int | None = None, slice_rows: int = 4096, bound: bool | None = None,
                 batched: bool = True, block_rows: int = 64, stack_below: int = 1024):  # fmt: skip
        self.bands = manifest.sh_bands
        # Outputs per row: bands^2, or 4 bands^2 with interreflection (direct, indirect R, G, B)
        self.n = getattr(manifest, "transfer_width", self.bands * self.bands)
        self.providers = list(providers) if providers else default_providers()
        self.threads = positive_int(threads, "threads") if threads is not None else (os.cpu_count() or 1)
        self.slice_rows = int(slice_rows)
        self.sessions: dict[int, object] = {}
        self.input_names: dict[int, str] = {}
        self.code: np.ndarray | None = None  # deformable scenes: (1, d) float32, the frame's shape code (set_code)
        self._coded: set[int] = set()  # segments whose model takes the code
        self.models: dict[int, object] = {}  # segment id -> model path, for messages
        self.analytic: set[int] = set()
        self.segment_count = len(manifest.segments)
        data: dict[int, bytes] = {}
        for seg in manifest.segments:
            if seg.kind == "analytic":
                self.analytic.add(seg.id)
                continue
            model = read_model(seg.model)  # refuses external data (files outside the scene folder)
            self.sessions[seg.id], self.input_names[seg.id] = self._open(model, seg.model)
            self.models[seg.id] = seg.model
            data[seg.id] = model
            if len(self.sessions[seg.id].get_inputs()) == 2:
                self._coded.add(seg.id)
        self.block_rows = positive_int(block_rows, "block_rows")
        self.stack_below = positive_int(stack_below, "stack_below")
        self.stacks: list[_Stack] = []
        self.stack_notes: list[str] = []  # why a group of segments did not stack (probe mismatch)
        self._stack_of = np.full(self.segment_count, -1, np.intp)
        self._stack_member = np.full(self.segment_count, -1, np.intp)
        self._build_stacks(data)
        self.batched = bool(batched)
        first = next(iter(self.sessions.values())).get_providers()[0] if self.sessions else "CPUExecutionProvider"
        self.bound = first in GPU_PROVIDERS if bound is None else bool(bound)
        self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="ort") if self._concurrent_slices() else None
        self.calls = 0  # network invocations so far (tests check relighting makes none)
        self.timings: dict[str, float] = {}

    def _open(self, model: bytes, path):
        """(session, input name) of one checked ONNX model (``path`` for messages)."""
        import onnxruntime as ort

        try:
            sess = ort.InferenceSession(model, self._session_options(), providers=self.providers)
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph types
            msg = " ".join(str(exc).split())[:200]
            raise InputError(f"{path}: cannot load ONNX model ({msg})") from None
        return sess, _check_signature(sess, path, self.n)

    def _session_options(self):
        """One intra-op thread per call, no spinning: parallelism comes from concurrent slices."""
        import onnxruntime as ort

        if not hasattr(self, "_options"):
            opts = ort.SessionOptions()
            opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            opts.intra_op_num_threads = 1  # parallelism comes from concurrent slices
            opts.inter_op_num_threads = 1
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
            opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
            self._options = opts
        return self._options

    def _build_stacks(self, data: dict[int, bytes]) -> None:
        """One stacked model per group of segments that share an architecture (two or more), each
        checked against the segments' own sessions on probe rows before it is used."""
        groups: dict[tuple, list[tuple[int, dict]]] = {}
        for s, model in data.items():
            if s in self._coded:
                continue
            read = read_network(model)
            key = stack_key(*read) if read is not None else None
            if key is not None:
                groups.setdefault(key, []).append((s, read[0]))
        for members in groups.values():
            if len(members) < 2:
                continue
            segments = np.array([s for s, _ in members], np.intp)
            try:
                sess = self._stack_session(stacked_model([a for _, a in members]))
            except InputError as exc:
                self.stack_notes.append(f"segments {segments[0]}..{segments[-1]}: not stacked ({exc})")
                continue
            stack = _Stack(sess, segments)
            worst = self._probe(stack, [a for _, a in members])
            if worst > STACK_TOLERANCE:
                self.stack_notes.append(f"segments {segments[0]}..{segments[-1]}: the stacked model differs from their "
                                        f"own by {worst:.2g} on probe rows; one session each")  # fmt: skip
                continue
            self._stack_of[segments] = len(self.stacks)
            self._stack_member[segments] = np.arange(len(segments))
            self.stacks.append(stack)

    def _stack_session(self, model: bytes):
        import onnxruntime as ort

        try:
            return ort.InferenceSession(model, self._session_options(), providers=self.providers)
        except Exception as exc:  # onnxruntime's own types
            raise InputError(" ".join(str(exc).split())[:200]) from None

    def _probe(self, stack, arrays: list[dict], rows: int = 4) -> float:
        """Largest difference, relative to max(1, |output|), between the stacked model and each
        member's own session on ``rows`` rows in and around the member's box."""
        rng = np.random.default_rng(0)
        x = np.empty((len(arrays), rows, 6), np.float32)
        for j, a in enumerate(arrays):
            x[j, :, :3] = a["enc_centre"] + rng.uniform(-1.2, 1.2, (rows, 3)) / a["enc_inv_half"]
            x[j, :, 3:] = rng.normal(size=(rows, 3))
        y = stack.session.run(None, {"x": x, "seg": np.arange(len(arrays), dtype=np.int64)})[0]
        worst = 0.0
        for j, s in enumerate(stack.segments):
            ref = self._infer(int(s), x[j])
            worst = max(worst, float(np.abs(y[j] - ref).max() / max(1.0, float(np.abs(ref).max()))))
        return worst

    def _concurrent_slices(self) -> bool:
        """Whether slices run on a pool of threads (else one after another, the engine's own threads inside)."""
        return self.threads > 1 and not self.bound

    def _infer_into(self, s: int, rows: np.ndarray, out: np.ndarray) -> None:
        """Segment ``s``'s network on ``rows`` (R, 6) written into ``out`` (R, n), C-contiguous float32,
        through I/O binding: on a GPU provider the engine copies the rows in and the transfer out
        itself, no intermediate arrays."""
        sess = self.sessions[s]
        io = sess.io_binding()
        io.bind_cpu_input(self.input_names[s], rows)
        if s in self._coded:
            if self.code is None:
                raise InputError(f"{self.models[s]}: the network takes a shape code; set one first (Renderer.set_deformation)")
            io.bind_cpu_input("code", self.code)
        io.bind_output(sess.get_outputs()[0].name, "cpu", 0, np.float32, list(out.shape), out.ctypes.data)
        try:
            sess.run_with_iobinding(io)
        except Exception as exc:  # the engine's own error types
            raise InputError(f"{self.models[s]}: inference failed ({' '.join(str(exc).split())[:200]})") from None

    def set_code(self, theta) -> None:
        """The shape code (d,) every shape-conditioned network takes from now on."""
        self.code = np.ascontiguousarray(np.asarray(theta, np.float32).reshape(1, -1))

    def _infer(self, s: int, rows: np.ndarray) -> np.ndarray:
        """Segment ``s``'s network on ``rows`` (R, 6) (and the shape code, for a deformable scene's)."""
        if s in self._coded:
            if self.code is None:
                raise InputError(f"{self.models[s]}: the network takes a shape code; set one first (Renderer.set_deformation)")
            return self.sessions[s].run(None, {self.input_names[s]: rows, "code": self.code})[0]
        return self.sessions[s].run(None, {self.input_names[s]: rows})[0]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        self.sessions.clear()

    def infer_sorted(self, x: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Transfer of rows grouped by segment (as :func:`segment_sort` lists them).

        Parameters
        ----------
        x : (M, 6) float32, C-contiguous, position xyz and normal xyz per row
        offsets : (S + 1,) int, segment ``s`` owns rows ``offsets[s]:offsets[s + 1]``

        Returns
        -------
        transfer : (M, n) float32, row for row
        Timings (ms) of the last call are in ``self.timings``: inference.
        """
        t0 = time.perf_counter()
        transfer = np.empty((len(x), self.n), dtype=np.float32)
        jobs, bound_calls = [], 0
        offsets = np.asarray(offsets)
        present = np.flatnonzero(offsets[1:] != offsets[:-1])
        stacked = 0
        if self.batched and self.stacks:
            known = present[present < self.segment_count]
            small = offsets[known + 1] - offsets[known] < self.stack_below
            chosen = known[(self._stack_of[known] >= 0) & small]
            stacked = self._infer_stacked(x, offsets, chosen, transfer)
            present = np.setdiff1d(present, chosen, assume_unique=True)
        for s in present.tolist():
            lo, hi = int(offsets[s]), int(offsets[s + 1])
            if s in self.analytic:
                self._analytic(transfer, slice(lo, hi), x[lo:hi, 3:6])
                continue
            if s not in self.sessions:
                raise InputError(f"segment {s} appears in the G-buffer but the scene has no such segment")
            if self.bound:  # one call per segment, into its block of the result
                self._infer_into(s, x[lo:hi], transfer[lo:hi])
                bound_calls += 1
                continue
            # The same slices as the pixel-ordered path: each segment's rows cut from its start.
            jobs += [(s, x[a : min(a + self.slice_rows, hi)], a) for a in range(lo, hi, self.slice_rows)]
        self.calls += bound_calls > 0 or (stacked > 0 and not jobs)  # a frame's calls count once, as in _run
        results = self._run([(s, None, rows, 0) for s, rows, _ in jobs])
        for (_, rows, a), y in zip(jobs, results):
            transfer[a : a + len(rows)] = y
        self.timings = {"inference": 1e3 * (time.perf_counter() - t0)}
        return transfer

    def _infer_stacked(self, x: np.ndarray, offsets: np.ndarray, segments: np.ndarray, transfer: np.ndarray) -> int:
        """The stacked models on the rows of ``segments`` (ascending, each with rows, each in a stack),
        written into ``transfer``: each stack's blocks cut into calls of about ``slice_rows`` rows
        (one call per stack on a GPU provider), run on the pool.  Returns the number of calls."""
        if not len(segments):
            return 0
        tasks = []
        B = self.block_rows
        per_call = len(x) if self.bound else max(1, self.slice_rows // B)
        group = self._stack_of[segments]
        for g in np.unique(group).tolist():
            stack, segs = self.stacks[g], segments[group == g]
            source, member, valid = block_layout(offsets[segs], offsets[segs + 1] - offsets[segs], B)
            seg = self._stack_member[segs][member].astype(np.int64)
            cuts = np.searchsorted(valid, np.arange(0, len(member) + per_call, per_call) * B)  # valid slots per call
            for c, k0 in enumerate(range(0, len(member), per_call)):
                k1 = min(k0 + per_call, len(member))
                tasks.append((stack, source[k0:k1], seg[k0:k1], valid[cuts[c] : cuts[c + 1]] - k0 * B))

        def run(task):
            stack, src, seg, slots = task
            try:
                y = stack.session.run(None, {"x": x[src], "seg": seg})[0]
            except Exception as exc:  # the engine's own error types
                raise InputError(f"{self.models[int(stack.segments[seg[0]])]} (stacked with its architecture's segments): "
                                 f"inference failed ({' '.join(str(exc).split())[:200]})") from None  # fmt: skip
            transfer[src.reshape(-1)[slots]] = y.reshape(-1, self.n)[slots]

        if self._pool is None:
            for task in tasks:
                run(task)
        else:
            list(self._pool.map(run, tasks))
        return len(tasks)

    def compute(self, inputs: np.ndarray, segment: np.ndarray, columns=(0, 1, 2, 3, 4, 5)):
        """Transfer of every covered pixel, in pixel order (the counting sort, then one scatter).

        Parameters and results as :meth:`compute_reference`, which it equals exactly.
        """
        t0 = time.perf_counter()
        order, offsets = segment_sort(segment, self.segment_count)  # InputError for an id the scene lacks
        x = np.ascontiguousarray(np.take(inputs, order, axis=0)[:, list(columns)])
        t1 = time.perf_counter()
        packed = self.infer_sorted(x, offsets)
        t2 = time.perf_counter()
        covered = np.sort(order)
        transfer = np.empty_like(packed)
        transfer[np.searchsorted(covered, order)] = packed
        t3 = time.perf_counter()
        self.timings = {"pack": 1e3 * (t1 - t0), "inference": 1e3 * (t2 - t1), "scatter": 1e3 * (t3 - t2)}
        return covered, transfer

    def compute_reference(self, inputs: np.ndarray, segment: np.ndarray, columns=(0, 1, 2, 3, 4, 5)):
        """Transfer of every covered pixel (the plain path: one pass per segment, then a scatter).

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
                self._analytic(transfer, rows, x[:, 3:6])
        t3 = time.perf_counter()
        self.timings = {"pack": 1e3 * (t1 - t0), "inference": 1e3 * (t2 - t1), "scatter": 1e3 * (t3 - t2)}
        return covered, transfer

    def _analytic(self, transfer: np.ndarray, rows, normals: np.ndarray) -> None:
        """Unshadowed transfer into ``transfer[rows]``; no interreflected light (indirect part 0)."""
        n = self.bands * self.bands
        transfer[rows, :n] = sh.unshadowed_transfer(normals, self.bands, dtype=np.float32)
        if self.n > n:
            transfer[rows, n:] = 0.0

    def _run(self, jobs):
        if not jobs:
            return []
        self.calls += 1

        def run(job):
            s, _, x, a = job
            rows = x[a : a + self.slice_rows]
            try:
                y = self._infer(s, rows)
            except Exception as exc:  # the engine's own error types
                raise InputError(f"{self.models[s]}: inference failed ({' '.join(str(exc).split())[:200]})") from None
            if not isinstance(y, np.ndarray) or y.shape != (len(rows), self.n) or y.dtype != np.float32:
                what = f"{getattr(y, 'shape', '?')} {getattr(y, 'dtype', type(y).__name__)}"
                raise InputError(f"{self.models[s]}: the model gave {what} for {len(rows)} rows, expected ({len(rows)}, {self.n}) float32")
            return y

        if self._pool is None:
            return [run(j) for j in jobs]
        return list(self._pool.map(run, jobs))


STACK_TOLERANCE = 1e-4
"""Largest difference, relative to max(1, |transfer|), a stacked model may show against its segments'
own sessions on the probe rows (float rounding of other GEMM kernels is ~1e-7)."""


class _Stack:
    """A stacked model (:mod:`prt.runtime.onnx_stack`) and the segment ids it holds, in stack order."""

    def __init__(self, session, segments: np.ndarray):
        self.session, self.segments = session, segments


class OnnxBackend(TransferBackend):
    """:class:`OnnxTransfer` on the G-buffer's targets: the transfer comes back on the CPU, in packed
    (segment-sorted) order, with the covered pixel of each row.

    Timings: ``readback`` (the two targets), ``pack`` (counting sort and gather), ``inference``.
    """

    name = "onnx"
    on_cpu = True

    def __init__(self, ctx, manifest, *, providers=None, threads: int | None = None, interpolate: float | None = None):
        super().__init__(ctx, manifest)
        self.engine = OnnxTransfer(manifest, providers=providers, threads=threads)
        self.interpolate = check_tolerance(interpolate, "interpolate")
        self.fraction = 1.0  # share of the covered pixels of the last frame that ran a network
        self._sampler = TransferInterpolator(self.interpolate, self.engine.threads) if self.interpolate is not None else None

    def run(self, gbuffer, target) -> CpuTransfer:
        t0 = time.perf_counter()
        position, normal = gbuffer.read_targets()  # (H, W, 4) each, top row first, no copy
        t1 = time.perf_counter()
        if self.interpolate is not None:
            return self._run_interpolated(position, normal, 1e3 * (t1 - t0))
        height, width = position.shape[:2]
        # The segment channel, top row first (a contiguous copy); ids are exact small integers.
        wide = self.engine.segment_count > 1 << 15
        segment = normal[..., 3].astype(np.int32 if wide else np.int16).reshape(-1)
        order, offsets = segment_sort(segment, self.engine.segment_count)
        # The targets keep GL's row order (bottom first): pixel i of the image is row (H-1 - i//W) there.
        gl_rows = order + width * (height - 1) - 2 * width * (order // width)
        raw = (position[::-1].reshape(-1, 4), normal[::-1].reshape(-1, 4))  # views of the read-back
        x = np.empty((len(order), 6), dtype=np.float32)
        # Whole-row takes (far faster than [rows, 0:3]), then xyz moved as one 12-byte item per row (a
        # 3-float column copy goes float by float); no temporary outlives its line (malloc reuses it).
        xyz = x.view("V12")  # (M, 2): pos.xyz, n.xyz
        xyz[:, 0] = np.take(raw[0], gl_rows, axis=0).view(np.uint8)[:, :12].view("V12")[:, 0]
        xyz[:, 1] = np.take(raw[1], gl_rows, axis=0).view(np.uint8)[:, :12].view("V12")[:, 0]
        t2 = time.perf_counter()
        transfer = self.engine.infer_sorted(x, offsets)
        self.timings = {"readback": 1e3 * (t1 - t0), "pack": 1e3 * (t2 - t1), **self.engine.timings}
        return CpuTransfer(order, transfer, x, segment[order])

    def _run_interpolated(self, position, normal, readback_ms: float) -> CpuTransfer:
        """The networks on a coarse grid and where interpolation is unsafe (:mod:`prt.runtime.interpolation`)."""
        network = [0.0]

        def infer(rows: np.ndarray, offsets: np.ndarray) -> np.ndarray:
            if len(offsets) - 1 > self.engine.segment_count:
                raise InputError(f"segment {len(offsets) - 2} appears in the G-buffer but the scene has no such segment")
            t = time.perf_counter()
            out = self.engine.infer_sorted(rows, offsets)
            network[0] += time.perf_counter() - t
            return out

        timings: dict[str, float] = {}
        result = self._sampler.run(position, normal, infer, self.engine.n, timings)
        self.fraction = result.fraction
        self.timings = {"readback": readback_ms, "pack": timings["pack"], "inference": 1e3 * network[0], "interpolate": timings["interpolate"]}
        return CpuTransfer(result.covered, result.transfer, result.inputs, result.segment)

    def set_code(self, theta) -> None:
        self.engine.set_code(theta)

    def release(self) -> None:
        self.engine.close()
        if self._sampler is not None:
            self._sampler.close()


def _check_signature(sess, path, n_out: int) -> str:
    """The name of the model's first input, after checking it is float32 [N, 6] (a shape-conditioned
    network's second input: ``code`` float32 [1, d]) and its one output float32 [N, n_out]."""
    inputs, outputs = sess.get_inputs(), sess.get_outputs()

    def fits(args, width):
        a = args[0]
        return len(args) == 1 and a.type == "tensor(float)" and len(a.shape) == 2 and a.shape[1] == width

    code = inputs[1:2]
    coded = len(inputs) == 2 and code[0].name == "code" and code[0].type == "tensor(float)" and len(code[0].shape) == 2 and code[0].shape[0] == 1
    if not fits(inputs[:1] if coded else inputs, 6):
        got = [(i.name, i.type, i.shape) for i in inputs]
        raise InputError(f"{path}: model input must be one float32 tensor [N, 6] (position, normal), and for a deformable scene code [1, d]; got {got}")
    if not fits(outputs, n_out):
        got = [(o.name, o.type, o.shape) for o in outputs]
        raise InputError(f"{path}: model output must be one float32 tensor [N, {n_out}], got {got}")
    return inputs[0].name
