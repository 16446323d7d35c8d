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

A *log-DC* network (``Architecture.head = "log-dc"``, ``prt-train --head``) outputs each group of
``bands^2`` coefficients (the direct transfer; each indirect channel) as its DC coefficient times
ratios, the DC in log space:

    v  = tanh(z) * out_scale + z * out_linear + out_offset      z = W_out h + b_out
    u  = min(v, out_max)
    dc = exp(u @ out_dc_select)                                 (N, groups): each group's DC
    T  = (dc @ out_dc_spread) * (u * (1 - out_dc_mask) + out_dc_mask)

The DC columns have ``out_scale`` 0 and ``out_linear`` :data:`LOG_DC_SLOPE` (``u`` is the log DC,
linear in ``z``, capped by ``out_max``); the others ``out_linear`` 0 (``u`` is the ratio to the
group's DC, tanh-bounded).  An error of the network is then relative to the group's brightness:
a dim wall beside bright samples is neither negative nor lifted (issue 43's inside views: the
plain head fitted a wall at 0.001 as -0.004, black, beside samples at 0.3).

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
           "residual_terms", "normal_quadratic", "HEADS", "LOG_DC_SLOPE", "head_terms", "log_dc_scaling", "log_dc_head_numpy"]

TARGET_RANGE = 0.9  # scaled targets live in [-0.9, 0.9], where tanh' >= 0.19
# Output layouts: "direct" (bands^2, the paper's), "direct+rgb" (direct + indirect R, G, B:
# 4 bands^2, interreflection) and "rgb" (three total transfers, 3 bands^2: measured, not built).
LAYOUTS = {"direct": 1, "direct+rgb": 4, "rgb": 3}


# Output heads: "linear" (tanh(z) * out_scale + out_offset) and "log-dc" (module docstring).
HEADS = ("linear", "log-dc")
LOG_DC_SLOPE = 1.5  # d(log DC) / dz of a log-DC head: z ~ 1 spans a factor of 4.5
LOG_DC_RATIO_CAP = 4.0  # |ratio| bound of a log-DC head's other coefficients (out_scale at most this)


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
    head: str = "linear"  # see HEADS; "log-dc": each group's DC in log space, the rest as ratios to it (module docstring)

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
        if self.head == "linear":  # nor a linear head's before log-DC heads
            del out["head"]
        return out

    def label(self) -> str:
        code = f"-c{self.code_dim}f{self.code_freqs}" if self.code_dim else ""
        return (f"k{self.hidden}-l{self.layers}-f{self.pos_freqs}" + ("" if self.layout == "direct" else f"-{self.layout}") + code
                + ("-res" if self.residual else "") + ("-logdc" if self.head == "log-dc" else ""))  # fmt: skip

    def __post_init__(self):
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")
        if self.head == "log-dc" and self.residual:
            raise ValueError("a network is residual or has a log-DC head, not both")


def head_terms(arch: Architecture) -> dict[str, np.ndarray]:
    """A log-DC head's constant arrays (float32): ``out_dc_select`` (outputs, groups): 1 at each
    group's DC column; ``out_dc_spread`` (groups, outputs): 1 over each group's columns;
    ``out_dc_mask`` (outputs,): 1 at the DC columns.  Groups: ``bands^2`` consecutive outputs."""
    n = arch.bands * arch.bands
    groups = arch.outputs // n
    select = np.zeros((arch.outputs, groups), np.float32)
    select[np.arange(groups) * n, np.arange(groups)] = 1.0
    spread = np.kron(np.eye(groups, dtype=np.float32), np.ones((1, n), np.float32))
    return {"out_dc_select": select, "out_dc_spread": spread, "out_dc_mask": select.sum(axis=1).astype(np.float32)}


def log_dc_scaling(transfer: np.ndarray, n: int) -> dict[str, np.ndarray]:
    """A log-DC head's fitted constants from a segment's targets (N, groups * n): ``out_scale``,
    ``out_offset``, ``out_linear``, ``out_max`` (outputs,) float32.  Per group: the DC column
    starts at the log of the median positive DC (``out_offset``) and is capped at 1.5 x the
    largest (``out_max``); each other column's ratio bound is its largest |T_k / DC| over the
    samples brighter than 5 % of the group's largest DC, over :data:`TARGET_RANGE` (at most
    :data:`LOG_DC_RATIO_CAP`)."""
    t = np.asarray(transfer, np.float64)
    groups = t.shape[1] // n
    t = t.reshape(len(t), groups, n)
    dc = np.maximum(t[:, :, 0], 0.0)
    top = dc.max(axis=0, initial=0.0)
    scale, offset = np.zeros((groups, n)), np.zeros((groups, n))
    linear, cap = np.zeros((groups, n)), np.full((groups, n), 1e4)
    for g in range(groups):
        positive = dc[:, g][dc[:, g] > 0]
        offset[g, 0] = math.log(max(float(np.median(positive)), 1e-6)) if len(positive) else math.log(1e-3)
        cap[g, 0] = math.log(max(float(top[g]), 1e-6) * 1.5)
        linear[g, 0] = LOG_DC_SLOPE
        bright = dc[:, g] > 0.05 * top[g]
        if bright.any() and n > 1:
            ratio = np.abs(t[bright, g, 1:]) / dc[bright, g][:, None]
            scale[g, 1:] = np.clip(ratio.max(axis=0) / TARGET_RANGE, 0.05, LOG_DC_RATIO_CAP)
        else:
            scale[g, 1:] = 1.0
    flat = lambda a: a.reshape(-1).astype(np.float32)  # noqa: E731
    return {"out_scale": flat(scale), "out_offset": flat(offset), "out_linear": flat(linear), "out_max": flat(cap)}


