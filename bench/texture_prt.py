"""The texture-space baseline: transfer textures (texture-space PRT) baked for a scene, cached.

For each ``--texture-size``, :func:`prt.train.transport.transfer_texture.bake_transfer_texture` bakes the
scene's mesh (``geometry.npz``) at ``--ref-rays`` rays per texel (the rays of every other path),
with the mesh file's own UVs where ``build.json``'s source has usable ones, else xatlas.  The
texture is cached in the bench cache (``<cache>/<scene>/transfer_texture-<size>-r<rays>.npz``
with its stats beside it; the ray-traced chunks in ``<cache>/transfer/texture-chunks``), and a
variant of the manifest naming it is rendered by the runtime's ``texture`` backend, so frames
are timed and compared exactly as the networks' are.  Mesh scenes only.

A scene built with ``--bounces N`` gets interreflection textures ("direct+rgb", 64 values per
texel; :func:`prt.train.transport.transfer_texture.scene_bounces`): their texels' bounce rays gather the
build's own precompute samples, as the networks' training data did, so the texture and the
networks are compared against the same bounce-aware reference.  Cached as
``transfer_texture-<size>-r<rays>-b<N>.npz``.  The records of those textures say so: their
``transfer`` is the scene's ``N bounces`` and their label names it (``texture 1024 2 bounces
diffuse``, :mod:`prt.bench.scene_bench`); the ``texture_baseline`` entry's ``bounces`` is N (0
for direct-only textures).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from prt.runtime.files import atomic_write_json
from prt.runtime.transfer_texture import TransferTextureInfo
from prt.train.transport.transfer_texture import bake_transfer_texture, save_transfer_texture, scene_bounces

__all__ = ["texture_variants"]


def texture_variants(manifest, geometry, tracer, sizes, rays: int, cache: Path, ctx, log=print):
    """Baked (or cached) transfer textures of a mesh scene, as manifests the texture backend renders.

    Returns
    -------
    variants : dict of int to Manifest
        Texture size -> a copy of ``manifest`` with its ``transfer_texture``.
    info : dict
        ``texture_baseline`` entry: ``bounces`` baked in (the scene's N, 0 without), and per size
        the bake's stats and timings (``precompute_s``, ``cached``); or a ``note`` when skipped.
    """
    if geometry.sdf is not None:
        return {}, {"note": "skipped: SDF scene (no UV atlas)"}
    source = None
    build = manifest.root / "build.json"
    if build.is_file():
        source = json.loads(build.read_text()).get("source")
    folder = Path(cache) / manifest.name
    record = getattr(manifest, "interreflection", None)
    variants, info = {}, {"bounces": 0 if record is None else int(record.bounces), "sizes": {}}
    bounces, suffix = None, f"-b{record.bounces}" if record is not None else ""
    for size in sizes:
        path = folder / f"transfer_texture-{size}-r{rays}{suffix}.npz"
        stats_path = path.with_suffix(".json")
        cached = path.is_file() and stats_path.is_file()
        if cached:
            stats = json.loads(stats_path.read_text())
        else:
            chunks = Path(cache) / "transfer" / "texture-chunks"
            if record is not None and bounces is None:
                bounces = scene_bounces(manifest, geometry, cache_dir=chunks, log=lambda line: log(f"  {line}"))
            texture = bake_transfer_texture(geometry, size, rays=rays, tracer=tracer, ctx=ctx, source_path=source, cache_dir=chunks,
                                            bounces=bounces, log=lambda line: log(f"  {line}"))  # fmt: skip
            save_transfer_texture(path, texture)
            stats = {**texture.stats, "timings_s": {k: round(v, 3) for k, v in texture.timings.items()}}
            atomic_write_json(stats_path, stats)
        stats = {**stats, "precompute_s": stats["timings_s"]["total_s"], "cached": cached, "file": str(path)}
        info["sizes"][str(size)] = stats
        entry = TransferTextureInfo(path=path, size=size, atlases=stats["atlases"],
                                    extra={"layout": stats["layout"], "uv_source": stats["uv_source"], "rays": rays, "bytes": stats["bytes"]})  # fmt: skip
        variants[size] = dataclasses.replace(manifest, transfer_texture=entry)
        log(f"  texture {size}x{size}: {stats['texels_covered']:,} texels, {stats['bytes']:,} bytes, "
            f"{stats['precompute_s']:.1f} s to bake{' (cached)' if cached else ''}; {stats['uv_note']}")  # fmt: skip
    return variants, info
