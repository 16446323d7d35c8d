"""The documentation: generated pages current, a strict site build, a short front door."""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_is_a_short_front_door():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines: details belong in docs/"
    text = "\n".join(lines)
    assert "make demo" in text and "make test" in text


def test_generated_pages_are_current():
    """CLI reference, scene.json reference, results pages and the README's table match the code and
    the recorded files (`make docs` regenerates them)."""
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "docs.py"), "--check"], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr


def test_site_builds_strictly(tmp_path):
    """mkdocs --strict: no broken link or anchor, no page missing from the navigation, docstrings parse."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                          capture_output=True, text=True, cwd=ROOT, env=env)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "reference" / "python-api" / "index.html").read_text(encoding="utf-8").count("Renderer") > 5
