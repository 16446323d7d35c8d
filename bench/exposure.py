"""``prt-bench --exposure auto``: every image scored at the exposure auto-exposure gives the reference's frame.

:func:`auto_exposure` is the rule of the runtime's auto-exposure (Reinhard et al. 2002, eq. 1
and 2): ``L = 0.2126 R + 0.7152 G + 0.0722 B`` of the linear radiance, ``L_avg = exp(mean over
covered pixels of log(EPS + L))``, exposure ``clip(KEY / L_avg, 2^-6, 2^10)`` with ``KEY =
0.18`` (scene-linear middle grey) and ``EPS = 1e-4``; 1 when nothing (or nothing but black) is
covered.  The benchmark computes it once per view and material from the ray-traced reference's
linear image, and tone-maps the reference and every configuration of that view with it, so an
interior that is nearly black at exposure 1 is judged as a viewer would show it.
"""

from __future__ import annotations

import math

import numpy as np

from prt.runtime.errors import InputError
from prt.runtime.exposure import auto_exposure as _runtime_auto_exposure

__all__ = ["KEY", "EPS", "EXPOSURE_RANGE", "LUMINANCE", "auto_exposure", "luminance", "parse_exposure"]

KEY = 0.18
EPS = 1.0e-4
EXPOSURE_RANGE = (2.0**-6, 2.0**10)
LUMINANCE = (0.2126, 0.7152, 0.0722)


def luminance(radiance_linear) -> np.ndarray:
    """Rec. 709 luminance of (..., 3) linear RGB; non-finite or negative values count as 0."""
    rad = np.asarray(radiance_linear, dtype=np.float64)
    if rad.ndim < 1 or rad.shape[-1] != 3:
        raise InputError(f"auto_exposure(): radiance must end in 3 channels (RGB), got shape {rad.shape}")
    lum = rad @ np.asarray(LUMINANCE)
    return np.where(np.isfinite(lum), np.maximum(lum, 0.0), 0.0)


def auto_exposure(radiance_linear, covered_mask) -> float:
    """The exposure that maps the log-average luminance of the covered pixels to :data:`KEY` (module docstring).

    Parameters
    ----------
    radiance_linear : array_like, shape (..., 3)
        Linear radiance, before any exposure.
    covered_mask : array_like of bool, shape (...)
        The pixels the scene covers (None: all).

    Returns
    -------
    float
        In :data:`EXPOSURE_RANGE`; 1.0 when no pixel is covered or every covered pixel is black.
    """
    lum = luminance(radiance_linear)
    if covered_mask is not None and np.asarray(covered_mask).shape != lum.shape:
        raise InputError(f"auto_exposure(): covered_mask has shape {np.asarray(covered_mask).shape}, the radiance {lum.shape}")
    return _runtime_auto_exposure(radiance_linear, covered_mask)  # one rule: the runtime's (prt.runtime.exposure)


def parse_exposure(text: str):
    """``"auto"``, or a positive finite number (a fixed exposure); ValueError otherwise (argparse's type)."""
    if text == "auto":
        return "auto"
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(text)
    return value
