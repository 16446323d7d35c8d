"""The scene manifest ``scene.json``: its typed model, loading and validation.

A trained scene is a folder holding ``scene.json`` plus the files it names (geometry, one
ONNX model and GLSL file per network segment, an optional environment map).  The format is
described by the JSON Schema ``schemas/scene.schema.json`` (format version 1); the checks a
schema cannot express are made by :mod:`prt.runtime.manifest_checks` (re-exported here):

- segment ids are ``0 .. S-1`` in list order;
- every index of the k-d tree is in range (roots and children -> nodes, leaves ->
  ``leaf_segment``, ``leaf_segment`` -> segments) and the nodes form trees (no cycles);
- boxes have ``min <= max``; ``lighting.sh`` has ``sh_bands**2`` rows; ``lighting.rotation``
  is a rotation; the camera's eye, target and up define a view;
- every path is relative and resolves (symlinks followed) to a file inside the scene folder;
- ``interreflection.albedos`` names objects of the (mesh) geometry.

Every failure raises :class:`~prt.runtime.errors.SpecError` with a one-line message naming
the file and the field, e.g. ``scene.json: segments[1].kind: 'netwrk' is not one of
['network', 'analytic']``.

One model serves both directions: :func:`load_manifest` returns a :class:`Manifest`
(:meth:`Manifest.from_dict`), and the writer :func:`prt.export.manifest.write_manifest`
serialises one (:meth:`Manifest.to_dict`) after the same checks.  The point -> segment rule
of the k-d tree lives in :mod:`prt.runtime.segmentation`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from .camera import DEFAULT_CAMERA
from .errors import ArgumentTypeError, SpecError
from .manifest_checks import (  # noqa: F401  (re-exported: the validation lives there)
    MANIFEST_NAME,
    SCENE_SCHEMA,
    _one_line,
    _resolve_paths,
    format_field_path,
    validate_manifest_dict,
    validate_manifest_field,
)
from .transfer_texture import TransferTextureInfo

__all__ = [
    "SCENE_SCHEMA",
    "FORMAT",
    "FORMAT_VERSION",
    "GENERATOR",
    "MANIFEST_NAME",
    "DEFAULT_CAMERA",
    "GeometryInfo",
    "SegmentInfo",
    "LightingInfo",
    "MaterialInfo",
    "CameraInfo",
    "MemoryInfo",
    "TransferTextureInfo",
    "InterreflectionInfo",
    "Manifest",
    "load_manifest",
    "validate_manifest_dict",
    "validate_manifest_field",
    "format_field_path",
]

FORMAT = "prt-scene"
FORMAT_VERSION = 3  # the newest version runtime/schemas/scene.schema.json describes (2: "mixed" geometry, 3: a deformation)
# Version 2 is the version of manifests with mixed geometry, every other manifest is version 1 (the
# schema ties them), so scenes without mixed geometry stay readable by version-1 runtimes.  Both load.
GENERATOR = "prt-train 0.1.0"  # what the build writes as ``generator``




def _array(value: Any) -> np.ndarray | None:
    """``value`` as a float64 array; None stays None."""
    return None if value is None else np.asarray(value, dtype=np.float64)


def _listed(value: Any) -> Any:
    """An array as nested lists (JSON arrays); anything else unchanged."""
    return value.tolist() if isinstance(value, np.ndarray) else value


def _relative(path: str | PurePath, root: Path) -> str:
    """POSIX path of ``path`` (absolute, or relative to the current directory) relative to ``root``."""
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(root))).as_posix()


@dataclass
class GeometryInfo:
    """The scene's geometry: a triangle mesh (``geometry.npz``), a built-in SDF scene, or a mixed
    scene (rasterised mesh objects + sphere-traced SDF objects, composited by depth).

    Attributes
    ----------
    type : str
        ``"mesh"``, ``"sdf"`` or ``"mixed"`` (format version 2).
    path : Path
        The mesh file (manifest field ``file``; mesh and mixed) or the SDF's GLSL (field ``glsl``);
        absolute and resolved in a loaded manifest.
    to_source : ndarray, shape (4, 4)
        Row-major affine transform from scene space back to source units.
    name : str or None
        SDF scene name (sdf only).
    triangles : int or None
        Triangle count (mesh only).
    objects : list of str or None
        Object names, indexed by object id (mesh and mixed).
    glsl : Path or None
        Mixed scenes: the SDF objects' GLSL (field ``glsl``): ``float scene_sdf(vec3 p)``, their
        union, setting ``int prt_scene_object`` to the nearest SDF object's id.
    kinds : list of str or None
        Mixed scenes: per object ``"mesh"`` (rasterised from :attr:`path`) or ``"sdf"`` (traced).
    """

    type: str
    path: Path
    to_source: np.ndarray
    name: str | None = None
    triangles: int | None = None
    objects: list[str] | None = None
    glsl: Path | None = None
    kinds: list[str] | None = None

    @property
    def path_field(self) -> str:
        """The manifest field that holds :attr:`path`: ``"file"`` (mesh, mixed) or ``"glsl"`` (sdf)."""
        return "glsl" if self.type == "sdf" else "file"

    @classmethod
    def from_dict(cls, data: dict, path: Path, glsl: Path | None = None) -> GeometryInfo:
        """From the manifest's ``geometry`` object, with its file already resolved to ``path`` (and a
        mixed scene's GLSL to ``glsl``)."""
        objects = data.get("objects")
        return cls(
            type=data["type"],
            path=path,
            to_source=np.asarray(data["to_source"], dtype=np.float64),
            name=data.get("name"),
            triangles=data.get("triangles"),
            objects=None if objects is None else list(objects),
            glsl=glsl,
            kinds=None if data.get("kinds") is None else list(data["kinds"]),
        )

    def to_dict(self, root: Path) -> dict:
        """The manifest's ``geometry`` object, :attr:`path` relative to the scene folder ``root``."""
        out = {"type": self.type, self.path_field: _relative(self.path, root), "to_source": _listed(self.to_source)}
        extra = {"name": self.name} if self.type == "sdf" else {"triangles": self.triangles, "objects": self.objects}
        if self.type == "mixed":
            extra |= {"glsl": _relative(self.glsl, root), "kinds": self.kinds}
        return out | extra


