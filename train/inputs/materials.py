"""Per-object materials read from a mesh's own files: OBJ + MTL, glTF / GLB.

One material per object of :class:`prt.train.inputs.geometry.Geometry` (the objects its reader made:
OBJ ``o``/``g`` groups, or ``usemtl`` runs in a file without groups; glTF node primitives).  An object
whose faces use several materials takes the one most of its faces use (one warning line).

Rules
-----
- MTL: ``Kd`` is the albedo.  ``Ks`` above zero makes the material glossy with specular ``Ks``
  and Phong exponent ``Ns`` (at least 1); otherwise it is diffuse.  ``map_Kd`` is recorded as
  the object's albedo texture (multiplied by ``Kd``, as the MTL format defines it); a missing
  texture file is a warning (``Kd`` alone is used), an unreadable one a one-line error.  ``d``
  (or ``1 - Tr``) and ``map_d`` make an object glass or a cut-out (:func:`obj_cut`; the geometry,
  not the material).  ``Ka``, ``Ke``, ``Ni`` and ``illum`` are ignored (no emission: lights are the env map).
- glTF (objects and names of :mod:`prt.train.inputs.gltf_scene`: one per node and triangle
  primitive, so every primitive keeps its own material).  Metallic-roughness: with ``base`` =
  ``baseColorFactor`` (linear RGB) times the primitive's mean ``COLOR_0``, ``m`` =
  ``metallicFactor`` and ``r`` = ``roughnessFactor`` (glTF defaults 1, 1; times the mean of the
  ``metallicRoughnessTexture``'s B and G channels where there is one), the diffuse albedo is
  ``base (1 - m)``, the specular ``0.04 (1 - m) + base * m`` (the glTF BRDF's F0; a metal's base
  times its colour texture's mean), and ``r`` maps to a Phong exponent by the Blinn-Phong
  equivalence of the GGX width ``alpha = r^2``: ``n = 2 / alpha^2 - 2`` (Walter et al. 2007),
  capped at :data:`MAX_EXPONENT` (four SH bands hold nothing sharper).  Below ``n = 1``
  (``r > ~0.90``, glTF's default included) the lobe is as wide as the diffuse one and is
  reflected diffusely: the material is diffuse with albedo ``base`` (a rough metal keeps its
  colour; the dielectric 4 % is dropped).  ``KHR_materials_pbrSpecularGlossiness`` (preferred
  where present, as the extension asks): ``c_diff = diffuseFactor * (1 - max(specular))``
  (times the mean ``COLOR_0``), F0 = ``specularFactor``, roughness ``1 - glossinessFactor``
  (both times the means of the ``specularGlossinessTexture``'s RGB and A), the same exponent
  rule; too rough for a lobe, albedo ``c_diff + specular`` (the specular over the diffuse
  texture's mean, at most 1).  ``baseColorTexture`` / ``diffuseTexture`` (embedded or beside
  the file, by its ``texCoord`` set and ``KHR_texture_transform``) is the object's albedo texture,
  multiplying the albedo; the other textures enter as their means, emission is ignored.  A
  missing image file or a GPU texture (KTX2, DDS) is a warning (the factors alone), an
  undecodable image a one-line error.
- Missing: objects with no material (no ``mtllib``, an unknown ``usemtl`` name, a missing MTL
  file, a glTF primitive without ``material``, PLY/STL files) take the scene-wide material; one
  warning line lists them (only them).

A malformed MTL statement (``Kd`` with a non-number, a negative value) is a one-line
:class:`~prt.runtime.errors.GeometryError` naming the file and line.
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

import numpy as np

from ...runtime.albedo_textures import MAX_TEXTURE_SIZE, read_albedo_texture, srgb_to_linear
from ...runtime.errors import GeometryError, InputError
from ...runtime.materials import ObjectMaterial
from ...runtime.shading import Material
from .objfile import DEFAULT_OBJECT

__all__ = ["read_mtl", "obj_material_names", "obj_alpha_masks", "obj_cut", "corner_uvs", "mesh_materials", "pbr_material", "spec_gloss_material", "gltf_part_material",
           "roughness_to_exponent", "MAX_EXPONENT"]

# Phong exponents above this are all "mirror" to 4 SH bands (their band factors are ~1).
MAX_EXPONENT = 1024.0
# Normal-incidence reflectance of a dielectric (index ~1.5), glTF's F0 for non-metals.
DIELECTRIC_F0 = 0.04


def roughness_to_exponent(roughness: float) -> float:
    """Phong exponent of a glTF roughness: ``n = 2 / alpha^2 - 2`` with ``alpha = roughness^2``
    (0 for a surface too rough to be glossy; at most :data:`MAX_EXPONENT`)."""
    alpha = max(float(roughness), 1e-4) ** 2
    return float(min(max(2.0 / alpha**2 - 2.0, 0.0), MAX_EXPONENT))


# --------------------------------------------------------------------------- MTL


def read_mtl(path: str) -> dict[str, dict]:
    """The materials of an MTL file: ``{name: {"Kd": (3,), "Ks": (3,), "Ns": float, "map_Kd": path}}``
    (keys present only when the file sets them; ``map_Kd`` resolved against the MTL's folder).

    Raises
    ------
    GeometryError
        Unreadable file, or a malformed ``Kd``/``Ks``/``Ns`` line (file and line named).
    """
    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        raise GeometryError(f"{path}: cannot read MTL file ({error.strerror or error})") from None
    if b"\x00" in data:
        raise GeometryError(f"{path}: not a text MTL file (contains binary data)")
    text = data.decode("utf-8-sig", errors="replace")
    materials: dict[str, dict] = {}
    current: dict | None = None
    folder = os.path.dirname(path)
    for number, line in enumerate(text.replace("\r\n", "\n").replace("\r", "\n").split("\n"), 1):
        parts = line.partition("#")[0].split()
        if not parts:
            continue
        key = parts[0]
        if key == "newmtl":
            current = materials.setdefault(" ".join(parts[1:]) or DEFAULT_OBJECT, {})
        elif current is None:
            continue
        elif key in ("Kd", "Ks"):
            values = _numbers(path, number, key, parts[1:])
            if len(values) == 1:
                values = values * 3
            if len(values) < 3:
                raise GeometryError(f"{path}, line {number}: {key} needs 3 numbers (or 1): {line.strip()!r}")
            current[key] = tuple(values[:3])
        elif key == "Ns":
            current["Ns"] = _numbers(path, number, key, parts[1:2])[0] if len(parts) > 1 else 0.0
        elif key in ("map_Kd", "map_d") and len(parts) > 1:
            name = _map_file(line.partition("#")[0].strip()[len(key):])
            if name:
                current[key] = _texture_path(folder, name)
        elif key in ("d", "Tr") and len(parts) > 1:
            value = min(_numbers(path, number, key, parts[1:2])[0], 1.0)
            if key == "d" or "d" not in current:  # Tr is 1 - d; d wins where both are given
                current["d"] = value if key == "d" else 1.0 - value
        elif key == "illum" and len(parts) > 1 and parts[1].isdigit():
            current["illum"] = int(parts[1])
    return materials


# A texture statement's options and how many values each takes (the MTL format's list); the file
# name is what follows them, spaces and all (``map_Kd -s 2 2 1 leaf texture.png``).
_MAP_OPTIONS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1, "-mm": 2, "-o": 3,
                "-s": 3, "-t": 3, "-texres": 1, "-type": 1}


def _map_file(text: str) -> str:
    """The file name of a ``map_...`` statement's arguments: its options skipped (``-o``, ``-s`` and
    ``-t`` take one to three numbers), the rest as written."""
    tokens = text.split()
    k = 0
    while k < len(tokens) and tokens[k] in _MAP_OPTIONS:
        count = _MAP_OPTIONS[tokens[k]]
        k += 1
        for _ in range(count):  # -o/-s/-t: v and w are optional; a value is a number
            if k < len(tokens) and (count < 3 or _is_number(tokens[k])) and k < len(tokens) - 1:
                k += 1
    return " ".join(tokens[k:])


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _texture_path(folder: str, name: str) -> str:
    """A texture named in an MTL file, beside it: Windows' backslashes read as separators where the
    name as written is not a file (MTL files written on Windows: ``map_Kd textures\\bricks.tga``)."""
    path = os.path.join(folder, name)
    if "\\" in name and not os.path.isfile(path):
        return os.path.join(folder, *name.split("\\"))
    return path


# MTL illumination models with transparency (the format's 4, 6, 7 and 9): only these make ``d`` (or
# ``Tr``) a dissolve.  Exporters write ``d 0`` beside ``illum 2`` on opaque materials (the Crytek
# Sponza's MTL as Blender exports it: every wall and column), which taken at its word leaves the
# building out.
TRANSPARENT_ILLUM = (4, 6, 7, 9)


def _numbers(path: str, number: int, key: str, tokens: list[str]) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise GeometryError(f"{path}, line {number}: {key} values must be numbers, got {' '.join(tokens)!r}") from None
    if not values or not all(np.isfinite(values)) or min(values) < 0:
        raise GeometryError(f"{path}, line {number}: {key} needs finite numbers >= 0, got {' '.join(tokens)!r}")
    return values


def obj_material_names(path: str) -> tuple[dict[str, Counter], list[str]]:
    """Which materials each object of an OBJ file uses, by the object rule of
    :mod:`prt.train.inputs.objfile`; and the ``mtllib`` files (resolved against the OBJ's folder).

    Returns
    -------
    uses : dict of str to Counter
        Object name -> faces per material name (None: faces before any ``usemtl``).
    libraries : list of str
    """
    with open(path, "rb") as handle:
        text = handle.read().decode("utf-8-sig", errors="replace")
    by_group: dict[str, Counter] = {}
    by_material: dict[str, Counter] = {}
    libraries: list[str] = []
    group, material, has_groups = DEFAULT_OBJECT, None, False
    for line in text.replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        parts = line.partition("#")[0].split()
        if not parts:
            continue
        key = parts[0]
        if key == "f":
            by_group.setdefault(group, Counter())[material] += 1
            by_material.setdefault(material or DEFAULT_OBJECT, Counter())[material] += 1
        elif key in ("o", "g"):
            group, has_groups = " ".join(parts[1:]) or DEFAULT_OBJECT, True
        elif key == "usemtl":
            material = " ".join(parts[1:]) or None
        elif key == "mtllib":
            folder, names = os.path.dirname(path), parts[1:]
            whole = os.path.join(folder, " ".join(names))  # one file name with spaces, where that is the file
            libraries.extend([whole] if len(names) > 1 and os.path.isfile(whole) else [os.path.join(folder, n) for n in names])
    return (by_group if has_groups else by_material), libraries


def obj_alpha_masks(path: str, object_names: list[str]) -> dict[str, tuple[np.ndarray | None, float]]:
    """The objects of an OBJ file whose material (the most used one, as for their colour) is not
    opaque: name -> (its ``map_d`` image's alpha (its alpha channel, else its first channel) as
    (H, W) float64 in [0, 1], None without one; its dissolve ``d``: 1 where not given or where
    its ``illum`` is not one with transparency, :data:`TRANSPARENT_ILLUM`).  A ``map_d`` that is
    missing or does not decode counts as none."""
    uses, library, _, _ = _obj_library(path, object_names)
    out, maps = {}, {}  # maps: each map_d read once, one array for every object using it
    for name in object_names:
        counts = uses.get(name, Counter())
        entry = library.get(counts.most_common(1)[0][0] if counts else None)
        if entry is None:
            continue
        d = float(entry.get("d", 1.0)) if entry.get("illum") in TRANSPARENT_ILLUM else 1.0
        alpha = None
        if "map_d" in entry and os.path.isfile(entry["map_d"]):
            if entry["map_d"] not in maps:
                maps[entry["map_d"]] = _dissolve_image(entry["map_d"])
            alpha = maps[entry["map_d"]]
        if alpha is not None or d < 1.0:
            out[name] = (alpha, d)
    return out


def _dissolve_image(path: str) -> np.ndarray | None:
    import warnings

    import imageio.v3 as iio

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            image = np.asarray(iio.imread(path))
    except Exception:  # not an image: treated as no map (the object is opaque but for its d)
        return None
    if image.dtype.kind != "u" or image.ndim not in (2, 3) or min(image.shape[:2]) < 1:
        return None
    channel = image if image.ndim == 2 else image[:, :, -1] if image.shape[2] in (2, 4) else image[:, :, 0]
    return channel.astype(np.float64) / float(np.iinfo(image.dtype).max)


def _mtl_material(entry: dict, default: Material) -> tuple[Material, str | None]:
    albedo = entry.get("Kd", default.albedo)
    specular = entry.get("Ks", (0.0, 0.0, 0.0))
    exponent = max(float(entry.get("Ns", default.exponent)), 1.0)
    if max(specular) > 0:
        material = Material("glossy", albedo=albedo, specular=specular, exponent=min(exponent, MAX_EXPONENT))
    else:
        material = Material("diffuse", albedo=albedo, exponent=min(exponent, MAX_EXPONENT))
    return material, entry.get("map_Kd")


def _obj_library(path: str, object_names: list[str], warn=None) -> tuple[dict, dict, dict, bool]:
    """An OBJ file's material uses per object (:func:`obj_material_names`, a file without groups
    named after the file), its libraries' entries and the library each came from, and whether
    the file refers to any material; ``warn`` (if given) hears of a missing library."""
    uses, libraries = obj_material_names(path)
    referenced = bool(libraries) or any(m is not None for counts in uses.values() for m in counts)
    library: dict[str, dict] = {}
    sources: dict[str, str] = {}
    for mtl in libraries:
        if not os.path.isfile(mtl):
            if warn is not None:
                warn(f"{path}: material library {os.path.basename(mtl)} not found")
            continue
        for name, entry in read_mtl(mtl).items():
            library.setdefault(name, entry)
            sources.setdefault(name, os.path.basename(mtl))
    if len(object_names) == 1 and object_names[0] not in uses and len(uses) == 1:
        uses = {object_names[0]: next(iter(uses.values()))}  # a file without groups, named after the file
    return uses, library, sources, referenced


def _obj_materials(path: str, object_names: list[str], default: Material, warn) -> tuple[list[ObjectMaterial], bool]:
    """The objects' materials, and whether the file refers to any (mtllib or usemtl)."""
    uses, library, sources, referenced = _obj_library(path, object_names, warn)
    out = []
    for name in object_names:
        counts = uses.get(name, Counter())
        if len([m for m in counts if m is not None]) > 1:
            warn(f"{path}: object {name!r} uses {len(counts)} materials; the most used one is taken for all of it")
        chosen = counts.most_common(1)[0][0] if counts else None
        if chosen is None or chosen not in library:
            continue
        material, texture = _mtl_material(library[chosen], default)
        if texture is not None and not os.path.isfile(texture):
            warn(f"{path}: object {name!r}: albedo texture {texture} not found; using Kd")
            texture = None
        if texture is not None:
            read_albedo_texture(texture, error=GeometryError)  # a corrupt image stops the build here
        out.append(ObjectMaterial(name, material, f"{sources[chosen]}: {chosen}", None if texture is None else Path(texture)))
    return out, referenced


