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
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...runtime.errors import PRTError, SpecError
from ..cache import atomic_save_npz, atomic_write_json
from ..outdir import check_output_folder, mark_output_folder
from ..inputs.adaptive import NEIGHBOURS, adaptive_samples
from ..inputs.sampling import TRAIN_STREAM, VALIDATION_STREAM, SurfaceSamples, sample_surface
from ..networks.segments import MARGIN_RULE, MERGE_RULE, SPLIT_BY, SPLIT_RULE, segment_samples
from ..inputs.visibility import SIDE_RULE, hidden_points, surface_sides
from .transfer import DEFAULT_CHUNK, SDF_TRACE_CHOICES, compute_transfer, make_tracer, sdf_trace_for

__all__ = ["PrecomputeSettings", "SpecLimits", "SPEC_LIMITS", "check_settings", "sample_limit", "precompute_key", "run_precompute",
           "load_precompute"]

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
    # share of ``samples`` drawn by a second pass where the first pass's transfer varies fastest
    # (prt.train.inputs.adaptive); 0: all area-uniform (and the cache key of older builds unchanged)
    adaptive: float = 0.0
    # which k-d leaf is cut next (prt.train.networks.segments.SPLIT_BY): "samples" (equal areas; the cache key
    # of older builds unchanged) or "residual" (leaves where the transfer is complex)
    split: str = "samples"
    # how SDF scenes are traced (prt.train.transport.transfer.sdf_trace_for): "auto" (the band tracer
    # where a neural SDF is in the scene), "band" or "sphere" (the plain sphere tracer); keyed by the
    # tracing rule it resolves to (mesh scenes and the sphere tracer keep the keys of older builds)
    sdf_trace: str = "auto"

    def validation_count(self) -> int:
        return self.validation or max(1000, self.samples // 20)


@dataclass(frozen=True)
class SpecLimits:
    """The largest values a build spec may ask for (the sample count's comes from memory: :func:`sample_limit`)."""

    bands: int = 8  # the manifest's sh_bands maximum
    rays: int = 1 << 16
    segments: int = 4096
    epochs: int = 1_000_000
    steps: int = 100_000_000
    batch: int = 1 << 24
    patience: int = 1_000_000
    hidden: int = 4096
    layers: int = 64
    freqs: int = 24  # 2^23 pi x: float32 position encodings are noise beyond
    seed: int = (1 << 63) - 1  # torch.manual_seed's range
    bounces: int = 16  # interreflection (prt-train --bounces); energy falls as albedo^N, 2 is the default study's pick
    bounce_rays: int = 1 << 12  # rays per sample of the bounce stage (indirect light is smooth)
    memory_share: float = 0.5  # samples + validation may take this share of physical memory


SPEC_LIMITS = SpecLimits()


def _physical_memory() -> int:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 8 << 30  # unknown: assume 8 GiB


def sample_bytes(bands: int) -> int:
    """Bytes one sample takes in ``samples.npz`` and in memory: points, normals (float32 x 3 each),
    face index, object id, segment (int64 each) and ``bands**2`` float32 transfer coefficients."""
    return 2 * 12 + 3 * 8 + 4 * bands * bands


def sample_limit(bands: int, memory: int | None = None) -> int:
    """Most samples (training + validation) a build may ask for: ``memory_share`` of physical memory
    divided by :func:`sample_bytes` (about 77 million at 4 bands on 16 GiB)."""
    memory = _physical_memory() if memory is None else memory
    return int(SPEC_LIMITS.memory_share * memory) // sample_bytes(bands)

def check_settings(settings: PrecomputeSettings, *, flags: bool = False) -> None:
    """Refuse settings that cannot work, before any work; errors name the field (``--flag`` if ``flags``).

    Counts are positive (``validation`` may be 0: automatic) and within :data:`SPEC_LIMITS`;
    samples + validation within :func:`sample_limit`; tolerances finite and non-negative.
    """

    def name(field: str) -> str:
        return "--" + field.replace("_", "-") if flags else field

    def is_int(value) -> bool:
        return isinstance(value, (int, np.integer)) and not isinstance(value, bool)

    for key in ("samples", "validation", "rays", "bands", "segments", "seed"):
        value = getattr(settings, key)
        if not is_int(value):
            raise SpecError(f"{name(key)}: expected an integer, got {value!r}")
        least = 0 if key in ("validation", "seed") else 1
        most = getattr(SPEC_LIMITS, key, None)
        if value < least or (most is not None and value > most):
            shown = f"{least} .. {most}" if most is not None else f"an integer >= {least}"
            raise SpecError(f"{name(key)}: expected {shown}, got {value}")
    total, most = settings.samples + settings.validation_count(), sample_limit(settings.bands)
    if total > most:
        raise SpecError(
            f"{name('samples')}: {settings.samples:,} samples (+ {settings.validation_count():,} validation) need "
            f"{total * sample_bytes(settings.bands) // 2**30:,} GiB; at most {most:,} fit in half of this machine's memory"
        )
    for key in ("merge_tolerance", "delta"):
        value = getattr(settings, key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise SpecError(f"{name(key)}: expected a finite non-negative number, got {value!r}")
    if settings.split not in SPLIT_BY:
        raise SpecError(f"{name('split')}: expected one of {', '.join(SPLIT_BY)}, got {settings.split!r}")
    if settings.sdf_trace not in SDF_TRACE_CHOICES:
        raise SpecError(f"{name('sdf_trace')}: expected one of {', '.join(SDF_TRACE_CHOICES)}, got {settings.sdf_trace!r}")
    share = settings.adaptive
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share <= 0.9:
        raise SpecError(f"{name('adaptive')}: expected a share of the samples in 0 .. 0.9, got {share!r}")
    if share and round(settings.samples * (1.0 - share)) < 2 * NEIGHBOURS:
        raise SpecError(f"{name('adaptive')}: the first pass needs at least {2 * NEIGHBOURS} samples, got {settings.samples} x {1 - share:g}")


def _geometry_key(geometry) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(geometry.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(geometry.mesh.faces, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(geometry.object_ids, dtype=np.int64).tobytes())
    if geometry.sdf is not None:
        h.update(geometry.sdf.glsl().encode())
    if geometry.kind == "mixed":  # the SDF objects' fields, not only their proxies
        h.update(geometry.mixed.glsl().encode())
    return h.hexdigest()[:16]


def precompute_key(geometry, settings: PrecomputeSettings, sides=None) -> str:
    """The precompute's cache key: the geometry and every setting that changes the result.

    Older builds keep their key: fields added later are keyed only when they differ from their
    default, and ``sdf_trace`` only where it resolves to the band tracer
    (:func:`prt.train.transport.transfer.sdf_trace_for`), whose hits are not the sphere tracer's bit
    for bit; mesh scenes and the sphere tracer keep the keys they had.
    """
    keyed = {k: v for k, v in asdict(settings).items() if (k != "adaptive" or v) and (k != "split" or v != "samples")
             and k != "sdf_trace"}  # fmt: skip
    if sdf_trace_for(geometry, settings.sdf_trace) == "band":
        from ..sdf.band_trace import TRACE_RULE

        keyed["sdf_trace"] = TRACE_RULE
    keyed["margin"] = MARGIN_RULE  # which neighbours' samples a segment trains on (its fits are keyed by this key)
    if settings.merge:
        keyed["merge"] = MERGE_RULE  # how far leaves merge
    if sides is not None and sides.changed:  # samples only on reachable sides (prt.train.inputs.visibility)
        keyed["sides"] = [SIDE_RULE, hashlib.sha1(np.packbits(sides.allowed).tobytes()
                                                  + np.packbits(sides.two_sided).tobytes()).hexdigest()[:16]]
    return hashlib.sha1(json.dumps([_geometry_key(geometry), keyed, FORMAT_VERSION]).encode()).hexdigest()[:16]


def run_precompute(
    geometry,
    out_dir,
    settings: PrecomputeSettings | None = None,
    *,
    threads: int | None = None,
    progress: bool = True,
    log=print,
    preview_envmap: np.ndarray | None = None,
    force: bool = False,
    executor=None,
) -> dict:
    """Run (or resume) the precompute stage for ``geometry`` into ``out_dir``.

    ``preview_envmap`` (H, W, 3) lights ``preview.png`` (default: a procedural sky).
    ``executor`` runs the transfer chunks (:mod:`prt.train.executor`; default: ``threads``
    threads here, or a Ray cluster: the results and the cache are the same either way).
    ``out_dir`` must be empty, new or a precompute folder of ours unless ``force``
    (:func:`prt.train.outdir.check_output_folder`).

    Returns the summary that is also written to ``precompute.json``.
    """
    settings = settings or PrecomputeSettings()
    out = Path(out_dir)
    check_settings(settings)
    check_output_folder(out, "precompute", force=force)
    mark_output_folder(out, "precompute")
    sides = scene_sides(geometry, seed=settings.seed, log=log)
    key = precompute_key(geometry, settings, sides)
    trace = sdf_trace_for(geometry, settings.sdf_trace)
    # Segments cut by the off-plane rule (train/networks/segments.py, split_value) where it moved a cut: then
    # the key changes, and the fits keyed by it are made anew; elsewhere the segments, the key and
    # the cached fits stay what they were.  A folder made before the rule is checked once (its
    # samples and transfer come from the chunk cache) and keeps its key where no cut moves.
    ruled = hashlib.sha1(f"{key}|{SPLIT_RULE}".encode()).hexdigest()[:16]
    summary_path = out / "precompute.json"
    previous = _read_summary(summary_path)
    if previous is not None:
        if (previous.get("key") in (key, ruled) and previous.get("split_rule") == SPLIT_RULE
                and all((out / f).is_file() for f in previous["files"])):  # fmt: skip
            log(f"precompute: up to date in {out} (key {previous['key']})")
            return previous

    timings = {}
    t0 = time.perf_counter()
    tracer = make_tracer(geometry, settings.sdf_trace, threads)
    timings["tracer_s"] = time.perf_counter() - t0
    if trace == "band":
        stats = tracer.sdf._band.band.stats if geometry.kind == "mixed" else tracer._band.band.stats
        log(f"precompute: band tracer: shells at +-{stats['delta']:.2e} ({stats['outer_faces']:,} + {stats['inner_faces']:,} "
            f"triangles), {stats['evaluated_points']:,} field samples, {timings['tracer_s']:.1f} s")  # fmt: skip
    t0 = time.perf_counter()
    first = settings.samples - int(round(settings.samples * settings.adaptive))
    allowed = sides.allowed if sides is not None and sides.changed else None
    train = sample_surface(geometry, first, seed=settings.seed, stream=TRAIN_STREAM, sides=allowed)
    valid = sample_surface(
        geometry, settings.validation_count(), seed=settings.seed, stream=VALIDATION_STREAM, sides=allowed
    )
    if allowed is not None:  # points inside other solids (interpenetrating parts): dropped
        train, valid, dropped = _drop_hidden_points(geometry, sides, train, valid, settings.seed)
        timings["hidden_points_dropped"] = dropped
        if sum(dropped):
            log(f"precompute: {dropped[0]:,} training and {dropped[1]:,} held-out samples inside other solids or in gaps drawn again")
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
        executor=executor,
    )
    log(f"precompute: {len(train):,} samples x {settings.rays} rays ({geometry.kind})")
    train_t = compute_transfer(geometry, train.points, train.normals, **common)
    if first < settings.samples:  # the second pass: where the first pass's transfer varies fastest
        extra, stats = adaptive_samples(geometry, train, train_t, settings.samples - first, seed=settings.seed)
        log(f"precompute: {len(extra):,} adaptive samples (top decile of variation drawn {stats['favoured']:.1f}x as often)")
        timings["adaptive"] = stats
        extra_t = compute_transfer(geometry, extra.points, extra.normals, **{**common, "cache_dir": out / "cache" / "adaptive"})
        train = SurfaceSamples(*(np.concatenate([a, b]) for a, b in zip(
            (train.points, train.normals, train.face_index, train.object_ids),
            (extra.points, extra.normals, extra.face_index, extra.object_ids))))  # fmt: skip
        train_t = np.concatenate([train_t, extra_t])
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
        normals=train.normals,
        max_segments=settings.segments,
        by_object=settings.by_object,
        merge=settings.merge,
        merge_tolerance=settings.merge_tolerance,
        delta=settings.delta,
        split=settings.split,
    )
    valid_seg = seg.assign(valid.points, valid.object_ids)
    timings["segments_s"] = time.perf_counter() - t0
    if seg.moved_cuts:
        log(f"precompute: {seg.moved_cuts} k-d cut(s) moved off a plane of samples (a floor or wall)")
        key = ruled

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
        "split_rule": SPLIT_RULE,
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


def scene_sides(geometry, *, seed: int = 0, log=print):
    """The reachable sides of a mesh scene (:func:`prt.train.inputs.visibility.surface_sides`), its
    ``two_sided`` flags updated in place where the rule changes them; None for SDF and mixed scenes."""
    if geometry.kind != "mesh":
        return None
    sides = surface_sides(geometry, seed=seed)
    for note in sides.notes:
        log(f"precompute: sides: {note}")
    if sides.changed:
        geometry.two_sided = sides.two_sided.copy()
    return sides


def _drop_hidden_points(geometry, sides, train: SurfaceSamples, valid: SurfaceSamples, seed: int):
    """Training and held-out samples without those inside other solids, each set topped up to its
    size from further draws (streams of their own); how many each lost."""
    out, dropped = [], []
    for k, (samples, stream) in enumerate(((train, TRAIN_STREAM), (valid, VALIDATION_STREAM))):
        hidden = hidden_points(geometry, sides, samples.points, samples.normals, seed=seed + k)
        lost = int(np.count_nonzero(hidden))
        kept, want = [samples.subset(np.flatnonzero(~hidden))] if lost else [samples], len(samples)
        for attempt in range(4):
            have = sum(len(s) for s in kept)
            if have >= want:
                break
            extra_count = int((want - have) * 1.5 * len(samples) / max(len(samples) - lost, 1)) + 64
            extra = sample_surface(geometry, extra_count, seed=seed, stream=stream + 16 * (attempt + 1), sides=sides.allowed)
            good = np.flatnonzero(~hidden_points(geometry, sides, extra.points, extra.normals, seed=seed + 16 * (attempt + 1) + k))
            kept.append(extra.subset(good[: want - have]))
        merged = kept[0] if len(kept) == 1 else SurfaceSamples(*(np.concatenate(parts) for parts in zip(
            *((s.points, s.normals, s.face_index, s.object_ids, s.weights) for s in kept))))  # fmt: skip
        if len(merged) == 0:
            merged = samples  # nothing would be left: keep them all
        out.append(merged)
        dropped.append(lost)
    return out[0], out[1], dropped


def _read_summary(path: Path) -> dict | None:
    """A previous ``precompute.json``; None (a cache miss) when missing, foreign or corrupt."""
    try:
        summary = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    files = summary.get("files") if isinstance(summary, dict) else None
    if not (isinstance(files, list) and all(isinstance(f, str) and "/" not in f and f not in ("", ".", "..") for f in files)):
        return None
    return summary


class DamagedPrecompute(PRTError):
    """A finished precompute's file cannot be read back (truncated, foreign); rerunning recomputes it."""


def load_precompute(out_dir) -> dict:
    """The arrays of a finished precompute: ``{"samples": {...}, "validation": {...}, ...}``.

    Raises :class:`DamagedPrecompute` (one line naming the file) if one is truncated or foreign.
    """
    out = Path(out_dir)
    name = "precompute.json"
    try:
        name = "samples.npz"
        with np.load(out / name, allow_pickle=False) as f:
            samples = {k: f[k] for k in _SAMPLE_KEYS}
        name = "validation.npz"
        with np.load(out / name, allow_pickle=False) as f:
            validation = {k: f[k] for k in _SAMPLE_KEYS}
        name = "segment_members.npz"
        with np.load(out / name, allow_pickle=False) as f:
            members = [f[f"members_{s}"] for s in range(len(f.files))]
        name = "segments.json"
        segments = json.loads((out / name).read_bytes())
        name = "precompute.json"
        summary = json.loads((out / name).read_bytes())
        if not (isinstance(segments, dict) and isinstance(segments.get("segments"), list)):
            raise ValueError("segments.json has no segment list")
    except MemoryError:
        raise
    except Exception as exc:  # zipfile, zlib, numpy and json each raise their own kind on damaged bytes
        raise DamagedPrecompute(f"{out / name}: damaged or not ours ({type(exc).__name__}: {' '.join(str(exc).split())[:200]})") from None
    return {
        "samples": samples,
        "validation": validation,
        "members": members,
        "segments": segments,
        "summary": summary,
    }


_SAMPLE_KEYS = ("points", "normals", "object_ids", "face_index", "transfer", "segment")
