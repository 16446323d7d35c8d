"""What a scene's web page reads, computed from the built scene (:mod:`prt.export.web` writes it).

Everything here is the desktop runtime's own data, laid out for WebGL2:

- **Programs**: the runtime's shader files assembled by :func:`prt.shaders.assemble` in the GLSL ES
  3.00 dialect (:data:`prt.shaders.GLSL_ES_VERSION`), with the scene's generated network GLSL
  and dispatch (the ``glsl`` backend's :class:`~prt.runtime.backends.glsl._CompactNetworks`), so
  the page runs the same G-buffer, transfer, shading, background and tone-mapping code as
  ``Renderer(backend="glsl")``; nothing is ported by hand.  The three.js material's stages
  (``three_programs``, ``shaders/three_prt.*``: the same files and fills in one forward fragment
  stage, without ``#version``, which three.js's ShaderMaterial prepends) for ``prt-three.js``.
- **Binary arrays** (little-endian): the G-buffer's vertex records (``runtime/gbuffer.py``: closed
  faces first, then the two-sided ones), the scene's weight texture (``(H, 1024, 4)`` float32),
  env maps as RGBE texels, per-object material tables and albedo textures, a deformable scene's
  posed vertex records and first-layer biases per recorded frame.
- **Lighting data**: each env map's SH projection (``load_envmap_sh``, as the renderer computes it),
  the SH rotation about +Y as a trigonometric polynomial (``D(theta) = C_0 + sum_m C_m cos(m theta)
  + S_m sin(m theta)``, m <= 3, fitted exactly from :func:`prt.runtime.sh.rotation_matrices`), the
  Gaunt tensor's non-zero entries (the light matrices of glossy shading) and the Phong lobes'
  coefficient scales for the exponents the page offers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..runtime import sh
from ..runtime.backends.glsl import _CompactNetworks  # the glsl backend's own stacking and dispatch
from ..runtime.camera import walk_info
from ..runtime.checks import read_text
from ..runtime.deformation import code_bias, load_code_arrays
from ..runtime.envmap import load_envmap_sh, read_envmap
from ..runtime.envmaps import BUNDLED_ENVMAPS, DEFAULT_ENVMAP, bundled_envmap_path
from ..runtime.errors import InputError
from ..runtime.exposure import exposure_defines, exposure_info
from ..runtime.gbuffer import _mesh_vertices, load_mesh, segment_tables
from ..runtime.materials import MaterialTable, load_albedo_textures, object_materials
from ..runtime.shading import GLSL_DEFINES, GLSL_FILES, MATERIAL_KINDS, Material
from ..shaders import GLSL_ES_VERSION, Source, assemble

__all__ = ["WebAssets", "scene_assets", "rotation_fourier", "gaunt_entries", "rgbe_bytes", "EXPONENTS", "GLOSSY_SPECULAR"]

EXPONENTS = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
"""Phong exponents the page's glossy control offers (their lobes computed here)."""
GLOSSY_SPECULAR = (0.3, 0.3, 0.3)
"""The page's glossy material: the scene's albedo with this specular (as ``prt-runtime --material glossy``)."""
ROTATION_HARMONICS = 3  # an SH rotation about one axis of 4 bands is a trigonometric polynomial of degree 3

_FLOAT_RECORD = 9  # floats per corner: position, smooth normal, face normal (gbuffer_mesh.vert)


@dataclass
class WebAssets:
    """A scene's page data: ``arrays`` (name -> bytes, written as files), ``programs`` (file name ->
    GLSL ES source) and ``info`` (the JSON the page reads, without the file table)."""

    info: dict
    arrays: dict[str, bytes] = field(default_factory=dict)
    programs: dict[str, str] = field(default_factory=dict)
    three_programs: dict[str, str] = field(default_factory=dict)
    """The three.js material's stages (``prt-three.js``), by file name: GLSL ES 3.00 bodies
    without ``#version`` (three.js prepends its own prefix)."""


# --------------------------------------------------------------------------- lighting data


