"""Which device a headless OpenGL context runs on: EGL device enumeration and the choice.

A headless context (:func:`prt.runtime.gl.create_context`) is made on one EGL device
(``EGL_EXT_device_enumeration`` + ``EGL_EXT_platform_device``; moderngl's ``device_index``).  With
libglvnd the list holds every vendor's devices: on a machine with an NVIDIA GPU and Mesa, the GPU
and Mesa's software rasteriser (llvmpipe, marked ``EGL_MESA_device_software``), in an order
nobody promises, so "device 0" may well be llvmpipe.  The choice (:func:`resolve_device`):

- ``auto`` (the default): the first device that is not a software rasteriser and gives a context,
  else the software one: the GPU where there is one, llvmpipe otherwise;
- an index (``"1"``): that device;
- a name (``"llvmpipe"``, ``"nvidia"``, ``"H200"``): the first device whose GL_RENDERER or
  GL_VENDOR contains it (case ignored), found by opening a context on each device.

The spec comes from the caller (``prt-runtime --gl-device``, ``prt-bench --gl-device``,
``Renderer(gl_device=...)``), else from the environment variable :data:`ENV_VAR`, else ``auto``.
A spec that names no device is an :class:`~prt.runtime.errors.InputError` naming the devices there are.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
from dataclasses import dataclass

from .errors import InputError

__all__ = ["ENV_VAR", "EglDevice", "egl_devices", "device_spec", "resolve_device", "describe_devices"]

ENV_VAR = "PRT_GL_DEVICE"
"""Environment variable naming the EGL device of headless contexts (an index or a name), for embedders."""

_EGL_EXTENSIONS = 0x3055
_EGL_DRM_DEVICE_FILE = 0x3233
_SOFTWARE = "EGL_MESA_device_software"


@dataclass(frozen=True)
class EglDevice:
    """One EGL device as the driver lists it (no context opened).

    Attributes
    ----------
    index : int
        Its position in ``eglQueryDevicesEXT``'s list (moderngl's ``device_index``).
    extensions : tuple of str
        The device's EGL extensions (``EGL_MESA_device_software`` marks a software rasteriser,
        ``EGL_NV_device_cuda`` an NVIDIA GPU).
    drm : str or None
        Its DRM device file, where the driver says.
    """

    index: int
    extensions: tuple[str, ...]
    drm: str | None = None

    @property
    def software(self) -> bool:
        return _SOFTWARE in self.extensions


@functools.lru_cache(maxsize=1)
def egl_devices() -> tuple[EglDevice, ...]:
    """The EGL devices of this machine, in the driver's order; empty where EGL or its device
    enumeration is missing (a context is then made on EGL's default display)."""
    name = ctypes.util.find_library("EGL")
    if name is None:
        return ()
    try:
        egl = ctypes.CDLL(name)
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        query = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
        query_string = egl.eglGetProcAddress(b"eglQueryDeviceStringEXT")
    except (OSError, AttributeError):
        return ()
    if not query:
        return ()
    devices_fn = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int))(query)
    count = ctypes.c_int(0)
    if not devices_fn(0, None, ctypes.byref(count)) or count.value < 1:
        return ()
    handles = (ctypes.c_void_p * count.value)()
    if not devices_fn(count.value, handles, ctypes.byref(count)):
        return ()
    string_fn = ctypes.CFUNCTYPE(ctypes.c_char_p, ctypes.c_void_p, ctypes.c_int)(query_string) if query_string else None
    out = []
    for i in range(count.value):
        extensions, drm = (), None
        if string_fn is not None:
            text = string_fn(handles[i], _EGL_EXTENSIONS) or b""
            extensions = tuple(text.decode(errors="replace").split())
            if "EGL_EXT_device_drm" in extensions:
                drm = (string_fn(handles[i], _EGL_DRM_DEVICE_FILE) or b"").decode(errors="replace") or None
        out.append(EglDevice(i, extensions, drm))
    return tuple(out)


def device_spec(spec: str | int | None = None) -> str:
    """The device spec in force: ``spec`` if given, else :data:`ENV_VAR`, else ``"auto"``
    (stripped; an empty value counts as unset)."""
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        spec = os.environ.get(ENV_VAR, "").strip() or "auto"
    if isinstance(spec, bool) or not isinstance(spec, (str, int)):
        raise InputError(f"gl device: expected an index or a name, got {type(spec).__name__} {spec!r}")
    return str(spec).strip()


def resolve_device(spec: str | int | None, open_context, *, origin: str = "gl_device"):
    """Open a context on the device ``spec`` chooses.

    Parameters
    ----------
    spec : str, int or None
        ``auto``, an index or a name (see the module docstring); None: :data:`ENV_VAR` or ``auto``.
    open_context : callable(device_index or None) -> moderngl.Context
        Opens a context on a device (None: EGL's default); raises on failure.
    origin : str
        What the spec came from, for messages (``--gl-device``, ``PRT_GL_DEVICE``).

    Returns
    -------
    moderngl.Context

    Raises
    ------
    InputError
        The spec names no device (one line listing the devices there are).
    """
    given = spec is not None and not (isinstance(spec, str) and not spec.strip())
    text = device_spec(spec)
    if not given and text != "auto":
        origin = ENV_VAR
    devices = egl_devices()
    if text.lower() == "auto":
        if not devices:
            return open_context(None)
        order = [d for d in devices if not d.software] + [d for d in devices if d.software]
        failure = None
        for device in order:
            try:
                return open_context(device.index)
            except Exception as exc:  # a GPU device without a usable driver: try the next one
                failure = exc
        raise failure
    if text.lstrip("-").isdigit():
        index = int(text)
        count = len(devices)
        if not 0 <= index < max(count, 1) or (not devices and index != 0):
            raise InputError(f"{origin} {text}: no such EGL device ({_listing(open_context)})")
        return open_context(index if devices else None)
    wanted = text.lower()
    for device in devices or (EglDevice(0, ()),):
        try:
            ctx = open_context(device.index if devices else None)
        except Exception:  # cannot open this one: it cannot be the one named
            continue
        renderer, vendor = ctx.info.get("GL_RENDERER", ""), ctx.info.get("GL_VENDOR", "")
        if wanted in renderer.lower() or wanted in vendor.lower():
            return ctx
        ctx.release()
    raise InputError(f"{origin} {text!r}: no EGL device has that name ({_listing(open_context)})")


def describe_devices(open_context) -> list[dict]:
    """Each device with its GL renderer and vendor (a context opened and released on each):
    ``[{"index", "renderer", "vendor", "software", "drm"}]``; a device that gives no context
    has renderer None and ``error``."""
    out = []
    for device in egl_devices() or (EglDevice(0, ()),):
        entry = {"index": device.index, "software": device.software, "drm": device.drm}
        try:
            ctx = open_context(device.index if egl_devices() else None)
        except Exception as exc:
            entry.update(renderer=None, vendor=None, error=" ".join(str(exc).split())[:200])
        else:
            entry.update(renderer=ctx.info.get("GL_RENDERER", ""), vendor=ctx.info.get("GL_VENDOR", ""))
            ctx.release()
        out.append(entry)
    return out


def _listing(open_context) -> str:
    devices = describe_devices(open_context)
    names = ", ".join(f"{d['index']}: {d['renderer'] or 'no context'}" for d in devices)
    return f"this machine has {len(devices)}: {names}" if devices else "this machine lists no EGL devices"
