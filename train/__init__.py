"""prt.train: from geometry to ground-truth transfer to fitted networks (exported by prt.export).

May use torch, trimesh and embreex; install with ``pip install "prt-runtime[train]"``.

- :func:`load_geometry`     mesh file or built-in SDF scene -> :class:`Geometry` (scene units)
- :func:`sample_surface`    area-uniform surface samples (:class:`SurfaceSamples`)
- :func:`compute_transfer`  ray-traced SH transfer at any surface points
- :func:`segment_samples`   object/spatial split, CPCA-style merging, seam margins
- :func:`run_precompute`    the whole stage, resumable, on disk (CLI: ``prt-precompute``,
                            :mod:`prt.train.precompute_cli`)
- :mod:`prt.train.build`    precompute -> fit -> export, cached (CLI: ``prt-train``,
                            :mod:`prt.train.train_cli`); imports torch, so not loaded here

Subpackages by stage: :mod:`.inputs` (geometry, materials, UVs, samples), :mod:`.transport`
(ray-traced transfer, precompute, bounces, transfer textures), :mod:`.networks` (segments,
networks, fitting, right-sizing), :mod:`.deform` (deformable objects), :mod:`.sdf` (SDF scenes
and neural SDFs).  The build's driver, commands, caches and executors sit at the top.
"""

import importlib

# Loaded on first use (PEP 562), so that ``prt.train.entry`` can report a missing [train] extra
# in one line before anything imports trimesh, embreex or torch.
_LAZY = {
    "Geometry": ".inputs.geometry", "load_geometry": ".inputs.geometry",
    "PrecomputeSettings": ".transport.precompute", "load_precompute": ".transport.precompute", "run_precompute": ".transport.precompute",
    "SurfaceSamples": ".inputs.sampling", "sample_surface": ".inputs.sampling",
    "Segmentation": ".networks.segments", "segment_samples": ".networks.segments",
    "compute_transfer": ".transport.transfer",
}  # fmt: skip


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


__all__ = [
    "Geometry",
    "load_geometry",
    "SurfaceSamples",
    "sample_surface",
    "compute_transfer",
    "Segmentation",
    "segment_samples",
    "PrecomputeSettings",
    "run_precompute",
    "load_precompute",
]
