"""A look at precomputed transfer: the samples splatted from the default camera and shaded.

Left: ambient visibility (``T_0 / Y_00``, 1 = open sky); right: diffuse white albedo under a
soft sky with a sun, ``dot(T, L)`` per channel, tone-mapped.  Point splats with a z-buffer,
numpy only (no GL needed at build time).
"""

from __future__ import annotations

import numpy as np

from ...runtime import sh
from ...runtime.camera import DEFAULT_CAMERA
from ..cache import atomic_write_bytes

__all__ = ["sky_envmap", "splat", "write_preview"]

EYE = np.array(DEFAULT_CAMERA["eye"])
TARGET = np.array(DEFAULT_CAMERA["target"])


def sky_envmap(height: int = 64, width: int = 128) -> np.ndarray:
    """A procedural sky (blue above, brown ground, a warm sun up and to the right): (H, W, 3)."""
    d = sh.envmap_directions(height, width)
    up = d[..., 1:2]
    sky = np.where(up > 0, 0.6 * np.array([0.55, 0.7, 1.0]) * (0.4 + up), 0.15 * np.array([0.5, 0.4, 0.3]))
    sun_dir = np.array([0.5, 0.75, 0.45]) / np.linalg.norm([0.5, 0.75, 0.45])
    sun = np.clip((d @ sun_dir - 0.97) / 0.03, 0.0, 1.0)[..., None] * np.array([40.0, 36.0, 30.0])
    return (sky + sun).astype(np.float32)


def splat(points, normals, colours, size: int = 384, fov: float = 40.0, area: float | None = None):
    """Square splats of coloured points seen from the default camera, nearest wins.

    points, normals : (N, 3); colours : (N, C) -> (size, size, C) image, background 0.
    area : total surface area the points sample (scene units^2); sets the splat size so the
        splats cover the surface without holes.  None: one-pixel points.
    """
    fwd = TARGET - EYE
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    rel = points - EYE
    depth = rel @ fwd
    facing = np.einsum("ij,ij->i", normals, -rel) > 0
    f = 1.0 / np.tan(np.radians(fov) / 2)
    safe = np.maximum(depth, 1e-6)
    x = (rel @ right) / safe * f
    y = (rel @ up) / safe * f
    px = ((x * 0.5 + 0.5) * size).astype(int)
    py = ((0.5 - y * 0.5) * size).astype(int)
    if area is None:
        radius = np.ones(len(points), dtype=int)
    else:  # side of the square each sample stands for, in pixels at its depth
        side = np.sqrt(area / max(len(points), 1)) * 3.0  # Poisson gaps and two-sided halves need overlap
        radius = np.clip(np.ceil(side * f * size / (2 * safe)), 1, 8).astype(int)
    ok = facing & (depth > 0)
    image = np.zeros((size, size, colours.shape[1]), dtype=np.float32)
    cand_px, cand_py, cand_i = [], [], []
    idx = np.flatnonzero(ok)
    for dx in range(int(radius[ok].max(initial=1))):
        for dy in range(int(radius[ok].max(initial=1))):
            sel = idx[radius[idx] > max(dx, dy)]
            cand_px.append(px[sel] + dx)
            cand_py.append(py[sel] + dy)
            cand_i.append(sel)
    cx, cy, ci = (np.concatenate(a) for a in (cand_px, cand_py, cand_i))
    inside = (cx >= 0) & (cx < size) & (cy >= 0) & (cy < size)
    cx, cy, ci = cx[inside], cy[inside], ci[inside]
    order = np.argsort(-depth[ci], kind="stable")  # far first, so near splats overwrite them
    image[cy[order], cx[order]] = colours[ci[order]]
    return image


def write_preview(path, points, normals, transfer, envmap=None, size: int = 384, area: float | None = None) -> None:
    """Write the two-panel PNG (visibility | shaded) for samples with ``transfer`` (N, n).

    envmap : (H, W, 3) equirectangular radiance, default :func:`sky_envmap`
    area : surface area the samples cover (sets the splat size)
    """
    import imageio.v3 as iio

    bands = int(round(np.sqrt(transfer.shape[1])))
    light = sh.project_envmap(envmap if envmap is not None else sky_envmap(), bands)  # (n, 3)
    visibility = np.clip(transfer[:, :1] / sh.basis(np.array([[0.0, 0.0, 1.0]]), 1)[0, 0], 0, 1)
    shaded = transfer.astype(np.float64) @ light
    shaded = shaded / (1.0 + shaded)  # Reinhard, then sRGB-ish gamma
    left = splat(points, normals, np.repeat(visibility, 3, axis=1), size, area=area)
    right = splat(points, normals, np.clip(shaded, 0, 1) ** (1 / 2.2), size, area=area)
    image = (np.concatenate([left, right], axis=1) * 255 + 0.5).astype(np.uint8)
    atomic_write_bytes(path, iio.imwrite("<bytes>", image, extension=".png"))
