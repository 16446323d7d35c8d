"""The precompute CLI end to end: outputs, reuse, interruption (SIGINT and SIGKILL), bad input."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from prt.train.transport.precompute import PrecomputeSettings
from prt.train.precompute_cli import build_parser, main, settings_from_args

DATA = Path(__file__).parent / "data"
CORNELL = str(DATA / "CornellBox-Original.obj")


def cli(*args, **kwargs):
    return subprocess.run(
        [sys.executable, "-m", "prt.train.precompute_cli", *map(str, args)], capture_output=True, text=True, **kwargs
    )


def start(*args):
    return subprocess.Popen(
        [sys.executable, "-m", "prt.train.precompute_cli", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def wait_for_chunks(folder: Path, count: int, proc, timeout: float = 60.0) -> None:
    t0 = time.time()
    while len(list(folder.glob("cache/*/chunk_*.npy"))) < count:
        assert proc.poll() is None, "the run ended before it could be interrupted"
        assert time.time() - t0 < timeout
        time.sleep(0.02)


def test_outputs_and_reuse(tmp_path):
    out = tmp_path / "cornell"
    proc = cli(CORNELL, "-o", out, "--samples", 3000, "--rays", 32, "--segments", 10, "--no-progress")
    assert proc.returncode == 0, proc.stderr
    assert "segment" in proc.stdout and "Mrays/s" in proc.stdout
    summary = json.loads((out / "precompute.json").read_text())
    with np.load(out / "samples.npz") as f:
        assert f["transfer"].shape == (3000, 16)
        assert f["segment"].min() >= 0
        assert np.isfinite(f["transfer"]).all()
    with np.load(out / "validation.npz") as f:
        assert f["transfer"].shape == (1000, 16)
        assert f["segment"].min() >= 0
    assert summary["validation_samples"] == 1000
    assert len(summary["segments"]) >= 1
    image = iio.imread(out / "preview.png")
    assert image.ndim == 3 and image.mean() > 5  # something was drawn
    again = cli(CORNELL, "-o", out, "--samples", 3000, "--rays", 32, "--segments", 10, "--no-progress")
    assert again.returncode == 0 and "up to date" in again.stdout


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_an_interrupted_run_resumes_bit_identically(tmp_path, sig):
    args = ["--samples", 24000, "--rays", 512, "--segments", 4, "--no-progress", "--threads", 1]
    whole = cli(CORNELL, "-o", tmp_path / "whole", *args)
    assert whole.returncode == 0, whole.stderr

    out = tmp_path / "interrupted"
    proc = start(CORNELL, "-o", out, *args)
    wait_for_chunks(out, 3, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    if sig == signal.SIGINT:
        assert proc.returncode == 130
        assert "resume" in err and len(err.strip().splitlines()) == 1
    else:
        assert proc.returncode == -signal.SIGKILL
    done = len(list(out.glob("cache/*/chunk_*.npy")))
    assert 3 <= done < 12 + 1  # 12 training chunks of 2048 (+ validation): it stopped part-way
    assert not (out / "samples.npz").exists()
    resumed = cli(CORNELL, "-o", out, *args)
    assert resumed.returncode == 0, resumed.stderr
    with np.load(tmp_path / "whole" / "samples.npz") as a, np.load(out / "samples.npz") as b:
        for key in a.files:
            assert np.array_equal(a[key], b[key]), key


def test_bad_input_gives_one_line_and_no_output(tmp_path, capsys):
    cases = {
        "unknown": ["no_such_scene_or_file", "-o", tmp_path / "a"],
        "corrupt": [tmp_path / "bad.obj", "-o", tmp_path / "b"],
        "unwritable": [CORNELL, "-o", tmp_path / "file.txt" / "sub"],
        "zero rays": [CORNELL, "-o", tmp_path / "c", "--rays", 0],
        "corrupt envmap": [CORNELL, "-o", tmp_path / "d", "--envmap", tmp_path / "sky.hdr"],
        "missing envmap": [CORNELL, "-o", tmp_path / "e", "--envmap", tmp_path / "nope.hdr"],
    }
    (tmp_path / "sky.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 8\n\x01\x02")
    (tmp_path / "bad.obj").write_bytes(b"v 0 0 0\nf 1 2 9\n\x00\xff garbage")
    (tmp_path / "file.txt").write_text("not a folder")
    for name, args in cases.items():  # in-process: the command's own error handling, without start-up time
        assert main([*map(str, args), "--samples", "100", "--no-progress"]) == 2, name
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("prt-precompute: error:"), (name, err)
    for folder in "bd":
        assert not (tmp_path / folder / "samples.npz").exists()
    assert "bad.obj" in cli(*cases["corrupt"], "--no-progress").stderr


def test_options_map_onto_the_settings():
    """Every option of the settings table lands in its PrecomputeSettings field; defaults are the dataclass's."""
    assert settings_from_args(build_parser().parse_args(["x"])) == PrecomputeSettings()
    args = build_parser().parse_args(
        ["x", "--samples", "7", "--validation", "3", "--rays", "5", "--bands", "3", "--segments", "2", "--delta", "0.1",
         "--merge-tolerance", "0.2", "--no-merge", "--no-object-split", "--seed", "9"]
    )  # fmt: skip
    assert settings_from_args(args) == PrecomputeSettings(
        samples=7, validation=3, rays=5, bands=3, segments=2, delta=0.1, merge_tolerance=0.2, merge=False, by_object=False, seed=9
    )
