"""Screen-space transfer interpolation: the networks run on a coarse grid of pixels and on the pixels
where interpolating between grid neighbours would not be safe; everywhere else the transfer is
the mean of its neighbours'.

Transfer is a smooth function of the surface point except at contact shadows, creases and
silhouettes, so most pixels of a frame can take it from their neighbours.  The grid is refined
in three levels (strides 4, 2, 1), coarse first:

1. the covered pixels with ``y % 4 == 0`` and ``x % 4 == 0`` run the network;
2. at stride ``s`` (2, then 1), a pixel of the stride-``s`` grid not on the stride-``2s`` grid
   has two neighbours on that grid (``x +- s`` on a grid row, ``y +- s`` on a grid column) or
   four (the diagonal corners ``y +- s, x +- s``).  It takes their mean when every test holds:

   - every neighbour is covered and in the pixel's segment (one network each side);
   - every neighbour's normal is within ``acos(NORMAL_COS)`` of the pixel's (no crease);
   - the pixel's position lies within ``POSITION_RATIO`` of the neighbours' spread from their
     mean position (no depth discontinuity: a pixel on a near surface between neighbours on a
     far one lies a third of the spread or more from their mean); the test is in the networks'
     input space, so a deformable scene's rest positions serve as well;
   - the neighbours' transfer residuals (below) agree: the L2 norm of their per-coefficient range
     is at most ``tolerance * (|T(t)| + TRANSFER_FLOOR)``, ``T(t)`` the interpolated transfer (the
     interpolation error is bounded by the neighbours' spread; the test is on transfer, not
     radiance, so it holds under any light and material, and relighting the cached frame stays
     exact);

   otherwise the pixel runs the network (all refused pixels of a level in one batch).

What is interpolated is the transfer's *residual* from the unshadowed transfer of each pixel's own
normal (:func:`prt.runtime.sh.unshadowed_transfer`; the first ``bands**2`` coefficients, the
direct part): ``T(t) = U(n_t) + mean_j (T(j) - U(n_j))``.  Where nothing occludes, the residual is
0 and the interpolation exact whatever the normals do (a bumpy surface); where something does,
the residual (the occluded part of the cosine lobe) varies more slowly than the transfer.  The
tests above compare the neighbours' residuals.  The mean of two or four neighbours is the
bilinear interpolation at the pixel's position (the midpoint or the centre).  Interpolated
values serve as neighbours at the next level.
Like any subsampling it cannot see a feature that lies wholly between the coarse grid's pixels
(a shadow line thinner than 4 pixels that no grid pixel touches); a tighter tolerance does not
help there, ``tolerance=None`` (every pixel) does.

:class:`TransferInterpolator` is the fast path (numba kernels on bands of rows, one per thread);
:func:`interpolate_transfer_reference` is its plain numpy twin (per-level array operations) that
tests hold it to.  Both take an ``infer`` callable (position and normal rows grouped by segment,
the segments' offsets) -> transfer rows, so the interpolation knows nothing of the engine.
"""

from __future__ import annotations

import os
import time
from typing import Callable

import numpy as np

from .segmentation import scatter_rows, segment_sort, take_rows

__all__ = [
    "TransferInterpolator",
    "interpolate_transfer",
    "interpolate_transfer_reference",
    "InterpolatedTransfer",
    "check_tolerance",
    "DEFAULT_TOLERANCE",
    "STRIDES",
    "NORMAL_COS",
    "POSITION_RATIO",
    "TRANSFER_FLOOR",
]

DEFAULT_TOLERANCE = 0.1
"""``prt-runtime``'s default tolerance (``--interpolate``); the Renderer's default is None (every pixel)."""

STRIDES = (4, 2, 1)
"""The grid strides, coarse first: the first is inferred, the others interpolated where safe."""

NORMAL_COS = 0.9
"""Smallest cosine between a pixel's normal and a neighbour's (about 26 degrees)."""

POSITION_RATIO = 0.25
"""Largest distance of a pixel's position from its neighbours' mean, as a fraction of the
neighbours' largest distance from that mean (a depth step puts it at 1/3 or more)."""

