"""Per-object materials: the manifest's optional ``materials`` list and the table the shading reads.

A mesh scene names its objects (``geometry.objects``; ``object_ids`` in ``geometry.npz`` index
that list).  The build reads each object's material from the mesh's own files (OBJ/MTL,
glTF; :mod:`prt.train.inputs.materials`) and records it in ``scene.json``::

    "materials": [{"object": "leftWall", "type": "diffuse", "albedo": [0.63, 0.065, 0.05]}, ...]

Objects without an entry use the scene-wide ``material``.  The field is optional: a manifest
without it loads as before and renders with one material (format version unchanged, the change
is additive).  Transfer does not depend on the albedo, so materials change without retraining;
:meth:`prt.runtime.renderer.Renderer.set_material` overrides them per object at run time.

The shading reads a :class:`MaterialTable`: one :class:`~prt.runtime.shading.Material` per object
id, as numpy rows for the CPU twin and as a small RGBA32F texture for ``shade_pass.frag``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import sh
from .errors import InputError, SpecError
from .shading import MATERIAL_KINDS, Material

__all__ = ["ObjectMaterial", "MaterialTable", "object_materials", "materials_to_dicts", "TABLE_ROWS"]

# Rows of the material texture (one column per object id): albedo + kind, specular, lobe
# factors, albedo texture (layer or -1, width, height).
TABLE_ROWS = 4


@dataclass(frozen=True)
class ObjectMaterial:
    """The material of one named object, as recorded in the manifest.

    Attributes
    ----------
    object : str
        A name in ``geometry.objects``.
    material : Material
    source : str or None
        Where it came from (``"file.mtl: leftWall"``), for people reading the manifest.
    albedo_texture : Path or None
        An image whose (linear) colour multiplies the albedo (:mod:`prt.runtime.albedo_textures`);
        in the manifest, relative to the scene folder.  At build time it may also be an image
        array (H, W, 3) uint8 (a glTF's embedded texture), which the export writes as a PNG.
    """

    object: str
    material: Material
    source: str | None = None
    albedo_texture: Path | None = None

    def to_dict(self) -> dict:
        m = self.material
        out = {"object": self.object, "type": m.kind, "albedo": list(m.albedo)}
        if m.kind == "glossy" or m.specular != Material().specular:
            out["specular"] = list(m.specular)
        out["exponent"] = m.exponent
        if self.albedo_texture is not None:
            out["albedo_texture"] = Path(self.albedo_texture).as_posix()
        if self.source:
            out["source"] = self.source
        return out


def object_materials(data: dict | None, objects: list[str] | None, source: str, root=None) -> list[ObjectMaterial]:
    """The manifest's ``materials`` list (already schema-checked) as :class:`ObjectMaterial` s.

    Parameters
    ----------
    data : dict or None
        The parsed manifest (``Manifest.raw``); no ``materials`` field gives ``[]``.
    objects : list of str or None
        ``geometry.objects``.
    source : str
        The manifest, for error messages.
    root : Path, optional
        The scene folder: ``albedo_texture`` paths are resolved against it (and must stay inside).

    Raises
    ------
    SpecError
        An entry names an object the geometry does not have, or names one twice, or a texture
        path leaves the scene folder.
    """
    entries = (data or {}).get("materials") or []
    names = list(objects or [])
    out, seen = [], set()
    for i, entry in enumerate(entries):
        name = entry["object"]
        if name not in names:
            raise SpecError(f"{source}: materials[{i}].object: {name!r} is not an object of the geometry ({', '.join(names) or 'none named'})")
        if name in seen:
            raise SpecError(f"{source}: materials[{i}].object: {name!r} has a material already")
        seen.add(name)
        params = {k: entry[k] for k in ("albedo", "specular", "exponent") if k in entry}
        try:
            material = Material(kind=entry["type"], **params)
        except InputError as exc:
            raise SpecError(f"{source}: materials[{i}]: {exc}") from None
        texture = entry.get("albedo_texture")
        if texture is not None and root is not None:
            base = Path(root).resolve()
            texture = (base / texture).resolve()
            if base not in texture.parents:
                raise SpecError(f"{source}: materials[{i}].albedo_texture: {entry['albedo_texture']!r} is outside the scene folder")
        out.append(ObjectMaterial(name, material, entry.get("source"), None if texture is None else Path(texture)))
    return out


def load_albedo_textures(per_object: list[ObjectMaterial]):
    """The textures the entries name (each file once, in order of first use) as an
    :class:`~prt.runtime.albedo_textures.AlbedoTextures`, or None when there are none.

    Raises
    ------
    SpecError
        A texture is missing or cannot be read (one line naming the file).
    """
    from .albedo_textures import AlbedoTextures, read_albedo_texture

    files = list(dict.fromkeys(e.albedo_texture for e in per_object if e.albedo_texture is not None))
    return AlbedoTextures([read_albedo_texture(f) for f in files]) if files else None


def materials_to_dicts(materials: list[ObjectMaterial]) -> list[dict]:
    """The manifest's ``materials`` list."""
    return [m.to_dict() for m in materials]


class MaterialTable:
    """One material per object id: the scene default, the manifest's per-object materials, overrides.

    Parameters
    ----------
    objects : list of str
        Object names in id order (``geometry.objects``; one unnamed object for an SDF scene).
    default : Material
        For objects without a material of their own.
    per_object : list of ObjectMaterial
    """

    def __init__(self, objects: list[str], default: Material, per_object: list[ObjectMaterial], textures=None):
        self.objects = list(objects) or ["default"]
        self.default = default
        self._materials = [default] * len(self.objects)
        for entry in per_object:
            self._materials[self.objects.index(entry.object)] = entry.material
        # Albedo texture layer per object id (-1: none) in ``textures`` (an AlbedoTextures).
        self.textures = textures
        self.texture_layer = np.full(len(self.objects), -1, dtype=np.int64)
        files = [e.albedo_texture for e in per_object if e.albedo_texture is not None]
        unique = list(dict.fromkeys(files))
        for entry in per_object:
            if entry.albedo_texture is not None and textures is not None:
                self.texture_layer[self.objects.index(entry.object)] = unique.index(entry.albedo_texture)
        self.version = 0  # bumped on every change (the GL texture is re-uploaded then)

    @property
    def uniform(self) -> bool:
        """True when every object has the same material and none a texture (one uniform material then)."""
        return all(m == self._materials[0] for m in self._materials) and not (self.texture_layer >= 0).any()

    @property
    def materials(self) -> list[Material]:
        return list(self._materials)

    def __getitem__(self, object_id: int) -> Material:
        return self._materials[object_id]

    def material_of(self, name: str) -> Material:
        return self._materials[self._index(name, "material_of")]

    def set_all(self, material: Material) -> None:
        """Every object takes ``material`` (what ``Renderer.set_material`` without ``object=`` does);
        a material set at run time has no texture, so the scene's albedo textures are dropped too."""
        self.default = material
        self._materials = [material] * len(self.objects)
        self.texture_layer[:] = -1
        self.version += 1

    def set(self, name: str, material: Material) -> None:
        """Object ``name`` takes ``material`` (without texture); InputError naming the known objects otherwise."""
        k = self._index(name, "set_material")
        self._materials[k] = material
        self.texture_layer[k] = -1
        self.version += 1

    def _index(self, name, caller: str) -> int:
        if not isinstance(name, str) or name not in self.objects:
            raise InputError(f"Renderer.{caller}: object {name!r} is not in the scene (objects: {', '.join(self.objects)})")
        return self.objects.index(name)

    def texture_data(self, bands: int = 4) -> np.ndarray:
        """(TABLE_ROWS, K, 4) float32: row 0 ``albedo.rgb, kind``, row 1 ``specular.rgb, 0``,
        row 2 the Phong lobe's band factors ``Lambda_0..3`` (see ``shade_pass.frag``)."""
        table = np.zeros((TABLE_ROWS, len(self._materials), 4), dtype=np.float32)
        for k, m in enumerate(self._materials):
            table[0, k] = (*m.albedo, MATERIAL_KINDS.index(m.kind))
            table[1, k, :3] = m.specular
            table[2, k] = sh.phong_lobe(m.exponent, bands)[:4]
            layer = int(self.texture_layer[k])
            if layer >= 0:
                width, height = self.textures.sizes[layer]
                table[3, k] = (layer, width, height, 0)
            else:
                table[3, k] = (-1, 0, 0, 0)
        return table


def shade_objects(transfer, object_ids, normals, view_dirs, lighting, table: MaterialTable, uv=None) -> np.ndarray:
    """Radiance of shaded points, each with its object's material (numpy twin of ``shade_pass.frag``
    with ``PRT_OBJECT_MATERIALS``).

    Parameters
    ----------
    transfer : (N, n) or (N, 4 n) float
        ``4 n``: with interreflection (direct, indirect R, G, B; :func:`prt.runtime.shading.shade`).
    object_ids : (N,) int
        Object id of each point (ids outside the table take the table's default material).
    normals, view_dirs : (N, 3) float or None
        Only read for glossy objects.
    lighting : Lighting
    table : MaterialTable
    uv : (N, 2) float or None
        Albedo-texture coordinates (read for objects with a texture).

    Returns
    -------
    (N, 3) float32, >= 0
    """
    from .shading import diffuse_light_matrix, shade

    transfer = np.asarray(transfer)
    n = lighting.sh.shape[0]
    object_ids = np.asarray(object_ids).reshape(-1)
    out = np.zeros((len(transfer), 3), dtype=np.float32)
    known = (object_ids >= 0) & (object_ids < len(table.objects))
    # RGB transfer (4 n wide): dot(T, L_c) + dot(T_ind_c, L_c) once for every row (one product),
    # so diffuse objects scale 3 values per row instead of gathering 4 n.
    incident = transfer.astype(np.float32, copy=False) @ diffuse_light_matrix(lighting, (1.0, 1.0, 1.0), transfer.shape[1]) if transfer.shape[1] > n else None
    for k in np.unique(np.where(known, object_ids, -1)):
        rows = np.flatnonzero(object_ids == k) if k >= 0 else np.flatnonzero(~known)
        material = table[int(k)] if k >= 0 else table.default
        layer = int(table.texture_layer[k]) if k >= 0 else -1
        if layer >= 0 and uv is not None:  # per-pixel albedo: each row's texel times the light it receives
            texel = table.textures.sample(layer, np.asarray(uv)[rows]) * np.asarray(material.albedo, dtype=np.float32)
            if incident is not None:  # direct + interreflected (diffuse, scaled by the receiver's albedo)
                received = incident[rows]
            else:
                received = transfer[rows].astype(np.float32, copy=False) @ diffuse_light_matrix(lighting, (1.0, 1.0, 1.0), transfer.shape[1])
            radiance = texel * received
            if material.kind == "glossy":
                t = np.asarray(transfer[rows, :n], dtype=np.float64)
                radiance = radiance + np.asarray(material.specular) * _specular(t, normals[rows], view_dirs[rows], lighting, material)
            out[rows] = np.maximum(radiance, 0.0)
            continue
        if material.kind == "diffuse" and incident is not None:
            out[rows] = np.maximum(incident[rows] * np.asarray(material.albedo, dtype=np.float32), 0.0)
        elif material.kind == "diffuse":  # as the renderer's uniform fast path: T @ (albedo * L)
            light = diffuse_light_matrix(lighting, material.albedo, transfer.shape[1])
            out[rows] = np.maximum(transfer[rows].astype(np.float32) @ light, 0.0)
        else:
            out[rows] = shade(transfer[rows], normals[rows], view_dirs[rows], lighting, material)
    return out


def _specular(t, normals, view_dirs, lighting, material: Material) -> np.ndarray:
    """The glossy lobe's incident radiance per channel before ``specular`` (as in ``shading.shade``)."""
    from .shading import reflect

    n_coeffs = lighting.sh.shape[0]
    lobe = sh.band_factors_to_coeff_scale(material.lobe_band_factors(lighting.bands))
    stacked = lighting.light_matrix.reshape(3 * n_coeffs, n_coeffs).T
    lobe_at_r = sh.basis(reflect(view_dirs, normals), lighting.bands) * lobe
    transferred = (t @ stacked).reshape(-1, 3, n_coeffs)
    return np.pi * np.einsum("pck,pk->pc", transferred, lobe_at_r)


def parse_object_albedo(text: str, flag: str = "--object-albedo") -> tuple[str, tuple[float, float, float]]:
    """``"NAME=R,G,B"`` (or ``NAME=V``) as ``(name, rgb)``; InputError naming ``flag`` otherwise."""
    name, sep, values = str(text).rpartition("=")
    try:
        numbers = [float(v) for v in values.split(",")]
    except ValueError:
        numbers = []
    if not sep or not name or len(numbers) not in (1, 3) or not all(np.isfinite(numbers)) or min(numbers) < 0:
        raise InputError(f"{flag}: expected NAME=R,G,B (or NAME=V) with finite values >= 0, got {text!r}")
    return name, tuple(numbers * 3 if len(numbers) == 1 else numbers)


def apply_object_albedo(renderer, name: str, albedo) -> None:
    """Give object ``name`` of ``renderer`` the albedo ``albedo``, keeping the rest of its material."""
    m = renderer.materials.material_of(name)
    renderer.set_material(m.kind, object=name, albedo=albedo, specular=m.specular, exponent=m.exponent)