@dataclass
class SegmentInfo:
    """One segment of a manifest.

    Attributes
    ----------
    id : int
        Segment id, equal to its index in :attr:`Manifest.segments`.
    kind : str
        ``"network"`` (an MLP gives the transfer) or ``"analytic"`` (unshadowed transfer, a
        function of the normal alone).
    model : Path or None
        The ONNX model (absolute and resolved in a loaded manifest); None for analytic segments.
    glsl : Path or None
        The generated GLSL, if any.
    glsl_weights : Path or None
        ``.npy`` (H, W, 4) float32 weight texture for GLSL generated with the texture layout.
    bounds : ndarray, shape (2, 3)
        ``[min, max]`` corners of the box the network's input encoding normalises to.
    architecture : dict or None
        ``hidden``, ``layers``, ``pos_freqs``, ``normal_freqs``, ``input_dim`` (the frequency
        encoding); a grid-encoded network (:attr:`encoding` ``"grid"``) has ``encoding``,
        ``levels``, ``features``, ``log2_table``, ``base_resolution``, ``max_resolution``,
        ``hidden``, ``layers``, ``normal_freqs``, ``position``, ``input_dim`` (its GLSL reads the
        tables and weights from ``glsl_weights``); None when analytic.
    flops_per_fragment, weight_bytes : int
        Cost of evaluating the network per fragment and size of its weights (0 when absent).
    samples : int
        Training samples of the segment.
    validation : dict
        ``coeff_mae`` (float) and ``shaded_mae`` (dict of lighting name -> float).
    sizing : dict or None
        What right-sizing chose and why (``rule``, ``target``, ``chosen``, ``psnr_db``, ``met``,
        ``reason``, ``tried``); absent in scenes built before it was recorded.
    """

    id: int
    kind: str
    model: Path | None
    glsl: Path | None
    bounds: np.ndarray
    architecture: dict | None
    flops_per_fragment: int
    weight_bytes: int
    samples: int
    validation: dict
    glsl_weights: Path | None = None
    sizing: dict | None = None
    code: Path | None = None  # deformable scenes: the first layer's code rows (prt.runtime.deformation)

    @property
    def is_network(self) -> bool:
        return self.kind == "network"

    @property
    def encoding(self) -> str | None:
        """``"freq"`` (the frequency-encoded MLP; manifests without ``encoding``) or ``"grid"``; None when analytic."""
        return None if self.architecture is None else self.architecture.get("encoding", "freq")

    @classmethod
    def from_dict(cls, data: dict, files: dict[str, Path | None]) -> SegmentInfo:
        """From one entry of the manifest's ``segments``; ``files`` maps ``model``, ``glsl``
        and ``glsl_weights`` to resolved paths."""
        return cls(
            id=data["id"],
            kind=data["kind"],
            model=files.get("model"),
            glsl=files.get("glsl"),
            glsl_weights=files.get("glsl_weights"),
            code=files.get("code"),
            bounds=np.asarray(data["bounds"], dtype=np.float64),
            architecture=dict(data["architecture"]) if "architecture" in data else None,
            flops_per_fragment=data.get("flops_per_fragment", 0),
            weight_bytes=data.get("weight_bytes", 0),
            samples=data["samples"],
            validation={
                "coeff_mae": data["validation"]["coeff_mae"],
                "shaded_mae": dict(data["validation"]["shaded_mae"]),
            },
            sizing=dict(data["sizing"]) if "sizing" in data else None,
        )

    def to_dict(self, root: Path) -> dict:
        """The manifest's entry of this segment, paths relative to the scene folder ``root``."""
        out = {
            "id": self.id,
            "kind": self.kind,
            "bounds": _listed(self.bounds),
            "samples": self.samples,
            "validation": {"coeff_mae": self.validation["coeff_mae"], "shaded_mae": dict(self.validation["shaded_mae"])},
        }
        out |= {key: _relative(p, root) for key, p in self._files().items() if p is not None}
        if self.is_network:  # analytic segments have no network fields
            out |= {
                "architecture": self.architecture,
                "flops_per_fragment": self.flops_per_fragment,
                "weight_bytes": self.weight_bytes,
            }
        if self.sizing is not None:
            out["sizing"] = self.sizing
        return out

    def _files(self) -> dict[str, Path | None]:
        return {"model": self.model, "glsl": self.glsl, "glsl_weights": self.glsl_weights, "code": self.code}


