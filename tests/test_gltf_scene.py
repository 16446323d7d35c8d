"""glTF scenes: deterministic object names, instancing, mirrored instances, and materials as files carry them.

Synthetic GLB files written here (``write_glb``) cover: a mesh instanced by three nodes (two of
the same name, one mirrored by a negative scale) under a transformed parent, ``baseColorFactor``
alone, an embedded ``baseColorTexture``, metallic-roughness (factors and texture),
``KHR_materials_pbrSpecularGlossiness``, a mesh with two primitives (and a line primitive)
used by two nodes of one name, and a primitive without a
material: the only object the "no material" warning may name.  Loading the same file in two
processes gives byte-identical ``geometry.npz`` and the same object names.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from prt.runtime.errors import GeometryError
from prt.runtime.shading import Material
from prt.train.deform.gltf_animation import pack_accessors, write_glb
from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.gltf_scene import _triangles, read_gltf_scene, unique_names
from prt.train.inputs.materials import mesh_materials, pbr_material, roughness_to_exponent, spec_gloss_material, textured_geometry

DEFAULT = {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}

# A unit box, outward (counter-clockwise seen from outside), 8 vertices, 12 triangles.
BOX_V = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float32)
BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.uint32)  # fmt: skip
QUAD_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float32)
QUAD_UV = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], dtype=np.float32)  # glTF: v = 0 at the image's top
QUAD_F = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
TEXTURE = np.array([[[200, 10, 10], [10, 200, 10]], [[10, 10, 200], [250, 250, 250]]], dtype=np.uint8)


def _png(image: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", image, extension=".png")


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    corners = vertices[faces]
    return float(np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6)


def write_house(path, *, bare: bool = True) -> None:
    """The synthetic scene of this module (see the module docstring)."""
    arrays = [BOX_V, BOX_F.reshape(-1, 1), QUAD_V, QUAD_F.reshape(-1, 1), QUAD_UV]
    views, accessors, binary = pack_accessors(arrays)
    png = _png(TEXTURE)
    mr_texture = np.zeros((2, 2, 3), np.uint8)
    mr_texture[:, :, 1], mr_texture[:, :, 2] = 128, 255  # G roughness ~0.5, B metalness 1
    mr_png = _png(mr_texture)
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    binary += png + b"\0" * ((-len(png)) % 4)
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(mr_png)})
    binary += mr_png + b"\0" * ((-len(mr_png)) % 4)
    box = {"attributes": {"POSITION": 0}, "indices": 1}
    quad = {"attributes": {"POSITION": 2, "TEXCOORD_0": 4}, "indices": 3}
    document = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 5, 6, 7, 8, 9, 10]}],
        "nodes": [
            {"name": "Storey", "translation": [0, 0, 10], "children": [1, 2, 3, 4]},
            {"name": "Chair", "mesh": 0, "translation": [2, 0, 0]},
            {"name": "Chair", "mesh": 0, "translation": [4, 0, 0]},
            {"name": "Chair", "mesh": 0, "translation": [6, 0, 0], "scale": [-1, 1, 1]},  # mirrored
            {"name": "Chair_1", "mesh": 4, "translation": [8, 0, 0]},  # a name a suffix must not take
            {"name": "Window", "mesh": 1, "translation": [0, 3, 0]},
            {"name": "Picture", "mesh": 2, "translation": [0, 6, 0]},
            {"mesh": 3, "translation": [0, 9, 0]},  # unnamed node: its mesh's name
            {"name": "Lamp", "mesh": 5, "translation": [0, 12, 0]},
            {"name": "Bare", "mesh": 6, "translation": [0, 15, 0]},
            {"name": "Window", "mesh": 1, "translation": [0, 18, 0]},  # a second window: Window_1/0, Window_1/1
        ],
        "meshes": [
            {"name": "chair_mesh", "primitives": [dict(box, material=0)]},
            {"name": "window_mesh", "primitives": [dict(box, material=1), dict(box, material=2), {"attributes": {"POSITION": 0}, "mode": 1}]},
            {"name": "picture_mesh", "primitives": [dict(quad, material=3)]},
            {"name": "Cabinet", "primitives": [dict(box, material=4)]},
            {"name": "side_chair", "primitives": [dict(box, material=0)]},
            {"name": "lamp_mesh", "primitives": [dict(box, material=5)]},
            {"name": "bare_mesh", "primitives": [dict(box)] if bare else [dict(box, material=0)]},
        ],
        "materials": [
            {"name": "wood", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.25, 0.125, 1.0]}},
            {"name": "gold", "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.6, 0.2, 1], "metallicFactor": 1.0, "roughnessFactor": 0.3}},
            {"name": "glass", "pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1]},  # the extension wins
             "extensions": {"KHR_materials_pbrSpecularGlossiness": {"diffuseFactor": [0.5, 0.5, 0.5, 1], "specularFactor": [0.2, 0.2, 0.2], "glossinessFactor": 0.6}}},
            {"name": "canvas", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "baseColorTexture": {"index": 0}, "metallicFactor": 0.0}},
            {"name": "steel", "pbrMetallicRoughness": {"baseColorFactor": [0.6, 0.6, 0.6, 1], "roughnessFactor": 0.8, "metallicRoughnessTexture": {"index": 1}}},
            {"name": "matte", "extensions": {"KHR_materials_pbrSpecularGlossiness": {"diffuseFactor": [0.3, 0.4, 0.5, 1], "specularFactor": [0.1, 0.1, 0.1], "glossinessFactor": 0.0}}},
        ],
        "textures": [{"source": 0}, {"source": 1}],
        "images": [{"bufferView": len(arrays), "mimeType": "image/png"}, {"bufferView": len(arrays) + 1, "mimeType": "image/png"}],
        "extensionsUsed": ["KHR_materials_pbrSpecularGlossiness"],
        "bufferViews": views,
        "accessors": accessors,
    }  # fmt: skip
    write_glb(path, document, binary)


NAMES = ["Chair", "Chair_2", "Chair_3", "Chair_1", "Window/0", "Window/1", "Picture", "Cabinet", "Lamp", "Bare", "Window_1/0", "Window_1/1"]


@pytest.fixture
def house(tmp_path):
    path = tmp_path / "house.glb"
    write_house(path)
    return path


# --------------------------------------------------------------------------- names and parts


def test_names_follow_the_rule(house):
    scene = read_gltf_scene(house)
    assert [p.name for p in scene.parts] == NAMES
    assert load_geometry(house).object_names == NAMES


def test_unique_names_never_take_a_given_name():
    assert unique_names(["a", "a", "a_1", "a", "b"]) == ["a", "a_2", "a_1", "a_3", "b"]
    assert unique_names(["x/0", "x/1"]) == ["x/0", "x/1"]


def test_instances_are_placed_and_mirrored_ones_keep_their_outside(house):
    parts = {p.name: p for p in read_gltf_scene(house).parts}
    for name, x in (("Chair", 2), ("Chair_2", 4)):
        assert np.allclose(parts[name].vertices, BOX_V + [x, 0, 10])  # the parent's translation composed
    mirrored = parts["Chair_3"]
    assert np.allclose(np.sort(mirrored.vertices[:, 0]), np.sort(6 - BOX_V[:, 0]))
    # glTF reverses front faces under a negative determinant: the reader's winding keeps every box outward.
    for part in (p for name, p in parts.items() if name != "Picture"):  # the boxes
        assert _signed_volume(part.vertices, part.faces) == pytest.approx(1.0)
    geometry = load_geometry(house)
    picture = geometry.object_ids == geometry.object_names.index("Picture")
    assert geometry.two_sided[picture].all() and not geometry.two_sided[~picture].any()


def test_strip_and_fan_follow_the_specification():
    assert _triangles(np.arange(5), 5).tolist() == [[0, 1, 2], [1, 3, 2], [2, 3, 4]]
    assert _triangles(np.arange(5), 6).tolist() == [[1, 2, 0], [2, 3, 0], [3, 4, 0]]
    assert _triangles(np.arange(6), 4).tolist() == [[0, 1, 2], [3, 4, 5]]


_HASH = """
import hashlib, io, json, sys, tempfile
from pathlib import Path
from prt.train.inputs.geometry import load_geometry
from prt.export.scene import export_geometry
g = load_geometry(sys.argv[1])
with tempfile.TemporaryDirectory() as out:
    export_geometry(g, Path(out))
    data = (Path(out) / "geometry.npz").read_bytes()
