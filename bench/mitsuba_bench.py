"""``prt-bench --reference mitsuba``: every configuration and our reference against Mitsuba 3, side by side.

For each scene and size, ``--mitsuba-views`` views spread over the orbit (view 0 first) are path
traced by Mitsuba 3 (:mod:`prt.bench.mitsuba_reference`: the scene as built, ``max_depth`` = 2 +
the build's bounces, ``--mitsuba-spp`` paths per pixel in two independent halves) and compared
(:mod:`prt.bench.mitsuba_compare`) with, diffuse, each pixel shaded with its object's albedo:

- our reference (the rays it settled on, two seeds: its own noise);
- the fp32 networks of the ONNX backend (and of the GLSL backend when measured);
- each vertex baseline (direct, and with the build's bounces) and each texture baseline;
- the probe grids (``--backends probes``: ``probes equal-bytes``, ``probes engine``).

The views are the benchmark's (the orbit, or ``--cameras``'); with ``--exposure auto`` every
image of a view (Mitsuba's included) is scaled by that view's diffuse exposure before the
tone-mapped PSNR, as the benchmark's own images are.

The scene entry's ``mitsuba`` record: ``variant``, ``libllvm``, ``mitsuba`` (version), ``spp``,
``max_depth``, ``views`` (orbit indices), ``albedos`` ({object: RGB}), ``envmap`` (the band-limited
map: ``height``, ``min_radiance``, ``clamped``, ``clamp_share``: the energy a map clamped at 0
would add, per channel, ``negative_part``: the negative radiance rendered apart and subtracted
(:func:`prt.bench.mitsuba_reference.envmap_parts`), ``lookup_error``), ``seconds`` (Mitsuba's render time, 0 when
cached), and per size ``sizes[WxH]``: ``pixels`` (compared, all views), ``mitsuba_noise_psnr``,
``rows`` (per configuration: ``label``, ``transfer``, ``psnr``, ``bias``, ``bias_se``,
``psnr_vs_ours``: against our reference on the same pixels; our reference's row adds
``ours_noise_psnr``, ``joint_noise_psnr``, ``mse_ratio``, ``within_noise`` (``mse_ratio`` <=
:data:`prt.bench.mitsuba_compare.NOISE_RATIO_LIMIT`) and ``bias_within`` (|bias| <= :data:`BIAS_LIMIT`)),
``per_view`` (our reference's metrics per view) and ``figure`` (``--images``: ours, Mitsuba and
their difference at the first view, our reference and the networks).
"""

from __future__ import annotations

import numpy as np

from prt.bench.mitsuba_compare import NOISE_RATIO_LIMIT, compare, compared_pixels, diffuse_radiance, linear_psnr, pixel_objects, side_by_side
from prt.bench.mitsuba_reference import MitsubaScene, cached_render, scene_albedos
from prt.bench.report import transfer_label
from prt.bench.vertex_prt import VertexPRT
from prt.runtime.gl import bind_framebuffer
from prt.runtime.renderer import Renderer, Scene

__all__ = ["BIAS_LIMIT", "mitsuba_comparison", "pooled"]

BIAS_LIMIT = 0.003  # |mean brightness bias| of our reference against Mitsuba (issue 38's target)


def _scene(sb, lighting) -> tuple[MitsubaScene, str]:
    """The scene's Mitsuba twin (built once per scene bench) and its content key."""
    if getattr(sb, "_mitsuba", None) is None:
        names = list(sb.geometry.object_names)
        albedos = scene_albedos(sb.manifest)
        table = np.array([albedos[n] for n in names], dtype=np.float64)
        scene = MitsubaScene(sb.geometry.mesh.vertices, sb.geometry.mesh.faces, sb.geometry.object_ids, sb.geometry.two_sided, table,
                             lighting.sh, sb.bounces, variant=sb.settings.mitsuba_variant, log=sb.log)  # fmt: skip
        key = f"{sb.geometry_id}|{table.tolist()}|{np.asarray(lighting.sh).tolist()}|b{sb.bounces}"
        sb._mitsuba = (scene, key, albedos, table)
    return sb._mitsuba


def _transfers(sb, base, size: int, camera, covered) -> dict:
    """{label: (transfer of the covered pixels, what it carries)} of every configuration at ``camera``."""
    out = {}
    if sb.entry["networks"]:
        base.set_camera_object(camera)
        out["onnx fp32"] = (base.render_transfer()[covered], transfer_label(sb.bounces))
        if "glsl" in sb.settings.backends:
            with Renderer(sb.scene, size, size, backend="glsl", ctx=sb.ctx) as glsl:
                glsl.set_camera_object(camera)
                out["glsl"] = (glsl.render_transfer()[covered], transfer_label(sb.bounces))
    for transfer, data in sb.vertex_variants():
        vertex = VertexPRT(sb.ctx, sb.geometry, *data, size, size)
        try:
            image, _ = vertex.render(camera)
            out[f"vertex {transfer}"] = (image[covered], transfer)
        finally:
            vertex.release()
    for texture_size, variant in sb.textures.items():
        bind_framebuffer(sb.ctx, sb.ctx.fbo)
        with Renderer(Scene(variant), size, size, backend="texture", ctx=sb.ctx) as texture:
            texture.set_camera_object(camera)
            out[f"texture {texture_size}"] = (texture.render_transfer()[covered], transfer_label(sb.bounces))
    base.set_camera_object(camera)
    return out


