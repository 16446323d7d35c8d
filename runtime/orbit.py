"""Render a turntable: views on an orbit about the scene's target, written as PNG frames.

What ``prt-runtime --headless`` does, as a library function: :func:`render_orbit`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .camera import orbit_views
from .checks import finite_array, positive_int
from .errors import OutputError
from .files import atomic_write_bytes
from .shading import to_srgb8

__all__ = ["render_orbit", "OrbitSummary"]


@dataclass(frozen=True)
class OrbitSummary:
    """Median timings of an orbit (warm-up frames excluded); ``str()`` gives the one-line report."""

    scene: str
    frames: int
    width: int
    height: int
    backend: str
    median_ms: dict  # stage -> median milliseconds, "frame" included
    out: Path

    @property
    def fps(self) -> float:
        return 1000.0 / self.median_ms["frame"]

    def __str__(self) -> str:
        med = self.median_ms
        parts = ", ".join(f"{k} {v:.1f}" for k, v in med.items() if k != "frame")
        return (
            f"{self.scene}: {self.frames} frames {self.width}x{self.height}, backend {self.backend}: median {self.fps:.1f} FPS "
            f"({med['frame']:.1f} ms/frame; {parts} ms); wrote {self.out}/frame_000.png ..."
        )


def render_orbit(r, frames: int, out, *, exposure: float = 1.0, warmup: int = 2) -> OrbitSummary:
    """Render ``frames`` views on a full orbit of the renderer's camera into ``out``/frame_NNN.png.

    Parameters
    ----------
    r : prt.runtime.renderer.Renderer
        Its camera is the first view, and is restored at the end.
    frames : int
        Views, evenly spaced (:func:`prt.runtime.camera.orbit_views`).
    out : str or os.PathLike
        Folder for the frames, created when the first frame is ready (never for a failed first
        frame); if the orbit fails later, the frames written and a folder it created are removed.
    exposure : float
        Exposure before tone mapping.
    warmup : int
        Frames rendered first, each from a view just short of the start, and not timed.

    Returns
    -------
    OrbitSummary
    """
    frames = positive_int(frames, "--frames")
    exposure = float(finite_array(exposure, "--exposure", (), minimum=0.0))
    out = Path(out)
    start = r.camera
    written: list[Path] = []
    created: list[Path] = []  # folders made here, deepest last
    try:
        for i in range(warmup):  # sessions, shader compilation, caches; a new view each time
            r.set_camera_object(start.orbit(-0.01 * (i + 1)))
            r.render()
        stages: dict[str, list[float]] = {}
        for i, camera in enumerate(orbit_views(start, frames)):
            r.set_camera_object(camera)
            image = r.render()
            for k, v in r.timings.items():
                stages.setdefault(k, []).append(v)
            png = iio.imwrite("<bytes>", to_srgb8(image, exposure), extension=".png")
            if not written:
                created = _make_folder(out)
            atomic_write_bytes(out / f"frame_{i:03d}.png", png)
            written.append(out / f"frame_{i:03d}.png")
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        for folder in reversed(created):
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    finally:
        r.set_camera_object(start)
    med = {k: float(np.median(v)) for k, v in stages.items()}
    return OrbitSummary(r.scene.name, frames, r.width, r.height, r.backend, med, out)


def _make_folder(out: Path) -> list[Path]:
    """Create ``out`` and its missing parents; the folders created, outermost first."""
    missing = [p for p in [out, *out.parents] if not p.exists()][::-1]
    try:
        out.mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:
        raise OutputError(f"{out}: cannot create the output folder ({getattr(exc, 'strerror', None) or exc})") from None
    if not out.is_dir():
        raise OutputError(f"{out}: not a folder")
    return missing
