"""Deformable scenes against the ray-traced reference and two baselines (issue 24, the bench side).

usage::

    python -m prt.bench.deform_bench scene.json [more scenes] [--json out.json] [--md out.md]
        [--images DIR] [--cache DIR] [--size 512] [--ref-rays 512] [--vertex-rays N] [--vertex-subdivide L] [--train-frames 3]
        [--lights scene venice_sunset] [--repeats 15] [--warmup 2] [--lmm-components 0] [--lmm-keep 0.999]
        [--threads N]

For a deformable scene (``prt-train INPUT --deform ...``) at the manifest camera and ``--size``, over
its unseen and extrapolated frames and ``--train-frames`` training frames spread over the rest:

- **reference**: transfer ray traced (``--ref-rays``) against the *posed* mesh at every covered
  pixel's posed position (:meth:`prt.runtime.gbuffer.GBufferPass.read_world`) and posed normal,
  shaded like the renderer (:mod:`prt.bench.reference`; cached by content under ``--cache``);
- **ours**: the renderer (ONNX backend; the GLSL backend at the same frame, reported as the max
  abs difference of the linear images);
- **nearest-frame vertex PRT**: per-vertex transfer (:func:`prt.bench.vertex_prt.vertex_transfer`)
  traced on the training pose nearest in shape code, drawn on the current pose (classic PRT, which
  does not follow the shape; ``--vertex-subdivide L`` gives both baselines a finer vertex set, the
  mesh's triangles split L times at their edge midpoints, :func:`subdivide_geometry`);
- **linear morphable model** (DeepPRT's baseline, :class:`LinearMorphableModel`): the per-vertex
  transfer of every training frame, PCA over the frames, the PCA coefficients regressed linearly on
  the shape code (least squares over the training frames), drawn as per-vertex PRT on the current pose.

Each is scored (:func:`prt.bench.metrics.image_metrics`, tone-mapped as ``prt-bench``) under every
``--lights`` entry (``scene``: the manifest's light; a bundled env-map name; ``venice_sunset``: the
shared data's map; or a path).  Frame time: in one run, alternating, a static frame that re-runs
the networks (a tiny camera move) and a frame with a new pose, ``--repeats`` of each after
``--warmup``; their median ratio is the cost of a pose change (target <= 1.5).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from prt.bench.metrics import image_metrics
from prt.bench.provenance import provenance
from prt.bench.reference import cached_transfer, mesh_checksum, shade_image
from prt.bench.report import ERROR_MAP_MAX
from prt.bench.vertex_prt import VertexPRT, vertex_transfer
from prt.runtime.envmaps import BUNDLED_ENVMAPS, bundled_envmap_path
from prt.runtime.errors import InputError, PRTError
from prt.runtime.files import atomic_write_bytes, atomic_write_json
from prt.runtime.gbuffer import load_mesh
from prt.runtime.renderer import Renderer, Scene, make_current
from prt.runtime.shading import shade, tonemap
from prt.train.inputs.geometry import Geometry
from prt.train.transport.transfer import make_tracer

__all__ = ["Settings", "LinearMorphableModel", "fit_lmm", "nearest_training_frame", "select_frames", "posed_geometry",
           "rest_geometry", "subdivide_geometry", "resolve_light", "frame_times", "DeformBench", "run", "markdown", "parse_args", "main", "METHODS", "TARGETS"]

METHODS = ("ours", "nearest_vertex", "lmm")
ROLES = ("train", "unseen", "extrapolated")
SHARED_ENVMAPS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "envmaps"
TARGETS = {"unseen_gap_db": 2.0, "unseen_ssim": 0.99, "bytes": 1_000_000, "pose_ratio": 1.5, "train_vs_nearest_db": -0.5}


@dataclass
class Settings:
    """What to measure (the command line's options)."""

    size: int = 512
    ref_rays: int = 512
    vertex_rays: int | None = None  # rays of the baselines' vertex transfer (None: ref_rays)
    vertex_subdivide: int = 0  # midpoint subdivisions of the baselines' mesh (0: the scene's own vertices)
    train_frames: int = 3  # training frames measured beside the unseen and extrapolated ones
    lights: tuple = ("scene", "venice_sunset")
    repeats: int = 15
    warmup: int = 2
    lmm_components: int = 0  # 0: the fewest that keep lmm_keep of the variance
    lmm_keep: float = 0.999
    backends: tuple = ("onnx", "glsl")
    cache: Path | None = None
    images: Path | None = None
    threads: int | None = None
    seed: int = 0


# ------------------------------------------------------------------ the linear morphable model


@dataclass
class LinearMorphableModel:
    """Per-vertex transfer as a linear function of the shape code: ``mean + ([1, theta] @ regression) @ basis``.

    Attributes
    ----------
    mean : (D,) float64, the training frames' mean transfer (D = V x C, flattened)
    basis : (K, D) float64, the PCA components over the training frames
    regression : (d + 1, K) float64, least-squares map from ``[1, theta]`` to PCA coefficients
    coeffs : (Kt, K) float64, the training frames' own PCA coefficients
    shape : (V, C), one frame's transfer
    explained : float, variance share the K components keep
    """

    mean: np.ndarray
    basis: np.ndarray
    regression: np.ndarray
    coeffs: np.ndarray
    shape: tuple
    explained: float

    @property
    def components(self) -> int:
        return int(self.basis.shape[0])

    def reconstruct(self, coeffs: np.ndarray) -> np.ndarray:
        """(V, C) transfer of PCA coefficients (K,)."""
        return (self.mean + np.asarray(coeffs, np.float64) @ self.basis).reshape(self.shape)

    def predict(self, theta) -> np.ndarray:
        """(V, C) transfer of a shape code (d,)."""
        features = np.concatenate([[1.0], np.asarray(theta, np.float64).reshape(-1)])
        return self.reconstruct(features @ self.regression)

    def stored_bytes(self, rows: int, columns: int = 16) -> int:
        """float32 bytes of the mean and basis for ``rows`` stored vertex rows of ``columns`` values, plus the regression."""
        return 4 * (rows * columns * (self.components + 1) + self.regression.size)


def fit_lmm(transfers, theta, components: int = 0, keep: float = 0.999) -> LinearMorphableModel:
    """The linear morphable model of training frames' per-vertex transfer.

    Parameters
    ----------
    transfers : (Kt, V, C)
        Per-vertex transfer of each training frame.
    theta : (Kt, d)
        Their shape codes.
    components : int
        PCA components K (at most Kt - 1); 0: the fewest that keep ``keep`` of the variance.
    keep : float
        Variance share of the automatic choice.
    """
    x = np.asarray(transfers, np.float64)
    codes = np.asarray(theta, np.float64)
    if x.ndim != 3 or codes.ndim != 2 or len(x) != len(codes) or len(x) < 2:
        raise InputError(f"linear morphable model: needs (Kt, V, C) transfers and (Kt, d) codes with Kt >= 2, got {x.shape} and {codes.shape}")
    flat = x.reshape(len(x), -1)
    mean = flat.mean(axis=0)
    _, sing, vt = np.linalg.svd(flat - mean, full_matrices=False)
    var = sing**2
    total = float(var.sum())
    most = len(x) - 1
    if components <= 0:
        share = np.cumsum(var) / total if total > 0 else np.ones(len(var))
        components = int(np.searchsorted(share[:most], keep - 1e-12) + 1) if total > 0 else 1
    k = int(min(max(components, 1), most))
    basis = vt[:k]
    coeffs = (flat - mean) @ basis.T
    design = np.concatenate([np.ones((len(codes), 1)), codes], axis=1)
    regression = np.linalg.lstsq(design, coeffs, rcond=None)[0]
    explained = float(var[:k].sum() / total) if total > 0 else 1.0
    return LinearMorphableModel(mean, basis, regression, coeffs, tuple(x.shape[1:]), explained)


# ------------------------------------------------------------------ frames, poses, lights


def nearest_training_frame(theta, codes, train: list[int]) -> int:
    """The training frame whose shape code is nearest (Euclidean) to ``theta`` (ties: the first)."""
    distances = np.linalg.norm(np.asarray(codes, np.float64)[train] - np.asarray(theta, np.float64)[None], axis=1)
    return int(train[int(np.argmin(distances))])


def select_frames(roles: dict, train_frames: int) -> dict:
    """Frames measured by role: ``train_frames`` training frames spread evenly, every unseen and extrapolated one."""
    train = list(roles.get("train", []))
    n = min(max(int(train_frames), 0), len(train))
    picked = sorted({train[int(round(i))] for i in np.linspace(0, len(train) - 1, n)}) if n else []
    return {"train": picked, "unseen": list(roles.get("unseen", [])), "extrapolated": list(roles.get("extrapolated", []))}


def posed_geometry(geometry, vertices):
    """``geometry`` (a mesh scene's) with its mesh moved to ``vertices`` (V, 3): same faces, sidedness, objects."""
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(geometry.mesh.faces), process=False, validate=False)
    return dataclasses.replace(geometry, mesh=mesh)