TRANSFER_FLOOR = 0.05
"""Added to the mean's norm in the transfer test, so that near-black pixels (norm ~0; the
unshadowed transfer's norm is 0.46) are judged against an absolute scale, not a relative one."""

Infer = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``infer(inputs, offsets)``: (R, 6) float32 position and normal rows grouped by segment (segment ``s``
owns rows ``offsets[s]:offsets[s + 1]``) -> (R, n) float32 transfer, row for row
(:meth:`prt.runtime.backends.onnx.OnnxTransfer.infer_sorted`'s contract)."""


class InterpolatedTransfer:
    """The transfer of every covered pixel of a frame and how it was obtained.

    Attributes
    ----------
    covered : (M,) int64, the covered pixels (row-major, row 0 at the top), ascending
    transfer : (M, n) float32
    inputs : (M, 6) float32, position and normal of each covered pixel
    segment : (M,) int32
    inferred : (M,) bool, True where the network ran (else interpolated)
    """

    __slots__ = ("covered", "transfer", "inputs", "segment", "inferred")

    def __init__(self, covered, transfer, inputs, segment, inferred):
        self.covered, self.transfer, self.inputs, self.segment, self.inferred = covered, transfer, inputs, segment, inferred

    @property
    def fraction(self) -> float:
        """Share of the covered pixels that ran the network."""
        return float(self.inferred.mean()) if len(self.inferred) else 0.0


def check_tolerance(tolerance, what: str = "interpolate") -> float | None:
    """``tolerance`` as a float in (0, 1], or None (every pixel runs the network) for None or 0."""
    from .errors import ArgumentTypeError, InputError

    if tolerance is None:
        return None
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.floating, np.integer)):
        raise ArgumentTypeError(f"{what}: expected a number (the relative transfer tolerance) or None, got {type(tolerance).__name__}")
    value = float(tolerance)
    if not (np.isfinite(value) and 0.0 <= value <= 1.0):
        raise InputError(f"{what}: the relative transfer tolerance must be in [0, 1] (0: no interpolation), got {tolerance!r}")
    return value or None


def _prepare(position: np.ndarray, normal: np.ndarray):
    """Covered pixels, their rows, inputs and segments from the two G-buffer targets.

    position, normal : (H, W, >=3) float32, row 0 at the top; ``normal[..., 3]`` is the segment
    id (-1 on background).  Returns covered (M,), row index image (H, W) int32 (-1: background),
    inputs (M, 6) float32, segment (M,) int32.
    """
    height, width = position.shape[:2]
    segment_image = normal[..., 3].astype(np.int32)
    covered = np.flatnonzero(segment_image.reshape(-1) >= 0)
    rows = np.full(height * width, -1, dtype=np.int32)
    rows[covered] = np.arange(len(covered), dtype=np.int32)
    y, x = np.divmod(covered, width)
    inputs = np.empty((len(covered), 6), dtype=np.float32)
    inputs[:, 0:3] = position[y, x, 0:3]
    inputs[:, 3:6] = normal[y, x, 0:3]
    return covered, rows.reshape(height, width), inputs, segment_image.reshape(-1)[covered]


DIRECT = 16
"""Coefficients of the direct (unshadowed-correctable) part: 4 SH bands, the renderer's."""


def unshadowed_monomials() -> np.ndarray:
    """(10, 16) float64 ``C`` with ``unshadowed_transfer(n) = [1, x, y, z, xx, yy, zz, xy, yz, xz] @ C``
    (:func:`prt.runtime.sh.unshadowed_quadratic` with its constant row first)."""
    from .sh import unshadowed_quadratic

    c0, w = unshadowed_quadratic(4)
    return np.ascontiguousarray(np.vstack([c0, w]))


def _unshadowed_reference(normals: np.ndarray, n: int) -> np.ndarray:
    """(M, n) float32: the unshadowed transfer in the direct part, 0 in the rest (the twin's, from sh)."""
    from .sh import unshadowed_transfer

    out = np.zeros((len(normals), n), np.float32)
    out[:, :DIRECT] = unshadowed_transfer(normals.astype(np.float64), 4, np.float64)
    return out


