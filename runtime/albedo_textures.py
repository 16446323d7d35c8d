"""Albedo textures: reading (imageio), the layer stack the shading samples, and its numpy twin.

An object's albedo may be a texture times its material's albedo (MTL ``map_Kd`` times ``Kd``;
glTF base colour texture times factor).  Textures are 8-bit sRGB images; they are decoded to
linear RGB once, at load, and stored as float32 so both shading twins multiply the same numbers.

Sampling, defined once (:func:`sample_bilinear`) and followed exactly by ``shade_pass.frag``
(which fetches texels with ``texelFetch`` rather than relying on the driver's filtering):

- UV convention: OBJ's, ``v = 0`` at the bottom of the image (trimesh gives glTF UVs the same way);
- bilinear between texel centres, wrapping (GL ``REPEAT``) in both directions:
  ``x = u W - 1/2``, ``y = (1 - v) H - 1/2`` with ``y`` counted in rows from the top.

The stack (:class:`AlbedoTextures`) holds every texture of a scene as one layer of a
``sampler2DArray`` as large as the largest; a smaller texture fills the top-left of its layer
and keeps its own size (wrapping uses that size).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .errors import SpecError

__all__ = ["read_albedo_texture", "srgb_to_linear", "sample_bilinear", "AlbedoTextures", "MAX_TEXTURE_SIZE"]

# Largest width or height accepted (a 3D texture layer is allocated at the largest size).
MAX_TEXTURE_SIZE = 8192


def srgb_to_linear(c) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1), float64 in, float64 out."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def read_albedo_texture(path, error=SpecError) -> np.ndarray:
    """An 8- or 16-bit image (PNG, JPEG, ...) as (H, W, 3) float32 linear RGB (alpha dropped).

    Raises
    ------
    error (default SpecError)
        One line naming the file: unreadable, not an image, or an unsupported shape or size.
    """
    import imageio.v3 as iio

    path = Path(path)
    try:
        # On bad bytes imageio tries its legacy plugins, which warn about their own deprecation.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            image = np.asarray(iio.imread(path, extension=path.suffix.lower() or None))
    except FileNotFoundError:
        raise error(f"{path}: albedo texture not found") from None
    except Exception as exc:  # imageio raises many kinds on bad bytes
        text = " ".join(str(exc).split())[:160]
        raise error(f"{path}: cannot read albedo texture, corrupt or not an image ({type(exc).__name__}: {text})") from None
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 2, 3, 4) or image.dtype.kind not in "uf" or min(image.shape[:2]) < 1:
        raise error(f"{path}: albedo texture must be a grey, RGB or RGBA image, got shape {image.shape} {image.dtype}")
    if max(image.shape[:2]) > MAX_TEXTURE_SIZE:
        raise error(f"{path}: albedo texture {image.shape[1]}x{image.shape[0]} exceeds {MAX_TEXTURE_SIZE} pixels a side")
    channels = image[:, :, :3] if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)
    if image.dtype.kind == "u":
        encoded = channels / float(np.iinfo(image.dtype).max)
    else:
        encoded = np.clip(channels.astype(np.float64), 0.0, 1.0)
    return srgb_to_linear(encoded).astype(np.float32)


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping lookup of ``image`` (H, W, C) at ``uv`` (N, 2); (N, C) float32.

    The reference the shader follows (see the module docstring); computed in float32 as there.
    """
    h, w = image.shape[:2]
    uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
    x = uv[:, 0] * np.float32(w) - np.float32(0.5)
    y = (np.float32(1.0) - uv[:, 1]) * np.float32(h) - np.float32(0.5)
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    x1, y1 = np.mod(x0 + 1, w), np.mod(y0 + 1, h)
    x0, y0 = np.mod(x0, w), np.mod(y0, h)
    top = image[y0, x0] * (np.float32(1) - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (np.float32(1) - fx) + image[y1, x1] * fx
    return (top * (np.float32(1) - fy) + bottom * fy).astype(np.float32)


class AlbedoTextures:
    """The textures of a scene as layers of one array.

    Parameters
    ----------
    images : list of (H, W, 3) float32
        Linear RGB, as :func:`read_albedo_texture` returns.
    """

    def __init__(self, images: list[np.ndarray]):
        self.images = list(images)
        self.sizes = [(int(i.shape[1]), int(i.shape[0])) for i in self.images]  # (W, H)
        width = max((s[0] for s in self.sizes), default=1)
        height = max((s[1] for s in self.sizes), default=1)
        self.layers = np.zeros((max(len(self.images), 1), height, width, 4), dtype=np.float32)
        for k, image in enumerate(self.images):
            self.layers[k, : image.shape[0], : image.shape[1], :3] = image
            self.layers[k, : image.shape[0], : image.shape[1], 3] = 1.0

    def __len__(self) -> int:
        return len(self.images)

    def sample(self, layer: int, uv: np.ndarray) -> np.ndarray:
        """(N, 3) float32: texture ``layer`` at ``uv`` (:func:`sample_bilinear`)."""
        return sample_bilinear(self.images[layer], uv)

    def gl_texture(self, ctx):
        """A moderngl ``texture_array`` (RGBA32F, nearest: the shader filters) of the layers; row 0 at the top."""
        import moderngl

        layers, height, width, _ = self.layers.shape
        texture = ctx.texture_array((width, height, layers), 4, data=np.ascontiguousarray(self.layers).tobytes(), dtype="f4")
        texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        return texture
