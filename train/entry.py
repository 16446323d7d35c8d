"""The console entry points of the build commands (``prt-train``, ``prt-precompute``); ``prt-bench`` uses :func:`load_command` alike.

They import their command module only when run, so that a machine without the ``[train]``
extra (torch, trimesh, embreex, ...: a runtime-only install) gets one line saying what to
install instead of a traceback.  ImportErrors of the project's own modules are not masked.
"""

from __future__ import annotations

import importlib
import sys
import time

__all__ = ["train_main", "precompute_main", "load_command"]

INSTALL = 'pip install "prt-runtime[train]"'


def load_command(module: str, command: str, purpose: str = "building scenes"):
    """``module`` imported, or None after one line on stderr when a dependency is missing
    (``purpose``: what needs the [train] extra, e.g. "benchmarking")."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        name = getattr(exc, "name", None) or ""
        if name == "prt" or name.startswith("prt."):
            raise  # a bug of ours, not a missing extra
        what = f"module {name!r} is not installed" if name else str(exc)
        print(f"{command}: error: {what}; {purpose} needs the [train] extra: {INSTALL}", file=sys.stderr)
        return None


def train_main(argv: list[str] | None = None) -> int:
    started = time.perf_counter()  # before the imports: a preset's build budget bounds the whole command
    module = load_command("prt.train.train_cli", "prt-train")
    return 2 if module is None else module.main(argv, started=started)


def precompute_main(argv: list[str] | None = None) -> int:
    module = load_command("prt.train.precompute_cli", "prt-precompute")
    return 2 if module is None else module.main(argv)
