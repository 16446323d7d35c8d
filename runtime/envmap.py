"""Reading and writing HDR environment maps (Radiance ``.hdr`` and OpenEXR ``.exr``).

Images are equirectangular (latitude-longitude, width = 2 * height), row 0 at the top, linear
RGB in channel order R, G, B; see :mod:`prt.runtime.sh` for the direction of each texel.
OpenCV decodes ``.hdr`` and the OpenEXR bindings (package ``openexr``) handle ``.exr``, since
OpenCV wheels may lack the EXR codec; both are imported lazily so this module stays cheap.
Every failure raises :class:`~prt.runtime.errors.EnvmapError` with a one-line message that
names the file.
"""

from __future__ import annotations

import os
import uuid
import warnings
from pathlib import Path

import numpy as np

from .errors import EnvmapError
from .sh import project_envmap

__all__ = ["read_envmap", "write_hdr", "load_envmap_sh", "SUPPORTED_EXTENSIONS"]

SUPPORTED_EXTENSIONS = (".hdr", ".exr")

# Negative values down to this fraction of the image maximum are resampling noise, clamped
# silently; anything more negative is clamped too but with a warning.
_NEGATIVE_NOISE = 1e-3


def _cv2():
    """Import OpenCV with its EXR codec enabled (the variable must be set before the import)."""
    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
    import cv2

    # OpenCV logs decode failures to stderr itself; we raise one EnvmapError line instead.
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:
        pass
    return cv2


def _one_line(text: object) -> str:
    """Collapse an arbitrary (possibly multi-line) message to one line."""
    return " ".join(str(text).split())


def _check_extension(path: Path) -> str:
    """Lower-case extension of ``path``; EnvmapError unless it is a supported one."""
    ext = path.suffix.lower()
    if ext not in SUPPORTED_EXTENSIONS:
        raise EnvmapError(
            f"{path}: unsupported env map extension {path.suffix!r}; expected .hdr or .exr"
        )
    return ext


def _read_hdr_bgr(path: Path) -> np.ndarray:
    """Decode a Radiance file with OpenCV (BGR order, as OpenCV returns it)."""
    cv2 = _cv2()
    try:
        # IMREAD_COLOR forces 3 channels (grey is replicated, alpha dropped); ANYDEPTH keeps floats.
        image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    except cv2.error as exc:
        raise EnvmapError(f"{path}: cannot decode .hdr file ({_one_line(exc)})") from None
    if image is None:
        raise EnvmapError(f"{path}: cannot decode .hdr file (corrupt or not a .hdr image)")
    return image


def _read_exr_bgr(path: Path) -> np.ndarray:
    """Decode an OpenEXR file's R, G, B channels with the OpenEXR bindings (BGR order)."""
    try:
        import OpenEXR
    except ImportError:
        raise EnvmapError(f"{path}: reading .exr needs the 'openexr' package (pip install openexr)") from None
    try:
        with OpenEXR.File(str(path)) as f:
            channels = f.channels()
            if "RGB" in channels:
                rgb = np.asarray(channels["RGB"].pixels)
            elif all(c in channels for c in "RGB"):
                rgb = np.stack([np.asarray(channels[c].pixels) for c in "RGB"], axis=-1)
            elif "Y" in channels:  # luminance-only map: grey light
                rgb = np.repeat(np.asarray(channels["Y"].pixels)[..., None], 3, axis=-1)
            else:
                raise EnvmapError(f"{path}: OpenEXR file has no R, G, B (or Y) channels: {sorted(channels)}")
    except EnvmapError:
        raise
    except Exception as exc:  # the bindings raise RuntimeError and friends for corrupt files
        raise EnvmapError(f"{path}: cannot decode .exr file ({_one_line(exc)})") from None
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise EnvmapError(f"{path}: expected a 3-channel colour image, got shape {rgb.shape}")
    return np.ascontiguousarray(rgb[..., ::-1]).astype(np.float32)


