"""The packing baseline: every network on every pixel (naive) against covered pixels by segment (packed).

The naive path gives each network segment's session all H*W pixels and picks the right one per
pixel afterwards; the packed path (the renderer's) runs only the covered pixels, batched by
segment.  Both run through :class:`prt.runtime.backends.onnx.OnnxTransfer`.
"""

from __future__ import annotations

import numpy as np

from prt.bench.machine import profile_network
from prt.runtime.gbuffer import PACKED_COLUMNS
from prt.runtime.backends.onnx import OnnxTransfer

__all__ = ["naive_transfer", "packing_baseline"]


def naive_transfer(onnx, packed: np.ndarray, segment: np.ndarray):
    """Every network segment's model on every pixel, the right one picked per pixel afterwards.

    Parameters
    ----------
    onnx : prt.runtime.backends.onnx.OnnxTransfer
    packed : (P, 8) float32
        The packed G-buffer (all pixels, background included).
    segment : (P,) int
        Segment id per pixel, -1 on background.

    Returns
    -------
    transfer : (P, 16) float32
        Zero on background.
    inference_ms : float
        Total network time.
    rows_per_segment : dict of int to int
        Rows each network segment's model ran on (always P).
    """
    transfer = np.zeros((len(packed), onnx.n), dtype=np.float32)
    inference_ms, rows_per_segment = 0.0, {}
    for s in onnx.sessions:
        rows, values = onnx.compute(packed, np.full(len(packed), s, dtype=np.int32), columns=PACKED_COLUMNS)
        inference_ms += onnx.timings["inference"]
        rows_per_segment[s] = len(rows)
        mine = segment == s
        transfer[mine] = values[mine]
    for s in onnx.analytic:  # no network: the analytic segments cost the same either way
        mine = np.flatnonzero(segment == s)
        _, values = onnx.compute(packed[mine], np.full(len(mine), s, dtype=np.int32), columns=PACKED_COLUMNS)
        transfer[mine] = values
    return transfer, inference_ms, rows_per_segment


def packing_baseline(manifest, gbuffer_pass, cameras, log) -> dict:
    """Naive (all pixels through every network) against packed (covered pixels, by segment).

    Parameters
    ----------
    manifest : Manifest
    gbuffer_pass : prt.runtime.gbuffer.GBufferPass
        At the resolution to measure.
    cameras : list of Camera
    log : callable

    Returns
    -------
    dict
        See the module docstring (``scenes[].packing[]``).
    """
    onnx = OnnxTransfer(manifest)
    naive_ms, packed_ms, covered_counts, diffs, rows = [], [], [], [], {}
    profile = None
    try:
        for i, camera in enumerate([cameras[0], *cameras]):  # the first pass warms the sessions up
            gbuffer_pass.render(camera)
            packed = gbuffer_pass.read_packed().copy()
            segment = packed[:, 7].astype(np.int32)
            covered, transfer = onnx.compute(packed, segment, columns=PACKED_COLUMNS)
            packed_time = onnx.timings["inference"]
            everywhere, naive_time, rows = naive_transfer(onnx, packed, segment)
            if i == 0:
                continue
            if profile is None:  # the first measured view: its largest network segment, one slice
                seg_cov = segment[covered]
                ids, counts = np.unique(seg_cov[np.isin(seg_cov, list(onnx.sessions))], return_counts=True)
                if len(ids):
                    s = int(ids[np.argmax(counts)])
                    x = packed[covered[seg_cov == s]][:, list(PACKED_COLUMNS)][: onnx.slice_rows]
                    model = next(seg.model for seg in manifest.segments if seg.id == s)
                    profile = {"segment": s, **profile_network(model, x)}
            packed_ms.append(packed_time)
            naive_ms.append(naive_time)
            covered_counts.append(len(covered))
            diffs.append(float(np.abs(everywhere[covered] - transfer).max(initial=0.0)))
    finally:
        onnx.close()
    all_pixels = gbuffer_pass.width * gbuffer_pass.height
    covered = float(np.median(covered_counts))
    naive, packed = float(np.median(naive_ms)), float(np.median(packed_ms))  # medians over the views
    result = {
        "resolution": f"{gbuffer_pass.width}x{gbuffer_pass.height}",
        "all_pixels": all_pixels,
        "covered_pixels": covered,
        "network_segments": len(rows),
        "naive_rows_per_segment": {str(s): n for s, n in rows.items()},
        "naive_total_rows": int(sum(rows.values())),
        "naive_inference_ms": round(naive, 3),
        "packed_inference_ms": round(packed, 3),
        "packing_speedup": round(naive / packed, 2) if packed > 0 else None,
        "pixel_ratio": round(all_pixels / covered, 2) if covered else None,
        "work_ratio": round(sum(rows.values()) / covered, 2) if covered else None,
        "naive_max_abs_diff": float(max(diffs, default=0.0)),
        "packing_views": len(packed_ms),
        "network_profile": profile,
    }
    log(
        f"  packing {result['resolution']}: naive {naive:.1f} ms ({len(rows)} x {all_pixels} rows) vs packed "
        f"{packed:.1f} ms ({covered:.0f} rows): {result['packing_speedup']}x; all/covered pixels {result['pixel_ratio']}x"
    )
    return result
