"""Writing a built scene: segment files (ONNX + generated GLSL), geometry, and ``scene.json``.

The build (:mod:`prt.train.build`) hands over what training produced; this module owns the
files of a scene folder:

    OUTDIR/segments/segNNN.onnx         one network per network segment
    OUTDIR/segments/segNNN.glsl         GLSL generated from it
    OUTDIR/segments/segNNN_weights.npy  its weight texture (texture layout only; a grid segment's
                                        tables and MLP, prt.export.grid_onnx.table_texture)
    OUTDIR/segments/segNNN_code.npz     deformable scenes: the first layer's shape-code rows
    OUTDIR/geometry.npz                 the normalised mesh (or scene_sdf.glsl for an SDF scene)
    OUTDIR/deformation.npz              deformable scenes: rest pose, frames, codes, PCA basis
    OUTDIR/scene.json                   the manifest the runtime loads
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..runtime.camera import DEFAULT_CAMERA
from ..runtime.files import atomic_save_npz, atomic_write_bytes, atomic_write_json
from ..runtime.materials import materials_to_dicts
from ..runtime.manifest import (
    GENERATOR,
    MANIFEST_NAME,
    CameraInfo,
    DeformationInfo,
    GeometryInfo,
    LightingInfo,
    Manifest,
    MaterialInfo,
    InterreflectionInfo,
    MemoryInfo,
    SegmentInfo,
    validate_manifest_field,
)
from .glsl_compact import FORMAT_LINE, freq_bias_texel, write_segment_glsl
from .grid_onnx import build_grid_model, save_grid_model
from .manifest import write_manifest
from .onnx_model import build_model, save_model

__all__ = ["TrainedSegment", "export_segment", "export_geometry", "export_scene"]

# Architecture fields the manifest records (the ONNX metadata also has ``bands``).
_ARCHITECTURE_FIELDS = ("hidden", "layers", "pos_freqs", "normal_freqs", "input_dim")
# A grid segment's (``encoding: "grid"``; the training record's ``kind``).
_GRID_FIELDS = ("levels", "features", "log2_table", "base_resolution", "max_resolution", "hidden", "layers", "normal_freqs", "position",
                "input_dim")  # fmt: skip
GRID_TABLE_DTYPE = "float16"  # the tables as stored (the study: fp16 tables cost nothing measurable)


@dataclass
class TrainedSegment:
    """One segment as training left it.

    Attributes
    ----------
    id : int
    bounds : array_like, shape (2, 3)
        Box the network's input encoding normalises to.
    samples : int
        Training samples of the segment.
    coeff_mae : float
        Validation MAE of the SH coefficients.
    shaded_mae : dict
        Lighting name -> validation error of shaded radiance.
    arrays : dict or None
        Initialiser name -> float32 array of the fitted network; None for an analytic segment.
    architecture : dict or None
        ``hidden``, ``layers``, ``pos_freqs``, ``normal_freqs``, ``bands``, ``input_dim``.
    flops_per_fragment, weight_bytes : int
        Cost of the network (0 when analytic).
    sizing : dict or None
        How right-sizing chose it (:mod:`prt.train.networks.rightsize`): rule, target, measured, reason, sizes tried.
    """

    id: int
    bounds: Any
    samples: int
    coeff_mae: float
    shaded_mae: dict = field(default_factory=dict)
    arrays: dict | None = None
    architecture: dict | None = None
    flops_per_fragment: int = 0
    weight_bytes: int = 0
    sizing: dict | None = None

    @property
    def is_network(self) -> bool:
        return self.arrays is not None


def export_segment(out: Path, segment: TrainedSegment, glsl_layout: str = "auto") -> SegmentInfo:
    """Write a network segment's ONNX model and GLSL into ``out/segments``; its manifest entry.

    ``glsl_layout`` is ``"auto"`` (the compact form, :mod:`prt.export.glsl_compact`), ``"const"`` or
    ``"texture"`` (a function per segment, :func:`prt.export.glsl.generate_glsl`).
    An analytic segment writes nothing.
    """
    s = segment.id
    info = SegmentInfo(
        id=s, kind="network" if segment.is_network else "analytic", model=None, glsl=None,
        bounds=segment.bounds, architecture=None, flops_per_fragment=0, weight_bytes=0,
        samples=segment.samples, validation={"coeff_mae": segment.coeff_mae, "shaded_mae": segment.shaded_mae}, sizing=segment.sizing,
    )  # fmt: skip
    if not segment.is_network:
        return info
    arch = segment.architecture
    if arch.get("kind") == "grid" or arch.get("encoding") == "grid":
        return _export_grid_segment(out, segment, info)
    info.model = out / f"segments/seg{s:03d}.onnx"
    info.glsl = out / f"segments/seg{s:03d}.glsl"
    save_model(build_model(segment.arrays, arch, name=f"segment{s}"), info.model)
    write_segment_glsl(info, glsl_layout)  # the runtime uploads the weights; it cannot read ONNX initialisers
    info.architecture = {k: arch[k] for k in _ARCHITECTURE_FIELDS}
    if arch.get("residual"):  # the graph adds the unshadowed transfer back (prt.train.networks.network): informative
        info.architecture["residual"] = "unshadowed"
    if "code_weight" in segment.arrays:  # shape-conditioned: the code rows, and where the first bias sits among the texels
        if info.glsl_weights is None or not _compact_line(info.glsl):
            raise ValueError(f"segment {s}: a shape-conditioned network needs the compact GLSL layout (glsl_layout 'auto')")
        info.code = out / f"segments/seg{s:03d}_code.npz"
        atomic_save_npz(info.code, layer0_bias=segment.arrays["layer0_bias"], code_weight=segment.arrays["code_weight"],
                        enc_code_freq=segment.arrays["enc_code_freq"], bias_texel=np.int64(freq_bias_texel(info.model)))  # fmt: skip
        info.architecture |= {"code_dim": int(arch["code_dim"]), "code_freqs": int(arch["code_freqs"])}
    info.flops_per_fragment = segment.flops_per_fragment
    info.weight_bytes = segment.weight_bytes
    return info


def _compact_line(path) -> str:
    """The compact format line of a segment's GLSL (its fourth line), or ''."""
    lines = Path(path).read_text().splitlines()
    return next((line for line in lines[:8] if line.startswith(FORMAT_LINE)), "")


