"""The segment rule: which segment a surface point belongs to, by the scene's k-d tree.

Training (:meth:`prt.train.networks.segments.Segmentation.assign`) and the runtime
(:func:`segment_of`, and per fragment the G-buffer's ``segment_lookup.glsl``) use this one
rule, so samples, points and fragments agree on every segment boundary.

From ``roots[object_id]`` the descent goes left when ``point[axis] <= split`` and right
otherwise, down to a leaf ``i``; the segment is ``leaf_segment[i]``.  Points of an object
with no root go to the segment whose box is nearest (Euclidean distance to the box, 0
inside it; ties to the lowest id).

:func:`segment_sort` groups pixels or rows by segment (a counting sort; the ONNX backend's
packing and the screen-space interpolation's refused pixels), with its plain twin
:func:`segment_sort_reference`.

:func:`face_segments` gives the segment of each triangle that lies wholly in one k-d leaf, with a
margin (the G-buffer draws those triangles with their segment as a flat attribute and runs the
per-fragment descent only on the others, :class:`prt.runtime.gbuffer.GBufferPass`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError

if TYPE_CHECKING:
    from .manifest import Manifest

__all__ = ["kd_arrays", "assign_segments", "segment_of", "segment_sort", "segment_sort_reference", "scatter_rows", "take_rows", "face_segments", "FACE_MARGIN"]

FACE_MARGIN = (1e-4, 1.0 / 16.0)
"""A triangle takes a side of a split only when all of it lies at least ``1e-4 + extent / 16`` from the
split (``extent``: the triangle's own extent along the split's axis): an interpolated fragment
position can lie a little outside its triangle (rounding, sub-pixel vertex snapping), never by that."""


def kd_arrays(nodes: list[dict]) -> tuple[np.ndarray, ...]:
    """A k-d tree's nodes as flat arrays ``(axis, split, left, right, leaf)``; axis -1 marks a leaf."""
    axis = np.array([n.get("axis", -1) for n in nodes], dtype=np.int64)
    split = np.array([n.get("split", 0.0) for n in nodes], dtype=np.float64)
    left = np.array([n.get("left", -1) for n in nodes], dtype=np.int64)
    right = np.array([n.get("right", -1) for n in nodes], dtype=np.int64)
    leaf = np.array([n.get("leaf", -1) for n in nodes], dtype=np.int64)
    return axis, split, left, right, leaf