def pooled(images: list) -> dict:
    """Stack per-view ``(ours, mitsuba render, mask, ours_second)`` into one (N, 1, 3) comparison."""
    ours = np.concatenate([o[m] for o, _, m, _ in images])[:, None]
    render = {"radiance": np.concatenate([r["radiance"][m] for _, r, m, _ in images])[:, None],
              "passes": np.concatenate([r["passes"][:, m] for _, r, m, _ in images], axis=1)[:, :, None]}  # fmt: skip
    second = None if images[0][3] is None else np.concatenate([s[m] for _, _, m, s in images])[:, None]
    return compare(ours, render, np.ones(ours.shape[:2], dtype=bool), second)


def mitsuba_comparison(sb, base, size: int, views: list, chosen: list) -> dict:
    """Compare the scene bench ``sb``'s configurations with Mitsuba at ``size`` on the views ``chosen``
    (indices into ``views``; module docstring); the size's record."""
    settings, resolution = sb.settings, f"{size}x{size}"
    scene, key, albedos, table = _scene(sb, base.lighting)
    record = sb.entry.setdefault("mitsuba", {
        "variant": scene.info["variant"], "libllvm": scene.info["libllvm"], "mitsuba": scene.info["mitsuba"], "spp": None,
        "max_depth": 2 + sb.bounces, "albedos": albedos, "envmap": scene.envmap_info, "views": [], "seconds": 0.0, "sizes": {},
    })  # fmt: skip
    record["views"] = list(chosen)
    rays, hit_rays = sb.entry["reference"]["rays_by_size"][resolution], sb.entry["reference"]["hit_rays_by_size"][resolution]
    per_config, ours_pool, per_view, figure = {}, [], [], None
    for v in chosen:
        view = views[v]
        g, camera = view.gbuffer, view.camera
        covered = g.covered
        tag = f"view{v:03d}-{resolution}"
        render = cached_render(sb.transfer_cache, tag, scene, key, camera, size, size, settings.mitsuba_spp, settings.seed)
        record["spp"] = render["spp"]
        record["seconds"] = round(record["seconds"] + render["seconds"], 1)
        objects = pixel_objects(sb.ctx, sb.manifest, camera, size, size, g)
        mask = compared_pixels(g, render, camera.eye) & (objects >= 0)
        albedo_rows = table[np.maximum(objects[covered], 0)]
        e = (view.exposure or {}).get("diffuse", 1.0)  # --exposure: every image of the view at the reference frame's
        render = {**render, "radiance": e * np.asarray(render["radiance"]), "passes": e * np.asarray(render["passes"])}

        def image(transfer=None, irradiance=None):
            out = np.zeros((size, size, 3))
            out[covered] = diffuse_radiance(transfer, base.lighting, albedo_rows) if irradiance is None else np.maximum(irradiance * albedo_rows, 0.0)
            return e * out

        points, normals = g.position[covered], g.normal[covered]
        ours = [image(sb.source.combine(t["direct"], t["indirect"]))
                for t in (sb.source.trace(tag, points, normals, rays, hit_rays, settings.seed + s) for s in (0, 1))]  # fmt: skip
        ours_pool.append((ours[0], render, mask, ours[1]))
        per_view.append({"view": v, **compare(ours[0], render, mask, ours[1])})
        for label, (transfer, carries) in _transfers(sb, base, size, camera, covered).items():
            per_config.setdefault(label, (carries, []))[1].append((image(transfer), render, mask, None, ours[0]))
        for density, grid in (getattr(sb, "probe_grids", None) or {}).items():  # the probe grid: irradiance x each object's albedo
            probes = image(irradiance=grid.irradiance(points, normals))
            per_config.setdefault(f"probes {density}", (transfer_label(sb.bounces), []))[1].append((probes, render, mask, None, ours[0]))
        if figure is None and settings.images is not None:
            rows = [("our reference", ours[0], render["radiance"], mask)]
            if "onnx fp32" in per_config:
                rows.append(("prt-runtime (onnx fp32)", per_config["onnx fp32"][1][-1][0], render["radiance"], mask))
            figure = sb.settings.images / f"{sb.manifest.name}-{resolution}-mitsuba.png"
            side_by_side(figure, rows, f"{sb.manifest.name} {resolution}, view {v}: ours, Mitsuba 3 ({render['spp']} spp), difference")
    reference = pooled(ours_pool)
    reference.update(label="our reference", transfer=transfer_label(sb.bounces), psnr_vs_ours=None,
                     within_noise=bool(reference["mse_ratio"] is not None and reference["mse_ratio"] <= NOISE_RATIO_LIMIT),
                     bias_within=bool(abs(reference["bias"]) <= BIAS_LIMIT))  # fmt: skip
    rows = [reference]
    for label, (carries, images) in per_config.items():
        row = pooled([item[:4] for item in images])
        versus = linear_psnr(np.concatenate([i[0][i[2]] for i in images]), np.concatenate([i[4][i[2]] for i in images]))
        row.update(label=label, transfer=carries, psnr_vs_ours=round(versus, 3))
        row.pop("mitsuba_noise_psnr", None)
        rows.append(row)
    out = record["sizes"][resolution] = {"pixels": reference["pixels"], "mitsuba_noise_psnr": reference["mitsuba_noise_psnr"],
                                         "rays": rays, "hit_rays": hit_rays, "rows": rows, "per_view": per_view,
                                         "figure": None if figure is None else str(figure)}  # fmt: skip
    sb.log(f"  mitsuba {resolution} ({record['variant']}, {record['spp']} spp, views {chosen}): our reference {reference['psnr']:.2f} dB, "
           f"bias {100 * reference['bias']:+.2f} % (se {100 * reference['bias_se']:.2f} %), noise ratio {reference['mse_ratio']}; "
           + ", ".join(f"{r['label']} {r['psnr']:.2f} dB {100 * r['bias']:+.2f} %" for r in rows[1:]))  # fmt: skip
    return out
