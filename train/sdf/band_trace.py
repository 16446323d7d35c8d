"""Occlusion rays against an SDF by Embree on its band's shells, the field evaluated only inside.

:meth:`prt.train.sdf.SDF.sphere_trace` steps every ray through the field from its origin to the
scene's edge: about 42 network evaluations per ray on the neural bunny, most of them far from
any surface.  This tracer asks Embree where the field can matter and evaluates it only there.

The band (:mod:`prt.train.sdf.band`) gives two closed triangle shells: the *inner* one where
the field is ``-delta`` (inside the solid) and the *outer* one at ``+delta`` (enclosing the solid).
Outside the outer shell the field is above the hit threshold, so no hit can happen there; the
inner shell lies where the field is below 0, so a ray that reaches it has crossed the surface.
For each ray (the same hit rule as the sphere tracer: the field below ``eps * (1 + t)``, the
same ``t_max`` and step budget):

1. **Embree** walks the ray's crossings of the two shells, up to the first inner-shell hit: the
   stretches inside the outer shell (the *segments*; the first starts at the origin when the
   origin lies in the band, as every origin on a surface does) and the inner-shell hit, if any.
2. **Confirmation.**  An inner-shell hit is a candidate; the field at that point decides it
   (one evaluation): below 0, the ray is occluded, whatever lies before.  A candidate the field
   does not confirm (the shell is off there), a ray that starts inside the inner shell, or one with
   more crossings than :data:`MAX_CROSSINGS`: the plain sphere tracer traces it from its origin.
3. **Segments** of the remaining rays are marched by sphere tracing with certified long steps:
   from ``t`` (field ``f``) a step ``d`` is taken up to ``0.9 * 2 (f - m) / (L - k)`` (``L``: the
   band's local slope bound; ``k``: the field's slope along the ray so far, at the origin from its
   gradient; ``m``: half the hit threshold) and kept only if the two Lipschitz cones meet above
   ``m``, ``f + f(t + d) - L d >= 2 m``: the field cannot reach the surface in between, nor come
   within half the sphere tracer's tolerance of it.  A step that fails falls back to the plain
   sphere step ``(f - m) / L``.  Where the field falls towards a surface, a probe at 1.5x the
   predicted crossing that finds the field below 0 settles the hit (the sphere tracer would stop
   there, or before); at most :data:`_PROBES` per segment.  A segment ends at a hit, when its last
   point's ball reaches the segment's end, or at the step budget (reported occluded, as the sphere
   tracer does; a ray's budget is per segment here, so a grazing ray the sphere tracer gives up on
   can come out free: those are its disagreements with the plain tracer, settled as the band
   tracer has them by the plain tracer with 16x the budget).

Where it can go wrong: a feature the outer shell does not enclose (features at least about 0.006
scene units thick at the field's median slope are: the band's rule); a slope the table
underestimates (measured on the neural bunny: at most 0.86x the table).  A proxy hit the field does
not confirm is traced plainly; rays that start inside the band march from their origin.  The plain
tracer stays the reference twin: ``tests/test_band_trace.py`` traces the same rays with both.

Measured on the neural bunny (64x4), 128k rays of the precompute: 2.4 network evaluations and 2.1
Embree queries per ray against the sphere tracer's 42 evaluations, the same hits but for the rays
the sphere tracer ran out of steps on; ``docs/benchmarks/neural_sdf_tracing.md`` has the timings.
"""

from __future__ import annotations

import hashlib
import threading

import numpy as np

from .band import BAND_RULE, Band, build_band

__all__ = ["BandTracer", "TRACE_RULE", "MAX_CROSSINGS"]

