"""Images against Mitsuba 3: which pixels compare, diffuse radiance per object, the metrics, the figure.

The renderer and Mitsuba (:mod:`prt.bench.mitsuba_reference`) see a view through the same
pixel-centre rays.  A pixel compares (:func:`compared_pixels`) where the G-buffer covers it,
Mitsuba's primary hit lies within :data:`POSITION_TOLERANCE` of the G-buffer's position and its
shading normal within :data:`NORMAL_TOLERANCE_DEG` of the G-buffer's (either way round: two-sided
faces): the rasteriser and the ray caster disagree on a few silhouette pixels, and at a crease
(the Cornell box's floor meeting a wall) on which face a pixel centre lies, both faces passing
through the same point (measured: one such pixel of 1,024 made the floor 4.8 % brighter).  Pixels
where the G-buffer turned a normal that faced away from the eye are left out too
(:data:`FACING_MIN`).  Each pixel's object (its albedo) is the G-buffer's own (:func:`pixel_objects`).

Every configuration is compared through its transfer at the covered pixels, shaded diffuse with
each pixel's object albedo (:func:`diffuse_radiance`: ``albedo_c * max(0, dot(T, L_c) +
dot(T_ind_c, L_c))``, the renderer's diffuse shading with per-object materials).

Metrics (:func:`compare`), over the compared pixels:

- ``psnr``: tone-mapped (:func:`prt.runtime.shading.tonemap`), as every prt-bench PSNR;
- ``bias``: ``sum(ours - mitsuba) / sum(mitsuba)`` of the linear radiance, all channels: the
  mean brightness error; ``bias_se`` its standard error from the measured noise of both (see
  :func:`compare`);
- ``mitsuba_noise_psnr``: the PSNR two independent Mitsuba images of this many paths reach
  against each other (from its even and odd passes: each half has half the paths, so the full
  image's variance is a quarter of their squared difference);
- with a second image of ours (another seed): ``ours_noise_psnr`` (two-seed PSNR; its
  variance is half the squared difference), ``joint_noise_psnr``, the PSNR two unbiased images
  with these noises would reach against each other (tone-mapped: what the PSNR is read against),
  and ``mse_ratio``: the squared error of the linear radiance over the sum of both images'
  measured per-pixel variances (Mitsuba's from the spread of its passes, ours from its two
  seeds): about 1 when the two differ by their noise alone.  It is judged in linear radiance,
  where variances add exactly: through the tone map a noisy image's variance is not what its
  halves' difference says (measured: 1.48 for agreeing images at 256 paths per pixel).
"""

from __future__ import annotations

import numpy as np

from prt.bench.metrics import psnr_from_mse
from prt.runtime.shading import diffuse_light_matrix, tonemap

__all__ = ["POSITION_TOLERANCE", "NORMAL_TOLERANCE_DEG", "FACING_MIN", "NOISE_RATIO_LIMIT", "compared_pixels", "pixel_objects", "diffuse_radiance", "linear_psnr", "halves",
           "compare", "side_by_side"]  # fmt: skip

# Scene units (the scene spans [-1, 1]^3): float32 positions of one ray's hit agree to ~1e-5.
POSITION_TOLERANCE = 1e-3
# Degrees: the same interpolated normal agrees to float32 rounding; faces meeting at a crease differ by tens.
NORMAL_TOLERANCE_DEG = 2.0
# A closed surface seen at a silhouette can have an interpolated normal facing away from the eye:
# the G-buffer turns it perpendicular to the view (n.v = 0) and shades it, Mitsuba's one-sided
# diffuse shades it black.  A convention, not an error of either: such pixels (n.v below this) are
# left out (measured: one pixel of Spot's 472 at 32x32 made the squared error 11x the noise's).
FACING_MIN = 1e-3
# ``mse_ratio`` up to this is "within the joint noise" (1 dB above the unbiased expectation).
NOISE_RATIO_LIMIT = 10 ** 0.1