def rotation_fourier(bands: int = 4) -> np.ndarray:
    """SH rotation about +Y as a trigonometric polynomial: ``(2 m + 1, n, n)`` float64 with ``n =
    bands**2``: ``[C_0, C_1, S_1, ..., C_m, S_m]`` so that ``D(theta) = C_0 + sum_k C_k cos(k theta)
    + S_k sin(k theta)`` is ``sh.rotation_matrices(R_y(theta))`` (``R_y`` as the viewer's light
    rotation: ``[[c, 0, s], [0, 1, 0], [-s, 0, c]]``).  Exact: the entries of band ``l`` are
    polynomials of degree ``l`` in ``cos theta``, ``sin theta``, and the fit samples ``2 m + 2`` angles."""
    m = bands - 1
    count = 2 * m + 2
    angles = 2.0 * np.pi * np.arange(count) / count
    d = sh.rotation_matrices(np.stack([_rotation_y(a) for a in angles]), bands)
    out = [d.mean(axis=0)]
    for k in range(1, m + 1):
        out.append(2.0 / count * np.einsum("a,aij->ij", np.cos(k * angles), d))
        out.append(2.0 / count * np.einsum("a,aij->ij", np.sin(k * angles), d))
    return np.stack(out)


def rotation_from_fourier(fourier: np.ndarray, theta: float) -> np.ndarray:
    """``D(theta)`` from :func:`rotation_fourier`'s terms (the page's JavaScript does the same)."""
    out = fourier[0].copy()
    for k in range(1, (len(fourier) - 1) // 2 + 1):
        out += fourier[2 * k - 1] * math.cos(k * theta) + fourier[2 * k] * math.sin(k * theta)
    return out


def _rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def gaunt_entries(bands: int = 4) -> list[list]:
    """The Gaunt tensor's non-zero entries ``[i, j, k, G_ijk]`` (the light matrix ``M_c[k, j] =
    sum_i L[i, c] G[i, j, k]`` of :func:`prt.runtime.shading.compute_light_matrix`)."""
    g = sh.gaunt(bands)
    return [[int(i), int(j), int(k), float(g[i, j, k])] for i, j, k in zip(*np.nonzero(np.abs(g) > 1e-14))]


def rgbe_bytes(image: np.ndarray) -> bytes:
    """Linear RGB (H, W, 3) as RGBE texels (H, W, 4) uint8, decoded ``byte * 2^(e - 136)`` (as
    OpenCV reads ``.hdr``: a map read from one comes back to the same bytes)."""
    rgb = np.maximum(np.asarray(image, dtype=np.float64), 0.0)
    top = rgb.max(axis=2)
    mantissa, exponent = np.frexp(top)
    scale = np.divide(mantissa * 256.0, top, out=np.zeros_like(top), where=top > 1e-32)
    out = np.zeros(rgb.shape[:2] + (4,), dtype=np.uint8)
    out[..., :3] = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    out[..., 3] = np.where(top > 1e-32, np.clip(exponent + 128, 0, 255), 0).astype(np.uint8)
    return out.tobytes()


def _envmaps(manifest) -> tuple[dict, dict[str, bytes], str]:
    """The env maps the page offers: the scene's own light (when it has one that is not a bundled
    map as it is) and the bundled maps; their SH, background images and which is first."""
    entries, arrays = {}, {}
    lighting = manifest.lighting
    scene_name = None
    if lighting.envmap is not None or lighting.sh is not None:
        same = _bundled_twin(lighting.envmap) if lighting.rotation is None else None
        if same is not None:
            scene_name = same
        else:
            scene_name = "scene"
            coeffs = load_envmap_sh(lighting.envmap, 4) if lighting.envmap is not None else np.asarray(lighting.sh, np.float64)
            rotation = np.eye(3) if lighting.rotation is None else np.asarray(lighting.rotation, np.float64)
            if lighting.rotation is not None:
                coeffs = sh.rotate(coeffs, rotation)
            entry = {"label": f"scene ({Path(lighting.envmap).name})" if lighting.envmap is not None else "scene (SH)",
                     "sh": coeffs.tolist(), "rotation": rotation.tolist(), "image": None}  # fmt: skip
            if lighting.envmap is not None:
                entry["image"] = _image_entry("scene", read_envmap(lighting.envmap), arrays)
            entries["scene"] = entry
    for name, file in BUNDLED_ENVMAPS.items():
        path = bundled_envmap_path(name)
        entries[name] = {"label": name, "sh": load_envmap_sh(path, 4).tolist(), "rotation": np.eye(3).tolist(),
                         "image": _image_entry(name, read_envmap(path), arrays)}  # fmt: skip
    return entries, arrays, scene_name or DEFAULT_ENVMAP


def _image_entry(name: str, image: np.ndarray, arrays: dict) -> dict:
    key = f"envmaps/{name}.rgbe"
    arrays[key] = rgbe_bytes(image)
    return {"file": key, "width": int(image.shape[1]), "height": int(image.shape[0])}


def _bundled_twin(path) -> str | None:
    """The bundled map with the same bytes as ``path`` (the demo's own map is one), else None."""
    if path is None:
        return None
    data = Path(path).read_bytes()
    for name in BUNDLED_ENVMAPS:
        if bundled_envmap_path(name).read_bytes() == data:
            return name
    return None


def _lobe(exponent: float) -> list[float]:
    """``u_lobe`` of a Phong exponent: each coefficient's band factor (``shading.shader_uniforms``)."""
    return sh.band_factors_to_coeff_scale(sh.phong_lobe(exponent, 4)).astype(np.float32).tolist()


# --------------------------------------------------------------------------- the networks


def _networks(manifest, blocks: int) -> tuple[dict, np.ndarray | None, list, dict]:
    """The transfer pass's fills and defines, the stacked weight texture (or None), the per-frame
    bias texels of shape-conditioned networks, and the uniforms (``u_segment_net`` / ``_base``)."""
    compact = _CompactNetworks(manifest.path, blocks)
    cases = []
    for seg in manifest.segments:
        if seg.kind == "analytic":
            compact.add_analytic(seg.id)
            cases.append(f"            case {seg.id}: prt_analytic_transfer(ns.xyz, t); break;")
            continue
        if seg.glsl is None:
            raise InputError(f"{manifest.path}: segments[{seg.id}] has no generated GLSL (the page runs the scene's GLSL networks)")
        if not compact.add(seg, read_text(seg.glsl, "GLSL")):
            raise InputError(f"{seg.glsl}: not compact GLSL (an older per-segment layout); the page reads compact files only: "
                             "rewrite the scene's GLSL with prt.export.glsl_compact.rewrite_scene_glsl(scene.json)")  # fmt: skip
    codes = []
    for seg in manifest.segments:
        if getattr(seg, "code", None) is not None:
            with np.load(seg.code, allow_pickle=False) as f:
                texel = int(f["bias_texel"]) if "bias_texel" in f.files else -1
            if not 0 < texel < len(compact.texels[list(compact.base).index(seg.id)]):
                raise InputError(f"{seg.code}: bias_texel missing or outside the segment's texels")
            codes.append((load_code_arrays(seg.code), compact.base[seg.id] + texel))
    defines = {"PRT_TRANSFER_BLOCKS": blocks} if blocks != 4 else {}
    if compact:
        defines["PRT_SEGMENTS"] = compact.segments
        fills = {"networks": Source.join(compact.sources()), "dispatch": "\n".join(compact.dispatch(cases))}
        texture = compact.texture(1 << 30)  # the page checks the browser's limit
    else:  # analytic segments only
        fills = {"networks": "", "dispatch": "\n".join(["        switch (segment) {", *cases, "        }"])}
        texture = None
    uniforms = {k: v.tolist() for k, v in compact.uniforms().items()}
    uniforms["u_analytic_scale"] = sh.unshadowed_coeff_scale(4).astype(np.float32).tolist()
    return {"fills": fills, "defines": defines}, texture, codes, uniforms


# --------------------------------------------------------------------------- programs


def _programs(tables: dict, blocks: int, transfer: dict, per_object: bool, deformable: bool) -> dict[str, str]:
    """Every program's stages as GLSL ES 3.00, by file name."""
    es = {"version": GLSL_ES_VERSION}
    lookup = {"PRT_KD_NODES": len(tables["nodes"]), "PRT_KD_OBJECTS": len(tables["roots"]), "PRT_SEGMENTS": len(tables["segment_min"])}
    gbuffer = {}
    if per_object:
        gbuffer["PRT_GBUFFER_MATERIAL"] = 2
    if deformable:
        gbuffer |= {"PRT_GBUFFER_REST": 1, "PRT_GBUFFER_WORLD": 2 + int(per_object)}
    out = {
        "gbuffer.vert": assemble("gbuffer_mesh.vert", defines=gbuffer, **es),
        "gbuffer.frag": assemble("segment_lookup.glsl", "gbuffer_mesh.frag", defines={**lookup, **gbuffer}, **es),
        "fullscreen.vert": assemble("fullscreen.vert", **es),
        "background.vert": assemble("fullscreen.vert", defines={"PRT_FULLSCREEN_Z": 1.0}, **es),
        "background.frag": assemble("background.frag", **es),
        "display.frag": assemble("tonemap.glsl", "viewer_blit.frag", defines=GLSL_DEFINES, **es),
        "log_luminance.frag": assemble("log_luminance.frag", defines={**exposure_defines(), "PRT_COVERED_BY_ALPHA": 1}, **es),
    }
    for targets in (4, 8) if blocks > 4 else (4,):
        defines = {**transfer["defines"], **({"PRT_TRANSFER_TARGETS": targets} if blocks > 4 else {})}
        out[f"transfer{targets}.frag"] = assemble("sh_basis.glsl", "transfer_pass.frag", fills=transfer["fills"], defines=defines, **es)
    shade = {**GLSL_DEFINES, "PRT_TRANSFER_ARRAY": 1, **({"PRT_INTERREFLECTION": 1} if blocks > 4 else {})}
    out["shade.frag"] = assemble(*GLSL_FILES, "shade_pass.frag", defines=shade, **es)
    if per_object:
        out["shade_materials.frag"] = assemble(*GLSL_FILES, "shade_pass.frag", defines={**shade, "PRT_OBJECT_MATERIALS": 1}, **es)
    return out


def _three_programs(tables: dict, transfer: dict, per_object: bool) -> dict[str, str]:
    """The three.js material's stages (``shaders/three_prt.*``): the G-buffer's segment rule, the
    networks (the transfer pass's fills) and the shading in one forward fragment stage; without
    ``#version`` and precision lines, which three.js's ShaderMaterial prepends."""
    segments = len(tables["segment_min"])
    if transfer["defines"].get("PRT_SEGMENTS", segments) != segments:  # one #define serves both files
        raise InputError(f"the networks' dispatch has {transfer['defines']['PRT_SEGMENTS']} segments, the segment tables {segments}")
    defines = {"PRT_KD_NODES": len(tables["nodes"]), "PRT_KD_OBJECTS": len(tables["roots"]), **transfer["defines"], "PRT_SEGMENTS": segments}
    out = {}
    for suffix, extra in (("", {}), ("_materials", {"PRT_OBJECT_MATERIALS": 1})) if per_object else (("", {}),):
        out[f"three{suffix}.vert"] = assemble("three_prt.vert", defines=extra, version=None)
        out[f"three{suffix}.frag"] = assemble("sh_basis.glsl", "segment_lookup.glsl", "shading.glsl", "three_prt.frag",
                                              defines={**defines, **extra}, fills=transfer["fills"], version=None)  # fmt: skip
    return out


# --------------------------------------------------------------------------- the scene


def scene_assets(scene) -> WebAssets:
    """Everything the page of ``scene`` (a :class:`prt.runtime.renderer.Scene`) reads.

    Raises
    ------
    InputError
        A scene the page cannot draw (SDF or mixed geometry, GLSL that is not compact), one line.
    """
    manifest = scene.manifest
    if manifest.geometry.type != "mesh":
        kind = {"sdf": "an SDF scene", "mixed": "a mixed scene (meshes and SDFs)"}.get(manifest.geometry.type, f"a {manifest.geometry.type} scene")
        raise InputError(f"{manifest.path}: {kind}, whose G-buffer is sphere traced; the web page draws triangle meshes only")
    if manifest.sh_bands != 4:
        raise InputError(f"{manifest.path}: the shaders handle 4 SH bands, the scene has {manifest.sh_bands}")
    blocks = manifest.transfer_width // 4
    mesh = load_mesh(manifest.geometry.path)
    n_faces = len(mesh["faces"])
    order = np.argsort(mesh["two_sided"], kind="stable")  # closed faces first (culled draw), as runtime/gbuffer.py
    records = _mesh_vertices(mesh).reshape(n_faces, 3)[order].reshape(-1)
    corners = 3 * n_faces
    floats = np.concatenate([records["position"], records["normal"], records["face_normal"]], axis=1).astype("<f4")
    sections = {"records": floats.tobytes(), "info": np.ascontiguousarray(records["info"], dtype="<i4").tobytes()}

    # Materials: per object when the manifest has them (the G-buffer's material target, the table).
    per_object_list = object_materials(manifest.raw, manifest.geometry.objects, str(manifest.path), root=manifest.root)
    textures = load_albedo_textures(per_object_list)
    scene_material = Material(kind=manifest.material.type, **{k: getattr(manifest.material, k) for k in ("albedo", "specular", "exponent")
                                                                if getattr(manifest.material, k) is not None})  # fmt: skip
    table = MaterialTable(manifest.geometry.objects or [], scene_material, per_object_list, textures)
    per_object = bool((manifest.raw or {}).get("materials"))  # the G-buffer's rule (GBufferPass)
    uniform_material = table[0] if table.uniform else scene_material  # what the renderer shades with then
    if per_object:
        albedo_uv = mesh.get("albedo_uv")
        uv = np.zeros((n_faces, 3, 2), np.float32) if albedo_uv is None else albedo_uv[order]
        sections["albedo_uv"] = np.ascontiguousarray(uv, dtype="<f4").tobytes()

    deformation = scene.deformation
    if deformation is not None:
        sections["rest"] = np.ascontiguousarray(mesh["vertices"][mesh["faces"]][order], dtype="<f4").tobytes()

    tables = segment_tables(manifest, mesh["object_ids"])
    transfer, weights, codes, transfer_uniforms = _networks(manifest, blocks)
    arrays: dict[str, bytes] = {}
    geometry, offset = {"file": "geometry.bin", "corners": corners, "closed": 3 * int(np.count_nonzero(~mesh["two_sided"]))}, 0
    for name, data in sections.items():
        geometry[name] = {"offset": offset, "bytes": len(data)}
        offset += len(data)
    arrays["geometry.bin"] = b"".join(sections.values())
    info: dict = {
        "scene": {"name": manifest.name, "triangles": n_faces, "segments": len(manifest.segments),
                  "networks": sum(s.is_network for s in manifest.segments), "objects": list(manifest.geometry.objects or []),
                  "interreflection": manifest.interreflection is not None},  # fmt: skip
        "camera": {**{k: list(map(float, getattr(manifest.camera, k))) for k in ("eye", "target", "up")}, "fov": float(manifest.camera.fov),
                   "near": 0.05, "far": 50.0, **walk_info(manifest)},  # fmt: skip  (Camera.from_manifest's clip distances)
        "exposure": exposure_info(manifest),
        "geometry": geometry,
        "transfer": {"blocks": blocks},
        "uniforms": {
            "gbuffer": {"prt_kd_nodes": tables["nodes"].tolist(), "prt_kd_roots": tables["roots"].tolist(),
                        "prt_segment_min": tables["segment_min"].tolist(), "prt_segment_max": tables["segment_max"].tolist()},
            "transfer": transfer_uniforms,
        },  # fmt: skip
    }
    if weights is not None:
        arrays["weights.bin"] = np.ascontiguousarray(weights, dtype="<f4").tobytes()
        info["weights"] = {"file": "weights.bin", "width": int(weights.shape[1]), "height": int(weights.shape[0])}
    envmaps, envmap_arrays, default = _envmaps(manifest)
    arrays.update(envmap_arrays)
    info["lighting"] = {
        "envmaps": envmaps, "default": default, "background": bool(manifest.lighting.background),
        "rotation_fourier": rotation_fourier(4).tolist(), "gaunt": gaunt_entries(4),
    }  # fmt: skip
    exponents = sorted({*EXPONENTS, *(m.exponent for m in table.materials), scene_material.exponent})
    info["material"] = {
        "scene": _material_dict(uniform_material),
        "per_object": per_object and not table.uniform,
        "glossy": {"albedo": list(scene_material.albedo), "specular": list(GLOSSY_SPECULAR), "exponent": 16.0},
        "lobes": {_key(e): _lobe(e) for e in exponents},
        "exponents": [float(e) for e in EXPONENTS],
        "kinds": list(MATERIAL_KINDS),
    }  # fmt: skip
    if per_object:
        info["material"]["table"] = table.texture_data().tolist()  # (4, K, 4): shade_pass.frag's u_material_table
        layers = textures.layers if textures is not None else np.zeros((1, 1, 1, 4), np.float32)
        arrays["albedo.bin"] = np.ascontiguousarray(layers, dtype="<f4").tobytes()
        info["material"]["albedo_textures"] = {"file": "albedo.bin", "layers": int(layers.shape[0]), "height": int(layers.shape[1]),
                                               "width": int(layers.shape[2])}  # fmt: skip
    if deformation is not None:
        arrays["poses.bin"], info["deformation"] = _poses(deformation, mesh, order, codes)
    programs = _programs(tables, blocks, transfer, per_object, deformation is not None)
    three = _three_programs(tables, transfer, per_object) if deformation is None else {}  # prt-three.js draws rigid scenes
    return WebAssets(info=info, arrays=arrays, programs=programs, three_programs=three)


def _key(exponent: float) -> str:
    return repr(float(exponent))


def _material_dict(m: Material) -> dict:
    return {"kind": m.kind, "albedo": list(m.albedo), "specular": list(m.specular), "exponent": float(m.exponent)}


def _poses(deformation, mesh: dict, order: np.ndarray, codes: list) -> tuple[bytes, dict]:
    """Per recorded frame: the posed vertex records (position, normals: the G-buffer's rule) and
    each shape-conditioned network's first-layer bias texels (``code_bias``, as the glsl backend's
    ``set_code``).  Frame-major float32."""
    n_faces = len(mesh["faces"])
    chunks, bias_layout = [], []
    for frame in range(deformation.frame_count):
        vertices, theta = deformation.pose(frame=frame)
        records = _mesh_vertices({**mesh, "vertices": np.asarray(vertices, np.float32)}).reshape(n_faces, 3)[order].reshape(-1)
        chunks.append(np.concatenate([records["position"], records["normal"], records["face_normal"]], axis=1).astype("<f4").tobytes())
        for arrays, texel in codes:
            bias = code_bias(arrays, theta)
            n = -(-bias.size // 4)
            chunks.append(np.pad(bias, (0, 4 * n - bias.size)).astype("<f4").tobytes())
            if frame == 0:
                bias_layout.append({"texel": int(texel), "texels": int(n)})
    frame_bytes = 4 * _FLOAT_RECORD * 3 * n_faces + sum(16 * b["texels"] for b in bias_layout)
    info = {"file": "poses.bin", "frames": int(deformation.frame_count), "frame_bytes": frame_bytes, "biases": bias_layout}
    return b"".join(chunks), info
