"""The hostile-input corpus (tests/hostile/): every case exits as it must, with one line, no traceback,
nothing left behind.  Regenerate the corpus with ``python tests/hostile/make_corpus.py``."""

import importlib
import re
import shutil
import sys
from pathlib import Path

import pytest

HOSTILE = Path(__file__).resolve().parent / "hostile"
sys.path.insert(0, str(HOSTILE))
from corpus import COMMANDS, load_case  # noqa: E402

CASES = sorted(p for p in (HOSTILE / "cases").glob("*") if (p / "case.json").is_file())


def _command(name):
    module, func = COMMANDS[name].split(":")
    return getattr(importlib.import_module(module), func)


def _tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.mark.parametrize("folder", CASES, ids=[p.name for p in CASES])
def test_hostile_case(folder, tmp_path, capsys, monkeypatch):
    case = load_case(folder)
    inputs = tmp_path / "case"
    shutil.copytree(folder, inputs)
    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.chdir(run)
    argv = [a.replace("{case}", str(inputs)).replace("{run}", str(run)) for a in case.argv]
    before_inputs = {p: p.read_bytes() for p in inputs.rglob("*") if p.is_file()}
    try:
        status = _command(case.command)(argv)
    except SystemExit as exc:  # argparse
        status = exc.code if isinstance(exc.code, int) else 1
    err = capsys.readouterr().err
    assert status == case.exit, f"{case.what}: exit {status}, expected {case.exit}; stderr: {err[-500:]}"
    assert "Traceback" not in err, f"{case.what}: traceback\n{err}"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if case.exit != 0:
        assert len(lines) >= 1 and re.search(case.message, lines[-1]), f"{case.what}: stderr {err!r} !~ {case.message!r}"
        assert len(lines) == 1 or all(ln.startswith("usage:") or ln.startswith(" ") for ln in lines[:-1]), f"{case.what}: more than one line: {err!r}"
    left = {p for p in _tree(run) if not any(Path(p).match(g) for g in case.leaves)}
    assert not left, f"{case.what}: left behind {sorted(left)}"
    for p, data in before_inputs.items():
        assert p.is_file() and p.read_bytes() == data, f"{case.what}: changed the user's file {p.name}"


def test_corpus_is_large_enough():
    assert len(CASES) >= 100, f"{len(CASES)} hostile cases; the corpus should hold at least 100"
