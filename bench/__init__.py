"""prt.bench: speed against error of the PRT renderer (the ``prt-bench`` command).

Needs the ``train`` extra (ray tracing the reference, ONNX variants, SSIM); may import
train, export and runtime (never the other way round).

- :mod:`~prt.bench.scene_bench`  :class:`Settings`, :class:`SceneBench` (every configuration of one
  scene), :func:`run` (every scene: the report)
- :mod:`~prt.bench.reference`    the ray-traced reference, its cache and its noise
- :mod:`~prt.bench.quiet_reference`  its rays raised (direct and bounce) until its noise clears what it judges
- :mod:`~prt.bench.mitsuba_reference`, :mod:`~prt.bench.mitsuba_compare`, :mod:`~prt.bench.mitsuba_bench`
  Mitsuba 3 as an independent reference (``--reference mitsuba``)
- :mod:`~prt.bench.metrics`      PSNR, SSIM, MAE of tone-mapped images; the FPS-PSNR Pareto front
- :mod:`~prt.bench.machine`      float32 GEMM limit (numpy, ONNX Runtime), CPU, load, network profile
- :mod:`~prt.bench.vertex_prt`   the per-vertex PRT baseline (Sloan et al. 2002)
- :mod:`~prt.bench.probe_grid`, :mod:`~prt.bench.probe_bench`  the engines' baseline: an L2 SH irradiance probe grid
- :mod:`~prt.bench.cameras`      ``--cameras``: views from a JSON file
- :mod:`~prt.bench.exposure`     ``--exposure auto``: the reference frame's auto exposure
- :mod:`~prt.bench.leak`         light leaking as a figure
- :mod:`~prt.bench.packing`      every network on every pixel against the packed path
- :mod:`~prt.bench.report`       JSON keys, Markdown, plot, error maps, scene checkpoints
- :mod:`~prt.bench.cli`          ``prt-bench`` (:func:`~prt.bench.cli.main`)
- :mod:`~prt.bench.segment_study`  helpers of the per-segment ONNX studies in ``studies/``

The precision variants (fp16, fp16-mlp, int8) are built by :mod:`prt.export.precision`.
Study scripts (paper table, int8, graph folding, stage timings) live in ``studies/``
of a checkout and are not installed.
"""

import importlib

__all__ = ["Settings", "SceneBench", "run", "markdown", "plot", "image_metrics", "pareto_front"]

# Loaded on first use (PEP 562), so that ``prt-bench`` (:mod:`prt.bench.cli`) can report a missing
# [train] extra in one line before anything imports scipy, scikit-image or trimesh.
_LAZY = {
    "image_metrics": ".metrics", "pareto_front": ".metrics", "markdown": ".report", "plot": ".report",
    "SceneBench": ".scene_bench", "Settings": ".scene_bench", "run": ".scene_bench",
}  # fmt: skip


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value