# --------------------------------------------------------------------------- glTF


def _gltf_materials(path: str, object_names: list[str], default: Material, warn) -> list[ObjectMaterial]:
    """The materials of a glTF file's objects, read by the reader (and names) load_geometry uses."""
    from .gltf_scene import read_gltf_scene

    scene = read_gltf_scene(path)  # errors already reported by load_geometry
    wanted = set(object_names)
    return [gltf_part_material(scene, part, warn) for part in scene.parts if part.name in wanted and part.material is not None]


def gltf_part_material(scene, part, warn) -> ObjectMaterial:
    """The :class:`ObjectMaterial` of one part (node primitive) of a :class:`~prt.train.inputs.gltf_scene.GltfScene`
    that has a ``material`` (the rules of the module docstring)."""
    from ..deform.gltf_animation import malformed_gltf
    from .gltf_scene import SPEC_GLOSS, albedo_texture_info

    with malformed_gltf(scene.path):
        spec = scene.document["materials"][part.material]
        label = spec.get("name") or f"material {part.material}"
        where = f"{scene.path}: object {part.name!r} ({label})"
        colour = scene.mean_vertex_colour(part)
        colour = np.ones(3) if colour is None else colour
        gloss = spec.get("extensions", {}).get(SPEC_GLOSS)
        texture_info = albedo_texture_info(scene.document, part.material)
        if gloss is not None:
            texture, mean = _albedo_texture(scene, part, texture_info, where, warn)
            specular = np.asarray(gloss.get("specularFactor", [1.0, 1.0, 1.0]), dtype=np.float64)[:3]
            glossiness = float(gloss.get("glossinessFactor", 1.0))
            if gloss.get("specularGlossinessTexture") is not None:
                image = _texture_image(scene, gloss["specularGlossinessTexture"], where, "specular-glossiness", warn)
                if image is not None:
                    specular = specular * srgb_to_linear(_unit(image)[:, :, :3]).mean(axis=(0, 1))
                    glossiness *= float(_unit(image)[:, :, 3].mean()) if image.shape[2] == 4 else 1.0
            diffuse = np.asarray(gloss.get("diffuseFactor", [1.0, 1.0, 1.0, 1.0]), dtype=np.float64)[:3] * colour
            material = spec_gloss_material(diffuse, specular, glossiness, mean)
        else:
            pbr = spec.get("pbrMetallicRoughness", {})
            texture, mean = _albedo_texture(scene, part, texture_info, where, warn)
            roughness, metallic = float(pbr.get("roughnessFactor", 1.0)), float(pbr.get("metallicFactor", 1.0))
            if pbr.get("metallicRoughnessTexture") is not None:
                image = _texture_image(scene, pbr["metallicRoughnessTexture"], where, "metallic-roughness", warn)
                if image is not None and image.shape[2] >= 3:  # linear: G roughness, B metalness
                    roughness *= float(_unit(image)[:, :, 1].mean())
                    metallic *= float(_unit(image)[:, :, 2].mean())
            base = np.asarray(pbr.get("baseColorFactor", [1.0, 1.0, 1.0, 1.0]), dtype=np.float64)[:3] * colour
            material = pbr_material(base, roughness, metallic, mean)
    return ObjectMaterial(part.name, material, f"{os.path.basename(scene.path)}: {label}", texture)


