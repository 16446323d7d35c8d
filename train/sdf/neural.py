"""Neural SDFs: a small MLP fitted to the signed distance of a mesh (Davies et al. 2021).

The network is the transfer network of :mod:`prt.train.networks.network` with one output and no
normal input (``Architecture(bands=1, normal_freqs=0)``), so the ONNX exporter of the
transfer networks exports it unchanged: the file is an ordinary ``prt-transfer-mlp/1`` ONNX
model whose single output is the distance.  Its ``normal`` input is ignored (its weights are
zero and it is fed 0).  Its GLSL is written loop-free by :mod:`.neural_glsl` (a sphere tracer
calls it inside its own loop, and llvmpipe caps the loop iterations of a shader invocation).

    f(p) = tanh(MLP(clip(p, -2, 2))) * out_scale          (scene units, negative inside)

Lipschitz handling: after fitting, the gradient norm of ``f`` is measured by autograd on
points filling the box and near the surface; ``out_scale`` is divided by
``L = max(1, LIPSCHITZ_MARGIN * max |grad f|)``, so the exported network is a distance
bound (|grad| <= 1 where measured) and sphere tracing it with unit steps neither tunnels
nor needs step clamping anywhere else.  The zero set is unchanged.

:class:`NeuralNode` is a :class:`~prt.train.sdf.nodes.Node` (numpy evaluation of the same
arrays, GLSL from :func:`.neural_glsl.network_glsl`), so :class:`~prt.train.sdf.SDF`
wraps it and everything the analytic SDF path does (sampling, projection, marching cubes,
the numpy sphere tracer of the ground truth, ``scene_sdf.glsl`` for the G-buffer) applies.

Signed distance of the mesh (training targets): unsigned distance to the nearest of dense
area-weighted surface samples (scipy cKDTree; coarse samples for far points, whose exact
distance matters little and whose queries are slow in a dense tree), sign by ray parity
through Embree (``trimesh.Trimesh.contains``, needs a watertight mesh).  Deterministic for
a seed.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np

from ...export.onnx_model import LEAKY_SLOPE
from .field import SDF
from .nodes import Node

__all__ = [
    "SDF_SIZES",
    "NEURAL_SDF_SUFFIX",
    "NeuralNode",
    "fit_neural_sdf",
    "load_neural_sdf",
    "parse_sdf_size",
    "mesh_signed_distance",
    "geometric_error",
]

# The two SDF sizes of the paper's Table 3 (hidden width x hidden layers).
SDF_SIZES = ((32, 4), (64, 4))
NEURAL_SDF_SUFFIX = ".sdf.onnx"
SCENE_FILL = 0.9  # the mesh is fitted into [-0.9, 0.9]^3: the zero set stays inside the box
BOX = 1.0  # samples and bounds: [-1, 1]^3 (the G-buffer's scene box)
LIPSCHITZ_MARGIN = 1.1
_CHUNK = 4096  # rows per pass of the network (measured fastest: 2048-8192)


class _SingleThreadedBlas:
    """While any network evaluation runs, BLAS runs on one thread (a process-wide setting, counted).

    These layers are small: a second BLAS thread gains little and, on a loaded machine, costs up
    to 10x in spin-waits (measured: float64 normals of 20k samples 1.9 s against 0.3 s).  Callers
    that want both cores run evaluations on two threads (:meth:`SDF.grid`, the band's refinement,
    the precompute's chunks)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._users = 0
        self._limit = None
        self._blas = None  # the BLAS libraries' controller, found once (finding them takes 0.5 ms)

    def __enter__(self):
        with self._lock:
            if self._users == 0:
                if self._blas is None:
                    from threadpoolctl import ThreadpoolController

                    self._blas = ThreadpoolController().select(user_api="blas")
                self._limit = self._blas.limit(limits=1)
            self._users += 1

    def __exit__(self, *exc):
        with self._lock:
            self._users -= 1
            if self._users == 0:
                self._limit.restore_original_limits()
                self._limit = None


_single_threaded_blas = _SingleThreadedBlas()


def parse_sdf_size(text: str) -> tuple[int, int]:
    """``"64x4"`` -> (64, 4); ValueError naming the value otherwise."""
    try:
        k, l = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise ValueError(f"--sdf-size: expected KxL such as 64x4, got {text!r}") from None
    if not (1 <= k <= 256 and 1 <= l <= 8):
        raise ValueError(f"--sdf-size: expected 1 <= K <= 256 and 1 <= L <= 8, got {text!r}")
    return k, l


class NeuralNode(Node):
    """An SDF node evaluating an exported SDF network (a ``prt-transfer-mlp/1`` ONNX file).

    Parameters
    ----------
    path : str or Path
        The ONNX file (one output, the distance).
    """

    def __init__(self, path):
        from ...export.onnx_model import read_arrays, read_metadata

        self.path = Path(path)
        self.arrays, self.arch = read_arrays(self.path)
        if int(self.arch["bands"]) != 1:
            raise ValueError(f"{self.path}: not an SDF network (it has {self.arch['bands']} SH bands)")
        meta = read_metadata(self.path)
        self.info = json.loads(meta.get("prt.sdf", "{}"))
        self.cost = 4.0 * int(self.arch["hidden"]) ** 2 * int(self.arch["layers"])
        self._cast = {}  # dtype -> the arrays in it

    def _eval(self, x, y, z):
        with _single_threaded_blas:
            return self._forward(x, y, z)

    def _forward(self, x, y, z):
        dtype = x.dtype
        a = self._arrays(dtype)
        p_all = np.stack([x, y, z], axis=1)
        out = np.empty(len(x), dtype=dtype)
        hidden = int(self.arch["hidden"])
        # Chunks of _CHUNK rows, computed in place in two buffers: the (_CHUNK, hidden) activations
        # stay in the L2 cache (3x faster than whole-batch temporaries, the same bytes).
        h = np.empty((min(_CHUNK, len(x)), hidden), dtype=dtype)
        g = np.empty_like(h)
        slope = dtype.type(LEAKY_SLOPE)
        for s in range(0, len(x), _CHUNK):
            n = min(_CHUNK, len(x) - s)
            p = np.clip((p_all[s : s + n] - a["enc_centre"]) * a["enc_inv_half"], -2.0, 2.0)
            if a["enc_pos_freq"].shape[1]:
                angle = p @ a["enc_pos_freq"]
                p = np.concatenate([p, np.sin(angle), np.cos(angle)], axis=1)
            hh, gg = h[:n], g[:n]
            # the normal input is fed 0, so its 3 features are 0: their rows of layer 0 drop out
            np.matmul(p, a["layer0_in"], out=hh)
            hh += a["layer0_bias"]
            for i in range(int(self.arch["layers"])):
                if i:
                    np.matmul(hh, a[f"layer{i}_weight"], out=gg)
                    gg += a[f"layer{i}_bias"]
                    hh, gg = gg, hh
                np.multiply(hh, slope, out=gg)
                np.maximum(hh, gg, out=hh)  # leaky relu (slope < 1)
            z_out = hh @ a["out_weight"] + a["out_bias"]
            out[s : s + n] = (np.tanh(z_out) * a["out_scale"] + a["out_offset"])[:, 0]
        return out

    def _arrays(self, dtype) -> dict:
        """The network's arrays in ``dtype`` (cached per dtype), with ``layer0_in``: the rows of layer 0
        that the position features feed."""
        arrays = self._cast.get(dtype)
        if arrays is None:  # two threads may both build it: equal arrays either way
            arrays = {k: v.astype(dtype) for k, v in self.arrays.items()}
            features = 3 + 6 * int(self.arch["pos_freqs"])
            arrays["layer0_in"] = np.ascontiguousarray(arrays["layer0_weight"][:features])
            self._cast[dtype] = arrays
        return arrays

    def emit_glsl(self, w, p):
        # Loop-free, unlike the transfer networks' generator: a sphere tracer calls this inside
        # its own loop, and llvmpipe caps the loop iterations of a whole invocation (neural_glsl).
        from .neural_glsl import network_glsl

        key = w.unique_key("net")
        name = f"{w.prefix}_{key}"
        # the generated text goes in as a value, never parsed as a template
        w.add_helper(key, "${body}", body=network_glsl(self.arrays, self.arch, name))
        return w.let("float", f"{name}({p})")

    def bounds(self, level: float = 0.0) -> np.ndarray:
        b = BOX + float(level)
        return np.array([[-b] * 3, [b] * 3], dtype=np.float64)

    def _cull_bound(self):
        return self.bounds(0.0), 2.0 * BOX


def load_neural_sdf(path) -> SDF:
    """The :class:`SDF` of an SDF network file (``*.sdf.onnx``); its name is the file name."""
    return SDF(Path(path).name, NeuralNode(path), description="neural SDF")


# ----- signed distance of a mesh ------------------------------------------------------


def mesh_signed_distance(mesh, points, *, dense: int = 400_000, coarse: int = 20_000, near: float = 0.1, seed: int = 0):
    """Signed distance (negative inside) from ``points`` (N, 3) to a watertight mesh.

    Unsigned: distance to the nearest of ``dense`` area-weighted surface samples, for
    points within ``near`` of the ``coarse`` samples; farther points use the coarse samples
    (error below their spacing, where precision matters little).  Sign: Embree ray parity.

    Returns
    -------
    (N,) float64
    """
    import trimesh
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    dense_pts, _ = trimesh.sample.sample_surface(mesh, dense, seed=seed)
    coarse_pts = dense_pts[:: max(1, dense // coarse)]
    d_coarse, _ = cKDTree(coarse_pts).query(points, workers=-1)
    d = d_coarse.copy()
    close = d_coarse < near
    if close.any():
        d_dense, _ = cKDTree(dense_pts).query(points[close], distance_upper_bound=near + 0.05, workers=-1)
        d[close] = np.minimum(d_coarse[close], d_dense)
    inside = mesh.contains(points)
    return np.where(inside, -d, d)


def _training_points(mesh, count: int, rng) -> tuple[np.ndarray, np.ndarray | None]:
    """Points on (40%), near (40%, Gaussian offsets of 0.01 and 0.05) and around (20%) the surface."""
    import trimesh

    n_surface, n_near = int(0.4 * count), int(0.4 * count)
    n_box = count - n_surface - n_near
    surface, _ = trimesh.sample.sample_surface(mesh, n_surface + n_near, seed=int(rng.integers(1 << 31)))
    sigma = np.where(np.arange(n_near) % 2 == 0, 0.01, 0.05)[:, None]
    near = surface[n_surface:] + rng.normal(size=(n_near, 3)) * sigma
    box = rng.uniform(-BOX, BOX, size=(n_box, 3))
    return surface[:n_surface], np.concatenate([near, box])


# ----- fitting ------------------------------------------------------------------------


def fit_neural_sdf(mesh, out_path, *, size=(64, 4), pos_freqs: int = 0, samples: int = 200_000, steps: int = 3000,
                   batch: int = 8192, lr: float = 2e-3, seed: int = 0, log=print) -> dict:  # fmt: skip
    """Fit an SDF network to a watertight mesh in scene units and export it as ONNX.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Inside [-SCENE_FILL, SCENE_FILL]^3 (see :func:`fit_scale`).
    out_path : path
        The ONNX file to write (``*.sdf.onnx``).
    size : (hidden, layers)
    pos_freqs : int
        Sine/cosine position frequencies (0: the plain MLP of Davies et al.).

    Returns
    -------
    dict
        Timings, the Lipschitz estimate and bound, the geometric error.
    """
    import torch

    from ...export.onnx_model import build_model, save_model
    from ..networks.network import Architecture, TransferMLP

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a small MLP: one thread is faster than two that wait on each other
    try:
        return _fit(mesh, out_path, size, pos_freqs, samples, steps, batch, lr, seed, log)
    finally:
        torch.set_num_threads(threads)


def _fit(mesh, out_path, size, pos_freqs, samples, steps, batch, lr, seed, log) -> dict:
    import torch

    from ...export.onnx_model import build_model, save_model
    from ..networks.network import Architecture, TransferMLP

    if not mesh.is_watertight:
        raise ValueError("the mesh is not watertight: the sign of its distance (ray parity) is undefined")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    on_surface, off_surface = _training_points(mesh, samples, rng)
    d_off = mesh_signed_distance(mesh, off_surface, seed=seed)
    t_distance = time.perf_counter() - t0
    log(f"neural SDF: signed distance of {len(off_surface):,} points in {t_distance:.1f} s "
        f"(+{len(on_surface):,} surface points at distance 0)")  # fmt: skip
    x = np.concatenate([on_surface, off_surface]).astype(np.float32)
    y = np.concatenate([np.zeros(len(on_surface)), d_off]).astype(np.float32)

    arch = Architecture(hidden=int(size[0]), layers=int(size[1]), pos_freqs=int(pos_freqs), normal_freqs=0, bands=1)
    scale = np.array([float(np.abs(y).max()) / 0.9], dtype=np.float32)
    bounds = np.array([[-BOX] * 3, [BOX] * 3])
    model = TransferMLP(arch, bounds, scale, np.zeros(1, dtype=np.float32))
    with torch.no_grad():  # the normal features are fed zeros; keep their weights at zero
        model.hidden[0].weight[:, 3 + 6 * arch.pos_freqs :] = 0.0
    xt = torch.from_numpy(np.concatenate([x, np.zeros_like(x)], axis=1))
    yt = torch.from_numpy(y)[:, None]
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=int(steps), pct_start=0.05)
    gen = torch.Generator().manual_seed(seed)
    t1 = time.perf_counter()
    for _ in range(int(steps)):
        idx = torch.randint(0, len(xt), (batch,), generator=gen)
        loss = torch.nn.functional.l1_loss(model(xt[idx]), yt[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        with torch.no_grad():
            model.hidden[0].weight.grad[:, 3 + 6 * arch.pos_freqs :] = 0.0
        opt.step()
        sched.step()
    t_fit = time.perf_counter() - t1

    lipschitz, bound = _lipschitz(model, np.concatenate([on_surface, off_surface]), rng)
    divide = max(1.0, LIPSCHITZ_MARGIN * lipschitz)
    arrays = model.arrays()
    arrays["out_scale"] = arrays["out_scale"] / np.float32(divide)
    info = {
        "size": f"{arch.hidden}x{arch.layers}",
        "pos_freqs": arch.pos_freqs,
        "samples": int(samples),
        "steps": int(steps),
        "seed": int(seed),
        "lipschitz_measured": lipschitz,
        "lipschitz_weight_bound": bound,
        "distance_divided_by": divide,
        "signed_distance": "nearest of dense surface samples (cKDTree); sign by Embree ray parity",
        "distance_s": round(t_distance, 2),
        "fit_s": round(t_fit, 2),
    }
    onnx_model = build_model(arrays, arch.as_dict(), name="neural_sdf")
    entry = onnx_model.metadata_props.add()
    entry.key, entry.value = "prt.sdf", json.dumps(info, sort_keys=True)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_model(onnx_model, out_path)
    log(f"neural SDF {info['size']}: fitted in {t_fit:.1f} s; max |grad| {lipschitz:.3f} (weight-norm bound "
        f"{bound:.1f}); distances divided by {divide:.3f}")  # fmt: skip
    return info


def _lipschitz(model, points: np.ndarray, rng) -> tuple[float, float]:
    """Measured max |grad f| on the given points plus a uniform grid, and the spectral-norm bound."""
    import torch

    grid = rng.uniform(-BOX, BOX, size=(100_000, 3))
    pts = np.concatenate([points[rng.permutation(len(points))[:100_000]], grid]).astype(np.float32)
    worst = 0.0
    for s in range(0, len(pts), 1 << 15):
        p = torch.from_numpy(pts[s : s + (1 << 15)]).requires_grad_(True)
        f = model(torch.cat([p, torch.zeros_like(p)], dim=1)).sum()
        (g,) = torch.autograd.grad(f, p)
        worst = max(worst, float(g.norm(dim=1).max()))
    with torch.no_grad():
        bound = float(model.out_scale.abs().max()) * float(model.inv_half.max())
        for layer in list(model.hidden) + [model.out]:
            bound *= float(torch.linalg.matrix_norm(layer.weight, ord=2))
    return worst, bound


def geometric_error(sdf: SDF, mesh, *, points: int = 50_000, resolution: int = 128, seed: int = 0) -> dict:
    """Mean |f| at mesh surface points and the Chamfer distance (mean of both directions)
    between the marching-cubes zero set of ``sdf`` and ``mesh`` (scene units).

    ``mean_abs_sdf`` is in distance units: the Lipschitz division of the exported output is
    undone (``mean_abs_bound`` is the exported value itself).
    """
    import trimesh
    from scipy.spatial import cKDTree

    on_mesh, _ = trimesh.sample.sample_surface(mesh, points, seed=seed)
    bound = float(np.abs(sdf.evaluate(on_mesh)).mean())
    divided = float(getattr(sdf.root, "info", {}).get("distance_divided_by", 1.0))
    zero_set = sdf.to_mesh(resolution=resolution)
    on_zero, _ = trimesh.sample.sample_surface(zero_set, points, seed=seed + 1)
    a, _ = cKDTree(on_zero).query(on_mesh, workers=-1)
    b, _ = cKDTree(on_mesh).query(on_zero, workers=-1)
    return {
        "mean_abs_sdf": bound * divided,
        "mean_abs_bound": bound,
        "chamfer": float(0.5 * (a.mean() + b.mean())),
        "chamfer_max": float(max(a.max(), b.max())),
    }
