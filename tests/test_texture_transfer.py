"""Texture-space transfer: atlases, the UV G-buffer, dilation, and the ``texture`` backend
against its numpy twin (:func:`prt.runtime.backends.texture.bilinear_lookup`)."""

import shutil

import numpy as np
import pytest
import trimesh

from prt.runtime import Renderer, Scene
from prt.runtime.backends import ALL_BACKENDS, BACKENDS, create_backend
from prt.runtime.backends.texture import bilinear_lookup
from prt.runtime.camera import Camera
from prt.runtime.errors import InputError
from prt.runtime.gbuffer import GBufferPass
from prt.runtime.renderer import demo_scene_path
from prt.train.inputs.geometry import load_geometry
from prt.train.transport.transfer_texture import add_transfer_texture, dilate, uv_gbuffer
from prt.train.inputs.uv_atlas import build_atlas, uv_overlap

SIZE = 64
# GL's bilinear weights have 8 fractional bits (llvmpipe, most GPUs): a fetch may differ from the
# exact weights by 1/256 of the spread of its 4 texels, plus float16 rounding of nothing (same data).
BILINEAR_TOLERANCE = 1.0 / 256.0


def _write_obj(path, vertices, faces, uvs=None, uv_faces=None, groups=None):
    lines = [f"v {x} {y} {z}" for x, y, z in vertices]
    lines += [f"vt {u} {v}" for u, v in (uvs if uvs is not None else [])]
    for i, face in enumerate(faces):
        if groups is not None and groups[i] is not None:
            lines.append(f"o {groups[i]}")
        if uvs is None:
            lines.append("f " + " ".join(str(a + 1) for a in face))
        else:
            lines.append("f " + " ".join(f"{a + 1}/{b + 1}" for a, b in zip(face, uv_faces[i])))
    path.write_text("\n".join(lines) + "\n")
    return path


def _tetrahedron(path, overlapping: bool):
    vertices = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
    faces = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]  # outward
    if overlapping:  # every face on the same UV triangle
        uvs, uv_faces = [(0.1, 0.1), (0.9, 0.1), (0.1, 0.9)], [(0, 1, 2)] * 4
    else:  # one triangle per quadrant
        uvs = [(qx + a, qy + b) for qx, qy in [(0, 0), (0.5, 0), (0, 0.5), (0.5, 0.5)] for a, b in [(0.05, 0.05), (0.45, 0.05), (0.05, 0.45)]]
        uv_faces = [(3 * i, 3 * i + 1, 3 * i + 2) for i in range(4)]
    return _write_obj(path, vertices, faces, uvs, uv_faces)


def _two_objects(path):
    """A closed box and an open quad (two-sided) as two objects, no UVs."""
    box = trimesh.creation.box((1, 1, 1))
    quad_v = [(-2, -1, -2), (2, -1, -2), (2, -1, 2), (-2, -1, 2)]
    vertices = [tuple(v) for v in box.vertices] + quad_v
    n = len(box.vertices)
    faces = [tuple(f) for f in box.faces] + [(n, n + 2, n + 1), (n, n + 3, n + 2)]
    groups = ["box"] + [None] * (len(box.faces) - 1) + ["floor", None]
    return _write_obj(path, vertices, faces, groups=groups)


def _all_sides_uv(atlas):
    faces, sides = atlas.sides()
    return atlas.corner_uv[faces, sides], atlas.atlas[faces]


# --------------------------------------------------------------------------- atlases


def test_xatlas_gives_open_faces_a_back_chart_and_nothing_overlaps(gl_ctx, tmp_path):
    geometry = load_geometry(_two_objects(tmp_path / "scene.obj"))
    assert geometry.two_sided.any() and not geometry.two_sided.all()
    atlas = build_atlas(geometry, SIZE, "shared", ctx=gl_ctx)
    assert atlas.source == "xatlas" and atlas.n_atlases == 1
    uv, _ = _all_sides_uv(atlas)
    assert uv.min() >= 0.0 and uv.max() <= 1.0
    twice, covered = uv_overlap(gl_ctx, uv, SIZE)
    assert twice == 0 and covered > 0
    open_faces = np.flatnonzero(geometry.two_sided)
    assert not np.allclose(atlas.corner_uv[open_faces, 0], atlas.corner_uv[open_faces, 1])


