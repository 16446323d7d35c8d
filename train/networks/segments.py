"""Segments: which network is responsible for which part of the scene.

1. Split: samples are grouped by object (optional), then each group is cut by a k-d tree
   (median split along the longest side of a leaf) until the leaf budget is spent.  Which leaf is
   cut next (``split``): the one with the most samples (``"samples"``, the default: leaves of
   equal area), or the one whose transfer a rank-``rank`` PCA explains least as a tone-mapped
   image shows it (``"residual"``: count x RMS residual^2 / (c + mean DC), the 1 / (c + m)
   weight of ``prt-train --loss relative``), so leaves go where shadows make the transfer complex
   and dim, and a smooth region that only sees the sky keeps one big leaf.
   A cut never runs through a plane of samples (a floor, a wall; :func:`split_value`).
2. Merge (CPCA in spirit): transfer in a region that only sees the sky is an exact function
   of the normal and lies in a low-dimensional affine subspace; shadows add what that subspace
   cannot explain.  For each leaf we keep the first and second moments of its transfer, so
   the residual of a rank-``r`` PCA of any union of leaves costs one small eigenproblem.
   Neighbouring segments are merged greedily, cheapest union first, while the union's RMS
   residual stays under a tolerance: simple regions share a network, complex ones keep theirs.
   A union holds at most :data:`MERGE_SHARE` times the leaf budget's share of the samples unless
   the subspace explains it to :data:`MERGE_EXACT` of its RMS transfer (:data:`MERGE_RULE`): the
   residual test sees only the subspace the transfer lies in, not how it varies over the surface,
   and on a building it passes for most of the house (dim rooms' transfer lies in a few dimensions
   whatever their shadows do), leaving a third of a house to one small network; a plane that only
   sees the sky is still one segment.
3. Margin: each segment also trains on the samples of its neighbours that continue its own
   surface within ``delta`` of it, so two networks agree where they meet (:data:`MARGIN_RULE`).
   A seam in an image is where one surface passes from one network to the next; a sample across
   a corner, on a parallel surface or on the far face of a thin wall (a room on the other side,
   the lit facade behind a dark wall) is never next to this network's pixels, and would only
   cost it capacity: it is left out.

4. Refinement (:func:`split_segment`): a build under its floor (:mod:`prt.train.refine`) cuts the
   segments where the held-out error concentrates in two after the fact: a segment of several
   merged leaves gives back half of them, a segment of one leaf has it cut as in 1.

The tree is kept, so ``assign(points, object_ids)`` tells the segment of any surface point
by the rule of :mod:`prt.runtime.segmentation` (the runtime applies it to fragments).  Every sample knows its segment.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ...runtime.segmentation import assign_segments, kd_arrays

__all__ = ["Segmentation", "segment_samples", "split_segment", "with_margin", "split_value", "SPLIT_RULE", "SPLIT_BY", "MARGIN_RULE", "MERGE_RULE"]

SPLIT_RULE = "off-plane-v1"
"""How cuts are placed (part of the precompute's cache key): the median, moved off planes of samples."""

MARGIN_RULE = "same-surface-v1"
"""Which neighbours' samples a segment's margin holds (part of the precompute's cache key): those within ``delta``
of one of its own samples whose normal is within 60 degrees of theirs (:data:`MARGIN_COS`) and that lie within 30
degrees of its tangent plane (:data:`MARGIN_SLOPE`), among its :data:`MARGIN_NEIGHBOURS` nearest own samples."""

MERGE_RULE = "share-2-exact-0.01"
"""How far merging may go (part of the precompute's cache key): a union of leaves holds at most
:data:`MERGE_SHARE` x samples / leaf budget samples, unless its PCA residual is at most
:data:`MERGE_EXACT` x its RMS transfer."""

MERGE_SHARE = 2.0
MERGE_EXACT = 0.01

MARGIN_COS = 0.5
MARGIN_SLOPE = 0.5
MARGIN_NEIGHBOURS = 8

SPLIT_BY = ("samples", "residual")
"""Which leaf the k-d split cuts next: the most samples, or the most unexplained transfer (see above)."""

DIM_FLOOR = 0.05
"""c of the "residual" split's 1 / (c + mean DC) weight: ``prt.train.networks.fit.RELATIVE_FLOOR`` (not imported:
this module stays free of torch), so a leaf in the dark weighs at most 6.6x one under the open sky."""

PLANE_SHARE = 0.02
"""Share of a leaf's samples within the tolerance of its median that makes the median lie on a plane."""

PLANE_TOLERANCE = 1e-3
"""Half-width of a plane of samples, as a share of the leaf's extent along the cut's axis: above the
G-buffer's distance from the true surface (sphere tracing stops within 1e-4 of the ray's length;
rasterised positions round in float32)."""


@dataclass
class _Moments:
    count: int
    total: np.ndarray  # (n,)
    outer: np.ndarray  # (n, n)

    @classmethod
    def of(cls, transfer: np.ndarray) -> "_Moments":
        t = np.asarray(transfer, dtype=np.float64)
        return cls(len(t), t.sum(axis=0), t.T @ t)

    def __add__(self, other: "_Moments") -> "_Moments":
        return _Moments(self.count + other.count, self.total + other.total, self.outer + other.outer)

    def rms(self) -> float:
        """RMS (per sample) of the transfer vectors' length."""
        return float(np.sqrt(max(np.trace(self.outer), 0.0) / self.count)) if self.count else 0.0

    def residual_rms(self, rank: int) -> float:
        """RMS (per sample, over all coefficients) of what a rank-``rank`` PCA leaves out."""
        if self.count == 0:
            return 0.0
        mean = self.total / self.count
        cov = self.outer / self.count - np.outer(mean, mean)
        eig = np.clip(np.linalg.eigvalsh(cov), 0.0, None)  # ascending
        return float(np.sqrt(eig[: max(len(eig) - rank, 0)].sum()))


@dataclass
class Segmentation:
    """Segments of a scene and the rule that maps surface points to them.

    nodes : k-d tree, one dict per node: ``{"axis", "split", "left", "right"}`` for inner
        nodes, ``{"leaf": i}`` for leaves
    roots : ``{object_id: root node index}``
    leaf_segment : (n_leaves,) int, final segment of each leaf (after merging)
    bounds : (S, 2, 3) float, box of each segment's own samples
    residual_rms : (S,) float, rank-``rank`` PCA residual of each segment's transfer
    home : (N,) int, segment of each sample
    members : list of S index arrays: own samples plus the margin samples of neighbours
    """

    nodes: list[dict]
    roots: dict[int, int]
    leaf_segment: np.ndarray
    bounds: np.ndarray
    residual_rms: np.ndarray
    home: np.ndarray
    members: list[np.ndarray]
    delta: float
    rank: int
    leaves_before_merge: int
    notes: list[str] = field(default_factory=list)
    moved_cuts: int = 0  # k-d cuts the off-plane rule moved from the median (split_value)

    @property
    def count(self) -> int:
        return len(self.bounds)

    def assign(self, points: np.ndarray, object_ids: np.ndarray) -> np.ndarray:
        """Segment of each point (N, 3) on object ``object_ids`` (N,).

        Points of an object that received no samples go to the segment with the nearest box.
        """
        return assign_segments(
            kd_arrays(self.nodes), self.roots, self.leaf_segment, self.bounds,
            np.asarray(points, dtype=np.float64), np.asarray(object_ids),
        )  # fmt: skip

    def to_json(self) -> dict:
        return {
            "count": self.count,
            "delta": self.delta,
            "pca_rank": self.rank,
            "leaves_before_merge": self.leaves_before_merge,
            "roots": {str(k): v for k, v in self.roots.items()},
            "nodes": self.nodes,
            "leaf_segment": self.leaf_segment.tolist(),
            "segments": [
                {
                    "id": s,
                    "bounds": self.bounds[s].tolist(),
                    "samples": int((self.home == s).sum()),
                    "margin_samples": int(len(self.members[s]) - (self.home == s).sum()),
                    "residual_rms": float(self.residual_rms[s]),
                }
                for s in range(self.count)
            ],
            "notes": self.notes,
        }


def segment_samples(
    points: np.ndarray,
    object_ids: np.ndarray,
    transfer: np.ndarray,
    *,
    normals: np.ndarray | None,
    max_segments: int = 8,
    by_object: bool = True,
    merge: bool = True,
    merge_tolerance: float = 0.01,
    rank: int = 8,
    delta: float = 0.05,
    min_samples: int = 256,
    split: str = "samples",
) -> Segmentation:
    """Split a scene's samples into segments, merge the simple ones, add seam margins.

    Parameters
    ----------
    points : (N, 3) sample positions (scene units)
    object_ids : (N,) object of each sample
    transfer : (N, n) ground-truth transfer of each sample
    normals : (N, 3) unit normal of each sample (the side it stands for): the margin holds only samples
        that continue a segment's surface; None: every neighbour within ``delta`` (a deforming build,
        whose samples carry their pose's normals at rest positions)
    max_segments : leaf budget of the spatial split (at least one leaf per object)
    by_object : never let a segment's tree cell span two objects before merging
    merge : merge neighbouring segments whose union stays simple
    merge_tolerance : largest RMS PCA residual a merged segment may have (and it holds at most
        :data:`MERGE_SHARE` x ``len(points) / max_segments`` samples unless :data:`MERGE_EXACT` holds)
    rank : PCA rank of the residual test (8 spans unshadowed transfer of 3 bands)
    delta : margin width (scene units) sampled into neighbouring segments (on the same surface)
    min_samples : leaves are not split below twice this count
    split : which leaf is cut next, one of :data:`SPLIT_BY`
    """
    if split not in SPLIT_BY:
        raise ValueError(f"split: expected one of {', '.join(SPLIT_BY)}, got {split!r}")
    points = np.asarray(points, dtype=np.float64)
    object_ids = np.asarray(object_ids, dtype=np.int64)
    transfer = np.asarray(transfer, dtype=np.float64)
    normals = None if normals is None else np.asarray(normals, dtype=np.float64)
    if not (len(points) == len(object_ids) == len(transfer) == (len(points) if normals is None else len(normals))):
        raise ValueError("points, normals, object_ids and transfer differ in length")
    if len(points) == 0:
        raise ValueError("no samples to segment")
    if not np.isfinite(points).all() or not np.isfinite(transfer).all() or (normals is not None and not np.isfinite(normals).all()):
        raise ValueError("samples contain NaN or Inf")

    groups = np.unique(object_ids) if by_object else np.array([-1])
    nodes: list[dict] = []
    roots: dict[int, int] = {}
    leaves: list[tuple[int, np.ndarray]] = []  # (node index, sample indices)
    for g in groups:
        sel = np.flatnonzero(object_ids == g) if by_object else np.arange(len(points))
        nodes.append({})
        leaves.append((len(nodes) - 1, sel))
        if by_object:
            roots[int(g)] = len(nodes) - 1
    if not by_object:
        roots = {int(o): 0 for o in np.unique(object_ids)}

    budget = max(int(max_segments), len(leaves))
    moved = 0  # cuts the off-plane rule moved from the median
    unexplained: dict[int, float] = {}  # node -> its "residual" score (count x RMS residual^2 / dim), once per leaf

    def score(leaf: tuple[int, np.ndarray]) -> float:
        node, sel = leaf
        if len(sel) < 2 * min_samples:
            return -1.0  # too small to cut
        if split == "samples":
            return float(len(sel))
        if node not in unexplained:
            dim = DIM_FLOOR + float(np.maximum(transfer[sel, 0], 0.0).mean())  # tone mapping magnifies dim errors
            unexplained[node] = len(sel) * _Moments.of(transfer[sel]).residual_rms(rank) ** 2 / dim
        return unexplained[node]

    while len(leaves) < budget:
        chosen = max(range(len(leaves)), key=lambda i: score(leaves[i]))
        node, sel = leaves[chosen]
        if score(leaves[chosen]) < 0:
            break  # every leaf is too small (or flat) to cut
        p = points[sel]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        cut = split_value(p[:, axis])
        left = p[:, axis] <= cut
        if left.all() or not left.any():  # all samples on one plane along the longest axis
            if split == "samples":
                break  # the biggest leaf cannot be cut: nothing left to cut
            unexplained[node] = -1.0  # this leaf stays whole; cut the next most complex one
            continue
        moved += cut != float(np.median(p[:, axis]))
        nodes.append({})
        nodes.append({})
        li, ri = len(nodes) - 2, len(nodes) - 1
        nodes[node] = {"axis": axis, "split": cut, "left": li, "right": ri}
        leaves[chosen] = (li, sel[left])
        leaves.append((ri, sel[~left]))

    for i, (node, _) in enumerate(leaves):
        nodes[node] = {"leaf": i}
    leaf_samples = [sel for _, sel in leaves]
    leaf_box = np.array([[points[s].min(axis=0), points[s].max(axis=0)] for s in leaf_samples])
    moments = [_Moments.of(transfer[s]) for s in leaf_samples]

    # Union-find style merging over a neighbour graph of boxes grown by delta.
    segment_of_leaf = np.arange(len(leaves))
    members_of = {i: [i] for i in range(len(leaves))}
    seg_moments = {i: moments[i] for i in range(len(leaves))}
    seg_box = {i: leaf_box[i].copy() for i in range(len(leaves))}
    notes: list[str] = []
    if merge:
        most = MERGE_SHARE * len(points) / max(int(max_segments), 1)
        while True:
            best = None
            ids = sorted(members_of)
            for a_i, a in enumerate(ids):
                for b in ids[a_i + 1 :]:
                    if not _boxes_touch(seg_box[a], seg_box[b], delta):
                        continue
                    union = seg_moments[a] + seg_moments[b]
                    cost = union.residual_rms(rank)
                    if union.count > most and cost > MERGE_EXACT * union.rms():
                        continue
                    if cost <= merge_tolerance and (best is None or cost < best[0]):
                        best = (cost, a, b)
            if best is None:
                break
            _, a, b = best
            members_of[a] += members_of.pop(b)
            seg_moments[a] = seg_moments[a] + seg_moments.pop(b)
            seg_box[a] = np.array([np.minimum(seg_box[a][0], seg_box[b][0]), np.maximum(seg_box[a][1], seg_box[b][1])])
            del seg_box[b]
    final_ids = sorted(members_of)
    for new, old in enumerate(final_ids):
        for leaf in members_of[old]:
            segment_of_leaf[leaf] = new

    home = np.empty(len(points), dtype=np.int64)
    for leaf, sel in enumerate(leaf_samples):
        home[sel] = segment_of_leaf[leaf]
    bounds = np.array([seg_box[old] for old in final_ids])
    residual = np.array([seg_moments[old].residual_rms(rank) for old in final_ids])

    members = [_with_margin(points, normals, home, s, bounds[s], delta) for s in range(len(final_ids))]
    if len(final_ids) < len(leaves):
        notes.append(f"merged {len(leaves)} leaves into {len(final_ids)} segments")
    return Segmentation(
        nodes=nodes,
        roots=roots,
        leaf_segment=segment_of_leaf,
        bounds=bounds,
        residual_rms=residual,
        home=home,
        members=members,
        delta=float(delta),
        rank=int(rank),
        leaves_before_merge=len(leaves),
        notes=notes,
        moved_cuts=int(moved),
    )


def split_segment(tree: dict, points: np.ndarray, object_ids: np.ndarray, home: np.ndarray, s: int, *,
                  min_samples: int = 256) -> tuple[dict, np.ndarray] | None:
    """Segment ``s`` cut in two: ``(tree, home)`` with the new segment's id ``len(tree["segments"])``,
    or None when it cannot be cut (too few samples, all on one plane).

    ``tree``: ``segments.json``'s ``nodes``, ``roots``, ``leaf_segment`` and ``segments`` (not
    changed: a new dict comes back); ``home``: the segment of each training sample (a new array
    comes back).  A segment of several leaves (merged) keeps the leaves of the lower half of its
    samples along its longest side and gives the others to the new segment; a segment of one leaf
    (or one leaf holding 3/4 of its samples) has that leaf cut by :func:`split_value` along the
    leaf's longest side.  The new segment's ``bounds`` and ``samples`` are set; its
    ``margin_samples`` and ``residual_rms`` are left to the caller.
    """
    nodes = [dict(n) for n in tree["nodes"]]
    leaf_segment = [int(v) for v in tree["leaf_segment"]]
    roots = {int(k): int(v) for k, v in tree["roots"].items()}
    own = np.flatnonzero(np.asarray(home) == s)
    if len(own) < 2 * min_samples:
        return None
    points = np.asarray(points, dtype=np.float64)
    leaves = [i for i, g in enumerate(leaf_segment) if g == s]
    leaf_of = assign_segments(kd_arrays(nodes), roots, np.arange(len(leaf_segment)), np.zeros((len(leaf_segment), 2, 3)),
                              points[own], np.asarray(object_ids)[own])  # fmt: skip
    counts = {i: int(np.count_nonzero(leaf_of == i)) for i in leaves}
    new = len(tree["segments"])
    largest = max(leaves, key=lambda i: counts[i])
    if len(leaves) > 1 and counts[largest] < 0.75 * len(own):
        p = points[own]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        order = sorted((i for i in leaves if counts[i]), key=lambda i: float(np.mean(p[leaf_of == i, axis])))
        kept, total = [], 0
        for i in order:
            if total >= 0.5 * len(own):
                break
            kept.append(i)
            total += counts[i]
        moved = [i for i in leaves if i not in kept]
        if not moved or not kept:
            return None
        for i in moved:
            leaf_segment[i] = new
        goes = np.isin(leaf_of, moved)
    else:
        sel = leaf_of == largest
        if sel.sum() < 2 * min_samples:
            return None
        p = points[own[sel]]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        cut = split_value(p[:, axis])
        left = p[:, axis] <= cut
        if left.all() or not left.any():
            return None
        node = next(k for k, n in enumerate(nodes) if n.get("leaf") == largest)
        nodes.append({"leaf": largest})
        nodes.append({"leaf": len(leaf_segment)})
        nodes[node] = {"axis": axis, "split": float(cut), "left": len(nodes) - 2, "right": len(nodes) - 1}
        leaf_segment.append(new)
        goes = np.zeros(len(own), dtype=bool)
        goes[np.flatnonzero(sel)[~left]] = True
    home = np.array(home, dtype=np.int64, copy=True)
    home[own[goes]] = new
    segments = [dict(g) for g in tree["segments"]]
    for g, idx in ((s, own[~goes]), (new, own[goes])):
        entry = {"id": g, "bounds": [points[idx].min(axis=0).tolist(), points[idx].max(axis=0).tolist()], "samples": int(len(idx))}
        if g < len(segments):
            segments[g] = {**segments[g], **entry}
        else:
            segments.append({**entry, "margin_samples": 0, "residual_rms": 0.0})
    return {**tree, "nodes": nodes, "roots": {str(k): v for k, v in roots.items()}, "leaf_segment": leaf_segment, "segments": segments,
            "count": len(segments)}, home  # fmt: skip


def with_margin(points: np.ndarray, normals: np.ndarray, home: np.ndarray, segment: int, delta: float) -> np.ndarray:
    """A segment's members (own samples and its neighbours' on its surface within ``delta``), its box from its own samples."""
    own = np.asarray(points)[np.asarray(home) == segment]
    box = np.array([own.min(axis=0), own.max(axis=0)])
    return _with_margin(np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64), np.asarray(home), segment, box, delta)


