"""A multiresolution feature-grid encoding of position feeding a tiny MLP (Mueller et al. 2022,
"Instant neural graphics primitives"), as an alternative segment network (issue 12, item 2a).

    x  = clip((p - centre) * inv_half, -1, 1);  u = x * 0.5 + 0.5        position in [0, 1]^3
    level l < L:  N_l = floor(N_min * b^l),  b = (N_max / N_min)^(1 / (L - 1))
        pos = u * N_l;  i0 = min(floor(pos), N_l - 1);  w = pos - i0      cell and offset
        corner c = i0 + d, d in {0, 1}^3 (d_x fastest: corner k has d = (k & 1, k >> 1 & 1, k >> 2))
        index(c) = c_x + (N_l + 1) c_y + (N_l + 1)^2 c_z                   dense: (N_l + 1)^3 <= T
                 = (c_x * 1  xor  c_y * 2654435761  xor  c_z * 805459861) mod T   hashed otherwise
        f_l = sum_k  w_k * table_l[index(c_k)],  w_k = prod_i (d_i ? w_i : 1 - w_i)    (F features)
    n  = normal / max(|normal|, 1e-8);  optional sin/cos(2^k pi n), k < normal_freqs
    h  = [f_0 .. f_{L-1}, x (if ``position``), n, sin n, cos n]
    h  = leaky_relu(W_i h + b_i), i < layers;   T = tanh(W_out h + b_out) * out_scale + out_offset

``T`` (the table size per hashed level) is a power of two, so ``mod T`` is ``& (T - 1)`` and the
hash gives the same index with 32-bit unsigned wrap-around (GLSL ``uint``) as with int64
(numpy, torch, ONNX): the low bits of a product do not depend on the high bits.

All levels' tables are stored as one ``(entries, F)`` array (``grid_table``; level ``l`` starts at
row ``grid_offset[l]``); :meth:`GridTransfer.arrays` gives it with the level constants and the
MLP weights as plain numpy, :func:`evaluate_numpy` is the reference evaluation of those arrays
(the torch forward and the ONNX graph of :mod:`prt.export.grid_onnx` are tested against it), and
:func:`fit_grid_segment` trains one segment with :func:`prt.train.networks.fit.fit_segment`'s conventions
(L1 on the scaled tanh output, Adam, warm-up + cosine schedule by steps, early stop on the
held-out samples, the same errors reported).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from ...export.onnx_model import LEAKY_SLOPE, NORMAL_EPS
from .fit import FitResult, FitSettings, Validation, _as_input, _predict, batch_loss, loss_weights, resolve_loss, seeded, shaded_error, transfer_error
from .network import layout_width, mlp_numpy, target_scaling

__all__ = [
    "GridArchitecture",
    "GridTransfer",
    "PRIMES",
    "CORNERS",
    "level_resolutions",
    "level_indices",
    "evaluate_numpy",
    "fit_grid_segment",
    "DEFAULT_GRID",
    "GRID_LIMITS",
    "parse_grid",
]

PRIMES = (1, 2654435761, 805459861)  # per axis, as in instant-ngp
CORNERS = np.array([[k & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], dtype=np.int64)  # (8, 3)
TRIG_FLOPS = 20  # a sin, cos or tanh, as train/networks/network.py counts them
TABLE_INIT = 1e-4  # tables start uniform in [-1e-4, 1e-4] (instant-ngp)


def level_resolutions(levels: int, base: int, finest: int) -> list[int]:
    """``N_l = floor(N_min * b^l)`` with ``b = (N_max / N_min)^(1 / (L - 1))`` (a hair of slack so
    that exact powers, e.g. 4 -> 8 -> 16, are not floored one below by rounding)."""
    if levels < 1 or base < 1 or finest < base:
        raise ValueError(f"need levels >= 1 and 1 <= base <= finest, got {levels}, {base}, {finest}")
    growth = math.exp((math.log(finest) - math.log(base)) / (levels - 1)) if levels > 1 else 1.0
    return [int(math.floor(base * growth**level + 1e-9)) for level in range(levels)]


@dataclass(frozen=True)
class GridArchitecture:
    """Size of one grid-encoded segment network."""

    levels: int = 8  # L
    features: int = 2  # F per level
    log2_table: int = 14  # T = 2^log2_table entries per level at most
    base_resolution: int = 4  # N_min (cells per axis)
    max_resolution: int = 128  # N_max
    hidden: int = 32
    layers: int = 2  # hidden layers
    normal_freqs: int = 0  # 0: the raw unit normal only
    position: bool = True  # also feed the normalised position x to the MLP
    bands: int = 4
    layout: str = "direct"  # as prt.train.networks.network.Architecture.layout ("direct+rgb": interreflection)

    kind = "grid"

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table

    def resolutions(self) -> list[int]:
        return level_resolutions(self.levels, self.base_resolution, self.max_resolution)

    def hashed(self) -> list[bool]:
        """Per level: True where (N + 1)^3 > T (a hashed table of T rows), else a dense one."""
        return [(n + 1) ** 3 > self.table_size for n in self.resolutions()]

    def level_sizes(self) -> list[int]:
        return [min((n + 1) ** 3, self.table_size) for n in self.resolutions()]

    def table_entries(self) -> int:
        return sum(self.level_sizes()) * self.features

    @property
    def input_dim(self) -> int:
        return self.levels * self.features + (3 if self.position else 0) + 3 + 6 * self.normal_freqs

    @property
    def outputs(self) -> int:
        return layout_width(self.layout, self.bands)

    def mlp_weight_count(self) -> int:
        k, d, o = self.hidden, self.input_dim, self.outputs
        return d * k + k + (self.layers - 1) * (k * k + k) + k * o + o

    def weight_count(self) -> int:
        """Every trained number: table entries and MLP weights."""
        return self.table_entries() + self.mlp_weight_count()

    def bytes(self, table_bytes: int = 2, mlp_bytes: int = 4) -> int:
        """Storage: tables at ``table_bytes`` per entry (2: fp16), MLP (and its output scale and
        offset, the box and the normal frequencies) at ``mlp_bytes``."""
        constants = 2 * self.outputs + 6 + 9 * self.normal_freqs
        return self.table_entries() * table_bytes + (self.mlp_weight_count() + constants) * mlp_bytes

    def flops_breakdown(self) -> dict[str, int]:
        """Arithmetic operations per fragment of the evaluation written in the module docstring
        (every add, sub, mul, div, min, max, floor, xor, and, sqrt counts 1; sin, cos, tanh 20;
        a table fetch is memory, counted apart as ``fetches``).

        - position: sub, mul, clamp (2), * 0.5, + 0.5 per axis: 18
        - per level: pos (3 mul), floor (3), min (3), w = pos - i0 (3), 1 - w (3), i1 = i0 + 1 (3);
          index: the y and z terms for both corner rows (4 mul; dense: (N+1) c_y, (N+1)^2 c_z,
          hashed: c_y P_2, c_z P_3), then per corner 2 adds (dense) or 2 xor + 1 and (hashed), and
          the level's offset into the shared table (1 add); weights: w_x w_y for 4 pairs, times
          w_z for 8 corners (12 mul); interpolation: 8 mul + 7 add per feature
        - normal: 3 mul + 2 add + sqrt + max + 3 div = 10; frequencies: 1 mul per argument
          (3 per frequency) and a sin and a cos of each
        - MLP: 2 in out per linear layer (multiply-adds with the bias), leaky ReLU 2 per unit
          (mul, max), tanh, * scale, + offset per output
        """
        per_level = []
        for hashed in self.hashed():
            index = 4 + 8 * (3 if hashed else 2) + 8
            per_level.append(18 + index + 12 + 15 * self.features)
        k, d, o = self.hidden, self.input_dim, self.outputs
        mlp = 2 * d * k + 2 * (self.layers - 1) * k * k + 2 * k * o + 2 * self.layers * k + (TRIG_FLOPS + 2) * o
        normal = 10 + 3 * self.normal_freqs + 6 * self.normal_freqs * TRIG_FLOPS
        return {"position": 18, "grid": sum(per_level), "normal": normal, "mlp": mlp, "fetches": 8 * self.levels}

    def flops_per_fragment(self) -> int:
        b = self.flops_breakdown()
        return b["position"] + b["grid"] + b["normal"] + b["mlp"]

    def as_dict(self) -> dict:
        """Fields (``layout`` only when not "direct"), ``kind`` "grid", ``input_dim``, the levels'
        resolutions and whether each is hashed (fit-cache keys and training records)."""
        out = {**asdict(self), "kind": self.kind, "input_dim": self.input_dim, "resolutions": self.resolutions(), "hashed": self.hashed()}
        if self.layout == "direct":
            del out["layout"]
        else:
            out["outputs"] = self.outputs
        return out

    def grid_label(self) -> str:
        """The grid alone, as ``--grid`` spells it: ``L6-F2-T12-N4-32``."""
        return f"L{self.levels}-F{self.features}-T{self.log2_table}-N{self.base_resolution}-{self.max_resolution}"

    def label(self) -> str:
        n = f"-nf{self.normal_freqs}" if self.normal_freqs else ""
        p = "" if self.position else "-nopos"
        lay = "" if self.layout == "direct" else f"-{self.layout}"
        return f"grid-{self.grid_label()}-k{self.hidden}-l{self.layers}{n}{p}{lay}"


# The grid of the measured Pareto front (docs/benchmarks/grid_encoding.md): 6 levels, 2 features,
# T = 2^12, resolutions 4 -> 32; with a k = 64, l = 2 MLP it is 13.7k FLOPs per fragment.
DEFAULT_GRID = "L6-F2-T12-N4-32"


@dataclass(frozen=True)
class GridLimits:
    """What ``--grid`` accepts (the GLSL texture holds F <= 4 features in a texel; the biggest
    tables, 16 levels of 2^20 rows, fit a 1024 x 16384 texture)."""

    levels: int = 16
    features: int = 4
    log2_table: tuple[int, int] = (4, 20)
    resolution: int = 4096


GRID_LIMITS = GridLimits()
_GRID_RE = r"L(\d{1,3})-F(\d{1,2})-T(\d{1,2})-N(\d{1,5})-(\d{1,5})"


def parse_grid(text) -> dict:
    """``"L6-F2-T12-N4-32"`` -> ``{levels, features, log2_table, base_resolution, max_resolution}``:
    L levels of F features, at most 2^T rows per level, N_min -> N_max cells per axis.  Raises
    ValueError with a one-line message on anything else."""
    import re

    if not isinstance(text, str) or not text.isprintable() or len(text) > 40:
        raise ValueError(f"expected L<levels>-F<features>-T<log2 table>-N<min>-<max> such as {DEFAULT_GRID}, got {str(text)[:40]!r}")
    m = re.fullmatch(_GRID_RE, text.strip(), flags=re.IGNORECASE)
    if m is None:
        raise ValueError(f"expected L<levels>-F<features>-T<log2 table>-N<min>-<max> such as {DEFAULT_GRID}, got {text!r}")
    levels, features, log2, base, finest = (int(g) for g in m.groups())
    lim = GRID_LIMITS
    if not 1 <= levels <= lim.levels:
        raise ValueError(f"levels L: expected 1 .. {lim.levels}, got {levels}")
    if not 1 <= features <= lim.features:
        raise ValueError(f"features F: expected 1 .. {lim.features} (a texel holds 4), got {features}")
    if not lim.log2_table[0] <= log2 <= lim.log2_table[1]:
        raise ValueError(f"table T: expected log2 of the rows per level, {lim.log2_table[0]} .. {lim.log2_table[1]}, got {log2}")
    if not 1 <= base <= finest <= lim.resolution:
        raise ValueError(f"resolutions N<min>-<max>: expected 1 <= min <= max <= {lim.resolution}, got {base} and {finest}")
    if levels == 1 and base != finest:
        raise ValueError(f"one level has one resolution: expected N{base}-{base}, got N{base}-{finest}")
    return {"levels": levels, "features": features, "log2_table": log2, "base_resolution": base, "max_resolution": finest}


def _normal_freq_matrix(freqs: int) -> np.ndarray:
    """(3, 3 freqs): column 3 k + i holds 2^k pi on row i (as train/networks/network.py's)."""
    b = np.zeros((3, 3 * freqs), dtype=np.float32)
    for k in range(freqs):
        for i in range(3):
            b[i, 3 * k + i] = (2.0**k) * math.pi
    return b


def level_indices(corners: np.ndarray, resolution: int, hashed: bool, table_size: int) -> np.ndarray:
    """Row of each integer corner ``(..., 3)`` in one level's table (int64, before the level offset)."""
    c = np.asarray(corners, dtype=np.int64)
    if hashed:
        return (c[..., 0] * PRIMES[0] ^ c[..., 1] * PRIMES[1] ^ c[..., 2] * PRIMES[2]) & (table_size - 1)
    s = resolution + 1
    return c[..., 0] + s * c[..., 1] + s * s * c[..., 2]


def _level_constants(arch: GridArchitecture) -> dict[str, np.ndarray]:
    sizes = arch.level_sizes()
    return {
        "grid_resolution": np.array(arch.resolutions(), dtype=np.int64),
        "grid_hashed": np.array(arch.hashed(), dtype=np.int64),
        "grid_size": np.array(sizes, dtype=np.int64),
        "grid_offset": np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64),
        "grid_table_size": np.array(arch.table_size, dtype=np.int64),
        "mlp_position": np.array(int(arch.position), dtype=np.int64),
    }


