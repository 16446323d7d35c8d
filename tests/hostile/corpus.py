"""The hostile-input corpus: what a careless or hostile user gives the commands, and what they must get.

Each case is one command line run in a fresh folder.  The corpus is written to
``tests/hostile/cases/<name>/`` by ``python tests/hostile/make_corpus.py`` (the inputs a case
needs, plus ``case.json``), committed, and run by ``tests/test_hostile.py``.  Cases come from
the ``cases_*.py`` modules beside this file, each defining ``cases() -> list[Case]``.

A case passes when the command exits with ``exit`` (2 for bad input), prints exactly one
non-empty line on stderr that matches ``message`` (a regular expression naming the file or
field), prints no traceback, and leaves no new file or folder behind except those in
``leaves`` (globs relative to the run folder).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

__all__ = ["Case", "COMMANDS", "load_case"]

# Command name -> "module:function" called in-process as function(argv) -> exit status.
COMMANDS = {
    "prt-train": "prt.train.train_cli:main",
    "prt-precompute": "prt.train.precompute_cli:main",
    "prt-runtime": "prt.runtime.cli:main",
    "prt-bench": "prt.bench.cli:main",
}


@dataclass
class Case:
    """One hostile input.

    name : folder name of the case (unique, ``[a-z0-9_-]+``).
    command : a key of :data:`COMMANDS`.
    argv : arguments; ``{case}`` is replaced by the case folder (inputs) and ``{run}`` by the
        fresh folder the command runs in (outputs).
    files : inputs to write into the case folder: relative path -> text (str) or bytes
        (written as given; bytes are stored as a ``.bin`` sidecar in case.json by hex).
    message : regular expression the single stderr line must match (``re.search``).
    exit : expected exit status.
    leaves : globs (relative to the run folder) of what the command may leave behind.
    what : one line saying what the case tries.
    """

    name: str
    command: str
    argv: list[str]
    message: str
    what: str
    files: dict[str, str | bytes] = field(default_factory=dict)
    exit: int = 2
    leaves: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        data = asdict(self)
        data["files"] = sorted(self.files)  # written beside case.json
        return data


def load_case(folder: Path) -> Case:
    data = json.loads((folder / "case.json").read_text(encoding="utf-8"))
    data["files"] = {}
    return Case(**data)
