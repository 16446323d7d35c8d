"""Alpha cut-outs as geometry: the opaque part of each triangle of an alpha-masked material.

Leaves, grilles, fences and hair cards are quads whose texture's alpha says where the surface is
(glTF ``alphaMode: MASK`` with its ``alphaCutoff``, 0.5 by default).  Transfer here is opaque
occlusion traced against triangles, and the G-buffer rasterises triangles, so the mask is applied
once, to the geometry, when the file is read: every stage after it (samples, rays, bounces, the
G-buffer, Mitsuba 3's reference, the probe grid) sees the holes without knowing of textures.

The rule (:func:`cut_triangles`): a triangle is split in four at its edges' midpoints, again and
again, where its texture footprint holds both opaque and transparent texels; a piece whose texels
(every texel its bilinear samples can touch, wrapping) are all opaque is kept whole, one whose
texels are all transparent is dropped.  A texel is opaque when ``factor_alpha * texel_alpha >=
cutoff``.  Splitting stops at about one texel per piece (:data:`TEXELS_PER_PIECE`) or at
:data:`MAX_DEPTH` levels; a piece still mixed there is kept when the bilinear alpha at its
centroid reaches the cutoff (the texture lookup of the GL and of
:func:`prt.runtime.albedo_textures.sample_bilinear`).  So the edge of a leaf is followed to about a
texel, as the rasteriser's alpha test would draw it, by pieces that keep the triangle's winding.

Counting opaque texels over a footprint is a summed-area table on the texture tiled without end
(:class:`OpaqueCounter`), so UVs outside [0, 1] (tiling textures) count right.
"""

from __future__ import annotations

import numpy as np

from ...runtime.albedo_textures import sample_bilinear

__all__ = ["OpaqueCounter", "cut_triangles", "cut_triangles_reference", "cut_within_budget", "cut_corners", "MAX_DEPTH", "TEXELS_PER_PIECE",
           "DEFAULT_CUTOFF", "CUT_BUDGET"]

DEFAULT_CUTOFF = 0.5
"""glTF's ``alphaCutoff`` where a MASK material gives none."""

MAX_DEPTH = 8
"""Most halvings of a triangle's edges (up to 4**8 pieces of it, along the mask's edges only)."""

TEXELS_PER_PIECE = 2.0
"""Splitting stops once a piece covers at most this many texels (its area in texel units)."""

CUT_BUDGET = 100_000
"""Pieces the cut-outs of one scene may make in all; past it every cut is made one level coarser.
Every piece brings up to three vertices, and a build's per-vertex PRT estimate traces every
vertex (a plant of 24 cards cut into 12,240 pieces, 10k vertices: 28 s of its 50 s draft build),
so a plant of a few hundred cards is held to about its leaves' outline at a few texels."""


class OpaqueCounter:
    """Opaque texels of an alpha image over texel boxes, the image tiled in both directions.

    Parameters
    ----------
    opaque : (H, W) bool, row 0 at the top of the image
    """

    def __init__(self, opaque: np.ndarray):
        opaque = np.asarray(opaque, dtype=bool)
        self.height, self.width = opaque.shape
        # int32 holds any count of a texture up to 46k a side (MAX_TEXTURE_SIZE is 8192): half the memory.
        table = np.zeros((self.height + 1, self.width + 1), dtype=np.int32)
        table[1:, 1:] = np.cumsum(np.cumsum(opaque, axis=0, dtype=np.int32), axis=1, dtype=np.int32)
        self._table = table

    def _prefix(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Opaque texels with column < x and row < y on the tiled plane, from column and row 0
        of the tile at the origin (x, y int64, any sign: counts below 0 are negative)."""
        t, h, w = self._table, self.height, self.width
        qx, rx = np.divmod(x, w)
        qy, ry = np.divmod(y, h)
        total = np.int64(t[h, w])
        return qx * qy * total + qx * t[ry, w].astype(np.int64) + qy * t[h, rx].astype(np.int64) + t[ry, rx].astype(np.int64)

    def count(self, x0, y0, x1, y1) -> np.ndarray:
        """Opaque texels in columns [x0, x1) and rows [y0, y1) (int arrays, x1 >= x0, y1 >= y0)."""
        x0, y0, x1, y1 = (np.asarray(a, dtype=np.int64) for a in (x0, y0, x1, y1))
        return self._prefix(x1, y1) - self._prefix(x0, y1) - self._prefix(x1, y0) + self._prefix(x0, y0)


def _split(bary: np.ndarray) -> np.ndarray:
    """(N, 3, 3) barycentric corners -> (4N, 3, 3): each piece's four children, winding kept."""
    a, b, c = bary[:, 0], bary[:, 1], bary[:, 2]
    ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    children = np.stack([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], axis=1)
    return children.reshape(-1, 3, 3)


def _texel_box(uv: np.ndarray, width: int, height: int):
    """Columns and rows [x0, x1) x [y0, y1) of every texel a bilinear lookup inside the pieces
    with corner UVs ``uv`` (N, 3, 2) can touch (OBJ's convention, v = 0 at the bottom)."""
    x = uv[:, :, 0] * width - 0.5
    y = (1.0 - uv[:, :, 1]) * height - 0.5
    x0, y0 = np.floor(x.min(axis=1)).astype(np.int64), np.floor(y.min(axis=1)).astype(np.int64)
    x1, y1 = np.floor(x.max(axis=1)).astype(np.int64) + 2, np.floor(y.max(axis=1)).astype(np.int64) + 2
    return x0, y0, x1, y1


def _depth_limits(uv: np.ndarray, width: int, height: int, max_depth: int) -> np.ndarray:
    """Per triangle, the level at which a piece covers at most TEXELS_PER_PIECE texels."""
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) * width * height
    levels = np.ceil(0.5 * np.log2(np.maximum(area / TEXELS_PER_PIECE, 1.0)))
    return np.clip(levels, 0, max_depth).astype(np.int64)


