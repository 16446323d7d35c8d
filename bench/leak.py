"""Light leaking as a figure: how much light a configuration puts where the reference is dark.

Per view and material, with ``e`` the auto exposure of the reference's frame
(:func:`prt.bench.exposure.auto_exposure`, whatever ``--exposure`` the images are scored at),
and luminances in units of the frame's key (``e L / KEY``: 1 is the frame's log average):

- *dark pixels*: covered pixels the reference shows below :data:`DARK` (1/8 of the key, three
  stops under it): shadowed walls of a room, the inside of a wall lit only from outside;
- ``leak``: the share of the dark pixels that the configuration lights above :data:`LIT` (half
  the key: four times the dark bound, clearly visible);
- ``leak_error``: the mean excess ``max(0, config - reference)`` over the dark pixels, in key units.

A view without dark pixels gives None for both (the record averages the views that have some;
None when none has).  The reference against itself is 0 by definition; the scene's
``reference.leak`` gives the reference's second seed against its first at view 0, the figure's
noise floor.
"""

from __future__ import annotations

import numpy as np

from prt.bench.exposure import KEY, luminance

__all__ = ["DARK", "LIT", "leak_figures", "mean_leak"]

DARK = 1.0 / 8.0
LIT = 0.5


def leak_figures(image_linear, reference_luminance, key_exposure: float, covered) -> dict:
    """``{"leak": share, "leak_error": key units}`` of one view (None, None without dark pixels).

    ``image_linear``: (H, W, 3) linear radiance of the configuration; ``reference_luminance``:
    (H, W) the reference's (:func:`prt.bench.exposure.luminance`); ``key_exposure``: the
    reference frame's auto exposure; ``covered``: (H, W) bool.
    """
    scale = float(key_exposure) / KEY
    ref = np.asarray(reference_luminance, dtype=np.float64) * scale
    conf = luminance(image_linear) * scale
    dark = np.asarray(covered, dtype=bool) & (ref < DARK)
    if not dark.any():
        return {"leak": None, "leak_error": None}
    return {"leak": float(np.mean(conf[dark] > LIT)), "leak_error": float(np.mean(np.maximum(conf[dark] - ref[dark], 0.0)))}


def mean_leak(figures: list[dict]) -> dict:
    """The views' figures averaged over the views that have dark pixels (rounded; None when none has)."""
    out = {}
    for key in ("leak", "leak_error"):
        values = [f[key] for f in figures if f[key] is not None]
        out[key] = round(float(np.mean(values)), 6) if values else None
    return out
