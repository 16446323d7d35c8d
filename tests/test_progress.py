"""The build's one progress display: its arithmetic on a fake clock, drawn on a pseudo-terminal only, silent into a pipe."""

from __future__ import annotations

import os
import select
import subprocess
import sys
from pathlib import Path

import pytest

from prt.train.progress import BOUNCE_RAY, RAY, STEP_OVERHEAD, BuildProgress, format_seconds, progress_bar, step_cost

DATA = Path(__file__).parent / "data"


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _pty_stream():
    master, slave = os.openpty()
    return master, os.fdopen(slave, "w")


def _read_all(fd) -> str:
    out = b""
    while select.select([fd], [], [], 0.1)[0]:
        try:
            chunk = os.read(fd, 65536)
        except OSError:  # the other end closed (Linux pty: EIO)
            break
        if not chunk:
            break
        out += chunk
    return out.decode(errors="replace")


def test_the_share_done_is_weighted_by_the_work_counts_across_stages():
    clock = Clock()
    p = BuildProgress(enabled=False, clock=clock)
    p.expect("precompute", 1000 * RAY)
    p.expect("bounces", 10 * BOUNCE_RAY)
    p.expect("export", 70.0)
    total = 1000 + 10 * BOUNCE_RAY + 70
    bar = p.bar("precompute", "transfer", 1000, unit_cost=RAY)
    bar.update(500)
    assert p.fraction() == pytest.approx(500 / total)
    bar.update(500)
    p.finish("precompute")
    bar = p.bar("bounces", "bounce rays", 10, unit_cost=BOUNCE_RAY)
    bar.update(5)
    assert p.fraction() == pytest.approx((1000 + 5 * BOUNCE_RAY) / total)  # not a bar restarting at 0 %
    assert p.current == "bounces" and "bounce rays 50%" in p.line()


def test_time_left_comes_from_the_measured_rates():
    clock = Clock()
    p = BuildProgress(enabled=False, clock=clock)
    p.expect("precompute", 1000.0)
    p.expect("fits", 3000.0)
    bar = p.bar("precompute", "transfer", 1000)
    assert p.seconds_left() is None  # nothing measured yet: no guess
    clock.t = 10.0
    bar.update(250)  # 25 units per second
    # the current stage at its own rate, the later one at the build's rate so far (the same here)
    assert p.seconds_left() == pytest.approx(750 / 25 + 3000 / 25)
    bar.update(750)
    clock.t = 20.0  # 1000 units in 20 s: 50 per second
    p.finish("precompute")
    fit = p.bar("fits", "segment 0", unit_cost=10.0)
    clock.t = 30.0
    fit.update(50)  # 500 units in 10 s: fits run at 50 per second too
    assert p.seconds_left() == pytest.approx(2500 / 50)
    assert "left" in p.line() and "fits: segment 0" in p.line()


def test_cached_work_counts_as_done_but_not_into_the_rate():
    clock = Clock()
    p = BuildProgress(enabled=False, clock=clock)
    p.expect("precompute", 1000.0)
    bar = p.bar("precompute", "transfer", 1000, initial=900)  # 900 rays' chunks read from the cache
    assert p.fraction() == pytest.approx(0.9)
    clock.t = 10.0
    bar.update(50)
    assert p.seconds_left() == pytest.approx(50 / 5.0)  # 5 per second, not 95
    # the same chunk store read again (bounces auto, then the bounce stage) does not count twice
    p.expect("bounces", 100.0)
    p.bar("bounces", "rays", 10, unit_cost=10.0, initial=10)
    p.bar("bounces", "rays", 10, unit_cost=10.0, initial=10)
    assert p.stages["bounces"].done == 100.0


def test_the_fit_plan_follows_the_segments_as_they_finish():
    p = BuildProgress(enabled=False, clock=Clock())
    p.plan_fits({0: 100.0, 1: 100.0}, batch=1000)
    assert p.stages["fits"].planned == 200.0
    p.add("fits", 40.0)
    p.segment_done(0)  # it took 40, not 100
    assert p.stages["fits"].planned == 140.0
    assert step_cost(5000, 1000) == pytest.approx(3 * 5000 * 1000 / 5000 + STEP_OVERHEAD)
    assert step_cost(5000, 2000) - step_cost(5000, 1000) == pytest.approx(3 * 5000 * 1000 / 5000)  # the FLOPs scale, the overhead not