def _export_grid_segment(out: Path, segment: TrainedSegment, info: SegmentInfo) -> SegmentInfo:
    """A grid-encoded segment (:mod:`prt.export.grid_onnx`): the ONNX file (opset 18, the tables in
    fp16), the compact GLSL function and its texels ``segNNN_weights.npy`` (box, output scaling,
    tables and MLP weights, :func:`~prt.export.glsl_compact.grid_texels`; the tables rounded to fp16
    as in the ONNX file, so both backends compute with the same numbers)."""
    s, arch = segment.id, segment.architecture
    arrays = dict(segment.arrays)
    arrays["grid_table"] = np.asarray(arrays["grid_table"], dtype=np.float32).astype(GRID_TABLE_DTYPE).astype(np.float32)
    info.model = out / f"segments/seg{s:03d}.onnx"
    info.glsl = out / f"segments/seg{s:03d}.glsl"
    info.glsl_weights = out / f"segments/seg{s:03d}_weights.npy"
    save_grid_model(build_grid_model(arrays, arch, name=f"segment{s}", table_dtype=GRID_TABLE_DTYPE), info.model)
    write_segment_glsl(info, "auto", grid_arrays=arrays)
    info.architecture = {"encoding": "grid", **{k: arch[k] for k in _GRID_FIELDS}}
    info.flops_per_fragment = segment.flops_per_fragment
    info.weight_bytes = segment.weight_bytes
    return info


