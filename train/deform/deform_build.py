"""Building a deformable scene: transfer that follows the shape (``prt-train INPUT --deform ...``).

One mesh with a fixed topology and a set of poses (:mod:`prt.train.deform.deform_sources`: a folder of
frames, a skinned or morphing glTF clip, a procedural deformer).  The networks learn

    T = sigma(rest position, deformed normal, theta)

with ``theta`` the shape code of :mod:`prt.runtime.deformation` (PCA of the vertex offsets over the
training frames, scaled to [-1, 1]): fixed memory whatever the number of frames.

Stages, each cached in OUTDIR (rerun the command to resume):

1. frames: the source normalised into the scene box (one transform for every pose), split into
   training frames, unseen frames between them (every ``holdout_every``-th) and extrapolated ones
   (the last ``extrapolate``: poses past the training range); the shape code from the training frames.
2. precompute, per frame: area-uniform samples on the deformed surface (their rest positions by
   barycentric weights, the G-buffer's normals of that pose), ray-traced transfer against that
   pose (``precompute/frames/fNNN.npz``, transfer chunks under ``precompute/cache``).
3. segments: the k-d split of the rest positions (static: the runtime's segment rule applies to
   the rest position the G-buffer carries).
4. one shape-conditioned network per segment (``train/segNNN.npz``).
5. export: ONNX (``code`` input), compact GLSL (the code enters through the first layer's bias
   texels), ``deformation.npz``, ``scene.json`` with its ``deformation`` record.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import trimesh
from tqdm import tqdm

from ...export.scene import TrainedSegment, export_scene
from ...runtime.camera import DEFAULT_CAMERA
from ...runtime.deformation import MAX_CODE_DIM
from ...runtime.errors import SpecError
from ...runtime.files import atomic_save_npz, atomic_write_json
from ..build import _env_lights
from ..networks.fit import FitSettings, fit_segment
from ..inputs.geometry import Geometry, _listed
from .deform_sources import orientation
from ..networks.network import Architecture, evaluate_numpy
from ..outdir import check_output_folder, mark_output_folder
from ..networks.rightsize import SCENE_LIGHT, residual_choice, shaded_psnr
from ..inputs.sampling import sample_surface
from ..networks.segments import SPLIT_RULE, segment_samples
from ..transport.transfer import compute_transfer

__all__ = ["DeformSpec", "shape_code", "split_frames", "run_deform_build", "DEFORM_FORMAT"]

DEFORM_FORMAT = 1
TRAIN_STREAM, VALID_STREAM = 11, 12


@dataclass(frozen=True)
class DeformSpec:
    """What a deformable build does (the ``prt-train --deform`` flags)."""

    samples: int = 20_000  # training samples per training frame
    validation: int = 2_000  # held-out samples per frame (every frame: training, unseen, extrapolated)
    rays: int = 256
    bands: int = 4
    segments: int = 4  # k-d leaf budget over the rest positions
    hidden: int = 64
    layers: int = 4
    pos_freqs: int = 6
    normal_freqs: int = 2
    code_dim: int = 0  # 0: the fewest PCA components that keep 99.9 % of the offsets' variance (at most 8)
    code_freqs: int = 0  # sin/cos frequencies of the code in the first layer; 0: theta alone (smooth in the code, no aliasing past the range)
    code_scale: str = "common"  # "common": one scale for every PCA component (the offsets' geometry); "component": each to [-1, 1]
    residual: str = "off"  # "on": networks learn T - U(n), U the posed normal's unshadowed transfer; "auto": where a segment's visibility >= 0.8
    steps: int = 3000
    batch: int = 8192  # samples per Adam step
    holdout_every: int = 4
    extrapolate: int = 1  # poses held out past the training range: the most extreme ones (farthest from the mean pose)
    extrapolate_from: str = "extreme"  # or "first" / "last": the first or last frames of the source's order
    seed: int = 0
    chunk_size: int = 4096
    material: dict = field(default_factory=lambda: {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]})
    camera: dict = field(default_factory=dict)

    def check(self) -> None:
        for name in ("samples", "validation", "rays", "segments", "hidden", "layers", "steps", "batch", "holdout_every", "chunk_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise SpecError(f"deform {name}: expected a positive integer, got {value!r}")
        for name, low, high in (("code_dim", 0, MAX_CODE_DIM), ("code_freqs", 0, 6), ("extrapolate", 0, 10_000),
                                ("pos_freqs", 0, 12), ("normal_freqs", 0, 8)):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise SpecError(f"deform {name}: expected an integer in {low}..{high}, got {value!r}")
        if self.code_scale not in ("common", "component"):
            raise SpecError(f"deform code_scale: expected common or component, got {self.code_scale!r}")
        if self.residual not in ("auto", "on", "off"):
            raise SpecError(f"deform residual: expected auto, on or off, got {self.residual!r}")
        if self.residual == "on" and self.bands > 4:
            raise SpecError(f"deform residual on: the unshadowed transfer is a quadratic of the normal up to 4 bands, not {self.bands}")
        if self.extrapolate_from not in ("extreme", "first", "last"):
            raise SpecError(f"deform extrapolate_from: expected extreme, first or last, got {self.extrapolate_from!r}")


def split_frames(count: int, holdout_every: int, extrapolate: int, extremeness: np.ndarray | None = None) -> dict[str, list[int]]:
    """Frame indices by role: ``extrapolated`` (the ``extrapolate`` most extreme poses: the largest
    ``extremeness``, e.g. the distance of a pose's offsets from the mean pose; without it the last
    frames), ``unseen`` (between training poses: every ``holdout_every``-th of the others from the
    middle of the first period, never the first frame) and ``train`` (the rest).  SpecError when
    fewer than 2 would train."""
    if extremeness is None:
        last = list(range(max(count - extrapolate, 0), count))
    else:
        last = sorted(np.argsort(-np.asarray(extremeness, np.float64), kind="stable")[:extrapolate].tolist())
    inner = [i for i in range(count) if i not in last]
    unseen = [i for k, i in enumerate(inner) if holdout_every > 1 and k > 0 and k % holdout_every == holdout_every // 2] if len(inner) > 2 else []
    train = [i for i in inner if i not in unseen]
    if len(train) < 2:
        raise SpecError(f"deform: {count} frames leave {len(train)} to train on (holdout every {holdout_every}, {extrapolate} extrapolated); "
                        "give more frames")  # fmt: skip
    return {"train": train, "unseen": unseen, "extrapolated": last}


def shape_code(rest: np.ndarray, frames: np.ndarray, train: list[int], dim: int = 0, keep: float = 0.999, max_auto: int = 8,
               scale: str = "common") -> dict:  # fmt: skip
    """The shape code of :mod:`prt.runtime.deformation`: PCA of the offsets ``frame - rest`` over the
    training frames.

    ``scale``: ``"common"`` divides every component by one number, the largest magnitude of the
    first component on the training frames, so the code keeps the offsets' geometry (a component
    with 1 % of the variance spans a tenth of the first one's range, and distances between codes
    are distances between shapes); ``"component"`` (builds before issue 38) divides each by its
    own largest magnitude, so every component spans [-1, 1] however little it moves the mesh.

    Returns ``theta`` (K, d) for every frame, ``mean`` (V, 3), ``basis`` (d, V, 3) with the scale folded
    in (``offset ~ mean + theta @ basis``), ``explained`` (variance share kept), ``dim`` and ``scale``.
    """
    if scale not in ("common", "component"):
        raise SpecError(f"deform code scale: expected common or component, got {scale!r}")
    offsets = (np.asarray(frames, np.float64) - np.asarray(rest, np.float64)[None]).reshape(len(frames), -1)
    mean = offsets[train].mean(axis=0)
    centred = offsets[train] - mean
    _, sing, vt = np.linalg.svd(centred, full_matrices=False)
    var = sing**2
    total = float(var.sum())
    rank = int(np.count_nonzero(sing > 1e-9 * max(float(sing[0]) if len(sing) else 0.0, 1e-30)))
    if dim <= 0:
        share = np.cumsum(var) / total if total > 0 else np.ones(len(var))
        dim = int(np.searchsorted(share, keep) + 1) if total > 0 else 1
        dim = max(1, min(dim, max_auto, max(rank, 1)))
    dim = min(dim, len(vt))
    comps = vt[:dim]
    coeffs = (offsets - mean) @ comps.T  # (K, d)
    spans = np.maximum(np.abs(coeffs[train]).max(axis=0), 1e-9)
    factor = spans if scale == "component" else np.full(dim, spans[0])
    theta = coeffs / factor
    basis = (comps * factor[:, None]).reshape(dim, -1, 3)
    explained = float(var[:dim].sum() / total) if total > 0 else 1.0
    return {"theta": theta.astype(np.float32), "mean": mean.reshape(-1, 3).astype(np.float32), "basis": basis.astype(np.float32),
            "explained": explained, "dim": dim, "scale": scale}  # fmt: skip


def _hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _pose_geometry(vertices: np.ndarray, faces: np.ndarray, two_sided: np.ndarray, source: str) -> Geometry:
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=faces, process=False, validate=False)
    return Geometry(mesh=mesh, object_ids=np.zeros(len(faces), np.int64), object_names=["object"], two_sided=two_sided,
                    to_source=np.eye(4), source=source)  # fmt: skip


def _frame_samples(pose: Geometry, rest: np.ndarray, faces: np.ndarray, count: int, seed: int, stream: int):
    s = sample_surface(pose, count, seed=seed, stream=stream)
    rest_points = np.einsum("nk,nkc->nc", s.weights, rest[faces[s.face_index]]).astype(np.float32)
    return rest_points, s.points, s.normals


def _load_frame(path: Path, key: str) -> dict | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None
            return {k: data[k] for k in data.files if k != "key"}
    except Exception:  # missing, foreign or damaged (OSError, KeyError, zipfile, zlib): recomputed
        return None


def _precompute_frames(out: Path, spec: DeformSpec, rest, frames, faces, two_sided, roles, source, *, threads, progress, log) -> dict:
    """Samples and ray-traced transfer of every frame (cached per frame), and each frame's cache key."""
    folder = out / "precompute" / "frames"
    folder.mkdir(parents=True, exist_ok=True)
    data, keys = {}, {}
    for role, indices in roles.items():
        for f in indices:
            key = _hash(DEFORM_FORMAT, spec.samples if role == "train" else 0, spec.validation, spec.rays, spec.bands, spec.seed,
                        spec.chunk_size, _digest(frames[f]), _digest(faces))  # fmt: skip
            path = folder / f"f{f:04d}.npz"
            keys[f] = key
            found = _load_frame(path, key)
            if found is not None:
                data[f] = found
                continue
            t0 = time.perf_counter()
            pose = _pose_geometry(frames[f], faces, two_sided, f"{source} frame {f}")
            parts = {}
            for part, count, stream in (("train", spec.samples if role == "train" else 0, TRAIN_STREAM), ("valid", spec.validation, VALID_STREAM)):
                if not count:
                    continue
                rest_p, points, normals = _frame_samples(pose, rest, faces, count, spec.seed + 7919 * f, stream)
                transfer = compute_transfer(pose, points, normals, spec.rays, spec.bands, seed=spec.seed + f, chunk_size=spec.chunk_size,
                                            threads=threads, cache_dir=out / "precompute" / "cache", progress=progress)  # fmt: skip
                parts |= {f"{part}_rest": rest_p, f"{part}_normals": normals.astype(np.float32), f"{part}_transfer": transfer.astype(np.float32)}
            atomic_save_npz(path, key=np.array(key), **parts)
            data[f] = parts
            log(f"frame {f} ({role}): {sum(len(v) for k, v in parts.items() if k.endswith('_rest')):,} samples traced in {time.perf_counter() - t0:.1f} s")
    return data, keys