def subdivide_geometry(geometry, levels: int):
    """``geometry`` with every triangle split into 4 at its edge midpoints, ``levels`` times.

    The new vertices are means of two old ones and the topology depends on the faces alone, so
    subdividing each pose gives one mesh family whose poses are linear in the coarse ones (the
    baselines' finer vertex set on the same surface).  Face ``i``'s four children are rows
    ``4 i .. 4 i + 3`` (:func:`trimesh.remesh.subdivide`), so sidedness and objects repeat by 4.
    """
    vertices, faces = np.asarray(geometry.mesh.vertices, np.float64), np.asarray(geometry.mesh.faces, np.int64)
    two_sided, object_ids = np.asarray(geometry.two_sided, bool), np.asarray(geometry.object_ids, np.int64)
    for _ in range(int(levels)):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
        two_sided, object_ids = np.repeat(two_sided, 4), np.repeat(object_ids, 4)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False, validate=False)
    return dataclasses.replace(geometry, mesh=mesh, two_sided=two_sided, object_ids=object_ids)


def rest_geometry(manifest) -> Geometry:
    """A deformable scene's rest mesh (``geometry.npz``) as a :class:`prt.train.inputs.geometry.Geometry` for tracing."""
    if manifest.geometry.type != "mesh":
        raise InputError(f"{manifest.path}: a deformable scene's geometry is a mesh, found {manifest.geometry.type!r}")
    mesh = load_mesh(manifest.geometry.path)
    n_faces = len(mesh["faces"])
    names = list(manifest.geometry.objects or [f"object{i}" for i in range(int(mesh["object_ids"].max(initial=0)) + 1)])
    return Geometry(mesh=trimesh.Trimesh(vertices=mesh["vertices"].astype(np.float64), faces=mesh["faces"], process=False, validate=False),
                    object_ids=mesh["object_ids"].astype(np.int64), object_names=names, two_sided=mesh["two_sided"].reshape(n_faces).astype(bool),
                    to_source=np.asarray(manifest.geometry.to_source, np.float64), source=str(manifest.geometry.path))  # fmt: skip


