"""``prt-train --device auto|cpu|cuda`` (issue 36): fits run where torch sees a GPU; the device keys no
cache and enters no file, so a CPU build is the same bytes with or without the flag; ``--device cuda``
without a GPU is one line, exit 2, nothing written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from prt.runtime.errors import InputError
from prt.train.networks.fit import FitSettings, resolve_device

SPOT = Path(__file__).resolve().parent / "data" / "spot.obj"


def test_device_keys_no_cache_and_resolves():
    assert FitSettings(device="cuda").cache_key() == FitSettings().cache_key()
    assert "device" not in FitSettings().cache_key()
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InputError, match="--device: expected one of auto, cpu, cuda"):
        resolve_device("tpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="torch sees a CUDA GPU here")
def test_cuda_without_a_gpu_is_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "scene"
    proc = subprocess.run([sys.executable, "-m", "prt.train.train_cli", str(SPOT), "-o", str(out), "--device", "cuda"],
                          capture_output=True, text=True)  # fmt: skip
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("prt-train: error: --device cuda: torch") and "no CUDA GPU" in lines[0]
    assert not out.exists()


def _build(out: Path, *flags: str) -> dict[str, bytes]:
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(SPOT), "-o", str(out), "--samples", "1000", "--validation", "200", "--rays", "8",
         "--segments", "1", "--hidden", "16", "--layers", "2", "--steps", "20", "--bounces", "0", "--no-progress", "--threads", "1", *flags],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    files = sorted([*out.glob("train/*.npz"), *out.glob("segments/*.onnx"), *out.glob("segments/*_weights.npy")])
    assert files
    return {f.relative_to(out).as_posix(): f.read_bytes() for f in files}


def test_a_cpu_build_is_the_same_bytes_with_and_without_the_flag(tmp_path):
    plain = _build(tmp_path / "plain")
    flagged = _build(tmp_path / "cpu", "--device", "cpu")
    assert plain.keys() == flagged.keys()
    assert all(plain[k] == flagged[k] for k in plain), [k for k in plain if plain[k] != flagged[k]]
    with np.load(tmp_path / "plain" / "train" / "seg000.npz") as a, np.load(tmp_path / "cpu" / "train" / "seg000.npz") as b:
        assert all(np.array_equal(a[k], b[k]) for k in a.files)
