"""Where a recorded figure comes from: date, command, machine, commit.

Every benchmark file under ``docs/benchmarks/`` written from now on carries
``"provenance": provenance()``; the results pages (``docs/gen_results.py``) show it beside each
figure.  CPUs of one name differ in what matters here (an "AMD EPYC" may or may not have
AVX-512 and VNNI), so the machine names its instruction-set extensions too.

- :func:`provenance`   ``{"date", "command", "machine", "commit"}``
- :func:`machine_info` CPU model, cores, the extensions that change kernels (AVX2, AVX-512, VNNI, AMX)
- :func:`cpu_label`    one line: ``"AMD EPYC (2 cores; AVX2 AVX-512 VNNI)"``
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

__all__ = ["provenance", "machine_info", "cpu_label", "cpu_extensions"]

# /proc/cpuinfo flag -> the name a reader knows; the kernels of numpy, ONNX Runtime, torch and
# llvmpipe differ by these.
_EXTENSIONS = {
    "avx2": "AVX2", "fma": "FMA", "avx512f": "AVX-512", "avx512_vnni": "VNNI", "avx_vnni": "AVX-VNNI",
    "avx512_bf16": "AVX512-BF16", "amx_tile": "AMX",
}  # fmt: skip


def _cpuinfo() -> dict[str, str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {}
    info = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            if info:
                break  # the first processor is enough
            continue
        info.setdefault(key.strip(), value.strip())
    return info


def cpu_extensions() -> list[str]:
    """The instruction-set extensions of :data:`_EXTENSIONS` that this CPU reports, in that order."""
    flags = set(_cpuinfo().get("flags", "").split())
    return [name for flag, name in _EXTENSIONS.items() if flag in flags]


def machine_info() -> dict:
    """CPU model, family/model numbers, usable cores and extensions (Linux; elsewhere :mod:`platform`)."""
    info = _cpuinfo()
    return {
        "cpu": info.get("model name") or platform.processor() or platform.machine(),
        "cpu_family": info.get("cpu family"),
        "cpu_model": info.get("model"),
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "extensions": cpu_extensions(),
        "arch": platform.machine(),
        "python": platform.python_version(),
    }


def cpu_label(machine: dict | None = None) -> str:
    """``"AMD EPYC (2 cores; AVX2 FMA AVX-512 VNNI)"`` for a :func:`machine_info` dict (default: this one)."""
    m = machine or machine_info()
    ext = " ".join(m.get("extensions") or [])
    return f"{m.get('cpu', '?')} ({m.get('cores', '?')} cores{'; ' + ext if ext else ''})"


def _commit() -> str | None:
    root = Path(__file__).resolve().parents[1]
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def provenance(argv: list[str] | None = None, **extra) -> dict:
    """What a recorded file says about its own making.

    Parameters
    ----------
    argv : list of str, optional
        The command as typed (default: ``sys.argv``, the program's path made relative to the
        working directory where it lies under it).
    **extra
        More machine facts (``gl_renderer=...``, ``gpu=...``), merged into ``machine``.
    """
    argv = list(sys.argv if argv is None else argv)
    if argv:
        prog = Path(argv[0])
        if prog.name in {"prt-bench", "prt-train", "prt-runtime", "prt-web", "prt-precompute"}:
            argv[0] = prog.name
        else:
            try:
                argv[0] = str(prog.resolve().relative_to(Path.cwd()))
            except ValueError:
                pass
            if prog.suffix == ".py":
                argv.insert(0, "python")
    return {
        "date": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": shlex.join(argv),
        "machine": {**machine_info(), **extra},
        "commit": _commit(),
    }
