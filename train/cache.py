"""A store of finished work chunks, so long runs survive interruption (atomic writes re-exported)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..runtime.files import atomic_save_npy, atomic_save_npz, atomic_write_bytes, atomic_write_json

__all__ = ["atomic_write_bytes", "atomic_save_npy", "atomic_save_npz", "atomic_write_json", "ChunkStore"]


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

    def load(self, k: int, shape: tuple | None = None) -> np.ndarray | None:
        """Chunk ``k``; None (recompute it) if the file is damaged, foreign or not of ``shape``."""
        try:
            value = np.load(self.path(k), allow_pickle=False)
        except (OSError, ValueError, EOFError):
            return None
        if shape is not None and (value.shape != tuple(shape) or value.dtype.kind != "f"):
            return None
        return value

    def save(self, k: int, value: np.ndarray) -> None:
        atomic_save_npy(self.path(k), value)

    def done(self) -> int:
        return sum(self.has(k) for k in range(self.n_chunks))