def log_dc_head_numpy(z: np.ndarray, arrays: dict[str, np.ndarray]) -> np.ndarray:
    """The plain numpy twin of a log-DC head (module docstring) on the output layer's ``z`` (N, outputs)."""
    z = np.asarray(z, np.float32)
    u = np.minimum(np.tanh(z) * arrays["out_scale"] + z * arrays["out_linear"] + arrays["out_offset"], arrays["out_max"])
    dc = np.exp(u @ arrays["out_dc_select"]) @ arrays["out_dc_spread"]
    mask = arrays["out_dc_mask"]
    return (dc * (u * (1 - mask) + mask)).astype(np.float32)


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

    def __init__(self, arch: Architecture, bounds: np.ndarray, out_scale: np.ndarray, out_offset: np.ndarray,
                 out_linear: np.ndarray | None = None, out_max: np.ndarray | None = None):
        """``out_offset``: the whole output's (a residual network's includes ``c0`` of :func:`residual_terms`);
        ``out_linear``, ``out_max``: a log-DC head's (:func:`log_dc_scaling`)."""
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
        if arch.head == "log-dc":
            if out_linear is None or out_max is None:
                raise ValueError("a log-DC head needs out_linear and out_max (log_dc_scaling)")
            self.register_buffer("out_linear", torch.tensor(out_linear, dtype=torch.float32))
            self.register_buffer("out_max", torch.tensor(out_max, dtype=torch.float32))
            dc = head_terms(arch)["out_dc_mask"] > 0
            bound = np.abs(np.asarray(out_scale, np.float64)) + np.abs(np.asarray(out_offset, np.float64))
            if np.any(np.asarray(out_scale)[dc] != 0) or np.any(np.asarray(out_linear)[~dc] != 0) or np.any(np.asarray(out_max)[~dc] < bound[~dc]):
                raise ValueError("a log-DC head's DC columns take no tanh term, the others no linear term and no reachable cap")
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

    def head(self, z: torch.Tensor) -> torch.Tensor:
        """The output layer's ``z`` to the network's output (the module docstring's last lines)."""
        if self.arch.head != "log-dc":
            return torch.tanh(z) * self.out_scale + self.out_offset
        return self.log_dc_combine(*self.log_dc_split(z))

    # A log-DC head in torch, by groups (the fast path of fits; log_dc_head_numpy and the ONNX graph
    # are the module docstring's formula over all columns): the DC columns' tanh term and the other
    # columns' cap are left out, exact where out_scale is 0 at the DC columns and out_max is above
    # |out_scale| + |out_offset| elsewhere (log_dc_scaling's constants; checked at construction).
    def log_dc_split(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(log DC before its cap (N, groups), ratios (N, groups, bands^2 - 1))``."""
        n = self.arch.bands * self.arch.bands
        z = z.reshape(len(z), -1, n)
        lin, off, scale = (t.reshape(-1, n) for t in (self.out_linear, self.out_offset, self.out_scale))
        return torch.addcmul(off[:, 0], z[:, :, 0], lin[:, 0]), torch.addcmul(off[:, 1:], torch.tanh(z[:, :, 1:]), scale[:, 1:])

    def log_dc_combine(self, log_dc: torch.Tensor, ratios: torch.Tensor) -> torch.Tensor:
        n = self.arch.bands * self.arch.bands
        dc = torch.exp(torch.minimum(log_dc, self.out_max.reshape(-1, n)[:, 0])).unsqueeze(2)
        return torch.cat([dc, dc * ratios], dim=2).reshape(len(log_dc), -1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.head(self.preactivation(x))
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
        if self.arch.head == "log-dc":
            out.update(out_linear=self.out_linear, out_max=self.out_max)
            out.update({k: torch.from_numpy(v) for k, v in head_terms(self.arch).items()})  # constants of the architecture
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
    ``layer{i}_weight/bias``, then ``tanh(out) * out_scale + out_offset`` (frequency and grid alike),
    or a log-DC head's (:func:`log_dc_head_numpy`) where the arrays hold one."""
    h = np.asarray(features, dtype=np.float32)
    i = 0
    while f"layer{i}_weight" in arrays:
        h = h @ arrays[f"layer{i}_weight"] + arrays[f"layer{i}_bias"]
        h = np.where(h > 0, h, np.float32(LEAKY_SLOPE) * h)
        i += 1
    z = h @ arrays["out_weight"] + arrays["out_bias"]
    if "out_dc_select" in arrays:
        return log_dc_head_numpy(z, arrays)
    return (np.tanh(z) * arrays["out_scale"] + arrays["out_offset"]).astype(np.float32)


def target_scaling(transfer: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-coefficient ``(scale, offset)`` that map ``transfer`` (N, n) into [-0.9, 0.9]."""
    t = np.asarray(transfer, dtype=np.float64)
    lo, hi = t.min(axis=0), t.max(axis=0)
    offset = (hi + lo) / 2
    scale = np.maximum((hi - lo) / 2, 1e-4) / TARGET_RANGE
    return scale.astype(np.float32), offset.astype(np.float32)