def split_value(values: np.ndarray) -> float:
    """Where a leaf's samples are cut along an axis (``values``: their coordinates on it): the median,
    unless the median lies on a plane of samples.

    A surface perpendicular to the axis (a floor, a wall, a box's face) holds many samples at one
    coordinate, and the median of a leaf holding it often lies exactly there.  A cut through that
    surface keeps its samples on one side, but the fragments the runtime shades there lie a hair
    off the surface (sphere tracing stops short of it, rasterised positions round), on either side
    of the cut: half the surface would run a network that never saw it.  So when at least
    ``PLANE_SHARE`` of the samples lie within ``PLANE_TOLERANCE`` of the leaf's extent from the
    median, the cut moves that tolerance beyond the plane's samples, to the side that leaves the two
    halves closer in size (the plane then lies wholly in one of them).
    """
    values = np.asarray(values, dtype=np.float64)
    median = float(np.median(values))
    tol = PLANE_TOLERANCE * float(values.max() - values.min())
    near = np.abs(values - median) <= tol
    if tol <= 0 or near.sum() < PLANE_SHARE * len(values):
        return median
    half = 0.5 * len(values)
    best = None
    for cut in (float(values[near].min()) - tol, float(values[near].max()) + tol):
        left = int(np.count_nonzero(values <= cut))
        if 0 < left < len(values) and (best is None or abs(left - half) < best[0]):
            best = (abs(left - half), cut)
    return median if best is None else best[1]


