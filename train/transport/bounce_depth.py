"""How many bounces: the truncation error of stopping interreflection after N bounces.

The bounce stage (:mod:`prt.train.transport.interreflection`) gives the terms ``T_1, T_2, ...`` of the
held-out (validation) samples.  Stopping after N bounces drops ``T_{N+1} + ...``; what that
costs is measured the way a render is judged, on the shaded radiance of the samples

    L_N(p)_c = max(0, a_c(p) * sum_k (T_0 + T_1 + ... + T_N)(p)_{k,c} * light_{k,c})

(``a``: the receiving surface's diffuse albedo, ``light``: an env map's SH coefficients, (n, 3))
against the sum of every measured term (``reference_bounces`` of them):

- ``rel_mae``: mean |L_N - L_ref| / mean L_ref over samples and channels (linear radiance);
- ``psnr``: PSNR of the tone-mapped values (:func:`prt.runtime.shading.tonemap`, ``exposure``,
  values in [0, 1]; the PSNR ``prt-bench`` reports over pixels, here over samples, capped at
  :data:`PSNR_CAP` dB).

:func:`truncation_errors` is the fast path (cumulative sums, one einsum per light);
``tests/test_bounce_depth.py`` checks it against a per-sample loop.  :func:`choose_bounces`
keeps the smallest N whose PSNR under every light is at least a threshold (``prt-train
--bounces auto``, :data:`AUTO_PSNR`).
"""

from __future__ import annotations

import numpy as np

from ...runtime.shading import tonemap

__all__ = ["PSNR_CAP", "AUTO_PSNR", "AUTO_MAX_BOUNCES", "shaded_radiance", "truncation_errors", "choose_bounces", "auto_bounces"]

PSNR_CAP = 100.0  # the same cap as prt-bench's metrics (identical values)
# ``--bounces auto``: the smallest N whose truncation PSNR is at least this under every lighting.
AUTO_PSNR = 50.0
# ``--bounces auto`` measures this many terms, their sum being the reference (the rays are traced
# once; each term is a sparse product, a few % of the tracing): the spec's limit.
AUTO_MAX_BOUNCES = 16


def _psnr(mse: float) -> float:
    return PSNR_CAP if mse <= 10.0 ** (-PSNR_CAP / 10.0) else float(-10.0 * np.log10(mse))


def shaded_radiance(transfer, albedo, light) -> np.ndarray:
    """(V, 3) diffuse radiance ``max(0, a_c * sum_k T_{k,c} light_{k,c})`` of RGB transfer (V, n, 3)."""
    transfer = np.asarray(transfer, dtype=np.float64)
    return np.maximum(np.asarray(albedo, dtype=np.float64) * np.einsum("vkc,kc->vc", transfer, np.asarray(light, dtype=np.float64)), 0.0)


def truncation_errors(direct, terms, albedo, lights: dict, exposure: float = 1.0) -> dict:
    """The error of stopping after N = 0 .. K-1 bounces against the sum of all K measured terms.

    Parameters
    ----------
    direct : (V, n) float
        Direct transfer of the samples.
    terms : sequence of K arrays (V, n, 3)
        ``T_1 .. T_K`` of the same samples.
    albedo : (V, 3) float
        Diffuse albedo of the receiving surface at each sample.
    lights : {name: (n, 3) SH coefficients}
    exposure : float
        Of the tone map (``prt-bench`` uses 1).

    Returns
    -------
    dict
        ``reference_bounces`` K, and per light name ``{"rel_mae": [K values], "psnr": [K values],
        "mean_radiance": mean L_ref}``, index N = bounces kept.
    """
    direct = np.asarray(direct, dtype=np.float64)
    partial = [np.repeat(direct[:, :, None], 3, axis=2)]
    for term in terms:
        partial.append(partial[-1] + np.asarray(term, dtype=np.float64))
    out = {"reference_bounces": len(terms)}
    for name, light in lights.items():
        radiance = [shaded_radiance(t, albedo, light) for t in partial]
        ref, ref_tm = radiance[-1], tonemap(radiance[-1], exposure).astype(np.float64)
        scale = max(float(ref.mean()), 1e-30)
        out[name] = {
            "rel_mae": [float(np.abs(r - ref).mean() / scale) for r in radiance[:-1]],
            "psnr": [_psnr(float(((tonemap(r, exposure) - ref_tm) ** 2).mean())) for r in radiance[:-1]],
            "mean_radiance": float(ref.mean()),
        }
    return out


def choose_bounces(errors: dict, threshold: float = AUTO_PSNR) -> int:
    """The smallest N whose truncation PSNR is >= ``threshold`` under every light of ``errors``
    (:func:`truncation_errors`); the largest measured N (K - 1) if none is."""
    count = int(errors["reference_bounces"])
    names = [k for k in errors if k != "reference_bounces"]
    for n in range(count):
        if all(errors[k]["psnr"][n] >= threshold for k in names):
            return n
    return max(count - 1, 0)


def auto_bounces(geometry, folder, train: dict, valid: dict, albedos: dict, lights: dict, *, threshold: float = AUTO_PSNR,
                 max_bounces: int = AUTO_MAX_BOUNCES, log=print, **trace) -> tuple[int, dict]:  # fmt: skip
    """``prt-train --bounces auto``: the bounce count of a build, measured on its validation samples.

    Traces the bounce rays once (:func:`prt.train.transport.interreflection.trace_stage` with ``trace``'s
    settings: the same chunk store :func:`~prt.train.transport.interreflection.bounce_stage` then reads),
    computes ``T_1 .. T_K`` (K = ``max_bounces``) of the validation samples, and keeps the smallest N
    whose truncation PSNR is >= ``threshold`` under every light (receivers: each object's diffuse
    albedo from ``albedos``, as the bounces use it).  Returns N and the record of what was
    measured (the manifest's and ``build.json``'s ``interreflection.auto``).
    """
    from .interreflection import bounce_terms, trace_stage

    names = list(geometry.object_names)
    per_object = np.asarray([albedos[n] for n in names], dtype=np.float64)
    found = trace_stage(geometry.mesh, folder, train, valid, log=log, **trace)
    terms = [v for _, _, v in bounce_terms(found, per_object[geometry.object_ids], train["transfer"], max_bounces)]
    errors = truncation_errors(valid["transfer"], terms, per_object[np.asarray(valid["object_ids"])], lights)
    count = choose_bounces(errors, threshold)
    lit = [k for k in errors if k != "reference_bounces"]
    record = {"threshold_psnr": float(threshold), "reference_bounces": int(max_bounces), "validation_samples": int(len(valid["points"])),
              "psnr": {k: [round(x, 2) for x in errors[k]["psnr"]] for k in lit},
              "rel_mae": {k: [round(x, 6) for x in errors[k]["rel_mae"]] for k in lit}}  # fmt: skip
    worst = min(errors[k]["psnr"][count] for k in lit)
    log(f"bounces auto: {count} (truncation PSNR >= {threshold:g} dB against {max_bounces} bounces under {', '.join(lit)}: worst {worst:.1f} dB)")
    return count, record
