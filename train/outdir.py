"""Output folders of the build commands: ours are marked, anyone else's are left alone.

A folder ``prt-train -o`` or ``prt-precompute -o`` writes into gets a marker file first,
``.prt-build`` (JSON: ``{"format": "prt-build", "version": 1, "kind": "scene" | "precompute"}``).
Before any work a command checks its output folder (:func:`check_output_folder`):

* missing or empty: fine (it is created only when there is something to write);
* marked by us, of the same kind: fine, the build resumes from what is there;
* made before the marker existed: recognised by our precompute summary (``precompute.json``
  for a precompute folder, ``precompute/precompute.json`` for a scene build) and adopted;
* anything else (someone's files, a build of the other kind, an unreadable marker): refused
  with one line, unless ``force`` (``--force``), since a build overwrites files by name.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..runtime.errors import OutputError
from ..runtime.files import atomic_write_json

__all__ = ["MARKER", "KINDS", "check_output_folder", "mark_output_folder"]

MARKER = ".prt-build"
MARKER_FORMAT, MARKER_VERSION = "prt-build", 1
KINDS = ("scene", "precompute")
# What a build folder made before the marker holds, by kind: the precompute summary.
_LEGACY = {"scene": "precompute/precompute.json", "precompute": "precompute.json"}


def _marker(kind: str) -> dict:
    return {"format": MARKER_FORMAT, "version": MARKER_VERSION, "kind": kind}


def _legacy_kind(out: Path) -> str | None:
    """The kind of an unmarked folder our build made before the marker existed, or None."""
    for kind, rel in _LEGACY.items():
        try:
            summary = json.loads((out / rel).read_bytes())
        except (OSError, ValueError):
            continue
        if isinstance(summary, dict) and "key" in summary and "settings" in summary:
            return kind
    return None


def _marked_kind(out: Path) -> str | None:
    """The kind the marker records; None when it is unreadable or not ours."""
    try:
        data = json.loads((out / MARKER).read_bytes())
    except (OSError, ValueError):
        return None
    if isinstance(data, dict) and data.get("format") == MARKER_FORMAT and data.get("kind") in KINDS:
        return data["kind"]
    return None


def check_output_folder(out, kind: str, *, force: bool = False) -> None:
    """Refuse an output folder the build would damage; creates nothing.

    Parameters
    ----------
    out : str or Path
        The output folder (may not exist yet).
    kind : {"scene", "precompute"}
        What the command builds there.
    force : bool
        Write into a non-empty folder that is not one of ours anyway.

    Raises
    ------
    OutputError
        One line naming the folder and saying why (not a folder, not writable, not ours).
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: output exists and is not a folder")
    existing = out
    while not existing.exists():  # the nearest folder that exists is where creation starts
        if existing.parent == existing:
            break
        existing = existing.parent
    if not existing.is_dir():
        raise OutputError(f"{out}: cannot create the output folder ({existing} is not a folder)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: output folder is not writable ({existing}: permission denied)")
    if not out.exists() or force:
        return
    try:
        empty = next(out.iterdir(), None) is None
    except OSError as exc:
        raise OutputError(f"{out}: cannot read the output folder ({exc.strerror or exc})") from None
    if empty:
        return
    if (out / MARKER).exists():
        found = _marked_kind(out)
        if found is None:
            raise OutputError(f"{out}: its {MARKER} marker is unreadable or not ours; pass --force to write there anyway")
        if found != kind:
            raise OutputError(f"{out}: holds a {found} build, not a {kind} build; choose another folder or pass --force")
        return
    found = _legacy_kind(out)
    if found == kind:
        return
    if found is not None:
        raise OutputError(f"{out}: holds a {found} build, not a {kind} build; choose another folder or pass --force")
    raise OutputError(
        f"{out}: not empty and not a prt build folder (no {MARKER}); files of the same names would be "
        "overwritten: choose an empty or new folder, or pass --force"
    )


def mark_output_folder(out, kind: str) -> Path:
    """Create ``out`` (and parents) and its marker unless present; call before the first write."""
    out = Path(out)
    created = []  # the folders made here, removed again if the marker cannot be written
    for folder in (*reversed(out.parents), out):
        if not folder.exists():
            try:
                folder.mkdir()
            except FileExistsError:
                continue
            except OSError as exc:
                _remove_empty(created)
                raise OutputError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
            created.append(folder)
    if _marked_kind(out) is None:
        try:
            atomic_write_json(out / MARKER, _marker(kind))
        except OSError:
            _remove_empty(created)
            raise
    return out


def _remove_empty(folders: list[Path]) -> None:
    for folder in reversed(folders):
        try:
            folder.rmdir()
        except OSError:
            return