def evaluate_numpy(arrays: dict[str, np.ndarray], points: np.ndarray, normals: np.ndarray, *, features_only: bool = False) -> np.ndarray:
    """The reference evaluation of :meth:`GridTransfer.arrays` (plain numpy, float32 arithmetic
    as the graph's, int64 indices): transfer (N, bands^2), or the grid features (N, L F) alone."""
    p = np.asarray(points, dtype=np.float32)
    x = np.clip((p - arrays["enc_centre"]) * arrays["enc_inv_half"], np.float32(-1), np.float32(1))
    u = x * np.float32(0.5) + np.float32(0.5)
    table = np.asarray(arrays["grid_table"], dtype=np.float32)
    size = int(arrays["grid_table_size"])
    feats = []
    for res, hashed, offset in zip(arrays["grid_resolution"], arrays["grid_hashed"], arrays["grid_offset"]):
        pos = u * np.float32(res)
        i0 = np.minimum(np.floor(pos), np.float32(res - 1))
        w = pos - i0
        corners = i0.astype(np.int64)[:, None, :] + CORNERS[None]  # (N, 8, 3)
        rows = level_indices(corners, int(res), bool(hashed), size) + int(offset)
        wk = np.where(CORNERS[None].astype(bool), w[:, None, :], np.float32(1) - w[:, None, :])  # (N, 8, 3)
        weight = wk[..., 0] * wk[..., 1] * wk[..., 2]
        feats.append((table[rows] * weight[..., None]).sum(axis=1, dtype=np.float32))
    grid = np.concatenate(feats, axis=1).astype(np.float32)
    if features_only:
        return grid
    n = np.asarray(normals, dtype=np.float32)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.float32(NORMAL_EPS))
    parts = [grid] + ([x] if int(arrays["mlp_position"]) else []) + [n]
    freq = arrays.get("enc_normal_freq")
    if freq is not None and freq.shape[1] > 0:
        a = n @ freq
        parts += [np.sin(a), np.cos(a)]
    return mlp_numpy(arrays, np.concatenate(parts, axis=1))


