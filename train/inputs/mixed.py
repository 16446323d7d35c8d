"""Mixed scenes: meshes, analytic SDFs and neural SDFs composed into one :class:`Geometry`.

A build spec may list ``objects`` instead of one ``geometry``::

    "objects": [
      {"mesh": "ground.obj", "name": "ground", "scale": 1.0, "translate": [0, -0.5, 0]},
      {"sdf": "sphere", "scale": 0.3, "translate": [0.5, -0.2, 0], "material": {"type": "glossy", ...}},
      {"neural_sdf": "bunny.sdf.onnx", "rotate": [0, 30, 0], "scale": 0.5}
    ]

Entries
-------
- exactly one of ``mesh`` (a mesh file), ``sdf`` (a built-in SDF: a library scene of
  :mod:`prt.train.sdf.library` or one of the unit primitives :data:`PRIMITIVES`) or
  ``neural_sdf`` (a ``*.sdf.onnx`` network built by ``prt-train MESH --neural-sdf``); relative
  paths resolve against the spec file's folder;
- optional ``name`` (default: the file stem or SDF name; repeats get ``_2``, ``_3``...),
  ``scale`` (a number > 0), ``rotate`` (degrees about x, y, z: the x rotation is applied
  first, then y, then z, i.e. ``R = Rz Ry Rx``), ``translate`` ([x, y, z]) and ``material``
  (the form of the spec's ``material``; objects without one take it).

Units
-----
Every object starts in the unit box: a mesh file is normalised into [-1, 1]^3 (as a lone mesh
is), library SDF scenes lie in [-0.95, 0.95]^3, neural SDFs in [-0.9, 0.9]^3 and the
primitives in [-1, 1]^3.  Each object is then scaled, rotated (about the origin) and translated,
in that order: ``p = translate + R (scale q)``.  The composed scene is finally fitted into the
G-buffer's scene box by one global similarity applied to meshes and SDF nodes alike: the
centre of its bounding box goes to the origin and its largest half extent to
:data:`SCENE_FILL`.  ``to_source`` maps scene units back to spec units.

Composition
-----------
``geometry.mesh`` holds the mesh objects' triangles followed by each SDF object's
marching-cubes proxy (so surface sampling stays area-uniform across all objects), one object
id per entry.  :class:`MixedParts` (``geometry.mixed``) keeps per face whether it is a proxy,
each SDF object's node tree in scene units (samples on a proxy are projected onto their own
object's zero set, with its gradient as normal) and their union, whose GLSL records the object
it hit (:meth:`MixedParts.glsl`).  Visibility (:class:`prt.train.transport.transfer.MixedTracer`) is blocked if Embree (the
mesh objects) or the sphere tracer (the SDF union) blocks a ray.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...runtime.errors import GeometryError, SpecError

__all__ = [
    "OBJECT_KINDS", "PRIMITIVES", "SCENE_FILL", "ObjectSpec", "MixedParts",
    "parse_objects", "resolve_objects", "rotation_matrix", "compose_objects", "sdf_object", "load_scene_geometry",
]  # fmt: skip

OBJECT_KINDS = ("mesh", "sdf", "neural_sdf")
_KEYS = set(OBJECT_KINDS) | {"name", "scale", "translate", "rotate", "material"}
SCENE_FILL = 0.95  # largest half extent of a composed scene (the G-buffer's box is 1.001)
PROXY_RESOLUTION = 96  # marching-cubes grid of each SDF object's proxy mesh (its own unit frame)


def _primitives() -> dict:
    from ..sdf import Box, Sphere, Torus

    return {
        "sphere": Sphere((0.0, 0.0, 0.0), 1.0),
        "box": Box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), rounding=0.05),
        "torus": Torus((0.0, 0.0, 0.0), 0.7, 0.3),
    }


PRIMITIVES = ("sphere", "box", "torus")  # unit primitives: sphere radius 1, box [-1, 1]^3, torus 0.7 / 0.3 flat in xz


@dataclass
class ObjectSpec:
    """One checked entry of ``objects``; ``source`` is a path (mesh, neural_sdf) or an SDF name."""

    kind: str
    source: str
    name: str
    scale: float = 1.0
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    material: dict | None = None

    def to_dict(self) -> dict:
        out = {self.kind: self.source, "name": self.name, "scale": self.scale, "translate": list(self.translate), "rotate": list(self.rotate)}
        return out | ({} if self.material is None else {"material": self.material})


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def parse_objects(objects, where: str = "objects") -> list[ObjectSpec]:
    """Check the spec's ``objects`` list; SpecError ``objects[i].field: ...`` (one line) on a bad entry."""
    from ...runtime.manifest import validate_manifest_field

    if not isinstance(objects, list) or not objects:
        raise SpecError(f"{where}: expected a non-empty list of objects ({{'mesh': path}}, {{'sdf': name}} or {{'neural_sdf': path}})")
    out, names = [], set()
    for i, entry in enumerate(objects):
        at = f"{where}[{i}]"
        if not isinstance(entry, dict):
            raise SpecError(f"{at}: expected an object such as {{'mesh': 'ground.obj'}}, got {type(entry).__name__}")
        unknown = sorted(set(entry) - _KEYS)
        if unknown:
            raise SpecError(f"{at}.{unknown[0]}: unknown field (known: {', '.join(sorted(_KEYS))})")
        kinds = [k for k in OBJECT_KINDS if k in entry]
        if len(kinds) != 1:
            raise SpecError(f"{at}: expected exactly one of 'mesh', 'sdf', 'neural_sdf', got {kinds or 'none'}")
        kind = kinds[0]
        source = entry[kind]
        if not isinstance(source, str) or not source.strip() or "\0" in source:
            raise SpecError(f"{at}.{kind}: expected a {'name' if kind == 'sdf' else 'file path'}, got {source!r}")
        if kind == "sdf":
            from ..sdf import sdf_names

            known = list(PRIMITIVES) + sdf_names()
            if source not in known:
                raise SpecError(f"{at}.sdf: unknown SDF {source!r} (known: {', '.join(known)})")
        if kind == "neural_sdf" and not source.lower().endswith(".sdf.onnx"):
            raise SpecError(f"{at}.neural_sdf: expected a '*.sdf.onnx' network (prt-train MESH --neural-sdf), got {source!r}")
        scale = entry.get("scale", 1.0)
        if not _finite(scale) or scale <= 0:
            raise SpecError(f"{at}.scale: expected a finite number > 0, got {scale!r}")
        vectors = {}
        for key in ("translate", "rotate"):
            value = entry.get(key, [0.0, 0.0, 0.0])
            if not isinstance(value, list) or len(value) != 3 or not all(_finite(v) for v in value):
                raise SpecError(f"{at}.{key}: expected 3 finite numbers [x, y, z]{' (degrees)' if key == 'rotate' else ''}, got {value!r}")
            vectors[key] = tuple(float(v) for v in value)
        material = entry.get("material")
        if material is not None:
            if not isinstance(material, dict):
                raise SpecError(f"{at}.material: expected an object like the spec's material, got {type(material).__name__}")
            try:
                validate_manifest_field("material", material, "spec")
            except SpecError as exc:
                raise SpecError(f"{at}.{str(exc).removeprefix('spec: ')}") from None
        name = entry.get("name")
        if name is None:
            stem = Path(source).name.removesuffix(".sdf.onnx") if kind == "neural_sdf" else Path(source).stem if kind == "mesh" else source
            name, k = stem or kind, 2
            while name in names:
                name, k = f"{stem}_{k}", k + 1
        elif not isinstance(name, str) or not name.strip() or any(ord(c) < 32 for c in name):
            raise SpecError(f"{at}.name: expected a non-empty name, got {name!r}")
        elif name in names:
            raise SpecError(f"{at}.name: {name!r} names an earlier object too (names must be unique)")
        names.add(name)
        out.append(ObjectSpec(kind, source, name, float(scale), vectors["translate"], vectors["rotate"], material))
    return out


