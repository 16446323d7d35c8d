"""The prepared GPU check (``studies/gpu_check.py``, issue 36) runs end to end here in its reduced mode
(toy sizes, llvmpipe, torch on the CPU), with the packages the lent GPU machine's image lacks blocked
(so it needs only what travels), and refuses to write ``docs/benchmarks/gpu.json`` without a GPU."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "studies" / "gpu_check.py"
RECORD = ROOT / "docs" / "benchmarks" / "gpu.json"
# Not in the H200 image (device README, KINDS.md) and not carried: nothing the check imports may need them.
ABSENT = ("trimesh", "embreex", "xatlas", "ray", "pygame", "imageio_ffmpeg", "OpenEXR")
RUNNER = f"""
import runpy, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {ABSENT!r}:
            raise ImportError(f'{{name}} is not on the GPU machine')
sys.meta_path.insert(0, Block())
sys.argv = [{str(SCRIPT)!r}, *sys.argv[1:]]
runpy.run_path({str(SCRIPT)!r}, run_name='__main__')
"""


def test_reduced_run_writes_every_part(tmp_path):
    out = tmp_path / "trial" / "gpu.json"
    proc = subprocess.run([sys.executable, "-c", RUNNER, "--reduced", "--json", str(out)], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    report = json.loads(out.read_text())
    assert "llvmpipe" in report["renderer"] and report["reduced"] is True
    assert {"date", "command", "machine", "commit"} <= set(report["provenance"])
    rows = report["frames"]
    for scene in ("demo", "bounce"):
        for size in ("24x24", "32x32", "40x24"):
            engines = {r["engine"].split(" ")[0] for r in rows if r["scene"] == scene and r["size"] == size}
            assert {"glsl", "onnxruntime", "onnx", "torch"} <= engines, (scene, size, engines)
    glsl = [r for r in rows if r["engine"] == "glsl"]
    assert all(r["frame_ms"] > 0 and r["relight_ms"] > 0 and r["readback_ms"] > 0 and "llvmpipe" in r["renderer"] for r in glsl)
    standin = [r["standin"] for r in rows if "standin" in r]
    assert standin and all(s["fp32_vs_onnxruntime_db"] > 90 for s in standin)  # torch computes the ONNX files' function
    assert report["fit"]["runs"]["cpu"]["steps"] == 5 and report["limits"]["fp32_gflops"] > 0
    assert all(t["met"] == "n/a (reduced run)" for t in report["targets"].values())
    assert "| demo | 24x24 | glsl |" in out.with_suffix(".md").read_text()


@pytest.mark.skipif(torch.cuda.is_available(), reason="torch sees a CUDA GPU: the check may write the record here")
def test_refuses_the_record_without_a_gpu(tmp_path):
    before = RECORD.read_bytes() if RECORD.exists() else None
    proc = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, cwd=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "refusing to write docs/benchmarks/gpu.json" in lines[0], proc.stderr
    assert (RECORD.read_bytes() if RECORD.exists() else None) == before
    proc = subprocess.run([sys.executable, str(SCRIPT), "--reduced"], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 2 and "--reduced needs --json" in proc.stderr
