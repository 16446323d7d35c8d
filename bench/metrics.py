"""Image errors against the reference, and the speed-error Pareto front.

On tone-mapped images (:func:`prt.runtime.shading.tonemap`, values in [0, 1]): ``mae`` and
``psnr`` over covered pixels, ``ssim`` the SSIM map (skimage, data_range 1, 7x7 window)
averaged over covered pixels, ``psnr_whole`` over the whole image (background counts, as in
the paper).  PSNR is capped at :data:`PSNR_CAP` dB (identical images).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from skimage.metrics import structural_similarity

__all__ = ["PSNR_CAP", "psnr_from_mse", "image_metrics", "pareto_front", "group_key", "mark_pareto"]

# Identical images would give infinite PSNR; JSON has no infinity.
PSNR_CAP = 100.0


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] images, capped at :data:`PSNR_CAP`."""
    return PSNR_CAP if mse <= 10.0 ** (-PSNR_CAP / 10.0) else float(-10.0 * np.log10(mse))


def image_metrics(image, reference, covered) -> dict:
    """Errors of a tone-mapped image against the tone-mapped reference.

    Parameters
    ----------
    image, reference : (H, W, 3) arrays in [0, 1]
    covered : (H, W) bool
        Pixels the scene covers.

    Returns
    -------
    dict
        ``mae``, ``psnr`` (covered pixels), ``ssim`` (SSIM map averaged over covered pixels),
        ``psnr_whole`` (every pixel).
    """
    image = np.asarray(image, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    diff = image[covered] - reference[covered]
    _, ssim_map = structural_similarity(reference, image, data_range=1.0, channel_axis=-1, full=True)
    return {
        "mae": float(np.abs(diff).mean()),
        "psnr": psnr_from_mse(float((diff**2).mean())),
        "ssim": float(ssim_map[covered].mean()),
        "psnr_whole": psnr_from_mse(float(((image - reference) ** 2).mean())),
    }


def pareto_front(points) -> list[int]:
    """Indices of the points no other point beats in both coordinates (both maximised).

    Parameters
    ----------
    points : sequence of (x, y)
        E.g. (FPS, PSNR).

    Returns
    -------
    list of int
        The non-dominated points, by increasing x (ties: by decreasing y).  A point is dominated
        when another is at least as good in both coordinates and better in one.
    """
    pts = [(float(x), float(y)) for x, y in points]
    front = [
        i for i, (x, y) in enumerate(pts)
        if not any(u >= x and v >= y and (u > x or v > y) for u, v in pts)
    ]  # fmt: skip
    return sorted(front, key=lambda i: (pts[i][0], -pts[i][1]))


def group_key(record: dict) -> str:
    """Configurations compete only with the same scene, resolution and material (the same reference)."""
    return f"{record['scene']} {record['resolution']} {record['material']}"


def mark_pareto(records: list) -> dict:
    """Set ``record["pareto"]`` per (scene, resolution, material); return each front's labels."""
    groups = defaultdict(list)
    for r in records:
        groups[group_key(r)].append(r)
    fronts = {}
    for name, group in groups.items():
        front = pareto_front([(r["fps"], r["psnr"]) for r in group])
        for i, r in enumerate(group):
            r["pareto"] = i in front
        fronts[name] = [group[i]["label"] for i in front]
    return fronts