def test_per_object_layout_makes_one_atlas_per_object(gl_ctx, tmp_path):
    geometry = load_geometry(_two_objects(tmp_path / "scene.obj"))
    atlas = build_atlas(geometry, SIZE, "per_object", ctx=gl_ctx)
    assert atlas.n_atlases == geometry.n_objects == 2
    assert np.array_equal(atlas.atlas, geometry.object_ids)
    uv, which = _all_sides_uv(atlas)
    for index in range(2):
        assert uv_overlap(gl_ctx, uv[which == index], SIZE)[0] == 0


def test_the_mesh_uvs_are_kept_when_they_do_not_overlap(gl_ctx, tmp_path):
    lines = []
    atlas = build_atlas(load_geometry(_tetrahedron(tmp_path / "tet.obj", False)), SIZE, ctx=gl_ctx, log=lines.append)
    assert atlas.source == "mesh" and lines == []


def test_overlapping_uvs_are_detected_and_reatlased_with_one_warning(gl_ctx, tmp_path):
    path = _tetrahedron(tmp_path / "tet.obj", True)
    lines = []
    atlas = build_atlas(load_geometry(path), SIZE, ctx=gl_ctx, log=lines.append)
    assert atlas.source == "xatlas" and "overlap" in atlas.note
    assert len(lines) == 1 and "overlap" in lines[0] and str(path) in lines[0] and "\n" not in lines[0]
    assert uv_overlap(gl_ctx, _all_sides_uv(atlas)[0], SIZE)[0] == 0


# --------------------------------------------------------------------------- UV G-buffer and dilation


@pytest.fixture(scope="module")
def box_gbuffer(gl_ctx, tmp_path_factory):
    gl_ctx.__enter__()  # current here too: module fixtures are set up before conftest's _gl_current
    geometry = load_geometry(_two_objects(tmp_path_factory.mktemp("uv") / "scene.obj"))
    atlas = build_atlas(geometry, SIZE, "shared", ctx=gl_ctx)
    vertices, faces = np.asarray(geometry.mesh.vertices, np.float32), np.asarray(geometry.mesh.faces)
    return geometry, atlas, uv_gbuffer(gl_ctx, vertices, faces, atlas, SIZE)


def test_the_uv_gbuffer_covers_every_triangle(box_gbuffer):
    geometry, atlas, (position, normal, covered) = box_gbuffer
    uv, which = _all_sides_uv(atlas)
    texel = np.clip((uv.mean(axis=1) * SIZE).astype(int), 0, SIZE - 1)  # (N, 2): column, row
    assert covered[which, texel[:, 1], texel[:, 0]].all()
    # every written texel holds a point of the surface and a unit normal
    low, high = geometry.mesh.bounds
    assert np.all(position[covered] >= low - 1e-5) and np.all(position[covered] <= high + 1e-5)
    np.testing.assert_allclose(np.linalg.norm(normal[covered], axis=1), 1.0, atol=1e-5)
    # the back chart of the open floor holds the reversed normal
    faces, sides = atlas.sides()
    back = np.flatnonzero(sides == 1)
    t = texel[back]
    face_normal = geometry.mesh.face_normals[faces[back]]
    assert np.all(np.einsum("nc,nc->n", normal[0, t[:, 1], t[:, 0]], face_normal) < -0.99)


def test_dilation_fills_the_bilinear_footprint_of_every_covered_texel(box_gbuffer):
    _, _, (position, _, covered) = box_gbuffer
    values, valid = dilate(position[0], covered[0])
    assert np.array_equal(values[covered[0]], position[0][covered[0]])  # covered texels keep their value
    padded = np.pad(valid, 1, constant_values=True)  # outside the image: clamped, never read empty
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            neighbour = padded[1 + dy : 1 + dy + SIZE, 1 + dx : 1 + dx + SIZE]
            assert neighbour[covered[0]].all()