def _level0_rows(rows: np.ndarray, stride: int) -> np.ndarray:
    """Rows of the covered pixels on the coarsest grid, ascending."""
    grid = rows[::stride, ::stride].reshape(-1)
    return np.sort(grid[grid >= 0])


def _fill(transfer: np.ndarray, inferred: np.ndarray, which: np.ndarray, inputs, segment, infer: Infer) -> None:
    """Run the networks on rows ``which`` (grouped by segment for ``infer``) and store their transfer."""
    if len(which):
        ids = segment[which]
        order, offsets = segment_sort(ids, int(ids.max()) + 1)
        which = which[order]
        scatter_rows(transfer, which, infer(take_rows(inputs, which), offsets))  # (a plain assignment where it must)
        inferred[which] = True


# --------------------------------------------------------------------------- numpy twin


def _neighbour_sets(height: int, width: int, s: int):
    """The pixels refined at stride ``s`` and their neighbours, as (ty, tx, [(ny, nx), ...]) per
    class: grid rows (two neighbours along x), grid columns (two along y), centres (four)."""
    c = 2 * s
    classes = []
    ty, tx = np.meshgrid(np.arange(0, height, c), np.arange(s, width, c), indexing="ij")
    classes.append((ty, tx, [(ty, tx - s), (ty, tx + s)]))
    ty, tx = np.meshgrid(np.arange(s, height, c), np.arange(0, width, c), indexing="ij")
    classes.append((ty, tx, [(ty - s, tx), (ty + s, tx)]))
    ty, tx = np.meshgrid(np.arange(s, height, c), np.arange(s, width, c), indexing="ij")
    classes.append((ty, tx, [(ty - s, tx - s), (ty - s, tx + s), (ty + s, tx - s), (ty + s, tx + s)]))
    return classes


def _refine_reference(rows, inputs, segment, transfer, unshadowed, s: int, tolerance: float) -> np.ndarray:
    """One level of the numpy twin: interpolates in place, returns the refused rows (ascending)."""
    height, width = rows.shape
    refused = []
    for ty, tx, corners in _neighbour_sets(height, width, s):
        t = rows[ty, tx].reshape(-1)
        ok = t >= 0
        cs = []
        for ny, nx in corners:
            inside = ((ny >= 0) & (ny < height) & (nx >= 0) & (nx < width)).reshape(-1)
            r = np.where(inside, rows[np.clip(ny, 0, height - 1), np.clip(nx, 0, width - 1)].reshape(-1), -1)
            ok &= r >= 0
            cs.append(r)
        tt = np.where(ok, t, 0)
        cs = [np.where(ok, r, 0) for r in cs]
        ok &= np.all([segment[r] == segment[tt] for r in cs], axis=0)
        n_t = inputs[tt, 3:6].astype(np.float64)
        for r in cs:
            ok &= np.sum(inputs[r, 3:6].astype(np.float64) * n_t, axis=1) >= NORMAL_COS
        p = [inputs[r, 0:3].astype(np.float64) for r in cs]
        p_mean = sum(p) / len(p)
        dev = np.sum((inputs[tt, 0:3] - p_mean) ** 2, axis=1)
        span = np.max([np.sum((q - p_mean) ** 2, axis=1) for q in p], axis=0)
        ok &= dev <= POSITION_RATIO**2 * span
        values = [transfer[r] - unshadowed[r] for r in cs]  # residuals
        mean = values[0] + values[1] if len(values) == 2 else (values[0] + values[1]) + (values[2] + values[3])
        mean = mean * np.float32(1.0 / len(values)) + unshadowed[tt]
        spread = np.max(values, axis=0).astype(np.float64) - np.min(values, axis=0)
        bound = tolerance * (np.sqrt(np.sum(mean.astype(np.float64) ** 2, axis=1)) + TRANSFER_FLOOR)
        ok &= np.sum(spread**2, axis=1) <= bound**2
        transfer[t[ok]] = mean[ok]
        refused.append(t[(t >= 0) & ~ok])
    return np.sort(np.concatenate(refused))


