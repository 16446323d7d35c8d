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
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError

if TYPE_CHECKING:
    from .manifest import Manifest

__all__ = ["kd_arrays", "assign_segments", "segment_of", "segment_sort", "segment_sort_reference"]


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


def segment_sort_reference(segment: np.ndarray, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Plain twin of :func:`segment_sort` (one ``flatnonzero`` pass per segment), for tests."""
    parts = [np.flatnonzero(segment == s) for s in range(n_segments)]
    if np.any(segment >= n_segments):
        raise InputError(f"segment {int(segment.max())} appears in the G-buffer but the scene has no such segment")
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    return (np.concatenate(parts) if parts else np.zeros(0, np.int64)).astype(np.int64), offsets
