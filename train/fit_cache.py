"""The fit cache: every network fitted on a precompute's segment, keyed by size and fit settings (``precompute/fits/``)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from ..runtime.files import atomic_save_npz, atomic_write_json
from .networks.fit import FitResult

__all__ = ["FIT_FORMAT", "fit_hash"]

FIT_FORMAT = 2  # layout of the fit cache (precompute/fits/); 2: trained by steps


def fit_hash(*parts) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


class _StoredModel:
    """A fitted network read back from the fit cache: just its arrays (all export needs)."""

    def __init__(self, arrays: dict):
        self._arrays = arrays

    def arrays(self) -> dict:
        return dict(self._arrays)


class _FitCache:
    """Every network fitted on a precompute's segment, keyed by size and fit settings.

    It lives inside the precompute folder, so builds that share one ground truth (the paper
    table links one precompute into its k = 64, k = 128 and right-sized builds) also share
    fits: ``--match 64x4`` reuses the k = 64 build's networks as its references.
    """

    def __init__(self, folder: Path, pre_key: str, segment: int, fit_settings):
        self.folder, self.base = Path(folder), (pre_key, segment, fit_settings.cache_key(), FIT_FORMAT)

    def _paths(self, arch):
        key = fit_hash(*self.base, arch.as_dict())
        return self.folder / f"{key}.json", self.folder / f"{key}.npz"

    def get(self, arch):
        meta_path, weights_path = self._paths(arch)
        if not (meta_path.is_file() and weights_path.is_file()):
            return None
        try:
            meta = json.loads(meta_path.read_bytes())
            with np.load(weights_path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            return FitResult(_StoredModel(arrays), arch, meta["val_mae"], meta["shaded"], meta["epochs"], meta["seconds"], meta["history"],
                             meta.get("steps", 0))  # fmt: skip
        except MemoryError:
            raise
        except Exception:  # json, zipfile, zlib and a foreign record's missing keys each raise their own kind
            return None  # a damaged entry is refitted

    def memo(self, archs) -> "_FitMemo":
        """The entries of ``archs`` fitted before, to travel with a task that runs elsewhere."""
        return _FitMemo({fit_hash(arch.as_dict()): fit for arch in archs if (fit := self.get(arch)) is not None})

    def put(self, result) -> None:
        meta_path, weights_path = self._paths(result.arch)
        self.folder.mkdir(parents=True, exist_ok=True)
        atomic_save_npz(weights_path, **result.model.arrays())  # weights first: the json marks the entry complete
        atomic_write_json(meta_path, {"arch": result.arch.as_dict(), "val_mae": result.val_mae, "shaded": result.shaded,
                                      "epochs": result.epochs, "seconds": result.seconds, "history": result.history,
                                      "steps": result.steps})  # fmt: skip


class _FitMemo:
    """A :class:`_FitCache` in memory, for a task on another machine: the new fits go back to the driver."""

    def __init__(self, known: dict):
        self.known, self.new = known, []

    def get(self, arch):
        return self.known.get(fit_hash(arch.as_dict()))

    def put(self, result) -> None:
        stored = dataclasses.replace(result, model=_StoredModel(result.model.arrays()))
        self.known[fit_hash(result.arch.as_dict())] = stored
        self.new.append(stored)