def export_geometry(geometry, out: Path, albedo_uv: np.ndarray | None = None) -> GeometryInfo:
    """Write the scene's geometry into ``out``; its manifest entry.

    Parameters
    ----------
    geometry : prt.train.inputs.geometry.Geometry
        Uses ``mesh`` (vertices, faces), ``object_ids``, ``object_names``, ``two_sided``,
        ``to_source`` and ``sdf`` (an SDF scene: ``name`` and ``glsl(function_name)``).
    out : Path
        The scene folder.
    albedo_uv : (F, 3, 2) float32, optional
        The mesh's own UV of every corner (albedo textures), stored as ``albedo_uv``.
    """
    to_source = np.asarray(geometry.to_source, dtype=np.float64)
    if geometry.sdf is not None:
        path = out / "scene_sdf.glsl"
        atomic_write_bytes(path, geometry.sdf.glsl("scene_sdf").encode())
        return GeometryInfo(type="sdf", path=path, to_source=to_source, name=geometry.sdf.name)
    mesh = geometry.mesh
    path = out / "geometry.npz"
    mixed = getattr(geometry, "kind", "mesh") == "mixed"
    # A mixed scene rasterises its mesh objects only: its SDF objects' proxy faces stay out.
    keep = ~np.asarray(geometry.mixed.proxy_faces) if mixed else np.ones(len(mesh.faces), dtype=bool)
    atomic_save_npz(
        path,
        vertices=np.asarray(mesh.vertices, dtype=np.float32),
        faces=np.asarray(mesh.faces, dtype=np.uint32)[keep],
        object_ids=np.asarray(geometry.object_ids, dtype=np.int32)[keep],
        two_sided=np.asarray(geometry.two_sided, dtype=bool)[keep],
        **({} if albedo_uv is None else {"albedo_uv": np.asarray(albedo_uv, dtype=np.float32)[keep]}),
    )
    if mixed:
        glsl = out / "scene_sdf.glsl"
        atomic_write_bytes(glsl, geometry.mixed.glsl("scene_sdf").encode())
        atomic_write_json(out / "mixed.json", geometry.mixed.record(out))
        return GeometryInfo(type="mixed", path=path, to_source=to_source, triangles=int(np.count_nonzero(keep)),
                            objects=list(geometry.object_names), glsl=glsl, kinds=list(geometry.mixed.kinds))  # fmt: skip
    return GeometryInfo(
        type="mesh", path=path, to_source=to_source, triangles=int(len(mesh.faces)), objects=list(geometry.object_names)
    )


def _export_texture(out: Path, index: int, material):
    """``material`` with its albedo texture written into ``out/textures`` (path relative to ``out``)."""
    import dataclasses
    import re

    texture = material.albedo_texture
    if texture is None:
        return material
    folder = out / "textures"
    folder.mkdir(exist_ok=True)
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", material.object)[:40] or "object"
    if isinstance(texture, np.ndarray):
        import imageio.v3 as iio

        name = f"{index:03d}_{stem}.png"
        atomic_write_bytes(folder / name, iio.imwrite("<bytes>", texture, extension=".png"))
    else:
        name = f"{index:03d}_{re.sub(r'[^A-Za-z0-9_.-]+', '_', Path(texture).name)}"
        atomic_write_bytes(folder / name, Path(texture).read_bytes())
    return dataclasses.replace(material, albedo_texture=Path("textures") / name)


def _lighting(out: Path, lighting_sh, envmap) -> LightingInfo:
    """The manifest's lighting: the SH, and the env map copied into the folder (the background) when given."""
    if envmap is None:
        return LightingInfo(sh=lighting_sh)
    source = Path(envmap)
    target = out / f"envmap{source.suffix.lower() or '.hdr'}"
    atomic_write_bytes(target, source.read_bytes())
    return LightingInfo(envmap=target, sh=lighting_sh, background=True)


