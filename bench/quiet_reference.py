"""A reference quiet enough to judge: its rays, direct and bounce, raised until its noise clears what it measures.

The reference's noise is measured, not assumed: at view 0 it is traced twice, with independent
seeds, and the two-seed PSNR (:func:`prt.bench.reference.noise_psnr`) is its noise.  A scene
with bounces splits it: the first seed's direct transfer with the second seed's indirect part
differs from the first image by the bounce noise alone, and the rest is the direct part's
(variances add).  What it has to clear is the best configuration the benchmark judges: a pilot
renders view 0 with every configuration (the fp32 networks, each vertex and texture baseline)
and takes the best PSNR per material.

:func:`quiet_plan` then picks the cheapest doubling of the direct rays (``--ref-rays``, up to
``--ref-rays-max``) and of the bounce rays per pixel (``--ref-hit-rays``, up to
``--ref-hit-rays-max``) whose predicted noise (Monte Carlo variance falls as 1/rays) clears
the best PSNR by :data:`REFERENCE_MARGIN_DB`, with the time the whole reference would take,
predicted from view 0's measured seconds, within ``--ref-budget``.  View 0 is traced again with
the rays chosen and the noise measured again, until the margin holds or nothing more is
allowed; the other views use the rays settled on.  When the margin cannot be reached the
verdict says why: ``caps`` (the ray limits) or ``budget`` (the time budget), and what the
cheapest plan that would reach it needs.

The higher bounces' independent samples (:func:`prt.bench.bounce_reference.higher_bounce_samples`)
are the same for both seeds, so their error is not part of this noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prt.bench.bounce_reference import cached_indirect, direct_rgb
from prt.bench.exposure import auto_exposure, luminance
from prt.bench.leak import leak_figures
from prt.bench.reference import REFERENCE_MARGIN_DB, View, cached_transfer, noise_psnr, reference_images, reference_linear
from prt.runtime.shading import tonemap

__all__ = ["MAX_DOUBLINGS", "quiet_plan", "ReferenceSource", "reference_views"]

MAX_DOUBLINGS = 12  # of either ray count in one plan: 4096x (a start of 1 ray to 4096 and more)


def _mse(db: float) -> float:
    return 10.0 ** (-float(db) / 10.0)


def _db(mse: float) -> float:
    return float(-10.0 * math.log10(mse)) if mse > 0 else math.inf


def quiet_plan(noise: dict, bounce_noise: dict | None, best: dict, rays: int, hit_rays: int, *, rays_max: int, hit_rays_max: int,
               seconds_direct: float | None, seconds_bounce: float | None, views: int, budget: float | None,
               margin: float = REFERENCE_MARGIN_DB) -> dict:  # fmt: skip
    """The rays at which the reference's noise should clear every material's best PSNR by ``margin``.

    Parameters
    ----------
    noise : {material: dB}
        Two-seed PSNR of the whole reference.
    bounce_noise : {material: dB} or None
        Two-seed PSNR of its indirect part alone (None: no bounces); the direct part's is what
        remains of ``noise`` (variances add).
    best : {material: dB}
        The best PSNR judged (the pilot's).
    rays, hit_rays : int
        Now: direct rays per pixel, bounce rays per pixel.
    rays_max, hit_rays_max : int
        Caps (never below the rays now).
    seconds_direct, seconds_bounce : float or None
        One view's reference time now, direct and bounce (None: unknown, taken as free).
    views : int
        Views the reference traces (the budget covers all of them).
    budget : float or None
        Seconds the whole reference may take (None: no limit).

    Returns
    -------
    dict
        ``rays``, ``hit_rays`` (to use next; the current ones when nothing helps), ``met`` (the
        plan is predicted to clear the margin), ``reason`` (None, ``"caps"`` or ``"budget"``),
        ``predicted_noise_psnr`` ({material: dB}), ``seconds`` (predicted for all views, or None),
        ``needs``: where not met, the cheapest plan that would meet it ignoring the limits that stopped it
        (``rays``, ``hit_rays``, ``seconds``), or None.
    """
    materials = [m for m in noise if m in best]
    total = {m: _mse(noise[m]) for m in materials}
    bounce = {m: min(_mse(bounce_noise[m]), total[m]) if bounce_noise else 0.0 for m in materials}
    direct = {m: total[m] - bounce[m] for m in materials}
    target = {m: _mse(best[m] + margin) for m in materials}
    known = seconds_direct is not None and seconds_bounce is not None
    a_max = MAX_DOUBLINGS
    b_max = MAX_DOUBLINGS if bounce_noise else 0

    def predict(a: int, b: int) -> dict:
        return {m: direct[m] / 2**a + bounce[m] / 2**b for m in materials}

    def seconds(a: int, b: int) -> float | None:
        return views * (seconds_direct * 2**a + seconds_bounce * 2**b) if known else None

    plans = []
    for a in range(a_max + 1):
        for b in range(b_max + 1):
            mse = predict(a, b)
            worst = max((mse[m] / target[m] for m in materials), default=0.0)
            within_caps = rays * 2**a <= max(rays_max, rays) and hit_rays * 2**b <= max(hit_rays_max, hit_rays)
            cost = seconds(a, b)
            plans.append({"a": a, "b": b, "worst": worst, "caps": within_caps, "cost": cost if cost is not None else float(a + b),
                          "budget": budget is None or cost is None or cost <= budget or (a, b) == (0, 0)})  # fmt: skip
    meeting = sorted((p for p in plans if p["worst"] <= 1.0), key=lambda p: (p["cost"], p["a"] + p["b"]))
    allowed = [p for p in meeting if p["caps"] and p["budget"]]
    if allowed:
        chosen, reason, needs = allowed[0], None, None
    else:
        usable = [p for p in plans if p["caps"] and p["budget"]]
        chosen = min(usable, key=lambda p: (p["worst"], p["cost"]))
        within_caps = [p for p in meeting if p["caps"]]
        reason = "budget" if within_caps else "caps"
        cheapest = (within_caps or meeting or [None])[0]
        needs = None if cheapest is None else {"rays": rays * 2 ** cheapest["a"], "hit_rays": hit_rays * 2 ** cheapest["b"],
                                               "seconds": None if not known else round(cheapest["cost"], 1)}  # fmt: skip
    mse = predict(chosen["a"], chosen["b"])
    return {"rays": rays * 2 ** chosen["a"], "hit_rays": hit_rays * 2 ** chosen["b"], "met": chosen["worst"] <= 1.0, "reason": reason,
            "predicted_noise_psnr": {m: round(_db(mse[m]), 2) for m in materials},
            "seconds": None if not known else round(seconds(chosen["a"], chosen["b"]), 1), "needs": needs}  # fmt: skip


@dataclass
class ReferenceSource:
    """What the reference traces: direct transfer, and with ``bounces`` the indirect part (cached by content)."""

    geometry: object
    tracer: object
    cache: object
    geometry_id: str
    bounces: int = 0
    bounce_albedo: object = None  # (F, 3)
    higher: object = None  # prt.bench.bounce_reference.higher_bounce_samples
    hit_transfer_rays: int = 128
    executor: object = None

    def trace(self, tag: str, points, normals, rays: int, hit_rays: int, seed: int) -> dict:
        """``direct`` (M, 16), ``indirect`` (M, 16, 3) or None, and ``seconds_direct``, ``seconds_bounce``
        (what each took, None when unknown) and ``spent`` (computed now; 0 when all was cached)."""
        cost_d, cost_b = {}, {}
        direct, spent = cached_transfer(self.cache, tag, self.geometry, self.tracer, points, normals, rays, seed, self.geometry_id,
                                        executor=self.executor, cost=cost_d)  # fmt: skip
        indirect, seconds_b = None, 0.0
        if self.bounces > 0:
            indirect, more = cached_indirect(self.cache, tag, self.geometry, self.tracer, points, normals, self.bounce_albedo, self.bounces,
                                             higher=self.higher, seed=seed, geometry_id=self.geometry_id, hit_rays=hit_rays,
                                             rays=self.hit_transfer_rays, cost=cost_b)  # fmt: skip
            spent += more
            seconds_b = cost_b.get("seconds")
        return {"direct": direct, "indirect": indirect, "seconds_direct": cost_d.get("seconds"), "seconds_bounce": seconds_b, "spent": spent}

    @staticmethod
    def combine(direct, indirect):
        """The networks' layout: direct (16), or direct + indirect RGB (64)."""
        return direct if indirect is None else direct_rgb(direct, indirect)


def reference_views(source: ReferenceSource, renderer, cameras, size: int, materials: dict, settings, pilot, entry: dict, flops, log) -> list:
    """The views at ``size``: G-buffers and reference images, with rays raised at view 0 (module docstring).

    Parameters
    ----------
    renderer : prt.runtime.renderer.Renderer
        Its G-buffer defines the pixels.
    pilot : callable
        ``pilot(references, covered, exposure) -> {material: best PSNR}`` of view 0's configurations against
        ``references`` (tone-mapped images per material, at ``exposure`` {material: e}); called with the renderer at view 0.
    entry : dict
        The scene's ``reference`` record: ``noise_psnr``, ``rays_by_size``, ``hit_rays_by_size``,
        ``plan``, ``leak`` (the second seed's :func:`prt.bench.leak.leak_figures` against the first at
        view 0) and (with bounces) ``interreflection.gi_off_psnr`` are filled per size.  Every view's
        images are tone-mapped at ``settings.exposure``: a number, or ``"auto"`` (the reference
        frame's :func:`prt.bench.exposure.auto_exposure`, per material).
    flops : callable
        ``flops(segment image) -> float`` for the View.
    """
    resolution = f"{size}x{size}"
    seed, rays, hit_rays = settings.seed, settings.ref_rays, settings.ref_hit_rays
    mode = getattr(settings, "exposure", 1.0)  # "auto" (prt.bench.exposure) or a fixed exposure
    views, computed, plan = [], 0.0, None
    for v, camera in enumerate(cameras):
        renderer.set_camera_object(camera)
        gbuffer = renderer.gbuffer_image()
        covered = gbuffer.covered
        points, normals = gbuffer.position[covered], gbuffer.normal[covered]
        tag = f"view{v:03d}-{resolution}"
        for _ in range(2 * MAX_DOUBLINGS + 1):  # view 0: until the plan keeps the rays (each round doubles at least one count)
            first = source.trace(tag, points, normals, rays, hit_rays, seed)
            computed += first["spent"]
            linear = reference_linear(source.combine(first["direct"], first["indirect"]), gbuffer, camera.eye, renderer.lighting, materials)
            key = {m: auto_exposure(image, covered) for m, image in linear.items()}  # the leak figure's key, and --exposure auto's
            exposure = key if mode == "auto" else {m: float(mode) for m in linear}
            references = {m: tonemap(image, exposure[m]) for m, image in linear.items()}
            if v != 0:
                break
            second = source.trace(tag, points, normals, rays, hit_rays, seed + 1)
            computed += second["spent"]
            other_linear = reference_linear(source.combine(second["direct"], second["indirect"]), gbuffer, camera.eye, renderer.lighting, materials)
            other = {m: tonemap(image, exposure[m]) for m, image in other_linear.items()}
            noise = entry["noise_psnr"][resolution] = noise_psnr(other, references, covered)
            entry.setdefault("leak", {})[resolution] = {m: leak_figures(other_linear[m], luminance(linear[m]), key[m], covered) for m in linear}
            bounce_noise = None
            if source.bounces > 0:
                mixed = reference_images(source.combine(first["direct"], second["indirect"]), gbuffer, camera.eye, renderer.lighting, materials, exposure)
                bounce_noise = entry.setdefault("bounce_noise_psnr", {})[resolution] = noise_psnr(mixed, references, covered)
                direct_only = reference_images(first["direct"], gbuffer, camera.eye, renderer.lighting, materials, exposure)
                entry["interreflection"]["gi_off_psnr"][resolution] = noise_psnr(direct_only, references, covered)
            renderer.set_camera_object(camera)
            best = pilot(references, covered, exposure)
            plan = quiet_plan(noise, bounce_noise, best, rays, hit_rays, rays_max=settings.ref_rays_max, hit_rays_max=settings.ref_hit_rays_max,
                              seconds_direct=first["seconds_direct"], seconds_bounce=first["seconds_bounce"], views=len(cameras),
                              budget=settings.ref_budget)  # fmt: skip
            plan.update(pilot_psnr={m: round(float(db), 2) for m, db in best.items()}, noise_psnr=noise, bounce_noise_psnr=bounce_noise)
            if (plan["rays"], plan["hit_rays"]) == (rays, hit_rays):
                break
            log(f"  reference {resolution}: noise PSNR {noise} at {rays} rays x {hit_rays} bounce rays is within "
                f"{REFERENCE_MARGIN_DB:g} dB of the pilot {plan['pilot_psnr']}; {plan['rays']} x {plan['hit_rays']}")  # fmt: skip
            rays, hit_rays = plan["rays"], plan["hit_rays"]
            renderer.set_camera_object(camera)
        views.append(View(camera, gbuffer, references, flops(gbuffer.segment), exposure,
                          {m: luminance(image).astype(np.float32) for m, image in linear.items()}, key))  # fmt: skip
    entry["rays_by_size"][resolution] = rays
    entry.setdefault("hit_rays_by_size", {})[resolution] = hit_rays if source.bounces > 0 else None
    entry.setdefault("plan", {})[resolution] = plan
    log(f"  reference {resolution}: {len(views)} views x {rays} rays{f' x {hit_rays} bounce rays' if source.bounces else ''} "
        f"({computed:.1f} s computed, rest cached); noise PSNR {entry['noise_psnr'][resolution]}")  # fmt: skip
    if plan is not None and not plan["met"]:
        log(f"  reference {resolution}: cannot reach {REFERENCE_MARGIN_DB:g} dB above the pilot {plan['pilot_psnr']} "
            f"({plan['reason']}; it would need {plan['needs']})")  # fmt: skip
    return views