@dataclass
class LightingInfo:
    """The scene's default lighting.

    Attributes
    ----------
    envmap : Path or None
        Environment map file (absolute and resolved in a loaded manifest).
    sh : ndarray, shape (sh_bands**2, 3), or None
        RGB light coefficients.
    rotation : ndarray, shape (3, 3), or None
        Rotation applied to the lighting.
    background : bool
        Draw ``envmap`` where no geometry is (else black).
    """

    envmap: Path | None = None
    sh: np.ndarray | None = None
    rotation: np.ndarray | None = None
    background: bool = False

    @classmethod
    def from_dict(cls, data: dict, envmap: Path | None) -> LightingInfo:
        """From the manifest's ``lighting`` object, with its env map already resolved."""
        return cls(envmap=envmap, sh=_array(data.get("sh")), rotation=_array(data.get("rotation")), background=bool(data.get("background", False)))

    def to_dict(self, root: Path) -> dict:
        """The manifest's ``lighting`` object; ``envmap`` is always written (null for none)."""
        out: dict[str, Any] = {"envmap": None if self.envmap is None else _relative(self.envmap, root)}
        if self.sh is not None:
            out["sh"] = _listed(self.sh)
        if self.rotation is not None:
            out["rotation"] = _listed(self.rotation)
        if self.background:
            out["background"] = True
        return out


@dataclass
class MaterialInfo:
    """The scene's default material.

    Attributes
    ----------
    type : str
        ``"diffuse"`` or ``"glossy"``.
    albedo : ndarray, shape (3,)
    specular : ndarray, shape (3,), or None
    exponent : float or None
        Phong exponent (glossy).
    """

    type: str
    albedo: np.ndarray
    specular: np.ndarray | None = None
    exponent: float | None = None

    @classmethod
    def from_dict(cls, data: dict) -> MaterialInfo:
        """From the manifest's ``material`` object."""
        exponent = data.get("exponent")
        return cls(
            type=data["type"],
            albedo=np.asarray(data["albedo"], dtype=np.float64),
            specular=_array(data.get("specular")),
            exponent=None if exponent is None else float(exponent),
        )

    def to_dict(self) -> dict:
        """The manifest's ``material`` object (fields that are None left out)."""
        out = {"type": self.type, "albedo": _listed(self.albedo)}
        if self.specular is not None:
            out["specular"] = _listed(self.specular)
        if self.exponent is not None:
            out["exponent"] = self.exponent
        return out


