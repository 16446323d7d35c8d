"""A scene's optional transfer texture (texture-space PRT): its manifest entry and its file.

``transfer_texture.npz`` (written by :func:`prt.train.transport.transfer_texture.save_transfer_texture`):

- ``transfer`` (A, S, S, n) float16: transfer per texel of each of A atlases (texture sets),
  row 0 at ``v`` near 0 (GL's texture row order), dilated into the gutters between charts; n is
  ``sh_bands**2``, or 4 times that for a scene with ``interreflection`` (the networks' "direct+rgb"
  layout: direct, then indirect R, G, B);
- ``corner_uv`` (F, 2, 3, 2) float32: UV of each corner of each face in ``geometry.npz``, for
  its front ``[:, 0]`` and back ``[:, 1]`` side (open faces have a chart for each side);
- ``atlas`` (F,) int32: the atlas of each face;
- ``bounces`` () int, interreflection textures only: the N they were baked with.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import GeometryError

__all__ = ["TransferTextureInfo", "load_transfer_texture"]


@dataclass
class TransferTextureInfo:
    """The manifest's optional ``transfer_texture`` entry.

    Attributes
    ----------
    path : Path
        ``transfer_texture.npz``, resolved.
    size : int
        Texels per side of each atlas.
    atlases : int
        Number of atlases (texture sets).
    extra : dict
        The other recorded fields (``layout``, ``uv_source``, ``rays``, ``bytes``).
    """

    path: Path
    size: int
    atlases: int
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_manifest(cls, data: dict, files: dict) -> TransferTextureInfo | None:
        """From a validated manifest dict and its resolved paths; None when it has no texture."""
        if "transfer_texture" not in data:
            return None
        entry = data["transfer_texture"]
        extra = {k: v for k, v in entry.items() if k not in ("file", "size", "atlases")}
        return cls(path=files["transfer_texture.file"], size=entry["size"], atlases=entry["atlases"], extra=extra)

    @staticmethod
    def path_fields(data: dict) -> list:
        """(field path, relative path) of the texture file, for the manifest's path checks."""
        return [(["transfer_texture", "file"], data["transfer_texture"]["file"])] if "transfer_texture" in data else []

    def to_dict(self, root: Path) -> dict:
        import os

        rel = Path(os.path.relpath(os.path.abspath(self.path), os.path.abspath(root))).as_posix()
        return {"file": rel, "size": self.size, "atlases": self.atlases, **self.extra}


def load_transfer_texture(info: TransferTextureInfo, n_faces: int, coefficients: int = 16, *, transfer: bool = True) -> dict[str, np.ndarray]:
    """Read and check ``transfer_texture.npz`` against the manifest entry and the mesh
    (``transfer=False``: the UVs only, as the G-buffer needs).

    Returns
    -------
    dict
        ``transfer`` (A, S, S, n) float16, ``corner_uv`` (F, 2, 3, 2) float32, ``atlas`` (F,) int32.

    Raises
    ------
    GeometryError
        If the file cannot be read or its arrays do not fit the entry or the mesh.
    """
    path = info.path
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = ("transfer", "corner_uv", "atlas") if transfer else ("corner_uv", "atlas")
            arrays = {key: data[key] for key in keys if key in data.files}
    except (OSError, ValueError) as exc:
        raise GeometryError(f"{path}: cannot read transfer texture ({' '.join(str(exc).split())})") from None
    for key in keys:
        if key not in arrays:
            raise GeometryError(f"{path}: no '{key}' array")
    corner_uv, atlas = arrays["corner_uv"], arrays["atlas"]
    if transfer:
        values, expected = arrays["transfer"], (info.atlases, info.size, info.size, coefficients)
        if values.ndim == 4 and values.shape[:3] == expected[:3] and values.shape[3] * 4 == coefficients:
            raise GeometryError(f"{path}: holds direct transfer only ({values.shape[3]} values per texel) but the scene has interreflection "
                                f"({coefficients}); bake it again (prt-train --transfer-texture with the scene's --bounces)")  # fmt: skip
        if values.shape != expected or values.dtype.kind != "f":
            raise GeometryError(f"{path}: transfer must be {expected} floats (scene.json's transfer_texture), got {values.shape} {values.dtype}")
        if not np.all(np.isfinite(values)):
            raise GeometryError(f"{path}: transfer contains NaN or Inf")
    if corner_uv.shape != (n_faces, 2, 3, 2) or corner_uv.dtype.kind != "f" or not np.all(np.isfinite(corner_uv)):
        raise GeometryError(f"{path}: corner_uv must be ({n_faces}, 2, 3, 2) finite floats, got {corner_uv.shape} {corner_uv.dtype}")
    if atlas.shape != (n_faces,) or atlas.dtype.kind not in "iu" or (n_faces and (atlas.min() < 0 or atlas.max() >= info.atlases)):
        raise GeometryError(f"{path}: atlas must be ({n_faces},) integers in 0..{info.atlases - 1}")
    out = {"corner_uv": corner_uv.astype(np.float32), "atlas": atlas.astype(np.int32)}
    if transfer:
        out["transfer"] = arrays["transfer"].astype(np.float16)
    return out
