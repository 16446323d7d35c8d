"""Every configuration of one scene, measured against the reference (:class:`SceneBench`), and :func:`run`.

For every scene, a camera trajectory of ``--views`` views orbits the manifest camera about its
target (the paper's Table 1 protocol), or the views of a ``--cameras`` file are rendered
(:mod:`prt.bench.cameras`; inside views too).  Images are scored at ``--exposure``
(``auto``: the reference frame's own, :mod:`prt.bench.exposure`); every record also carries the
light-leaking figure (:mod:`prt.bench.leak`); ``--backends probes`` adds the engines' L2 SH
probe grid (:mod:`prt.bench.probe_bench`).  Every configuration (backend ``onnx`` at each ONNX
precision, :mod:`prt.export.precision`; backend ``glsl``; the vertex-space baseline,
:mod:`prt.bench.vertex_prt`; the texture-space baseline at each ``--texture-size``,
:mod:`prt.bench.texture_prt`; material diffuse and glossy, :data:`MATERIALS`; each ``--size``)
renders all views after ``--warmup`` frames (or, under ``--config-budget``, as many views as
the budget allows at the warm-up's frame time, at least 4, spread over the orbit; the record's
``views`` says how many), and is compared (:mod:`prt.bench.metrics`) with a ray-traced
reference of the same G-buffer (:mod:`prt.bench.reference`), whose rays are raised until its
noise clears the best PSNR by 6 dB (:mod:`prt.bench.quiet_reference`).  With ``--reference
mitsuba`` every configuration and the reference are also compared with Mitsuba 3
(:mod:`prt.bench.mitsuba_bench`).  Every record says which transfer it
renders (``transfer``, :func:`prt.bench.report.transfer_label`): a scene built with ``--bounces N`` has networks,
texture baseline and reference with N bounces, and its vertex baseline is measured twice, direct
only and with the same N bounces (:func:`prt.bench.vertex_prt.vertex_bounce_transfer`, the build's
bounce estimator on the vertices).  Each size also measures the
naive-vs-packed baseline (:mod:`prt.bench.packing`); the report's format is in
:mod:`prt.bench.report`.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnxruntime
from threadpoolctl import threadpool_limits

from prt.bench.leak import leak_figures, mean_leak
from prt.bench.machine import busy_seconds, cpu_name, machine_gemm, other_cpu_share
from prt.bench.metrics import image_metrics, mark_pareto
from prt.bench.packing import packing_baseline
from prt.bench.bounce_reference import HIT_RAYS, HIT_TRANSFER_RAYS, face_albedo, higher_bounce_samples
from prt.bench.quiet_reference import ReferenceSource, reference_views
from prt.bench.reference import convergence, load_scene_geometry
from prt.bench.report import error_figure, scene_checkpoint, transfer_label
from prt.bench.texture_prt import texture_variants
from prt.bench.vertex_prt import VertexPRT, vertex_bounce_transfer, vertex_transfer
from prt.export.precision import PRECISIONS, model_weight_bytes, variant_manifest
from prt.runtime.backends.onnx import OnnxTransfer
from prt.runtime.camera import Camera, fit_near, orbit_views, scene_box
from prt.runtime.checks import read_text
from prt.runtime.errors import InputError, PRTError
from prt.runtime.files import atomic_write_json
from prt.runtime.gbuffer import load_mesh
from prt.runtime.gl import bind_framebuffer, create_context
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import Material, diffuse_light_matrix, shade, tonemap
from prt.train.transport.transfer import make_tracer

__all__ = ["MATERIALS", "GLOSSY", "Settings", "SceneBench", "budget_views", "spread", "check_scene", "run"]

MATERIALS = ("diffuse", "glossy")
# The glossy material of the paper's comparisons: albedo stays the scene's.
GLOSSY = {"specular": (0.3, 0.3, 0.3), "exponent": 16.0}


@dataclasses.dataclass
class Settings:
    """What to measure (the command line's options)."""

    views: int = 30
    sizes: tuple = (512,)
    ref_rays: int = 1024
    ref_rays_max: int = 4096  # more rays, up to this, where the reference is not 6 dB above the best PSNR
    ref_hit_rays_max: int = 1024  # and bounce rays per pixel, up to this (bench/quiet_reference.py)
    ref_budget: float | None = 3600.0  # seconds the reference of one scene and size may take (predicted); None: no limit
    warmup: int = 3
    config_budget: float | None = None  # seconds of frames per configuration (slow ones measure fewer views)
    packing_views: int | None = None  # views of the naive-vs-packed baseline (None: all), spread over the orbit
    precisions: tuple = PRECISIONS
    interpolate: tuple = ()  # tolerances of extra fp32 ONNX rows with screen-space interpolation (runtime/interpolation.py)
    backends: tuple = ("onnx", "glsl", "vertex")
    texture_sizes: tuple = (1024,)  # transfer texture sizes of the texture baseline (backend "texture")
    cache: Path | None = None
    gemm_size: int = 4096
    seed: int = 0
    blas_threads: int | None = None
    fresh: bool = False  # re-measure scenes a checkpoint already holds
    images: Path | None = None  # folder for the error-map figures (None: none)
    ref_hit_rays: int = HIT_RAYS  # interreflection reference: bounce rays per pixel (bench/bounce_reference.py)
    ref_hit_transfer_rays: int = HIT_TRANSFER_RAYS  # and rays of the direct transfer at each hit
    baseline_rays: int | None = None  # rays per vertex / texel of the vertex and texture baselines (None: ref_rays)
    reference: str = "ours"  # "mitsuba": also compare every configuration with Mitsuba 3 (bench/mitsuba_bench.py)
    mitsuba_spp: int = 1024  # paths per pixel of Mitsuba's images
    mitsuba_views: int = 3  # views compared with Mitsuba, spread over the orbit
    mitsuba_variant: str = "auto"  # llvm_ad_rgb where a libLLVM works, else scalar_rgb
    equal_bytes: bool = False  # also the vertex baseline on the mesh decimated to the build's bytes (bench/equal_bytes.py)
    gl_device: str | None = None  # the EGL device that draws (runtime/gl_devices.py; None: $PRT_GL_DEVICE, else auto)
    cameras: tuple | None = None  # --cameras: ([eye], [target], [up], fov) per view (bench/cameras.py); None: the orbit
    cameras_file: str | None = None  # where they came from (reported)
    exposure: object = 1.0  # every image's exposure: a number, or "auto" (the reference frame's, bench/exposure.py)

    @property
    def rays_of_baselines(self) -> int:
        """Rays per vertex or texel of the baselines' direct transfer and of their bounces."""
        return self.ref_rays if self.baseline_rays is None else self.baseline_rays


def _materials(manifest) -> dict:
    """The diffuse and glossy materials, both with the scene's albedo."""
    albedo = tuple(float(a) for a in manifest.material.albedo)
    return {"diffuse": Material("diffuse", albedo=albedo), "glossy": Material("glossy", albedo=albedo, **GLOSSY)}


def _segment_flops(manifest, segment_image) -> float:
    """Manifest FLOPs of evaluating the networks at every covered pixel of a segment-id image."""
    counts = np.bincount(segment_image[segment_image >= 0].ravel(), minlength=len(manifest.segments))
    return float(sum(counts[s.id] * s.flops_per_fragment for s in manifest.segments if s.kind == "network"))


def _summarise(stage_lists, metric_lists, gflops, frame_ms) -> dict:
    """Medians of timings, means of metrics over views."""
    frame = float(np.median(frame_ms))
    stages = {k: round(float(np.median(v)), 3) for k, v in stage_lists.items() if k != "frame"}
    out = {"fps": round(1000.0 / frame, 2), "frame_ms": round(frame, 3), "stages_ms": stages}
    out.update({k: float(np.mean(v)) for k, v in metric_lists.items()})
    out["achieved_gflops"] = round(float(np.median(gflops)), 3) if gflops else 0.0
    return out


def budget_views(views: list, budget_s: float | None, frame_s: float | None, least: int = 4) -> list:
    """The views one configuration measures under a time budget (``--config-budget``).

    All of them without a budget (or before any frame was timed); else as many as
    ``budget_s / frame_s`` allow, at least ``least``, spread evenly over the orbit and always
    starting at view 0 (whose transfer the precision variants are compared on).
    """
    if budget_s is None or frame_s is None or frame_s <= 0:
        return list(views)
    return spread(views, int(max(least, budget_s // frame_s)))


def spread(views: list, n: int | None) -> list:
    """``n`` of ``views`` evenly over the orbit, starting at view 0 (all when ``n`` is None or too many)."""
    if n is None or n >= len(views):
        return list(views)
    picks = np.unique(np.round(np.linspace(0, len(views) - 1, n)).astype(int)) if n > 1 else np.array([0])
    return [views[i] for i in picks]


def _measure_renderer(renderer, views, material_name, material, settings, transfer_fp32=None) -> tuple[dict, np.ndarray]:
    """Render every view with one material after warm-up; timings, metrics and view 0's transfer."""
    kw = {"albedo": material.albedo}
    if material.kind == "glossy":
        kw.update(specular=material.specular, exponent=material.exponent)
    renderer.set_material(material.kind, **kw)
    renderer.set_background(False)  # the reference is black where no geometry is
    warm_s = None
    for i in range(settings.warmup):  # sessions, shader compilation, caches; a new view each time
        renderer.set_camera_object(views[0].camera.orbit(0.01 * (i + 1)))
        t0 = time.perf_counter()
        renderer.render()
        warm_s = time.perf_counter() - t0
    measured = budget_views(views, settings.config_budget, warm_s)
    stages, metrics, gflops, frames, fractions, leaks = defaultdict(list), defaultdict(list), [], [], [], []
    transfer0 = None
    for k, view in enumerate(measured):
        renderer.set_camera_object(view.camera)
        image = renderer.render()
        for name, ms in renderer.timings.items():
            stages[name].append(ms)
        frames.append(renderer.timings["frame"])
        fractions.append(renderer.stats["network_fraction"])
        network_ms = renderer.timings.get("inference", renderer.timings.get("network", 0.0))
        if network_ms > 0:  # with interpolation only that share of the covered pixels ran (segments weighted alike)
            gflops.append(view.flops * fractions[-1] / (network_ms * 1e-3) / 1e9)
        for name, value in image_metrics(view.tonemap(image, material_name), view.references[material_name], view.gbuffer.covered).items():
            metrics[name].append(value)
        leaks.append(_leak(image, view, material_name))
        if k == 0:
            transfer0 = renderer.render_transfer()[view.gbuffer.covered]  # cached: no network runs
            image0 = view.tonemap(image, material_name)
    summary = {**_summarise(stages, metrics, gflops, frames), **mean_leak(leaks)}
    summary["network_ms"] = summary["stages_ms"].get("inference", summary["stages_ms"].get("network", 0.0))
    summary["views"] = len(measured)
    summary["network_fraction"] = round(float(np.median(fractions)), 4)  # covered pixels that ran a network (< 1 with screen-space interpolation)
    summary["_image0"] = image0  # for the error maps; not part of the record
    if transfer_fp32 is not None:
        summary["transfer_max_abs_diff"] = float(np.abs(transfer0 - transfer_fp32).max(initial=0.0))
    return summary, transfer0


def _leak(image, view, material_name) -> dict:
    """:func:`prt.bench.leak.leak_figures` of one linear image of ``view``."""
    if view.luminance is None:
        return {"leak": None, "leak_error": None}
    return leak_figures(image, view.luminance[material_name], view.key_exposure[material_name], view.gbuffer.covered)


def vertex_frame(vertex, gbuffer_pass, camera, material, lighting) -> tuple[np.ndarray, dict]:
    """One frame of the vertex baseline: G-buffer pass + transfer raster + CPU shading; (linear (H, W, 3), timings)."""
    t0 = time.perf_counter()
    gbuffer_pass.render(camera)
    packed = gbuffer_pass.read_packed()
    t1 = time.perf_counter()
    transfer, _ = vertex.render(camera)
    t2 = time.perf_counter()
    covered = np.flatnonzero(packed[:, 3] > 0.5)
    rows, t = packed[covered], transfer.reshape(len(packed), -1)[covered]
    if material.kind == "diffuse":  # the renderer's own float32 fast path (direct or "direct+rgb")
        radiance = np.maximum(t @ diffuse_light_matrix(lighting, material.albedo, t.shape[1]), 0.0)
    else:
        radiance = shade(t, rows[:, 4:7], camera.eye[None, :] - rows[:, 0:3], lighting, material)
    image = np.zeros((len(packed), 3), dtype=np.float32)
    image[covered] = radiance
    t3 = time.perf_counter()
    timings = {"gbuffer": 1e3 * (t1 - t0), **vertex.timings, "shade": 1e3 * (t3 - t2)}
    timings["frame"] = 1e3 * (t3 - t0)
    return image.reshape(vertex.height, vertex.width, 3), timings


def _measure_vertex(vertex, gbuffer_pass, views, material_name, material, lighting, settings) -> dict:
    """The vertex baseline's frames (:func:`vertex_frame`) and its errors."""
    def frame(camera):
        return vertex_frame(vertex, gbuffer_pass, camera, material, lighting)

    return _measure_frames(frame, views, material_name, settings)


def _measure_frames(frame, views, material_name, settings) -> dict:
    """The frames of a baseline drawn by ``frame(camera) -> (linear image, timings)`` and their errors."""
    for i in range(settings.warmup):
        frame(views[0].camera.orbit(0.01 * (i + 1)))
    stages, metrics, frames, leaks = defaultdict(list), defaultdict(list), [], []
    image0 = None
    for view in views:
        image, timings = frame(view.camera)
        image0 = view.tonemap(image, material_name) if image0 is None else image0
        for name, ms in timings.items():
            stages[name].append(ms)
        frames.append(timings["frame"])
        for name, value in image_metrics(view.tonemap(image, material_name), view.references[material_name], view.gbuffer.covered).items():
            metrics[name].append(value)
        leaks.append(_leak(image, view, material_name))
    summary = {**_summarise(stages, metrics, [], frames), **mean_leak(leaks)}
    summary["network_ms"] = 0.0
    summary["_image0"] = image0
    return summary


class SceneBench:
    """Every configuration of one scene (see the module docstring).

    Parameters
    ----------
    scene_path : path-like
    settings : Settings
    ctx : moderngl.Context
        Shared by every renderer of the run.
    machine_gflops : float
    log : callable
    """

    def __init__(self, scene_path, settings: Settings, ctx, machine_gflops: float, log, executor=None):
        self.settings, self.ctx, self.machine_gflops, self.log = settings, ctx, machine_gflops, log
        self.executor = executor  # where the reference's transfer chunks run (None: threads here)
        self.scene = Scene.load(scene_path)
        manifest = self.manifest = self.scene.manifest
        self.geometry, geo_info = load_scene_geometry(manifest)
        if geo_info["matches_build_source"] is False:
            log(f"  warning: {manifest.root / 'build.json'}'s source no longer gives geometry.npz's mesh; using geometry.npz")
        self.geometry_id = geo_info["checksum"] or f"sdf:{geo_info['source']}"
        self.tracer = make_tracer(self.geometry)
        self.cache = settings.cache / manifest.name  # this scene's precision variants
        # Ray-traced transfer is keyed by its inputs (points, normals, rays, seed, geometry), so
        # scenes of one mesh (k = 64, k = 128, right-sized) share their references and vertices.
        self.transfer_cache = settings.cache / "transfer"
        if settings.cameras:  # --cameras: the views a file gives (bench/cameras.py), in the manifest camera's clip range
            near_far = Camera.from_manifest(manifest.camera)
            box = scene_box(manifest)  # views inside the scene get the interior near plane, as the viewer's walk does
            self.cameras = [fit_near(Camera(eye, target, up, fov, near_far.near, near_far.far), box)
                            for eye, target, up, fov in settings.cameras]  # fmt: skip
        else:
            self.cameras = orbit_views(Camera.from_manifest(manifest.camera), settings.views)
        self.materials = _materials(manifest)
        self.variants = {p: variant_manifest(manifest, p, self.cache / "models") for p in settings.precisions}
        self.weights = {p: model_weight_bytes(m) for p, m in self.variants.items()}
        self.vertex_data, vertex_info = self._vertex_transfer()
        self.textures, texture_info = {}, {"note": "skipped (--backends)"}
        if "texture" in settings.backends and self.geometry.kind == "mixed":
            texture_info = {"note": "skipped: mixed scene (SDF objects have no UV atlas)"}
        elif "texture" in settings.backends:
            self.textures, texture_info = texture_variants(manifest, self.geometry, self.tracer, settings.texture_sizes,
                                                           settings.rays_of_baselines, settings.cache, ctx, log)  # fmt: skip
        self.entry = {
            "scene": manifest.name, "path": str(manifest.path), "geometry": geo_info,
            "networks": sum(s.kind == "network" for s in manifest.segments), "weight_bytes": self.weights["fp32"],
            "reference": {"rays": settings.ref_rays, "seed": settings.seed, "cache": str(self.transfer_cache), "noise_psnr": {},
                          "noise_note": "PSNR between two references with different seeds at view 0 (covered pixels); "
                                        "each is ~3 dB closer to the converged image than this",
                          "rays_by_size": {}, "hit_rays_by_size": {}, "plan": {}, "convergence": {},
                          "rays_max": settings.ref_rays_max, "hit_rays_max": settings.ref_hit_rays_max, "budget_s": settings.ref_budget},
            "packing": [], "vertex_baseline": vertex_info, "texture_baseline": texture_info, "error_images": [],
            "views_from": settings.cameras_file or "orbit", "exposure": settings.exposure,
        }  # fmt: skip
        self.probe_grids = None  # baked at the first size (bench/probe_bench.py)
        self._interreflection()
        self.vertex_bounced = self._vertex_bounces()
        self.records: list[dict] = []
        self.images: dict = defaultdict(list)  # (resolution, material) -> [(label, view 0 image, its PSNR)]
        self._pilot_images = None  # view 0's configurations at the size being measured (the quiet reference's pilot)

    def _interreflection(self) -> None:
        """Scenes built with ``--bounces N``: the reference gets the same N bounces (:mod:`prt.bench.bounce_reference`)."""
        record = (self.manifest.raw or {}).get("interreflection") or {}
        self.bounces = int(record.get("bounces", 0))
        self.bounce_albedo, self.higher = None, None
        settings = self.settings
        if self.bounces > 0:
            if self.geometry.kind != "mesh":
                raise InputError(f"{self.manifest.path}: interreflection in an SDF scene: the reference traces bounces on meshes only")
            self.bounce_albedo = face_albedo(record.get("albedos") or {}, self.geometry)
            self.higher = higher_bounce_samples(self.geometry, self.tracer, self.bounce_albedo, self.bounces, rays=settings.ref_rays,
                                                seed=settings.seed, cache=self.transfer_cache, geometry_id=self.geometry_id, log=self.log)  # fmt: skip
            self.entry["reference"]["interreflection"] = {"bounces": self.bounces, "gi_off_psnr": {}, "hit_rays": settings.ref_hit_rays,
                                                          "hit_transfer_rays": settings.ref_hit_transfer_rays,
                                                          "note": "PSNR of the direct-only reference against the N-bounce one at view 0: what GI changes"}  # fmt: skip
        self.source = ReferenceSource(self.geometry, self.tracer, self.transfer_cache, self.geometry_id, self.bounces, self.bounce_albedo,
                                      self.higher, settings.ref_hit_transfer_rays, self.executor)  # fmt: skip

    def run(self) -> tuple[dict, list]:
        """Measure every size; returns the ``scenes[]`` entry and the ``records[]`` of this scene."""
        for size in self.settings.sizes:
            # This renderer's G-buffer defines the pixels; every other renderer draws the same ones.
            with Renderer(self.scene, size, size, backend="onnx", ctx=self.ctx) as base:
                for v, camera in enumerate(self.cameras if self.settings.cameras else []):  # before any ray is traced
                    base.set_camera_object(camera)
                    if not base.gbuffer_image().covered.any():
                        raise InputError(f"{self.settings.cameras_file}: views[{v}] sees no part of the scene at {size}x{size}")
                self._pilot_images = None  # view 0's configurations at this size (bench/quiet_reference.py's pilot)
                views = reference_views(self.source, base, self.cameras, size, self.materials, self.settings,
                                        lambda refs, covered, exposure: self._pilot(base, refs, covered, exposure, size), self.entry["reference"],
                                        lambda segment: _segment_flops(self.manifest, segment), self.log)  # fmt: skip
                if self.entry["networks"] and "onnx" in self.settings.backends:
                    cameras = spread(self.cameras, self.settings.packing_views)
                    self.entry["packing"].append(packing_baseline(self.manifest, base.gbuffer, cameras, self.log))
                self._network_records(size, views)
                if self.vertex_data is not None:
                    self._vertex_records(size, views, base.gbuffer, base.lighting)
                self._texture_records(size, views)
                if "probes" in self.settings.backends:
                    self._probe_records(size, views, base.gbuffer, base.lighting)
                self._check_convergence(size)
                if self.settings.images is not None:
                    path = Path(self.settings.images) / f"{self.manifest.name}-{size}x{size}.png"
                    error_figure(views[0], {m: self.images[(f"{size}x{size}", m)] for m in self.materials}, path,
                                 f"{self.manifest.name} {size}x{size}, view 0")  # fmt: skip
                    self.entry["error_images"].append(str(path))
                    self.log(f"  error maps: {path}")
                if self.settings.reference == "mitsuba":
                    from prt.bench.mitsuba_bench import mitsuba_comparison

                    mitsuba_comparison(self, base, size, views, spread(list(range(len(views))), self.settings.mitsuba_views))
        return self.entry, self.records

    # ------------------------------------------------------------------ pieces

    def _vertex_transfer(self):
        """Per-vertex transfer of the vertex baseline and its ``vertex_baseline`` entry."""
        if self.geometry.kind != "mesh":
            return None, {"note": f"skipped: {self.geometry.kind} scene (no vertices for the SDF objects)"}
        if "vertex" not in self.settings.backends:
            return None, {"note": "skipped (--backends)"}
        rays = self.settings.rays_of_baselines
        front, back, back_vertices = vertex_transfer(self.geometry, self.tracer, rays, self.transfer_cache, self.geometry_id)
        n_vertices = len(self.geometry.mesh.vertices)
        info = {"vertices": n_vertices, "back_vertices": back_vertices, "weight_bytes": 16 * 4 * (n_vertices + back_vertices), "rays": rays}
        return (front, back), info

    def vertex_variants(self) -> list[tuple[str, tuple]]:
        """(transfer label, per-vertex data) of the vertex baseline: direct, then with the scene's N
        bounces where it has them; empty without a vertex baseline."""
        variants = [] if self.vertex_data is None else [("direct", self.vertex_data)]
        if self.vertex_bounced is not None:
            variants.append((transfer_label(self.bounces), self.vertex_bounced))
        return variants

    def _vertex_bounces(self):
        """The vertex baseline with the scene's N bounces ("direct+rgb"; None without bounces or vertex baseline).

        Adds ``bounces`` to the ``vertex_baseline`` entry: ``bounces``, ``rays`` (bounce rays per
        vertex sample: ``--baseline-rays``, as its direct transfer; default ``--ref-rays``), ``estimator``,
        ``weight_bytes`` (64 float32 per vertex and side), ``seconds`` (0 when cached).
        """
        if self.vertex_data is None or self.bounces <= 0:
            return None
        rays, info = self.settings.rays_of_baselines, self.entry["vertex_baseline"]
        front, back, seconds = vertex_bounce_transfer(self.geometry, *self.vertex_data, self.bounce_albedo, self.bounces, rays=rays,
                                                      seed=self.settings.seed, cache=self.transfer_cache, geometry_id=self.geometry_id)  # fmt: skip
        info["bounces"] = {
            "bounces": self.bounces, "rays": rays, "weight_bytes": 4 * front.shape[1] * (info["vertices"] + info["back_vertices"]),
            "estimator": "the build's bounce stage on the vertex samples: nearest vertex sample at each hit, sparse products",
            "seconds": round(seconds, 3),
        }  # fmt: skip
        self.log(f"  vertex baseline, {transfer_label(self.bounces)}: {rays} bounce rays per vertex sample"
                 f"{f' ({seconds:.1f} s)' if seconds else ' (cached)'}")  # fmt: skip
        return front, back

    def _equal_bytes(self):
        """``--equal-bytes``: (front, back, info) of the vertex baseline on the mesh decimated to the build's
        bytes (:mod:`prt.bench.equal_bytes`), computed once per scene; None without the option."""
        if not self.settings.equal_bytes:
            return None
        if getattr(self, "_equal", None) is None:
            from prt.bench.equal_bytes import equal_bytes_vertex

            albedo = self.bounce_albedo if self.bounce_albedo is not None else np.zeros((len(self.geometry.mesh.faces), 3))
            self._equal = equal_bytes_vertex(self.geometry, self.weights["fp32"], width=64 if self.bounces > 0 else 16, bounces=self.bounces,
                                             face_albedo=albedo, rays=self.settings.rays_of_baselines, seed=self.settings.seed,
                                             cache=self.transfer_cache, geometry_id=self.geometry_id, log=self.log)  # fmt: skip
            self.entry["vertex_baseline"]["equal_bytes"] = self._equal[2]
        return self._equal

    def _pilot(self, renderer, references: dict, covered, exposure: dict, size: int) -> dict:
        """{material: best PSNR} at view 0 (the renderer's view) against ``references``, over the fp32
        networks and every vertex and texture baseline (:mod:`prt.bench.quiet_reference`)."""
        if self._pilot_images is None:
            self._pilot_images = self._configuration_images(renderer, size, renderer.camera, self.materials)
        best = {}
        for images in self._pilot_images.values():
            for name, image in images.items():
                psnr = image_metrics(tonemap(image, exposure[name]), references[name], covered)["psnr"]
                best[name] = max(best.get(name, -math.inf), psnr)
        return best

    def _configuration_images(self, renderer, size: int, camera, materials: dict) -> dict:
        """{label: {material: linear (H, W, 3) image}} of ``camera``'s view: the fp32 networks (``renderer``),
        each vertex baseline and each texture baseline, with ``materials`` ({name: Material})."""
        out = {}
        if self.entry["networks"]:
            renderer.set_camera_object(camera)
            out["onnx fp32"] = {}
            for name, material in materials.items():
                kw = {"specular": material.specular, "exponent": material.exponent} if material.kind == "glossy" else {}
                renderer.set_material(material.kind, albedo=material.albedo, **kw)
                out["onnx fp32"][name] = renderer.render().copy()
        for transfer, data in self.vertex_variants():
            vertex = VertexPRT(self.ctx, self.geometry, *data, size, size)
            try:
                out[f"vertex {transfer}"] = {name: vertex_frame(vertex, renderer.gbuffer, camera, m, renderer.lighting)[0]
                                             for name, m in materials.items()}  # fmt: skip
            finally:
                vertex.release()
        for texture_size, variant in self.textures.items():
            bind_framebuffer(self.ctx, self.ctx.fbo)
            with Renderer(Scene(variant), size, size, backend="texture", ctx=self.ctx) as texture:
                texture.set_background(False)
                texture.set_camera_object(camera)
                out[f"texture {texture_size}"] = {}
                for name, material in materials.items():
                    kw = {"specular": material.specular, "exponent": material.exponent} if material.kind == "glossy" else {}
                    texture.set_material(material.kind, albedo=material.albedo, **kw)
                    out[f"texture {texture_size}"][name] = texture.render().copy()
        renderer.set_camera_object(camera)
        return out

    def _check_convergence(self, size: int) -> None:
        """Record the reference's noise against the best PSNR measured at ``size`` (``floor`` when under 6 dB apart)."""
        resolution = f"{size}x{size}"
        best = {}
        for r in self.records:
            if r["resolution"] == resolution:
                best[r["material"]] = max(best.get(r["material"], -math.inf), r["psnr"])
        ref = self.entry["reference"]
        verdict = ref["convergence"][resolution] = convergence(ref["noise_psnr"][resolution], best, ref["rays_by_size"][resolution])
        verdict["hit_rays"] = ref["hit_rays_by_size"][resolution]
        plan = ref["plan"].get(resolution)
        if verdict["floor"]:
            # Why it could not be quieter: the ray caps or the time budget stopped it, or the views'
            # mean PSNR beat view 0's pilot that the rays were chosen for.
            verdict["reason"] = plan["reason"] if plan and not plan["met"] else "pilot"
            verdict["needs"] = plan["needs"] if plan and not plan["met"] else None
            self.log(f"  reference {resolution}: noise PSNR {verdict['noise_psnr']} is not 6 dB above the best PSNR "
                     f"{verdict['best_psnr']} at {verdict['rays']} rays ({verdict['reason']}): the reference is the floor")  # fmt: skip

    def _common(self, size: int, views: list) -> dict:
        """The fields every record of this scene and size shares."""
        covered = [int(v.gbuffer.covered.sum()) for v in views]
        flops = sum(v.flops for v in views)
        return {
            "scene": self.manifest.name, "resolution": f"{size}x{size}", "width": size, "height": size,
            "views": len(views), "covered_pixels": float(np.median(covered)),
            "flops_per_fragment": round(flops / sum(covered), 1) if sum(covered) else 0.0,
            "machine_gflops": round(self.machine_gflops, 2), "ref_rays": self.entry["reference"]["rays_by_size"][f"{size}x{size}"],
        }  # fmt: skip

    def _add(self, common: dict, backend: str, precision: str, material: str, summary: dict, weight_bytes: int,
             transfer: str | None = None) -> None:
        """One record; ``transfer`` defaults to the scene's (:func:`transfer_label` of its bounces)."""
        noise = self.entry["reference"]["noise_psnr"][common["resolution"]][material]
        image0 = summary.pop("_image0", None)
        summary = {**summary, "transfer": transfer or transfer_label(self.bounces)}
        record = _record(common, backend, precision, material, summary, weight_bytes, noise, self.log)
        self.records.append(record)
        if image0 is not None:
            self.images[(common["resolution"], material)].append((record["label"], image0))

    def _network_records(self, size: int, views: list) -> None:
        """The ONNX backend at every precision, then the GLSL backend, each with both materials."""
        onnx = "onnx" in self.settings.backends
        configs = [("onnx", p, None) for p in self.settings.precisions] if onnx else []
        configs += [("onnx", "fp32", tol) for tol in self.settings.interpolate] if onnx else []
        if "glsl" in self.settings.backends:
            configs.append(("glsl", "fp32", None))
        common = self._common(size, views)
        transfer_fp32 = None  # view 0's transfer on the fp32 ONNX path, what the others are compared with
        for backend, precision, tol in configs:
            scene = Scene(self.variants[precision]) if backend == "onnx" else self.scene
            with Renderer(scene, size, size, backend=backend, ctx=self.ctx, interpolate=tol) as renderer:
                for name, material in self.materials.items():
                    summary, transfer0 = _measure_renderer(renderer, views, name, material, self.settings, transfer_fp32)
                    if (backend, precision, tol) == ("onnx", "fp32", None):
                        transfer_fp32 = transfer0
                        summary["transfer_max_abs_diff"] = 0.0
                    self._add(common, backend, precision, name, {**summary, "interpolate": tol}, self.weights[precision])

    def _texture_records(self, size: int, views: list) -> None:
        """The texture baseline at each texture size with both materials (:mod:`prt.bench.texture_prt`)."""
        common = {**self._common(size, views), "flops_per_fragment": 0.0}
        for texture_size, variant in self.textures.items():
            stats = self.entry["texture_baseline"]["sizes"][str(texture_size)]
            bind_framebuffer(self.ctx, self.ctx.fbo)  # the default one if a baseline left a released one bound
            with Renderer(Scene(variant), size, size, backend="texture", ctx=self.ctx) as renderer:
                for name, material in self.materials.items():
                    summary, _ = _measure_renderer(renderer, views, name, material, self.settings)
                    summary.update(achieved_gflops=0.0, texture_size=texture_size, precompute_s=stats["precompute_s"],
                                   network_ms=summary["stages_ms"].get("texture", 0.0))  # the transfer stage: the fetch pass
                    self._add(common, "texture", "fp16", name, summary, stats["bytes"])

    def _probe_records(self, size: int, views: list, gbuffer_pass, lighting) -> None:
        """The probe-grid baseline at both densities, diffuse only (:mod:`prt.bench.probe_bench`)."""
        from prt.bench.probe_bench import probe_frame, scene_grids

        if self.probe_grids is None:
            self.probe_grids, self.entry["probe_grid"] = scene_grids(self, lighting)
        common = {**self._common(size, views), "flops_per_fragment": 0.0}
        material = self.materials["diffuse"]
        for density, grid in self.probe_grids.items():
            summary = _measure_frames(lambda camera: probe_frame(grid, gbuffer_pass, camera, material.albedo, size, size), views, "diffuse", self.settings)
            summary.update(network_ms=summary["stages_ms"].get("probes", 0.0), achieved_gflops=0.0, transfer_max_abs_diff=None, probe_grid=grid.info)
            self._add(common, "probes", "fp32", "diffuse", summary, grid.weight_bytes)

    def _vertex_records(self, size: int, views: list, gbuffer_pass, lighting) -> None:
        """The vertex baseline with both materials, and how well its pixels match the G-buffer's."""
        resolution = f"{size}x{size}"
        info = self.entry["vertex_baseline"]
        common = {**self._common(size, views), "flops_per_fragment": 0.0}
        variants = [("direct", self.vertex_data, info["weight_bytes"])]
        if self.vertex_bounced is not None:  # beside the direct rows: the same N bounces as the networks
            variants.append((transfer_label(self.bounces), self.vertex_bounced, info["bounces"]["weight_bytes"]))
        equal = self._equal_bytes()
        if equal is not None:  # at the build's bytes, with the networks' transfer
            variants.append(("equal bytes", equal[:2], equal[2]["weight_bytes"]))
        for transfer, data, weight_bytes in variants:
            vertex = VertexPRT(self.ctx, self.geometry, *data, size, size)
            try:
                if transfer == "direct":
                    agreement = []
                    for view in views:
                        drawn = vertex.render(view.camera)[1]
                        covered = view.gbuffer.covered
                        agreement.append(np.logical_and(drawn, covered).sum() / max(covered.sum(), 1))
                    info.setdefault("coverage_agreement", {})[resolution] = round(float(np.min(agreement)), 5)
                decimated = {k: equal[2][k] for k in ("vertices", "faces", "target_bytes")} if transfer == "equal bytes" else None
                for name, material in self.materials.items():
                    summary = _measure_vertex(vertex, gbuffer_pass, views, name, material, lighting, self.settings)
                    summary.update(achieved_gflops=0.0, transfer_max_abs_diff=None, **({"equal_bytes": decimated} if decimated else {}))
                    self._add(common, "vertex", "fp32", name, summary, weight_bytes, transfer_label(self.bounces) if decimated else transfer)
            finally:
                vertex.release()


def _record(common, backend, precision, material, summary, weight_bytes, noise_psnr, log) -> dict:
    """One configuration's JSON record (rounded), printed as a progress line."""
    record = {**common, "backend": backend, "precision": precision, "material": material, **summary}
    for key in ("mae", "ssim"):
        record[key] = round(record[key], 6)
    for key in ("psnr", "psnr_whole"):
        record[key] = round(record[key], 3)
    record["weight_bytes"] = int(weight_bytes)
    gflops = record.get("achieved_gflops", 0.0)
    record["machine_percent"] = round(100.0 * gflops / record["machine_gflops"], 3) if record["machine_gflops"] else None
    record["ref_noise_psnr"] = noise_psnr
    # Baselines name their transfer when it is not direct: a scene's vertex rows come both ways.
    carries = "" if backend not in ("vertex", "texture") or record["transfer"] == "direct" else f" {record['transfer']}"
    interpolate = f" interpolate {record['interpolate']:g}" if record.get("interpolate") else ""
    record["label"] = f"{backend} {precision}{interpolate} {material}" if backend == "onnx" else f"{backend}{carries} {material}"
    if record.get("equal_bytes"):  # the vertex baseline on the mesh decimated to the build's bytes
        record["label"] = f"vertex equal-bytes{carries} {material}"
    if "texture_size" in record:
        record["label"] = f"{backend} {record['texture_size']}{carries} {material}"
    if "probe_grid" in record:  # the probe grid, at equal bytes or the engine density
        record["label"] = f"probes {record['probe_grid']['density']} {material}"
    record.setdefault("transfer_max_abs_diff", None)
    leak = "" if record.get("leak") is None else f", leak {100 * record['leak']:.1f} % ({record['leak_error']:.3f} key)"
    log(
        f"  {record['scene']} {record['resolution']} {record['label']}: {record['fps']:.1f} FPS "
        f"({record['frame_ms']:.1f} ms, network {record['network_ms']:.1f} ms), PSNR {record['psnr']:.2f} dB "
        f"(whole {record['psnr_whole']:.2f}), SSIM {record['ssim']:.4f}, MAE {record['mae']:.4f}{leak}"
    )
    return record


# Points per network segment on which check_scene runs each network once.
_PROBE_POINTS = 64


def check_scene(path, settings: Settings) -> Scene:
    """Everything about a scene that can fail, checked before anything is measured.

    The manifest (:func:`prt.runtime.manifest.load_manifest`: schema, confined paths), the mesh,
    every network model (no external data, float32 [N, 6] -> [N, 16], finite transfer on points
    inside its segment's box), and the GLSL the ``glsl`` backend compiles.

    Raises
    ------
    PRTError
        One line naming the file and the fault.
    """
    scene = Scene.load(path)
    manifest = scene.manifest
    if scene.deformation is not None:  # its reference is traced per pose, at the posed points
        raise InputError(f"{manifest.path}: a deformable scene; measure it with prt-bench deform {manifest.path.parent}")
    if settings.reference == "mitsuba" and manifest.geometry.type != "mesh":
        raise InputError(f"{manifest.path}: --reference mitsuba compares mesh scenes only; this one is {manifest.geometry.type}")
    if manifest.geometry.type == "mesh":
        load_mesh(manifest.geometry.path)
    if "glsl" in settings.backends:
        for seg in scene.network_segments:
            if seg.glsl is None:
                raise InputError(f"{manifest.path}: segments[{seg.id}] has no generated GLSL (needed by --backends glsl)")
            read_text(seg.glsl, "GLSL")
    if not scene.network_segments:
        return scene
    engine = OnnxTransfer(manifest, threads=1)
    try:
        rng = np.random.default_rng(0)
        for seg in scene.network_segments:
            lo, hi = seg.bounds
            normals = rng.normal(size=(_PROBE_POINTS, 3))
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
            inputs = np.concatenate([rng.uniform(lo, hi, size=(_PROBE_POINTS, 3)), normals], axis=1).astype(np.float32)
            _, transfer = engine.compute(inputs, np.full(_PROBE_POINTS, seg.id))
            if not np.isfinite(transfer).all():
                raise InputError(f"{seg.model}: the network gives NaN or Inf transfer inside its segment's box")
    finally:
        engine.close()
    return scene


def run(scene_paths, settings: Settings, log=print, executor=None) -> dict:
    """Benchmark every scene; the report described in the module docstring.

    Every scene is checked first (:func:`check_scene`); one that fails then, or while it is
    measured, is left out of the measurements and listed in the report's ``failed``
    (``{"scene": path, "error": one line}``); the others are measured as usual.

    Parameters
    ----------
    scene_paths : list of path-like
    settings : Settings
    log : callable
        Receives one progress line at a time.

    Returns
    -------
    dict
    """
    settings.cache = Path(settings.cache or Path(tempfile.gettempdir()) / "prt_bench_cache")
    failed: list[dict] = []
    valid = []
    for path in scene_paths:
        try:
            check_scene(path, settings)
            valid.append(path)
        except PRTError as exc:
            failed.append({"scene": str(path), "error": str(exc)})
            log(f"scene {path}: skipped: {exc}")
    if not valid:
        return {"tool": "prt-bench", "created": datetime.datetime.now().isoformat(timespec="seconds"), "scenes": [],
                "records": [], "failed": failed}  # fmt: skip
    load_start = os.getloadavg()[0]
    if load_start > 0.5:
        log(f"note: load average {load_start:.2f} at the start: other work on this machine will slow the timings")
    busy_start = busy_seconds()
    t0 = time.perf_counter()
    gemm = machine_gemm(settings.gemm_size)
    machine_gflops = gemm["best"]
    log(f"machine: float32 GEMM {settings.gemm_size}^3: numpy {gemm['numpy']:.1f}, onnxruntime {gemm['onnxruntime']:.1f} GFLOP/s "
        f"({time.perf_counter() - t0:.1f} s); the limit is the higher")
    ctx = create_context(device=settings.gl_device, origin="--gl-device")
    try:
        machine = {
            "cpu": cpu_name(), "cores": os.cpu_count(), "gl_renderer": ctx.info.get("GL_RENDERER"),
            "onnxruntime": onnxruntime.__version__, "numpy": np.__version__,
            "gemm_size": settings.gemm_size, "gemm_numpy_gflops": gemm["numpy"],
            "gemm_onnxruntime_gflops": gemm["onnxruntime"], "machine_gflops": machine_gflops,
        }  # fmt: skip
        scenes, records, resumed = [], [], []
        # numpy's BLAS threads also run the renderer's small shading products (None: as found).
        limits = threadpool_limits(limits=settings.blas_threads, user_api="blas") if settings.blas_threads else None
        try:
            for path in valid:
                # Each finished scene is kept, so an interrupted run resumes at the scene it was on.
                checkpoint = scene_checkpoint(path, settings)
                if checkpoint.exists() and not settings.fresh:
                    kept = json.loads(checkpoint.read_text())
                    entry, recs = kept["scene"], kept["records"]
                    entry.setdefault("error_images", [])
                    resumed.append({"scene": entry["scene"], "measured": entry["measured"]})
                    log(f"scene {path}: measured at {entry['measured']} (against a {recs[0]['machine_gflops'] if recs else '?'} "
                        f"GFLOP/s limit), kept in {checkpoint}; --fresh measures it again")  # fmt: skip
                else:
                    log(f"scene {path}")
                    try:
                        entry, recs = SceneBench(path, settings, ctx, machine_gflops, log, executor).run()
                    except PRTError as exc:  # e.g. a frame with NaN: this scene is reported, the others measured
                        failed.append({"scene": str(path), "error": str(exc)})
                        log(f"scene {path}: failed: {exc}")
                        continue
                    entry["measured"] = datetime.datetime.now().isoformat(timespec="seconds")
                    entry["checkpoint"] = str(checkpoint)
                    atomic_write_json(checkpoint, {"scene": entry, "records": recs})
                scenes.append(entry)
                records.extend(recs)
        finally:
            if limits is not None:
                limits.restore_original_limits()
    finally:
        ctx.release()
    machine["resumed"] = resumed
    machine["load_average"] = round(load_start, 2)
    machine["other_cpu_share"] = other_cpu_share(busy_start, time.perf_counter() - t0)
    fronts = mark_pareto(records)
    config = {k: (str(v) if isinstance(v, Path) else list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()}
    return {
        "tool": "prt-bench", "created": datetime.datetime.now().isoformat(timespec="seconds"),
        "settings": config, "machine": machine, "scenes": scenes, "records": records, "pareto": fronts,
        "failed": failed,
    }  # fmt: skip