def interpolate_transfer_reference(position, normal, tolerance: float, infer: Infer, n: int) -> InterpolatedTransfer:
    """Plain numpy twin of :func:`interpolate_transfer` (same arguments and result)."""
    covered, rows, inputs, segment = _prepare(position, normal)
    transfer = np.zeros((len(covered), n), dtype=np.float32)
    inferred = np.zeros(len(covered), dtype=bool)
    unshadowed = _unshadowed_reference(inputs[:, 3:6], n)
    _fill(transfer, inferred, _level0_rows(rows, STRIDES[0]), inputs, segment, infer)
    for s in STRIDES[1:]:
        _fill(transfer, inferred, _refine_reference(rows, inputs, segment, transfer, unshadowed, s, tolerance), inputs, segment, infer)
    return InterpolatedTransfer(covered, transfer, inputs, segment, inferred)


# --------------------------------------------------------------------------- fast path


_KERNELS = None


def _kernels():
    """The numba kernels, compiled on first use (cached on disk where numba can write)."""
    global _KERNELS
    if _KERNELS is None:
        _KERNELS = _compile()
    return _KERNELS


FASTMATH = {"reassoc", "contract", "nsz", "arcp", "afn"}
"""The kernels' LLVM flags: sums may be reordered (vectorised); NaN and Inf keep their meaning."""