def cut_triangles(uv: np.ndarray, alpha: np.ndarray, cutoff: float, max_depth: int = MAX_DEPTH) -> tuple[np.ndarray, np.ndarray]:
    """The opaque pieces of triangles under an alpha mask (the rule of the module docstring).

    Parameters
    ----------
    uv : (F, 3, 2) float64
        Each triangle's corner UVs, OBJ's convention.
    alpha : (H, W) float
        Alpha per texel (the material's factor applied), row 0 at the top.
    cutoff : float
        Opaque where alpha >= cutoff.
    max_depth : int

    Returns
    -------
    face : (K,) int64
        The triangle each piece comes from, ascending.
    bary : (K, 3, 3) float64
        Each piece's corners as barycentric weights of its triangle's corners.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 3, 2)
    alpha = np.asarray(alpha, dtype=np.float32)
    height, width = alpha.shape
    counter = OpaqueCounter(alpha >= cutoff)
    # A triangle without finite UVs (a malformed file) has no texels to test: kept whole.
    broken = ~np.isfinite(uv).all(axis=(1, 2))
    uv = np.where(broken[:, None, None], 0.0, uv)
    limits = _depth_limits(uv, width, height, max_depth)
    face = np.arange(len(uv), dtype=np.int64)
    bary = np.broadcast_to(np.eye(3), (len(uv), 3, 3)).copy()
    kept_face, kept_bary = [face[broken]], [bary[broken]]
    face, bary = face[~broken], bary[~broken]
    depth = 0
    while len(face):
        corners = np.einsum("kcj,kjd->kcd", bary, uv[face])  # (N, 3, 2) piece UVs
        x0, y0, x1, y1 = _texel_box(corners, width, height)
        opaque = counter.count(x0, y0, x1, y1)
        full = opaque == (x1 - x0) * (y1 - y0)
        mixed = (opaque > 0) & ~full
        last = mixed & (limits[face] <= depth)
        if last.any():
            centre = corners[last].mean(axis=1)
            inside = sample_bilinear(alpha[:, :, None], centre)[:, 0] >= np.float32(cutoff)
            full[np.flatnonzero(last)[inside]] = True
        kept_face.append(face[full])
        kept_bary.append(bary[full])
        go = mixed & ~last
        face, bary = np.repeat(face[go], 4), _split(bary[go])
        depth += 1
    face = np.concatenate(kept_face) if kept_face else np.zeros(0, dtype=np.int64)
    bary = np.concatenate(kept_bary) if kept_bary else np.zeros((0, 3, 3))
    order = np.argsort(face, kind="stable")
    return face[order], bary[order]


def cut_triangles_reference(uv: np.ndarray, alpha: np.ndarray, cutoff: float, max_depth: int = MAX_DEPTH) -> tuple[np.ndarray, np.ndarray]:
    """Plain twin of :func:`cut_triangles`: one triangle at a time, depth first, texels counted
    by looping over the box (wrapped with ``%``)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 3, 2)
    alpha = np.asarray(alpha, dtype=np.float32)
    height, width = alpha.shape
    opaque_image = alpha >= cutoff
    out_face, out_bary = [], []
    for f in range(len(uv)):
        if not np.isfinite(uv[f]).all():
            out_face.append(f)
            out_bary.append(np.eye(3))
            continue
        limit = _depth_limits(uv[f : f + 1], width, height, max_depth)[0]
        stack = [(np.eye(3), 0)]
        pieces = []
        while stack:
            b, depth = stack.pop()
            corners = b @ uv[f]
            x0, y0, x1, y1 = (int(v[0]) for v in _texel_box(corners[None], width, height))
            opaque = sum(bool(opaque_image[r % height, c % width]) for r in range(y0, y1) for c in range(x0, x1))
            total = (x1 - x0) * (y1 - y0)
            if opaque == total:
                pieces.append((depth, b))
            elif opaque > 0:
                if depth >= limit:
                    if sample_bilinear(alpha[:, :, None], corners.mean(axis=0)[None])[0, 0] >= np.float32(cutoff):
                        pieces.append((depth, b))
                else:
                    for child in _split(b[None])[::-1]:
                        stack.append((child, depth + 1))
        # the fast path lists a triangle's pieces level by level, each level in split order
        pieces.sort(key=lambda p: p[0])
        out_face += [f] * len(pieces)
        out_bary += [p[1] for p in pieces]
    return np.asarray(out_face, dtype=np.int64), np.asarray(out_bary, dtype=np.float64).reshape(-1, 3, 3)


