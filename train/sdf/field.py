"""The SDF field of a scene: evaluation, gradients, GLSL, meshing, projection, sphere tracing.

:class:`SDF` wraps a root :class:`~prt.train.sdf.nodes.Node` with the operations the
precompute needs.  Its :meth:`SDF.sphere_trace` is the one numpy sphere tracer of the project;
the transfer's ``SDFTracer`` calls it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .glsl import GLSLWriter
from .nodes import Node, as_points, columns

__all__ = ["SDF", "FieldGrid"]

# Points per batch of finite-difference taps in SDF.gradient.
_GRADIENT_CHUNK = 1 << 17


def _ray_box(o, d, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ray parameters of the AABB [lo, hi] for (n,) component lists o, d."""
    t_in = np.full(o[0].shape, -np.inf, dtype=o[0].dtype)
    t_out = np.full(o[0].shape, np.inf, dtype=o[0].dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(3):
            inv = 1.0 / d[i]
            t1, t2 = (lo[i] - o[i]) * inv, (hi[i] - o[i]) * inv
            # fmin/fmax skip the NaN of 0 * inf (origin on a slab, direction parallel to it).
            t_in = np.fmax(t_in, np.fmin(t1, t2))
            t_out = np.fmin(t_out, np.fmax(t1, t2))
    return t_in, t_out


@dataclass(frozen=True)
class FieldGrid:
    """A field sampled on a regular grid: ``values[i, j, k]`` at ``origin + spacing * (i, j, k)``.

    Attributes
    ----------
    values : (nx, ny, nz) float32 ndarray
        Shared by every user of :meth:`SDF.grid`'s cache: read it, never write to it (it stays
        writeable because scikit-image's marching cubes refuses read-only arrays).
    origin : (3,) float64 ndarray
        Scene position of ``values[0, 0, 0]``.
    spacing : float
        Grid step (scene units), the same along every axis.
    """

    values: np.ndarray
    origin: np.ndarray
    spacing: float


def _sample_grid(sdf, resolution: int, threads: int | None) -> FieldGrid:
    """Evaluate ``sdf`` on the grid of :meth:`SDF.grid`, one x-slab per task (bounded memory)."""
    from ..executor import LocalExecutor

    lo, hi = sdf.bounds
    h = float((hi - lo).max()) / (resolution - 1)
    lo = lo - 2.0 * h  # two voxels of margin: the grid boundary is strictly outside
    counts = np.ceil((hi + 2.0 * h - lo) / h).astype(int) + 1
    axes = [lo[i] + h * np.arange(counts[i]) for i in range(3)]
    values = np.empty(tuple(counts), dtype=np.float32)
    yz = np.stack(np.meshgrid(axes[1], axes[2], indexing="ij"), axis=-1).reshape(-1, 2)
    slabs = [(i, np.column_stack([np.full(len(yz), x), yz]).astype(np.float32)) for i, x in enumerate(axes[0])]
    for (i, _), f in LocalExecutor(threads).map(_evaluate_slab, sdf, slabs):
        values[i] = f.reshape(counts[1], counts[2])
    return FieldGrid(values, lo, h)


def _evaluate_slab(sdf, slab) -> np.ndarray:
    """One task of :func:`_sample_grid`: the field at one slab's points."""
    return sdf.evaluate(slab[1])


@dataclass(frozen=True, eq=False)
class SDF:
    """A named SDF scene: a node tree plus what the precompute and the renderer need.

    Parameters
    ----------
    name : str
        Scene name (the :data:`~prt.train.sdf.library.SDF_SCENES` key of a library scene).
    root : Node
        The distance expression.
    description : str
        One line for listings.
    """

    name: str
    root: Node
    description: str = ""

    def __post_init__(self):
        if not isinstance(self.root, Node):
            raise ValueError(f"SDF {self.name!r}: root must be a Node, got {type(self.root).__name__}")

    # ----- evaluation -----------------------------------------------------------------

    def evaluate(self, points) -> np.ndarray:
        """Signed distance at points.

        Parameters
        ----------
        points : (N, 3) array_like
            Query points; float32 is evaluated in float32, anything else in float64.

        Returns
        -------
        (N,) ndarray, float32 for float32 input, else float64
            Distance bound, negative inside.
        """
        return self.root.eval_np(as_points(points))

    __call__ = evaluate

    def gradient(self, points, eps: float = 1e-4) -> np.ndarray:
        """Gradient of the distance by central differences (6 evaluations per point).

        Parameters
        ----------
        points : (N, 3) array_like
            Query points.
        eps : float
            Half the difference step.

        Returns
        -------
        (N, 3) ndarray, float32 for float32 input, else float64
            Computed in float64 either way (float32 differences would be noise).
        """
        p = as_points(points)
        offsets = np.concatenate([np.eye(3), -np.eye(3)]) * eps
        grad = np.empty(p.shape, dtype=np.float64)
        for s in range(0, len(p), _GRADIENT_CHUNK):  # bounds the 6x tap array
            chunk = p[s : s + _GRADIENT_CHUNK].astype(np.float64)
            taps = (chunk[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
            f = self.root.eval_np(taps).reshape(6, len(chunk))
            grad[s : s + len(chunk)] = (f[:3] - f[3:]).T / (2.0 * eps)
        return grad.astype(p.dtype, copy=False)

    def normals(self, points, eps: float = 1e-4) -> np.ndarray:
        """Unit outward normals: the normalised :meth:`gradient`, (N, 3) in the input's dtype."""
        g = self.gradient(points, eps)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        return g / np.maximum(norm, np.finfo(g.dtype).tiny)

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 AABB ``[min, max]`` that contains the surface and the interior (read-only)."""
        box = self.root.bounds(0.0)
        box.flags.writeable = False
        return box

    # ----- GLSL ----------------------------------------------------------------------

    def glsl(self, function_name: str = "scene_sdf") -> str:
        """Self-contained GLSL 330 source defining ``float <function_name>(vec3 p)``.

        Helper functions and constants are prefixed with ``<function_name>_``; every
        constant is written with ``repr`` so numpy and GLSL use the same float32 values.
        """
        reserved = "__" in function_name or function_name.startswith("gl_")
        if reserved or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", function_name):
            raise ValueError(f"function_name must be a GLSL identifier, got {function_name!r}")
        w = GLSLWriter(function_name)
        result = self.root.emit_glsl(w, "p")
        lines = [f"// SDF scene '{self.name}', generated by prt.train.sdf; do not edit.\n"]
        lines += list(w.helpers.values())
        body = "\n".join(w.body)
        lines.append(f"float {function_name}(vec3 p) {{\n{body}\n    return {result};\n}}\n")
        return "\n".join(lines)

    # ----- meshing and projection ----------------------------------------------------

    def grid(self, resolution: int = 128, threads: int | None = None) -> "FieldGrid":
        """The field sampled on a regular grid over :attr:`bounds` (cached per resolution).

        The grid :meth:`to_mesh` runs marching cubes on; the band tracer
        (:mod:`prt.train.sdf.band`) refines it near the surface, so a build evaluates it once.

        Parameters
        ----------
        resolution : int
            Grid samples along the longest side of the bounds (cubic voxels); two voxels of
            margin on every side keep the grid boundary strictly outside the surface.
        threads : int, optional
            Worker threads for the evaluation (default: all cores).

        Returns
        -------
        FieldGrid
        """
        if int(resolution) < 8:
            raise ValueError(f"resolution must be >= 8, got {resolution}")
        cache = self.__dict__.setdefault("_grids", {})  # frozen dataclass: its __dict__ is the cache
        grid = cache.get(int(resolution))
        if grid is None:
            grid = cache[int(resolution)] = _sample_grid(self, int(resolution), threads)
        return grid

    def to_mesh(self, resolution: int = 128):
        """Triangle mesh of the zero level set by marching cubes over :attr:`bounds`.

        Parameters
        ----------
        resolution : int
            Grid samples along the longest side of the bounds (cubic voxels).

        Returns
        -------
        trimesh.Trimesh
            Merged vertices, outward-facing consistent winding, no degenerate faces.
        """
        import trimesh
        from skimage.measure import marching_cubes

        grid = self.grid(resolution)
        h = grid.spacing
        verts, faces, _, _ = marching_cubes(grid.values, level=0.0, spacing=(h, h, h))
        mesh = trimesh.Trimesh(vertices=verts + grid.origin, faces=faces, process=True)
        mesh.update_faces(mesh.nondegenerate_faces())
        mesh.remove_unreferenced_vertices()
        # The level set is closed (the grid boundary is outside), so a negative signed
        # volume means inward winding; checking beats relying on skimage's convention.
        if mesh.volume < 0.0:
            mesh.invert()
        return mesh

    def project_to_surface(self, points, iterations: int = 8, tol: float = 1e-7) -> np.ndarray:
        """Move points onto the zero level set by Newton steps ``p -= f * g / |g|^2``.

        Parameters
        ----------
        points : (N, 3) array_like
            Points near the surface (e.g. marching-cubes samples).
        iterations : int
            Maximum Newton steps; stops early once every ``|f| <= tol``.
        tol : float
            Convergence threshold on ``|f|``.

        Returns
        -------
        (N, 3) ndarray, float32 for float32 input, else float64
            Projected points (computed in float64).  In smooth regions ``|f| < 1e-5``
            afterwards; on creases (min/max without blending) convergence may be slower.
        """
        p_in = as_points(points)
        p = p_in.astype(np.float64, copy=True)
        todo = np.arange(len(p))
        for _ in range(int(iterations)):
            f = self.root.eval_np(p[todo])
            moving = np.abs(f) > tol
            todo, f = todo[moving], f[moving]
            if todo.size == 0:
                break
            g = self.gradient(p[todo])
            g2 = np.maximum(np.einsum("ij,ij->i", g, g), 1e-12)
            p[todo] -= (f / g2)[:, None] * g
        return p.astype(p_in.dtype, copy=False)

    # ----- visibility ----------------------------------------------------------------

    def start_points(self, points, normals, offset: float, margin: float = 4e-4, most: float = 0.02) -> np.ndarray:
        """Ray origins for surface points: ``points + offset * normals``, moved further out along the
        normal where the field there is still below ``margin``.

        A fixed offset is not enough where the field grows slowly: a neural SDF divided by its
        Lipschitz bound has gradients of 0.03 to 0.4, so 2e-3 along the normal can leave the origin
        below :meth:`sphere_trace`'s hit threshold (1e-4), and every ray from it "hits" at once (a
        lit ear tip came out black).  Such origins take up to three Newton steps along the normal
        (the field's slope along it from :meth:`gradient`) to ``margin`` (4x the threshold), at
        most ``most`` further out in all.  An exact distance (slope 1) never moves.

        Returns
        -------
        (N, 3) float32
        """
        p = np.asarray(points, dtype=np.float64)
        n = np.asarray(normals, dtype=np.float64)
        origins = p + float(offset) * n
        moved = np.zeros(len(p))
        todo = np.arange(len(p))
        f = self.evaluate(origins)
        for _ in range(3):
            low = f < margin
            todo, f = todo[low], f[low]
            if todo.size == 0:
                break
            slope = np.einsum("ij,ij->i", self.gradient(origins[todo]), n[todo])
            grows = slope > 1e-3  # where the field does not grow outwards, stay
            todo, f, slope = todo[grows], f[grows], slope[grows]
            step = np.clip((margin - f) / np.maximum(slope, 1e-3), 0.0, most - moved[todo])
            trial = origins[todo] + step[:, None] * n[todo]
            f_trial = self.evaluate(trial)
            better = f_trial > f  # a step that lands nearer another surface (an occluder) is refused
            todo, f = todo[better], f_trial[better]
            origins[todo] = trial[better]
            moved[todo] += step[better]
        return origins.astype(np.float32)

    def sphere_trace(
        self,
        origins,
        dirs,
        t_max=None,
        eps: float = 1e-4,
        max_steps: int = 256,
        *,
        chunk_size: int = 1 << 18,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Occlusion test of many rays at once by batched float32 sphere tracing.

        A ray hits when the distance at ``origin + t * dir`` drops below ``eps * (1 + t)``
        and misses once ``t > t_max`` or it leaves :attr:`bounds` (nothing lies outside).
        Each step evaluates only the still-active rays (compaction).  A ray that exhausts
        ``max_steps`` is reported as a HIT: that happens to grazing rays creeping along a
        surface, where calling them occluded is the conservative choice.

        Parameters
        ----------
        origins : (N, 3) array_like
            Ray origins, outside the surface (offset surface points along the normal by
            more than ``eps``, e.g. 1e-3, or they hit immediately).
        dirs : (N, 3) array_like
            Ray directions (normalised here).
        t_max : float or (N,) array_like, optional
            Maximum ray parameter; by default :attr:`crossing`, far enough to leave the
            scene from anywhere in it (whole-scene visibility, as the transfer needs).
        eps : float
            Hit threshold at t = 0, growing linearly with t.
        max_steps : int
            Step budget per ray.
        chunk_size : int
            Rays traced together; bounds temporary memory (about 100 bytes per ray).
        out : (N,) bool ndarray, optional
            Written with the result and returned.

        Returns
        -------
        (N,) bool ndarray
            True where the ray is occluded.
        """
        o = np.asarray(origins, dtype=np.float32)
        d = np.asarray(dirs, dtype=np.float32)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise ValueError(f"origins and dirs must both be (N, 3), got {o.shape} and {d.shape}")
        n = len(o)
        if t_max is None:
            t_max = self.crossing
        t_max = np.broadcast_to(np.asarray(t_max, dtype=np.float32), (n,))
        if out is None:
            out = np.empty(n, dtype=bool)
        elif out.shape != (n,) or out.dtype != bool:
            raise ValueError(f"out must be a ({n},) bool array, got {out.shape} {out.dtype}")
        for s in range(0, n, int(chunk_size)):
            sl = slice(s, s + int(chunk_size))
            out[sl] = self._trace_chunk(o[sl], d[sl], t_max[sl], np.float32(eps), int(max_steps))
        return out

    @cached_property
    def crossing(self) -> float:
        """Ray length that crosses the whole scene: the diagonal of :attr:`bounds` plus 0.1."""
        lo, hi = np.asarray(self.bounds, dtype=np.float64)
        return float(np.linalg.norm(hi - lo)) + 0.1

    @cached_property
    def _trace_box(self) -> np.ndarray:
        """Bounds padded past the hit threshold, as float32 (2, 3)."""
        return self.root.bounds(0.01).astype(np.float32)

    def _trace_chunk(self, o, d, t_max, eps, max_steps) -> np.ndarray:
        """Trace one chunk of rays; see :meth:`sphere_trace`."""
        n = len(o)
        hit = np.zeros(n, dtype=bool)
        ox, oy, oz = columns(o)
        dx, dy, dz = columns(d)
        inv_len = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx * inv_len, dy * inv_len, dz * inv_len
        lo, hi = self._trace_box
        t_in, t_out = _ray_box((ox, oy, oz), (dx, dy, dz), lo, hi)
        t = np.maximum(t_in, np.float32(0.0))  # jump to the box: nothing to hit before it
        t_end = np.minimum(t_max, t_out)
        live = np.flatnonzero(t <= t_end)
        ox, oy, oz, dx, dy, dz, t, t_end = (a[live] for a in (ox, oy, oz, dx, dy, dz, t, t_end))
        one = np.float32(1.0)
        for _ in range(max_steps):
            if live.size == 0:
                break
            f = self.root._eval(ox + t * dx, oy + t * dy, oz + t * dz)
            close = f < eps * (one + t)
            t += f
            done = close | (t > t_end)
            hit[live[close]] = True
            if done.any():
                keep = np.flatnonzero(~done)
                live, ox, oy, oz, dx, dy, dz, t, t_end = (
                    a[keep] for a in (live, ox, oy, oz, dx, dy, dz, t, t_end)
                )
        hit[live] = True  # steps exhausted: conservatively occluded
        return hit
