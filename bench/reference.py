"""The ray-traced reference every configuration is compared with, and its cache.

The G-buffer of each view (the renderer's own, so pixels match), ground-truth transfer ray
traced at every covered pixel with :func:`prt.train.compute_transfer` (``--ref-rays``
cosine-weighted rays; the same geometry the scene was built from: ``geometry.npz``, or the SDF
scene by name), shaded with :func:`prt.runtime.shading.shade` under the renderer's lighting and
material.  Cached by content (points, normals, rays, seed, geometry) as ``.npz`` in
``transfer/`` of the cache folder (``--cache``; default: ``<json stem>_cache`` next to
``--json``), so scenes built from one mesh share their references.  Its
own noise is reported: PSNR between two references with different seeds (frame spins) at view 0
(:func:`noise_psnr`); how many rays it traces is :mod:`prt.bench.quiet_reference`'s choice.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from prt.bench.metrics import image_metrics
from prt.runtime.files import atomic_save_npz
from prt.runtime.shading import shade, tonemap
from prt.train import compute_transfer
from prt.train.inputs.geometry import Geometry, load_geometry

__all__ = ["mesh_checksum", "load_scene_geometry", "cached_transfer", "shade_image", "reference_linear", "reference_images", "noise_psnr", "View",
           "REFERENCE_MARGIN_DB", "convergence"]

# The reference's two-seed PSNR must exceed the best configuration's PSNR by this much (issue 12).
REFERENCE_MARGIN_DB = 6.0


@dataclass
class View:
    """What every configuration of one view shares: camera, G-buffer, references, network FLOPs."""

    camera: object
    gbuffer: object
    references: dict  # material name -> tone-mapped (H, W, 3) reference image
    flops: float
    exposure: dict | None = None  # material name -> the exposure every image of this view is tone-mapped at (None: 1)
    luminance: dict | None = None  # material name -> (H, W) linear luminance of the reference (prt.bench.leak)
    key_exposure: dict | None = None  # material name -> the reference frame's auto exposure (prt.bench.leak)

    def tonemap(self, image, material: str):
        """``image`` (linear) tone-mapped as this view's reference of ``material`` is."""
        return tonemap(image, (self.exposure or {}).get(material, 1.0))


