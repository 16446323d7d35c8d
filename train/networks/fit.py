"""Fitting one segment's network: L1 loss (or, ``loss="relative"``, L1 weighted by each sample's
inverse brightness, :func:`loss_weights`), Adam, warm-up + cosine learning rate, early stop
on the held-out validation samples, deterministic for a seed.  Right-sizing walks a ladder of
sizes and keeps the smallest network that meets the error target.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import threading
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from ...export.onnx_model import NORMAL_EPS
from ...runtime.sh import unshadowed_transfer
from .network import Architecture, TransferMLP, log_dc_scaling, normal_quadratic, residual_terms, target_scaling

__all__ = [
    "FitSettings",
    "DEFAULT_STEPS",
    "FitResult",
    "fit_segment",
    "right_size",
    "DEFAULT_LADDER",
    "right_size_matching",
    "PAPER_SIZES",
    "shaded_error",
    "total_transfer",
    "transfer_error",
    "bf16_supported",
    "LOSSES",
    "RELATIVE_FLOOR",
    "loss_weights",
    "weighted_l1_numpy",
    "loss_numpy",
    "DEFAULT_LOSS",
    "LOSS_VISIBILITY",
    "resolve_loss",
    "mean_visibility",
    "batch_loss",
    "brightness",
    "seeded",
    "FIT_THREADS",
]

# Fitting losses: "l2" (squared error on the coefficients), "l1" (the paper's: L1 on the
# coefficients), "relative" (each sample's L1 divided by c + m, m its brightness, so the loss follows
# the relative error that a tone-mapped image shows), and "auto" (the default): per segment, L1 where
# its samples see at least LOSS_VISIBILITY of their cosine lobe, L2 elsewhere.
# Why: the targets are Monte Carlo estimates, and what a network cannot resolve it fits by the loss's
# optimum: L2's is the mean, the transfer; L1's is the median.  Where most of the light is occluded
# (a room lit through its windows: few samples see the sun patch, most see none of it, and the noise
# of each is skewed the same way) the median lies far below the mean: fitted with L1 the Duplex
# house's sunlit floor came out at 0.002 against 0.155 (docs/benchmarks/loss_l2_duplex.md).  Where
# little is occluded (Spot, open surfaces) L1 fitted better: 41.9 vs 40.6 dB held out on Spot's
# standard build, where every segment sees >= 0.8 of its lobe.
LOSSES = ("auto", "l2", "l1", "relative")
DEFAULT_LOSS = "auto"
LOSS_VISIBILITY = 0.8
"""``loss: "auto"``: a segment whose samples see at least this share of their cosine lobe on average
(its mean DC coefficient over the unshadowed one's, as ``residual: "auto"`` measures it) fits with
"l1", below it with "l2"."""
# c of "relative", in transfer units: an unoccluded surface's DC coefficient is 0.282 (Y_00), the
# Cornell box's dim interior's about 0.04; below c a sample's weight stops growing.  0.02 let the
# dark samples (DC ~ 0) outweigh the open ones so far that a k32 network of the Cornell floor fitted
# its unoccluded side as black (docs/benchmarks/loss_weighting.md); 0.05 caps the weight ratio at 6.6.
RELATIVE_FLOOR = 0.05

# Smallest first.  Each rung is (hidden k, layers l, position frequencies F).
DEFAULT_LADDER = (
    Architecture(hidden=16, layers=2, pos_freqs=4),
    Architecture(hidden=32, layers=2, pos_freqs=5),
    Architecture(hidden=32, layers=3, pos_freqs=6),
    Architecture(hidden=48, layers=3, pos_freqs=6),
    Architecture(hidden=64, layers=3, pos_freqs=6),
    Architecture(hidden=64, layers=4, pos_freqs=6),
    Architecture(hidden=128, layers=4, pos_freqs=6),
)
PAPER_SIZES = (Architecture(hidden=64, layers=4), Architecture(hidden=128, layers=4))


# Adam steps per network unless a spec says otherwise, chosen by measurement (README, "Training
# length"): on Spot (100k samples, 8 segments, k = 64, l = 4, batch 8192) validation MAE falls
# 0.00191 / 0.00154 / 0.00135 / 0.00126 at 500 / 1000 / 2000 / 4000 steps: 4000 buys 7 % for 2x time.
DEFAULT_STEPS = 2000
# Validation passes over a run measured in steps (early stopping looks at these).
EVALUATIONS = 50


@dataclass
class FitSettings:
    """How long and how one network trains.

    The run is ``steps`` Adam steps, whatever the sample count, or, where ``epochs`` is set,
    at least ``epochs`` passes over the samples (the larger of the two); both None: DEFAULT_STEPS.
    With only ``epochs`` the run is epoch-based as before (validation once per epoch); otherwise
    validation runs EVALUATIONS times and ``patience`` counts those.  ``max_seconds`` also ends
    the run, and the learning-rate schedule then decays over the time budget as well (whichever
    of steps and seconds runs out first); a fit cut by time is not reproducible bit for bit.
    """

    epochs: int | None = None  # at least this many passes over the data (None: steps alone)
    batch: int = 8192
    lr: float = 3e-3
    warmup_epochs: float = 1.0  # epoch-based runs; a run in steps warms up over 2 % of its steps
    patience: int = 8  # evaluations without a 0.5 % better validation MAE
    # No early stop before this share of the run: while the cosine schedule's rate is still
    # high a plateau (or a spike, as k = 128 at lr 1e-2 shows) is not convergence.
    min_epochs_fraction: float = 0.5
    seed: int = 0
    bf16: bool | None = False  # True: bf16 autocast (2x faster here, ~9 % higher error); None: where native
    max_seconds: float | None = None  # wall-clock budget per fit
    steps: int | None = None  # Adam steps per network (None: DEFAULT_STEPS unless ``epochs`` is set)
    loss: str = DEFAULT_LOSS  # see LOSSES; the kept network is the one with the lowest validation error in the loss's own terms
    loss_floor: float = RELATIVE_FLOOR  # c of the "relative" loss
    # Where frequency networks train: "cpu" or "cuda" (resolve_device; grid networks stay on the CPU).
    # Not in the cache key: a fit made on either device serves a build on the other.
    device: str = "cpu"

    def cache_key(self) -> dict:
        """The fields that key cached fits: every field but the device; the loss where not "l1" (so
        "l1" fits keep the keys they had before the loss option), its floor only for "relative"."""
        keyed = asdict(self)
        del keyed["device"]
        if self.loss == "l1":
            del keyed["loss"], keyed["loss_floor"]
        elif self.loss != "relative":
            del keyed["loss_floor"]
        return keyed

    def plan(self, n: int) -> tuple[int, int, int, int]:
        """(batch, total steps, steps between validations, warm-up steps) for ``n`` training samples."""
        batch = max(1, min(self.batch, n))
        per_epoch = max(1, math.ceil(n / batch))
        if self.steps is None and self.epochs is not None:  # epoch-based, as before steps existed
            total = self.epochs * per_epoch
            return batch, total, per_epoch, max(1, int(self.warmup_epochs * per_epoch))
        steps = DEFAULT_STEPS if self.steps is None else self.steps
        total = max(steps, (self.epochs or 0) * per_epoch)
        return batch, total, max(1, total // EVALUATIONS), max(1, total // 50)


@dataclass
class FitResult:
    model: TransferMLP
    arch: Architecture
    val_mae: float  # mean absolute error of the coefficients on held-out samples
    shaded: dict[str, float]  # env name -> relative MAE of dot(T, L) on held-out samples
    epochs: int  # validations run (epochs in an epoch-based run)
    seconds: float
    history: list[dict] = field(default_factory=list)
    steps: int = 0  # Adam steps taken


DEVICES = ("auto", "cpu", "cuda")
"""``prt-train --device``: auto (CUDA where torch sees a GPU, else the CPU), cpu, cuda."""


def resolve_device(device: str = "auto", origin: str = "--device") -> str:
    """``"cpu"`` or ``"cuda"`` for a ``--device`` value; InputError (one line) for ``cuda`` where torch
    sees no GPU, or a value not in :data:`DEVICES`."""
    from ...runtime.errors import InputError

    if device not in DEVICES:
        raise InputError(f"{origin}: expected one of {', '.join(DEVICES)}, got {device!r}")
    available = torch.cuda.is_available()
    if device == "cuda" and not available:
        raise InputError(f"{origin} cuda: torch {torch.__version__} sees no CUDA GPU (a CPU build of torch, or no driver); use --device cpu or auto")
    return "cuda" if device == "cuda" or (device == "auto" and available) else "cpu"


def bf16_supported() -> bool:
    """True where the CPU has native bf16 dot products (AVX512-BF16 or AMX)."""
    try:
        flags = open("/proc/cpuinfo").read()
    except OSError:
        return False
    return (" avx512_bf16" in flags or " amx_bf16" in flags) and torch.backends.mkldnn.is_available()


def total_transfer(t: np.ndarray, n: int | None = None) -> np.ndarray:
    """The transfer a network's output stands for: ``t`` itself (direct layout, ``n`` wide), or for
    the "direct+rgb" layout of interreflection (``4 n`` wide: direct, indirect R, G, B) the total RGB
    transfer ``direct + indirect_c``, shape (M, n, 3); the "rgb" layout (``3 n``: R, G, B) likewise."""
    t = np.asarray(t)
    if n is None or t.shape[1] == n:
        return t
    if t.shape[1] == 3 * n:  # the "rgb" layout: three total transfers
        return t.reshape(len(t), 3, n).transpose(0, 2, 1)
    direct, indirect = t[:, :n], t[:, n:].reshape(len(t), 3, n)
    return direct[:, :, None] + indirect.transpose(0, 2, 1)


def transfer_error(pred: np.ndarray, truth: np.ndarray, n: int | None = None) -> float:
    """Validation MAE: of the coefficients (direct layout), or of the total RGB transfer (so the same
    ``target`` means the same error in the shading with or without interreflection)."""
    return float(np.abs(total_transfer(pred, n) - total_transfer(truth, n)).mean())


def shaded_error(pred: np.ndarray, truth: np.ndarray, lights: dict[str, np.ndarray], n: int | None = None) -> dict[str, float]:
    """Relative MAE of the diffuse shading ``T @ L`` per env map: mean|dT L| / mean|T L|
    (RGB transfer, ``n`` coefficients per channel: ``sum_i T_ic L_ic``)."""
    out = {}
    for name, light in lights.items():
        if n is None or np.shape(truth)[1] == n:
            ref = truth.astype(np.float64) @ light
            err = pred.astype(np.float64) @ light - ref
        else:
            ref = np.einsum("mnc,nc->mc", total_transfer(truth, n).astype(np.float64), light)
            err = np.einsum("mnc,nc->mc", total_transfer(pred, n).astype(np.float64), light) - ref
        out[name] = float(np.abs(err).mean() / max(np.abs(ref).mean(), 1e-12))
    return out


def brightness(transfer: np.ndarray, n: int) -> np.ndarray:
    """Per-sample brightness proxy m: the DC coefficient of the total transfer, averaged over the
    colour channels (direct layout: ``T_0``; "direct+rgb": ``T_0 + mean_c T_ind,c,0``), at least 0."""
    total = total_transfer(np.asarray(transfer, dtype=np.float64), n)
    dc = total[:, 0] if total.ndim == 2 else total[:, 0, :].mean(axis=1)
    return np.maximum(dc, 0.0)


def loss_weights(transfer: np.ndarray, n: int, loss: str = "relative", floor: float = RELATIVE_FLOOR) -> np.ndarray | None:
    """Per-sample loss weights, shape (M,) float32, mean 1: ``1 / (floor + m)`` (m: :func:`brightness`)
    normalised so the loss keeps the plain L1's scale; None for ``loss="l1"`` and ``"l2"`` (unweighted).
    Every output of a sample (all 64 of "direct+rgb") gets its sample's weight."""
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {', '.join(LOSSES)}, got {loss!r}")
    if loss != "relative":
        return None
    if not (math.isfinite(floor) and floor > 0):
        raise ValueError(f"loss_floor must be finite and > 0, got {floor!r}")
    w = 1.0 / (floor + brightness(transfer, n))
    return (w / w.mean()).astype(np.float32)


def mean_visibility(transfer: np.ndarray, bands: int) -> float:
    """The samples' mean visibility: the mean DC coefficient of their (direct) transfer over the
    unshadowed transfer's (the same for every normal); 0 for no samples."""
    u00 = float(unshadowed_transfer(np.array([[0.0, 0.0, 1.0]]), bands)[0, 0])
    return float(np.mean(np.asarray(transfer[:, 0], np.float64))) / u00 if len(transfer) else 0.0


def resolve_loss(loss: str, transfer: np.ndarray, bands: int) -> str:
    """The loss a fit uses: ``loss`` itself, or for "auto" "l1" where the samples' :func:`mean_visibility`
    is at least :data:`LOSS_VISIBILITY`, else "l2"."""
    if loss != "auto":
        return loss
    return "l1" if mean_visibility(transfer, bands) >= LOSS_VISIBILITY else "l2"


# A log-DC head's fit adds LOG_DC_WEIGHT * mean(DC^2) / bands^2 times the squared error of each
# group's log DC (against log max(DC, LOG_DC_EPS * the group's largest)) to the loss on the transfer.
# Without it, a group driven dim early has exp()'s vanishing gradient and stays black: the Duplex copy's
# largest inside segment (127k samples, k128-l4) fitted all-zero (held out 14.9 dB against 30.0 with the
# linear head); with it 33.2 dB.  On six inside segments (the build's sizes, 1000 steps; scratch
# /work/scratch/s16/logdc.py, 2026-12-07, AMD EPYC) against the linear head: held out +1.4 to +6.4 dB on
# five, -1.4 on one; the inside views' pixels at their exposure +3.3 to +11.6 dB on four, -2.7 and -0.9
# on two.  A weight of 1 instead of 0.3 was no better.  The scale makes a group of average brightness
# weigh its relative error about as much as the transfer loss weighs its absolute one.
LOG_DC_WEIGHT = 0.3
LOG_DC_EPS = 1e-3


def log_dc_targets(transfer: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The log-DC term's targets (N, groups) and per-group weights (groups,), float32."""
    t = np.asarray(transfer, np.float64)
    dc = np.maximum(t.reshape(len(t), -1, n)[:, :, 0], 0.0)
    floor = np.maximum(LOG_DC_EPS * dc.max(axis=0, initial=0.0), 1e-8)
    weight = LOG_DC_WEIGHT * np.mean(dc**2, axis=0) / n if len(dc) else np.zeros(dc.shape[1])
    return np.log(np.maximum(dc, floor)).astype(np.float32), np.asarray(weight, np.float32)


def weighted_l1_numpy(pred: np.ndarray, truth: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Plain reference of the L1 fitting losses: mean over samples and outputs of ``w_i |pred - truth|``
    (``weights`` None: plain L1)."""
    err = np.abs(np.asarray(pred, np.float64) - np.asarray(truth, np.float64))
    if weights is not None:
        err = err * np.asarray(weights, np.float64)[:, None]
    return float(err.mean())


def loss_numpy(pred: np.ndarray, truth: np.ndarray, loss: str = DEFAULT_LOSS, weights: np.ndarray | None = None) -> float:
    """Plain reference of :func:`batch_loss` for ``loss``: the mean squared error over samples and
    outputs ("l2"), else :func:`weighted_l1_numpy` (``weights``: the "relative" loss's)."""
    if loss == "l2":
        return float(np.square(np.asarray(pred, np.float64) - np.asarray(truth, np.float64)).mean())
    return weighted_l1_numpy(pred, truth, weights)


def batch_loss(out: torch.Tensor, target_scaled: torch.Tensor, scale: torch.Tensor | None, weights: torch.Tensor | None = None,
               loss: str = DEFAULT_LOSS) -> torch.Tensor:
    """The fitting loss of a batch on the transfer itself (``out`` and ``target_scaled`` are in the
    network's scaled units, ``scale`` (outputs,) maps them back; None: they are the transfer): the
    squared error ("l2"), or the absolute error, each sample's row times its weight ((B, 1),
    :func:`loss_weights`) where given.  :func:`loss_numpy` is its plain twin."""
    diff = out - target_scaled if scale is None else (out - target_scaled) * scale
    if loss == "l2":
        return diff.square().mean()
    if weights is None:
        return diff.abs().mean()
    return (diff.abs() * weights).mean()


def _as_input(points: np.ndarray, normals: np.ndarray, codes: np.ndarray | None = None) -> torch.Tensor:
    parts = [points, normals] + ([] if codes is None else [codes])
    return torch.from_numpy(np.ascontiguousarray(np.concatenate(parts, axis=1), dtype=np.float32))


def _predict(model: torch.nn.Module, x: torch.Tensor, batch: int = 65536) -> np.ndarray:
    """The model on ``x`` (a CPU tensor) in batches, on the model's device; (N, outputs) float32 numpy."""
    device = next(model.parameters()).device
    with torch.inference_mode():
        return torch.cat([model(x[i : i + batch].to(device)).cpu() for i in range(0, len(x), batch)]).numpy()


class Validation:
    """The held-out check a fit runs every few steps (frequency and grid networks alike): the
    history, the progress callback, the best state so far (a 0.5 % better score restarts the
    patience count) and early stopping.  The score is the fit's own loss on the held-out samples:
    the mean squared error of the total transfer ("l2"), the validation MAE ("l1"), or with
    ``weights`` (the relative loss) the weighted L1 of :func:`weighted_l1_numpy`."""

    def __init__(self, xv: torch.Tensor, yv: np.ndarray, n_coeffs: int, weights, settings, progress=None):
        self.xv, self.yv, self.n_coeffs, self.weights = xv, yv, n_coeffs, weights
        self.squared = getattr(settings, "loss", DEFAULT_LOSS) == "l2"
        self.settings, self.progress = settings, progress
        self.best = (math.inf, None, 0)  # (score, state, evaluation that last improved by 0.5 %)
        self.history: list[dict] = []
        self.evaluation = 0

    def __call__(self, model, step: int, total_steps: int, train_l1: float) -> bool:
        """Evaluate ``model`` (left in training mode); True when the fit should stop."""
        self.evaluation += 1
        model.eval()
        val_pred = _predict(model, self.xv)
        val_mae = transfer_error(val_pred, self.yv, self.n_coeffs)
        model.train()
        self.history.append({"epoch": self.evaluation, "step": step, "train_l1": train_l1, "val_mae": val_mae})
        if self.progress is not None:
            self.progress(step, total_steps, train_l1, val_mae)
        if self.squared:
            score = float(np.square(total_transfer(val_pred, self.n_coeffs) - total_transfer(self.yv, self.n_coeffs)).mean())
        else:
            score = val_mae if self.weights is None else weighted_l1_numpy(val_pred, self.yv, self.weights)
        if score < self.best[0] * (1 - 5e-3):
            self.best = (score, copy.deepcopy(model.state_dict()), self.evaluation)
        elif score < self.best[0]:
            self.best = (score, copy.deepcopy(model.state_dict()), self.best[2])
        settings = self.settings
        return self.evaluation - self.best[2] >= settings.patience and step >= settings.min_epochs_fraction * total_steps


_SEED_LOCK = threading.Lock()
FIT_THREADS = 1
"""Torch threads of one fit in a build; a build runs as many fits at once as it has threads (its fit
stage and each refinement round).  Two one-thread fits at once did 1.3-1.8x the steps of one
two-thread fit (k64-l3 .. k16-l2, 1000 steps of 4096 on 15k samples, AMD EPYC, 2 cores)."""


def seeded(seed: int, make):
    """``make()`` (a network's constructor) right after ``torch.manual_seed(seed)``, under a lock: its
    initial weights come from torch's process-wide generator, and fits run two or more at a time
    on threads of one process (:mod:`prt.train.build`, :mod:`prt.train.refine`), so the seeding and
    the draws must not interleave with another fit's.  Nothing after construction draws from that
    generator (the batches come from each fit's own ``torch.Generator``)."""
    with _SEED_LOCK:
        torch.manual_seed(seed)
        return make()


def fit_segment(
    points: np.ndarray,
    normals: np.ndarray,
    transfer: np.ndarray,
    val_points: np.ndarray,
    val_normals: np.ndarray,
    val_transfer: np.ndarray,
    arch: Architecture,
    bounds: np.ndarray,
    settings: FitSettings | None = None,
    *,
    lights: dict[str, np.ndarray] | None = None,
    progress=None,
    codes: np.ndarray | None = None,
    val_codes: np.ndarray | None = None,
) -> FitResult:
    """Train one network on a segment's samples (own + margin), validate on held-out samples.

    Parameters
    ----------
    points, normals : (N, 3) training inputs; transfer : (N, arch.outputs) targets (the "direct+rgb"
        layout: direct, indirect R, G, B; its validation error is that of the total RGB transfer)
    val_points, val_normals : (M, 3); val_transfer : (M, n) held-out samples (M >= 1)
    arch : network size; bounds : (2, 3) box the encoding normalises to
    lights : env name -> (n, 3) SH lighting for the shaded error
    progress : callable(step, total_steps, train_loss, val_mae) or None, after each validation
    codes, val_codes : (N, d), (M, d) shape codes of the samples (deformable scenes, ``arch.code_dim`` = d)
    """
    settings = settings or FitSettings()
    if settings.loss == "auto":
        settings = dataclasses.replace(settings, loss=resolve_loss("auto", transfer, arch.bands))
    for name, a in (("points", points), ("normals", normals), ("transfer", transfer)):
        if not np.isfinite(a).all():
            raise ValueError(f"training {name} contain NaN or Inf")
    if len(points) == 0 or len(val_points) == 0:
        raise ValueError("a segment needs at least one training and one validation sample")
    n_coeffs = arch.bands * arch.bands  # per channel; the "direct+rgb" layout outputs 4 sets
    if np.shape(transfer)[1] != arch.outputs:
        raise ValueError(f"transfer has {np.shape(transfer)[1]} columns, the network {arch.outputs} outputs ({arch.layout})")
    gen = torch.Generator().manual_seed(settings.seed)
    target = transfer
    if arch.residual:  # the network learns T - U(n); its graph adds U back (prt.train.networks.network)
        c0, w_u = residual_terms(arch)
        n_unit = np.asarray(normals, np.float64) / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), NORMAL_EPS)
        target = (np.asarray(transfer, np.float64) - (c0 + normal_quadratic(n_unit) @ w_u)).astype(np.float32)
    device = torch.device(settings.device)  # the samples move there once; on the CPU every .to() below is a no-op
    log_dc = arch.head == "log-dc"
    if log_dc:  # the loss is on the transfer itself: the head's output is in its units (scale 1, offset 0)
        head = log_dc_scaling(target, n_coeffs)
        model = seeded(settings.seed, lambda: TransferMLP(arch, bounds, head["out_scale"], head["out_offset"], head["out_linear"], head["out_max"]))
        scale, offset = np.ones(arch.outputs, np.float32), np.zeros(arch.outputs, np.float32)
        model = model.to(device)
    else:
        scale, offset = target_scaling(target)
        model = seeded(settings.seed, lambda: TransferMLP(arch, bounds, scale, offset + c0 if arch.residual else offset)).to(device)
    if (codes is None) != (arch.code_dim == 0) or (codes is None) != (val_codes is None):
        raise ValueError(f"a network with code_dim {arch.code_dim} needs {'codes' if arch.code_dim else 'no codes'} for training and validation")
    x = _as_input(points, normals, codes).to(device)
    y = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32)).to(device)  # the scaled tanh output's target
    xv = _as_input(val_points, val_normals, val_codes)
    yv = np.asarray(val_transfer, dtype=np.float32)
    # the loss on the transfer itself, computed through the scaled tanh output
    inv_scale = torch.from_numpy(1.0 / scale).to(device)
    y_scaled = (y - torch.from_numpy(offset).to(device)) * inv_scale
    weights = loss_weights(transfer, n_coeffs, settings.loss, settings.loss_floor)
    w = None if weights is None else torch.from_numpy(weights)[:, None].to(device)
    log_target = log_weight = None
    if log_dc:
        log_target, log_weight = (torch.from_numpy(a).to(device) for a in log_dc_targets(target, n_coeffs))
    val_weights = loss_weights(yv, n_coeffs, settings.loss, settings.loss_floor)

    n = len(x)
    batch, total_steps, eval_every, warmup = settings.plan(n)
    # The encoding has no parameters: computed once per fit, each step gathers its rows (at batches of 256 a
    # step's sin / cos were 12-13 % of its time; encode_once_matches is the per-step twin's test).
    with torch.no_grad():
        encoded = model.encode(x)  # fp32: sin/cos of 2^k pi x needs the precision
    budget = settings.max_seconds
    t0 = time.perf_counter()

    def progress_share(step: int) -> float:  # of the run, by steps or by the time budget
        share = step / total_steps
        if budget is not None:
            share = max(share, (time.perf_counter() - t0) / budget)
        return min(share, 1.0)

    opt = torch.optim.Adam(model.parameters(), lr=settings.lr)
    on_gpu = device.type != "cpu"
    use_bf16 = (torch.cuda.is_bf16_supported() if on_gpu else bf16_supported()) if settings.bf16 is None else settings.bf16
    scale_t = torch.from_numpy(scale).to(device)

    check = Validation(xv, yv, n_coeffs, val_weights, settings, progress)
    step = 0
    perm, cursor, total, counted = torch.randperm(n, generator=gen), 0, 0.0, 0
    model.train()
    while step < total_steps:
        if cursor >= n:  # a new pass over the samples
            perm, cursor = torch.randperm(n, generator=gen), 0
        idx = perm[cursor : cursor + batch].to(device)  # drawn on the CPU: the same order on either device
        cursor += batch
        rate = min(1.0, (step + 1) / warmup) * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * progress_share(step))))
        for group in opt.param_groups:
            group["lr"] = settings.lr * rate
        features = encoded[idx]
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
            pre = model.trunk(features)
        if log_dc:  # the transfer itself; each group's log DC against the target's: a gradient however dim the group
            log_dc_pred, ratios = model.log_dc_split(pre.float())
            loss = batch_loss(model.log_dc_combine(log_dc_pred, ratios), y[idx], None, None if w is None else w[idx], settings.loss)
            loss = loss + ((log_dc_pred - log_target[idx]).square() * log_weight).mean()
        else:
            loss = batch_loss(torch.tanh(pre.float()), y_scaled[idx], scale_t, None if w is None else w[idx], settings.loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        # On a GPU .item() would wait for every step: the sum stays there until the validation reads it.
        total += loss.detach() * len(idx) if on_gpu else loss.detach().item() * len(idx)
        counted += len(idx)
        out_of_time = budget is not None and time.perf_counter() - t0 > budget
        if step % eval_every and step < total_steps and not out_of_time:
            continue
        stop = check(model, step, total_steps, float(total) / counted)
        total, counted = 0.0, 0
        if stop or out_of_time:
            break
    model.load_state_dict(check.best[1])
    model = model.cpu().eval()  # the export reads its arrays
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


def right_size_matching(fit, reference: Architecture, ladder=DEFAULT_LADDER, tolerance: float = 0.05, log=print):
    """The cheapest size that is as accurate as ``reference`` (e.g. the paper's k = 64, l = 4).

    Trains ``reference`` first; its validation MAE times ``1 + tolerance`` is the bar.  Then walks
    the rungs of ``ladder`` with fewer FLOPs per fragment than the reference, largest first, while
    they clear the bar, and keeps the last (cheapest) that did.  So the result never has more
    FLOPs than the reference nor (up to ``tolerance``) more error; when no smaller rung clears the
    bar it is the reference fit itself, at no extra training.  A rung that misses ends the walk:
    smaller ones are not tried (a rung is rarely more accurate than a larger one).

    Returns ``(chosen FitResult, records of the sizes tried, the bar)``.
    """
    if tolerance < 0:
        raise ValueError(f"tolerance must be >= 0, got {tolerance}")
    ref = fit(reference)
    bar = ref.val_mae * (1.0 + tolerance)
    tried = [{"arch": reference.label(), "val_mae": ref.val_mae, "flops": reference.flops_per_fragment(), "seconds": ref.seconds, "reference": True}]
    log(f"  {reference.label():>12}: val MAE {ref.val_mae:.5f} ({ref.seconds:.1f} s)  reference; bar {bar:.5f}")
    chosen = ref
    cheaper = sorted((a for a in ladder if a.flops_per_fragment() < reference.flops_per_fragment()), key=lambda a: -a.flops_per_fragment())
    for arch in cheaper:
        result = fit(arch)
        ok = result.val_mae <= bar
        tried.append({"arch": arch.label(), "val_mae": result.val_mae, "flops": arch.flops_per_fragment(), "seconds": result.seconds})
        log(f"  {arch.label():>12}: val MAE {result.val_mae:.5f} ({result.seconds:.1f} s)  {'meets' if ok else 'misses'} the bar")
        if not ok:
            break
        chosen = result
    return chosen, tried, bar


def right_size(fit, ladder=DEFAULT_LADDER, target: float = 0.004, log=print) -> tuple[FitResult, list[dict]]:
    """Smallest rung of ``ladder`` whose validation MAE meets ``target``.

    ``fit(arch) -> FitResult`` trains one size.  Returns the chosen fit (the best one tried if
    no rung meets the target) and one record per size tried.
    """
    tried = []
    best = None
    for arch in ladder:
        result = fit(arch)
        tried.append({"arch": arch.label(), "val_mae": result.val_mae, "flops": arch.flops_per_fragment(), "seconds": result.seconds})
        log(f"  {arch.label():>12}: val MAE {result.val_mae:.5f} ({result.seconds:.1f} s)")
        if best is None or result.val_mae < best.val_mae:
            best = result
        if result.val_mae <= target:
            return result, tried
    return best, tried