def export_scene(
    out: str | Path,
    *,
    name: str,
    geometry,
    segmentation: dict,
    segments: list[TrainedSegment],
    sh_bands: int,
    lighting_sh: np.ndarray,
    material: dict,
    camera: dict,
    glsl_layout: str = "auto",
    materials: list | None = None,
    albedo_uv: np.ndarray | None = None,
    interreflection: dict | None = None,
    deformation: dict | None = None,
    envmap: str | Path | None = None,
) -> Manifest:
    """Write a whole scene folder: segment files, geometry, then ``scene.json``.

    Parameters
    ----------
    out : str or Path
        The scene folder (must exist).
    name : str
        Scene name.
    geometry : prt.train.inputs.geometry.Geometry
        See :func:`export_geometry`.
    segmentation : dict
        ``roots`` (object id -> node), ``nodes`` and ``leaf_segment`` of the k-d tree.
    segments : list of TrainedSegment
        Indexed by segment id.
    sh_bands : int
    lighting_sh : ndarray, shape (sh_bands**2, 3)
        The scene's default lighting.
    material, camera : dict
        Manifest ``material`` and ``camera`` objects (fields the camera leaves out come from
        :data:`~prt.runtime.camera.DEFAULT_CAMERA`).
    glsl_layout : str
        ``"auto"``, ``"const"`` or ``"texture"``.
    materials : list of prt.runtime.materials.ObjectMaterial, optional
        Per-object materials, written as the manifest's optional ``materials`` list; their
        albedo textures are written to ``textures/``.
    albedo_uv : (F, 3, 2) float32, optional
        Corner UVs for the albedo textures (see :func:`export_geometry`).
    interreflection : dict, optional
        ``bounces``, ``bounce_rays``, ``layout`` ("direct+rgb") and ``albedos`` (object -> RGB):
        the manifest's ``interreflection`` (the networks then output 4 ``sh_bands**2`` values).
    envmap : str or Path, optional
        The equirectangular map ``lighting_sh`` was projected from (a bundled map's file, or a
        user's): copied into the folder as ``envmap<suffix>`` and recorded as the manifest's
        ``lighting.envmap`` with ``background: true``, so the scene shows its environment behind
        the geometry (without it the light is SH only and the background black).
    deformation : dict, optional
        A deformable object (:mod:`prt.train.deform.deform_build`): ``arrays`` (``rest``, ``frames``, ``theta``,
        ``mean``, ``basis``, written to ``deformation.npz``), ``source``, ``code`` and ``frames`` (the
        manifest's ``deformation`` record).

    Returns
    -------
    Manifest
        The manifest written (paths inside ``out``).

    Raises
    ------
    SpecError
        If the manifest would be invalid (nothing is written to ``scene.json`` then).
    """
    out = Path(out)
    path = out / MANIFEST_NAME
    infos = [export_segment(out, segment, glsl_layout) for segment in segments]
    geometry_info = export_geometry(geometry, out, albedo_uv)
    deformation_info = None
    if deformation is not None:
        deformation_info = DeformationInfo(path=out / "deformation.npz", source=deformation["source"], code=deformation["code"],
                                           frames=deformation["frames"])  # fmt: skip
        atomic_save_npz(deformation_info.path, **{k: np.asarray(v, np.float32) for k, v in deformation["arrays"].items()})
    for key, value in (("material", material), ("camera", camera)):
        validate_manifest_field(key, value, str(path))
    manifest = Manifest(
        path=path,
        root=out,
        name=name,
        generator=GENERATOR,
        sh_bands=sh_bands,
        geometry=geometry_info,
        segmentation=segmentation,
        segments=infos,
        lighting=_lighting(out, lighting_sh, envmap),
        material=MaterialInfo(**material),
        camera=CameraInfo(**{**DEFAULT_CAMERA, **camera}),
        memory=MemoryInfo(
            weight_bytes=sum(s.weight_bytes for s in infos if s.is_network),
            vertex_storage_bytes=int(len(geometry.mesh.vertices) * sh_bands**2 * 4 * (4 if interreflection else 1)),
        ),
        interreflection=None if interreflection is None else InterreflectionInfo.from_dict(interreflection),
        deformation=deformation_info,
    )
    if materials:
        data = manifest.to_dict(root=out)
        data["materials"] = materials_to_dicts([_export_texture(out, k, m) for k, m in enumerate(materials)])
        write_manifest(path, data)
        manifest.raw = data
    else:
        write_manifest(path, manifest)
    return manifest