def resolve_objects(objects: list[dict], spec_path) -> list[dict]:
    """``objects`` with relative file paths made relative to the spec file's folder; SpecError
    ``SPEC: objects[i].mesh: no such file`` when a file is missing."""
    folder = Path(spec_path).parent
    out = []
    for i, entry in enumerate(objects):
        entry = dict(entry)
        for kind in ("mesh", "neural_sdf"):
            if isinstance(entry.get(kind), str):
                path = Path(entry[kind])
                path = path if path.is_absolute() else folder / path
                if not path.is_file():
                    raise SpecError(f"{spec_path}: objects[{i}].{kind}: no such file {str(path)!r}")
                entry[kind] = str(path)
        out.append(entry)
    return out


def rotation_matrix(degrees) -> np.ndarray:
    """``Rz @ Ry @ Rx`` for rotations of ``degrees`` (x, y, z) about the axes (x first)."""
    x, y, z = np.radians(np.asarray(degrees, dtype=np.float64))
    rx = np.array([[1, 0, 0], [0, math.cos(x), -math.sin(x)], [0, math.sin(x), math.cos(x)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    rz = np.array([[math.cos(z), -math.sin(z), 0], [math.sin(z), math.cos(z), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _base_sdf(kind: str, source: str):
    """The untransformed SDF of an ``sdf`` or ``neural_sdf`` entry (an :class:`~prt.train.sdf.SDF`)."""
    from ..sdf import SDF, Box, Intersection, get_sdf

    if kind == "sdf":
        primitives = _primitives()
        return SDF(source, primitives[source]) if source in primitives else get_sdf(source)
    from ..sdf.neural import load_neural_sdf

    try:
        net = load_neural_sdf(source)
    except (ValueError, OSError) as error:
        raise GeometryError(f"{source}: not a neural SDF network ({error})") from None
    # The network is fitted in [-1, 1]^3 only; outside it (clipped input) its values mean nothing.
    # Intersecting with a box just inside keeps the field a distance bound everywhere.
    # It is also the network's lower bound (max(net, box) >= box): the GLSL skips the network where the
    # box is farther than the nearest other object (_lower_bound).
    return SDF(net.name, Intersection((net.root, Box((0.0, 0.0, 0.0), (0.98, 0.98, 0.98)))), "neural SDF")


def _lower_bound(sdf):
    """An SDF ``b`` with ``b <= sdf`` everywhere, cheap to evaluate, or None: for a (placed) neural
    object, its intersecting box under the same transforms."""
    from ..sdf import SDF, Box, Intersection, Rotate, Scale, Translate

    chain, node = [], sdf.root
    while isinstance(node, (Translate, Rotate, Scale)):
        chain.append(node)
        node = node.child
    if not isinstance(node, Intersection) or node.cost < 100.0:
        return None
    boxes = [c for c in node.children if isinstance(c, Box)]
    if not boxes:
        return None
    bound = boxes[0]
    for wrapper in reversed(chain):
        bound = type(wrapper)(**{**{f: getattr(wrapper, f) for f in wrapper.__dataclass_fields__}, "child": bound})
    return SDF(sdf.name + "_bound", bound)


def sdf_object(kind: str, source: str, scale: float, rotation: np.ndarray, translate, name: str | None = None):
    """An SDF entry placed in scene units: ``p = translate + rotation (scale q)`` (an ``SDF``)."""
    from ..sdf import SDF, Rotate, Scale, Translate

    base = _base_sdf(kind, source)
    node = base.root
    if scale != 1.0:
        node = Scale(float(scale), node)
    if not np.allclose(rotation, np.eye(3)):
        node = Rotate(tuple(map(tuple, np.asarray(rotation, dtype=np.float64))), node)
    if np.any(np.asarray(translate) != 0.0):
        node = Translate(tuple(float(t) for t in translate), node)
    return SDF(name or base.name, node, base.description), base


@dataclass
class MixedParts:
    """What a mixed :class:`~prt.train.inputs.geometry.Geometry` holds beyond its triangles.

    Attributes
    ----------
    objects : list of ObjectSpec
        The entries, in object-id order.
    kinds : list of str
        Per object: ``"mesh"`` (rasterised) or ``"sdf"`` (sphere traced; analytic or neural).
    proxy_faces : (F,) bool
        Faces of ``geometry.mesh`` that are an SDF object's marching-cubes proxy.
    sdfs : dict of int -> SDF
        Each SDF object's field in scene units, by object id.
    placements : list of dict
        Per object, the final placement in scene units (``scale``, ``rotation`` 3x3, ``translate``),
        spec transform and global fit together; a bench rebuilds the SDF objects from it.
    materials : list of ObjectMaterial
        The entries' own materials.
    """

    objects: list[ObjectSpec]
    kinds: list[str]
    proxy_faces: np.ndarray
    sdfs: dict
    placements: list[dict]
    materials: list = field(default_factory=list)

    @property
    def sdf_ids(self) -> list[int]:
        return sorted(self.sdfs)

    def union(self):
        """The union of the SDF objects (an ``SDF``), or None without any."""
        from ..sdf import SDF, Union

        if not self.sdfs:
            return None
        roots = tuple(self.sdfs[k].root for k in self.sdf_ids)
        return SDF("mixed_sdf", roots[0] if len(roots) == 1 else Union(roots), "SDF objects of a mixed scene")

    def glsl(self, function_name: str = "scene_sdf") -> str:
        """GLSL defining ``float scene_sdf(vec3 p)`` (the union) and ``int prt_scene_object``, the
        object id of the nearest SDF object at the last call (each object's function has one call
        site, so a neural network is inlined once; it runs only where its box bound is nearer
        than the other objects)."""
        parts = [f"// SDF objects of a mixed scene, generated by prt.train.inputs.mixed; do not edit.\nint prt_scene_object = -1;\n"]
        calls = []
        # Objects with a cheap lower bound (neural SDFs: their box) go last and are skipped where the
        # bound is not below the nearest distance so far: the minimum, and its object, are unchanged.
        bounds = {k: _lower_bound(self.sdfs[k]) for k in self.sdf_ids}
        for k in sorted(self.sdf_ids, key=lambda k: (bounds[k] is not None, k)):
            fn = f"{function_name}_o{k}"
            parts.append(self.sdfs[k].glsl(fn))
            update = f"d = {fn}(p);\n    if (d < best) {{ best = d; prt_scene_object = {k}; }}"
            if bounds[k] is not None:
                parts.append(bounds[k].glsl(f"{fn}_bound"))
                update = f"if ({fn}_bound(p) < best) {{\n        {update.replace(chr(10), chr(10) + '    ')}\n    }}"
            calls.append("    " + update)
        body = "\n".join(calls)
        parts.append(f"float {function_name}(vec3 p) {{\n    float best = 3.0e38;\n    float d;\n{body}\n    return best;\n}}\n")
        return "\n".join(parts)

    def nearest_object(self, points: np.ndarray) -> np.ndarray:
        """Object id of the SDF object nearest to each point (the GLSL's ``prt_scene_object``), (N,) int64."""
        ids = self.sdf_ids
        d = np.stack([self.sdfs[k].evaluate(np.asarray(points, dtype=np.float64)) for k in ids])
        return np.asarray(ids, dtype=np.int64)[np.argmin(d, axis=0)]

    def record(self, out: Path) -> dict:
        """The ``mixed.json`` record of a scene folder: the objects with their final placements; a
        neural SDF's network is copied into the folder (``objects/<k>_<name>``) so the folder is whole."""
        from ...runtime.files import atomic_write_bytes

        records = []
        for k, (obj, kind, place) in enumerate(zip(self.objects, self.kinds, self.placements)):
            entry = {"name": obj.name, "kind": obj.kind, "render": kind, "spec": obj.to_dict(),
                     "scale": float(place["scale"]), "rotation": np.asarray(place["rotation"]).tolist(),
                     "translate": np.asarray(place["translate"], dtype=np.float64).tolist()}  # fmt: skip
            if obj.kind == "neural_sdf":
                folder = out / "objects"
                folder.mkdir(exist_ok=True)
                target = folder / f"{k}_{Path(obj.source).name}"
                atomic_write_bytes(target, Path(obj.source).read_bytes())
                entry["source"] = os.path.relpath(target, out)
            elif obj.kind == "sdf":
                entry["source"] = obj.source
            records.append(entry)
        return {"format": "prt-mixed", "version": 1, "objects": records}


def load_scene_geometry(spec, *, sdf_resolution: int = PROXY_RESOLUTION):
    """The geometry of a build spec: its ``objects`` composed, or ``load_geometry(spec.geometry)``."""
    from .geometry import load_geometry

    if getattr(spec, "objects", None):
        return compose_objects(parse_objects(spec.objects), sdf_resolution=sdf_resolution, source=spec.geometry or "mixed")
    return load_geometry(spec.geometry)


def compose_objects(objects: list[ObjectSpec], *, sdf_resolution: int = PROXY_RESOLUTION, source: str = "mixed"):
    """Compose checked entries into one :class:`~prt.train.inputs.geometry.Geometry` of kind ``"mixed"``
    (``"mesh"`` when every entry is a mesh: a plain mesh scene of several objects).  See the module docstring for units.

    Raises
    ------
    GeometryError
        ``objects[i].<kind>: ...`` when an entry's file cannot be loaded.
    """
    import trimesh

    from ...runtime.materials import object_materials
    from .geometry import Geometry, load_geometry

    pieces = []  # (vertices in spec units, faces, two_sided, is_proxy, sdf base or None)
    for i, obj in enumerate(objects):
        rotation = rotation_matrix(obj.rotate)
        try:
            if obj.kind == "mesh":
                g = load_geometry(obj.source)
                vertices, faces, two_sided, base = np.asarray(g.mesh.vertices), np.asarray(g.mesh.faces), g.two_sided, None
            else:
                base = _base_sdf(obj.kind, obj.source)
                proxy = base.to_mesh(resolution=sdf_resolution)
                vertices, faces = np.asarray(proxy.vertices, dtype=np.float64), np.asarray(proxy.faces, dtype=np.int64)
                two_sided = np.zeros(len(faces), dtype=bool)
        except GeometryError as exc:
            raise GeometryError(f"objects[{i}].{obj.kind}: {exc}") from None
        if len(faces) == 0:
            raise GeometryError(f"objects[{i}].{obj.kind}: {obj.source}: no surface (empty proxy mesh)")
        placed = (obj.scale * vertices) @ rotation.T + np.asarray(obj.translate)
        pieces.append((placed, faces, np.asarray(two_sided, dtype=bool), base is not None, rotation))

    every = np.concatenate([p[0] for p in pieces])
    low, high = every.min(axis=0), every.max(axis=0)
    centre = (low + high) / 2.0
    fit = SCENE_FILL / max(float((high - low).max()) / 2.0, 1e-12)
    vertices, faces, object_ids, two_sided, proxy = [], [], [], [], []
    sdfs, placements, offset = {}, [], 0
    for k, ((placed, f, sided, is_sdf, rotation), obj) in enumerate(zip(pieces, objects)):
        vertices.append((placed - centre) * fit)
        faces.append(f + offset)
        offset += len(placed)
        object_ids.append(np.full(len(f), k, dtype=np.int64))
        two_sided.append(sided)
        proxy.append(np.full(len(f), is_sdf))
        # p_scene = fit (translate + R scale q - centre) = (fit scale) R q + fit (translate - centre)
        placement = {"scale": fit * obj.scale, "rotation": rotation, "translate": fit * (np.asarray(obj.translate) - centre)}
        placements.append(placement)
        if is_sdf:
            sdfs[k] = sdf_object(obj.kind, obj.source, placement["scale"], rotation, placement["translate"], obj.name)[0]
    mesh = trimesh.Trimesh(np.concatenate(vertices), np.concatenate(faces), process=False, validate=False)
    to_source = np.eye(4)
    to_source[:3, :3] /= fit
    to_source[:3, 3] = centre
    names = [o.name for o in objects]
    entries = [{"object": o.name, **o.material} for o in objects if o.material is not None]
    materials = object_materials({"materials": entries}, names, source)
    proxy_faces = np.concatenate(proxy)
    geometry = Geometry(
        mesh=mesh, object_ids=np.concatenate(object_ids), object_names=names, two_sided=np.concatenate(two_sided),
        to_source=to_source, source=source,
    )  # fmt: skip
    parts = MixedParts(list(objects), ["sdf" if k in sdfs else "mesh" for k in range(len(objects))], proxy_faces, sdfs, placements, materials)
    geometry.mixed = parts  # kind "mixed" with an SDF object, else "mesh" (the materials stay here)
    return geometry


def sdfs_from_record(record: dict, root: Path) -> dict:
    """Each SDF object's field (``SDF``) by object id, rebuilt from a ``mixed.json`` record."""
    out = {}
    for k, entry in enumerate(record["objects"]):
        if entry["render"] != "sdf":
            continue
        source = entry["source"] if entry["kind"] == "sdf" else str(Path(root) / entry["source"])
        out[k] = sdf_object(entry["kind"], source, entry["scale"], np.asarray(entry["rotation"]), entry["translate"], entry["name"])[0]
    return out