TRACE_RULE = f"{BAND_RULE}+trace-v1"  # what cache keys record: the band's rule and this tracer's
MAX_CROSSINGS = 24  # shell crossings a ray may have before it is traced plainly
_ADVANCE = np.float32(1e-5)  # past a crossing before the next Embree query (never re-hits the same face)
_RELAX = np.float32(0.9)  # of the longest step the slope estimate allows
_PROBE_SLOPE = 0.05  # probe for a crossing where the field falls faster than this share of L ...
_PROBES = 3  # ... at most this many times per segment (measured on the neural bunny: 2.42 -> 2.36 evaluations per ray)
_SLOPE_EPS = 1e-3  # forward-difference step of the origins' gradients (scene units)
# A certified stretch keeps the field above this share of the hit threshold: strictly above the
# surface (0 would do for that), with room for the sphere tracer's own tolerance.  Measured on the
# neural bunny: 1.0 costs 4.1 evaluations per ray, 0.5 costs 2.4, with the same hits.
_MARGIN = np.float32(0.5)


class BandTracer:
    """Occlusion of rays against an SDF through its band (see the module docstring).

    Parameters
    ----------
    sdf : prt.train.sdf.SDF
    band : Band, optional
        Built from ``sdf`` when not given (:func:`prt.train.sdf.band.build_band`).
    eps, max_steps :
        The hit threshold at ``t = 0`` and the step budget, as :meth:`SDF.sphere_trace`'s.
    """

    def __init__(self, sdf, band: Band | None = None, *, eps: float = 1e-4, max_steps: int = 256, threads: int | None = None):
        self.sdf = sdf
        self.band = band if band is not None else build_band(sdf, threads=threads)
        self.eps = np.float32(eps)
        self.max_steps = int(max_steps)
        self.identity = f"{TRACE_RULE}:" + hashlib.sha1(sdf.glsl().encode()).hexdigest()
        self._scene, self._lock = None, threading.Lock()
        self.scene()
        self.counts = {"rays": 0, "evaluations": 0, "queries": 0, "plain": 0}  # running totals (benchmarks)

    def __getstate__(self):
        # an Embree scene cannot be pickled: it is rebuilt where the tracer lands (a cluster worker)
        return {k: v for k, v in self.__dict__.items() if k not in ("_scene", "_lock")}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._scene, self._lock = None, threading.Lock()

    def scene(self):
        """The Embree scene of both shells: geometry 0 the inner shell, 1 the outer one (built once)."""
        with self._lock:
            if self._scene is None:
                from embreex import rtcore_scene
                from embreex.mesh_construction import TriangleMesh

                scene = rtcore_scene.EmbreeScene()
                for verts, faces in (self.band.inner, self.band.outer):
                    if len(faces) == 0:  # an empty shell would shift the geometry ids: one far-away degenerate triangle
                        verts, faces = np.full((3, 3), 1e6, dtype=np.float32), np.array([[0, 1, 2]], dtype=np.int32)
                    TriangleMesh(scene, verts, faces)
                # the BVH is built at the first query: one ray now, so no worker thread waits on it
                scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
                self._scene = scene
        return self._scene

    # ----- the field -----------------------------------------------------------------

    def _field(self, points: np.ndarray) -> np.ndarray:
        self.counts["evaluations"] += len(points)
        return self.sdf.evaluate(np.asarray(points, dtype=np.float32))

    # ----- tracing -------------------------------------------------------------------

    def occluded(self, origins, dirs, t_max=None) -> np.ndarray:
        """Occlusion of rays: (N,) bool, True where the ray hits the SDF.

        Parameters
        ----------
        origins, dirs : (N, 3) array_like
            Ray origins (outside the solid, as the sphere tracer wants them) and directions
            (normalised here).
        t_max : float, optional
            Maximum ray parameter; by default the SDF's :attr:`~prt.train.sdf.SDF.crossing`.
        """
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.asarray(dirs, dtype=np.float32)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise ValueError(f"origins and dirs must both be (N, 3), got {o.shape} and {d.shape}")
        d = np.ascontiguousarray(d / np.linalg.norm(d, axis=1, keepdims=True))
        n = len(o)
        t_end = np.float32(self.sdf.crossing if t_max is None else t_max)
        self.counts["rays"] += n
        hit = np.zeros(n, dtype=bool)
        if n == 0:
            return hit
        f0, k0 = self._origin_field(o, d)
        seg_ray, seg_a, seg_b, cand_ray, cand_t, plain = self._crossings(o, d, t_end)
        if len(cand_ray):
            confirmed = self._field(o[cand_ray] + cand_t[:, None] * d[cand_ray]) < 0.0
            hit[cand_ray[confirmed]] = True
            plain[cand_ray[~confirmed]] = True
        keep = ~(hit[seg_ray] | plain[seg_ray])
        seg_ray, seg_a, seg_b = seg_ray[keep], seg_a[keep], seg_b[keep]
        if len(seg_ray):
            hit[seg_ray[self._march(o, d, seg_ray, seg_a, seg_b, f0, k0)]] = True
        todo = np.flatnonzero(plain & ~hit)
        if todo.size:
            self.counts["plain"] += int(todo.size)
            hit[todo] = self.sdf.sphere_trace(o[todo], d[todo], t_end, eps=float(self.eps), max_steps=self.max_steps)
        return hit

    def _origin_field(self, o: np.ndarray, d: np.ndarray):
        """The field (N,) at every origin and its slope (N,) along the ray, from one evaluation per
        distinct origin and three forward differences (rays of one sample share their origin)."""
        new = np.ones(len(o), dtype=bool)
        new[1:] = (o[1:] != o[:-1]).any(axis=1)
        run = np.cumsum(new) - 1
        unique = o[new]
        taps = np.concatenate([unique] + [unique + np.float32(_SLOPE_EPS) * np.eye(3, dtype=np.float32)[i] for i in range(3)])
        f = self._field(taps).reshape(4, len(unique))
        grad = ((f[1:] - f[0]) / np.float32(_SLOPE_EPS)).T  # (U, 3)
        return f[0][run], np.einsum("ij,ij->i", grad[run], d).astype(np.float32)

    def _crossings(self, o, d, t_end):
        """Embree's walk along each ray: the segments inside the outer shell, the first inner-shell hit.

        Returns
        -------
        seg_ray, seg_a, seg_b : (S,) the ray and parameter range of each segment
        cand_ray, cand_t : (C,) rays with an inner-shell hit and its parameter
        plain : (N,) bool, rays to trace with the plain sphere tracer
        """
        scene = self.scene()
        n = len(o)
        plain = np.zeros(n, dtype=bool)
        segments, candidates = [], []
        # the state of the rays still walking, compacted: index, position, direction, t, inside, segment start
        alive, here, dirs = np.arange(n), o, d
        t = np.zeros(n, dtype=np.float32)
        start = np.zeros(n, dtype=np.float32)
        inside = np.zeros(n, dtype=bool)
        for step in range(MAX_CROSSINGS):
            if alive.size == 0:
                break
            res = scene.run(here, dirs, dists=np.maximum(t_end - t, np.float32(0.0)), query="INTERSECT", output=1)
            self.counts["queries"] += int(alive.size)
            got = res["primID"] >= 0
            at = t + res["tfar"]
            outward = np.einsum("ij,ij->i", res["Ng"], dirs) > 0.0
            is_inner = got & (res["geomID"] == 0)
            exits = got & ~is_inner & outward
            entries = got & ~is_inner & ~outward
            if step == 0:  # the origin is in the band if the first crossing leaves it (or reaches the inner shell)
                inside = exits | (is_inner & ~outward)
            plain[alive[is_inner & outward]] = True  # leaving the inner shell unentered: it is off here
            # the stretch inside the outer shell that ends here (or at t_end where nothing is hit)
            closes = inside & (exits | is_inner | ~got)
            segments.append((alive[closes], start[closes], np.where(got, at, t_end)[closes]))
            inner_hit = is_inner & ~outward
            candidates.append((alive[inner_hit], at[inner_hit]))
            start = np.where(entries, at, start)
            inside = entries | (inside & ~exits)
            walk = exits | entries
            alive, dirs, t, start, inside = alive[walk], dirs[walk], at[walk] + _ADVANCE, start[walk], inside[walk]
            here = np.ascontiguousarray(o[alive] + t[:, None] * dirs)
        plain[alive] = True  # still crossing shells after MAX_CROSSINGS
        cat = lambda parts, i, dtype: np.concatenate([p[i] for p in parts]).astype(dtype)  # noqa: E731
        return (cat(segments, 0, np.int64), cat(segments, 1, np.float32), cat(segments, 2, np.float32),
                cat(candidates, 0, np.int64), cat(candidates, 1, np.float32), plain)  # fmt: skip

    def _march(self, o, d, ray, a, b, f0, k0) -> np.ndarray:
        """Certified sphere tracing of segments ``[a, b]`` of rays ``ray``: (S,) bool, True where one hits."""
        eps, one, band = self.eps, np.float32(1.0), self.band
        cell = np.float32(band.cell)
        hit = np.zeros(len(ray), dtype=bool)
        origin_seg = a == 0.0
        oo, dd = o[ray], d[ray]
        f = np.empty(len(ray), dtype=np.float32)
        f[origin_seg] = f0[ray[origin_seg]]
        rest = np.flatnonzero(~origin_seg)
        if rest.size:
            f[rest] = self._field(oo[rest] + a[rest, None] * dd[rest])
        k = np.where(origin_seg, k0[ray], np.float32(0.0)).astype(np.float32)
        t = a.copy()
        lip = band.slope_at(oo + t[:, None] * dd)
        live = np.arange(len(ray))  # the state arrays below hold the live segments only
        probes = np.zeros(len(ray), dtype=np.int32)
        steps = np.zeros(len(ray), dtype=np.int32)
        while live.size:
            # the table bounds the slope within a cell of the point: a ball reaching further uses the global bound
            lip = np.where(f > cell * lip, one, lip)
            thr = eps * (one + t)
            margin = _MARGIN * thr  # what a certified stretch keeps the field above
            stop = (f < thr) | (steps >= self.max_steps)  # a hit (or the budget spent: reported occluded)
            done = stop | (t + (f - margin) / lip >= b)
            if done.any():
                hit[live[stop]] = True
                keep = ~done
                live, oo, dd, t, f, k, b, lip, margin, probes, steps = (
                    x[keep] for x in (live, oo, dd, t, f, k, b, lip, margin, probes, steps)
                )
                if live.size == 0:
                    break
            steps += 1
            # where the field falls towards a surface: a probe past the predicted crossing
            probe = (k < -_PROBE_SLOPE * lip) & (probes < _PROBES)
            # else the longest step whose two cones would meet above the margin if the field kept its slope
            kk = np.clip(k, 0.0, np.float32(0.8) * lip)
            step = np.maximum(np.minimum(_RELAX * 2.0 * (f - margin) / (lip - kk), cell), (f - margin) / lip)
            step = np.where(probe, np.float32(1.5) * f / -np.minimum(k, np.float32(-1e-12)), step)
            t_new = t + step
            at = oo + t_new[:, None] * dd
            f_new = self._field(at)
            found = probe & (f_new < 0.0)  # a probe that finds the field below 0: the ray crosses the surface
            probes += probe
            lip_new = np.maximum(lip, band.slope_at(at))
            ok = ~probe & (f + f_new - lip_new * step >= np.float32(2.0) * margin)
            slope = (f_new - f) / step
            back = ~ok & ~found  # failed steps (and probes) fall back to the plain step from t
            if back.any():
                tb = t[back] + (f[back] - margin[back]) / lip[back]
                at = oo[back] + tb[:, None] * dd[back]
                t_new[back], f_new[back], slope[back] = tb, self._field(at), np.float32(0.0)
                lip_new[back] = np.maximum(lip[back], band.slope_at(at))
                steps[back] += 1
            f_new[found] = -one  # ends next round as a hit
            t, f, k, lip = t_new, f_new, slope.astype(np.float32), lip_new
        return hit
