"""The transfer network ``sigma(position, normal) -> T`` (Dhawal, KT, Narayanan 2022).

    x  = clip((p - centre) * inv_half_extent, -2, 2)     position in the segment's box, ~[-1, 1]
    n  = normal / max(|normal|, 1e-8)
    ax = x @ B_p,  an = n @ B_n                           B: block-diagonal 2^k * pi, k < F
    f  = [x, sin(ax), cos(ax), n, sin(an), cos(an)]       (6 + 6 F_p + 6 F_n features)
    h  = leaky_relu(W_0 f + b_0); h = leaky_relu(W_i h + b_i), i < layers
    T  = tanh(W_out h + b_out) * out_scale + out_offset   (bands^2 coefficients)

A *residual* network (``Architecture.residual``, ``prt-train --residual``) learns the direct
transfer's residual from the unshadowed transfer of its normal, ``U(n) = c0 + q(n) @ W_u``
(:func:`prt.runtime.sh.unshadowed_quadratic`; ``q`` the quadratic terms of ``n``); the graph adds
it back (``c0`` folded into ``out_offset``, ``W_u`` the constant ``out_normal_quad``):

    T  = tanh(W_out h + b_out) * out_scale + out_offset + q(n) @ out_normal_quad

Where little is occluded the residual is small and smooth, and the network spends its capacity
on the shadows instead of the cosine lobe (``docs/benchmarks/residual_fit.md``).

With interreflection (``layout = "direct+rgb"``, ``prt-train --bounces N``) the output is
``4 bands^2`` wide: the direct transfer, then the indirect transfer of the R, G and B channels
(``bands^2`` each): ``[T_direct, T_ind_R, T_ind_G, T_ind_B]``.

The targets are mapped into [-0.9, 0.9] by ``out_scale``/``out_offset`` (stored in the model),
so tanh never has to saturate to reach a real transfer value.  Clipping the normalised
position keeps the output finite and bounded far outside the segment's box.

:meth:`TransferMLP.arrays` gives every parameter as numpy, named as the ONNX initialisers;
the exporter (:mod:`prt.export.onnx_model`) builds the graph from those arrays alone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from ...export.onnx_model import LEAKY_SLOPE, NORMAL_EPS, POSITION_CLIP
from ...runtime.deformation import code_features, code_frequencies
from ...runtime.sh import unshadowed_quadratic

__all__ = ["Architecture", "TransferMLP", "evaluate_numpy", "mlp_numpy", "frequency_matrix", "target_scaling", "TARGET_RANGE", "LAYOUTS", "layout_width",
           "residual_terms", "normal_quadratic"]

TARGET_RANGE = 0.9  # scaled targets live in [-0.9, 0.9], where tanh' >= 0.19
# Output layouts: "direct" (bands^2, the paper's), "direct+rgb" (direct + indirect R, G, B:
# 4 bands^2, interreflection) and "rgb" (three total transfers, 3 bands^2: measured, not built).
LAYOUTS = {"direct": 1, "direct+rgb": 4, "rgb": 3}


def layout_width(layout: str, bands: int) -> int:
    """Outputs of a network of ``layout`` at ``bands`` SH bands."""
    return LAYOUTS[layout] * bands * bands


@dataclass(frozen=True)
class Architecture:
    """Size of one segment network."""

    hidden: int = 64
    layers: int = 4
    pos_freqs: int = 6
    normal_freqs: int = 2
    bands: int = 4
    layout: str = "direct"  # see LAYOUTS
    code_dim: int = 0  # deformable scenes: the shape code's dimensions (prt.runtime.deformation)
    code_freqs: int = 0  # sin/cos frequencies of each code component
    residual: bool = False  # learns T - U(n), the graph adds U back (module docstring); up to 4 bands

    @property
    def input_dim(self) -> int:
        """Features a fragment computes (the shape code's are one vector per frame, not counted)."""
        return 6 + 6 * self.pos_freqs + 6 * self.normal_freqs

    @property
    def code_features(self) -> int:
        """Features of the shape code ``[theta, sin, cos]``: rows of the first layer fed once per frame."""
        return self.code_dim * (1 + 2 * self.code_freqs)

    @property
    def outputs(self) -> int:
        return layout_width(self.layout, self.bands)

    def flops_per_fragment(self) -> int:
        """Multiply-adds count 2; encoding: 3 per sin/cos argument and ~20 per sin/cos.  The shape
        code's rows are folded into the first layer's bias once per frame: not per fragment."""
        k, d, o = self.hidden, self.input_dim, self.outputs
        mlp = 2 * (d * k + (self.layers - 1) * k * k + k * o) + self.layers * k + 2 * o
        n_trig = 6 * (self.pos_freqs + self.normal_freqs)
        encoding = 9 + 3 * n_trig + 20 * n_trig
        quad = 6 + 2 * 9 * self.bands * self.bands if self.residual else 0  # q(n), then q @ W_u on the direct part
        return int(mlp + encoding + 20 * o + quad)  # tanh of each output

    def weight_count(self) -> int:
        k, d, o = self.hidden, self.input_dim + self.code_features, self.outputs
        return d * k + k + (self.layers - 1) * (k * k + k) + k * o + o + (9 * o if self.residual else 0)  # out_normal_quad: stored, not learnt

    def as_dict(self) -> dict:
        """Fields and ``input_dim``; ``layout`` and ``outputs`` only when not "direct" (so the
        records and files of a direct-only build are what they were before layouts existed)."""
        out = {**asdict(self), "input_dim": self.input_dim}
        if self.layout == "direct":
            del out["layout"]
        else:
            out["outputs"] = self.outputs
        if not self.code_dim:  # a static network's record is what it was before shape codes
            del out["code_dim"], out["code_freqs"]
        if not self.residual:  # nor a plain one's before residual networks
            del out["residual"]
        return out

    def label(self) -> str:
        code = f"-c{self.code_dim}f{self.code_freqs}" if self.code_dim else ""
        return (f"k{self.hidden}-l{self.layers}-f{self.pos_freqs}" + ("" if self.layout == "direct" else f"-{self.layout}") + code
                + ("-res" if self.residual else ""))  # fmt: skip


def residual_terms(arch: Architecture) -> tuple[np.ndarray, np.ndarray]:
    """``(c0, W_u)`` of a residual network's outputs: (outputs,) and (9, outputs) float32, the
    unshadowed transfer's in the direct part (the first bands^2 outputs) and 0 in the indirect."""
    if arch.bands > 4:
        raise ValueError(f"a residual network needs at most 4 SH bands (the unshadowed transfer is then a quadratic of the normal), not {arch.bands}")
    c0, w = unshadowed_quadratic(arch.bands)
    nd = arch.bands * arch.bands
    c0_out = np.zeros(arch.outputs, np.float32)
    w_out = np.zeros((9, arch.outputs), np.float32)
    c0_out[:nd], w_out[:, :nd] = c0, w
    return c0_out, w_out


def normal_quadratic(n):
    """The quadratic terms ``q(n)`` (N, 9) of unit normals ``n`` (N, 3), torch or numpy alike:
    ``[x, y, z, xx, yy, zz, xy, yz, zx]`` (:data:`prt.runtime.sh.QUADRATIC_TERMS`)."""
    rolled = n[:, [1, 2, 0]]
    parts = [n, n * n, n * rolled]
    return torch.cat(parts, dim=1) if isinstance(n, torch.Tensor) else np.concatenate(parts, axis=1)


def frequency_matrix(freqs: int) -> np.ndarray:
    """(3, 3 * freqs) float32: column ``3 k + i`` holds ``2^k pi`` on row ``i``."""
    b = np.zeros((3, 3 * freqs), dtype=np.float32)
    for k in range(freqs):
        for i in range(3):
            b[i, 3 * k + i] = (2.0**k) * math.pi
    return b


class TransferMLP(nn.Module):
    """One segment's network.  ``forward(x)`` takes ``x`` (N, 6) = [position, normal], or with a
    shape code (``arch.code_dim`` = d > 0) ``x`` (N, 6 + d) = [rest position, deformed normal, theta]."""

    def __init__(self, arch: Architecture, bounds: np.ndarray, out_scale: np.ndarray, out_offset: np.ndarray):
        """``out_offset``: the whole output's (a residual network's includes ``c0`` of :func:`residual_terms`)."""
        super().__init__()
        self.arch = arch
        bounds = np.asarray(bounds, dtype=np.float64)
        centre = (bounds[0] + bounds[1]) / 2
        half = np.maximum((bounds[1] - bounds[0]) / 2, 1e-3)  # a flat segment still gets a box
        self.register_buffer("centre", torch.tensor(centre, dtype=torch.float32))
        self.register_buffer("inv_half", torch.tensor(1.0 / half, dtype=torch.float32))
        self.register_buffer("pos_freq", torch.from_numpy(frequency_matrix(arch.pos_freqs)))
        self.register_buffer("normal_freq", torch.from_numpy(frequency_matrix(arch.normal_freqs)))
        self.register_buffer("out_scale", torch.tensor(out_scale, dtype=torch.float32))
        self.register_buffer("out_offset", torch.tensor(out_offset, dtype=torch.float32))
        if arch.residual:
            self.register_buffer("out_normal_quad", torch.from_numpy(residual_terms(arch)[1]))
        if arch.code_dim and arch.layers < 1:
            raise ValueError("a shape-conditioned network needs at least one hidden layer (the code enters its bias)")
        if arch.code_dim:
            self.register_buffer("code_freq", torch.from_numpy(code_frequencies(arch.code_dim, arch.code_freqs)))
        sizes = [arch.input_dim + arch.code_features] + [arch.hidden] * arch.layers
        self.hidden = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.out = nn.Linear(arch.hidden, arch.outputs)
        for layer in self.hidden:  # He init suits leaky-relu
            nn.init.kaiming_uniform_(layer.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
            nn.init.zeros_(layer.bias)
        nn.init.xavier_uniform_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        p, n = x[:, :3], x[:, 3:6]
        p = torch.clamp((p - self.centre) * self.inv_half, -POSITION_CLIP, POSITION_CLIP)
        n = n / torch.clamp(torch.linalg.vector_norm(n, dim=1, keepdim=True), min=NORMAL_EPS)
        ap = p @ self.pos_freq
        an = n @ self.normal_freq
        features = [p, torch.sin(ap), torch.cos(ap), n, torch.sin(an), torch.cos(an)]
        if self.arch.code_dim:  # [theta, sin, cos] after the fragment's features (code_features' order)
            theta = x[:, 6 : 6 + self.arch.code_dim]
            ac = theta @ self.code_freq
            features += [theta, torch.sin(ac), torch.cos(ac)]
        return torch.cat(features, dim=1)

    def trunk(self, features: torch.Tensor) -> torch.Tensor:
        """The MLP on encoded features, before tanh (bf16 autocast may run this part)."""
        h = features
        for layer in self.hidden:
            h = nn.functional.leaky_relu(layer(h), LEAKY_SLOPE)
        return self.out(h)

    def preactivation(self, x: torch.Tensor) -> torch.Tensor:
        """Network output before tanh."""
        return self.trunk(self.encode(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.tanh(self.preactivation(x)) * self.out_scale + self.out_offset
        if self.arch.residual:
            out = out + self.unshadowed_part(x)
        return out

    def unshadowed_part(self, x: torch.Tensor) -> torch.Tensor:
        """``q(n) @ out_normal_quad``: what a residual network adds to its scaled tanh output."""
        n = x[:, 3:6]
        n = n / torch.clamp(torch.linalg.vector_norm(n, dim=1, keepdim=True), min=NORMAL_EPS)
        return normal_quadratic(n) @ self.out_normal_quad

    def arrays(self) -> dict[str, np.ndarray]:
        """Every constant of the graph as float32 numpy, keyed by its ONNX initialiser name."""
        out = {
            "enc_centre": self.centre,
            "enc_inv_half": self.inv_half,
            "enc_pos_freq": self.pos_freq,
            "enc_normal_freq": self.normal_freq,
            "out_scale": self.out_scale,
            "out_offset": self.out_offset,
            "out_weight": self.out.weight.T,
            "out_bias": self.out.bias,
        }
        if self.arch.residual:
            out["out_normal_quad"] = self.out_normal_quad
        for i, layer in enumerate(self.hidden):
            out[f"layer{i}_weight"] = layer.weight.T  # (in, out): x @ W
            out[f"layer{i}_bias"] = layer.bias
        if self.arch.code_dim:  # the first layer's code rows apart: the fragment part keeps a static shape
            d = self.arch.input_dim
            out["code_weight"] = out["layer0_weight"][d:]
            out["layer0_weight"] = out["layer0_weight"][:d]
            out["enc_code_freq"] = self.code_freq
        return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in out.items()}


def evaluate_numpy(arrays: dict[str, np.ndarray], points: np.ndarray, normals: np.ndarray, codes: np.ndarray | None = None) -> np.ndarray:
    """The plain numpy evaluation of :meth:`TransferMLP.arrays` (float32, as the ONNX graph): the
    network's output (N, outputs) at ``points`` (N, 3) with ``normals`` (N, 3) (and shape ``codes``
    (N, d) for a shape-conditioned network: their features concatenated to each row's, the plain
    twin of the runtime's per-frame bias).  Used to score fits read back from the fit cache, where
    only the arrays survive."""
    p = np.asarray(points, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float32)
    x = np.clip((p - arrays["enc_centre"]) * arrays["enc_inv_half"], np.float32(-POSITION_CLIP), np.float32(POSITION_CLIP))
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.float32(NORMAL_EPS))
    ap, an = x @ arrays["enc_pos_freq"], n @ arrays["enc_normal_freq"]
    features = np.concatenate([x, np.sin(ap), np.cos(ap), n, np.sin(an), np.cos(an)], axis=1)
    if "code_weight" in arrays:
        if codes is None:
            raise ValueError("a shape-conditioned network needs codes")
        g = code_features(np.asarray(codes, np.float32).reshape(len(p), -1), arrays["enc_code_freq"])
        arrays = {**arrays, "layer0_weight": np.concatenate([arrays["layer0_weight"], arrays["code_weight"]])}
        features = np.concatenate([features, g], axis=1)
    out = mlp_numpy(arrays, features)
    if "out_normal_quad" in arrays:  # a residual network: the unshadowed transfer's quadratic part
        out = (out + normal_quadratic(n) @ arrays["out_normal_quad"]).astype(np.float32)
    return out


def mlp_numpy(arrays: dict[str, np.ndarray], features: np.ndarray) -> np.ndarray:
    """The MLP of a network's arrays on encoded ``features`` in numpy (float32): LeakyReLU layers
    ``layer{i}_weight/bias``, then ``tanh(out) * out_scale + out_offset`` (frequency and grid alike)."""
    h = np.asarray(features, dtype=np.float32)
    i = 0
    while f"layer{i}_weight" in arrays:
        h = h @ arrays[f"layer{i}_weight"] + arrays[f"layer{i}_bias"]
        h = np.where(h > 0, h, np.float32(LEAKY_SLOPE) * h)
        i += 1
    z = h @ arrays["out_weight"] + arrays["out_bias"]
    return (np.tanh(z) * arrays["out_scale"] + arrays["out_offset"]).astype(np.float32)


def target_scaling(transfer: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-coefficient ``(scale, offset)`` that map ``transfer`` (N, n) into [-0.9, 0.9]."""
    t = np.asarray(transfer, dtype=np.float64)
    lo, hi = t.min(axis=0), t.max(axis=0)
    offset = (hi + lo) / 2
    scale = np.maximum((hi - lo) / 2, 1e-4) / TARGET_RANGE
    return scale.astype(np.float32), offset.astype(np.float32)