def read_envmap(path) -> np.ndarray:
    """Read an equirectangular HDR environment map.

    Parameters
    ----------
    path : str or os.PathLike
        A Radiance ``.hdr`` or OpenEXR ``.exr`` file (extension is case-insensitive).

    Returns
    -------
    ndarray, shape (H, 2*H, 3), float32
        Linear RGB radiance (channel order R, G, B), row 0 at the top, all values finite and
        >= 0.  Negative values are clamped to 0 (with a warning when they are more than
        resampling noise).

    Raises
    ------
    EnvmapError
        If the file is missing, has an unsupported extension, cannot be decoded, is not
        2:1 equirectangular, or contains NaN or Inf.
    """
    path = Path(path)
    ext = _check_extension(path)
    if not path.is_file():
        raise EnvmapError(f"{path}: env map file not found")

    if ext == ".exr":
        image = _read_exr_bgr(path)
    else:
        image = _read_hdr_bgr(path)
    if image.ndim != 3 or image.shape[2] != 3:
        raise EnvmapError(f"{path}: expected a 3-channel colour image, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise EnvmapError(
            f"{path}: expected floating-point HDR data, got {image.dtype} (low dynamic range?)"
        )

    height, width = image.shape[:2]
    if width != 2 * height:
        raise EnvmapError(
            f"{path}: not an equirectangular env map: {width}x{height} texels, width must be "
            "2 * height"
        )

    rgb = np.ascontiguousarray(image[..., ::-1], dtype=np.float32)
    if not np.isfinite(rgb).all():
        bad = int(np.count_nonzero(~np.isfinite(rgb)))
        raise EnvmapError(f"{path}: env map contains {bad} NaN or Inf values")
    lowest = float(rgb.min())
    if lowest < 0.0:
        if lowest < -_NEGATIVE_NOISE * max(float(rgb.max()), 1.0):
            warnings.warn(
                f"{path}: env map has negative values (min {lowest:.4g}); clamped to 0",
                stacklevel=2,
            )
        np.maximum(rgb, 0.0, out=rgb)
    return rgb


def write_hdr(path, image) -> None:
    """Write an HDR image atomically (temporary file in the same folder, then rename).

    Parameters
    ----------
    path : str or os.PathLike
        Target ``.hdr`` (Radiance RGBE, about 1% precision) or ``.exr`` (float32) file.
    image : array_like, shape (H, W, 3)
        Linear RGB (channel order R, G, B), finite and >= 0.  Any size is accepted; only
        :func:`read_envmap` requires 2:1.

    Raises
    ------
    EnvmapError
        If the extension is unsupported, the image has the wrong shape, holds NaN, Inf or
        negative values, or OpenCV cannot write the file.
    """
    path = Path(path)
    ext = _check_extension(path)
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise EnvmapError(f"{path}: image to write must have shape (H, W, 3), got {img.shape}")
    img = img.astype(np.float32)
    if not np.isfinite(img).all():
        raise EnvmapError(f"{path}: image to write contains NaN or Inf values")
    if (img < 0).any():
        raise EnvmapError(f"{path}: image to write has negative values (HDR stores radiance >= 0)")

    # Same folder so os.replace is atomic; the temporary keeps the extension because OpenCV
    # picks the encoder from it.
    tmp_name = str(path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}{ext}"))
    try:
        if ext == ".exr":
            _write_exr(path, tmp_name, img)
        else:
            cv2 = _cv2()
            try:
                ok = cv2.imwrite(tmp_name, np.ascontiguousarray(img[..., ::-1]))
            except cv2.error as exc:
                raise EnvmapError(f"{path}: cannot write {ext} file ({_one_line(exc)})") from None
            if not ok:
                raise EnvmapError(f"{path}: cannot write {ext} file (OpenCV encoder failed)")
        os.replace(tmp_name, path)
    except BaseException:
        if os.path.exists(tmp_name):
            os.unlink(tmp_name)
        raise


def _write_exr(path: Path, tmp_name: str, rgb: np.ndarray) -> None:
    try:
        import OpenEXR
    except ImportError:
        raise EnvmapError(f"{path}: writing .exr needs the 'openexr' package (pip install openexr)") from None
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    try:
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}) as f:
            f.write(tmp_name)
    except Exception as exc:
        raise EnvmapError(f"{path}: cannot write .exr file ({_one_line(exc)})") from None


def load_envmap_sh(path, bands: int = 4) -> np.ndarray:
    """Read an env map and project it onto real SH.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.hdr`` or ``.exr`` equirectangular env map.
    bands : int
        Number of SH bands.

    Returns
    -------
    ndarray, shape (bands**2, 3), float64
        ``project_envmap(read_envmap(path), bands)``.

    Raises
    ------
    EnvmapError
        As :func:`read_envmap`.
    """
    return project_envmap(read_envmap(path), bands)
