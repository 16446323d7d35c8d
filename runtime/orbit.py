"""Render a turntable or a camera path headlessly: PNG frames, linear EXR frames, or an MP4.

What ``prt-runtime --headless`` does, as library functions: :func:`render_orbit` (the orbit of
the renderer's camera) and :func:`render_camera_path` (a :class:`~prt.runtime.camera_path.CameraPath`).
Output is never left half-written: each frame file is written through a temporary file and a
rename, a video is encoded into a temporary file renamed at the end, the output folder is
created only when the first frame is ready, and a failure removes what the call wrote.

Frames are rendered back to back and held in memory (up to :data:`HOLD_BYTES`), then tone-mapped,
encoded and written; the timings cover the rendering only, the report gives the writing's seconds
apart.
"""

from __future__ import annotations

import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .camera_path import CameraPath, orbit_path
from .camera import fit_near, scene_box
from .checks import finite_array, positive_int
from .envmap import write_hdr
from .errors import ArgumentTypeError, InputError, OutputError
from .exposure import ExposureAdapter, parse_exposure
from .files import atomic_write_bytes
from .shading import to_srgb8

__all__ = ["render_orbit", "render_camera_path", "OrbitSummary", "FORMATS", "VIDEO_INSTALL"]

FORMATS = ("png", "exr", "mp4")
HOLD_BYTES = 256 << 20
"""Memory for rendered frames not yet written (float32; at least one frame): the frames of a
path are rendered back to back, as the viewer renders them, and written after.  Writing each frame
between two renders leaves the renderer's threads idle for the encoding, and they come back slow:
on the 2-core machine the demo's frames took 1.17x as long, its network stage 1.46x
(``studies/demo_fps.py``, ``docs/benchmarks/demo_fps.md``)."""
PNG_LEVEL = 1
"""zlib level of the PNG frames: 4x faster to encode than Pillow's default 6, files about a third larger."""
VIDEO_INSTALL = 'pip install "prt-runtime[video]"  (imageio-ffmpeg)'


@dataclass(frozen=True)
class OrbitSummary:
    """Median timings of an orbit or path (warm-up frames excluded); ``str()`` gives the one-line report."""

    scene: str
    frames: int
    width: int
    height: int
    backend: str
    median_ms: dict  # stage -> median milliseconds, "frame" included
    out: Path
    wrote: str = ""  # what was written, for the report (default: the PNG frames in ``out``)
    write_s: float = 0.0  # seconds spent tone mapping, encoding and writing the frames (not in median_ms)
    renderer: str = ""  # the GL renderer that drew the frames (GL_RENDERER)
    exposure: str = ""  # the exposure of the frames: a number, or "auto" with the range it took

    @property
    def fps(self) -> float:
        return 1000.0 / self.median_ms["frame"]

    def __str__(self) -> str:
        med = self.median_ms
        parts = ", ".join(f"{k} {v:.1f}" for k, v in med.items() if k not in ("frame", "frame_readback"))
        on = f" on {self.renderer}" if self.renderer else ""
        # A frame shaded on the GPU is timed to its texture; reading it back for the files is apart.
        readback = f"; read back {med['frame_readback']:.1f} ms apart" if "frame_readback" in med else ""
        return (
            f"{self.scene}: {self.frames} frames {self.width}x{self.height}, backend {self.backend}{on}: median {self.fps:.1f} FPS "
            f"({med['frame']:.1f} ms/frame; {parts} ms{readback}); wrote {self.wrote or f'{self.out}/frame_000.png ...'}"
            f" in {self.write_s:.1f} s" + (f"; exposure {self.exposure}" if self.exposure else "")
        )


def render_orbit(r, frames: int, out, *, exposure=None, warmup: int = 2, fmt: str = "png", fps: float = 30.0) -> OrbitSummary:
    """Render ``frames`` views on a full orbit of the renderer's camera into ``out``.

    Parameters
    ----------
    r : prt.runtime.renderer.Renderer
        Its camera is the first view, and is restored at the end.
    frames : int
        Views, evenly spaced (:func:`prt.runtime.camera.orbit_views`).
    out, exposure, warmup, fmt, fps
        As :func:`render_camera_path`.

    Returns
    -------
    OrbitSummary
    """
    frames = positive_int(frames, "--frames")
    return render_camera_path(r, orbit_path(r.camera, frames), out, exposure=exposure, warmup=warmup, fmt=fmt, fps=fps)


