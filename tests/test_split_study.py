"""``prt-train --split residual`` end to end, and the per-segment image error study on its build."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).parent / "data"
QUICK = ["--samples", 4000, "--validation", 1000, "--rays", 32, "--epochs", 3, "--batch", 512, "--bounces", 0, "--no-progress",
         "--segments", 4, "--hidden", 16, "--layers", 2, "--no-analytic"]  # fmt: skip


@pytest.fixture(scope="module")
def residual_build(tmp_path_factory):
    out = tmp_path_factory.mktemp("spot-residual")
    cmd = [sys.executable, "-m", "prt.train.train_cli", str(DATA / "spot.obj"), "-o", str(out), "--split", "residual", *map(str, QUICK)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return out


def test_the_split_rule_reaches_the_precompute_and_the_manifest_segments_follow_it(residual_build):
    pre = json.loads((residual_build / "precompute" / "precompute.json").read_text())
    assert pre["settings"]["split"] == "residual"
    built = json.loads((residual_build / "build.json").read_text())
    assert built["spec"]["split"] == "residual"
    sizes = [s["samples"] for s in built["segments"]]
    assert len(sizes) >= 2 and sum(sizes) == 4000


def test_segment_error_shares_add_up_to_the_image_error(bench_module, residual_build, tmp_path):
    study = bench_module("segment_error_share")
    res = study.measure(residual_build, views=2, size=48, rays=16)
    rows = res["segments"]
    assert res["covered_pixels"] > 200 and len(rows) >= 2
    assert sum(r["pixel_share"] for r in rows) == pytest.approx(1.0)
    assert sum(r["error_share"] for r in rows) == pytest.approx(1.0)
    # the segments' own errors, weighted by their pixels, are the image's error
    mse = sum(r["pixel_share"] * 10 ** (-r["psnr_db"] / 10) for r in rows)
    assert 10 * np.log10(1 / mse) == pytest.approx(res["psnr_db"], abs=1e-6)
    # an exact segment can only raise the PSNR, the most where the error share is largest
    assert all(r["psnr_if_exact_db"] >= res["psnr_db"] for r in rows)
    assert rows[0]["psnr_if_exact_db"] == max(r["psnr_if_exact_db"] for r in rows)
    # the command line writes the report and the crop image
    assert study.main([str(residual_build), "--views", "1", "--size", "48", "--rays", "16", "--json", str(tmp_path / "r.json"),
                       "--md", str(tmp_path / "r.md"), "--png", str(tmp_path / "r.png")]) == 0  # fmt: skip
    assert "squared error %" in (tmp_path / "r.md").read_text() and (tmp_path / "r.png").stat().st_size > 100
    assert len(json.loads((tmp_path / "r.json").read_text())["results"][0]["segments"]) >= 2