@dataclass
class CameraInfo:
    """The scene's default camera; fields a manifest leaves out come from :data:`DEFAULT_CAMERA`.

    Attributes
    ----------
    eye, target, up : ndarray, shape (3,)
    fov : float
        Vertical field of view in degrees.
    """

    eye: np.ndarray = field(default_factory=lambda: np.asarray(DEFAULT_CAMERA["eye"], dtype=np.float64))
    target: np.ndarray = field(default_factory=lambda: np.asarray(DEFAULT_CAMERA["target"], dtype=np.float64))
    up: np.ndarray = field(default_factory=lambda: np.asarray(DEFAULT_CAMERA["up"], dtype=np.float64))
    fov: float = float(DEFAULT_CAMERA["fov"])

    @classmethod
    def from_dict(cls, data: dict) -> CameraInfo:
        """From the manifest's ``camera`` object (or a part of it)."""
        cam = {**DEFAULT_CAMERA, **data}
        vectors = {k: np.asarray(cam[k], dtype=np.float64) for k in ("eye", "target", "up")}
        return cls(**vectors, fov=float(cam["fov"]))

    def to_dict(self) -> dict:
        """The manifest's ``camera`` object (all four fields)."""
        return {"eye": _listed(self.eye), "target": _listed(self.target), "up": _listed(self.up), "fov": self.fov}


@dataclass
class MemoryInfo:
    """Storage of the scene's networks vs per-vertex transfer, in bytes."""

    weight_bytes: int
    vertex_storage_bytes: int

    @classmethod
    def from_dict(cls, data: dict) -> MemoryInfo:
        return cls(weight_bytes=data["weight_bytes"], vertex_storage_bytes=data["vertex_storage_bytes"])

    def to_dict(self) -> dict:
        return {"weight_bytes": self.weight_bytes, "vertex_storage_bytes": self.vertex_storage_bytes}


@dataclass
class InterreflectionInfo:
    """Diffuse interreflection baked into the transfer (``prt-train --bounces``; optional field).

    Attributes
    ----------
    bounces : int
        N >= 1 diffuse bounces.
    bounce_rays : int
        Rays per sample of the bounce stage.
    layout : str
        ``"direct+rgb"``: each network outputs the direct transfer, then the indirect transfer of
        the R, G and B channels (``4 sh_bands**2`` values).
    albedos : dict of str to list of 3 floats
        Diffuse albedo of each object as it bounced light (fixed at build time).
    auto : dict or None
        With ``prt-train --bounces auto``: what chose ``bounces`` (threshold, truncation PSNR and
        relative MAE per env map and N, :func:`prt.train.transport.bounce_depth.auto_bounces`).
    """

    bounces: int
    bounce_rays: int
    layout: str = "direct+rgb"
    albedos: dict = field(default_factory=dict)
    auto: dict | None = None

    # Outputs of a network per SH coefficient of the direct transfer.
    WIDTHS = {"direct+rgb": 4}

    @classmethod
    def from_dict(cls, data: dict) -> InterreflectionInfo:
        return cls(bounces=data["bounces"], bounce_rays=data["bounce_rays"], layout=data["layout"],
                   albedos={k: [float(x) for x in v] for k, v in data["albedos"].items()}, auto=data.get("auto"))  # fmt: skip

    def to_dict(self) -> dict:
        return {"bounces": self.bounces, "bounce_rays": self.bounce_rays, "layout": self.layout,
                "albedos": {k: [float(x) for x in v] for k, v in self.albedos.items()}, **({"auto": self.auto} if self.auto else {})}  # fmt: skip


@dataclass
class DeformationInfo:
    """A deformable object (``prt-train --deform``; format version 3).

    Attributes
    ----------
    path : Path
        ``deformation.npz`` (:class:`prt.runtime.deformation.Deformation`): rest pose, frames, codes, basis.
    source : dict
        Where the poses came from (``kind``: sequence, gltf or procedural; path, animation, parameters).
    code : dict
        The shape code: ``kind`` ("pca"), ``dim``, ``freqs`` (and how much variance it keeps).
    frames : dict
        ``count`` and the frames' roles: ``train``, ``unseen``, ``extrapolated`` (indices); names, parameters.
    """

    path: Path
    source: dict
    code: dict
    frames: dict

    @classmethod
    def from_dict(cls, data: dict, path: Path) -> DeformationInfo:
        return cls(path=path, source=dict(data["source"]), code=dict(data["code"]), frames=dict(data["frames"]))

    def to_dict(self, root: Path) -> dict:
        return {"file": _relative(self.path, root), "source": self.source, "code": self.code, "frames": self.frames}


