"""prt-train --cluster: a real two-node Ray cluster on 127.0.0.1 gives a local build's bytes.

The cluster (a head and a second node, one CPU each) is started with ``ray start`` in a temporary
folder and stopped in a finaliser by the ids of its processes (``ray stop`` would stop every Ray
process on the machine, other people's too).  Artefacts are compared byte for byte, except the
JSON files that also record timings (``build.json``, ``precompute/precompute.json``,
``train/segNNN.json``, ``precompute/fits/*.json``), which are compared with the timing fields
(``timings``, ``seconds``, ``train_s``) left out.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
# 10 transfer chunks of 2048 samples x 128 rays and 3 segment fits: enough tasks to kill one.
BUILD = ["--samples", 20000, "--validation", 1500, "--rays", 128, "--epochs", 4, "--batch", 512,
         "--segments", 3, "--hidden", 16, "--layers", 2, "--no-analytic", "--threads", 1]  # fmt: skip
TIMING_FIELDS = {"timings", "seconds", "train_s"}
WITH_TIMINGS = ("build.json", "precompute/precompute.json", "train/seg*.json", "precompute/fits/*.json")


def prt_train(*args, **kwargs):
    cmd = [sys.executable, "-m", "prt.train.train_cli", str(DATA / "spot.obj"), *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, env=_env(), **kwargs)


def _env():
    return {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _processes() -> dict[int, tuple[int, str]]:
    """pid -> (parent pid, command line) of every process we can see."""
    out = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            out[int(entry.name)] = (int(stat.rsplit(")", 1)[1].split()[1]), cmdline)
    return out


def _cluster_pids(folder: str) -> set[int]:
    """The processes of the cluster in ``folder``: those naming it, and all their descendants."""
    procs = _processes()
    found = {pid for pid, (_, cmd) in procs.items() if folder in cmd and pid != os.getpid()}
    while True:
        more = {pid for pid, (ppid, _) in procs.items() if ppid in found} - found
        if not more:
            return found
        found |= more


def _stop_cluster(folder: str) -> None:
    for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 2.0)):
        pids = _cluster_pids(folder)
        for pid in pids:
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait
        while pids and time.monotonic() < deadline:
            pids = {pid for pid in pids if _state(pid) not in ("Z", "gone")}
            time.sleep(0.1)


def _state(pid: int) -> str:
    """The state letter of a process (``Z``: a zombie, done), or ``gone``."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return "gone"


@pytest.fixture(scope="module")
def cluster(request):
    """``(address, folder)`` of a head and a second node on 127.0.0.1, one CPU each."""
    pytest.importorskip("ray")
    ray_cli = Path(sys.executable).with_name("ray")
    folder = tempfile.mkdtemp(prefix="prtray-", dir="/tmp")  # short: Ray's socket paths have a length limit
    request.addfinalizer(lambda: (_stop_cluster(folder), shutil.rmtree(folder, ignore_errors=True)))  # set before starting: a failed start is cleaned up too
    port = _free_port()
    small = ["--num-cpus", "1", "--object-store-memory", str(80 * 2**20), "--disable-usage-stats"]
    head = [ray_cli, "start", "--head", "--port", str(port), "--temp-dir", folder,
            "--include-dashboard=false", *small]  # fmt: skip
    second = [ray_cli, "start", "--address", f"127.0.0.1:{port}", *small]
    for cmd in (head, second):
        proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=120)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    return f"127.0.0.1:{port}", folder


