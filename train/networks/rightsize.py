"""Right-sizing one segment: which encoding and size its network gets, and a record of why.

A build's spec picks one rule; every segment's training record and its manifest entry keep what
was chosen and why (``sizing``: the rule, its target, the measured value, the sizes tried):

- ``"fixed"``: one size for every network (``--hidden/--layers``).
- ``"target_mae"``: the first size, cheapest first, whose validation coefficient MAE meets
  ``target`` (:func:`prt.train.networks.fit.right_size`; the default before ``target_db``).
- ``"match"``: the cheapest size as accurate as a reference size (``--match 64x4``,
  :func:`prt.train.networks.fit.right_size_matching`).
- ``"vertex"`` (the default of mesh builds, :mod:`prt.train.presets`): the cheapest size whose held-out
  shaded PSNR is ``vertex_margin`` dB above per-vertex PRT's on the same samples under every
  bundled env map (per-vertex PRT estimated by :mod:`prt.train.transport.vertex_estimate`), among the
  sizes within the segment's share of per-vertex PRT's bytes (its share of the training samples);
  the record says where it ended: ``"error"`` (margin reached), ``"bytes"`` (the byte share cut
  the ladder and the largest size allowed missed) or ``"ladder"`` (the largest size missed).
  Each segment at the margin puts the scene's pooled held-out PSNR at the margin too (the pooled
  MSE is the sample-weighted mean of the segments').
- ``"target_db"``: the cheapest candidate, by FLOPs per fragment, whose **shaded PSNR** on the
  segment's held-out samples meets ``target_db`` (:func:`search_cheapest`).  The shaded PSNR is
  what ``prt-bench`` measures over pixels, here over samples: the diffuse radiance ``a (T . L)``
  under each bundled env map, tone-mapped (:func:`prt.runtime.shading.tonemap`), against the
  ray-traced transfer, under the scene's lighting (:data:`SCENE_LIGHT`, the manifest's default,
  which ``prt-bench`` renders under; the record keeps the other bundled maps' figures too;
  :func:`shaded_psnr`).  If every segment meets
  X dB, the pooled MSE of all held-out samples is at most ``10^(-X/10)``, so the scene's PSNR
  over its samples is at least X.  With ``encoding: "auto"`` the candidates are the frequency
  ladder and the grid ladder together (:func:`candidates`).

Fits read back from the fit cache carry only their arrays, so the PSNR is computed from the
arrays in numpy (:func:`predict_numpy`), for new and cached fits alike.

Before sizing, :func:`residual_choice` decides whether the segment's frequency networks learn
the direct transfer's residual from the unshadowed transfer (``Architecture.residual``; the
spec's ``residual``: "on", "off", or "auto": where the segment's mean visibility is high, both
kinds fitted at one size and the lower validation MAE kept); every size tried, and a ``match``
reference, is then that kind of network.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from ...runtime.exposure import LUMINANCE, exposure_from_log_mean
from ...runtime.sh import unshadowed_transfer
from ...runtime.shading import tonemap
from .fit import LOSS_VISIBILITY, FitSettings, fit_segment, mean_visibility, resolve_loss, right_size, right_size_matching, shaded_error, total_transfer, transfer_error
from .grid_encoding import GridArchitecture, fit_grid_segment
from .grid_encoding import evaluate_numpy as grid_evaluate
from .network import Architecture
from .network import evaluate_numpy as freq_evaluate

__all__ = ["RULES", "ENDINGS", "pooled_psnr", "scene_sizing", "RESIDUAL_MODES", "RESIDUAL_VISIBILITY", "residual_choice", "HEAD_MODES", "head_choice", "PSNR_CAP", "shaded_psnr", "exposed_psnr", "predict_numpy", "candidates", "search_cheapest", "weight_bytes", "train_segment", "SegmentJob",
           "segment_task", "validation_split", "SCENE_LIGHT"]  # fmt: skip

RULES = ("fixed", "target_mae", "match", "target_db", "vertex")
ENDINGS = ("error", "bytes", "ladder")  # where the "vertex" rule ended (module docstring)
PSNR_CAP = 100.0  # the same cap as prt-bench's metrics
DEFAULT_ALBEDO = (0.7, 0.7, 0.7)  # the spec's default material
# The lighting a build's manifest gets (prt.train.build) and the shaded target is measured under.
# The held-out samples cover every surface, the dark ones a view rarely shows too, and the sRGB
# curve is steep near black: on Spot the pooled sample PSNR sat 2.9-8.0 dB below the rendered
# images', with no stable offset (docs/benchmarks/rightsize_auto.md): a conservative,
# view-independent bound, not a prediction of a view's PSNR.
SCENE_LIGHT = "potsdamer"
RESIDUAL_MODES = ("auto", "on", "off")
# Output heads of frequency networks (prt.train.networks.network.HEADS): "auto" gives a segment
# the log-DC head where its samples see less than LOSS_VISIBILITY of their cosine lobe on average
# (rooms lit through windows, shadowed sides: brightness spans decades within one segment) and
# the linear head elsewhere (open surfaces, where residual networks serve).  The build's default
# is "linear" (BuildSpec.head: "auto" built the Duplex and AS1 copies worse).
HEAD_MODES = ("auto", "linear", "log-dc")
RESIDUAL_VISIBILITY = 0.8
"""``residual: "auto"``: a segment whose samples see at least this share of their cosine lobe on
average is fitted both ways at one size (the ``match`` reference, else the first frequency size),
and keeps the kind with the lower validation MAE; a segment below it stays plain without the
extra fit.  In the study (``docs/benchmarks/residual_fit.md``, 20 segments of the bunny, the
daffodil and the Cornell box, same size, seed and steps) every segment at >= 0.80 fitted better
as a residual (+0.4 to +2.8 dB), every one at <= 0.797 worse or the same (-2.7 to +0.1 dB): where
most of the lobe is occluded, the cosine lobe is no longer the part to subtract.  Visibility is not
enough on its own: the demo's flat ground (0.86; one normal, so nothing for the residual to take
away) fitted 7 % worse as a residual, and its images lost 1.2 dB (``residual_networks.md``)."""


def residual_choice(mode: str, transfer: np.ndarray, normals: np.ndarray, bands: int) -> tuple[bool, float]:
    """Whether a segment's networks may learn the residual from the unshadowed transfer, and the
    segment's mean visibility (the mean of its samples' DC coefficient over the unshadowed one's).

    ``mode``: "on", "off", or "auto" (:data:`RESIDUAL_VISIBILITY`; :func:`train_segment` then
    fits both kinds once and keeps the better); beyond 4 bands the unshadowed transfer is not a
    quadratic of the normal, so "auto" says no ("on" is refused by the spec)."""
    visibility = mean_visibility(transfer, bands)
    if mode == "on":
        return True, visibility
    if mode == "off" or bands > 4:
        return False, visibility
    return visibility >= RESIDUAL_VISIBILITY, visibility


def head_choice(mode: str, visibility: float, residual: bool) -> str:
    """A segment's output head (:data:`HEAD_MODES`): "log-dc" or "linear"; a residual segment's is linear."""
    if residual or mode == "linear":
        return "linear"
    return "log-dc" if mode == "log-dc" or visibility < LOSS_VISIBILITY else "linear"


def _with_head(arch, head: str):
    """``arch`` with output ``head`` where it is a frequency network (grids keep theirs)."""
    return dataclasses.replace(arch, head=head) if isinstance(arch, Architecture) and arch.head != head else arch


def _as_residual(arch, use: bool):
    """``arch`` as a residual network where ``use`` and it is a frequency network (grids are not)."""
    return dataclasses.replace(arch, residual=True) if use and isinstance(arch, Architecture) else arch


def shaded_psnr(pred, truth, lights: dict, n: int, albedo=DEFAULT_ALBEDO, exposure: float = 1.0) -> dict[str, float]:
    """Per env map, the PSNR (dB, capped at :data:`PSNR_CAP`) of the tone-mapped diffuse radiance
    ``max(0, a_c sum_k T_kc L_kc)`` of ``pred`` against ``truth`` over the samples.

    ``pred``, ``truth``: (M, n) direct transfer or (M, 4 n) "direct+rgb" (the total RGB transfer
    counts); ``lights``: name -> (n, 3) SH coefficients; ``albedo``: RGB.
    """
    albedo = np.asarray(albedo, dtype=np.float64).reshape(3)
    tp = total_transfer(np.asarray(pred, dtype=np.float64), n)
    tt = total_transfer(np.asarray(truth, dtype=np.float64), n)
    out = {}
    for name, light in lights.items():
        rp, rt = _radiance(tp, light, albedo), _radiance(tt, light, albedo)
        out[name] = _tonemapped_psnr(rp, rt, exposure)
    return out


def exposed_psnr(pred, truth, light, n: int, albedo=DEFAULT_ALBEDO) -> float:
    """:func:`shaded_psnr` under one light at the exposure that puts the median luminance of ``truth``'s
    radiance (of its lit samples, :data:`LIT_SHARE`) at :data:`prt.runtime.exposure.KEY`: the samples' error as a view they filled would show
    it, exposed for them (``prt-bench --exposure auto``).  A room lit through its windows is dark at
    exposure 1, so its error hardly counts in the absolute figure, while a view inside it is exposed
    5-20x brighter.  The median, not auto-exposure's log-average: area-uniform samples include the
    black ones no view shows much of (undersides, backs against walls, the insides of cupboards), and
    where a segment holds many of them the log-average fell so far that its lit samples saturated
    and its near-black ones decided the figure (the Duplex's largest segment, 34.5 dB at exposure 1:
    7.0 dB at its log-average's exposure).
    """
    albedo = np.asarray(albedo, dtype=np.float64).reshape(3)
    rp = _radiance(total_transfer(np.asarray(pred, dtype=np.float64), n), light, albedo)
    rt = _radiance(total_transfer(np.asarray(truth, dtype=np.float64), n), light, albedo)
    lum = rt @ np.asarray(LUMINANCE)
    lit = lum[lum > LIT_SHARE * (float(lum.max()) if len(lum) else 0.0)]
    median = float(np.median(lit)) if len(lit) else 0.0
    return _tonemapped_psnr(rp, rt, exposure_from_log_mean(math.log(median) if median > 0.0 else None))


LIT_SHARE = 1e-3
""":func:`exposed_psnr`'s median is over the samples brighter than this share of the brightest: a dim
room's segment whose samples are mostly black (undersides, voids) is exposed for its lit part, as a view
into the room would be, not left at exposure 1 (the Duplex house's segment of view 1's room had a median of
0 and was reported at 30.7 dB, its PSNR at exposure 1)."""


def _radiance(t: np.ndarray, light, albedo: np.ndarray) -> np.ndarray:
    """(M, 3) diffuse radiance ``max(0, a_c sum_k T_kc L_kc)`` of :func:`total_transfer`'s ``t``."""
    light = np.asarray(light, dtype=np.float64)
    r = t @ light if t.ndim == 2 else np.einsum("mkc,kc->mc", t, light)
    return np.maximum(r * albedo, 0.0)


def _tonemapped_psnr(rp: np.ndarray, rt: np.ndarray, exposure: float) -> float:
    a = tonemap(rp, exposure).astype(np.float64)
    b = tonemap(rt, exposure).astype(np.float64)
    mse = float(np.mean((a - b) ** 2)) if a.size else 0.0
    return PSNR_CAP if mse <= 10.0 ** (-PSNR_CAP / 10.0) else min(PSNR_CAP, float(-10.0 * np.log10(mse)))


def predict_numpy(arch, arrays: dict, points, normals) -> np.ndarray:
    """A fitted network's output from its arrays alone (frequency or grid encoding)."""
    evaluate = grid_evaluate if isinstance(arch, GridArchitecture) else freq_evaluate
    return evaluate(arrays, points, normals)


def weight_bytes(arch) -> int:
    """Stored bytes of a network: fp32 weights; a grid's tables in fp16 (as exported)."""
    return arch.bytes() if isinstance(arch, GridArchitecture) else arch.weight_count() * 4


def _cost(arch) -> tuple[int, int]:
    return arch.flops_per_fragment(), weight_bytes(arch)


def candidates(*ladders) -> list:
    """The sizes of every ladder, cheapest first: by FLOPs per fragment, then bytes (duplicates dropped)."""
    seen, out = set(), []
    for arch in (a for ladder in ladders for a in ladder):
        key = (type(arch).__name__, json.dumps(arch.as_dict(), sort_keys=True))
        if key not in seen:
            seen.add(key)
            out.append(arch)
    return sorted(out, key=_cost)


def search_cheapest(fit, archs, quality, target: float, log=print) -> tuple[object, list[dict], bool]:
    """The cheapest of ``archs`` (sorted cheapest first) whose ``quality(fit(arch))`` is >= ``target``.

    A bisection over the cost order: it assumes quality grows with cost, so it fits about
    ``log2(len(archs)) + 1`` sizes instead of all of them; of the sizes it fitted it keeps the
    cheapest that met the target (every fit is in the returned records, so a size that broke the
    assumption shows).  When none met it, the best quality fitted (the search then ends at the
    largest size).  Returns ``(chosen fit, records of the sizes tried in cost order, met)``.
    """
    if not archs:
        raise ValueError("search_cheapest: no sizes to choose from")
    results = {}
    lo, hi = 0, len(archs) - 1
    while lo <= hi:
        mid = (lo + hi) // 2
        result = fit(archs[mid])
        q = float(quality(result))
        results[mid] = (result, q)
        ok = q >= target
        flops, size = _cost(archs[mid])
        log(f"  {archs[mid].label():>12}: {q:.2f} dB, val MAE {result.val_mae:.5f}, {flops:,} FLOPs ({result.seconds:.1f} s)  {'meets' if ok else 'misses'}")
        if ok:
            hi = mid - 1
        else:
            lo = mid + 1
    met = [i for i, (_, q) in results.items() if q >= target]
    pick = min(met) if met else max(results, key=lambda i: results[i][1])
    tried = []
    for i in sorted(results):
        result, q = results[i]
        flops, size = _cost(archs[i])
        tried.append({"arch": archs[i].label(), "encoding": _encoding(archs[i]), "val_mae": result.val_mae, "psnr_db": round(q, 3),
                      "flops": flops, "bytes": size, "seconds": result.seconds})  # fmt: skip
    return results[pick][0], tried, bool(met)


def _encoding(arch) -> str:
    return "grid" if isinstance(arch, GridArchitecture) else "freq"


@dataclass
class SegmentJob:
    """What the fits of one build share (sent once to a cluster).  ``log`` None: lines come back."""

    spec: object  # prt.train.build.BuildSpec
    samples: dict
    valid: dict
    members: list
    archs: list
    fit_settings: FitSettings
    lights: dict
    progress: object  # bool, or a prt.train.progress.BuildProgress (local fits only)
    log: object = None
    vertex: object = None  # the "vertex" rule's prt.train.transport.vertex_estimate.VertexEstimate


def segment_task(job: SegmentJob, item) -> tuple[dict, list, list[str]]:
    """Fit one segment ``(seg, key, fits)``: a task.  Returns (record, new fits for the cache, log lines)."""
    seg, key, fits = item
    lines = []
    s = seg["id"]
    record = train_segment(job.spec, s, job.samples, job.valid, job.members[s], job.archs, job.fit_settings, job.lights, job.progress,
                           job.log or lines.append, fits, vertex=job.vertex)  # fmt: skip
    record["key"] = key
    return record, getattr(fits, "new", []), lines


def validation_split(s, valid, own_idx, seed):
    """Held-out samples of segment ``s``; if the validation set has too few, hold out 10 % of its own."""
    vsel = np.flatnonzero(valid["segment"] == s)
    if len(vsel) >= 32:
        return vsel, None
    rng = np.random.default_rng([seed, 0x5E6, s])
    n_hold = max(1, len(own_idx) // 10)
    held = rng.choice(own_idx, size=min(n_hold, max(len(own_idx) - 1, 1)), replace=False)
    return None, held


def spec_rule(spec) -> str:
    """The right-sizing rule a spec asks for (:data:`RULES`)."""
    if spec.fixed is not None:
        return "fixed"
    if getattr(spec, "vertex_margin", None) is not None:
        return "vertex"
    if spec.match is not None:
        return "match"
    return "target_db" if spec.target_db is not None else "target_mae"


def _albedo(spec) -> list[float]:
    albedo = spec.material.get("albedo", DEFAULT_ALBEDO) if isinstance(spec.material, dict) else DEFAULT_ALBEDO
    return [float(a) for a in albedo]


def train_segment(spec, s, samples, valid, member_idx, archs, fit_settings, lights, progress, log, fits=None, vertex=None) -> dict:
    """Fit segment ``s`` by the spec's rule; its training record (weights in ``arrays``, the choice in ``sizing``).

    ``vertex``: the per-vertex PRT estimate the "vertex" rule sizes against
    (:class:`prt.train.transport.vertex_estimate.VertexEstimate`); ``progress``: show each fit's
    steps (a :class:`prt.train.progress.BuildProgress` counts them into the build's display)."""
    own_idx = member_idx[samples["segment"][member_idx] == s]
    vsel, held = validation_split(s, valid, own_idx, spec.seed)
    if held is not None:
        train_idx = np.setdiff1d(member_idx, held)
        held_out = {k: samples[k][held] for k in ("points", "normals", "transfer", "face_index") if k in samples}
        note = f"validation set had {int((valid['segment'] == s).sum())} samples here; held out {len(held)} of its own"
    else:
        train_idx = member_idx
        held_out = {k: valid[k][vsel] for k in ("points", "normals", "transfer", "face_index") if k in valid}
        note = ""
    vp, vn, vt = held_out["points"], held_out["normals"], held_out["transfer"]
    p, n, t = samples["points"][train_idx], samples["normals"][train_idx], samples["transfer"][train_idx]
    bounds = np.array([p.min(axis=0), p.max(axis=0)])
    bounds = bounds + np.array([[-1.0], [1.0]]) * 0.01 * np.maximum(bounds[1] - bounds[0], 1e-3)
    base = {
        "id": s,
        "samples": int(len(own_idx)),
        "margin_samples": int(len(member_idx) - len(own_idx)),
        "validation_samples": int(len(vt)),
        "bounds": bounds.tolist(),
        "note": note,
    }
    rule = spec_rule(spec)
    n_coeffs = spec.bands * spec.bands
    albedo = _albedo(spec)

    def psnr_of(pred) -> dict[str, float]:
        return {k: round(v, 3) for k, v in shaded_psnr(pred, vt, lights, n_coeffs, albedo).items()}

    reference = spec.reference_architecture()
    if rule == "vertex":
        if vertex is None:
            raise ValueError("the 'vertex' sizing rule needs the per-vertex PRT estimate (a mesh scene)")
        v_psnr = psnr_of(vertex.predict(vp, vn, held_out["face_index"]))
        budget = vertex.weight_bytes * len(own_idx) / max(len(samples["points"]), 1)
    analytic = None
    if spec.analytic:
        pred = unshadowed_transfer(vn, spec.bands)
        if vt.shape[1] > n_coeffs:  # "direct+rgb": an analytic segment has no indirect light
            pred = np.concatenate([pred, np.zeros((len(pred), vt.shape[1] - n_coeffs), dtype=pred.dtype)], axis=1)
        mae = transfer_error(pred, vt, n_coeffs)
        analytic = {**base, "kind": "analytic", "val_mae": mae, "shaded": shaded_error(pred, vt, lights, n_coeffs), "tried": [], "flops_per_fragment": 0,
                    "weight_bytes": 0}  # fmt: skip
        a_psnr = psnr_of(pred)
        a_worst = a_psnr.get(SCENE_LIGHT, min(a_psnr.values(), default=PSNR_CAP))
        if rule == "target_db" and a_worst >= spec.target_db:
            log(f"segment {s}: analytic (unshadowed; shaded PSNR {a_worst:.2f} dB >= {spec.target_db} dB)")
            return {**analytic, "sizing": _sizing(rule, spec, "analytic", a_psnr, True, [],
                                                  f"unshadowed transfer already meets {spec.target_db} dB ({a_worst:.2f} dB)")}  # fmt: skip
        # A floor (the preset's absolute held-out PSNR) holds for the unshadowed transfer too: where vertex
        # PRT is poor (coarse CAD and BIM meshes) beating it says nothing of the segment's own error.
        under_floor = getattr(spec, "floor_db", None) is not None and a_worst < spec.floor_db
        if rule == "vertex" and _gain(a_psnr, v_psnr) >= spec.vertex_margin and not under_floor:
            log(f"segment {s}: analytic (unshadowed; {_gain(a_psnr, v_psnr):+.2f} dB over vertex PRT >= {spec.vertex_margin:+g} dB"
                f"{f', {a_worst:.2f} dB >= the floor {spec.floor_db:g} dB' if getattr(spec, 'floor_db', None) is not None else ''})")
            return {**analytic, "vertex": _vertex_record(v_psnr, budget, "error", _gain(a_psnr, v_psnr)),
                    "sizing": _sizing(rule, spec, "analytic", a_psnr, True, [], f"unshadowed transfer already {_gain(a_psnr, v_psnr):+.2f} dB "
                                      f"over vertex PRT", extra=_vertex_extra(v_psnr, budget, "error"))}  # fmt: skip
        if rule == "target_mae" and mae <= spec.target:
            log(f"segment {s}: analytic (unshadowed; validation MAE {mae:.5f} <= {spec.target})")
            return {**analytic, "sizing": _sizing(rule, spec, "analytic", a_psnr, True, [],
                                                  f"unshadowed transfer already meets the validation MAE target {spec.target} ({mae:.5f})")}  # fmt: skip

    log(f"segment {s}: {len(train_idx):,} training samples ({base['margin_samples']:,} margin), {len(vt):,} held out")
    mode = getattr(spec, "residual", "off")
    use, visibility = residual_choice(mode, t, n, spec.bands)
    base["loss"] = resolve_loss(fit_settings.loss, t, spec.bands)  # what fit_segment makes of "auto" on these samples
    scores, done, exposed = {}, {}, {}

    def fit(arch):
        if arch in done:  # fitted in this call already (the residual probe, then the sizing rule)
            return done[arch]
        cached = fits.get(arch) if fits is not None else None
        if cached is not None:
            log(f"  {arch.label():>12}: fitted before on this precompute (cached)")
            result = cached
        else:
            result = _fit(arch)
            if fits is not None:
                fits.put(result)
        pred = predict_numpy(arch, result.model.arrays(), vp, vn)
        scores[arch.label()] = psnr_of(pred)
        if SCENE_LIGHT in lights:
            exposed[arch.label()] = round(exposed_psnr(pred, vt, lights[SCENE_LIGHT], n_coeffs, albedo), 3)
        done[arch] = result
        return result

    def _fit(arch):
        bar = None
        if hasattr(progress, "fit_bar"):  # the build's one display (prt.train.progress)
            bar = progress.fit_bar(s, arch)
        elif progress:
            bar = tqdm(desc=f"  seg {s} {arch.label()}", unit="step", leave=False, mininterval=0.5)

        def on_epoch(step, total_steps, train_l1, val_mae):
            if bar is not None:
                bar.total = total_steps
                bar.update(step - bar.n)
                bar.set_postfix(val_mae=f"{val_mae:.5f}", refresh=False)

        try:
            if isinstance(arch, GridArchitecture):
                return fit_grid_segment(p, n, t, vp, vn, vt, arch, bounds, fit_settings, lights=lights, progress=on_epoch)
            return fit_segment(p, n, t, vp, vn, vt, arch, bounds, fit_settings, lights=lights, progress=on_epoch)
        finally:
            if bar is not None:
                bar.close()

    def worst(label):  # the target's measure: the scene's lighting (every map's when it is absent)
        psnr = scores[label]
        return psnr[SCENE_LIGHT] if SCENE_LIGHT in psnr else min(psnr.values(), default=PSNR_CAP)

    base["residual"] = {"mode": mode, "mean_visibility": round(visibility, 4)}
    if rule == "vertex":  # the sizes within the segment's share of vertex PRT's bytes (the smallest at least)
        allowed = [a for a in archs if weight_bytes(a) <= budget] or archs[:1]
        cut = len(allowed) < len(archs)
    probe = reference if reference is not None else next((a for a in archs if isinstance(a, Architecture)), None)
    if rule == "vertex":  # the bisection's first size: fitted both ways, the kind kept continues without refitting it
        probe = allowed[(len(allowed) - 1) // 2]
    if mode == "auto" and use and probe is not None:  # both kinds at the probe size: the lower validation MAE decides
        plain, residual = fit(probe), fit(_as_residual(probe, True))
        use = residual.val_mae < plain.val_mae
        base["residual"]["val_mae"] = {"plain": plain.val_mae, "residual": residual.val_mae, "size": probe.label()}
        log(f"segment {s}: mean visibility {visibility:.3f}; validation MAE {plain.val_mae:.5f} plain, {residual.val_mae:.5f} residual: "
            f"{'residual' if use else 'plain'} networks")  # fmt: skip
    elif use:
        log(f"segment {s}: mean visibility {visibility:.3f}: the networks learn the residual from the unshadowed transfer")
    base["residual"]["used"] = bool(use and probe is not None)
    if use:
        archs = [_as_residual(a, True) for a in archs]
        reference = None if reference is None else _as_residual(reference, True)
        if rule == "vertex":
            allowed = [_as_residual(a, True) for a in allowed]
    base["head"] = head_choice(getattr(spec, "head", "linear"), visibility, base["residual"]["used"])
    if base["head"] != "linear":
        archs = [_with_head(a, base["head"]) for a in archs]
        reference = None if reference is None else _with_head(reference, base["head"])
        if rule == "vertex":
            allowed = [_with_head(a, base["head"]) for a in allowed]

    vertex_record = None
    if rule == "vertex":
        result, tried, met = search_cheapest(fit, allowed, lambda r: _gain(scores[r.arch.label()], v_psnr), spec.vertex_margin,
                                             log=_gain_log(log))  # fmt: skip
        for record in tried:  # search_cheapest's quality was the gain
            record["gain_db"], record["psnr_db"] = record["psnr_db"], round(worst(record["arch"]), 3)
        bar = spec.vertex_margin
        chosen = result.arch
        gain = _gain(scores[chosen.label()], v_psnr)
        ended = "error" if met else ("bytes" if cut else "ladder")
        why = {"error": f"cheapest of {len(allowed)} sizes within {budget:,.0f} bytes (the segment's share of vertex PRT's) "
                        f"{gain:+.2f} dB over vertex PRT (margin {spec.vertex_margin:+g} dB)",
               "bytes": f"vertex PRT's bytes reached: the largest size within {budget:,.0f} bytes is {gain:+.2f} dB over vertex PRT "
                        f"(margin {spec.vertex_margin:+g} dB)",
               "ladder": f"the largest size is {gain:+.2f} dB over vertex PRT (margin {spec.vertex_margin:+g} dB)"}[ended]
        vertex_record = _vertex_record(v_psnr, budget, ended, gain)
        if not met and analytic is not None and _gain(a_psnr, v_psnr) >= gain:
            log(f"segment {s}: analytic (unshadowed transfer is as accurate as the best network tried)")
            return {**analytic, "tried": tried, "vertex": _vertex_record(v_psnr, budget, ended, _gain(a_psnr, v_psnr)),
                    "sizing": _sizing(rule, spec, "analytic", a_psnr, False, tried, "no network reached the margin and the unshadowed "
                                      "transfer is as accurate", extra=_vertex_extra(v_psnr, budget, ended))}  # fmt: skip
    elif rule == "target_db":
        result, tried, met = search_cheapest(fit, archs, lambda r: worst(r.arch.label()), spec.target_db, log=log)
        bar = spec.target_db
        chosen = result.arch
        why = (f"cheapest of {len(archs)} candidates ({'/'.join(sorted({_encoding(a) for a in archs}))}, by FLOPs per fragment) meeting "
               f"{spec.target_db} dB under {SCENE_LIGHT}: {worst(chosen.label()):.2f} dB at {chosen.flops_per_fragment():,} FLOPs") if met else (
               f"no candidate met {spec.target_db} dB; the most accurate tried ({worst(chosen.label()):.2f} dB)")  # fmt: skip
        if not met and analytic is not None and a_worst >= worst(chosen.label()):
            log(f"segment {s}: analytic (unshadowed transfer is as accurate as the best network tried)")
            return {**analytic, "tried": tried, "sizing": _sizing(rule, spec, "analytic", a_psnr, False, tried,
                                                                  "no network met the target and the unshadowed transfer is as accurate")}  # fmt: skip
    elif reference is not None:
        result, tried, bar = right_size_matching(fit, reference, archs, tolerance=spec.match_tolerance, log=log)
        if analytic is not None and analytic["val_mae"] <= min(bar, spec.target):
            log(f"segment {s}: analytic (unshadowed; validation MAE {analytic['val_mae']:.5f} <= the bar {bar:.5f})")
            return {**analytic, "tried": tried, "bar": bar,
                    "sizing": _sizing(rule, spec, "analytic", a_psnr, True, tried, f"unshadowed transfer within the bar {bar:.5f} of {reference.label()}")}  # fmt: skip
        met = result.val_mae <= bar
        why = (f"cheapest size within {spec.match_tolerance:.0%} of {reference.label()}'s validation MAE (bar {bar:.5f}): "
               f"{result.val_mae:.5f} at {result.arch.flops_per_fragment():,} FLOPs")  # fmt: skip
    else:
        result, tried = right_size(fit, archs, target=spec.target, log=log)
        met, bar = result.val_mae <= spec.target, spec.target
        if rule == "fixed":
            # analytic only where as accurate as the network asked for: a segment whose mean MAE passes
            # the plain target may still hold a shadow (Spot: 2.8 dB, docs/benchmarks/many_networks.md)
            cap = min(result.val_mae * (1.0 + spec.match_tolerance), spec.target)
            if analytic is not None and analytic["val_mae"] <= cap:
                log(f"segment {s}: analytic (unshadowed; validation MAE {analytic['val_mae']:.5f} <= {cap:.5f}, the fixed network's)")
                return {**analytic, "tried": tried, "sizing": _sizing(rule, spec, "analytic", a_psnr, True, tried,
                        f"unshadowed transfer as accurate as the fixed {result.arch.label()} network (MAE {analytic['val_mae']:.5f} <= {cap:.5f})")}  # fmt: skip
            why = f"fixed size {result.arch.label()} (--hidden/--layers)"
        else:
            why = (f"first size, cheapest first, meeting validation MAE {spec.target}: {result.val_mae:.5f}" if met else
                   f"no size met validation MAE {spec.target}; the most accurate tried ({result.val_mae:.5f})")  # fmt: skip
    if rule not in ("target_db", "vertex"):
        for record in tried:
            record["psnr_db"] = round(worst(record["arch"]), 3) if record["arch"] in scores else None
    arch = result.arch
    return {
        **base,
        "kind": "network",
        "arch": arch.as_dict(),
        "arch_label": arch.label(),
        "val_mae": result.val_mae,
        "shaded": result.shaded,
        "epochs": result.epochs,
        "steps": result.steps,
        "train_s": result.seconds,
        "tried": tried,
        "met_target": met,
        "bar": bar,
        "flops_per_fragment": arch.flops_per_fragment(),
        "weight_bytes": weight_bytes(arch),
        "arrays": result.model.arrays(),
        "history": result.history,
        **({"vertex": vertex_record} if vertex_record is not None else {}),
        "sizing": _sizing(rule, spec, arch.label(), scores[arch.label()], met, tried, why, encoding=_encoding(arch),
                          extra={**(_vertex_extra(v_psnr, budget, vertex_record["ended"]) if vertex_record else {}),
                                 **({"exposed_psnr_db": exposed[arch.label()]} if arch.label() in exposed else {})}),
    }


def _gain(psnr: dict, vertex_psnr: dict) -> float:
    """dB over per-vertex PRT: the smallest difference over the env maps both were measured under."""
    return min((psnr[k] - vertex_psnr[k] for k in vertex_psnr if k in psnr), default=0.0)


def _gain_log(log):
    """:func:`search_cheapest`'s lines, its quality being dB over vertex PRT."""
    return lambda line: log(line.replace(" dB, val MAE", " dB over vertex PRT, val MAE", 1))


def _vertex_record(v_psnr: dict, budget: float, ended: str, gain: float) -> dict:
    """The training record's ``vertex``: the estimate's held-out PSNR, the byte share, where sizing ended, the gain."""
    return {"psnr_db": v_psnr, "byte_budget": int(budget), "ended": ended, "gain_db": round(float(gain), 3)}


def _vertex_extra(v_psnr: dict, budget: float, ended: str) -> dict:
    return {"vertex_psnr_db": v_psnr, "byte_budget": int(budget), "ended": ended}


def _sizing(rule, spec, chosen, psnr, met, tried, reason, encoding=None, extra=None) -> dict:
    """The manifest's ``sizing`` of a segment: what was chosen, by which rule, and why (``extra``: the
    "vertex" rule's estimate, byte share and where it ended)."""
    target = {"target_db": spec.target_db, "target_mae": spec.target, "match": spec.match, "fixed": spec.fixed,
              "vertex": getattr(spec, "vertex_margin", None)}[rule]  # fmt: skip
    out = {"rule": rule, "target": target, "chosen": chosen, **({"encoding": encoding} if encoding else {}),
           "psnr_db": psnr, "met": bool(met), "reason": reason, **(extra or {}),
           "tried": [{k: r[k] for k in ("arch", "encoding", "flops", "bytes", "val_mae", "psnr_db", "gain_db") if k in r} for r in tried]}  # fmt: skip
    return out


def pooled_psnr(psnr_by_segment: list[tuple[int, float]]) -> float:
    """The PSNR of all held-out samples together from each segment's ``(samples, PSNR)``: the pooled
    MSE is the sample-weighted mean of the segments' (capped at :data:`PSNR_CAP`)."""
    count = sum(n for n, _ in psnr_by_segment)
    if count <= 0:
        return PSNR_CAP
    mse = sum(n * 10.0 ** (-p / 10.0) for n, p in psnr_by_segment) / count
    return PSNR_CAP if mse <= 10.0 ** (-PSNR_CAP / 10.0) else min(PSNR_CAP, float(-10.0 * np.log10(mse)))


def scene_sizing(records: list[dict], vertex_bytes: int, margin: float) -> dict:
    """The "vertex" rule's scene summary (``build.json``'s ``sizing``): pooled held-out PSNR of the
    networks and of the vertex PRT estimate per env map, their bytes, and where sizing ended: "error"
    when every segment reached the margin, else "bytes" when a segment stopped at its share of
    vertex PRT's bytes, else "ladder" (the largest size missed)."""
    rows = [r for r in records if "vertex" in r]
    lights = sorted({k for r in rows for k in r["vertex"]["psnr_db"]})
    network = {k: round(pooled_psnr([(r["validation_samples"], r["sizing"]["psnr_db"][k]) for r in rows]), 3) for k in lights}
    vertex = {k: round(pooled_psnr([(r["validation_samples"], r["vertex"]["psnr_db"][k]) for r in rows]), 3) for k in lights}
    endings = [r["vertex"]["ended"] for r in rows]
    ended = "error" if all(e == "error" for e in endings) else ("bytes" if "bytes" in endings else "ladder")
    return {"rule": "vertex", "margin_db": margin, "network_psnr_db": network, "vertex_psnr_db": vertex,
            "gain_db": round(min((network[k] - vertex[k] for k in lights), default=0.0), 3),
            "network_bytes": int(sum(r["weight_bytes"] for r in records)), "vertex_bytes": int(vertex_bytes),
            "held_out_samples": int(sum(r["validation_samples"] for r in rows)), "ended": ended,
            "segments_ended": {e: endings.count(e) for e in ENDINGS if e in endings}}  # fmt: skip