def _with_margin(points: np.ndarray, normals: np.ndarray | None, home: np.ndarray, segment: int, box: np.ndarray, delta: float) -> np.ndarray:
    """Own samples plus other segments' samples that continue one of the own samples' surface within ``delta``
    (:data:`MARGIN_RULE`)."""
    from scipy.spatial import cKDTree

    own = home == segment
    near_box = np.all((points >= box[0] - delta) & (points <= box[1] + delta), axis=1) & ~own
    candidates = np.flatnonzero(near_box)
    if len(candidates) and delta > 0:
        own_idx = np.flatnonzero(own)
        k = min(MARGIN_NEIGHBOURS, len(own_idx))
        dist, idx = cKDTree(points[own_idx]).query(points[candidates], k=k, distance_upper_bound=delta)
        dist, idx = dist.reshape(len(candidates), k), idx.reshape(len(candidates), k)
        found = np.isfinite(dist)
        if normals is None:  # the distance rule
            return np.sort(np.concatenate([own_idx, candidates[found[:, 0]]]))
        near = own_idx[np.where(found, idx, 0)]  # (C, k) own samples next to each candidate
        facing = np.einsum("ckj,cj->ck", normals[near], normals[candidates]) >= MARGIN_COS
        off_plane = np.abs(np.einsum("ckj,ckj->ck", normals[near], points[candidates][:, None] - points[near]))
        in_plane = off_plane <= MARGIN_SLOPE * np.where(found, dist, 0.0) + 1e-9
        candidates = candidates[(found & facing & in_plane).any(axis=1)]
    else:
        candidates = candidates[:0]
    return np.sort(np.concatenate([np.flatnonzero(own), candidates]))


def _boxes_touch(a: np.ndarray, b: np.ndarray, delta: float) -> bool:
    return bool(np.all(a[0] - delta <= b[1]) and np.all(b[0] - delta <= a[1]))