@pytest.fixture(scope="module")
def local_build(tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    proc = prt_train("-o", out, *BUILD, "--no-progress")
    assert proc.returncode == 0, proc.stderr
    return out


def _without_timings(value):
    if isinstance(value, dict):
        return {k: _without_timings(v) for k, v in value.items() if k not in TIMING_FIELDS}
    if isinstance(value, list):
        return [_without_timings(v) for v in value]
    return value


def assert_same_build(a: Path, b: Path) -> None:
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert any(f.suffix == ".onnx" for f in files) and any(f.name.startswith("chunk_") for f in files)
    for f in files:
        if any(f.match(pattern) for pattern in WITH_TIMINGS):
            assert _without_timings(json.loads((a / f).read_text())) == _without_timings(json.loads((b / f).read_text())), f
        else:
            assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_cluster_build_is_byte_identical_and_resumes_locally(cluster, local_build, tmp_path):
    address, _ = cluster
    out = tmp_path / "cluster"
    proc = prt_train("-o", out, *BUILD, "--cluster", address)
    assert proc.returncode == 0, proc.stderr
    # the driver counts the segments into the build's one progress line, drawn on a terminal only (tests/test_progress.py)
    assert "\r" not in proc.stderr and "\r" not in proc.stdout
    assert_same_build(local_build, out)
    # The driver wrote the same caches a local run does: a local rerun finds everything done.
    again = prt_train("-o", out, *BUILD, "--no-progress")
    assert again.returncode == 0, again.stderr
    assert "up to date" in again.stdout and again.stdout.count(": cached") == 3


def test_a_worker_killed_mid_run_is_retried(cluster, local_build, tmp_path):
    address, folder = cluster
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "prt.train.train_cli", str(DATA / "spot.obj"), "-o", str(out), *map(str, BUILD),
           "--cluster", address, "--no-progress"]  # fmt: skip
    driver = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    killed = None
    try:
        deadline = time.monotonic() + 90
        while killed is None and driver.poll() is None and time.monotonic() < deadline:
            # A worker's title is ray::<function> while it runs a task (ray::IDLE otherwise).
            busy = [pid for pid in _cluster_pids(folder) if _processes().get(pid, (0, ""))[1].startswith("ray::_run_task")]
            if busy:
                killed = busy[0]
                os.kill(killed, signal.SIGKILL)
            time.sleep(0.02)
        stdout, stderr = driver.communicate(timeout=180)
    finally:
        if driver.poll() is None:
            driver.kill()
    assert killed is not None, "no task was seen running"
    assert driver.returncode == 0, stderr
    assert_same_build(local_build, out)


def test_precompute_on_the_cluster(cluster, tmp_path):
    address, _ = cluster
    quick = [str(DATA / "spot.obj"), "--samples", "4096", "--validation", "1000", "--rays", "16", "--no-progress"]
    runs = {}
    for name, extra in (("local", []), ("cluster", ["--cluster", address])):
        cmd = [sys.executable, "-m", "prt.train.precompute_cli", *quick, "-o", str(tmp_path / name), *extra]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=_env())
        assert proc.returncode == 0, proc.stderr
        runs[name] = tmp_path / name
    assert (runs["local"] / "samples.npz").read_bytes() == (runs["cluster"] / "samples.npz").read_bytes()


@pytest.mark.parametrize("command", ["prt-train", "prt-precompute", "prt-bench"])
def test_cluster_without_ray_says_how_to_install(command, monkeypatch, tmp_path, capsys):
    from prt.bench.cli import main as bench
    from prt.train.precompute_cli import main as precompute
    from prt.train.train_cli import main as train

    main = {"prt-train": train, "prt-precompute": precompute, "prt-bench": bench}[command]
    target = [str(tmp_path / "scene.json")] if command == "prt-bench" else [str(DATA / "spot.obj"), "-o", str(tmp_path / "out")]
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert main([*target, "--cluster", "auto"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{command}: error: --cluster needs Ray")
    assert err[0].endswith('pip install "prt-runtime[cluster]"')


def test_unreachable_cluster_fails_in_one_line(tmp_path, capsys):
    pytest.importorskip("ray")
    from prt.train.precompute_cli import main

    # Ray itself would retry for minutes; a closed port is reported at once.
    assert main([str(DATA / "spot.obj"), "-o", str(tmp_path / "out"), "--cluster", f"127.0.0.1:{_free_port()}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no Ray cluster answers there" in err[0]
