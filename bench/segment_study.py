"""Shared by the per-segment ONNX studies (``studies/int8_static.py``, ``onnx_graph_fold.py``).

A scene built by ``prt-train`` keeps its training and held-out samples in ``precompute/``
beside ``scene.json``; these helpers read them, give each network segment its own samples,
open one-thread ONNX Runtime sessions, and time several versions of a model alternately so
that machine noise hits them alike.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from prt.runtime.errors import PRTError
from prt.runtime.files import atomic_write_json
from prt.runtime.manifest import load_manifest

__all__ = ["StudyError", "SegmentSamples", "study_parser", "network_segments", "session", "interleaved_ms", "write_report"]


class StudyError(Exception):
    """Bad input to a study: one line for the user, exit status 2."""


@dataclass
class SegmentSamples:
    segment: object  # prt.runtime.manifest segment (kind "network")
    train: np.ndarray  # (n, 6) float32 position + normal, the segment's training samples
    held: np.ndarray  # (m, 6) float32, its held-out samples
    held_transfer: np.ndarray  # (m, bands^2) ray-traced ground truth of ``held``


def study_parser(description: str) -> argparse.ArgumentParser:
    """The options every per-segment study takes: the scene, rows per call, repeats, the JSON report."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("scene", type=Path)
    p.add_argument("--rows", type=int, default=4096, help="rows per call (the runtime's slice)")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--json", type=Path, default=None)
    return p


def network_segments(scene: Path):
    """Every network segment of ``scene`` with its own samples (those with none are skipped)."""
    try:
        manifest = load_manifest(scene)
    except PRTError as exc:
        raise StudyError(str(exc)) from None
    pre = Path(scene).parent / "precompute"
    if not (pre / "samples.npz").is_file():
        raise StudyError(f"{pre}/samples.npz: not found (a scene built by prt-train keeps it)")
    samples, valid = np.load(pre / "samples.npz"), np.load(pre / "validation.npz")
    x_train = np.concatenate([samples["points"], samples["normals"]], axis=1).astype(np.float32)
    x_valid = np.concatenate([valid["points"], valid["normals"]], axis=1).astype(np.float32)
    out = []
    for seg in manifest.segments:
        if seg.kind != "network":
            continue
        own = np.flatnonzero(samples["segment"] == seg.id)
        held = np.flatnonzero(valid["segment"] == seg.id)
        if len(own) and len(held):
            out.append(SegmentSamples(seg, x_train[own], x_valid[held], valid["transfer"][held]))
    if not out:
        raise StudyError(f"{scene}: no network segment with samples")
    return out


def session(model):
    """A one-thread CPU session of an ONNX file (path) or serialised model (bytes)."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(model if isinstance(model, bytes) else str(model), opts, providers=["CPUExecutionProvider"])


def interleaved_ms(sessions: dict, x: np.ndarray, repeats: int) -> dict[str, float]:
    """Median milliseconds per call of each session on ``x``, the sessions taking turns."""
    for s in sessions.values():
        s.run(None, {"x": x})  # warm-up
    times = {k: [] for k in sessions}
    for _ in range(repeats):
        for k, s in sessions.items():
            t0 = time.perf_counter()
            s.run(None, {"x": x})
            times[k].append(time.perf_counter() - t0)
    return {k: 1e3 * float(np.median(v)) for k, v in times.items()}


def write_report(path: Path | None, scene: Path, rows: int, repeats: int, segments: list, median: dict) -> None:
    """The study's JSON report (atomically), when ``path`` is given."""
    if path is None:
        return
    atomic_write_json(path, {"scene": str(scene), "rows": rows, "repeats": repeats, "threads": 1,
                             "onnxruntime": ort.__version__, "segments": segments, "median": median})  # fmt: skip