def resolve_light(spec: str) -> tuple[str, Path | None]:
    """``(label, env-map path)`` of a ``--lights`` entry; ``scene`` has no path (the manifest's light).

    An entry is ``scene``, a bundled env-map name, a name of the shared data's maps
    (``venice_sunset`` -> ``shared/data/envmaps/venice_sunset_1k.hdr``) or a file path.
    """
    if spec == "scene":
        return "scene", None
    if spec in BUNDLED_ENVMAPS:
        return spec, bundled_envmap_path(spec)
    shared = SHARED_ENVMAPS / f"{spec}_1k.hdr"
    if shared.is_file():
        return spec, shared
    path = Path(spec)
    if path.is_file():
        return path.stem, path
    raise InputError(f"--lights: {spec!r} is not 'scene', a bundled env map ({', '.join(BUNDLED_ENVMAPS)}), "
                     f"a map in {SHARED_ENVMAPS} or an existing file")  # fmt: skip


def apply_light(renderer: Renderer, path: Path | None) -> None:
    """Light ``renderer`` by an env-map file, or (``None``) by its scene's own light as the renderer starts with."""
    lighting = renderer.scene.manifest.lighting
    if path is not None:
        renderer.set_envmap(path)
    elif lighting.sh is not None:
        renderer.set_lighting_sh(lighting.sh, rotation=lighting.rotation)
    elif lighting.envmap is not None:
        renderer.set_envmap(lighting.envmap, rotation=lighting.rotation)
    else:
        renderer.set_envmap(next(iter(BUNDLED_ENVMAPS)))


# ------------------------------------------------------------------ frame time


def frame_times(renderer: Renderer, frames: list[int], repeats: int, warmup: int) -> dict:
    """Static against new-pose frame time, alternating in one run.

    Each round renders (a) a static frame that re-runs the networks (the camera turned by
    +-1e-3 rad, which invalidates the transfer) and (b) a frame with the next of ``frames``
    (``set_deformation`` + render).  Wall times of ``repeats`` rounds after ``warmup``.

    Returns
    -------
    dict
        ``static_ms``, ``pose_ms`` (medians), ``ratio`` (pose / static), ``repeats``, and the
        renderer's stage medians for each (``static_stages_ms``, ``pose_stages_ms``).
    """
    camera = renderer.camera
    static, pose, static_stages, pose_stages = [], [], [], []
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        renderer.set_camera_object(camera.orbit(1e-3 if i % 2 else -1e-3))
        renderer.render()
        t1 = time.perf_counter()
        a = dict(renderer.timings)
        renderer.set_deformation(frame=frames[i % len(frames)])
        renderer.render()
        t2 = time.perf_counter()
        if i >= warmup:
            static.append(1e3 * (t1 - t0))
            pose.append(1e3 * (t2 - t1))
            static_stages.append(a)
            pose_stages.append(dict(renderer.timings))
    renderer.set_camera_object(camera)

    def stages(rows):
        return {k: round(float(np.median([r.get(k, 0.0) for r in rows])), 3) for k in rows[0]}

    a_ms, b_ms = float(np.median(static)), float(np.median(pose))
    return {"static_ms": round(a_ms, 3), "pose_ms": round(b_ms, 3), "ratio": round(b_ms / a_ms, 4), "repeats": int(repeats),
            "static_stages_ms": stages(static_stages), "pose_stages_ms": stages(pose_stages)}  # fmt: skip


