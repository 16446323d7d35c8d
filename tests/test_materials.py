"""Per-object materials: MTL and glTF reading, the manifest field, and shading with them.

The renderer's per-object shading (both backends) is checked against a numpy reference built
from the transfer image and each pixel's object id; the shared Cornell box keeps its red and
green walls.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.runtime.backends import BACKENDS
from prt.runtime.errors import GeometryError, InputError, SpecError
from prt.runtime.materials import MaterialTable, ObjectMaterial, object_materials, parse_object_albedo, shade_objects
from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import Lighting, Material, shade
from prt.train.inputs.materials import mesh_materials, pbr_material, read_mtl, roughness_to_exponent

DATA = Path(__file__).parent / "data"
CORNELL = DATA / "CornellBox-Original.obj"
TET = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
DEFAULT = {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}
SIZE = 64


# --------------------------------------------------------------------------- reading


def test_mtl_fields_and_single_value_colours(tmp_path):
    (tmp_path / "a.mtl").write_text(
        "# comment\nnewmtl red\n  Kd 0.5 0.1 0.0 # trailing\n  Ks 0 0 0\n  Ns 20\n"
        "newmtl shiny\nKd 0.2\nKs 0.3 0.3 0.3\nNs 64\nmap_Kd -s 1 1 1 tex/wood.png\n"
    )
    mtl = read_mtl(str(tmp_path / "a.mtl"))
    assert mtl["red"] == {"Kd": (0.5, 0.1, 0.0), "Ks": (0.0, 0.0, 0.0), "Ns": 20.0}
    assert mtl["shiny"]["Kd"] == (0.2, 0.2, 0.2)
    assert mtl["shiny"]["map_Kd"] == str(tmp_path / "tex" / "wood.png")


def test_a_material_library_named_with_spaces(tmp_path):
    from prt.train.inputs.materials import obj_material_names

    (tmp_path / "my model.mtl").write_text("newmtl red\nKd 1 0 0\n")
    (tmp_path / "m.obj").write_text("mtllib my model.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n")
    (tmp_path / "two.obj").write_text("mtllib a.mtl b.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert obj_material_names(str(tmp_path / "m.obj"))[1] == [str(tmp_path / "my model.mtl")]
    assert obj_material_names(str(tmp_path / "two.obj"))[1] == [str(tmp_path / "a.mtl"), str(tmp_path / "b.mtl")]


def test_texture_names_with_spaces_and_options():
    """A map statement's options are skipped by the format's list (-o, -s, -t take up to three
    numbers) and the file name is the rest, spaces and all (Windows exports)."""
    from prt.train.inputs.materials import _map_file

    assert _map_file(" -s 2 2 1 leaf texture.png") == "leaf texture.png"
    assert _map_file(" -o 0.5 my file.png") == "my file.png"  # -o with u alone
    assert _map_file(" -clamp on -mm 0 1 -bm 0.3 mask.png") == "mask.png"
    assert _map_file(" -s 2 1.png") == "1.png"  # a name, not a number
    assert _map_file(" plain.png") == "plain.png"


@pytest.mark.parametrize("line, message", [
    ("Kd red 0 0", r"a\.mtl, line 2: Kd values must be numbers"),
    ("Kd 0.5 0.5", r"a\.mtl, line 2: Kd needs 3 numbers"),
    ("Ks -1 0 0", r"a\.mtl, line 2: Ks needs finite numbers >= 0"),
    ("Ns nan", r"a\.mtl, line 2: Ns needs finite numbers >= 0"),
])  # fmt: skip
def test_bad_mtl_lines_are_one_line_errors(tmp_path, line, message):
    (tmp_path / "a.mtl").write_text(f"newmtl m\n{line}\n")
    with pytest.raises(GeometryError, match=message) as info:
        read_mtl(str(tmp_path / "a.mtl"))
    assert "\n" not in str(info.value)


def test_obj_objects_take_their_mtl_materials_and_missing_ones_warn_once(tmp_path):
    (tmp_path / "m.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl gloss\nKd 0 0 1\nKs 0.5 0.5 0.5\nNs 32\n")
    (tmp_path / "s.obj").write_text(
        "mtllib m.mtl\n" + TET + "o a\nusemtl red\nf 1 3 2\nf 1 2 4\nusemtl gloss\nf 1 4 3\n"
        "o b\nusemtl gloss\nf 2 3 4\no c\nusemtl unknown\nf 1 2 3\n"
    )
    lines = []
    found = mesh_materials(str(tmp_path / "s.obj"), ["a", "b", "c"], DEFAULT, lines.append)
    by_name = {m.object: m.material for m in found}
    assert by_name["a"] == Material("diffuse", albedo=(1, 0, 0), exponent=8.0)  # the most used of its two
    assert by_name["b"] == Material("glossy", albedo=(0, 0, 1), specular=(0.5, 0.5, 0.5), exponent=32)
    assert "c" not in by_name
    assert sum("no material for c" in line for line in lines) == 1
    assert any("'a' uses 2 materials" in line for line in lines)


def test_obj_without_materials_is_silent_and_missing_library_warns(tmp_path):
    (tmp_path / "plain.obj").write_text(TET + "f 1 3 2\n")
    lines = []
    assert mesh_materials(str(tmp_path / "plain.obj"), ["plain"], DEFAULT, lines.append) == []
    assert lines == []
    (tmp_path / "lost.obj").write_text("mtllib gone.mtl\nusemtl x\n" + TET + "f 1 3 2\n")
    assert mesh_materials(str(tmp_path / "lost.obj"), ["x"], DEFAULT, lines.append) == []
    assert any("gone.mtl not found" in line for line in lines) and any("no material for x" in line for line in lines)


def test_roughness_rule():
    assert roughness_to_exponent(1.0) == 0.0  # rough: diffuse
    alpha = 0.5**2
    assert roughness_to_exponent(0.5) == pytest.approx(2 / alpha**2 - 2)  # 30
    assert roughness_to_exponent(0.0) == 1024.0
    m = pbr_material([255, 128, 0, 255], 0.5, 0.0)
    assert m.kind == "glossy" and m.exponent == pytest.approx(30.0)
    assert np.allclose(m.albedo, [1.0, 128 / 255, 0.0]) and np.allclose(m.specular, 0.04)
    metal = pbr_material([0.8, 0.6, 0.2], 0.3, 1.0)
    assert np.allclose(metal.albedo, 0) and np.allclose(metal.specular, [0.8, 0.6, 0.2])
    assert pbr_material(None, None, None) == Material("diffuse", albedo=(1, 1, 1))


def test_gltf_base_colour_and_roughness(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    from trimesh.visual.material import PBRMaterial

    scene = trimesh.Scene()
    for name, offset, colour, rough in (("left", -2, [1.0, 0.0, 0.0, 1.0], 1.0), ("right", 2, [0.0, 1.0, 0.0, 1.0], 0.5)):
        box = trimesh.creation.box()
        box.apply_translation([offset, 0, 0])
        box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=colour, roughnessFactor=rough, metallicFactor=0.0))
        scene.add_geometry(box, node_name=name, geom_name=name)
    scene.export(tmp_path / "two.glb")
    from prt.train.inputs.geometry import load_geometry

    geometry = load_geometry(tmp_path / "two.glb")
    found = {m.object: m.material for m in mesh_materials(str(tmp_path / "two.glb"), geometry.object_names, DEFAULT, print)}
    assert set(found) == set(geometry.object_names) == {"left", "right"}
    assert found["left"].kind == "diffuse" and np.allclose(found["left"].albedo, [1, 0, 0], atol=1 / 255)
    assert found["right"].kind == "glossy" and found["right"].exponent == pytest.approx(30.0)
    assert np.allclose(found["right"].albedo, [0, 1, 0], atol=1 / 255)


def test_cornell_box_walls_are_red_and_green():
    from prt.train.inputs.geometry import load_geometry

    geometry = load_geometry(CORNELL)
    found = {m.object: m.material for m in mesh_materials(str(CORNELL), geometry.object_names, DEFAULT, print)}
    assert found["leftWall"].albedo == (0.63, 0.065, 0.05)
    assert found["rightWall"].albedo == (0.14, 0.45, 0.091)
    assert set(found) == set(geometry.object_names)


# --------------------------------------------------------------------------- runtime model


def test_manifest_entries_and_their_errors():
    data = {"materials": [{"object": "b", "type": "glossy", "albedo": [0.1, 0.2, 0.3], "specular": [0.5, 0.5, 0.5], "exponent": 4}]}
    (entry,) = object_materials(data, ["a", "b"], "scene.json")
    assert entry == ObjectMaterial("b", Material("glossy", albedo=(0.1, 0.2, 0.3), specular=(0.5, 0.5, 0.5), exponent=4))
    assert object_materials({}, ["a"], "scene.json") == []  # older manifests: no field
    with pytest.raises(SpecError, match=r"scene\.json: materials\[0\]\.object: 'z' is not an object"):
        object_materials({"materials": [{"object": "z", "type": "diffuse", "albedo": [1, 1, 1]}]}, ["a"], "scene.json")
    table = MaterialTable(["a", "b"], Material(), [entry])
    assert table[0] == Material() and table[1] == entry.material and not table.uniform
    with pytest.raises(InputError, match=r"object 'c' is not in the scene \(objects: a, b\)"):
        table.set("c", Material())
    assert parse_object_albedo("left wall=0.1,0.2,0.3") == ("left wall", (0.1, 0.2, 0.3))
    assert parse_object_albedo("a=0.5") == ("a", (0.5, 0.5, 0.5))
    for bad in ("a", "a=x", "=1", "a=1,2", "a=-1"):
        with pytest.raises(InputError, match="--object-albedo"):
            parse_object_albedo(bad)


def test_shade_objects_matches_shade_per_object():
    rng = np.random.default_rng(0)
    t = rng.normal(size=(40, 16)) * 0.2
    t[:, 0] += 1.0
    n = rng.normal(size=(40, 3))
    v = rng.normal(size=(40, 3))
    ids = rng.integers(-1, 3, size=40)
    light = Lighting.from_sh(rng.normal(size=(16, 3)) * 0.3 + np.eye(16, 3)[:, :1] * 2)
    mats = [Material("diffuse", albedo=(1, 0, 0)), Material("glossy", albedo=(0, 1, 0), specular=(0.3, 0.3, 0.3), exponent=8),
            Material("diffuse", albedo=(0, 0, 1))]  # fmt: skip
    table = MaterialTable(["a", "b", "c"], Material(), [ObjectMaterial(x, m) for x, m in zip("abc", mats)])
    got = shade_objects(t, ids, n, v, light, table)
    for k in range(-1, 3):
        rows = ids == k
        want = shade(t[rows], n[rows], v[rows], light, mats[k] if k >= 0 else Material())
        assert np.allclose(got[rows], want, atol=1e-5)



def test_shade_objects_with_a_texture_and_bounces_shades_every_object_by_its_own_rows():
    """RGB (interreflected) transfer, a textured object listed before untextured diffuse ones: each
    object's rows shaded as if alone (the textured branch once overwrote the rows' shared incident
    light, and the next object indexed the textured object's rows: an IndexError or, where the
    sizes allowed, another object's light)."""
    from prt.runtime.albedo_textures import AlbedoTextures, sample_bilinear
    from prt.runtime.shading import split_transfer

    rng = np.random.default_rng(1)
    t = rng.normal(size=(70, 64)) * 0.05
    t[:, 0] += 1.0
    ids = np.repeat([0, 1, 2, 3], [10, 25, 25, 10])  # the textured objects (0, 3) have fewer rows than the others
    uv = rng.random((70, 2))
    normals, views = rng.normal(size=(70, 3)), rng.normal(size=(70, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    light = Lighting.from_sh(rng.normal(size=(16, 3)) * 0.3 + np.eye(16, 3)[:, :1] * 2)
    image = rng.random((4, 4, 3)).astype(np.float32)
    gloss = Material("glossy", albedo=(0.9, 0.8, 0.7), specular=(0.3, 0.3, 0.3), exponent=8)
    mats = [Material("diffuse", albedo=(0.5, 0.5, 0.5)), Material("diffuse", albedo=(1, 0, 0)), Material("diffuse", albedo=(0, 0, 1)), gloss]
    per_object = [ObjectMaterial(x, m, albedo_texture=Path("t.png") if x in "ad" else None) for x, m in zip("abcd", mats)]
    table = MaterialTable(["a", "b", "c", "d"], Material(), per_object, textures=AlbedoTextures([image]))
    got = shade_objects(t, ids, normals, views, light, table, uv)
    direct, indirect = split_transfer(t, 16)
    received = direct @ light.sh + np.einsum("pcn,nc->pc", indirect, light.sh)
    albedo = np.asarray([m.albedo for m in mats])[ids]
    textured = np.isin(ids, [0, 3])
    albedo[textured] *= sample_bilinear(image, uv[textured])
    want = albedo * received
    lobe = Material("glossy", albedo=(0, 0, 0), specular=gloss.specular, exponent=gloss.exponent)  # the specular part alone
    want[ids == 3] += shade(direct[ids == 3], normals[ids == 3], views[ids == 3], light, lobe)
    assert np.allclose(got, np.maximum(want, 0), atol=1e-4)


# --------------------------------------------------------------------------- rendering


@pytest.fixture(scope="module")
def cornell_scene(tmp_path_factory):
    """The Cornell box (with its MTL) built fast: every segment analytic (a target nothing misses)."""
    out = tmp_path_factory.mktemp("cornell") / "scene"
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(CORNELL), "-o", str(out), "--samples", "3000",
         "--validation", "1000", "--rays", "32", "--segments", "4", "--target", "10", "--bounces", "0", "--no-progress"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out / "scene.json"


def _reference(r: Renderer) -> np.ndarray:
    """Per-pixel numpy shading of the renderer's own transfer with each pixel's object material."""
    transfer = r.render_transfer().reshape(-1, 16)
    g = r.gbuffer_image()
    ids = r.gbuffer.read_material()[0]
    covered = g.covered.reshape(-1)
    normals, positions = g.normal.reshape(-1, 3), g.position.reshape(-1, 3)
    out = np.zeros((len(covered), 3), np.float32)
    c = np.flatnonzero(covered)
    for k in np.unique(ids[c]):
        rows = c[ids[c] == k]
        out[rows] = shade(transfer[rows], normals[rows], r.camera.eye - positions[rows], r.lighting, r.materials[int(k)])
    return out.reshape(r.height, r.width, 3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_per_object_materials_render_against_numpy(gl_ctx, cornell_scene, backend):
    scene = Scene.load(cornell_scene)
    assert [m["object"] for m in json.loads(cornell_scene.read_text())["materials"]]
    with Renderer(scene, SIZE, SIZE, backend=backend, ctx=gl_ctx) as r:
        r.set_envmap("studio")
        r.set_material("glossy", object="floor", albedo=(0.2, 0.3, 0.9), specular=(0.4, 0.4, 0.4), exponent=6)
        image = r.render()
        want = _reference(r)
        assert np.abs(image - want).max() < 1e-4 * max(1.0, float(want.max()))
        ids = r.gbuffer.read_material()[0].reshape(SIZE, SIZE)
    objects = scene.manifest.geometry.objects
    left, right = image[ids == objects.index("leftWall")], image[ids == objects.index("rightWall")]
    assert (left[:, 0] > 2 * left[:, 1]).mean() > 0.95  # red
    assert (right[:, 1] > 1.5 * right[:, 0]).mean() > 0.95  # green


def test_set_material_without_object_overrides_all_and_relights_only(gl_ctx, cornell_scene):
    with Renderer(Scene.load(cornell_scene), SIZE, SIZE, ctx=gl_ctx) as r:
        light = np.zeros((16, 3))
        light[0] = np.sqrt(4 * np.pi)
        r.set_lighting_sh(light)
        r.render()
        runs = r.network_calls
        r.set_material("diffuse", albedo=(0.25, 0.5, 0.75))
        image = r.render()
        assert r.network_calls == runs  # a material change re-shades the cached transfer
        covered = r.gbuffer_image().covered
        assert np.allclose(image[covered] / image[covered][:, :1], [1, 2, 3], atol=1e-3)


def test_object_material_on_a_scene_without_materials(gl_ctx, cornell_scene, tmp_path):
    """A scene built without materials gets an object's material at run time (the G-buffer gains object ids)."""
    import shutil

    folder = tmp_path / "plain"
    shutil.copytree(cornell_scene.parent, folder)
    data = json.loads((folder / "scene.json").read_text())
    del data["materials"]
    (folder / "scene.json").write_text(json.dumps(data))
    with Renderer(Scene.load(folder), SIZE, SIZE, backend="glsl", ctx=gl_ctx) as r:
        assert r.gbuffer.material_texture is None
        r.set_envmap("studio")
        r.set_material("diffuse", object="leftWall", albedo=(1, 0, 0))
        image = r.render()
        assert r.gbuffer.material_texture is not None
        assert np.abs(image - _reference(r)).max() < 1e-4


# --------------------------------------------------------------------------- albedo textures


def test_bilinear_sampling_at_texel_centres_between_them_and_wrapping():
    from prt.runtime.albedo_textures import sample_bilinear

    image = np.arange(2 * 3 * 1, dtype=np.float32).reshape(2, 3, 1)  # rows from the top: [0 1 2], [3 4 5]
    # Texel (row, col) centre: u = (col + 0.5) / 3, v = 1 - (row + 0.5) / 2.
    centre = lambda row, col: ((col + 0.5) / 3, 1 - (row + 0.5) / 2)  # noqa: E731
    got = sample_bilinear(image, [centre(0, 0), centre(1, 2), centre(0, 0.5), centre(0.5, 1)])
    assert np.allclose(got[:, 0], [0, 5, 0.5, 2.5])
    # Wrapping: half-way between the last and the first column, and u shifted by whole periods.
    assert np.allclose(sample_bilinear(image, [centre(0, 2.5)])[:, 0], [1.0])
    assert np.allclose(sample_bilinear(image, [(0.3 + 2, 0.6 - 3)]), sample_bilinear(image, [(0.3, 0.6)]), atol=1e-5)


def test_texture_reading_decodes_srgb_and_rejects_corrupt_files(tmp_path):
    import imageio.v3 as iio

    from prt.runtime.albedo_textures import read_albedo_texture

    iio.imwrite(tmp_path / "t.png", np.array([[[0, 128, 255, 255]]], dtype=np.uint8))
    got = read_albedo_texture(tmp_path / "t.png")
    assert got.shape == (1, 1, 3) and np.allclose(got[0, 0], [0.0, ((128 / 255 + 0.055) / 1.055) ** 2.4, 1.0], atol=1e-6)
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(SpecError, match=r"bad\.png: cannot read albedo texture") as info:
        read_albedo_texture(tmp_path / "bad.png")
    assert "\n" not in str(info.value)


def _textured_spot(folder: Path, texture: bytes | None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "spot.obj").write_bytes(b"mtllib spot.mtl\nusemtl spot\n" + (DATA / "spot.obj").read_bytes())
    (folder / "spot.mtl").write_text("newmtl spot\nKd 1 0.9 0.8\nmap_Kd spot_texture.png\n")
    if texture is not None:
        (folder / "spot_texture.png").write_bytes(texture)
    return folder / "spot.obj"


def test_missing_texture_warns_and_corrupt_texture_stops(tmp_path):
    path = _textured_spot(tmp_path / "missing", None)
    lines = []
    (found,) = mesh_materials(str(path), ["spot"], DEFAULT, lines.append)
    assert found.albedo_texture is None and found.material.albedo == (1.0, 0.9, 0.8)
    assert any("spot_texture.png not found; using Kd" in line for line in lines)
    path = _textured_spot(tmp_path / "corrupt", b"not a png at all")
    with pytest.raises(GeometryError, match=r"spot_texture\.png: cannot read albedo texture"):
        mesh_materials(str(path), ["spot"], DEFAULT, print)


def test_corner_uvs_survive_the_geometry_cleaning():
    from prt.train.inputs.albedo_uv import file_corner_uvs, match_corner_uvs
    from prt.train.inputs.geometry import load_geometry

    geometry = load_geometry(DATA / "spot.obj")
    positions, uvs = file_corner_uvs(str(DATA / "spot.obj"))
    albedo_uv, unmatched = match_corner_uvs(geometry, positions, uvs)
    assert unmatched == 0 and albedo_uv.shape == (len(geometry.mesh.faces), 3, 2)
    # Brute force on a sample: the file triangle with the same corners, and each corner's UV.
    to_source = geometry.to_source
    built = geometry.mesh.vertices @ to_source[:3, :3].T + to_source[:3, 3]
    for f in np.random.default_rng(1).choice(len(geometry.mesh.faces), 40, replace=False):
        corners = built[geometry.mesh.faces[f]]
        for c in range(3):
            hits = np.argwhere(np.abs(positions - corners[c]).max(axis=2) < 1e-5)
            same = [uvs[t, k] for t, k in hits if all(np.abs(positions[t] - q).max(axis=1).min() < 1e-5 for q in corners)]
            assert any(np.allclose(albedo_uv[f, c], uv, atol=1e-6) for uv in same)


@pytest.fixture(scope="module")
def spot_scene(tmp_path_factory):
    """Spot with its texture (public domain, tests/data), built fast (analytic segments)."""
    folder = tmp_path_factory.mktemp("spot")
    path = _textured_spot(folder / "mesh", (DATA / "spot_texture.png").read_bytes())
    proc = subprocess.run(
        [sys.executable, "-m", "prt.train.train_cli", str(path), "-o", str(folder / "scene"), "--samples", "3000",
         "--validation", "1000", "--rays", "32", "--segments", "2", "--target", "10", "--bounces", "0", "--no-progress"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return folder / "scene" / "scene.json"


def _textured_reference(r: Renderer) -> np.ndarray:
    from prt.runtime.albedo_textures import sample_bilinear

    transfer = r.render_transfer().reshape(-1, 16).astype(np.float64)
    covered = r.gbuffer_image().covered.reshape(-1)
    ids, uv = r.gbuffer.read_material()
    texture = r.materials.textures.images[0]
    albedo = sample_bilinear(texture, uv[covered]) * np.asarray(r.materials[0].albedo)
    out = np.zeros((len(covered), 3))
    out[covered] = np.maximum(albedo * (transfer[covered] @ r.lighting.sh), 0)
    return out.reshape(r.height, r.width, 3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_albedo_texture_in_both_backends_against_numpy(gl_ctx, spot_scene, backend):
    data = json.loads(spot_scene.read_text())
    assert data["materials"][0]["albedo_texture"].startswith("textures/")
    with Renderer(Scene.load(spot_scene), SIZE, SIZE, backend=backend, ctx=gl_ctx) as r:
        r.set_envmap("studio")
        r.set_background(False)  # a new build shows its env map behind it; the reference is the surface alone
        image = r.render()
        want = _textured_reference(r)
    assert np.abs(image - want).max() < 1e-4 * max(1.0, float(want.max()))
    covered = want.sum(axis=2) > 0
    assert np.std(image[covered].sum(axis=1) / np.maximum(want[covered].sum(axis=1), 1e-6)) < 1e-3
    # the texture is visible: dark patches and white ones on the same cow
    luminance = image[covered].mean(axis=1)
    assert np.percentile(luminance, 5) < 0.3 * np.percentile(luminance, 95)


def test_a_material_set_at_run_time_has_no_texture(gl_ctx, spot_scene):
    with Renderer(Scene.load(spot_scene), SIZE, SIZE, backend="glsl", ctx=gl_ctx) as r:
        r.set_envmap("studio")
        textured = r.render()
        r.set_material("diffuse", object="spot", albedo=(0.5, 0.5, 0.5))
        plain = r.render()
        transfer = r.render_transfer()
    covered = transfer.any(axis=2)
    want = np.maximum(transfer[covered].astype(np.float64) @ (0.5 * r.lighting.sh), 0)
    assert np.abs(plain[covered] - want).max() < 1e-4
    assert np.abs(textured - plain).max() > 0.05