@dataclass
class Manifest:
    """A scene manifest: what :func:`load_manifest` returns and the writer serialises.

    Attributes
    ----------
    path : Path
        The manifest file (absolute and resolved when loaded).
    root : Path
        The scene folder (``path.parent``); every referenced file lies inside it.
    name : str
        Scene name.
    generator : str or None
        What wrote the manifest, e.g. :data:`GENERATOR`.
    sh_bands : int
        SH bands of the transfer; each segment outputs ``sh_bands**2`` coefficients.
    geometry : GeometryInfo
    segmentation : dict
        ``roots`` (dict of int object id -> node index), ``nodes`` (list of dicts) and
        ``leaf_segment`` (int64 ndarray); see :func:`prt.runtime.segmentation.segment_of`.
    segments : list of SegmentInfo
        Indexed by segment id.
    lighting : LightingInfo
    material : MaterialInfo
    camera : CameraInfo
    memory : MemoryInfo or None
        If recorded.
    transfer_texture : TransferTextureInfo or None
        If the scene has one (optional field; older manifests have none).
    interreflection : InterreflectionInfo or None
        Diffuse bounces baked into the transfer (optional field; absent: direct light only).
    raw : dict or None
        The parsed JSON, unchanged (None for a manifest not read from a file).
    """

    path: Path
    root: Path
    name: str
    generator: str | None
    sh_bands: int
    geometry: GeometryInfo
    segmentation: dict
    segments: list[SegmentInfo]
    lighting: LightingInfo
    material: MaterialInfo
    camera: CameraInfo
    memory: MemoryInfo | None
    transfer_texture: TransferTextureInfo | None = None
    raw: dict | None = field(default=None, repr=False)
    interreflection: InterreflectionInfo | None = None
    deformation: DeformationInfo | None = None

    @property
    def transfer_width(self) -> int:
        """Values a segment outputs per fragment: ``sh_bands**2``, or 4 times that with interreflection
        (direct, indirect R, G, B)."""
        n = self.sh_bands * self.sh_bands
        return n if self.interreflection is None else n * InterreflectionInfo.WIDTHS[self.interreflection.layout]

    @property
    def bounds(self) -> np.ndarray:
        """(S, 2, 3) boxes of all segments, indexed by segment id."""
        return np.stack([s.bounds for s in self.segments])

    @classmethod
    def from_dict(cls, data: Any, path: str | Path, source: str | None = None) -> Manifest:
        """Validate a parsed manifest and resolve its paths against the folder of ``path``.

        Parameters
        ----------
        data : dict
            Parsed JSON of the manifest.
        path : str or Path
            The manifest file; its folder is the scene folder.
        source : str, optional
            Name used at the start of error messages (default: ``str(path)``).

        Raises
        ------
        SpecError
            As :func:`load_manifest`.
        """
        source = str(path) if source is None else source
        validate_manifest_dict(data, source)
        resolved = Path(path).resolve()
        root = resolved.parent
        files = _resolve_paths(data, root, source)

        geometry = data["geometry"]
        seg = data["segmentation"]
        segmentation = {
            "roots": {int(k): v for k, v in seg["roots"].items()},
            "nodes": [dict(n) for n in seg["nodes"]],
            "leaf_segment": np.asarray(seg["leaf_segment"], dtype=np.int64),
        }
        segments = [
            SegmentInfo.from_dict(s, {k: files.get(f"segments[{i}].{k}") for k in ("model", "glsl", "glsl_weights", "code")})
            for i, s in enumerate(data["segments"])
        ]
        return cls(
            path=resolved,
            root=root,
            name=data["name"],
            generator=data.get("generator"),
            sh_bands=data["sh_bands"],
            geometry=GeometryInfo.from_dict(geometry, files[f"geometry.{'glsl' if geometry['type'] == 'sdf' else 'file'}"], files.get("geometry.glsl")),
            segmentation=segmentation,
            segments=segments,
            lighting=LightingInfo.from_dict(data["lighting"], files.get("lighting.envmap")),
            material=MaterialInfo.from_dict(data["material"]),
            camera=CameraInfo.from_dict(data.get("camera", {})),
            memory=MemoryInfo.from_dict(data["memory"]) if "memory" in data else None,
            transfer_texture=TransferTextureInfo.from_manifest(data, files),
            raw=data,
            interreflection=InterreflectionInfo.from_dict(data["interreflection"]) if "interreflection" in data else None,
            deformation=DeformationInfo.from_dict(data["deformation"], files["deformation.file"]) if "deformation" in data else None,
        )

    def to_dict(self, root: str | Path | None = None) -> dict:
        """The manifest as JSON types (format :data:`FORMAT`; version :data:`FORMAT_VERSION` for mixed
        geometry, else 1, the lowest version that holds the content).

        Parameters
        ----------
        root : str or Path, optional
            The scene folder the paths are written relative to (default: :attr:`root`).
        """
        root = Path(self.root if root is None else root)
        seg = self.segmentation
        version = 3 if self.deformation is not None else 2 if self.geometry.type == "mixed" else 1
        out: dict[str, Any] = {"format": FORMAT, "version": version, "name": self.name}
        if self.generator is not None:
            out["generator"] = self.generator
        out |= {
            "sh_bands": self.sh_bands,
            "geometry": self.geometry.to_dict(root),
            "segmentation": {
                "roots": {str(k): v for k, v in seg["roots"].items()},
                "nodes": seg["nodes"],
                "leaf_segment": _listed(seg["leaf_segment"]),
            },
            "segments": [s.to_dict(root) for s in self.segments],
            "lighting": self.lighting.to_dict(root),
            "material": self.material.to_dict(),
            "camera": self.camera.to_dict(),
        }
        if self.memory is not None:
            out["memory"] = self.memory.to_dict()
        if self.transfer_texture is not None:
            out["transfer_texture"] = self.transfer_texture.to_dict(root)
        if self.interreflection is not None:
            out["interreflection"] = self.interreflection.to_dict()
        if self.deformation is not None:
            out["deformation"] = self.deformation.to_dict(root)
        return out


