"""Write the hostile-input corpus: ``python tests/hostile/make_corpus.py`` (see corpus.py).

Rewrites ``tests/hostile/cases/`` from the ``cases_*.py`` modules beside this file.
"""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # a script beside its modules, not a package

from corpus import COMMANDS, Case  # noqa: E402


def all_cases() -> list[Case]:
    cases = []
    for path in sorted(HERE.glob("cases_*.py")):
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        cases.extend(module.cases())
    names = [c.name for c in cases]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise SystemExit(f"make_corpus: duplicate case names {dupes}")
    for c in cases:
        if not re.fullmatch(r"[a-z0-9_-]+", c.name) or c.command not in COMMANDS:
            raise SystemExit(f"make_corpus: bad case {c.name!r} ({c.command})")
    return cases


def main() -> int:
    out = HERE / "cases"
    if out.exists():
        shutil.rmtree(out)
    for case in all_cases():
        folder = out / case.name
        folder.mkdir(parents=True)
        for rel, content in case.files.items():
            path = folder / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8"))
        (folder / "case.json").write_text(json.dumps(case.to_json(), indent=1) + "\n", encoding="utf-8")
    print(f"make_corpus: {len(list(out.iterdir()))} cases in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