def _digest(a: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def run_deform_build(source, out_dir, spec: DeformSpec | None = None, *, name: str | None = None, threads: int | None = None,
                     progress: bool = True, log=print, force: bool = False) -> dict:  # fmt: skip
    """Build (or resume) a deformable scene from a :class:`prt.train.deform.deform_sources.DeformSource`;
    returns the report written to ``build.json``."""
    spec = spec or DeformSpec()
    spec.check()
    t_start = time.perf_counter()
    out = Path(out_dir)
    check_output_folder(out, "scene", force=force)
    if threads:
        torch.set_num_threads(threads)
    normalised, transform = source.normalised()
    rest = np.asarray(normalised.rest, np.float64)
    frames = np.asarray(normalised.frames, np.float64)
    faces = np.asarray(normalised.faces, np.int64)
    faces, two_sided = orientation(rest, faces)
    offsets = (frames - rest[None]).reshape(len(frames), -1)
    extremeness = {"extreme": np.linalg.norm(offsets - offsets.mean(axis=0), axis=1), "last": np.arange(len(frames), dtype=float),
                   "first": -np.arange(len(frames), dtype=float)}[spec.extrapolate_from]  # fmt: skip
    roles = split_frames(len(frames), spec.holdout_every, spec.extrapolate, extremeness)
    code = shape_code(rest, frames, roles["train"], spec.code_dim, scale=spec.code_scale)
    theta = code["theta"]
    name = name or Path(str(source.description.get("path", "deformable"))).stem or "deformable"
    log(f"deform: {source.kind} source, {len(rest):,} vertices, {len(faces):,} triangles, {len(frames)} frames "
        f"({len(roles['train'])} train, {len(roles['unseen'])} unseen, {len(roles['extrapolated'])} extrapolated); "
        f"shape code: {code['dim']} PCA components ({100 * code['explained']:.2f} % of the offsets' variance)")  # fmt: skip
    opaque = source.description.get("drawn_opaque")
    if opaque:
        log(f"warning: {len(opaque)} primitives have alpha-masked or see-through materials; a deformable build draws and traces them "
            f"opaque: {_listed(opaque)}")  # fmt: skip
    mark_output_folder(out, "scene")

    t0 = time.perf_counter()
    data, frame_keys = _precompute_frames(out, spec, rest, frames, faces, two_sided, roles, name, threads=threads, progress=progress, log=log)
    precompute_s = time.perf_counter() - t0

    def stack(part: str, indices: list[int]):
        cols = {k: np.concatenate([data[f][f"{part}_{k}"] for f in indices]) for k in ("rest", "normals", "transfer")}
        cols["theta"] = np.concatenate([np.repeat(theta[f][None], len(data[f][f"{part}_rest"]), axis=0) for f in indices])
        return cols

    train, valid = stack("train", roles["train"]), stack("valid", roles["train"])
    seg = segment_samples(train["rest"], np.zeros(len(train["rest"]), np.int64), train["transfer"], normals=None,
                          max_segments=spec.segments)  # posed normals at rest positions: the margin by distance
    valid_home = seg.assign(valid["rest"], np.zeros(len(valid["rest"]), np.int64))
    lights = _env_lights(spec.bands)
    arch = Architecture(hidden=spec.hidden, layers=spec.layers, pos_freqs=spec.pos_freqs, normal_freqs=spec.normal_freqs, bands=spec.bands,
                        code_dim=code["dim"], code_freqs=spec.code_freqs)  # fmt: skip
    settings = FitSettings(steps=spec.steps, seed=spec.seed, batch=spec.batch)
    t0 = time.perf_counter()
    trained, records = [], []
    data_key = _hash(DEFORM_FORMAT, [frame_keys[f] for f in sorted(data)], spec.segments, arch.as_dict(), settings.cache_key())
    if spec.code_scale != "component" or spec.residual != "off":  # builds before issue 38 keep their cached fits
        data_key = _hash(data_key, spec.code_scale, spec.residual, _digest(theta))
    if seg.moved_cuts:  # the off-plane rule changed the segments (train/networks/segments.py): fits cached before do not fit them
        data_key = _hash(data_key, SPLIT_RULE)
    for s in range(seg.count):
        members = seg.members[s]
        vmask = valid_home == s  # a segment without held-out samples validates on some of its own training samples
        v_idx = np.flatnonzero(vmask) if vmask.any() else members[: max(1, len(members) // 20)]
        vsrc = valid if vmask.any() else train
        residual, visibility = residual_choice(spec.residual, train["transfer"][members], train["normals"][members], spec.bands)
        seg_arch = dataclasses.replace(arch, residual=residual)
        key = _hash(data_key, s)
        record_path, weights_path = out / "train" / f"seg{s:03d}.json", out / "train" / f"seg{s:03d}.npz"
        record = _cached(record_path, weights_path, key)
        if record is None:
            bar = tqdm(total=spec.steps, desc=f"fit segment {s}/{seg.count}", unit="step", leave=False) if progress else None

            def advance(step, total, train_l1, val_mae, bar=bar):
                if bar is not None:
                    bar.total = total
                    bar.update(step - bar.n)
                    bar.set_postfix(val_mae=f"{val_mae:.5f}")

            result = fit_segment(train["rest"][members], train["normals"][members], train["transfer"][members],
                                 vsrc["rest"][v_idx], vsrc["normals"][v_idx], vsrc["transfer"][v_idx], seg_arch, seg.bounds[s], settings,
                                 lights=lights, codes=train["theta"][members], val_codes=vsrc["theta"][v_idx],
                                 progress=advance)  # fmt: skip
            if bar is not None:
                bar.close()
            arrays = result.model.arrays()
            record = {"key": key, "id": s, "samples": int(len(members)), "val_mae": result.val_mae, "shaded": result.shaded,
                      "arch": {**seg_arch.as_dict(), "bands": spec.bands}, "arch_label": seg_arch.label(), "seconds": result.seconds,
                      "steps": result.steps, "residual": {"used": residual, "visibility": round(visibility, 4), "mode": spec.residual}}  # fmt: skip
            (out / "train").mkdir(parents=True, exist_ok=True)
            atomic_save_npz(weights_path, **arrays)
            atomic_write_json(record_path, record)
            log(f"segment {s}: {seg_arch.label()} on {len(members):,} samples, val MAE {result.val_mae:.5f} ({result.seconds:.0f} s)")
        else:
            log(f"segment {s}: cached")
        with np.load(weights_path) as f:
            arrays = dict(f)
        records.append(record)
        trained.append(TrainedSegment(id=s, bounds=seg.bounds[s], samples=record["samples"], coeff_mae=record["val_mae"],
                                      shaded_mae=record["shaded"], arrays=arrays, architecture=record["arch"],
                                      flops_per_fragment=seg_arch.flops_per_fragment(), weight_bytes=4 * seg_arch.weight_count()))  # fmt: skip
    train_s = time.perf_counter() - t0

    frame_report = _frame_errors(data, roles, theta, seg, trained, lights, spec.bands)
    t0 = time.perf_counter()
    deformation = {
        "source": {**source.description, "normalisation": transform},
        "code": {"kind": "pca", "dim": code["dim"], "freqs": spec.code_freqs, "explained": code["explained"], "scale": code["scale"],
                 "why": "PCA of the vertex offsets over the training frames: one rule for sequences, skinning, morphs and "
                        "procedural deformers; nearby shapes get nearby codes, so unseen poses interpolate"},
        "frames": {"count": int(len(frames)), **{k: [int(i) for i in v] for k, v in roles.items()},
                   "names": list(source.frame_names), "parameters": np.asarray(source.parameters, float).tolist(),
                   "parameter_names": list(source.parameter_names)},
        "arrays": {"rest": rest.astype(np.float32), "frames": frames.astype(np.float32), "theta": theta, "mean": code["mean"], "basis": code["basis"]},
    }  # fmt: skip
    geometry = _pose_geometry(rest, faces, two_sided, name)
    geometry.to_source = _to_source(transform)
    lights_sh = lights[SCENE_LIGHT]
    export_scene(out, name=name, geometry=geometry,
                 segmentation={"roots": {int(k): v for k, v in seg.roots.items()}, "nodes": seg.nodes, "leaf_segment": np.asarray(seg.leaf_segment, np.int64)},
                 segments=trained, sh_bands=spec.bands, lighting_sh=lights_sh, material=spec.material,
                 camera=spec.camera or default_camera(frames, faces),
                 deformation=deformation)  # fmt: skip
    export_s = time.perf_counter() - t0
    report = {
        "name": name,
        "source": source.description,
        "spec": {k: v for k, v in dataclasses.asdict(spec).items()},
        "code": {k: code[k] for k in ("dim", "explained", "scale")},
        "frames": roles,
        "frame_errors": frame_report,
        "segments": [{k: v for k, v in r.items() if k != "key"} for r in records],
        "memory": {"weight_bytes": int(sum(t.weight_bytes for t in trained)), "vertices": int(len(rest)), "frames": int(len(frames)),
                   "frame_bytes": int(frames.size * 4)},  # fmt: skip
        "timings": {"precompute_s": precompute_s, "train_s": train_s, "export_s": export_s, "total_s": time.perf_counter() - t_start},
    }
    atomic_write_json(out / "build.json", report)
    return report


def default_camera(frames: np.ndarray, faces: np.ndarray) -> dict:
    """The manifest camera of a deformable object: of a few views around and above it (the default
    camera's distance), the one that sees the most surface over all poses (area facing it), so a
    flat sheet is seen from above and a standing figure from the front."""
    distance = float(np.linalg.norm(DEFAULT_CAMERA["eye"]))
    best, eye = -1.0, None
    for elevation in (10.0, 35.0, 60.0):
        for azimuth in (0.0, 30.0, -30.0):
            e, a = np.radians(elevation), np.radians(azimuth)
            d = np.array([np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)])
            seen = 0.0
            for v in frames:
                cross = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # 2 x area x normal
                seen += float(np.abs(cross @ d).sum())  # two-sided: either side may face the camera
            if seen > best * (1 + 1e-6):
                best, eye = seen, d * distance
    return {"eye": [round(float(x), 4) for x in eye], "target": [0.0, 0.0, 0.0]}


def _cached(record_path: Path, weights_path: Path, key: str) -> dict | None:
    try:
        record = json.loads(record_path.read_bytes())
        with np.load(weights_path, allow_pickle=False) as data:
            for k in data.files:
                data[k]
    except Exception:
        return None
    return record if isinstance(record, dict) and record.get("key") == key else None


def _to_source(transform: dict) -> np.ndarray:
    """Scene units to source units (``x_scene = (x - centre) * scale``)."""
    m = np.eye(4)
    m[:3, :3] /= float(transform["scale"])
    m[:3, 3] = np.asarray(transform["centre"], np.float64)
    return m


def _frame_errors(data, roles, theta, seg, trained, lights, bands) -> dict:
    """Per frame: the held-out samples' shaded, tone-mapped PSNR (dB) of the networks against the
    ray-traced transfer, under each bundled env map; means per role."""
    per_frame = {}
    for role, indices in roles.items():
        for f in indices:
            rest_p, normals, truth = data[f]["valid_rest"], data[f]["valid_normals"], data[f]["valid_transfer"]
            home = seg.assign(rest_p, np.zeros(len(rest_p), np.int64))
            pred = np.zeros_like(truth)
            for t in trained:
                m = home == t.id
                if m.any():
                    pred[m] = evaluate_numpy(t.arrays, rest_p[m], normals[m], np.repeat(theta[f][None], int(m.sum()), axis=0))
            per_frame[int(f)] = {"role": role, "psnr": shaded_psnr(pred, truth, lights, bands * bands)}
    means = {}
    for role in roles:
        rows = [v["psnr"] for v in per_frame.values() if v["role"] == role]
        if rows:
            means[role] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    return {"per_frame": per_frame, "mean": means, "metric": "held-out samples: PSNR of tone-mapped diffuse shading, dB"}