class _Interpolate(torch.autograd.Function):
    """``sum_k w_k table[rows_k]`` over each group of 8 rows; the table's gradient by ``index_add_``
    (a plain scatter: several times faster on the CPU than indexing's or embedding_bag's sort)."""

    @staticmethod
    def forward(ctx, table, rows, weight):  # rows (M 8,), weight (M, 8) -> (M, F)
        ctx.save_for_backward(rows, weight)
        ctx.table_shape = table.shape
        return (table.index_select(0, rows).view(-1, 8, table.shape[1]) * weight[..., None]).sum(1)

    @staticmethod
    def backward(ctx, grad):
        rows, weight = ctx.saved_tensors
        contrib = (weight[..., None] * grad[:, None, :]).reshape(-1, grad.shape[1])
        return torch.zeros(ctx.table_shape, dtype=grad.dtype).index_add_(0, rows, contrib), None, None


class GridTransfer(nn.Module):
    """One segment's grid-encoded network; ``forward(x)`` takes ``x`` (N, 6) = [position, normal]."""

    def __init__(self, arch: GridArchitecture, bounds: np.ndarray, out_scale: np.ndarray, out_offset: np.ndarray):
        super().__init__()
        self.arch = arch
        bounds = np.asarray(bounds, dtype=np.float64)
        centre = (bounds[0] + bounds[1]) / 2
        half = np.maximum((bounds[1] - bounds[0]) / 2, 1e-3)
        self.register_buffer("centre", torch.tensor(centre, dtype=torch.float32))
        self.register_buffer("inv_half", torch.tensor(1.0 / half, dtype=torch.float32))
        self.register_buffer("normal_freq", torch.from_numpy(_normal_freq_matrix(arch.normal_freqs)))
        self.register_buffer("out_scale", torch.tensor(out_scale, dtype=torch.float32))
        self.register_buffer("out_offset", torch.tensor(out_offset, dtype=torch.float32))
        consts = _level_constants(arch)
        self._consts = consts
        self.register_buffer("res", torch.tensor(consts["grid_resolution"], dtype=torch.float32).view(1, -1, 1))
        self.register_buffer("offsets", torch.from_numpy(consts["grid_offset"]).view(1, -1, 1))
        strides = [[1, n + 1, (n + 1) ** 2] for n in arch.resolutions()]
        self.register_buffer("strides", torch.tensor(strides, dtype=torch.int64).view(1, -1, 3))
        dense = sum(1 for h in arch.hashed() if not h)
        if any(arch.hashed()[:dense]) or not all(arch.hashed()[dense:]):
            raise ValueError("dense levels must come before hashed ones (resolutions grow)")
        self.dense_levels, self.hashed_levels = slice(0, dense), slice(dense, arch.levels)
        self.register_buffer("primes", torch.tensor(PRIMES, dtype=torch.int64))
        self.table = nn.Parameter(torch.empty(sum(arch.level_sizes()), arch.features).uniform_(-TABLE_INIT, TABLE_INIT))
        sizes = [arch.input_dim] + [arch.hidden] * arch.layers
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.out = nn.Linear(arch.hidden, arch.outputs)
        for layer in self.hidden:
            nn.init.kaiming_uniform_(layer.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
            nn.init.zeros_(layer.bias)
        nn.init.xavier_uniform_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def unit_position(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.clamp((p - self.centre) * self.inv_half, -1.0, 1.0)
        return x, x * 0.5 + 0.5

    def grid_rows(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Table rows (N, L, 8) and trilinear weights (N, L, 8) of unit positions ``u`` (N, 3);
        corner k = 4 d_z + 2 d_y + d_x as :data:`CORNERS`."""
        pos = u[:, None, :] * self.res  # (N, L, 3)
        i0f = torch.minimum(torch.floor(pos), self.res - 1)
        w = pos - i0f
        i0 = i0f.long()
        ends = torch.stack([i0, i0 + 1], dim=-1)  # (N, L, 3, 2): per axis, the two corner rows
        rows = []
        for part, hashed in ((self.dense_levels, False), (self.hashed_levels, True)):
            if part.stop <= part.start:
                continue
            e = ends[:, part]
            if hashed:
                t = e * self.primes.view(1, 1, 3, 1)
                r = t[:, :, 2, :, None, None] ^ t[:, :, 1, None, :, None] ^ t[:, :, 0, None, None, :]
                r = torch.bitwise_and(r, self.arch.table_size - 1)
            else:
                t = e * self.strides[:, part].view(1, -1, 3, 1)
                r = t[:, :, 2, :, None, None] + t[:, :, 1, None, :, None] + t[:, :, 0, None, None, :]
            rows.append(r.reshape(len(u), -1, 8))
        rows = torch.cat(rows, dim=1) + self.offsets
        wk = torch.stack([1.0 - w, w], dim=-1)  # (N, L, 3, 2)
        weight = (wk[:, :, 0, None, None, :] * wk[:, :, 1, None, :, None]) * wk[:, :, 2, :, None, None]
        return rows, weight.reshape(len(u), -1, 8)

    def grid_features(self, u: torch.Tensor) -> torch.Tensor:
        rows, weight = self.grid_rows(u)
        return _Interpolate.apply(self.table, rows.reshape(-1), weight.reshape(-1, 8)).reshape(len(u), -1)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        p, n = x[:, :3], x[:, 3:6]
        xn, u = self.unit_position(p)
        n = n / torch.clamp(torch.linalg.vector_norm(n, dim=1, keepdim=True), min=NORMAL_EPS)
        parts = [self.grid_features(u)] + ([xn] if self.arch.position else []) + [n]
        if self.arch.normal_freqs:
            a = n @ self.normal_freq
            parts += [torch.sin(a), torch.cos(a)]
        return torch.cat(parts, dim=1)

    def trunk(self, features: torch.Tensor) -> torch.Tensor:
        h = features
        for layer in self.hidden:
            h = nn.functional.leaky_relu(layer(h), LEAKY_SLOPE)
        return self.out(h)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.trunk(self.encode(x))) * self.out_scale + self.out_offset

    def arrays(self) -> dict[str, np.ndarray]:
        """Every constant as numpy (float32, the level constants int64), named for
        :func:`evaluate_numpy` and :mod:`prt.export.grid_onnx`."""
        out = {
            "enc_centre": self.centre,
            "enc_inv_half": self.inv_half,
            "enc_normal_freq": self.normal_freq,
            "grid_table": self.table,
            "out_scale": self.out_scale,
            "out_offset": self.out_offset,
            "out_weight": self.out.weight.T,
            "out_bias": self.out.bias,
        }
        for i, layer in enumerate(self.hidden):
            out[f"layer{i}_weight"] = layer.weight.T
            out[f"layer{i}_bias"] = layer.bias
        arrays = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in out.items()}
        return {**arrays, **{k: v.copy() for k, v in self._consts.items()}}


def fit_grid_segment(
    points: np.ndarray,
    normals: np.ndarray,
    transfer: np.ndarray,
    val_points: np.ndarray,
    val_normals: np.ndarray,
    val_transfer: np.ndarray,
    arch: GridArchitecture,
    bounds: np.ndarray,
    settings: FitSettings | None = None,
    *,
    lights: dict[str, np.ndarray] | None = None,
    table_lr_scale: float = 1.0,
    progress=None,
) -> FitResult:
    """:func:`prt.train.networks.fit.fit_segment` for a :class:`GridTransfer`: the same loss, target
    scaling, plan (``settings.plan``), schedule, early stop and errors; the tables train with
    ``settings.lr * table_lr_scale`` (Adam, eps 1e-15 as instant-ngp), the MLP with ``settings.lr``.
    bf16 and ``max_seconds`` are not supported (ignored)."""
    settings = settings or FitSettings()
    if settings.loss == "auto":  # as fit_segment
        settings = dataclasses.replace(settings, loss=resolve_loss("auto", transfer, arch.bands))
    for name, a in (("points", points), ("normals", normals), ("transfer", transfer)):
        if not np.isfinite(a).all():
            raise ValueError(f"training {name} contain NaN or Inf")
    if len(points) == 0 or len(val_points) == 0:
        raise ValueError("a segment needs at least one training and one validation sample")
    if np.shape(transfer)[1] != arch.outputs:
        raise ValueError(f"transfer has {np.shape(transfer)[1]} columns, the network {arch.outputs} outputs")
    n_coeffs = arch.bands * arch.bands  # per channel; the "direct+rgb" layout outputs 4 sets
    gen = torch.Generator().manual_seed(settings.seed)
    scale, offset = target_scaling(transfer)
    model = seeded(settings.seed, lambda: GridTransfer(arch, bounds, scale, offset))
    x = _as_input(points, normals)
    y = torch.from_numpy(np.ascontiguousarray(transfer, dtype=np.float32))
    xv = _as_input(val_points, val_normals)
    yv = np.asarray(val_transfer, dtype=np.float32)
    y_scaled = (y - torch.from_numpy(offset)) * torch.from_numpy(1.0 / scale)
    scale_t = torch.from_numpy(scale)
    weights = loss_weights(transfer, n_coeffs, settings.loss, settings.loss_floor)  # settings.loss, as fit_segment
    w = None if weights is None else torch.from_numpy(weights)[:, None]
    val_weights = loss_weights(yv, n_coeffs, settings.loss, settings.loss_floor)
    n = len(x)
    batch, total_steps, eval_every, warmup = settings.plan(n)
    mlp_params = [p for name, p in model.named_parameters() if name != "table"]
    opt = torch.optim.Adam(
        [{"params": [model.table], "lr_scale": table_lr_scale, "eps": 1e-15}, {"params": mlp_params, "lr_scale": 1.0}],
        lr=settings.lr,
    )
    t0 = time.perf_counter()
    check = Validation(xv, yv, n_coeffs, val_weights, settings, progress)
    step = 0
    perm, cursor, total, counted = torch.randperm(n, generator=gen), 0, 0.0, 0
    model.train()
    while step < total_steps:
        if cursor >= n:
            perm, cursor = torch.randperm(n, generator=gen), 0
        idx = perm[cursor : cursor + batch]
        cursor += batch
        rate = min(1.0, (step + 1) / warmup) * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(step / total_steps, 1.0))))
        for group in opt.param_groups:
            group["lr"] = settings.lr * rate * group["lr_scale"]
        out = torch.tanh(model.trunk(model.encode(x[idx])))
        loss = batch_loss(out, y_scaled[idx], scale_t, None if w is None else w[idx], settings.loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        total += loss.detach().item() * len(idx)
        counted += len(idx)
        if step % eval_every and step < total_steps:
            continue
        stop = check(model, step, total_steps, total / counted)
        total, counted = 0.0, 0
        if stop:
            break
    model.load_state_dict(check.best[1])
    model.eval()
    pred = _predict(model, xv)
    return FitResult(
        model=model,
        arch=arch,
        val_mae=transfer_error(pred, yv, n_coeffs),
        shaded=shaded_error(pred, yv, lights or {}, n_coeffs),
        epochs=check.evaluation,
        seconds=time.perf_counter() - t0,
        history=check.history,
        steps=step,
    )