print(json.dumps({"npz": hashlib.sha256(data).hexdigest(), "names": g.object_names}))
"""


def test_two_processes_give_identical_geometry_npz(house):
    runs = [json.loads(subprocess.run([sys.executable, "-c", _HASH, str(house)], check=True, capture_output=True, text=True).stdout)
            for _ in range(2)]  # fmt: skip
    assert runs[0] == runs[1]
    assert runs[0]["names"] == NAMES


def test_malformed_primitive_is_one_line(tmp_path):
    views, accessors, binary = pack_accessors([QUAD_V, np.array([[0], [1], [7]], dtype=np.uint32)])
    document = {"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}], "bufferViews": views, "accessors": accessors}  # fmt: skip
    write_glb(tmp_path / "bad.glb", document, binary)
    with pytest.raises(GeometryError, match=r"bad\.glb: cannot read GLB file.*outside its 4 vertices") as info:
        load_geometry(tmp_path / "bad.glb")
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------- materials


def test_only_objects_without_a_material_are_warned_about(house, tmp_path):
    geometry = load_geometry(house)
    lines: list[str] = []
    found = {m.object: m for m in mesh_materials(str(house), geometry.object_names, DEFAULT, lines.append)}
    assert set(found) == set(NAMES) - {"Bare"}
    warned = [line for line in lines if "no material" in line]
    assert len(warned) == 1 and "no material for Bare;" in warned[0]
    # Every primitive with a material: no such line at all.
    write_house(tmp_path / "full.glb", bare=False)
    lines.clear()
    full = mesh_materials(str(tmp_path / "full.glb"), load_geometry(tmp_path / "full.glb").object_names, DEFAULT, lines.append)
    assert len(full) == len(NAMES) and not any("no material" in line for line in lines)


def test_material_rules(house):
    geometry = load_geometry(house)
    found = {m.object: m for m in mesh_materials(str(house), geometry.object_names, DEFAULT, print)}
    # baseColorFactor only: glTF's defaults (metallic 1, roughness 1) are too rough for a lobe: diffuse base colour.
    for name in ("Chair", "Chair_2", "Chair_3", "Chair_1"):
        assert found[name].material == Material("diffuse", albedo=(0.5, 0.25, 0.125))
    gold = found["Window/0"].material
    assert gold.kind == "glossy" and np.allclose(gold.albedo, 0) and np.allclose(gold.specular, [0.8, 0.6, 0.2])
    assert gold.exponent == pytest.approx(2 / 0.09**2 - 2)
    glass = found["Window/1"].material  # spec-gloss: c_diff = 0.5 (1 - 0.2), F0 0.2, roughness 0.4
    assert glass.kind == "glossy" and np.allclose(glass.albedo, 0.4) and np.allclose(glass.specular, 0.2)
    assert glass.exponent == pytest.approx(2 / 0.16**2 - 2)
    matte = found["Lamp"].material  # glossiness 0: the specular joins the diffuse albedo
    assert matte.kind == "diffuse" and np.allclose(matte.albedo, np.array([0.3, 0.4, 0.5]) * 0.9 + 0.1)
    steel = found["Cabinet"].material  # texture means: roughness 0.8 * 128/255, metalness 1
    assert steel.kind == "glossy" and np.allclose(steel.albedo, 0) and np.allclose(steel.specular, 0.6)
    assert steel.exponent == pytest.approx(roughness_to_exponent(0.8 * 128 / 255))
    canvas = found["Picture"]
    assert canvas.material == Material("diffuse", albedo=(1, 1, 1))
    assert np.array_equal(canvas.albedo_texture, TEXTURE)
    assert found["Chair"].source == "house.glb: wood"


def test_base_colour_texture_gets_the_file_uvs(house):
    geometry = load_geometry(house)
    materials = mesh_materials(str(house), geometry.object_names, DEFAULT, print)
    materials, albedo_uv = textured_geometry(str(house), geometry, materials, print)
    picture = geometry.object_names.index("Picture")
    faces = geometry.mesh.faces[geometry.object_ids == picture]
    corners = geometry.mesh.vertices[faces] @ geometry.to_source[:3, :3].T + geometry.to_source[:3, 3]
    uv = albedo_uv[geometry.object_ids == picture]
    # OBJ convention: v = 1 - v_glTF; the quad's corner (x, y) has glTF UV (x, 1 - y), so OBJ UV (x, y).
    assert np.allclose(uv, corners[:, :, :2] - [0, 6], atol=1e-6)


def test_missing_texture_file_warns_and_uses_the_factor(tmp_path):
    views, accessors, binary = pack_accessors([QUAD_V, QUAD_F.reshape(-1, 1), QUAD_UV])
    document = {"asset": {"version": "2.0"}, "scenes": [{"nodes": [0, 1]}],
                "nodes": [{"name": "a", "mesh": 0}, {"name": "b", "mesh": 0, "translation": [0, 0, 1]}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]}],
                "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.3, 0.4, 1], "baseColorTexture": {"index": 0}}}],
                "textures": [{"source": 0}], "images": [{"uri": "gone.png"}], "bufferViews": views, "accessors": accessors}  # fmt: skip
    write_glb(tmp_path / "lost.glb", document, binary)
    lines: list[str] = []
    found = mesh_materials(str(tmp_path / "lost.glb"), ["a", "b"], DEFAULT, lines.append)
    assert [m.albedo_texture for m in found] == [None, None] and np.allclose(found[0].material.albedo, [0.2, 0.3, 0.4])
    assert sum("image file is missing" in line for line in lines) == 2 and not any("no material" in line for line in lines)


def test_pbr_and_spec_gloss_rules():
    # A rough metal keeps its colour; a glossy one becomes a tinted lobe.
    assert pbr_material([0.9, 0.5, 0.1], 1.0, 1.0) == Material("diffuse", albedo=(0.9, 0.5, 0.1))
    metal = pbr_material([0.9, 0.5, 0.1], 0.5, 1.0, texture_mean=[0.5, 0.5, 0.5])
    assert np.allclose(metal.specular, [0.45, 0.25, 0.05]) and np.allclose(metal.albedo, 0)
    half = pbr_material([1.0, 1.0, 1.0], 0.5, 0.5)
    assert np.allclose(half.albedo, 0.5) and np.allclose(half.specular, 0.52)
    assert roughness_to_exponent(0.0) == 1024.0 and roughness_to_exponent(0.95) < 1 <= roughness_to_exponent(0.9)
    rough = spec_gloss_material([0.8, 0.8, 0.8], [0.04, 0.04, 0.04], 0.0, texture_mean=[0.5, 0.5, 0.5])
    assert rough.kind == "diffuse" and np.allclose(rough.albedo, 0.8 * 0.96 + 0.08)
    assert spec_gloss_material([1, 1, 1], [1, 1, 1], 1.0) == Material("glossy", albedo=(0, 0, 0), specular=(1, 1, 1), exponent=1024.0)



def test_corrupt_embedded_image_is_one_line(tmp_path):
    views, accessors, binary = pack_accessors([QUAD_V, QUAD_F.reshape(-1, 1), QUAD_UV])
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": 16})
    document = {"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "nodes": [{"name": "a", "mesh": 0}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]}],
                "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}], "textures": [{"source": 0}],
                "images": [{"bufferView": 3, "mimeType": "image/png"}], "bufferViews": views, "accessors": accessors}  # fmt: skip
    write_glb(tmp_path / "bad.glb", document, binary + b"\x89PNG not really!")
    with pytest.raises(GeometryError, match=r"bad\.glb: image 0: cannot decode the image") as info:
        mesh_materials(str(tmp_path / "bad.glb"), ["bad"], DEFAULT, print)
    assert "\n" not in str(info.value)


def test_texture_transform_moves_the_albedo_uvs(tmp_path):
    """KHR_texture_transform (offset, rotation, scale; its own texCoord) on the colour texture: the
    UVs the build carries are the transformed ones, by the extension's formula written out per
    coordinate (glTF's v, then OBJ's flip)."""
    from prt.train.inputs.albedo_uv import file_corner_uvs

    uv0 = np.array([[0.1, 0.9], [0.7, 0.8], [0.6, 0.2], [0.2, 0.3]], np.float32)
    views, accessors, binary = pack_accessors([QUAD_V, QUAD_F.reshape(-1, 1), QUAD_UV, uv0])
    png = _png(TEXTURE)
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    binary += png + b"\0" * ((-len(png)) % 4)
    transform = {"offset": [0.25, -0.5], "rotation": 0.3, "scale": [2.0, 3.0], "texCoord": 1}
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"name": "tile", "mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2, "TEXCOORD_1": 3}, "indices": 1, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0, "texCoord": 0, "extensions": {"KHR_texture_transform": transform}}}}],
        "textures": [{"source": 0}], "images": [{"bufferView": 4, "mimeType": "image/png"}],
        "extensionsUsed": ["KHR_texture_transform"], "bufferViews": views, "accessors": accessors,
    }  # fmt: skip
    path = tmp_path / "tile.glb"
    write_glb(path, document, binary)
    positions, uvs = file_corner_uvs(str(path))
    c, s = np.cos(0.3), np.sin(0.3)
    u, v = uv0[:, 0].astype(np.float64), uv0[:, 1].astype(np.float64)  # the extension's texCoord: set 1
    moved_u = c * 2.0 * u + s * 3.0 * v + 0.25
    moved_v = -s * 2.0 * u + c * 3.0 * v - 0.5
    want = np.stack([moved_u, 1.0 - moved_v], axis=1)[QUAD_F.astype(np.int64)]
    assert np.allclose(uvs, want, atol=1e-6)