def compared_pixels(gbuffer, render: dict, eye, tolerance: float = POSITION_TOLERANCE) -> np.ndarray:
    """(H, W) bool: covered by ``gbuffer``, hit by Mitsuba's primary ray (``render``) at the same point
    with the same normal, and not where the G-buffer had to turn a normal facing away (:data:`FACING_MIN`)."""
    position = np.asarray(gbuffer.position, dtype=np.float64)
    gap = np.linalg.norm(np.asarray(render["position"], dtype=np.float64) - position, axis=-1)
    normal = np.asarray(render["normal"], dtype=np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-30)
    ours = np.asarray(gbuffer.normal, dtype=np.float64)
    agree = np.abs(np.einsum("hwc,hwc->hw", normal, ours)) > np.cos(np.radians(NORMAL_TOLERANCE_DEG))
    to_eye = np.asarray(eye, dtype=np.float64) - position
    to_eye /= np.maximum(np.linalg.norm(to_eye, axis=-1, keepdims=True), 1e-30)
    facing = np.einsum("hwc,hwc->hw", ours, to_eye) > FACING_MIN
    return np.asarray(gbuffer.covered, dtype=bool) & (gap < tolerance) & agree & facing


def pixel_objects(ctx, manifest, camera, width: int, height: int, gbuffer=None) -> np.ndarray:
    """(H, W) object id of each pixel as the G-buffer rasterises it (-1: none), by a G-buffer pass
    with the per-object material target; where ``gbuffer`` (the view's own) is given, pixels whose
    position or normal differ from it get -1."""
    from prt.runtime.gbuffer import GBufferPass

    with GBufferPass(ctx, manifest, width, height, object_materials=True) as gpass:
        gpass.render(camera)
        objects = gpass.read_material()[0].reshape(height, width)
        if gbuffer is not None:
            again = gpass.read()
            same = (again.position == gbuffer.position).all(axis=-1) & (again.normal == gbuffer.normal).all(axis=-1)
            objects = np.where(same, objects, -1)
    return objects


def diffuse_radiance(transfer, lighting, albedo) -> np.ndarray:
    """Linear diffuse radiance (M, 3): ``albedo_c * max(0, dot(T, L_c) + dot(T_ind_c, L_c))``.

    Parameters
    ----------
    transfer : (M, n) or (M, 4 n)
        Direct, or "direct+rgb" transfer rows.
    lighting : prt.runtime.shading.Lighting
    albedo : (M, 3)
        Each row's albedo.
    """
    transfer = np.asarray(transfer, dtype=np.float32)
    light = diffuse_light_matrix(lighting, (1.0, 1.0, 1.0), transfer.shape[1]).astype(np.float64)
    return np.asarray(albedo, dtype=np.float64) * np.maximum(transfer.astype(np.float64) @ light, 0.0)


def linear_psnr(a, b) -> float:
    """PSNR (dB) between two sets of linear radiance (..., 3), tone-mapped first (prt-bench's images)."""
    return psnr_from_mse(float(((tonemap(np.asarray(a, dtype=np.float64)) - tonemap(np.asarray(b, dtype=np.float64))) ** 2).mean()))


def halves(passes) -> np.ndarray:
    """(2, ...) the means of the even and of the odd passes: two independent estimates."""
    passes = np.asarray(passes, dtype=np.float64)
    return np.stack([passes[0::2].mean(axis=0), passes[1::2].mean(axis=0)])


