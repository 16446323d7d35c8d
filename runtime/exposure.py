"""Automatic exposure: a key value from the frame's log-average luminance (numpy reference).

The rule (Reinhard et al. 2002, "Photographic tone reproduction", eq. 1 and 2)::

    L      = 0.2126 R + 0.7152 G + 0.0722 B          (Rec. 709 luminance of linear radiance)
    L_avg  = exp(mean over covered pixels of log(EPS + L))
    auto   = clip(KEY / L_avg, *EXPOSURE_RANGE)

``KEY = 0.18`` is scene-linear middle grey: the frame's log-average lands on 0.18 before this
renderer's tone map (:func:`prt.runtime.shading.tonemap`, ACES filmic then sRGB), which shows it
as ``ACES(0.18) = 0.267`` linear, sRGB 142/255 -- the middle grey of a print.  Brighter pixels
keep their ratio to it up to ACES' shoulder (1 from ``x ~ 7.2``, i.e. 40x the average).
``EPS`` keeps black pixels finite (they pull the average down, as in Reinhard's operator).
Only covered pixels count (the scene, not the background or the empty screen): a frame with no
covered pixel, or only black ones below ``EPS``, keeps exposure 1.  The clip bounds the gain a
nearly black frame would ask for.

Temporal adaptation (:class:`ExposureAdapter`): the exposure moves towards each frame's target
in log space, ``log e <- log e + (log t - log e) (1 - exp(-dt / TAU))`` with ``dt`` the frame's
duration, so a camera walking from a lit room into a dark one adapts over about ``TAU`` seconds
and a steady view keeps a steady exposure; the first frame takes its target exactly.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import InputError

__all__ = ["KEY", "EPS", "EXPOSURE_RANGE", "TAU", "LUMINANCE", "log_average_luminance", "auto_exposure",
           "exposure_from_log_mean", "ExposureAdapter", "parse_exposure", "default_exposure", "SCENE_OBJECTS", "BLOCK",
           "exposure_defines", "exposure_info"]

KEY = 0.18
EPS = 1.0e-4
EXPOSURE_RANGE = (2.0**-6, 2.0**10)
TAU = 0.5
LUMINANCE = (0.2126, 0.7152, 0.0722)
BLOCK = 16
"""Tile side of the GPU reduction (``shaders/log_luminance.frag``): each tile's sums are read back."""


def _luminance(radiance_linear) -> np.ndarray:
    rad = np.asarray(radiance_linear)
    if rad.dtype != np.float32:
        rad = rad.astype(np.float64)
    if rad.ndim < 1 or rad.shape[-1] != 3:
        raise InputError(f"auto_exposure(): radiance must end in 3 channels (RGB), got shape {rad.shape}")
    lum = (rad @ np.asarray(LUMINANCE, dtype=rad.dtype)).astype(np.float64)  # a float32 frame: weighted in float32
    return np.where(np.isfinite(lum), np.maximum(lum, 0.0), 0.0)


def log_average_luminance(radiance_linear, covered_mask=None) -> float | None:
    """``exp(mean(log(EPS + L)))`` over the covered pixels; None when none is covered.

    ``radiance_linear``: (..., 3) linear RGB; ``covered_mask``: bool array of its leading shape
    (None: every pixel counts).  Non-finite or negative luminance counts as 0.
    """
    lum = _luminance(radiance_linear)
    if covered_mask is not None:
        mask = np.asarray(covered_mask, dtype=bool)
        if mask.shape != lum.shape:
            raise InputError(f"auto_exposure(): covered_mask has shape {mask.shape}, the radiance {lum.shape}")
        lum = lum[mask]
    if lum.size == 0:
        return None
    return float(np.exp(np.mean(np.log(EPS + lum.ravel()))))


def exposure_from_log_mean(log_mean: float | None) -> float:
    """The auto exposure from ``mean(log(EPS + L))`` (the GPU path reduces to this number)."""
    if log_mean is None or not math.isfinite(log_mean) or log_mean <= math.log(EPS) + 1e-9:
        return 1.0  # nothing covered, or every covered pixel black: keep exposure 1
    lo, hi = EXPOSURE_RANGE
    return float(min(max(KEY / math.exp(log_mean), lo), hi))


