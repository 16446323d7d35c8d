"""Choosing the GL device (issue 36): EGL device enumeration, the choice (auto, an index, a name,
``PRT_GL_DEVICE``), the one-line errors of the commands, and which renderer every report names.

This machine has one EGL device (Mesa's llvmpipe); the choice among several is checked on a list
of devices given to :func:`resolve_device` (its opener records which it opened).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from prt.runtime import gl_devices
from prt.runtime.errors import InputError
from prt.runtime.gl import context_info, create_context, list_devices
from prt.runtime.gl_devices import EglDevice, egl_devices, resolve_device

ROOT = Path(__file__).resolve().parents[1]


def test_this_machine_lists_llvmpipe_as_a_software_device():
    devices = egl_devices()
    assert devices, "EGL lists no device (EGL_EXT_device_enumeration missing?)"
    described = list_devices()
    assert [d["index"] for d in described] == [d.index for d in devices]
    soft = [d for d in described if "llvmpipe" in (d["renderer"] or "")]
    assert soft and all(d["software"] for d in soft), described


@pytest.mark.parametrize("spec", ["auto", "0", 0, "llvmpipe", "LLVMpipe", "mesa"])
def test_contexts_on_the_device_chosen(spec, monkeypatch):
    monkeypatch.delenv("PRT_GL_DEVICE", raising=False)
    ctx = create_context(device=spec)
    try:
        assert "llvmpipe" in context_info(ctx)["renderer"]
    finally:
        ctx.release()


@pytest.mark.parametrize("spec, message", [("nvidia", "no EGL device has that name"), ("7", "no such EGL device"), ("-1", "no such EGL device")])
def test_a_device_that_is_not_there_is_one_line_naming_the_devices(spec, message):
    with pytest.raises(InputError) as info:
        create_context(device=spec, origin="--gl-device")
    text = str(info.value)
    assert text.startswith(f"--gl-device {spec!r}" if not spec.lstrip("-").isdigit() else f"--gl-device {spec}")
    assert message in text and "llvmpipe" in text and "\n" not in text


def test_the_environment_variable_chooses_when_the_caller_does_not(monkeypatch):
    monkeypatch.setenv("PRT_GL_DEVICE", "no-such-gpu")
    with pytest.raises(InputError, match="^PRT_GL_DEVICE 'no-such-gpu': no EGL device"):
        create_context()
    ctx = create_context(device="llvmpipe")  # the caller's spec wins over the variable
    ctx.release()
    monkeypatch.setenv("PRT_GL_DEVICE", "0")
    ctx = create_context()
    ctx.release()


class _Ctx:
    def __init__(self, renderer, vendor="v"):
        self.info = {"GL_RENDERER": renderer, "GL_VENDOR": vendor}
        self.released = False

    def release(self):
        self.released = True


def _opener(renderers, broken=()):
    opened = []

    def open_context(index):
        opened.append(index)
        if index in broken:
            raise RuntimeError("eglInitialize failed")
        return _Ctx(renderers[index])

    return open_context, opened


def test_auto_takes_the_gpu_before_llvmpipe_and_falls_back_when_it_fails(monkeypatch):
    # glvnd lists every vendor's devices in no promised order: llvmpipe may well be device 0.
    devices = (EglDevice(0, ("EGL_MESA_device_software",)), EglDevice(1, ("EGL_NV_device_cuda", "EGL_EXT_device_drm")))
    monkeypatch.setattr(gl_devices, "egl_devices", lambda: devices)
    monkeypatch.delenv("PRT_GL_DEVICE", raising=False)
    renderers = {0: "llvmpipe (LLVM 15.0.6, 256 bits)", 1: "NVIDIA H200/PCIe/SSE2"}
    open_context, opened = _opener(renderers)
    assert resolve_device("auto", open_context).info["GL_RENDERER"].startswith("NVIDIA") and opened == [1]
    open_context, opened = _opener(renderers, broken={1})  # a GPU whose driver gives no context
    assert "llvmpipe" in resolve_device(None, open_context).info["GL_RENDERER"] and opened == [1, 0]
    open_context, opened = _opener(renderers)
    assert "llvmpipe" in resolve_device("0", open_context).info["GL_RENDERER"]
    open_context, opened = _opener(renderers)
    found = resolve_device("h200", open_context)  # by name: contexts opened until one matches, the others released
    assert found.info["GL_RENDERER"] == "NVIDIA H200/PCIe/SSE2" and opened == [0, 1]


def test_without_device_enumeration_the_default_display_is_used(monkeypatch):
    monkeypatch.setattr(gl_devices, "egl_devices", lambda: ())
    open_context, opened = _opener({None: "llvmpipe"})
    resolve_device("auto", open_context)
    resolve_device("0", open_context)
    assert opened == [None, None]
    with pytest.raises(InputError, match="no such EGL device"):
        resolve_device("1", open_context)


def _run(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=kwargs.pop("cwd", None), **kwargs)


def test_commands_refuse_a_missing_device_or_provider_in_one_line_writing_nothing(tmp_path):
    out = tmp_path / "frames"
    cases = [
        (["prt.runtime.cli", "--headless", "--frames", "1", "--size", "16", "--out", str(out), "--gl-device", "nvidia"], "--gl-device 'nvidia'"),
        (["prt.runtime.cli", "--headless", "--frames", "1", "--size", "16", "--out", str(out), "--onnx-providers", "cuda,cpu"],
         "--onnx-providers: CUDAExecutionProvider not available"),
        (["prt.bench.cli", str(ROOT / "runtime" / "data" / "demo"), "--json", str(tmp_path / "b.json"), "--gl-device", "3"], "--gl-device 3"),
    ]  # fmt: skip
    for argv, start in cases:
        proc = _run(*argv)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and start in lines[0], (argv, proc.stderr)
        assert "Traceback" not in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_headless_report_names_the_renderer(tmp_path):
    proc = _run("prt.runtime.cli", "--headless", "--frames", "1", "--size", "16", "--out", str(tmp_path / "f"), "--backend", "glsl",
                "--gl-device", "llvmpipe")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "backend glsl on llvmpipe" in proc.stdout and "read back" in proc.stdout