# ------------------------------------------------------------------ one scene


@dataclass
class Pixels:
    """What the reference and the baselines shade: posed position, posed normal, coverage (H, W)."""

    position: np.ndarray
    normal: np.ndarray
    covered: np.ndarray


class DeformBench:
    """One deformable scene measured frame by frame (see the module docstring).

    Parameters
    ----------
    scene_path : path-like
    settings : Settings
    log : callable
    """

    def __init__(self, scene_path, settings: Settings, log=print):
        self.settings, self.log = settings, log
        self.scene = Scene.load(scene_path)
        self.manifest = m = self.scene.manifest
        self.deformation = self.scene.deformation
        if self.deformation is None or m.deformation is None:
            raise InputError(f"{m.path}: not a deformable scene (built without --deform)")
        self.geometry = rest_geometry(m)
        self.faces = np.asarray(self.geometry.mesh.faces, np.int64)
        self.roles = {r: [int(i) for i in m.deformation.frames.get(r, [])] for r in ROLES}
        if len(self.roles["train"]) < 2:
            raise InputError(f"{m.path}: deformation.frames.train lists {len(self.roles['train'])} frames, the baselines need 2")
        self.lights = [resolve_light(s) for s in settings.lights]
        cache = settings.cache if settings.cache is not None else Path(tempfile.mkdtemp(prefix="prt-deform-bench-"))
        self.transfer_cache = Path(cache) / "transfer"
        self.transfer_cache.mkdir(parents=True, exist_ok=True)
        self.vertex_rays = settings.vertex_rays or settings.ref_rays

    def pose(self, frame: int):
        """The posed geometry of a recorded frame and its checksum."""
        vertices = self.deformation.frames[frame]
        return posed_geometry(self.geometry, vertices), mesh_checksum(vertices, self.faces)

    def vertex_pose(self, frame: int):
        """The baselines' mesh at a recorded frame (``--vertex-subdivide`` times subdivided) and its checksum."""
        geometry = subdivide_geometry(self.pose(frame)[0], self.settings.vertex_subdivide)
        return geometry, mesh_checksum(geometry.mesh.vertices, geometry.mesh.faces)

    def vertex_frames(self) -> tuple[dict, int]:
        """Per-vertex transfer (front | back, (V, 32)) of every training frame, and the vertices with a back side."""
        out, back_vertices = {}, 0
        for f in self.roles["train"]:
            geometry, checksum = self.vertex_pose(f)
            front, back, back_vertices = vertex_transfer(geometry, make_tracer(geometry), self.vertex_rays, self.transfer_cache, checksum)
            out[f] = np.concatenate([front, back], axis=1)
        return out, back_vertices

    def reference(self, frame: int, pixels: Pixels, seed: int) -> np.ndarray:
        """Ray-traced transfer (M, 16) of the covered pixels against the posed mesh."""
        geometry, checksum = self.pose(frame)
        cov = pixels.covered
        transfer, seconds = cached_transfer(self.transfer_cache, f"{self.manifest.name}-f{frame:04d}-{self.settings.size}", geometry,
                                            make_tracer(geometry), pixels.position[cov], pixels.normal[cov], self.settings.ref_rays,
                                            seed, checksum)  # fmt: skip
        if seconds:
            self.log(f"  frame {frame}: reference traced in {seconds:.1f} s")
        return transfer

    def vertex_image(self, ctx, frame: int, transfer: np.ndarray, camera, pixels: Pixels, lighting, material) -> np.ndarray:
        """Linear (H, W, 3) image of per-vertex transfer (V, 32: front | back) drawn on frame ``frame``'s pose."""
        make_current(ctx)
        size = self.settings.size
        vertex = VertexPRT(ctx, self.vertex_pose(frame)[0], transfer[:, :16], transfer[:, 16:], size, size)
        try:
            image, _ = vertex.render(camera)
        finally:
            vertex.release()
        out = np.zeros((size, size, 3), np.float32)
        cov = pixels.covered
        out[cov] = shade(image[cov], pixels.normal[cov], camera.eye[None, :] - pixels.position[cov], lighting, material)
        return out

    def run(self) -> dict:
        """Measure every selected frame; the scene's report entry (with ``_strip`` images for the figure)."""
        s, m = self.settings, self.manifest
        vertex, back_vertices = self.vertex_frames()
        train = self.roles["train"]
        theta = self.deformation.theta
        lmm = fit_lmm(np.stack([vertex[f] for f in train]), theta[train], s.lmm_components, s.lmm_keep)
        renderers = {b: Renderer(self.scene, s.size, s.size, backend=b, threads=s.threads) for b in s.backends}
        try:
            for r in renderers.values():
                r.set_background(False)
            frames, strip = [], {}
            for role, indices in select_frames(self.roles, s.train_frames).items():
                for f in indices:
                    record, images = self.measure_frame(renderers, f, role, vertex, lmm, noise=not frames)
                    frames.append(record)
                    if role not in strip:
                        strip[role] = (f, images)
            timing = {}
            order = sorted({f for fs in self.roles.values() for f in fs})
            for b, r in renderers.items():
                apply_light(r, None)
                r.set_deformation(frame=order[0])
                timing[b] = frame_times(r, order[1:] + order[:1], s.repeats, s.warmup)
                self.log(f"  {b}: static {timing[b]['static_ms']:.1f} ms, new pose {timing[b]['pose_ms']:.1f} ms, ratio {timing[b]['ratio']:.2f}")
        finally:
            for r in renderers.values():
                r.close()
        baseline_vertices = len(vertex[train[0]])
        rows = baseline_vertices + back_vertices
        bytes_ = {"ours": int(sum(seg.weight_bytes for seg in m.segments if seg.kind == "network")),
                  "nearest_vertex_per_frame": 4 * 16 * rows, "nearest_vertex_all_frames": 4 * 16 * rows * len(train),
                  "lmm": lmm.stored_bytes(rows)}  # fmt: skip
        entry = {
            "scene": m.name, "path": str(m.path), "size": s.size, "vertices": int(len(self.deformation.rest)), "back_vertices": int(back_vertices),
            "vertex_subdivide": s.vertex_subdivide, "baseline_vertices": int(baseline_vertices),
            "code_dim": self.deformation.dim, "roles": self.roles, "camera": {"eye": np.asarray(m.camera.eye, float).tolist(), "target": np.asarray(m.camera.target, float).tolist(), "fov": float(m.camera.fov)},
            "lights": [label for label, _ in self.lights], "ref_rays": s.ref_rays, "vertex_rays": self.vertex_rays,
            "lmm": {"components": lmm.components, "explained": round(lmm.explained, 6), "train_frames": len(train)},
            "bytes": bytes_, "frames": frames, "frame_time": timing,
        }  # fmt: skip
        entry["summary"] = summarise(entry)
        entry["_strip"] = strip
        return entry

    def measure_frame(self, renderers: dict, frame: int, role: str, vertex: dict, lmm: LinearMorphableModel,
                      noise: bool = False) -> tuple[dict, dict]:  # fmt: skip
        """One frame under every light: the record and, under the first light, the tone-mapped images of the strip.

        ``noise``: also trace a second reference (the next seed) and record the reference's own
        error (``reference_noise``: the second against the first, per light).
        """
        s = self.settings
        onnx = renderers["onnx"]
        theta = self.deformation.theta[frame]
        nearest = nearest_training_frame(theta, self.deformation.theta, self.roles["train"])
        onnx.set_deformation(frame=frame)
        apply_light(onnx, None)
        onnx.render()
        gb = onnx.gbuffer.read()
        pixels = Pixels(onnx.gbuffer.read_world().reshape(s.size, s.size, 3).copy(), gb.normal, gb.covered)
        reference = self.reference(frame, pixels, s.seed)
        other = self.reference(frame, pixels, s.seed + 1) if noise else None
        baselines = {"nearest_vertex": vertex[nearest], "lmm": lmm.predict(theta).astype(np.float32)}
        record = {"frame": int(frame), "role": role, "theta": [round(float(t), 5) for t in theta], "nearest_train_frame": nearest,
                  "covered": int(gb.covered.sum()), "metrics": {}, "glsl_max_abs_diff": {}}  # fmt: skip
        if noise:
            record["reference_noise"] = {}
        strip = {}
        for b, r in renderers.items():
            if b != "onnx":
                r.set_deformation(frame=frame)
        for label, path in self.lights:
            images = {}
            for b, r in renderers.items():
                apply_light(r, path)
                images[b] = r.render()
            ref = tonemap(shade_image(reference, pixels, onnx.camera.eye, onnx.lighting, onnx.material))
            shown = {"ours": tonemap(images["onnx"])}
            for name, transfer in baselines.items():
                shown[name] = tonemap(self.vertex_image(onnx.ctx, frame, transfer, onnx.camera, pixels, onnx.lighting, onnx.material))
            record["metrics"][label] = {k: _rounded(image_metrics(img, ref, gb.covered)) for k, img in shown.items()}
            if other is not None:
                second = tonemap(shade_image(other, pixels, onnx.camera.eye, onnx.lighting, onnx.material))
                record["reference_noise"][label] = _rounded(image_metrics(second, ref, gb.covered))
            if "glsl" in images:
                record["glsl_max_abs_diff"][label] = float(np.abs(images["glsl"] - images["onnx"]).max(initial=0.0))
            if not strip:
                strip = {"reference": ref, **shown, "covered": gb.covered}
        ours = record["metrics"][self.lights[0][0]]
        self.log(f"  frame {frame} ({role}, nearest train {nearest}): PSNR ours {ours['ours']['psnr']:.2f}, "
                 f"vertex {ours['nearest_vertex']['psnr']:.2f}, LMM {ours['lmm']['psnr']:.2f} dB")  # fmt: skip
        return record, strip