def compare(ours, mitsuba: dict, mask, ours_second=None) -> dict:
    """Metrics of a linear image of ours against a Mitsuba render (see the module docstring).

    Parameters
    ----------
    ours : (H, W, 3) linear radiance
    mitsuba : dict
        ``radiance`` (H, W, 3) and ``passes`` (P, H, W, 3): :meth:`prt.bench.mitsuba_reference.MitsubaScene.render`'s result.
    mask : (H, W) bool
        The compared pixels.
    ours_second : (H, W, 3), optional
        Ours again with another seed: its noise.

    Notes
    -----
    ``bias_se`` counts Mitsuba's share from the spread of its passes' pooled sums (the pixels of
    one pass are not independent) and ours from its two seeds' per-pixel differences (each pixel
    traces its own rays).
    """
    mask = np.asarray(mask, dtype=bool)
    pixels = int(mask.sum())
    ours = np.asarray(ours, dtype=np.float64)[mask]
    theirs = np.asarray(mitsuba["radiance"], dtype=np.float64)[mask]
    passes = np.asarray(mitsuba["passes"], dtype=np.float64)[:, mask]
    h = halves(passes)
    mse = float(((tonemap(ours) - tonemap(theirs)) ** 2).mean()) if pixels else 0.0
    noise_m = float(((tonemap(h[0]) - tonemap(h[1])) ** 2).mean()) / 4.0 if pixels else 0.0  # the full image's variance
    total = float(theirs.sum())
    sums = passes.reshape(len(passes), -1).sum(axis=1)
    var_sum = float(sums.var(ddof=1)) / len(passes) if len(passes) > 1 else 0.0
    var_pixels = passes.var(axis=0, ddof=1) / len(passes) if len(passes) > 1 else np.zeros_like(theirs)  # of the mean image
    out = {"pixels": pixels, "psnr": round(psnr_from_mse(mse), 3), "bias": float((ours - theirs).sum() / total) if total > 0 else 0.0,
           "mitsuba_noise_psnr": round(psnr_from_mse(2.0 * noise_m), 3)}  # fmt: skip
    # (the two-seed convention of prt-bench: the PSNR of two independent images of this noise)
    if ours_second is not None:
        second = np.asarray(ours_second, dtype=np.float64)[mask]
        noise_o = float(((tonemap(ours) - tonemap(second)) ** 2).mean()) / 2.0 if pixels else 0.0
        var_sum += float(((ours - second) ** 2).sum()) / 2.0
        # Linear radiance, where variances add exactly: the squared error over both images' measured
        # per-pixel variances (Mitsuba's from its passes, ours from its two seeds).
        expected = float((var_pixels + (ours - second) ** 2 / 2.0).sum())
        error = float(((ours - theirs) ** 2).sum())
        out.update(ours_noise_psnr=round(psnr_from_mse(2.0 * noise_o), 3), joint_noise_psnr=round(psnr_from_mse(noise_o + noise_m), 3),
                   mse_ratio=round(error / expected, 4) if expected > 0 else None)  # fmt: skip
    out["bias_se"] = float(np.sqrt(var_sum) / total) if total > 0 else 0.0
    return out


def side_by_side(path, rows: list, title: str, scale: float = 10.0) -> None:
    """A PNG: per row ours, Mitsuba, and their difference (tone-mapped, ``scale`` x, red: ours brighter).

    ``rows``: ``[(label, ours (H, W, 3) linear, mitsuba (H, W, 3) linear, mask (H, W))]``.
    """
    from prt.bench.report import _pyplot, save_figure

    plt = _pyplot()
    panel = max(2.6, rows[0][1].shape[1] / 80) if rows else 2.6
    fig, axes = plt.subplots(len(rows), 3, figsize=(3 * panel + 0.8, (panel + 0.35) * len(rows) + 0.4), squeeze=False,
                             layout="constrained")  # fmt: skip
    shown = None
    for i, (label, ours, theirs, mask) in enumerate(rows):
        a, b = tonemap(ours), tonemap(theirs)
        diff = (a - b).mean(axis=2)
        diff[~mask] = np.nan
        axes[i, 0].imshow(np.clip(a, 0, 1))
        axes[i, 0].set_title(label, fontsize=9)
        axes[i, 1].imshow(np.clip(b, 0, 1))
        axes[i, 1].set_title("Mitsuba 3", fontsize=9)
        shown = axes[i, 2].imshow(scale * diff, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
        axes[i, 2].set_facecolor("#d0d0d0")
        axes[i, 2].set_title(f"difference x {scale:g}", fontsize=9)
        for ax in axes[i]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle(title, fontsize=10)
    if shown is not None:
        fig.colorbar(shown, ax=axes, shrink=0.8, label=f"{scale:g} x (ours - Mitsuba), tone-mapped")
    save_figure(fig, path, dpi=100)
