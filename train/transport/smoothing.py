"""The bounce stage's training targets averaged over neighbours on their side of walls (issue 43).

The indirect part of each training sample's transfer (:func:`prt.train.transport.interreflection.bounce_stage`)
is the mean of a few dozen gathered rays; :func:`smooth_indirect` averages it with the sample's nearest
samples on the same side, :func:`smooth_indirect_reference` is its plain twin.
"""

from __future__ import annotations

import numpy as np

from .interreflection import CLEAR_RULE, NORMAL_WEIGHT, clear_between

__all__ = ["smooth_indirect", "smooth_indirect_reference", "SMOOTH_NEIGHBOURS", "SMOOTH_REACH", "SMOOTH_RULE"]


# The indirect targets the networks fit are averaged over each training sample's nearest samples
# on its side of the surface (:func:`smooth_indirect`): 32 gathered rays leave the indirect part
# noisy (a room lit by a sun patch: a few rays of 32 find it), and networks with 1000 steps fit
# part of that noise.  One-off check on the Duplex house's build (2 of its segments, networks
# refitted at their build sizes, 800 held-out points against a quiet reference: 2048 direct rays,
# 512 bounce rays): raw targets 24.1 / 28.8 dB, averaged over 8 neighbours 26.8 / 30.2 dB.
SMOOTH_NEIGHBOURS = 8
# Neighbours farther than this many times the median distance of every sample's SMOOTH_NEIGHBOURS-th
# neighbour (in (position, NORMAL_WEIGHT * normal)) are left out: the filter's width follows the
# sample spacing, and an isolated sample (a small part, a sliver) keeps its own value.
SMOOTH_REACH = 2.0
SMOOTH_RULE = "smooth8-" + CLEAR_RULE  # part of the fits' cache key (prt.train.build)


def smooth_indirect(points, normals, indirect, neighbours: int = SMOOTH_NEIGHBOURS, *, tracer=None, chunk: int = 65536,
                    workers: int = -1) -> np.ndarray:  # fmt: skip
    """Each sample's indirect transfer averaged with its ``neighbours - 1`` nearest samples on its side.

    Nearest in (position, :data:`NORMAL_WEIGHT` * normal), the bounce stage's own distance: the other
    side of a sheet, and a surface turned by more than a few degrees, lie far beyond the sample spacing.
    Neighbours beyond :data:`SMOOTH_REACH` times the median distance of the samples' last neighbour are
    left out (the sample itself, at distance 0, always counts).  Indirect light varies on the scale of the scene, not of
    the sample spacing, so the mean keeps it and takes out the gather's noise.  With the scene's
    ``tracer``, a neighbour whose segment from the sample crosses a surface (:func:`clear_between`:
    the floor beyond a wall) is left out too.

    Parameters
    ----------
    points, normals : (S, 3)
    indirect : (S, n, 3) the bounce stage's indirect transfer
    neighbours : samples in each mean, the sample included (<= 1: ``indirect`` unchanged)
    tracer : the scene's tracer (:class:`prt.train.transport.transfer.EmbreeTracer`), optional

    Returns
    -------
    (S, n, 3) float32
    """
    from scipy.spatial import cKDTree

    indirect = np.asarray(indirect)
    k = min(int(neighbours), len(indirect))
    if k <= 1:
        return indirect.astype(np.float32)
    key = np.concatenate([np.asarray(points, np.float64), NORMAL_WEIGHT * np.asarray(normals, np.float64)], axis=1)
    tree = cKDTree(key)
    dist, near = tree.query(key, k=k, workers=workers)
    reach = SMOOTH_REACH * float(np.median(dist[:, -1]))
    keep = dist <= reach  # the first is the sample itself (or a sample at its very place): distance 0
    if tracer is not None:
        keep[:, 1:] &= _clear_neighbours(tracer, key, near, keep)
    out = np.empty(indirect.shape, np.float32)
    for a in range(0, len(indirect), chunk):
        b = min(a + chunk, len(indirect))
        w = keep[a:b].astype(np.float64)
        total = np.einsum("sk,sknc->snc", w, indirect[near[a:b]].astype(np.float64))
        out[a:b] = total / w.sum(axis=1)[:, None, None]
    return out


def _clear_neighbours(tracer, key, near, keep) -> np.ndarray:
    """(S, k - 1) bool: the segment from each sample to each of its kept neighbours after the first is clear."""
    rows, cols = np.nonzero(keep[:, 1:])
    clear = np.zeros(keep[:, 1:].shape, dtype=bool)
    other = key[near[rows, cols + 1]]
    clear[rows, cols] = clear_between(tracer, key[rows, :3], key[rows, 3:], other[:, :3], other[:, 3:])
    return clear


def smooth_indirect_reference(points, normals, indirect, neighbours: int = SMOOTH_NEIGHBOURS, *, tracer=None) -> np.ndarray:
    """Plain twin of :func:`smooth_indirect`: all pairwise distances, one sample and neighbour at a time (small inputs)."""
    indirect = np.asarray(indirect, np.float64)
    k = min(int(neighbours), len(indirect))
    if k <= 1:
        return indirect.astype(np.float32)
    key = np.concatenate([np.asarray(points, np.float64), NORMAL_WEIGHT * np.asarray(normals, np.float64)], axis=1)
    d = np.sqrt(((key[:, None, :] - key[None, :, :]) ** 2).sum(axis=2))
    kth = np.sort(d, axis=1)[:, k - 1]
    reach = SMOOTH_REACH * float(np.median(kth))
    out = np.empty(indirect.shape, np.float32)
    for i in range(len(indirect)):
        order = np.argsort(d[i], kind="stable")[:k]
        kept = [j for j in order if d[i, j] <= reach
                and (tracer is None or j == order[0] or clear_between(tracer, key[None, i, :3], key[None, i, 3:], key[None, j, :3], key[None, j, 3:])[0])]
        out[i] = indirect[kept].mean(axis=0)
    return out
