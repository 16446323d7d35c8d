"""``prt-train MESH --neural-sdf``: fit the mesh's SDF network first, then build it as an SDF scene.

The network goes into the scene folder as ``<stem>.sdf.onnx`` (with ``neural_sdf.json``,
its settings, timings and geometric error); the build then loads that file as its geometry
(:func:`prt.train.inputs.geometry.load_geometry` knows ``*.sdf.onnx``), so precompute, fitting and
export follow the SDF path unchanged.  Rerunning the same command reuses the network.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ...runtime.errors import GeometryError, InputError
from ...runtime.files import atomic_write_json

__all__ = ["prepare_neural_sdf", "require_torch"]

REPORT = "neural_sdf.json"


def require_torch() -> None:
    """One-line InputError when the train extra (torch) is missing."""
    try:
        import torch  # noqa: F401
    except ModuleNotFoundError:
        raise InputError("--neural-sdf needs torch: pip install 'prt-runtime[train]'") from None


def prepare_neural_sdf(mesh_path, out_dir, *, size=(64, 4), samples: int = 200_000, steps: int = 3000, seed: int = 0,
                       pos_freqs: int = 0, log=print) -> Path:  # fmt: skip
    """Fit (or reuse) the SDF network of a mesh file into ``out_dir``; return the ``.sdf.onnx`` path.

    The mesh is normalised as for a mesh build, then scaled by ``SCENE_FILL`` so the zero
    set keeps a margin inside the SDF scene box.
    """
    require_torch()
    from ..inputs.geometry import load_geometry
    from .neural import NEURAL_SDF_SUFFIX, SCENE_FILL, fit_neural_sdf, geometric_error, load_neural_sdf

    out = Path(out_dir)
    path = out / (Path(mesh_path).name.split(".")[0] + NEURAL_SDF_SUFFIX)
    settings = {"source": str(mesh_path), "size": f"{size[0]}x{size[1]}", "samples": int(samples), "steps": int(steps),
                "seed": int(seed), "pos_freqs": int(pos_freqs)}  # fmt: skip
    report_path = out / REPORT
    if path.is_file() and report_path.is_file():
        old = json.loads(report_path.read_text())
        if old.get("settings") == settings:
            log(f"neural SDF: reusing {path}")
            return path
    geometry = load_geometry(mesh_path)
    if not geometry.watertight:
        raise GeometryError(f"{mesh_path}: --neural-sdf needs a watertight mesh (the sign of the distance is by ray parity)")
    mesh = geometry.mesh.copy()
    mesh.apply_scale(SCENE_FILL)
    t0 = time.perf_counter()
    info = fit_neural_sdf(mesh, path, size=size, pos_freqs=pos_freqs, samples=samples, steps=steps, seed=seed, log=log)
    error = geometric_error(load_neural_sdf(path), mesh, seed=seed)
    log(f"neural SDF geometric error (scene units, scene box 2): mean |f| on the mesh {error['mean_abs_sdf']:.2e}, "
        f"Chamfer {error['chamfer']:.2e} (max {error['chamfer_max']:.2e})")  # fmt: skip
    to_source = np.asarray(geometry.to_source) @ np.diag([1 / SCENE_FILL] * 3 + [1.0])
    atomic_write_json(report_path, {"settings": settings, "fit": info, "geometric_error": error,
                                    "seconds": round(time.perf_counter() - t0, 2),
                                    "to_source": to_source.tolist()})  # fmt: skip
    return path