def test_texels_buried_under_a_box_do_not_darken_its_contact_line(gl_ctx, tmp_path):
    from prt.train.transport.transfer_texture import bake_transfer_texture

    box = trimesh.creation.box((1, 1, 1))
    vertices = [tuple(v + (0, 0.5, 0)) for v in box.vertices] + [(-2, 0, -2), (2, 0, -2), (2, 0, 2), (-2, 0, 2)]
    n = len(box.vertices)
    faces = [tuple(f) for f in box.faces] + [(n, n + 2, n + 1), (n, n + 3, n + 2)]
    groups = ["box"] + [None] * (len(box.faces) - 1) + ["floor", None]
    geometry = load_geometry(_write_obj(tmp_path / "box_on_floor.obj", vertices, faces, groups=groups))
    texture = bake_transfer_texture(geometry, SIZE, rays=32, ctx=gl_ctx, log=lambda line: None)
    assert texture.stats["texels_buried"] > 0  # the floor under the box
    lit = texture.transfer[0, ..., 0].astype(np.float32) > 0
    visible = texture.covered[0] & lit
    padded = np.pad(lit, 1, constant_values=True)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):  # no fetch around a visible texel reads a buried (black) one
            assert padded[1 + dy : 1 + dy + SIZE, 1 + dx : 1 + dx + SIZE][visible].all()


# --------------------------------------------------------------------------- the backend


@pytest.fixture(scope="module")
def textured_scene(tmp_path_factory):
    """The demo scene (Spot) with a 64x64 transfer texture (16 rays)."""
    folder = tmp_path_factory.mktemp("textured") / "spot"
    shutil.copytree(demo_scene_path().parent, folder)
    texture = add_transfer_texture(folder, SIZE, rays=16, log=lambda line: None)
    return Scene.load(folder), texture


def test_texture_is_a_backend_only_for_scenes_with_a_texture(gl_ctx):
    assert "texture" in ALL_BACKENDS and "texture" not in BACKENDS
    demo = Scene.load()
    assert demo.manifest.transfer_texture is None  # older manifests load without the field
    with pytest.raises(InputError, match="transfer_texture"):
        create_backend("texture", gl_ctx, demo.manifest)


def test_the_manifest_records_the_texture(textured_scene):
    scene, texture = textured_scene
    info = scene.manifest.transfer_texture
    assert (info.size, info.atlases) == (SIZE, 1) and info.extra["bytes"] == texture.nbytes
    assert scene.manifest.to_dict()["transfer_texture"]["file"] == "transfer_texture.npz"
    assert texture.stats["float16_rms_error_relative"] < 1e-3


def test_the_uv_target_leaves_position_and_normal_unchanged(gl_ctx, textured_scene):
    scene, _ = textured_scene
    plain = Scene.load()  # the same mesh without a texture: its G-buffer draws no UVs
    camera = Camera.from_manifest(scene.manifest.camera)
    reads = []
    for s in (plain, scene):
        with GBufferPass(gl_ctx, s.manifest, 40, 32) as gbuffer:
            assert (gbuffer.uv_texture is None) == (s is plain)
            gbuffer.render(camera)
            reads.append(gbuffer.read_packed().copy())
    assert np.array_equal(reads[0], reads[1])


def test_the_backend_agrees_with_its_numpy_twin(gl_ctx, textured_scene):
    scene, texture = textured_scene
    with Renderer(scene, 48, 48, backend="texture", ctx=gl_ctx) as r:
        transfer = r.render_transfer()
        uv_image = np.frombuffer(r.gbuffer.uv_texture.read(), dtype=np.float32).reshape(48, 48, 4)[::-1]
    covered = uv_image[..., 3] > 0.5
    assert covered.sum() > 100
    expected = bilinear_lookup(texture.transfer, uv_image[covered][:, :2], np.rint(uv_image[covered][:, 2]).astype(int))
    spread = np.abs(texture.transfer.astype(np.float32)).max()
    np.testing.assert_allclose(transfer[covered], expected, rtol=0, atol=BILINEAR_TOLERANCE * spread)
    assert np.all(transfer[~covered] == 0.0)


def test_end_to_end_the_texture_renders_close_to_the_networks(gl_ctx, textured_scene):
    scene, _ = textured_scene
    images = {}
    for backend in ("onnx", "texture"):
        with Renderer(scene, 48, 48, backend=backend, ctx=gl_ctx) as r:
            images[backend] = r.render()
    a, b = images["texture"], images["onnx"]
    assert np.isfinite(a).all() and np.array_equal(a.max(axis=2) > 0, b.max(axis=2) > 0)
    psnr = 10 * np.log10(b.max() ** 2 / np.mean((a - b) ** 2))
    assert psnr > 30.0  # 64x64 texels, 16 rays against small networks: the same picture