def _unit(image: np.ndarray) -> np.ndarray:
    """An 8- or 16-bit image's values in [0, 1] (float64)."""
    return image.astype(np.float64) / float(np.iinfo(image.dtype).max)


def _texture_image(scene, info, where: str, role: str, warn) -> np.ndarray | None:
    image = scene.image(int(info["index"]))
    if image is None and int(info["index"]) in scene.unreadable:
        warn(f"{where}: the {role} texture is a {scene.unreadable[int(info['index'])]} GPU texture, not decoded here; using the factors alone")
    elif image is None:
        warn(f"{where}: the {role} texture's image file is missing; using the factors alone")
    elif max(image.shape[:2]) > MAX_TEXTURE_SIZE:
        raise GeometryError(f"{where}: {role} texture {image.shape[1]}x{image.shape[0]} exceeds {MAX_TEXTURE_SIZE} pixels a side")
    return image


def _albedo_texture(scene, part, info, where: str, warn) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The base colour (diffuse) texture as (H, W, 3) uint8 sRGB and its mean linear colour, or (None, None)."""
    if info is None:
        return None, None
    if scene.texture_coords(part, info) is None:
        warn(f"{where}: its colour texture needs TEXCOORD_{int(info.get('texCoord', 0))}, which the primitive lacks; using the factors alone")
        return None, None
    image = _texture_image(scene, info, where, "colour", warn)
    if image is None:
        return None, None
    rgb = image[:, :, :3] if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)
    rgb8 = rgb if rgb.dtype == np.uint8 else np.round(_unit(rgb) * 255.0).astype(np.uint8)
    linear = srgb_to_linear(rgb8 / 255.0)
    # A cut-out's clear texels are not surface (gltf_scene.cut_parts): its colour is its opaque texels'.
    from .gltf_scene import alpha_cutoff, factor_alpha

    spec = scene.document["materials"][part.material]
    cutoff = alpha_cutoff(spec)
    if cutoff is not None and image.shape[2] in (2, 4):
        opaque = factor_alpha(spec) * _unit(image[:, :, -1]) >= cutoff
        if opaque.any():
            return np.ascontiguousarray(rgb8), linear[opaque].mean(axis=0)
    return np.ascontiguousarray(rgb8), linear.mean(axis=(0, 1))


def pbr_material(base_color, roughness, metallic, texture_mean=None) -> Material:
    """A glTF metallic-roughness material as a :class:`Material` (see the module docstring).

    ``base_color`` is RGB(A) in [0, 1] or uint8; None means 1.  ``roughness`` and ``metallic``
    None take glTF's defaults (1).  ``texture_mean``: the base colour texture's mean linear colour
    (it tints a metal's specular; None: no texture).
    """
    base = np.ones(3) if base_color is None else np.asarray(base_color, dtype=np.float64).reshape(-1)[:3]
    if base_color is not None and np.asarray(base_color).dtype.kind in "ui":
        base = base / 255.0
    base = np.clip(base, 0.0, 1.0)
    rough = 1.0 if roughness is None else float(np.clip(roughness, 0.0, 1.0))
    metal = 1.0 if metallic is None else float(np.clip(metallic, 0.0, 1.0))
    tint = np.ones(3) if texture_mean is None else np.asarray(texture_mean, dtype=np.float64)
    exponent = roughness_to_exponent(rough)
    if exponent < 1.0:  # a lobe as wide as the diffuse one: reflected diffusely (4 % dielectric dropped)
        return Material("diffuse", albedo=base)
    specular = DIELECTRIC_F0 * (1.0 - metal) + base * tint * metal
    return Material("glossy", albedo=base * (1.0 - metal), specular=specular, exponent=exponent)


def spec_gloss_material(diffuse, specular, glossiness, texture_mean=None) -> Material:
    """A ``KHR_materials_pbrSpecularGlossiness`` material as a :class:`Material` (module docstring).

    ``diffuse`` and ``specular`` RGB in [0, 1], ``glossiness`` in [0, 1]; ``texture_mean``: the
    diffuse texture's mean linear colour (None: no texture).
    """
    spec = np.clip(np.asarray(specular, dtype=np.float64).reshape(-1)[:3], 0.0, 1.0)
    c_diff = np.clip(np.asarray(diffuse, dtype=np.float64).reshape(-1)[:3], 0.0, 1.0) * (1.0 - float(spec.max()))
    exponent = roughness_to_exponent(1.0 - float(np.clip(glossiness, 0.0, 1.0)))
    if exponent < 1.0:  # too rough for a lobe: the specular reflection joins the diffuse albedo
        tint = np.ones(3) if texture_mean is None else np.maximum(np.asarray(texture_mean, dtype=np.float64), 1e-3)
        return Material("diffuse", albedo=np.minimum(c_diff + spec / tint, 1.0))
    return Material("glossy", albedo=c_diff, specular=spec, exponent=exponent)


# --------------------------------------------------------------------------- entry point


def mesh_materials(path: str, object_names: list[str], default: dict, log=print) -> list[ObjectMaterial]:
    """The materials of a mesh file's objects; objects without one are left out (they take the
    scene-wide ``default``), listed in one warning line.

    Parameters
    ----------
    path : str
        The mesh file (``.obj``, ``.gltf``, ``.glb``; other formats have no materials).
    object_names : list of str
        ``Geometry.object_names``.
    default : dict
        The build's scene-wide manifest ``material`` (albedo etc. for what a file leaves out).
    log : callable
        Receives warning lines.
    """
    try:
        base = Material(kind=default.get("type", "diffuse"), **{k: default[k] for k in ("albedo", "specular", "exponent") if k in default})
    except InputError as exc:
        raise GeometryError(f"material: {exc}") from None
    warnings: list[str] = []
    extension = os.path.splitext(path)[1][1:].lower()
    referenced = False  # a file that names no material at all is not warned about
    if extension == "obj":
        found, referenced = _obj_materials(path, object_names, base, warnings.append)
    elif extension in ("gltf", "glb"):
        found = _gltf_materials(path, object_names, base, warnings.append)
    else:
        found = []
    named = {m.object for m in found}
    missing = [n for n in object_names if n not in named]
    if missing and (found or referenced):
        shown = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        warnings.append(f"{path}: no material for {shown}; using the scene material (albedo {', '.join(f'{a:g}' for a in base.albedo)})")
    for line in warnings:
        log(f"warning: {line}")
    return found


def textured_geometry(path: str, geometry, materials: list[ObjectMaterial], log=print):
    """The corner UVs the materials' albedo textures need, found on ``geometry``'s triangles
    (:mod:`prt.train.inputs.albedo_uv`); without UVs in the file the textures are dropped (one warning).

    Returns
    -------
    materials : list of ObjectMaterial
    albedo_uv : (F, 3, 2) float32 or None
        None when no material has a texture.
    """
    import dataclasses

    from .albedo_uv import match_corner_uvs

    if not any(m.albedo_texture is not None for m in materials):
        return materials, None
    found = corner_uvs(path)
    if found is None:
        log(f"warning: {path}: albedo textures need texture coordinates and the file has none; using the colours alone")
        return [dataclasses.replace(m, albedo_texture=None) for m in materials], None
    albedo_uv, unmatched = match_corner_uvs(geometry, *found)
    if unmatched:
        log(f"warning: {path}: {unmatched} triangles matched no triangle of the file; their texture coordinates are 0")
    return materials, albedo_uv


def obj_cut(path: str, vertices, faces, object_ids, object_names, found=None):
    """An OBJ file's triangles with its dissolved objects applied (:func:`obj_alpha_masks`):
    an object whose ``d`` is under 0.5 without a ``map_d`` is left out as glass (as glTF's clear
    blended parts), one with a ``map_d`` is cut where ``d`` times the map's alpha is under 0.5
    (:func:`prt.train.inputs.cutout.cut_corners`).  ``found``: the file's corner UVs
    (:func:`prt.train.inputs.albedo_uv.file_corner_uvs`, read here when None).

    Returns
    -------
    vertices, faces, object_ids : the triangles (as corners, three vertices each, where anything was cut)
    report : dict with ``see_through`` (names), ``cut`` (name -> (pieces, triangles before)),
        ``cut_away`` (names), ``uncut`` (names whose map could not be lined up with the file's UVs)
    found : the corner UVs of the result, (positions, uvs), or None
    """
    from .albedo_uv import _obj_corner_uvs
    from .cutout import cut_corners

    report = {"see_through": [], "cut": {}, "cut_away": [], "uncut": []}
    masks = obj_alpha_masks(path, object_names)
    if not masks:
        return vertices, faces, object_ids, report, found
    index = {name: k for k, name in enumerate(object_names)}
    glass = [name for name, (alpha, d) in masks.items() if alpha is None and d < 0.5]
    scaled: dict = {}  # (map, d) -> d x the map: shared by the objects that use both (one table per texture)
    for alpha, d in masks.values():
        if alpha is not None and (id(alpha), d) not in scaled:
            scaled[id(alpha), d] = (d * alpha).astype(np.float32)
    textured = {index[name]: (scaled[id(alpha), d], 0.5) for name, (alpha, d) in masks.items() if alpha is not None}
    keep = ~np.isin(object_ids, [index[name] for name in glass])
    if len(glass) == len(object_names) or not (glass or textured):  # nothing left, or nothing to do
        return vertices, faces, object_ids, report, found
    report["see_through"] = glass
    if found is None and textured:
        found = _obj_corner_uvs(path)
    corners = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    if textured and (found is None or found[0].shape != corners.shape or not np.allclose(found[0], corners)):
        report["uncut"], textured = [object_names[o] for o in textured], {}
    uvs = found[1] if found is not None and found[1].shape[0] == len(corners) else np.zeros(corners.shape[:2] + (2,))
    positions, uvs, owner, _ = cut_corners(corners[keep], uvs[keep], np.asarray(object_ids)[keep], textured)
    for o in textured:
        before, after = int(np.count_nonzero(np.asarray(object_ids) == o)), int(np.count_nonzero(owner == o))
        if after == 0:
            report["cut_away"].append(object_names[o])
        elif after != before or not np.array_equal(positions[owner == o], corners[np.asarray(object_ids) == o]):
            report["cut"][object_names[o]] = (after, before)
    faces = np.arange(3 * len(positions), dtype=np.int64).reshape(-1, 3)
    return positions.reshape(-1, 3), faces, owner, report, (positions, uvs) if found is not None else None


def corner_uvs(path: str):
    """The file's triangles with their corner UVs (:func:`prt.train.inputs.albedo_uv.file_corner_uvs`)
    as :func:`prt.train.inputs.geometry.load_geometry` has the triangles: an OBJ's cut-outs cut
    (:func:`obj_cut`; glTF's are cut by its reader)."""
    from .albedo_uv import file_corner_uvs
    from .objfile import read_obj

    found = file_corner_uvs(path)
    if found is None or os.path.splitext(path)[1].lower() != ".obj":
        return found
    vertices, faces, object_ids, names = read_obj(path)
    names = [os.path.splitext(os.path.basename(path))[0]] if names == [DEFAULT_OBJECT] else names  # as load_geometry names it
    return obj_cut(path, vertices, faces, object_ids, names, found)[4]