def render_camera_path(r, path: CameraPath, out, *, exposure=None, warmup: int = 2, fmt: str = "png",
                       fps: float = 30.0, poses: list[int] | None = None) -> OrbitSummary:  # fmt: skip
    """Render every frame of ``path``.

    Parameters
    ----------
    r : prt.runtime.renderer.Renderer
        Its camera is restored at the end.
    path : CameraPath
    out : str or os.PathLike
        ``png`` / ``exr``: folder for ``frame_NNN.png`` (tone-mapped sRGB) or ``frame_NNN.exr``
        (linear radiance times ``exposure``, float32).  ``mp4``: the video file if ``out`` ends
        in ``.mp4``, else ``out/turntable.mp4``.  Folders are created when the first frame is
        ready (never for a failed first frame); if a later frame fails, what was written and
        the folders created are removed.
    exposure : float or "auto", optional
        Exposure before tone mapping (PNG, MP4) or scale of the radiance (EXR); default the
        renderer's (:attr:`Renderer.exposure`: "auto" for a scene).  ``"auto"``: each frame's
        :meth:`Renderer.frame_exposure`, smoothed along the path at ``1 / fps`` seconds a frame
        (:class:`prt.runtime.exposure.ExposureAdapter`, the first frame exact); stage ``exposure``.
    warmup : int
        Frames rendered first, each from a view just short of the start, and not timed.
    fmt : {"png", "exr", "mp4"}
    fps : float
        Frame rate of the video.
    poses : list of int, optional
        Deformable scenes: the recorded frame (:meth:`Renderer.set_deformation`) of each output frame.

    Returns
    -------
    OrbitSummary
    """
    if not isinstance(path, CameraPath):
        raise ArgumentTypeError(f"render_camera_path: expected a CameraPath, got {type(path).__name__}")
    if fmt not in FORMATS:
        raise InputError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    exposure = parse_exposure(r.exposure if exposure is None else exposure, "--exposure")
    adapter = ExposureAdapter() if exposure == "auto" else None
    fps = float(finite_array(fps, "--fps", ()))
    if not 0 < fps <= 1000:
        raise InputError(f"--fps must be in (0, 1000], got {fps}")
    box = scene_box(r.scene.manifest)
    cameras = [fit_near(c, box) for c in path.cameras()]  # every view checked before anything is written; inside: near plane for interiors
    exposures = [1.0] * len(cameras)
    out = Path(out)
    sink = _VideoSink(out, r.width, r.height, fps) if fmt == "mp4" else _FrameSink(out, fmt)
    start = r.camera
    # Rendered frames not yet written go into slots allocated (and touched) once: a fresh array per
    # held frame would make the next renders pay for new pages.
    frame_bytes = r.height * r.width * 3 * 4
    slots = np.ones((max(1, min(len(cameras), HOLD_BYTES // frame_bytes)), r.height, r.width, 3), np.float32)
    held: list[int] = []  # the path's indices of the frames in the slots, in order
    write_s = 0.0
    try:
        for i in range(warmup):  # sessions, shader compilation, caches; a new view each time
            r.set_camera_object(cameras[0].orbit(-0.01 * (i + 1)))
            r.render()
        stages: dict[str, list[float]] = {}
        for i, camera in enumerate(cameras):
            r.set_camera_object(camera)
            if poses is not None:
                r.set_deformation(frame=poses[i % len(poses)])
            image = r.render()
            for k, v in r.timings.items():
                stages.setdefault(k, []).append(v)
            if adapter is not None:
                t0 = time.perf_counter()
                exposures[i] = adapter.update(r.frame_exposure(image), 1.0 / fps)
                stages.setdefault("exposure", []).append(1e3 * (time.perf_counter() - t0))
            else:
                exposures[i] = exposure
            if i == 0:
                sink.open()  # the folders, once the first frame is ready (a bad output path fails now)
            np.copyto(slots[len(held)], image)
            held.append(i)
            if i == len(cameras) - 1 or len(held) == len(slots):
                t0 = time.perf_counter()
                for k, j in enumerate(held):
                    sink.add(j, slots[k], exposures[j])
                held.clear()
                write_s += time.perf_counter() - t0
        t0 = time.perf_counter()
        sink.finish()
        write_s += time.perf_counter() - t0
    except BaseException:
        sink.abort()
        raise
    finally:
        r.set_camera_object(start)
    med = {k: float(np.median(v)) for k, v in stages.items()}
    used = f"auto {min(exposures):.3g}..{max(exposures):.3g}" if adapter is not None else f"{exposure:g}"
    return OrbitSummary(r.scene.name, len(cameras), r.width, r.height, r.backend, med, out, sink.wrote(), write_s, r.gl_renderer, used)


class _FrameSink:
    """PNG or EXR frames in a folder."""

    def __init__(self, out: Path, fmt: str) -> None:
        self.out, self.fmt = out, fmt
        self.written: list[Path] = []
        self.created: list[Path] = []  # folders made here, outermost first

    def open(self) -> None:
        self.created = _make_folder(self.out)

    def add(self, i: int, image: np.ndarray, exposure: float) -> None:
        target = self.out / f"frame_{i:03d}.{self.fmt}"
        if self.fmt == "png":
            data = iio.imwrite("<bytes>", to_srgb8(image, exposure), extension=".png", compress_level=PNG_LEVEL)
        if self.fmt == "png":
            atomic_write_bytes(target, data)
        else:
            try:
                write_hdr(target, image * np.float32(exposure))  # temporary file, then rename
            except InputError as exc:  # EnvmapError: the writer's words, as an output problem
                raise OutputError(str(exc)) from None
        self.written.append(target)

    def finish(self) -> None:
        pass

    def abort(self) -> None:
        for path in self.written:
            path.unlink(missing_ok=True)
        _remove_folders(self.created)

    def wrote(self) -> str:
        return f"{self.out}/frame_000.{self.fmt} ..."


class _VideoSink:
    """An H.264 MP4 through imageio-ffmpeg, encoded into a temporary file renamed at the end."""

    def __init__(self, out: Path, width: int, height: int, fps: float) -> None:
        try:
            import imageio_ffmpeg
        except ImportError:
            raise InputError(f"--format mp4 needs imageio-ffmpeg: {VIDEO_INSTALL}") from None
        self.ffmpeg = imageio_ffmpeg
        self.path = out if out.suffix.lower() == ".mp4" else out / "turntable.mp4"
        self.tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.mp4")
        self.fps = fps
        self.writer = None
        self.created: list[Path] = []

    def open(self) -> None:
        self.created = _make_folder(self.path.parent)

    def add(self, i: int, image: np.ndarray, exposure: float) -> None:
        frame = to_srgb8(image, exposure)
        # H.264 in yuv420p needs even sizes: repeat the last row / column of an odd one
        frame = np.ascontiguousarray(np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0)), mode="edge"))
        if self.writer is None:
            size = (frame.shape[1], frame.shape[0])
            self.writer = self.ffmpeg.write_frames(str(self.tmp), size, fps=self.fps, codec="libx264",
                                                   quality=8, macro_block_size=1, ffmpeg_log_level="error")  # fmt: skip
            self._call(self.writer.send, None)
        self._call(self.writer.send, frame)

    def _call(self, fn, *args) -> None:
        try:
            fn(*args)
        except (OSError, RuntimeError, StopIteration) as exc:
            raise OutputError(f"{self.path}: cannot encode the video ({' '.join(str(exc).split())[:200]})") from None

    def finish(self) -> None:
        if self.writer is not None:
            self._call(self.writer.close)
            self.writer = None
            try:
                os.replace(self.tmp, self.path)
            except OSError as exc:
                raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None

    def abort(self) -> None:
        if self.writer is not None:
            try:
                self.writer.close()
            except Exception:  # the encoder may have died already; the file goes anyway
                pass
        if self.writer is not None or self.created:  # the temporary exists only once encoding began
            self.tmp.unlink(missing_ok=True)
        _remove_folders(self.created)

    def wrote(self) -> str:
        return str(self.path)


def _remove_folders(created: list[Path]) -> None:
    for folder in reversed(created):
        try:
            folder.rmdir()
        except OSError:
            break


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