# --------------------------------------------------------------------------- loading


class _JSONValueError(Exception):
    """Raised from json hooks: a value that parses but that a manifest must not hold."""


def _reject_constant(name: str) -> None:
    raise _JSONValueError(f"non-finite number {name} is not allowed")


def _object_without_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    # json keeps the last of duplicated keys silently; in a hand-edited manifest that hides mistakes.
    obj: dict = {}
    for key, value in pairs:
        if key in obj:
            raise _JSONValueError(f"duplicate key {key!r}")
        obj[key] = value
    return obj


def _read_json(path: Path, source: str) -> Any:
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise SpecError(f"{source}: manifest not found") from None
    except UnicodeDecodeError as exc:
        raise SpecError(f"{source}: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise SpecError(f"{source}: cannot read manifest ({_one_line(exc.strerror or exc)})") from None
    except ValueError as exc:  # a NUL byte in the path
        raise SpecError(f"{source}: cannot read manifest ({_one_line(exc)})") from None
    try:
        return json.loads(
            text, parse_constant=_reject_constant, object_pairs_hook=_object_without_duplicates
        )
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno}, column {exc.colno}"
        raise SpecError(f"{source}: invalid JSON at {where}: {exc.msg}") from None
    except _JSONValueError as exc:
        raise SpecError(f"{source}: invalid manifest JSON: {exc}") from None
    except RecursionError:
        raise SpecError(f"{source}: invalid manifest JSON: nested too deeply") from None
    except ValueError as exc:  # an integer of thousands of digits
        raise SpecError(f"{source}: invalid manifest JSON: {_one_line(exc)}") from None


def load_manifest(path: str | Path) -> Manifest:
    """Read, validate and resolve a scene manifest.

    Parameters
    ----------
    path : str or Path
        The ``scene.json`` file, or the scene folder holding it.

    Returns
    -------
    Manifest
        With every referenced path resolved to an absolute path inside the scene folder.

    Raises
    ------
    SpecError
        If the file is missing or not JSON (line and column given), breaks the schema or a
        semantic rule, or references a path that is absolute, escapes the folder (also via a
        symlink) or does not exist.  The message is one line naming the file and the field.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ArgumentTypeError(f"scene path must be a str or a path, got {type(path).__name__}")
    path = Path(path)
    try:
        if path.is_dir():
            path = path / MANIFEST_NAME
    except (OSError, ValueError):
        pass  # reading it says what is wrong
    source = str(path)
    return Manifest.from_dict(_read_json(path, source), path, source)