def _compile():
    import numba

    # The kernels are serial and release the GIL; a pool of Python threads runs them on bands of
    # image rows.  (numba's own parallel loops leave its worker threads busy for milliseconds
    # after each kernel, which slowed the ONNX Runtime call that follows by half.)

    @numba.njit(cache=True, nogil=True)
    def prepare(normal, segment_image, row_counts, first, step):
        """Covered pixels' segment ids, counted per image row (rows first, first + step, ...)."""
        height, width = segment_image.shape
        for y in range(first, height, step):
            count = 0
            for x in range(width):
                sid = np.int32(normal[y, x, 3])
                segment_image[y, x] = sid
                if sid >= 0:
                    count += 1
            row_counts[y] = count

    @numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
    def gather(position, normal, segment_image, starts, rows, covered, inputs, segment, coeffs, unshadowed, first, step):
        """Rows, inputs and segments of the covered pixels, and the unshadowed transfer of their normals
        (``unshadowed_monomials``: ``coeffs`` float32 (10, nd))."""
        height, width = rows.shape
        nd = coeffs.shape[1]
        for y in range(first, height, step):
            r = starts[y]
            for x in range(width):
                sid = segment_image[y, x]
                if sid >= 0:
                    rows[y, x] = r
                    covered[r] = y * width + x
                    for a in range(3):
                        inputs[r, a] = position[y, x, a]
                        inputs[r, 3 + a] = normal[y, x, a]
                    segment[r] = sid
                    nx, ny, nz = normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]
                    xx, yy, zz, xy, yz, xz = nx * nx, ny * ny, nz * nz, nx * ny, ny * nz, nx * nz
                    for ch in range(nd):
                        unshadowed[r, ch] = (coeffs[0, ch] + nx * coeffs[1, ch] + ny * coeffs[2, ch] + nz * coeffs[3, ch]
                                             + xx * coeffs[4, ch] + yy * coeffs[5, ch] + zz * coeffs[6, ch]
                                             + xy * coeffs[7, ch] + yz * coeffs[8, ch] + xz * coeffs[9, ch])  # fmt: skip
                    r += 1
                else:
                    rows[y, x] = -1

    @numba.njit(cache=True, inline="always", fastmath=FASTMATH)
    def neighbour_ok(rows, inputs, segment, t, y, x, height, width, normal_cos):
        """Row of the neighbour at (y, x) if it is inside, covered, in t's segment and its normal
        is within the angle of t's; else -1."""
        if y < 0 or y >= height or x < 0 or x >= width:
            return -1
        r = rows[y, x]
        if r < 0 or segment[r] != segment[t]:
            return -1
        dot = np.float64(inputs[r, 3]) * np.float64(inputs[t, 3]) + np.float64(inputs[r, 4]) * np.float64(inputs[t, 4])
        dot += np.float64(inputs[r, 5]) * np.float64(inputs[t, 5])
        return r if dot >= normal_cos else -1

    @numba.njit(cache=True, inline="always", fastmath=FASTMATH)
    def spread_from(inputs, r, m0, m1, m2):
        d0 = np.float64(inputs[r, 0]) - m0
        d1 = np.float64(inputs[r, 1]) - m1
        d2 = np.float64(inputs[r, 2]) - m2
        return d0 * d0 + d1 * d1 + d2 * d2

    @numba.njit(cache=True, nogil=True, fastmath=FASTMATH)
    def refine(rows, inputs, segment, transfer, unshadowed, s, tolerance, normal_cos, position_ratio, floor, refused, first, step):
        """Level s on the pairs of image rows (a grid row of the coarser level and the row between
        it and the next) starting at first, first + step, ... (multiples of 2 s)."""
        height, width = rows.shape
        n = transfer.shape[1]
        c = 2 * s
        ratio2 = position_ratio * position_ratio
        for base in range(first, height, step):
            for y in range(base, min(base + c, height), s):
                ey = y % c == 0
                for x in range(s if ey else 0, width, c if ey else s):  # a grid row's pixels between the coarser grid's
                    t = rows[y, x]
                    if t < 0:
                        continue
                    ex = x % c == 0
                    if ey:  # on a grid row: neighbours along x
                        r0 = neighbour_ok(rows, inputs, segment, t, y, x - s, height, width, normal_cos)
                        r1 = neighbour_ok(rows, inputs, segment, t, y, x + s, height, width, normal_cos) if r0 >= 0 else -1
                        r2 = r3 = 0
                        ok = r1 >= 0
                    elif ex:  # on a grid column: along y
                        r0 = neighbour_ok(rows, inputs, segment, t, y - s, x, height, width, normal_cos)
                        r1 = neighbour_ok(rows, inputs, segment, t, y + s, x, height, width, normal_cos) if r0 >= 0 else -1
                        r2 = r3 = 0
                        ok = r1 >= 0
                    else:  # a cell centre: the four corners
                        r0 = neighbour_ok(rows, inputs, segment, t, y - s, x - s, height, width, normal_cos)
                        r1 = neighbour_ok(rows, inputs, segment, t, y - s, x + s, height, width, normal_cos) if r0 >= 0 else -1
                        r2 = neighbour_ok(rows, inputs, segment, t, y + s, x - s, height, width, normal_cos) if r1 >= 0 else -1
                        r3 = neighbour_ok(rows, inputs, segment, t, y + s, x + s, height, width, normal_cos) if r2 >= 0 else -1
                        ok = r3 >= 0
                    four = not (ey or ex)
                    if ok:
                        if four:
                            m0 = (np.float64(inputs[r0, 0]) + np.float64(inputs[r1, 0]) + np.float64(inputs[r2, 0]) + np.float64(inputs[r3, 0])) / 4
                            m1 = (np.float64(inputs[r0, 1]) + np.float64(inputs[r1, 1]) + np.float64(inputs[r2, 1]) + np.float64(inputs[r3, 1])) / 4
                            m2 = (np.float64(inputs[r0, 2]) + np.float64(inputs[r1, 2]) + np.float64(inputs[r2, 2]) + np.float64(inputs[r3, 2])) / 4
                            span = max(max(spread_from(inputs, r0, m0, m1, m2), spread_from(inputs, r1, m0, m1, m2)),
                                       max(spread_from(inputs, r2, m0, m1, m2), spread_from(inputs, r3, m0, m1, m2)))
                        else:
                            m0 = (np.float64(inputs[r0, 0]) + np.float64(inputs[r1, 0])) / 2
                            m1 = (np.float64(inputs[r0, 1]) + np.float64(inputs[r1, 1])) / 2
                            m2 = (np.float64(inputs[r0, 2]) + np.float64(inputs[r1, 2])) / 2
                            span = max(spread_from(inputs, r0, m0, m1, m2), spread_from(inputs, r1, m0, m1, m2))
                        ok = spread_from(inputs, t, m0, m1, m2) <= ratio2 * span
                    if ok:  # the mean goes in at once; a refused pixel's is overwritten by its network
                        norm2 = np.float32(0.0)
                        spread2 = np.float32(0.0)
                        nd = unshadowed.shape[1]  # residuals from the unshadowed transfer in the direct part
                        # Two loops, the direct part (residuals) and the rest, without a branch per
                        # coefficient: each vectorises across the coefficients.
                        if four:
                            for ch in range(nd):
                                v0 = transfer[r0, ch] - unshadowed[r0, ch]
                                v1 = transfer[r1, ch] - unshadowed[r1, ch]
                                v2 = transfer[r2, ch] - unshadowed[r2, ch]
                                v3 = transfer[r3, ch] - unshadowed[r3, ch]
                                mean = ((v0 + v1) + (v2 + v3)) * np.float32(0.25) + unshadowed[t, ch]
                                transfer[t, ch] = mean
                                norm2 += mean * mean
                                d = max(max(v0, v1), max(v2, v3)) - min(min(v0, v1), min(v2, v3))
                                spread2 += d * d
                            for ch in range(nd, n):
                                v0 = transfer[r0, ch]
                                v1 = transfer[r1, ch]
                                v2 = transfer[r2, ch]
                                v3 = transfer[r3, ch]
                                mean = ((v0 + v1) + (v2 + v3)) * np.float32(0.25)
                                transfer[t, ch] = mean
                                norm2 += mean * mean
                                d = max(max(v0, v1), max(v2, v3)) - min(min(v0, v1), min(v2, v3))
                                spread2 += d * d
                        else:
                            for ch in range(nd):
                                v0 = transfer[r0, ch] - unshadowed[r0, ch]
                                v1 = transfer[r1, ch] - unshadowed[r1, ch]
                                mean = (v0 + v1) * np.float32(0.5) + unshadowed[t, ch]
                                transfer[t, ch] = mean
                                norm2 += mean * mean
                                d = max(v0, v1) - min(v0, v1)
                                spread2 += d * d
                            for ch in range(nd, n):
                                v0 = transfer[r0, ch]
                                v1 = transfer[r1, ch]
                                mean = (v0 + v1) * np.float32(0.5)
                                transfer[t, ch] = mean
                                norm2 += mean * mean
                                d = max(v0, v1) - min(v0, v1)
                                spread2 += d * d
                        bound = tolerance * (np.sqrt(np.float64(norm2)) + floor)
                        ok = np.float64(spread2) <= bound * bound
                    if not ok:
                        refused[t] = True

    return prepare, gather, refine