def test_prt_bench_measures_the_texture_baseline_per_size(tmp_path):
    from prt.bench import cli

    paths = {"json": tmp_path / "r.json", "md": tmp_path / "r.md", "plot": tmp_path / "r.png"}
    argv = [str(demo_scene_path()), "--size", "24", "--views", "1", "--ref-rays", "16", "--warmup", "0", "--gemm-size", "64",
            "--backends", "onnx", "texture", "--texture-size", "16", "32", "--precisions", "fp32", "--cache", str(tmp_path / "cache"),
            "--json", str(paths["json"]), "--md", str(paths["md"]), "--plot", str(paths["plot"])]  # fmt: skip
    assert cli.main(argv) == 0
    import json

    report = json.loads(paths["json"].read_text())
    textures = [r for r in report["records"] if r["backend"] == "texture"]
    assert sorted({r["texture_size"] for r in textures}) == [16, 32] and len(textures) == 4
    sizes = report["scenes"][0]["texture_baseline"]["sizes"]
    for r in textures:
        assert r["weight_bytes"] == sizes[str(r["texture_size"])]["bytes"] and r["precompute_s"] > 0 and r["psnr"] > 15
    assert "texture 32^2" in paths["md"].read_text() and "texture baseline 32x32" in paths["md"].read_text()
    assert paths["plot"].stat().st_size > 0


def test_a_broken_texture_file_is_one_geometry_error(gl_ctx, textured_scene, tmp_path):
    from prt.runtime.errors import GeometryError

    scene, _ = textured_scene
    folder = tmp_path / "broken"
    shutil.copytree(scene.manifest.root, folder, ignore=shutil.ignore_patterns("cache"))
    (folder / "transfer_texture.npz").write_bytes(b"not a zip file")
    with pytest.raises(GeometryError, match=r"transfer_texture\.npz: cannot read") as info:
        Renderer(Scene.load(folder), 8, 8, backend="texture", ctx=gl_ctx)
    assert "\n" not in str(info.value)
    with np.load(scene.manifest.transfer_texture.path) as data:
        arrays = dict(data)
    np.savez(folder / "transfer_texture.npz", **{**arrays, "transfer": arrays["transfer"][:, :8]})
    with Renderer(Scene.load(folder), 8, 8, backend="texture", ctx=gl_ctx) as r:  # the backend starts on first use
        with pytest.raises(GeometryError, match="transfer must be"):
            r.render()


def test_a_texture_beyond_the_contexts_array_layers_is_refused_in_one_line(gl_ctx, textured_scene):
    from types import SimpleNamespace

    from prt.runtime.backends.texture import check_texture_limits

    scene, _ = textured_scene
    manifest = scene.manifest
    real = gl_ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"]
    check_texture_limits(gl_ctx, manifest, SIZE, real)  # what this context holds passes
    with pytest.raises(InputError, match=r"scene\.json: transfer_texture needs 257 texture-array layers .* allows 256") as info:
        # a driver at GL 3.3's guaranteed minimum: 17 atlases of 64-value transfer do not fit
        check_texture_limits(SimpleNamespace(info={"GL_MAX_ARRAY_TEXTURE_LAYERS": 256, "GL_MAX_TEXTURE_SIZE": 16384}), manifest, SIZE, 257)
    assert "\n" not in str(info.value)
    with pytest.raises(InputError, match="GL_MAX_TEXTURE_SIZE 1024"):
        check_texture_limits(SimpleNamespace(info={"GL_MAX_ARRAY_TEXTURE_LAYERS": 256, "GL_MAX_TEXTURE_SIZE": 1024}), manifest, 2048, 4)


def test_a_bake_beyond_the_guaranteed_array_layers_warns_in_one_line(gl_ctx, tmp_path, monkeypatch):
    import prt.train.transport.transfer_texture as baking
    from prt.train.transport.transfer_texture import bake_transfer_texture

    geometry = load_geometry(_two_objects(tmp_path / "scene.obj"))
    lines = []
    bake_transfer_texture(geometry, 16, layout="per_object", rays=8, ctx=gl_ctx, log=lines.append)
    assert not [line for line in lines if "texture-array layers" in line]  # 2 atlases x 4 layers fit in 256
    monkeypatch.setattr(baking, "GL_GUARANTEED_LAYERS", 7)  # a driver at a lower limit: 8 layers do not fit
    lines.clear()
    bake_transfer_texture(geometry, 16, layout="per_object", rays=8, ctx=gl_ctx, log=lines.append)
    warnings = [line for line in lines if "texture-array layers" in line]
    assert len(warnings) == 1 and warnings[0].startswith("warning: 8 texture-array layers (2 atlases)")