def auto_exposure(radiance_linear, covered_mask=None) -> float:
    """Exposure that maps the frame's log-average luminance to :data:`KEY` (module docstring).

    Parameters
    ----------
    radiance_linear : array_like, shape (..., 3)
        Linear radiance (what :meth:`Renderer.render` returns), before any exposure.
    covered_mask : array_like of bool, shape (...), optional
        The pixels the scene covers; None: all.

    Returns
    -------
    float
        In :data:`EXPOSURE_RANGE`; 1.0 when no pixel is covered or all covered pixels are black.
    """
    avg = log_average_luminance(radiance_linear, covered_mask)
    return exposure_from_log_mean(None if avg is None else math.log(avg))


class ExposureAdapter:
    """Exposure steady across frames: exponential smoothing in log space, first frame exact.

    ``adapter.update(target, dt)`` returns the exposure to show this frame; ``dt`` is the time
    since the last frame in seconds (``1 / fps`` for a camera path or video).
    """

    def __init__(self, tau: float = TAU):
        if not (math.isfinite(tau) and tau >= 0):
            raise InputError(f"ExposureAdapter: tau must be finite and >= 0, got {tau!r}")
        self.tau = float(tau)
        self.value: float | None = None

    def reset(self) -> None:
        self.value = None

    def update(self, target: float, dt: float) -> float:
        target = float(target)
        if not (math.isfinite(target) and target > 0):
            raise InputError(f"ExposureAdapter.update(): target must be finite and > 0, got {target!r}")
        if self.value is None or self.tau == 0:
            self.value = target
        else:
            a = 1.0 - math.exp(-max(float(dt), 0.0) / self.tau)
            self.value = math.exp(math.log(self.value) + (math.log(target) - math.log(self.value)) * a)
        return self.value


def parse_exposure(value, name: str = "--exposure"):
    """``"auto"`` or a finite number >= 0 (float); else InputError naming ``name``."""
    if isinstance(value, str):
        if value.strip().lower() == "auto":
            return "auto"
        try:
            value = float(value)
        except ValueError:
            raise InputError(f"{name}: expected a number >= 0 or 'auto', got {value!r}") from None
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number >= 0 or 'auto', got {value!r}") from None
    if not (math.isfinite(x) and x >= 0):
        raise InputError(f"{name}: expected a number >= 0 or 'auto', got {value!r}")
    return x


SCENE_OBJECTS = 10
"""Objects from which a build counts as a scene (buildings, assemblies, levels) for :func:`default_exposure`."""


def default_exposure(manifest):
    """The exposure a scene opens with: ``"auto"`` for a scene, 1.0 for an object.

    The rule: ``"auto"`` when the manifest's camera stands inside the scene's bounds (an
    interior; :func:`prt.runtime.camera.inside_bounds`) or the geometry has at least
    :data:`SCENE_OBJECTS` objects; else 1.0, so single objects on a ground disc (the demo, the
    bunny, scans, plants) keep the images they had.
    """
    from .camera import inside_bounds, scene_box

    objects = getattr(manifest.geometry, "objects", None) or []
    if len(objects) >= SCENE_OBJECTS or inside_bounds(manifest.camera.eye, scene_box(manifest)):
        return "auto"
    return 1.0


def exposure_defines(block: int = BLOCK) -> dict:
    """The ``#define`` values of ``shaders/log_luminance.frag`` (the one definition of each is here)."""
    return {"PRT_BLOCK": block, "PRT_EPS": EPS, "PRT_LUM_R": LUMINANCE[0], "PRT_LUM_G": LUMINANCE[1], "PRT_LUM_B": LUMINANCE[2]}


def exposure_info(manifest) -> dict:
    """What the web page needs to compute the same auto exposure (``web.json``'s ``exposure``)."""
    return {"default": default_exposure(manifest), "key": KEY, "eps": EPS, "range": list(EXPOSURE_RANGE), "tau": TAU, "block": BLOCK}