def _rounded(metrics: dict) -> dict:
    return {"psnr": round(metrics["psnr"], 3), "ssim": round(metrics["ssim"], 6), "mae": round(metrics["mae"], 6)}


def summarise(entry: dict) -> dict:
    """Means by role, method and light, and the issue's targets (each with its verdict)."""
    means: dict = {}
    for light in entry["lights"]:
        for method in METHODS:
            for role in ROLES:
                rows = [f["metrics"][light][method] for f in entry["frames"] if f["role"] == role]
                if rows:
                    means.setdefault(light, {}).setdefault(method, {})[role] = {
                        k: round(float(np.mean([r[k] for r in rows])), 6 if k == "ssim" else 3) for k in ("psnr", "ssim")}
    targets = {}
    for light, by_method in means.items():
        ours, lmm = by_method["ours"], by_method["lmm"]
        t = {}
        if "train" in ours and "unseen" in ours:
            gap = ours["train"]["psnr"] - ours["unseen"]["psnr"]
            t["unseen_gap_db"] = {"value": round(gap, 3), "target": TARGETS["unseen_gap_db"], "met": gap <= TARGETS["unseen_gap_db"]}
        if "unseen" in ours:
            value = ours["unseen"]["ssim"]
            t["unseen_ssim"] = {"value": value, "target": TARGETS["unseen_ssim"], "met": value >= TARGETS["unseen_ssim"]}
        if "extrapolated" in ours:
            lead = ours["extrapolated"]["psnr"] - lmm["extrapolated"]["psnr"]
            t["extrapolated_ours_minus_lmm_db"] = {"value": round(lead, 3), "target": 0.0, "met": lead >= 0.0}
        if "train" in ours:  # "about equal" to the nearest training frame's vertex PRT on the frames it was traced on
            lead = ours["train"]["psnr"] - by_method["nearest_vertex"]["train"]["psnr"]
            t["train_ours_minus_nearest_db"] = {"value": round(lead, 3), "target": TARGETS["train_vs_nearest_db"],
                                                "met": lead >= TARGETS["train_vs_nearest_db"]}
        targets[light] = t
    bytes_ok = entry["bytes"]["ours"] <= TARGETS["bytes"]
    ratios = {b: {"value": t["ratio"], "target": TARGETS["pose_ratio"], "met": t["ratio"] <= TARGETS["pose_ratio"]}
              for b, t in entry["frame_time"].items()}  # fmt: skip
    diffs = [v for f in entry["frames"] for v in f["glsl_max_abs_diff"].values()]
    first = entry["frames"][0] if entry["frames"] else {}
    noise = {"frame": first.get("frame"), "lights": first.get("reference_noise", {})}
    return {"means": means, "targets": targets, "reference_noise": noise, "bytes": {"value": entry["bytes"]["ours"], "target": TARGETS["bytes"], "met": bytes_ok},
            "pose_ratio": ratios, "glsl_max_abs_diff": max(diffs) if diffs else None}  # fmt: skip


