"""The ONNX backend's providers (issue 36): names short or full, ``PRT_ONNX_PROVIDERS``, one line for a
provider this onnxruntime lacks (CUDA on a CPU build); the bound path a GPU provider takes (a segment's
rows in one call, output bound into the transfer array) against the sliced CPU path, bit for bit."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest

from prt.runtime.backends.onnx import OnnxTransfer, check_providers
from prt.runtime.errors import ArgumentTypeError, InputError
from prt.runtime.renderer import Renderer, Scene


def test_providers_by_short_or_full_name_and_from_the_environment(monkeypatch):
    monkeypatch.delenv("PRT_ONNX_PROVIDERS", raising=False)
    assert check_providers(None) is None  # the default: CUDA where present, then CPU
    assert check_providers(["cpu"]) == ["CPUExecutionProvider"]
    assert check_providers("CPU, CPUExecutionProvider") == ["CPUExecutionProvider"]
    monkeypatch.setenv("PRT_ONNX_PROVIDERS", "cpu")
    assert check_providers(None) == ["CPUExecutionProvider"]
    with pytest.raises(ArgumentTypeError):
        check_providers([1, 2])


@pytest.mark.skipif("CUDAExecutionProvider" in ort.get_available_providers(), reason="this onnxruntime has CUDA")
def test_cuda_where_there_is_none_is_one_line(monkeypatch):
    with pytest.raises(InputError) as info:
        check_providers(["cuda", "cpu"], "--onnx-providers")
    text = str(info.value)
    assert text.startswith("--onnx-providers: CUDAExecutionProvider not available") and "CPUExecutionProvider" in text and "\n" not in text
    monkeypatch.setenv("PRT_ONNX_PROVIDERS", "tensorrt")
    with pytest.raises(InputError, match="^PRT_ONNX_PROVIDERS: TensorrtExecutionProvider not available"):
        Renderer(Scene.load(), 8, 8)


def test_bound_path_equals_the_sliced_path():
    manifest = Scene.load().manifest
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (9000, 6)).astype(np.float32)
    segment = rng.integers(-1, len(manifest.segments), 9000)
    sliced, bound = OnnxTransfer(manifest, threads=2, slice_rows=1000), OnnxTransfer(manifest, threads=2, bound=True)
    try:
        assert not sliced.bound and bound.bound and bound._pool is None
        a, b = sliced.compute(x, segment), bound.compute(x, segment)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        assert bound.calls == 1
    finally:
        sliced.close()
        bound.close()
