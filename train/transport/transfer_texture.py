"""Texture-space transfer (PRT transfer textures): transfer baked per texel of a UV atlas.

1. UVs (:func:`prt.train.inputs.uv_atlas.build_atlas`): the mesh's own or xatlas's; open faces get a
   back-side chart.
2. A UV-space G-buffer rasterised with ModernGL (:func:`uv_gbuffer`): each texel centre that a
   UV triangle covers gets that point's scene-space position and the normal the view-space
   G-buffer interpolates there (:func:`prt.runtime.normals.corner_normals`, reversed on back
   sides).  Before the triangles, every face's corners and centroid are drawn as points, so a
   sliver too small to cover a texel centre still has a texel holding a point of it.  Then each
   empty texel next to a chart takes the point of a neighbour's triangle nearest its centre
   (barycentric coordinates clamped to the triangle), so fetches at chart borders blend true
   transfer.  (Not edges
   as lines: GL extrapolates a line's attributes up to half a texel past its ends, which put
   some texels inside the mesh, fully shadowed: dark dashes along chart borders.)
3. Transfer per covered texel through :func:`prt.train.compute_transfer` (the same rays, seeds
   and chunked, resumable, deterministic cache as every other path).
4. Dilation (:func:`dilate`): empty texels next to covered ones take the mean of their covered
   neighbours, :data:`DILATE_RINGS` rings deep, so a bilinear fetch anywhere on a chart reads
   transfer, never an empty texel.  Texels buried inside a solid (every ray blocked, e.g. a floor
   under a box standing on it) count as empty, so the contact line does not darken.
5. Stored as float16 (:func:`save_transfer_texture`, ``transfer_texture.npz``), read by the
   runtime's ``texture`` backend (:mod:`prt.runtime.backends.texture`).

Interreflection (a scene built with ``prt-train --bounces N``, :class:`TextureBounces`): each
texel then holds the "direct+rgb" layout of the networks, 64 values: its direct transfer (step 3),
then the indirect transfer of R, G and B.  The indirect part is the estimator of the build's bounce
stage (:mod:`prt.train.transport.interreflection`) applied to the texel's point: ``bounce_rays`` cosine rays
from the texel, at each hit the nearest precompute sample of the side the ray sees, gathering that
sample's ``T_0 + ... + T_{N-1}`` (the bounce stage run on the build's own samples, N - 1 bounces)
times the hit's albedo (the manifest's ``interreflection.albedos``).  So texture and networks
represent the same transfer.  The texels' rays are traced in chunks cached beside the direct ones
(resumable, deterministic; their own seed stream); dilation, float16 and buried texels (judged by
the direct part) as above.

Mesh scenes only (as the vertex baseline).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import moderngl
import numpy as np

from ...runtime.files import atomic_save_npz
from ...runtime.gl import bind_framebuffer
from ...runtime.normals import corner_normals
from .transfer import DEFAULT_CHUNK, _fingerprint, compute_transfer, make_tracer
from .interreflection import RAY_RULE
from ..inputs.uv_atlas import UVAtlas, build_atlas

__all__ = ["TransferTexture", "TextureBounces", "scene_bounces", "texel_indirect", "uv_gbuffer", "dilate", "bake_transfer_texture",
           "save_transfer_texture", "DILATE_RINGS", "FORMAT"]

# Array layers every OpenGL 3.3 driver holds (GL_MAX_ARRAY_TEXTURE_LAYERS >= 256).
GL_GUARANTEED_LAYERS = 256

FORMAT = 1  # transfer_texture.npz layout version
# Rings of empty texels filled around the charts (>= 1 keeps bilinear fetches off empty texels;
# more keeps lower-resolution reads of the same file, e.g. mipmaps, clean too).
DILATE_RINGS = 4

_RECORD = np.dtype([("uv", "<f4", 2), ("position", "<f4", 3), ("normal", "<f4", 3), ("side", "<f4")])
# Neighbours whose triangle a texel just outside a chart borrows: edge neighbours first.
_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))

_VERTEX_SHADER = """#version 330
in vec2 in_uv;
in vec3 in_position;
in vec3 in_normal;
in float in_side;
out vec3 v_position;
out vec3 v_normal;
flat out float v_side;
void main() {
    v_position = in_position;
    v_normal = in_normal;
    v_side = in_side;
    gl_Position = vec4(2.0 * in_uv - 1.0, 0.0, 1.0);
}
"""
# The view-space G-buffer's rule: the interpolated corner normal, normalised.
_FRAGMENT_SHADER = """#version 330
in vec3 v_position;
in vec3 v_normal;
flat in float v_side;
layout(location = 0) out vec4 o_position;
layout(location = 1) out vec4 o_normal;  // .w: the lit side's index + 1 (0: empty)
void main() {
    o_position = vec4(v_position, 1.0);
    o_normal = vec4(dot(v_normal, v_normal) > 0.0 ? normalize(v_normal) : vec3(0.0), v_side + 1.0);
}
"""


@dataclass
class TransferTexture:
    """A baked transfer texture and what it cost.

    Attributes
    ----------
    transfer : (A, S, S, n) float16
        Transfer per texel of each atlas; row 0 is ``v`` near 0 (GL's texture row order).  n = 16,
        or 64 with interreflection (direct, then indirect R, G, B).
    atlas : UVAtlas
    covered : (A, S, S) bool
        Texels holding a surface sample (inside a chart or one texel around it), before dilation.
    timings : dict
        Seconds: ``atlas_s``, ``gbuffer_s``, ``transfer_s``, (``bounce_s``), ``dilate_s``, ``total_s``.
    stats : dict
        Texel counts, the float16 error against float32, bytes.
    bounces : int
        N of the interreflected part (0: direct transfer only).
    """

    transfer: np.ndarray
    atlas: UVAtlas
    covered: np.ndarray
    timings: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    bounces: int = 0

    @property
    def size(self) -> int:
        return int(self.transfer.shape[1])

    @property
    def nbytes(self) -> int:
        """Bytes of the texture and the per-corner UVs the G-buffer draws with."""
        return int(self.transfer.nbytes + self.atlas.corner_uv.nbytes + self.atlas.atlas.nbytes)


def _side_records(vertices: np.ndarray, faces: np.ndarray, atlas: UVAtlas, which: np.ndarray) -> np.ndarray:
    """(N, 3) vertex records of the lit sides ``which`` (indices into :meth:`UVAtlas.sides`)."""
    face_of, side_of = atlas.sides()
    face_of, side_of = face_of[which], side_of[which]
    _, corner = corner_normals(vertices, faces)
    sign = np.where(side_of == 1, -1.0, 1.0)[:, None, None]
    records = np.empty((len(face_of), 3), dtype=_RECORD)
    records["uv"] = atlas.corner_uv[face_of, side_of]
    records["position"] = vertices[faces[face_of]]
    records["normal"] = corner[face_of] * sign
    records["side"] = np.asarray(which, dtype=np.float32)[:, None]
    return records


def uv_gbuffer(ctx: moderngl.Context, vertices, faces, atlas: UVAtlas, size: int, *, border: bool = True):
    """The UV-space G-buffer: position and normal at the texel centres of every atlas.

    Parameters
    ----------
    ctx : moderngl.Context
    vertices : (V, 3) float
    faces : (F, 3) int
    atlas : UVAtlas
    size : int
        Texels per side of each atlas.
    border : bool
        Also give the empty texels next to each chart a point of its border (see the module
        docstring); False leaves only what the rasteriser drew.

    Returns
    -------
    position, normal : (A, S, S, 3) float32
        Row 0 is ``v`` near 0; zeros where nothing was drawn.
    covered : (A, S, S) bool
    """
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64)
    face_of, _ = atlas.sides()
    program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
    targets = [ctx.texture((size, size), 4, dtype="f4") for _ in range(2)]
    fbo = ctx.framebuffer(targets)
    out = np.zeros((2, atlas.n_atlases, size, size, 4), dtype=np.float32)
    previous = ctx.fbo  # bound again before our framebuffer is released
    try:
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        for index in range(atlas.n_atlases):
            records = _side_records(vertices, faces, atlas, np.flatnonzero(atlas.atlas[face_of] == index))
            if len(records) == 0:
                continue
            centroid = np.empty(len(records), dtype=_RECORD)
            for name in _RECORD.names:
                centroid[name] = records[name].mean(axis=1)
            # The triangles overwrite the points: a point keeps only a texel no triangle covers.
            draws = [
                (moderngl.POINTS, np.concatenate([records.reshape(-1), centroid])),
                (moderngl.TRIANGLES, records.reshape(-1)),
            ]
            fbo.use()
            fbo.clear(0.0, 0.0, 0.0, 0.0)
            for mode, data in draws:
                vbo = ctx.buffer(np.ascontiguousarray(data).tobytes())
                vao = ctx.vertex_array(program, [(vbo, "2f 3f 3f 1f", "in_uv", "in_position", "in_normal", "in_side")])
                vao.render(mode, vertices=len(data))
                vao.release()
                vbo.release()
            for k in range(2):
                fbo.read_into(out[k, index], components=4, attachment=k, dtype="f4")
    finally:
        bind_framebuffer(ctx, previous)
        for obj in (fbo, *targets, program):
            obj.release()
    position, normal, covered = out[0, ..., :3], out[1, ..., :3], out[0, ..., 3] > 0.5
    side = np.rint(out[1, ..., 3]).astype(np.int64) - 1
    if border:
        _border_samples(vertices, faces, atlas, position, normal, covered, side)
    return position, normal, covered


def _border_samples(vertices, faces, atlas: UVAtlas, position, normal, covered, side) -> None:
    """Give each empty texel next to a chart a point between its neighbour's and the chart's edge.

    The texel centre's barycentric coordinates in a neighbour's UV triangle, clamped to the
    triangle, give the point of the chart's edge nearest the centre (never off the surface, as
    extrapolating would); the sample is halfway between it and the neighbour's point, so bilinear
    fetches at the border blend transfer of the surface there rather than copies.  In place.
    """
    size = covered.shape[1]
    face_of, side_of = atlas.sides()
    _, corner = corner_normals(vertices, faces)
    centre = (np.arange(size) + 0.5) / size
    for index in range(atlas.n_atlases):
        owner = np.full((size, size), -1, dtype=np.int64)
        lender = np.zeros((size, size, 6))  # the neighbour's position and normal
        padded = np.pad(np.where(covered[index], side[index], -1), 1, constant_values=-1)
        samples = np.pad(np.concatenate([position[index], normal[index]], axis=2), ((1, 1), (1, 1), (0, 0)))
        for dy, dx in _NEIGHBOURS:
            lent = padded[1 + dy : 1 + dy + size, 1 + dx : 1 + dx + size]
            take = ~covered[index] & (owner < 0) & (lent >= 0)
            owner[take] = lent[take]
            lender[take] = samples[1 + dy : 1 + dy + size, 1 + dx : 1 + dx + size][take]
        ys, xs = np.nonzero(owner >= 0)
        sides, lent_sample = owner[ys, xs], lender[ys, xs]
        faces_of, back = face_of[sides], side_of[sides]
        tri = atlas.corner_uv[faces_of, back].astype(np.float64)  # (N, 3, 2)
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        d = np.stack([centre[xs], centre[ys]], axis=1) - tri[:, 0]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > 1e-30
        det = np.where(ok, det, 1.0)
        b1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
        b2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
        weights = np.clip(np.stack([1.0 - b1 - b2, b1, b2], axis=1), 0.0, None)
        weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-30)
        point = np.einsum("nk,nkc->nc", weights, vertices[faces[faces_of]].astype(np.float64))
        mixed = np.einsum("nk,nkc->nc", weights, corner[faces_of]) * np.where(back == 1, -1.0, 1.0)[:, None]
        # Halfway back to the neighbour: a point exactly on a chart's edge may sit on the crease
        # line where another surface meets it (a wall's foot), where its rays start inside that surface.
        point = 0.5 * (point + lent_sample[:, :3])
        mixed = mixed + lent_sample[:, 3:]
        length = np.linalg.norm(mixed, axis=1)
        ok &= length > 1e-12
        ys, xs = ys[ok], xs[ok]
        position[index, ys, xs] = point[ok]
        normal[index, ys, xs] = mixed[ok] / length[ok, None]
        covered[index, ys, xs] = True


def dilate(values: np.ndarray, valid: np.ndarray, rings: int = DILATE_RINGS) -> tuple[np.ndarray, np.ndarray]:
    """Fill empty texels next to valid ones with the mean of their valid 8-neighbours, ``rings`` times.

    Parameters
    ----------
    values : (H, W, C) float
    valid : (H, W) bool

    Returns
    -------
    values : (H, W, C) float32, a new array
    valid : (H, W) bool, the texels that now hold a value
    """
    values = np.array(values, dtype=np.float32)
    valid = np.array(valid, dtype=bool)
    height, width = valid.shape
    for _ in range(rings):
        total = np.zeros_like(values)
        count = np.zeros((height, width), dtype=np.float32)
        padded_v = np.pad(values * valid[..., None], ((1, 1), (1, 1), (0, 0)))
        padded_c = np.pad(valid.astype(np.float32), 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    total += padded_v[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width]
                    count += padded_c[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width]
        grow = ~valid & (count > 0)
        if not grow.any():
            break
        values[grow] = total[grow] / count[grow][:, None]
        valid |= grow
    return values, valid


@dataclass
class TextureBounces:
    """What a texel's bounce rays gather (the build's bounce stage, :mod:`prt.train.transport.interreflection`).

    Attributes
    ----------
    points, normals : (S, 3) float
        The build's precompute (training) samples: what the hit points search.
    gathered : (S, n, 3) float
        ``T_0 + ... + T_{N-1}`` of those samples (RGB): what a hit on them contributes, times its albedo.
    face_albedo : (F, 3) float
        Albedo of every triangle (the manifest's ``interreflection.albedos``).
    bounces : int
        N >= 1.
    rays : int
        Bounce rays per texel (the build's ``bounce_rays``).
    seed : int
    direct : (S, n) float, optional
        ``T_0`` of the samples: with it, a texel's hits far from any clear sample read the direct
        transfer traced there instead (the bounce stage's rule, :data:`prt.train.transport.interreflection.TRACE_FAR`).
    """

    points: np.ndarray
    normals: np.ndarray
    gathered: np.ndarray
    face_albedo: np.ndarray
    bounces: int
    rays: int
    seed: int = 0
    direct: np.ndarray | None = None


def scene_bounces(manifest, geometry, *, cache_dir=None, threads: int | None = None, progress: bool = False,
                  log=print) -> TextureBounces | None:  # fmt: skip
    """The :class:`TextureBounces` of a built scene with ``interreflection`` (None without).

    Reads the build's precompute samples (``<scene>/precompute``), the albedos and N from the
    manifest, seed and chunk size from ``build.json``'s spec, and runs the bounce stage's N - 1
    bounces on the samples (:func:`prt.train.transport.interreflection.bounce_stage`, its rays chunked and
    cached in ``cache_dir``; the same rays as the build's: same seed, stream and chunks).
    """
    import json

    from .interreflection import bounce_stage
    from .precompute import load_precompute

    info = getattr(manifest, "interreflection", None)
    if info is None:
        return None
    spec = {}
    if (manifest.root / "build.json").is_file():
        spec = json.loads((manifest.root / "build.json").read_text()).get("spec") or {}
    seed, chunk_size = int(spec.get("seed", 0)), int(spec.get("chunk_size", DEFAULT_CHUNK))  # prt-train keeps the default chunk
    try:
        samples = load_precompute(manifest.root / "precompute")["samples"]
    except FileNotFoundError as exc:
        raise ValueError(f"{manifest.path}: interreflection textures need the build's precompute samples ({exc.filename})") from None
    missing = [n for n in geometry.object_names if n not in info.albedos]
    if missing:
        raise ValueError(f"{manifest.path}: interreflection.albedos has no albedo for object(s) {', '.join(missing)}")
    table = np.asarray([info.albedos[n] for n in geometry.object_names], dtype=np.float64).reshape(-1, 3)
    face_albedo = table[np.asarray(geometry.object_ids)]
    direct = np.asarray(samples["transfer"], dtype=np.float64)
    gathered = np.repeat(direct[:, :, None], 3, axis=2)
    if info.bounces > 1:  # T_1 + ... + T_{N-1} of the samples, as the bounce stage found them
        n = direct.shape[1]
        empty = {"points": np.zeros((0, 3)), "normals": np.zeros((0, 3)), "transfer": np.zeros((0, n))}
        key = _fingerprint(samples["points"], samples["normals"], info.bounce_rays, seed, chunk_size, "v2", RAY_RULE)
        folder = Path(cache_dir) if cache_dir is not None else manifest.root / "cache" / "transfer_texture"
        indirect, _ = bounce_stage(geometry.mesh, folder, samples, empty, face_albedo, info.bounces - 1, rays=info.bounce_rays,
                                   seed=seed, chunk_size=chunk_size, key=key, threads=threads, progress=progress, log=log)  # fmt: skip
        gathered += indirect
    return TextureBounces(np.asarray(samples["points"], np.float64), np.asarray(samples["normals"], np.float64), gathered,
                          face_albedo, int(info.bounces), int(info.bounce_rays), seed, direct)  # fmt: skip


def texel_indirect(tracer, points, normals, bounces: TextureBounces, *, chunk_size: int = DEFAULT_CHUNK, cache_dir=None,
                   threads: int | None = None, progress: bool = False) -> np.ndarray:  # fmt: skip
    """Indirect RGB transfer ``T_1 + ... + T_N`` at arbitrary surface points (the texels): (P, n, 3) float32.

    ``bounces.rays`` cosine rays per point (:class:`prt.train.transport.interreflection.BounceJob`, seed
    stream 2: apart from the build's training and validation rays), the nearest sample at each
    hit, ``mean_j a(hit_j) gathered[nearest_j]``; with ``bounces.direct``, a hit with no clear sample or
    one farther than :data:`~prt.train.transport.interreflection.TRACE_FAR` spacings takes the direct
    transfer traced there plus its clear sample's higher bounces (``gathered - direct``; none without
    one), as the bounce stage's first bounce does.  Chunked through a local executor; with
    ``cache_dir`` the chunks' ray indices and traced transfer (not the albedos) are kept, so a bake resumes.
    """
    from ..executor import LocalExecutor
    from .interreflection import (
        TRACE_FAR, TRACE_RULE, BounceJob, BounceRays, _IndexStore, bounce_matrices, collect_rays, run_ray_chunks, sample_spacing, surface_faces,
        traced_term,
    )  # fmt: skip

    points = np.ascontiguousarray(points, dtype=np.float64)
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    count, rays = len(points), int(bounces.rays)
    n_chunks = (count + chunk_size - 1) // chunk_size
    gathered = np.asarray(bounces.gathered, dtype=np.float64)
    trace = bounces.direct is not None
    far = TRACE_FAR * sample_spacing(bounces.points, bounces.normals) if trace else None
    bands = int(round(np.sqrt(gathered.shape[1])))
    out = np.full((count, 3 if trace else 2, rays), -1, dtype=np.int32)
    store, todo, traced = None, list(range(n_chunks)), {}
    if cache_dir is not None:
        key = _fingerprint(points, normals, bounces.points, bounces.normals, rays, bounces.seed, chunk_size, tracer.identity, "v3", RAY_RULE,
                           TRACE_RULE if trace else "")  # fmt: skip
        store = _IndexStore(Path(cache_dir) / f"bounce-texels-{key}", n_chunks, traced=trace)
        todo = store.load_into(out, chunk_size)
        traced = store.traced
    job = BounceJob(tracer, bounces.points, bounces.normals, rays=rays, seed=bounces.seed, stream=2, workers=1, trace_far=far, bands=bands)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=count * rays, unit="ray", unit_scale=True, desc="texel bounce rays", mininterval=0.5)
    faces = surface_faces(tracer, points, normals)  # the texels' own faces: rays entering the surface carry nothing
    items = [(k, points[k * chunk_size : (k + 1) * chunk_size], normals[k * chunk_size : (k + 1) * chunk_size],
              faces[k * chunk_size : (k + 1) * chunk_size]) for k in todo]  # fmt: skip
    run_ray_chunks(LocalExecutor(threads), job, items, out, chunk_size, rays, store=store, bar=bar, traced=traced)
    if not trace:
        found = BounceRays(out[:, 0].astype(np.int64), out[:, 1].astype(np.int64))
        matrices = bounce_matrices(found, bounces.face_albedo, targets=len(bounces.points))
        return np.stack([matrices[c] @ gathered[:, :, c] for c in range(3)], axis=2).astype(np.float32)
    found = collect_rays(out, traced, chunk_size, bands)
    every = bounce_matrices(found, bounces.face_albedo, targets=len(bounces.points))
    first = bounce_matrices(found, bounces.face_albedo, targets=len(bounces.points), first=True)
    direct = np.asarray(bounces.direct, dtype=np.float64)
    # every ray's gathered sample, less the direct part of the traced rays' samples, plus what they traced
    return (np.stack([every[c] @ gathered[:, :, c] - (every[c] - first[c]) @ direct for c in range(3)], axis=2)
            + traced_term(found, bounces.face_albedo)).astype(np.float32)  # fmt: skip


def bake_transfer_texture(
    geometry,
    size: int,
    *,
    layout: str = "shared",
    rays: int = 512,
    seed: int = 0,
    chunk_size: int = DEFAULT_CHUNK,
    cache_dir=None,
    tracer=None,
    ctx: moderngl.Context | None = None,
    atlas: UVAtlas | None = None,
    source_path=None,
    bounces: TextureBounces | None = None,
    progress: bool = False,
    log=print,
) -> TransferTexture:
    """Bake the transfer texture of a mesh scene.

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
        The scene exactly as the runtime draws it (``geometry.npz``'s mesh).
    size : int
        Texels per side of each atlas.
    layout : ``"shared"`` or ``"per_object"``
        One atlas for the scene, or one per object (texture sets).
    rays, seed, chunk_size, cache_dir, tracer, progress :
        As :func:`prt.train.compute_transfer`; ``cache_dir`` makes the bake resumable.
    ctx : moderngl.Context, optional
        Default: a new headless context.
    atlas : UVAtlas, optional
        Reuse an atlas (default: :func:`build_atlas`).
    source_path : path, optional
        The mesh file, for its own UVs (default: ``geometry.source``).
    bounces : TextureBounces, optional
        Bake the interreflected "direct+rgb" layout (64 values per texel; :func:`scene_bounces`).
    log : callable
        Progress lines and the warning about overlapping UVs.
    """
    size = int(size)
    if size < 8:
        raise ValueError(f"texture size must be >= 8, got {size}")
    own_ctx = ctx is None
    if own_ctx:
        from ...runtime.gl import create_context

        ctx = create_context()
    timings = {}
    t_start = time.perf_counter()
    try:
        if atlas is None:
            atlas = build_atlas(geometry, size, layout, source_path=source_path, ctx=ctx, log=log)
        timings["atlas_s"] = atlas.seconds
        t0 = time.perf_counter()
        vertices = np.asarray(geometry.mesh.vertices, dtype=np.float32)
        faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
        position, normal, covered = uv_gbuffer(ctx, vertices, faces, atlas, size)
        timings["gbuffer_s"] = time.perf_counter() - t0
    finally:
        if own_ctx:
            ctx.release()
    t0 = time.perf_counter()
    tracer = tracer if tracer is not None else make_tracer(geometry)
    points, normals = position[covered], normal[covered]
    log(f"transfer texture: {atlas.n_atlases} x {size}x{size}, {len(points):,} texels x {rays} rays ({atlas.note})")
    layers = atlas.n_atlases * (16 if bounces is not None else 4)  # RGBA array layers at run time
    if layers > GL_GUARANTEED_LAYERS:
        log(f"warning: {layers} texture-array layers ({atlas.n_atlases} atlases): OpenGL 3.3 guarantees {GL_GUARANTEED_LAYERS}, "
            f"so the texture backend loads this scene only where the driver allows more (--texture-layout shared makes one atlas)")
    transfer = compute_transfer(
        geometry, points, normals, rays=rays, seed=seed, chunk_size=chunk_size, cache_dir=cache_dir, tracer=tracer, progress=progress
    )
    timings["transfer_s"] = time.perf_counter() - t0
    direct_width = transfer.shape[1]
    if bounces is not None:  # [direct, indirect R, G, B], as the networks' "direct+rgb"
        t0 = time.perf_counter()
        log(f"transfer texture: {bounces.bounces} bounce(s), {len(points):,} texels x {bounces.rays} bounce rays")
        indirect = texel_indirect(tracer, points, normals, bounces, chunk_size=chunk_size, cache_dir=cache_dir, progress=progress)
        transfer = np.concatenate([transfer, indirect.transpose(0, 2, 1).reshape(len(indirect), -1)], axis=1)
        timings["bounce_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    texture = np.zeros((atlas.n_atlases, size, size, transfer.shape[1]), dtype=np.float16)
    full = np.zeros((size, size, transfer.shape[1]), dtype=np.float32)
    errors = []
    start = 0
    # Texels whose every ray is blocked lie inside a solid (a floor under a box resting on it):
    # no view sees them, and fetches at the contact must not blend them in.  Dilation refills them.
    buried = ~np.any(transfer[:, :direct_width] != 0.0, axis=1)
    for index in range(atlas.n_atlases):
        mask = covered[index].copy()
        count = int(mask.sum())
        full[:] = 0.0
        full[mask] = transfer[start : start + count]
        mask[mask] = ~buried[start : start + count]
        start += count
        filled, _ = dilate(full, mask)
        texture[index] = filled.astype(np.float16)
        errors.append(texture[index][mask].astype(np.float32) - filled[mask])
    timings["dilate_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    error = np.concatenate(errors) if errors else np.zeros((0, transfer.shape[1]), np.float32)
    scale = float(np.sqrt(np.mean(transfer.astype(np.float64) ** 2))) if len(transfer) else 1.0
    stats = {
        "size": size,
        "atlases": atlas.n_atlases,
        "layout": layout,
        "uv_source": atlas.source,
        "uv_note": atlas.note,
        "texels_covered": int(covered.sum()),
        "texels_buried": int(buried.sum()),
        "texel_utilisation": round(float(covered.mean()), 4),
        "rays": rays,
        "seed": seed,
        # float16 storage against the float32 bake (covered texels, all coefficients)
        "float16_max_abs_error": float(np.abs(error).max()) if len(error) else 0.0,
        "float16_rms_error_relative": float(np.sqrt(np.mean(error.astype(np.float64) ** 2)) / max(scale, 1e-30)) if len(error) else 0.0,
    }
    if bounces is not None:
        stats |= {"bounces": bounces.bounces, "bounce_rays": bounces.rays, "channels": int(transfer.shape[1])}
    result = TransferTexture(texture, atlas, covered, timings, stats, bounces.bounces if bounces is not None else 0)
    stats["bytes"] = result.nbytes
    return result


def save_transfer_texture(path, texture: TransferTexture) -> Path:
    """Write ``transfer_texture.npz`` (read by :func:`prt.runtime.backends.texture.load_transfer_texture`).

    Arrays: ``transfer`` (A, S, S, n) float16 (row 0 at ``v`` near 0; n = 16, or 64 with
    interreflection), ``corner_uv`` (F, 2, 3, 2) float32 (front and back side), ``atlas`` (F,)
    int32, ``format`` () int; with interreflection also ``bounces`` () int.
    """
    path = Path(path)
    atomic_save_npz(
        path,
        transfer=texture.transfer,
        corner_uv=texture.atlas.corner_uv,
        atlas=texture.atlas.atlas,
        format=np.int64(FORMAT),
        **({"bounces": np.int64(texture.bounces)} if texture.bounces else {}),
    )
    return path


def scene_geometry(manifest):
    """The :class:`~prt.train.inputs.geometry.Geometry` a mesh scene draws (its ``geometry.npz``, exactly)."""
    import trimesh

    from ...runtime.gbuffer import load_mesh
    from ..inputs.geometry import Geometry

    mesh = load_mesh(manifest.geometry.path)
    return Geometry(
        mesh=trimesh.Trimesh(vertices=mesh["vertices"].astype(np.float64), faces=mesh["faces"], process=False),
        object_ids=mesh["object_ids"].astype(np.int64),
        object_names=list(manifest.geometry.objects or [f"object{i}" for i in range(int(mesh["object_ids"].max()) + 1)]),
        two_sided=mesh["two_sided"],
        to_source=np.asarray(manifest.geometry.to_source, dtype=np.float64),
        source=str(manifest.geometry.path),
    )


def add_transfer_texture(scene, size: int, *, layout: str = "shared", rays: int = 512, seed: int = 0,
                         source_path=None, cache_dir=None, ctx=None, progress: bool = False, log=print) -> TransferTexture:
    """Bake a transfer texture for a built mesh scene and record it in its ``scene.json``.

    Writes ``transfer_texture.npz`` into the scene folder and the manifest's optional
    ``transfer_texture`` entry (both atomically).  ``source_path`` (default: the ``source`` in
    the scene's ``build.json``) lends the mesh file's own UVs; ``cache_dir`` (default:
    ``<scene>/cache/transfer_texture``) keeps finished chunks, so an interrupted bake resumes.
    A scene built with ``--bounces N`` gets the interreflected "direct+rgb" texture (64 values per
    texel, :func:`scene_bounces`), which the texture backend then shades as the networks' transfer.
    """
    import json

    from ...runtime.files import atomic_write_json
    from ...runtime.manifest import load_manifest
    from ...runtime.transfer_texture import TransferTextureInfo

    manifest = load_manifest(scene)
    if manifest.geometry.type != "mesh":
        raise ValueError(f"{manifest.path}: transfer textures need a mesh scene (this one is {manifest.geometry.type})")
    if source_path is None and (manifest.root / "build.json").is_file():
        source_path = json.loads((manifest.root / "build.json").read_text()).get("source")
    geometry = scene_geometry(manifest)
    cache_dir = manifest.root / "cache" / "transfer_texture" if cache_dir is None else cache_dir
    bounces = scene_bounces(manifest, geometry, cache_dir=cache_dir, progress=progress, log=log)
    texture = bake_transfer_texture(geometry, size, layout=layout, rays=rays, seed=seed, cache_dir=cache_dir,
                                    ctx=ctx, source_path=source_path, bounces=bounces, progress=progress, log=log)  # fmt: skip
    path = save_transfer_texture(manifest.root / "transfer_texture.npz", texture)
    stats = texture.stats
    extra = {"layout": layout, "uv_source": stats["uv_source"], "rays": rays, "bytes": stats["bytes"]}
    manifest.transfer_texture = TransferTextureInfo(path=path, size=texture.size, atlases=stats["atlases"], extra=extra)
    atomic_write_json(manifest.path, manifest.to_dict())
    return texture
