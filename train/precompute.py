"""The precompute stage: geometry -> samples -> ray-traced transfer -> segments, on disk.

Output folder (every file written atomically; rerunning with the same settings reuses what
is there, and an interrupted transfer resumes from its finished chunks):

    precompute.json      settings, geometry summary, timings, segment table
    samples.npz          training samples: points, normals, object_ids, face_index, transfer, segment
    validation.npz       held-out samples drawn independently (another random stream), same keys
    segments.json        the segmentation: k-d tree, merges, bounds, residuals
    segment_members.npz  ``members_<s>``: indices into samples.npz of each segment (own + margin)
    preview.png          the samples splatted and shaded, for a person to look at
    cache/               finished transfer chunks
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .cache import atomic_save_npz, atomic_write_json
from .sampling import TRAIN_STREAM, VALIDATION_STREAM, sample_surface
from .segments import segment_samples
from .transfer import DEFAULT_CHUNK, compute_transfer, make_tracer

__all__ = ["PrecomputeSettings", "run_precompute", "load_precompute"]

FORMAT_VERSION = 2  # 2: samples carry the G-buffer's interpolated normals (1: face normals)


@dataclass
class PrecomputeSettings:
    """What the precompute stage does; every field is part of the cache key."""

    samples: int = 1_000_000
    validation: int = 0  # 0: 5 % of ``samples``, at least 1000
    rays: int = 512
    bands: int = 4
    seed: int = 0
    segments: int = 8
    by_object: bool = True
    merge: bool = True
    merge_tolerance: float = 0.01
    delta: float = 0.05
    chunk_size: int = DEFAULT_CHUNK

    def validation_count(self) -> int:
        return self.validation or max(1000, self.samples // 20)


def _geometry_key(geometry) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(geometry.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(geometry.mesh.faces, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(geometry.object_ids, dtype=np.int64).tobytes())
    if geometry.sdf is not None:
        h.update(geometry.sdf.glsl().encode())
    return h.hexdigest()[:16]


def run_precompute(
    geometry,
    out_dir,
    settings: PrecomputeSettings | None = None,
    *,
    threads: int | None = None,
    progress: bool = True,
    log=print,
    preview_envmap: np.ndarray | None = None,
) -> dict:
    """Run (or resume) the precompute stage for ``geometry`` into ``out_dir``.

    ``preview_envmap`` (H, W, 3) lights ``preview.png`` (default: a procedural sky).

    Returns the summary that is also written to ``precompute.json``.
    """
    settings = settings or PrecomputeSettings()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key = hashlib.sha1(
        json.dumps([_geometry_key(geometry), asdict(settings), FORMAT_VERSION]).encode()
    ).hexdigest()[:16]
    summary_path = out / "precompute.json"
    if summary_path.is_file():
        previous = json.loads(summary_path.read_text())
        if previous.get("key") == key and all((out / f).is_file() for f in previous["files"]):
            log(f"precompute: up to date in {out} (key {key})")
            return previous

    timings = {}
    tracer = make_tracer(geometry)
    t0 = time.perf_counter()
    train = sample_surface(geometry, settings.samples, seed=settings.seed, stream=TRAIN_STREAM)
    valid = sample_surface(
        geometry, settings.validation_count(), seed=settings.seed, stream=VALIDATION_STREAM
    )
    timings["sampling_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    common = dict(
        rays=settings.rays,
        bands=settings.bands,
        seed=settings.seed,
        chunk_size=settings.chunk_size,
        threads=threads,
        cache_dir=out / "cache",
        progress=progress,
        tracer=tracer,
    )
    log(f"precompute: {len(train):,} samples x {settings.rays} rays ({geometry.kind})")
    train_t = compute_transfer(geometry, train.points, train.normals, **common)
    timings["transfer_s"] = time.perf_counter() - t0
    timings["rays_per_s"] = len(train) * settings.rays / max(timings["transfer_s"], 1e-9)
    t0 = time.perf_counter()
    valid_t = compute_transfer(geometry, valid.points, valid.normals, **common)
    timings["validation_transfer_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    seg = segment_samples(
        train.points,
        train.object_ids,
        train_t,
        max_segments=settings.segments,
        by_object=settings.by_object,
        merge=settings.merge,
        merge_tolerance=settings.merge_tolerance,
        delta=settings.delta,
    )
    valid_seg = seg.assign(valid.points, valid.object_ids)
    timings["segments_s"] = time.perf_counter() - t0

    atomic_save_npz(
        out / "samples.npz",
        points=train.points,
        normals=train.normals,
        object_ids=train.object_ids,
        face_index=train.face_index,
        transfer=train_t,
        segment=seg.home,
    )
    atomic_save_npz(
        out / "validation.npz",
        points=valid.points,
        normals=valid.normals,
        object_ids=valid.object_ids,
        face_index=valid.face_index,
        transfer=valid_t,
        segment=valid_seg,
    )
    atomic_save_npz(out / "segment_members.npz", **{f"members_{s}": m for s, m in enumerate(seg.members)})
    atomic_write_json(out / "segments.json", seg.to_json())
    files = ["samples.npz", "validation.npz", "segment_members.npz", "segments.json"]
    try:
        from .preview import write_preview

        write_preview(
            out / "preview.png", train.points, train.normals, train_t, envmap=preview_envmap, area=float(geometry.mesh.area)
        )
        files.append("preview.png")
    except ImportError as exc:  # matplotlib-free installs still get the data
        log(f"precompute: no preview ({exc})")

    summary = {
        "format": FORMAT_VERSION,
        "key": key,
        "source": geometry.source,
        "geometry": geometry.summary(),
        "settings": asdict(settings),
        "validation_samples": len(valid),
        "timings": timings,
        "segments": seg.to_json()["segments"],
        "segment_notes": seg.notes,
        "files": files,
    }
    atomic_write_json(summary_path, summary)
    return summary


def load_precompute(out_dir) -> dict:
    """The arrays of a finished precompute: ``{"samples": {...}, "validation": {...}, ...}``."""
    out = Path(out_dir)
    with np.load(out / "samples.npz") as f:
        samples = dict(f)
    with np.load(out / "validation.npz") as f:
        validation = dict(f)
    with np.load(out / "segment_members.npz") as f:
        members = [f[f"members_{s}"] for s in range(len(f.files))]
    return {
        "samples": samples,
        "validation": validation,
        "members": members,
        "segments": json.loads((out / "segments.json").read_text()),
        "summary": json.loads((out / "precompute.json").read_text()),
    }