# ------------------------------------------------------------------ outputs


def strip_png(strip: dict) -> bytes:
    """PNG bytes: one row per role's first frame, reference | ours | nearest-vertex | LMM | ours' error map."""
    import imageio.v3 as iio
    from matplotlib import colormaps

    rows = []
    for _, images in strip.values():
        error = np.abs(images["ours"] - images["reference"]).mean(axis=2) / ERROR_MAP_MAX
        coloured = colormaps["magma"](np.clip(error, 0.0, 1.0))[..., :3]
        coloured[~images["covered"]] = 0.8
        panels = [images[k] for k in ("reference", *METHODS)] + [coloured]
        rows.append(np.concatenate(panels, axis=1))
    pixels = (np.clip(np.concatenate(rows, axis=0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return iio.imwrite("<bytes>", pixels, extension=".png")


def markdown(report: dict) -> str:
    """The report as Markdown: per scene its frames, means, targets, bytes and frame times."""
    out = [f"# Deformable scenes ({report['date']})", ""]
    for e in report["scenes"]:
        out += [f"## {e['scene']} ({e['vertices']:,} vertices, code {e['code_dim']}-d, {e['size']}x{e['size']}, "
                f"reference {e['ref_rays']} rays, baselines on {e['baseline_vertices']:,} vertices, LMM K = {e['lmm']['components']} of {e['lmm']['train_frames']} training frames)", ""]  # fmt: skip
        for light in e["lights"]:
            out += [f"### light: {light}", "", "| frame | role | nearest train | ours PSNR / SSIM | nearest-vertex PSNR / SSIM | LMM PSNR / SSIM | glsl-onnx max diff |",
                    "|---|---|---|---|---|---|---|"]  # fmt: skip
            for f in e["frames"]:
                cells = [f"{f['metrics'][light][k]['psnr']:.2f} / {f['metrics'][light][k]['ssim']:.4f}" for k in METHODS]
                diff = f["glsl_max_abs_diff"].get(light)
                out.append(f"| {f['frame']} | {f['role']} | {f['nearest_train_frame']} | " + " | ".join(cells) + f" | {'-' if diff is None else f'{diff:.2e}'} |")
            out += ["", "| mean | " + " | ".join(f"{m} PSNR / SSIM" for m in METHODS) + " |", "|---|---|---|---|"]
            means = e["summary"]["means"][light]
            for role in ROLES:
                if role in means["ours"]:
                    out.append(f"| {role} | " + " | ".join(f"{means[m][role]['psnr']:.2f} / {means[m][role]['ssim']:.4f}" for m in METHODS) + " |")
            out += ["", "Targets: " + "; ".join(f"{k} {v['value']} (target {v['target']}: {'met' if v['met'] else 'NOT met'})"
                                                for k, v in e["summary"]["targets"][light].items()), ""]  # fmt: skip
        noise = e["summary"]["reference_noise"]
        if noise["lights"]:
            out += ["Reference noise (a second seed against the first, frame " + str(noise["frame"]) + "): " + "; ".join(
                f"{light} {v['psnr']:.2f} dB / SSIM {v['ssim']:.4f}" for light, v in noise["lights"].items()) + ".", ""]  # fmt: skip
        b = e["bytes"]
        out += [f"Bytes: ours {b['ours']:,} (target <= {TARGETS['bytes']:,}: {'met' if e['summary']['bytes']['met'] else 'NOT met'}); "
                f"nearest-frame vertex PRT {b['nearest_vertex_per_frame']:,} per frame, {b['nearest_vertex_all_frames']:,} for all training frames; "
                f"LMM {b['lmm']:,}.", ""]  # fmt: skip
        out += ["| backend | static frame (ms) | new pose (ms) | ratio (target <= 1.5) |", "|---|---|---|---|"]
        for backend, t in e["frame_time"].items():
            out.append(f"| {backend} | {t['static_ms']:.1f} | {t['pose_ms']:.1f} | {t['ratio']:.2f} |")
        out.append("")
    for failure in report["failed"]:
        out.append(f"- failed: {failure['scene']}: {failure['error']}")
    return "\n".join(out) + "\n"


def run(scene_paths, settings: Settings, log=print) -> dict:
    """Every scene measured (a failing scene is reported under ``failed`` and left out); PNG strips under ``settings.images``."""
    report = {"provenance": provenance(), "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
              "command": " ".join(sys.argv),
              "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(settings).items()},
              "targets": TARGETS, "scenes": [], "failed": []}  # fmt: skip
    for path in scene_paths:
        try:
            log(f"{path}:")
            entry = DeformBench(path, settings, log).run()
        except PRTError as exc:
            report["failed"].append({"scene": str(path), "error": " ".join(str(exc).split())})
            continue
        strip = entry.pop("_strip")
        if settings.images is not None:
            target = Path(settings.images) / f"deform_{entry['scene']}.png"
            atomic_write_bytes(target, strip_png(strip))
            entry["image"] = str(target)
        report["scenes"].append(entry)
    return report


def parse_args(argv=None) -> argparse.Namespace:
    """The command line's options, checked."""
    p = argparse.ArgumentParser(prog="prt-bench deform", description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+", type=Path, help="deformable scene.json files (or their folders)")
    p.add_argument("--json", type=Path, default=None, help="write the JSON report here")
    p.add_argument("--md", type=Path, default=None, help="write the Markdown report here")
    p.add_argument("--images", type=Path, default=None, metavar="DIR", help="write one PNG strip per scene into DIR")
    p.add_argument("--cache", type=Path, default=None, help="reference / vertex transfer cache (default: next to --json)")
    p.add_argument("--size", type=int, default=512, help="image size, square (default 512)")
    p.add_argument("--ref-rays", type=int, default=512, help="rays per pixel of the reference (default 512)")
    p.add_argument("--vertex-rays", type=int, default=None, help="rays per vertex of the baselines (default: --ref-rays)")
    p.add_argument("--vertex-subdivide", type=int, default=0, metavar="L",
                   help="split the baselines' triangles L times at their edge midpoints (default 0: the scene's vertices)")
    p.add_argument("--train-frames", type=int, default=3, help="training frames measured for comparison (default 3)")
    p.add_argument("--lights", nargs="+", default=None,
                   help="'scene' (the manifest's light), bundled env-map names, venice_sunset, or .hdr/.exr paths "
                        "(default: scene, and venice_sunset where the shared data has it)")
    p.add_argument("--repeats", type=int, default=15, help="frames of each kind timed (default 15)")
    p.add_argument("--warmup", type=int, default=2, help="untimed rounds first (default 2)")
    p.add_argument("--lmm-components", type=int, default=0, help="PCA components of the LMM (default 0: keep --lmm-keep of the variance)")
    p.add_argument("--lmm-keep", type=float, default=0.999, help="variance share of the automatic LMM size (default 0.999)")
    p.add_argument("--backends", nargs="+", choices=("onnx", "glsl"), default=["onnx", "glsl"], help="onnx is always measured")
    p.add_argument("--threads", type=int, default=None, help="CPU threads of the ONNX backend (default: all)")
    args = p.parse_args(argv)
    for flag in ("size", "ref_rays", "repeats"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag.replace('_', '-')} must be positive, got {getattr(args, flag)}")
    for flag in ("vertex_rays", "threads"):
        if getattr(args, flag) is not None and getattr(args, flag) < 1:
            p.error(f"--{flag.replace('_', '-')} must be positive, got {getattr(args, flag)}")
    if args.warmup < 0 or args.train_frames < 0 or not 0 <= args.vertex_subdivide <= 6 or args.lmm_components < 0 or not 0.0 < args.lmm_keep <= 1.0:
        p.error("--warmup, --train-frames and --lmm-components must be >= 0, --vertex-subdivide in 0..6, --lmm-keep in (0, 1]")
    args.backends = ["onnx", *(b for b in args.backends if b != "onnx")]
    return args


def main(argv=None) -> int:
    """``prt-bench deform``: measure, print the Markdown, write the reports asked for; the exit status."""
    args = parse_args(argv)
    if args.lights is None:  # the sunlit map lives in the shared data, which a user's clone lacks
        args.lights = ["scene", "venice_sunset"] if (SHARED_ENVMAPS / "venice_sunset_1k.hdr").is_file() else ["scene"]
        if len(args.lights) == 1:
            print(f"prt-bench deform: {SHARED_ENVMAPS} has no venice_sunset_1k.hdr; measuring under the scene's light only", file=sys.stderr)
    cache = args.cache if args.cache is not None or args.json is None else args.json.parent / f"{args.json.stem}_cache"
    settings = Settings(size=args.size, ref_rays=args.ref_rays, vertex_rays=args.vertex_rays, vertex_subdivide=args.vertex_subdivide, train_frames=args.train_frames,
                        lights=tuple(args.lights), repeats=args.repeats, warmup=args.warmup, lmm_components=args.lmm_components,
                        lmm_keep=args.lmm_keep, backends=tuple(args.backends), cache=cache, images=args.images, threads=args.threads)  # fmt: skip
    try:
        for light in settings.lights:
            resolve_light(light)
    except PRTError as exc:
        print(f"prt-bench deform: error: {exc}", file=sys.stderr)
        return 2
    report = run(args.scenes, settings, log=lambda text: print(text, file=sys.stderr))
    for failure in report["failed"]:
        print(f"prt-bench deform: error: {failure['error']} (scene skipped)", file=sys.stderr)
    if not report["scenes"]:
        return 2
    text = markdown(report)
    print(text)
    if args.json:
        atomic_write_json(args.json, report)
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    return 2 if report["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
