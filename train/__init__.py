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
"""

from .geometry import Geometry, load_geometry
from .precompute import PrecomputeSettings, load_precompute, run_precompute
from .sampling import SurfaceSamples, sample_surface
from .segments import Segmentation, segment_samples
from .transfer import compute_transfer

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