def mesh_checksum(vertices, faces) -> str:
    """sha1 of float32 vertices and uint32 faces: equal exactly when the normalised meshes are."""
    digest = hashlib.sha1(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
    digest.update(np.ascontiguousarray(faces, dtype=np.uint32).tobytes())
    return digest.hexdigest()


def load_scene_geometry(manifest):
    """The geometry a scene was built from, for ray tracing its reference.

    Mesh scenes use ``geometry.npz`` (exactly what the G-buffer rasterises) and, where
    ``build.json`` names a source file that still exists, check that re-loading it gives the
    same normalised mesh.  SDF scenes are re-loaded by name.

    Parameters
    ----------
    manifest : prt.runtime.manifest.Manifest

    Returns
    -------
    geometry : prt.train.inputs.geometry.Geometry
    info : dict
        ``type``, ``source``, ``checksum``, ``matches_build_source`` (bool, or None when the
        check could not be made).
    """
    if manifest.geometry.type == "mixed":
        return _mixed_geometry(manifest)
    if manifest.geometry.type == "sdf":
        name = manifest.geometry.name
        network = manifest.root / name  # a neural SDF travels in the scene folder as <name>.sdf.onnx
        geometry = load_geometry(str(network) if name.endswith(".sdf.onnx") and network.is_file() else name)
        return geometry, {"type": "sdf", "source": name, "checksum": None, "matches_build_source": None}
    path = Path(manifest.geometry.path)
    with np.load(path) as data:
        vertices, faces = data["vertices"], data["faces"]
        n_faces = len(faces)
        object_ids = data["object_ids"] if "object_ids" in data else np.zeros(n_faces, dtype=np.int32)
        two_sided = data["two_sided"] if "two_sided" in data else np.zeros(n_faces, dtype=bool)
    names = list(manifest.geometry.objects or [f"object{i}" for i in range(int(object_ids.max()) + 1)])
    geometry = Geometry(
        mesh=trimesh.Trimesh(vertices=vertices.astype(np.float64), faces=faces.astype(np.int64), process=False),
        object_ids=object_ids.astype(np.int64), object_names=names, two_sided=two_sided.astype(bool),
        to_source=np.asarray(manifest.geometry.to_source, dtype=np.float64), source=str(path), sdf=None,
    )  # fmt: skip
    checksum = mesh_checksum(vertices, faces)
    matches = None
    build = manifest.root / "build.json"
    if build.is_file():
        source = json.loads(build.read_text()).get("source")
        if isinstance(source, str) and source and Path(source).is_file():  # a deformable build records a dict
            again = load_geometry(source)
            matches = mesh_checksum(again.mesh.vertices, again.mesh.faces) == checksum
    return geometry, {"type": "mesh", "source": str(path), "checksum": checksum, "matches_build_source": matches}


def cached_transfer(cache: Path, tag: str, geometry, tracer, points, normals, rays: int, seed: int, geometry_id: str, executor=None,
                    cost: dict | None = None):
    """Ray-traced transfer at ``points``, read from ``cache`` when computed before.

    Parameters
    ----------
    cache : Path
        Folder of ``.npz`` files, keyed by a hash of every input.
    tag : str
        Readable start of the file name (scene, view, size).
    geometry, tracer :
        For :func:`prt.train.compute_transfer`.
    points, normals : (N, 3) float32
    rays, seed : int
    geometry_id : str
        Identity of the geometry (checksum or SDF name), part of the key.
    executor : prt.train.executor.Executor, optional
        Where the chunks run (``prt-bench --cluster``); the result does not depend on it.
    cost : dict, optional
        Receives ``seconds``: what computing it took (then, or when it was cached; None for a
        file cached before its time was kept).

    Returns
    -------
    transfer : (N, 16) float32
    seconds : float
        Time spent computing (0 when read from the cache).
    """
    points = np.ascontiguousarray(points, dtype=np.float32)
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    rule = getattr(tracer, "origin_rule", "")  # SDFs: how ray origins leave the surface (older caches traced otherwise)
    if getattr(tracer, "trace_rule", ""):  # SDFs traced by the band tracer: not the sphere tracer's bytes
        rule = f"{rule}|{tracer.trace_rule}"
    digest = hashlib.sha1(points.tobytes() + normals.tobytes() + f"|{rays}|{seed}|{geometry_id}|v1{'|' + rule if rule else ''}".encode())
    path = cache / f"{tag}-r{rays}-s{seed}-{digest.hexdigest()[:12]}.npz"
    if path.is_file():
        with np.load(path) as data:
            if cost is not None:
                cost["seconds"] = float(data["seconds"]) if "seconds" in data else None
            return data["transfer"], 0.0
    t0 = time.perf_counter()
    transfer = compute_transfer(geometry, points, normals, rays=rays, seed=seed, tracer=tracer, executor=executor)
    seconds = time.perf_counter() - t0
    atomic_save_npz(path, transfer=transfer, seconds=np.float64(seconds))
    if cost is not None:
        cost["seconds"] = seconds
    return transfer, seconds


def shade_image(transfer, gbuffer, eye, lighting, material) -> np.ndarray:
    """Linear (H, W, 3) image of ``transfer`` (M, 16) at the covered pixels of ``gbuffer``."""
    covered = gbuffer.covered
    image = np.zeros(covered.shape + (3,), dtype=np.float32)
    position = gbuffer.position[covered]
    image[covered] = shade(transfer, gbuffer.normal[covered], np.asarray(eye)[None, :] - position, lighting, material)
    return image


def reference_linear(transfer, gbuffer, eye, lighting, materials: dict) -> dict:
    """Linear reference image per material: {name: (H, W, 3)}."""
    return {m: shade_image(transfer, gbuffer, eye, lighting, material) for m, material in materials.items()}


def reference_images(transfer, gbuffer, eye, lighting, materials: dict, exposure: dict | None = None) -> dict:
    """Tone-mapped reference image per material: {name: (H, W, 3) in [0, 1]}, at ``exposure`` ({name: e}; None: 1)."""
    linear = reference_linear(transfer, gbuffer, eye, lighting, materials)
    return {m: tonemap(image, (exposure or {}).get(m, 1.0)) for m, image in linear.items()}


def noise_psnr(other: dict, references: dict, covered) -> dict:
    """The reference's own noise: {material: PSNR (dB, covered pixels) of a second seed's image against it}."""
    return {m: round(image_metrics(other[m], references[m], covered)["psnr"], 2) for m in references}


def convergence(noise: dict, best: dict, rays: int, margin: float = REFERENCE_MARGIN_DB) -> dict:
    """The report's verdict: per material the noise, best PSNR and their gap; ``floor`` when a gap < ``margin``."""
    gap = {m: round(noise[m] - best[m], 2) for m in noise if m in best}
    return {"rays": rays, "noise_psnr": dict(noise), "best_psnr": {m: round(best[m], 2) for m in gap}, "margin_db": gap,
            "required_db": margin, "floor": any(g < margin for g in gap.values())}  # fmt: skip


def _mixed_geometry(manifest):
    """A mixed scene's geometry for tracing: its mesh objects from ``geometry.npz``, its SDF objects
    rebuilt from ``mixed.json`` (their placements in scene units; neural networks in the folder)."""
    from prt.runtime.errors import GeometryError
    from prt.train.inputs.mixed import MixedParts, sdfs_from_record

    record_path = manifest.root / "mixed.json"
    try:
        record = json.loads(record_path.read_text())
        sdfs = sdfs_from_record(record, manifest.root)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise GeometryError(f"{record_path}: cannot rebuild the mixed scene's SDF objects ({' '.join(str(exc).split())})") from None
    path = Path(manifest.geometry.path)
    with np.load(path) as data:
        vertices, faces, object_ids, two_sided = data["vertices"], data["faces"], data["object_ids"], data["two_sided"]
    names = list(manifest.geometry.objects)
    geometry = Geometry(
        mesh=trimesh.Trimesh(vertices=vertices.astype(np.float64), faces=faces.astype(np.int64), process=False),
        object_ids=object_ids.astype(np.int64), object_names=names, two_sided=two_sided.astype(bool),
        to_source=np.asarray(manifest.geometry.to_source, dtype=np.float64), source=str(path), sdf=None,
    )  # fmt: skip
    kinds = list(manifest.geometry.kinds)
    geometry.mixed = MixedParts([], kinds, np.zeros(len(faces), dtype=bool), sdfs, [])
    digest = hashlib.sha1(mesh_checksum(vertices, faces).encode())
    digest.update(geometry.mixed.glsl().encode())
    return geometry, {"type": "mixed", "source": str(path), "checksum": digest.hexdigest(), "matches_build_source": None}