class TransferInterpolator:
    """The fast path: numba kernels (compiled on first use, cached on disk where numba can write)
    run on bands of image rows by a pool of ``threads`` threads.

    Parameters
    ----------
    tolerance : relative transfer tolerance of an interpolation (module docstring), > 0
    threads : threads for the kernels (default: all cores)
    """

    def __init__(self, tolerance: float, threads: int | None = None):
        from concurrent.futures import ThreadPoolExecutor

        self.tolerance = float(tolerance)
        self.threads = max(1, int(threads or os.cpu_count() or 1))
        self._kernels = _kernels()
        self._coeffs = unshadowed_monomials().astype(np.float32)
        self._pool = ThreadPoolExecutor(max_workers=self.threads - 1, thread_name_prefix="interpolate") if self.threads > 1 else None
        # Two sets of frame-sized arrays used in turn: a frame's result stays intact while the next is
        # computed, and frames do not pay for fresh pages.
        self._buffers: list[dict] = [{}, {}]
        self._turn = 0

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _bands(self, kernel, step: int, *args) -> None:
        """``kernel(*args, first, stride)`` on every thread: the image rows (multiples of ``step``)
        dealt out in turn, so that each thread gets as many of the covered ones as the others."""
        n = self.threads
        if self._pool is None:
            kernel(*args, 0, step)
            return
        futures = [self._pool.submit(kernel, *args, i * step, n * step) for i in range(1, n)]
        kernel(*args, 0, n * step)  # the first band on this thread (the kernels release the GIL)
        for future in futures:
            future.result()

    def _arrays(self, height: int, width: int, n: int) -> dict:
        """This frame's set of arrays (the other set holds the previous frame's result)."""
        self._turn ^= 1
        b = self._buffers[self._turn]
        if b.get("shape") != (height, width, n):
            pixels = height * width
            b.clear()
            b.update(shape=(height, width, n), rows=np.empty((height, width), np.int32), segment_image=np.empty((height, width), np.int32),
                     counts=np.empty(height, np.int64), starts=np.zeros(height, np.int64), covered=np.empty(pixels, np.int64),
                     inputs=np.empty((pixels, 6), np.float32), segment=np.empty(pixels, np.int32),
                     transfer=np.empty((pixels, n), np.float32), inferred=np.empty(pixels, np.bool_), refused=np.empty(pixels, np.bool_),
                     unshadowed=np.empty((pixels, DIRECT), np.float32))  # fmt: skip
        return b

    def prepare(self, position, normal, b: dict | None = None):
        """:func:`_prepare` with the kernels (the same arrays; views of ``b``'s when given), and the
        unshadowed transfer of each row's normal."""
        prepare, gather = self._kernels[:2]
        height, width = position.shape[:2]
        if b is None:
            b = {"rows": np.empty((height, width), np.int32), "segment_image": np.empty((height, width), np.int32),
                 "counts": np.empty(height, np.int64), "starts": np.zeros(height, np.int64), "covered": np.empty(height * width, np.int64),
                 "inputs": np.empty((height * width, 6), np.float32), "segment": np.empty(height * width, np.int32),
                 "unshadowed": np.empty((height * width, DIRECT), np.float32)}  # fmt: skip
        rows, counts, starts = b["rows"], b["counts"], b["starts"]
        self._bands(prepare, 1, normal, b["segment_image"], counts)
        np.cumsum(counts[:-1], out=starts[1:])
        m = int(counts.sum())
        covered, inputs, segment, unshadowed = b["covered"][:m], b["inputs"][:m], b["segment"][:m], b["unshadowed"][:m]
        self._bands(gather, 1, position, normal, b["segment_image"], starts, rows, covered, inputs, segment, self._coeffs, unshadowed)
        return covered, rows, inputs, segment, unshadowed

    def run(self, position, normal, infer: Infer, n: int, timings: dict | None = None) -> InterpolatedTransfer:
        """The transfer of every covered pixel, the network run only where interpolation is unsafe.

        Parameters
        ----------
        position, normal : (H, W, >=3) float32 (views are fine), row 0 at the top; ``normal[..., 3]``
            holds the segment id, -1 on background (the G-buffer's two targets)
        infer : see :data:`Infer`
        n : coefficients per pixel
        timings : if given, gets ``pack`` and ``interpolate`` (ms; the network's own time is the caller's)

        Returns
        -------
        InterpolatedTransfer
        """
        refine = self._kernels[2]
        t0 = time.perf_counter()
        b = self._arrays(position.shape[0], position.shape[1], n)
        covered, rows, inputs, segment, unshadowed = self.prepare(position, normal, b)
        m = len(covered)
        transfer, inferred, refused = b["transfer"][:m], b["inferred"][:m], b["refused"][:m]
        inferred[:] = False  # every covered row's transfer is written below: by a network or a mean
        t1 = time.perf_counter()
        _fill(transfer, inferred, _level0_rows(rows, STRIDES[0]), inputs, segment, infer)
        spent = 0.0
        for s in STRIDES[1:]:
            t2 = time.perf_counter()
            refused[:] = False
            args = (rows, inputs, segment, transfer, unshadowed, s, self.tolerance, NORMAL_COS, POSITION_RATIO, TRANSFER_FLOOR, refused)
            self._bands(refine, 2 * s, *args)
            which = np.flatnonzero(refused)
            spent += time.perf_counter() - t2
            _fill(transfer, inferred, which, inputs, segment, infer)
        if timings is not None:
            timings["pack"] = 1e3 * (t1 - t0)
            timings["interpolate"] = 1e3 * spent
        return InterpolatedTransfer(covered, transfer, inputs, segment, inferred)


def interpolate_transfer(position, normal, tolerance: float, infer: Infer, n: int, timings: dict | None = None,
                      threads: int | None = None) -> InterpolatedTransfer:  # fmt: skip
    """:meth:`TransferInterpolator.run` once (a sampler of its own, closed after)."""
    sampler = TransferInterpolator(tolerance, threads)
    try:
        return sampler.run(position, normal, infer, n, timings)
    finally:
        sampler.close()