def cut_within_budget(jobs: list, budget: int = CUT_BUDGET) -> list:
    """:func:`cut_triangles` on every ``(uv, alpha, cutoff)`` of ``jobs``, all at the deepest
    level (at most :data:`MAX_DEPTH`) whose pieces number ``budget`` or fewer in all (at least
    one level: 0)."""
    # Jobs on the same alpha array and cutoff (parts sharing a texture) are cut in one call: one
    # summed-area table per texture, however many parts use it.
    groups: dict = {}
    for k, (uv, alpha, cutoff) in enumerate(jobs):
        groups.setdefault((id(alpha), float(cutoff)), []).append(k)
    for depth in range(MAX_DEPTH, -1, -1):
        results: list = [None] * len(jobs)
        for members in groups.values():
            uvs = [np.asarray(jobs[k][0], dtype=np.float64).reshape(-1, 3, 2) for k in members]
            face, bary = cut_triangles(np.concatenate(uvs), jobs[members[0]][1], jobs[members[0]][2], depth)
            edges = np.cumsum([0] + [len(u) for u in uvs])
            for k, lo, hi in zip(members, edges[:-1], edges[1:]):
                rows = (face >= lo) & (face < hi)
                results[k] = (face[rows] - lo, bary[rows])
        if sum(len(face) for face, _ in results) <= budget:
            break
    return results


def cut_corners(positions: np.ndarray, uvs: np.ndarray, owner: np.ndarray, masks: dict, budget: int = CUT_BUDGET):
    """Triangles given by their corners, those of the masked owners replaced by their opaque pieces.

    Parameters
    ----------
    positions : (T, 3, 3) float64
    uvs : (T, 3, 2) float64
    owner : (T,) int, the object of each triangle
    masks : dict of owner -> (alpha (H, W), cutoff)

    Returns
    -------
    positions (T', 3, 3), uvs (T', 3, 2), owner (T',), source (T',) int64
        Each kept triangle or piece in the order of the triangles it comes from; ``source``: that
        triangle's index.
    """
    owner = np.asarray(owner, dtype=np.int64)
    cut = [np.flatnonzero(owner == o) for o in masks]
    results = cut_within_budget([(uvs[rows], alpha, cutoff) for rows, (alpha, cutoff) in zip(cut, masks.values())], budget)
    keep = np.ones(len(owner), dtype=bool)
    source, bary = [], []
    for rows in cut:
        keep[rows] = False
    whole = np.flatnonzero(keep)
    source.append(whole)
    bary.append(np.broadcast_to(np.eye(3), (len(whole), 3, 3)))
    for rows, (face, weights) in zip(cut, results):
        source.append(rows[face])
        bary.append(weights)
    source, bary = np.concatenate(source), np.concatenate(bary)
    order = np.argsort(source, kind="stable")
    source, bary = source[order], bary[order]
    interpolate = lambda corners: np.einsum("kcj,kjd->kcd", bary, corners[source])  # noqa: E731
    return interpolate(np.asarray(positions, np.float64)), interpolate(np.asarray(uvs, np.float64)), owner[source], source