def assign_segments(kd: tuple[np.ndarray, ...], roots: dict[int, int], leaf_segment: np.ndarray,
                    bounds: np.ndarray, points: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The segment rule shared by training and runtime (see the module docstring).

    kd : :func:`kd_arrays` of the nodes; roots : object id -> root node; leaf_segment : (L,);
    bounds : (S, 2, 3) segment boxes; points : (N, 3) float64; ids : (N,) int -> (N,) int64
    """
    axis, split, left, right, leaf = kd
    node = np.full(len(points), -1, dtype=np.int64)
    for obj, root in roots.items():
        node[ids == obj] = root
    # One tree level per pass over the points still at inner nodes; validation ruled out cycles.
    active = np.flatnonzero(node >= 0)
    while active.size:
        current = node[active]
        inner = axis[current] >= 0
        active, current = active[inner], current[inner]
        go_left = points[active, axis[current]] <= split[current]
        node[active] = np.where(go_left, left[current], right[current])

    out = np.empty(len(points), dtype=np.int64)
    rooted = node >= 0
    out[rooted] = np.asarray(leaf_segment)[leaf[node[rooted]]]
    if not rooted.all():
        p = points[~rooted][:, None, :]
        gap = np.maximum(bounds[None, :, 0] - p, 0.0) + np.maximum(p - bounds[None, :, 1], 0.0)
        out[~rooted] = np.argmin(np.linalg.norm(gap, axis=2), axis=1)
    return out


def segment_of(manifest: Manifest, points: Any, object_ids: Any) -> np.ndarray:
    """Segment of each surface point, by the manifest's k-d tree (the rule above).

    Parameters
    ----------
    manifest : Manifest
    points : array_like, shape (N, 3)
        Scene-space positions.
    object_ids : array_like of int, shape (N,)
        Object of each point.

    Returns
    -------
    ndarray of int64, shape (N,)

    Raises
    ------
    InputError
        If the shapes or the id dtype are wrong.
    """
    points = np.asarray(points, dtype=np.float64)
    ids = np.asarray(object_ids)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"segment_of: points must have shape (N, 3), got {points.shape}")
    if ids.shape != (len(points),):
        raise InputError(f"segment_of: object_ids must have shape ({len(points)},), got {ids.shape}")
    if len(ids) and ids.dtype.kind not in "iu":
        raise InputError(f"segment_of: object_ids must be integers, got dtype {ids.dtype}")

    seg = manifest.segmentation
    return assign_segments(kd_arrays(seg["nodes"]), seg["roots"], seg["leaf_segment"], manifest.bounds, points, ids)


def segment_sort(segment: np.ndarray, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """The covered pixels grouped by segment: a stable counting sort, O(N).

    Parameters
    ----------
    segment : (P,) int, segment id per pixel, -1 on background
    n_segments : ids must lie in ``0 .. n_segments - 1``

    Returns
    -------
    order : (M,) int64, the covered pixels (segment >= 0), segment by segment, ascending within each
    offsets : (n_segments + 1,) int64, segment ``s`` is ``order[offsets[s]:offsets[s + 1]]``

    Raises
    ------
    InputError
        If an id is ``n_segments`` or more.
    """
    covered = np.flatnonzero(segment >= 0)
    seg = segment[covered]
    if len(seg) and int(seg.max()) >= n_segments:
        raise InputError(f"segment {int(seg.max())} appears in the G-buffer but the scene has no such segment")
    # NumPy's stable argsort is a radix (counting) sort for 8- and 16-bit integers.
    small = np.uint8 if n_segments <= 1 << 8 else np.uint16 if n_segments <= 1 << 16 else np.int64
    order = np.argsort(seg.astype(small), kind="stable")
    offsets = np.searchsorted(seg[order], np.arange(n_segments + 1)).astype(np.int64)
    return covered[order], offsets


def scatter_rows(image: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """``image[rows] = values`` for C-contiguous (P, C) and (M, C) of one dtype: each row moved as one
    C * itemsize-byte item (a plain 2-D fancy assignment moves element by element, 3x slower)."""
    width = image.shape[1] * image.itemsize
    if image.flags.c_contiguous and values.flags.c_contiguous and values.dtype == image.dtype and len(values):
        image.view(f"V{width}").reshape(-1)[rows] = values.view(f"V{width}").reshape(-1)
    else:
        image[rows] = values


def take_rows(array: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``array[rows]`` (a new (M, C) array) for a C-contiguous (P, C) array, each row taken as one item."""
    if array.ndim != 2 or not array.flags.c_contiguous or array.shape[1] == 0:
        return array[rows]
    return array.view(f"V{array.shape[1] * array.itemsize}").reshape(-1)[rows].view(array.dtype).reshape(len(rows), array.shape[1])


def segment_sort_reference(segment: np.ndarray, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Plain twin of :func:`segment_sort` (one ``flatnonzero`` pass per segment), for tests."""
    parts = [np.flatnonzero(segment == s) for s in range(n_segments)]
    if np.any(segment >= n_segments):
        raise InputError(f"segment {int(segment.max())} appears in the G-buffer but the scene has no such segment")
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    return (np.concatenate(parts) if parts else np.zeros(0, np.int64)).astype(np.int64), offsets


def face_segments(corners: np.ndarray, object_ids: np.ndarray, nodes: np.ndarray, roots: np.ndarray) -> np.ndarray:
    """Segment of every triangle that lies wholly in one leaf of its object's k-d tree, -1 for the others.

    Parameters
    ----------
    corners : (F, 3, 3) float32, the triangles' corners (the positions the segment rule takes)
    object_ids : (F,) int, object id per triangle
    nodes, roots : the G-buffer's tables (:func:`prt.runtime.gbuffer.segment_tables`): nodes (N, 4)
        float32 inner ``(axis, split, left, right)``, leaf ``(-1, 0, segment, segment)``; roots (M,)
        int root node per object id, -1 without one (the nearest-box rule: -1 here)

    Returns
    -------
    (F,) int32.  A triangle gets a segment when, at every node of its descent, its corners lie all
    at or below the split (left) or all above it, by :data:`FACE_MARGIN`, until a leaf or a subtree
    whose leaves are all one segment; then every point of it, and every fragment drawn from it,
    ends in that segment.
    """
    corners = np.asarray(corners, dtype=np.float32)
    lo, hi = corners.min(axis=1).astype(np.float64), corners.max(axis=1).astype(np.float64)
    ids = np.asarray(object_ids, dtype=np.int64)
    inside = (ids >= 0) & (ids < len(roots))
    node = np.where(inside, np.asarray(roots)[np.clip(ids, 0, max(len(roots) - 1, 0))], -1).astype(np.int64)
    out = np.full(len(corners), -1, dtype=np.int32)
    whole = _subtree_segments(nodes)
    active = np.flatnonzero(node >= 0)
    for _ in range(len(nodes) + 1):  # a descent visits each node at most once
        if not len(active):
            break
        n = nodes[node[active]]
        axis = n[:, 0].astype(np.int64)
        done = whole[node[active]] >= 0  # a leaf, or a subtree of one segment: the descent's end
        out[active[done]] = whole[node[active[done]]]
        active, n, axis = active[~done], n[~done], axis[~done]
        split = n[:, 1].astype(np.float64)
        a_lo, a_hi = lo[active, axis], hi[active, axis]
        margin = FACE_MARGIN[0] + FACE_MARGIN[1] * (a_hi - a_lo)
        left, right = a_hi + margin <= split, a_lo - margin > split
        node[active] = np.where(left, n[:, 2], n[:, 3]).astype(np.int64)
        active = active[left | right]  # a triangle across a split keeps -1 (looked up per fragment)
    return out


def _subtree_segments(nodes: np.ndarray) -> np.ndarray:
    """(N,) int32 per node: the segment of every leaf below it when that is one segment, else -1."""
    whole = np.full(len(nodes), -2, dtype=np.int64)  # -2: not yet known
    for root in range(len(nodes)):
        stack, seen = [root], set()
        while stack:  # children before parents, without recursion (trees may be deep)
            i = stack[-1]
            axis, _, left, right = nodes[i]
            if whole[i] != -2:
                stack.pop()
            elif axis < 0:
                whole[i] = int(left)
                stack.pop()
            elif i in seen:
                a, b = whole[int(left)], whole[int(right)]
                whole[i] = a if a == b and a >= 0 else -1  # (a child still unknown: a loop, no shortcut)
                stack.pop()
            else:
                seen.add(i)
                stack += [c for c in (int(left), int(right)) if whole[c] == -2 and c not in seen]
    return whole.astype(np.int32)
