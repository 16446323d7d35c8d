"""Atomic files and a store of finished work chunks, so long runs survive interruption."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["atomic_write_bytes", "atomic_save_npy", "atomic_save_npz", "atomic_write_json", "ChunkStore"]


def _atomic(path: Path, write) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: never half a file."""
    _atomic(path, lambda f: f.write(data))


def atomic_save_npy(path, array: np.ndarray) -> None:
    _atomic(path, lambda f: np.save(f, array, allow_pickle=False))


def atomic_save_npz(path, **arrays: np.ndarray) -> None:
    _atomic(path, lambda f: np.savez(f, **arrays))


def atomic_write_json(path, obj) -> None:
    _atomic(path, lambda f: f.write((json.dumps(obj, indent=2) + "\n").encode()))


class ChunkStore:
    """Finished chunks ``chunk_00042.npy`` in one folder, each written atomically.

    A chunk file either exists complete or not at all, so ``has`` is all a resume needs.
    Stale temporary files of a killed run are removed on open.
    """

    def __init__(self, folder, n_chunks: int):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.n_chunks = n_chunks
        for stale in self.folder.glob(".chunk_*.tmp"):
            stale.unlink(missing_ok=True)

    def path(self, k: int) -> Path:
        return self.folder / f"chunk_{k:05d}.npy"

    def has(self, k: int) -> bool:
        return self.path(k).is_file()

    def load(self, k: int) -> np.ndarray:
        return np.load(self.path(k), allow_pickle=False)

    def save(self, k: int, value: np.ndarray) -> None:
        atomic_save_npy(self.path(k), value)

    def done(self) -> int:
        return sum(self.has(k) for k in range(self.n_chunks))