def test_the_line_is_drawn_on_a_terminal_and_cleared_at_the_end():
    master, stream = _pty_stream()
    try:
        clock = Clock()
        p = BuildProgress(stream=stream, clock=clock, interval=0.0)
        assert p.enabled
        p.expect("precompute", 100.0)
        bar = p.bar("precompute", "transfer", 100)
        clock.t = 2.0
        bar.update(50)
        p.log("a log line")
        p.close()
        stream.flush()
        text = _read_all(master)
    finally:
        stream.close()
        os.close(master)
    assert "\r[" in text and " 50% | precompute: transfer 50% | 2s left" in text
    assert "\r\x1b[K" in text  # cleared before the log line and at the end


@pytest.mark.parametrize("enabled", [True, False])
def test_nothing_is_written_into_a_pipe_nor_with_no_progress(enabled):
    read, write = os.pipe()
    stream = os.fdopen(write, "w")
    try:
        p = BuildProgress(enabled=enabled, stream=stream, interval=0.0)
        assert not p.enabled
        p.expect("fits", 10.0)
        p.bar("fits", "segment 0", 10).update(5)
        p.close()
        stream.flush()
        assert _read_all(read) == ""
    finally:
        stream.close()
        os.close(read)
    if not enabled:  # and not on a terminal either
        master, tty = _pty_stream()
        try:
            p = BuildProgress(enabled=False, stream=tty, interval=0.0)
            p.bar("fits", "segment 0", 10).update(5)
            tty.flush()
            assert _read_all(master) == ""
        finally:
            tty.close()
            os.close(master)


def test_progress_bar_picks_the_display_a_tqdm_bar_or_none():
    p = BuildProgress(enabled=False)
    assert progress_bar(p, "precompute", "transfer", 10, unit="ray").display is p
    assert progress_bar(False, "precompute", "transfer", 10, unit="ray") is None
    bar = progress_bar(True, "precompute", "transfer", 10, unit="ray", disable=True)
    assert type(bar).__name__ == "tqdm"
    bar.close()
    assert format_seconds(59) == "59s" and format_seconds(200) == "3m20s" and format_seconds(3720) == "1h02m"


def test_prt_train_draws_one_line_for_the_whole_build_on_a_terminal_and_nothing_into_a_pipe(tmp_path):
    args = [sys.executable, "-m", "prt.train.train_cli", str(DATA / "spot.obj"), "--samples", "3000", "--validation", "1000", "--rays", "32",
            "--segments", "2", "--steps", "30", "--batch", "512", "--bounces", "1", "--bounce-rays", "4", "--threads", "1"]  # fmt: skip
    master, slave = os.openpty()
    try:
        proc = subprocess.Popen([*args, "-o", str(tmp_path / "tty")], stdout=subprocess.DEVNULL, stderr=slave)
        os.close(slave)
        chunks = []
        while proc.poll() is None:
            chunks.append(_read_all(master))
        chunks.append(_read_all(master))
    finally:
        os.close(master)
    assert proc.returncode == 0
    text = "".join(chunks)
    lines = [part for part in text.split("\r") if part.startswith("[")]
    for stage in ("precompute", "bounces", "vertices", "fits", "export"):  # the vertex estimate's rays under their own stage
        assert any(f"| {stage}" in s for s in lines), stage
    assert any("| precompute: transfer" in s for s in lines) and any("| fits: segment 0" in s for s in lines)
    shares = [int(s.split("]")[1].split("%")[0]) for s in lines]
    assert shares[-1] >= 90 and shares == sorted(shares)  # one display from start to end, never restarting
    piped = subprocess.run([*args, "-o", str(tmp_path / "pipe")], capture_output=True, text=True)
    assert piped.returncode == 0, piped.stderr
    assert "\r" not in piped.stderr and "\r" not in piped.stdout and "time:" in piped.stdout
