"""Alpha cut-outs (glTF ``alphaMode`` MASK, a blended texture's clear texels) become holes in the geometry.

The cut (prt.train.inputs.cutout) against its plain twin and a brute-force texel count; its area
against a disc's; a GLB with a leaf card (MASK, a checkered alpha texture) over a ground, a part
wholly clear under its cutoff and an opaque part with the same texture: the card is cut, the clear
part left out and named, the opaque part untouched, the same file gives the same triangles, the
cut card's texture coordinates are found again on the built geometry, and the rays traced
against the built geometry are blocked exactly where an alpha test at the ray's crossing of the
card (bilinear, as the GL samples) says the card is opaque: the per-ray reference, computed from
the texture without the cut.  The same card as OBJ (``map_d``) is cut the same way and a pane with
``d 0.2`` is left out as glass.
"""

from __future__ import annotations

import numpy as np
import pytest

from prt.runtime.albedo_textures import sample_bilinear
from prt.train.deform.gltf_animation import pack_accessors, write_glb
from prt.train.inputs.cutout import OpaqueCounter, cut_triangles, cut_triangles_reference
from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.gltf_scene import alpha_cutoff, read_gltf_scene


def _area(points: np.ndarray) -> np.ndarray:
    """Areas of triangles (K, 3, D) in 2-d or 3-d."""
    d1, d2 = points[:, 1] - points[:, 0], points[:, 2] - points[:, 0]
    if points.shape[2] == 2:
        return 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    return 0.5 * np.linalg.norm(np.cross(d1, d2), axis=1)


def test_opaque_counts_match_a_brute_force_count_on_the_tiled_plane():
    rng = np.random.default_rng(1)
    opaque = rng.random((5, 7)) < 0.4
    counter = OpaqueCounter(opaque)
    for _ in range(300):
        x0, y0 = rng.integers(-30, 30, 2)
        x1, y1 = x0 + rng.integers(0, 25), y0 + rng.integers(0, 25)
        brute = sum(bool(opaque[r % 5, c % 7]) for r in range(y0, y1) for c in range(x0, x1))
        assert counter.count(x0, y0, x1, y1) == brute


def test_the_cut_matches_its_plain_twin():
    rng = np.random.default_rng(2)
    alpha = rng.random((11, 13)).astype(np.float32)  # odd sizes; smooth enough to leave whole pieces
    alpha = (alpha + np.roll(alpha, 1, 0) + np.roll(alpha, 1, 1) + np.roll(alpha, 2, 1)) / 4
    uv = rng.uniform(-1.5, 2.5, (12, 3, 2))  # outside [0, 1]: the texture repeats
    uv[3, 1, 0] = np.nan  # a malformed triangle: kept whole
    for depth in (0, 3, 5):
        face, bary = cut_triangles(uv, alpha, 0.5, depth)
        face2, bary2 = cut_triangles_reference(uv, alpha, 0.5, depth)
        assert np.array_equal(face, face2) and np.array_equal(bary, bary2)
        assert np.allclose(bary.sum(axis=2), 1.0) and (bary >= 0).all()
        assert np.array_equal(bary[face == 3], np.eye(3)[None])
    assert 0 < len(face) and len(np.unique(face)) > 1


def test_a_disc_is_cut_to_its_area_and_pieces_keep_their_winding():
    size = 256
    y, x = np.mgrid[0:size, 0:size] + 0.5
    alpha = (((x - 128) ** 2 + (y - 128) ** 2) < 100.0**2).astype(np.float32)
    uv = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], dtype=np.float64)
    face, bary = cut_triangles(uv, alpha, 0.5)
    pieces = np.einsum("kcj,kjd->kcd", bary, uv[face])
    area = _area(pieces).sum()
    assert area == pytest.approx(np.pi * (100 / 256) ** 2, rel=0.01)
    d1, d2 = pieces[:, 1] - pieces[:, 0], pieces[:, 2] - pieces[:, 0]
    assert (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] > 0).all()  # counter-clockwise like their triangles
    assert len(face) < 4000  # split along the rim only (a uniform split at a texel would be 130k)
    centre = pieces.mean(axis=1)
    assert (sample_bilinear(alpha[:, :, None], centre)[:, 0] >= 0.5).mean() > 0.99



def test_a_budget_cuts_every_part_coarser():
    from prt.train.inputs.cutout import cut_within_budget

    size = 256
    y, x = np.mgrid[0:size, 0:size] + 0.5
    alpha = (((x - 128) ** 2 + (y - 128) ** 2) < 100.0**2).astype(np.float32)
    uv = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], dtype=np.float64)
    full = cut_within_budget([(uv, alpha, 0.5), (uv[:1], alpha, 0.5)])
    small = cut_within_budget([(uv, alpha, 0.5), (uv[:1], alpha, 0.5)], budget=600)
    assert sum(len(f) for f, _ in full) > 600 >= sum(len(f) for f, _ in small) > 100
    for face, bary in small:  # coarser, still about the disc
        pieces = np.einsum("kcj,kjd->kcd", bary, uv[face])
        assert _area(pieces).sum() / (np.pi * (100 / 256) ** 2 * len(np.unique(face)) / 2) == pytest.approx(1.0, abs=0.05)


def test_parts_sharing_a_texture_are_cut_as_each_alone():
    """One call per texture (its summed-area table built once) gives every part what cutting it alone gives."""
    from prt.train.inputs.cutout import cut_within_budget

    rng = np.random.default_rng(4)
    alpha = (rng.random((16, 16)) > 0.5).astype(np.float32)
    other = (rng.random((8, 8)) > 0.3).astype(np.float32)
    uvs = [rng.uniform(0, 1, (n, 3, 2)) for n in (3, 5, 2)]
    jobs = [(uvs[0], alpha, 0.5), (uvs[1], other, 0.5), (uvs[2], alpha, 0.5), (uvs[0], alpha, 0.7)]
    for (face, bary), (uv, a, cutoff) in zip(cut_within_budget(jobs), jobs):
        alone_face, alone_bary = cut_triangles(uv, a, cutoff)
        assert np.array_equal(face, alone_face) and np.array_equal(bary, alone_bary)

# --------------------------------------------------------------------------- a GLB with a leaf card

CELLS = 4  # the card's alpha: CELLS x CELLS squares, opaque and clear in turn (2 texels each)


def _checker() -> np.ndarray:
    texel = np.arange(2 * CELLS) // 2
    opaque = (texel[:, None] + texel[None, :]) % 2 == 0
    image = np.zeros((2 * CELLS, 2 * CELLS, 4), np.uint8)
    image[:, :, 1] = np.where(opaque, 160, 0)
    image[:, :, 3] = np.where(opaque, 255, 0)
    return image


def write_card_scene(path) -> None:
    """A horizontal card (y = 0.5, x and z in [0, 1], UV (x, z), MASK) over a ground box, a clear
    MASK card beside it and an OPAQUE card with the same texture above."""
    import imageio.v3 as iio

    card_v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], np.float32)
    card_uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)  # glTF v: 1 - z (OBJ's v = z)
    card_f = np.array([[0, 2, 1], [0, 3, 2]], np.uint32)  # facing +y
    ground_v = np.array([[x, y, z] for x in (-2, 3) for y in (-0.1, 0) for z in (-2, 3)], np.float32)
    ground_f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)  # fmt: skip
    arrays = [card_v, card_f.reshape(-1, 1), card_uv, ground_v, ground_f.reshape(-1, 1)]
    views, accessors, binary = pack_accessors(arrays)
    png = iio.imwrite("<bytes>", _checker(), extension=".png")
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    binary += png + b"\0" * ((-len(png)) % 4)
    card = {"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1}
    document = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2, 3]}],
        "nodes": [
            {"name": "leaf", "mesh": 0, "translation": [0, 0.5, 0]},
            {"name": "ground", "mesh": 1},
            {"name": "mist", "mesh": 2, "translation": [1.5, 0.5, 0]},
            {"name": "sign", "mesh": 3, "translation": [-1.5, 0.5, 0]},
        ],
        "meshes": [
            {"primitives": [dict(card, material=0)]},
            {"primitives": [{"attributes": {"POSITION": 3}, "indices": 4, "material": 1}]},
            {"primitives": [dict(card, material=2)]},
            {"primitives": [dict(card, material=3)]},
        ],
        "materials": [
            {"name": "leaf", "alphaMode": "MASK", "alphaCutoff": 0.5, "doubleSided": True,
             "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0}},
            {"name": "soil", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.4, 0.3, 1], "metallicFactor": 0.0}},
            {"name": "mist", "alphaMode": "MASK", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 0.2]}},
            {"name": "sign", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0}},
        ],
        "textures": [{"source": 0}],
        "images": [{"bufferView": len(arrays), "mimeType": "image/png"}],
        "bufferViews": views,
        "accessors": accessors,
    }  # fmt: skip
    write_glb(path, document, binary)


@pytest.fixture
def card_scene(tmp_path):
    path = tmp_path / "cards.glb"
    write_card_scene(path)
    return path


def test_alpha_modes():
    assert alpha_cutoff({"alphaMode": "MASK"}) == 0.5
    assert alpha_cutoff({"alphaMode": "MASK", "alphaCutoff": 0.3}) == 0.3
    assert alpha_cutoff({"alphaMode": "BLEND"}) == 0.5
    assert alpha_cutoff({"alphaMode": "OPAQUE"}) is None and alpha_cutoff({}) is None


def test_the_card_is_cut_the_clear_part_left_out_and_both_named(card_scene):
    scene = read_gltf_scene(card_scene)
    parts = {p.name: p for p in scene.parts}
    assert sorted(parts) == ["ground", "leaf", "sign"] and scene.cut_away == ["mist"]
    assert list(scene.cut) == ["leaf"] and scene.cut["leaf"][1] == 2
    leaf = parts["leaf"]
    assert _area(leaf.vertices[leaf.faces]).sum() == pytest.approx(0.5, abs=1e-9)  # half the cells
    assert len(parts["sign"].faces) == 2  # OPAQUE: the texture's alpha is not looked at
    uv = scene.texcoords(leaf)[leaf.faces]  # the pieces' UVs, interpolated in their triangles
    assert np.allclose(uv[:, :, 0], leaf.vertices[leaf.faces][:, :, 0]) and np.allclose(uv[:, :, 1], leaf.vertices[leaf.faces][:, :, 2])
    alpha = _checker()[:, :, 3].astype(np.float32)[:, :, None] / 255
    assert (sample_bilinear(alpha, uv.mean(axis=1))[:, 0] >= 0.5).all()
    again = read_gltf_scene(card_scene)
    assert all(np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces) for a, b in zip(scene.parts, again.parts))

    geometry = load_geometry(card_scene)
    summary = geometry.summary()
    assert "1 alpha-masked parts cut along their texture's alpha (2 triangles ->" in summary and "leaf" in summary
    assert "1 parts left out, wholly clear under their alpha cutoff: mist" in summary
    assert geometry.object_names == ["leaf", "ground", "sign"]


def test_the_cut_cards_texture_coordinates_are_found_on_the_built_geometry(card_scene):
    from prt.train.inputs.albedo_uv import file_corner_uvs, match_corner_uvs

    geometry = load_geometry(card_scene)
    albedo_uv, unmatched = match_corner_uvs(geometry, *file_corner_uvs(str(card_scene)))
    assert unmatched == 0
    leaf = np.flatnonzero(geometry.object_ids == geometry.object_names.index("leaf"))
    alpha = _checker()[:, :, 3].astype(np.float32)[:, :, None] / 255
    assert (sample_bilinear(alpha, albedo_uv[leaf].mean(axis=1))[:, 0] >= 0.5).all()


def test_rays_through_the_card_are_blocked_where_its_alpha_test_says(card_scene):
    """The per-ray reference: each ray from the ground under the card crosses the card's plane at
    one point; the texture's bilinear alpha there (the rasteriser's alpha test) decides whether
    the card blocks it.  Embree on the built (cut) geometry must agree but for rays crossing within
    a texel of a cell's edge (the cut follows the mask to about a texel)."""
    from prt.train.transport.transfer import EmbreeTracer

    geometry = load_geometry(card_scene)
    to_source = np.asarray(geometry.to_source)
    rng = np.random.default_rng(5)
    n = 20000
    start = np.stack([rng.uniform(0.05, 0.95, n), np.full(n, 0.001), rng.uniform(0.05, 0.95, n)], axis=1)  # source units
    dirs = rng.normal(size=(n, 3))
    dirs[:, 1] = np.abs(dirs[:, 1]) + 0.3
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = (0.5 - start[:, 1]) / dirs[:, 1]
    cross = start + t[:, None] * dirs  # where each ray meets the card's plane
    on_card = (cross[:, 0] > 0) & (cross[:, 0] < 1) & (cross[:, 2] > 0) & (cross[:, 2] < 1)
    alpha = _checker()[:, :, 3].astype(np.float32)[:, :, None] / 255
    blocked_ref = on_card & (sample_bilinear(alpha, cross[:, [0, 2]])[:, 0] >= 0.5)
    blocked_ref |= (cross[:, 0] > -1.5) & (cross[:, 0] < -0.5) & (cross[:, 2] > 0) & (cross[:, 2] < 1)  # the opaque sign
    # the scene's (normalised) coordinates
    inverse = np.linalg.inv(to_source)
    origins = (start @ inverse[:3, :3].T + inverse[:3, 3]).astype(np.float32)
    blocked = EmbreeTracer(geometry.mesh).occluded(origins, np.ascontiguousarray(dirs, dtype=np.float32))
    texel = 1.0 / (2 * CELLS)
    near_edge = np.min(np.abs(((cross[:, [0, 2]] + texel) % (2 * texel)) - texel), axis=1) < texel / 2
    far = ~near_edge | ~on_card
    assert on_card.sum() > 5000 and blocked_ref[far].any() and (~blocked_ref[far & on_card]).any()
    assert np.array_equal(blocked[far], blocked_ref[far])
    assert (blocked != blocked_ref).mean() < 0.05


def test_a_cut_cards_texture_mean_is_its_opaque_texels(card_scene):
    """The leaf's texels are green where opaque and black where clear: its texture's mean colour
    (what tints a metal's lobe) is the green, not half of it; the opaque sign's averages all."""
    from prt.runtime.albedo_textures import srgb_to_linear
    from prt.train.inputs.gltf_scene import albedo_texture_info
    from prt.train.inputs.materials import _albedo_texture

    scene = read_gltf_scene(card_scene)
    parts = {p.name: p for p in scene.parts}
    green = srgb_to_linear(160 / 255)
    info = albedo_texture_info(scene.document, parts["leaf"].material)
    _, leaf = _albedo_texture(scene, parts["leaf"], info, "leaf", print)
    _, sign = _albedo_texture(scene, parts["sign"], info, "sign", print)
    assert np.allclose(leaf, [0, green, 0], atol=1e-6) and np.allclose(sign, [0, green / 2, 0], atol=1e-6)


def write_card_obj(folder):
    """The leaf card and ground as OBJ: the card's material has the checker as ``map_d`` (a grey
    map, named with Windows' backslash; and as ``map_Kd``); a pane with ``d 0.2`` and ``illum 4``
    (glass) and one with ``d 0`` and ``illum 2`` (opaque: the Crytek Sponza's MTL writes that on
    every wall) beside it; the ground has ``Tr 0.9`` and ``illum 9`` (d 0.1, but Tr is read only
    where d is not given: here d 1, opaque)."""
    import imageio.v3 as iio

    (folder / "textures").mkdir()
    iio.imwrite(folder / "textures" / "leaf_mask.png", _checker()[:, :, 3])  # a grey map: its first channel
    iio.imwrite(folder / "leaf.png", _checker()[:, :, :3])
    (folder / "cards.mtl").write_text("newmtl leaf\nKd 1 1 1\nmap_Kd leaf.png\nmap_d -clamp on textures\\leaf_mask.png\n"
                                      "newmtl soil\nKd 0.5 0.4 0.3\nd 1.0\nTr 0.9\nillum 9\nnewmtl glass\nKd 0.9 0.9 0.9\nd 0.2\nillum 4\n"
                                      "newmtl film\nd 0.000000\nillum 2\n")
    lines = ["mtllib cards.mtl", "v 0 0.5 0", "v 1 0.5 0", "v 1 0.5 1", "v 0 0.5 1", "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1",
             "o leaf", "usemtl leaf", "f 1/1 3/3 2/2", "f 1/1 4/4 3/3",
             "v -2 0 -2", "v 3 0 -2", "v 3 0 3", "v -2 0 3", "o ground", "usemtl soil", "f 5 8 7 6",
             "v 1.5 0.5 0", "v 2.5 0.5 0", "v 2.5 0.5 1", "o pane", "usemtl glass", "f 9 11 10",
             "v -1.5 0.5 0", "v -0.5 0.5 0", "v -0.5 0.5 1", "o film", "usemtl film", "f 12 14 13"]  # fmt: skip
    (folder / "cards.obj").write_text("\n".join(lines) + "\n")
    return folder / "cards.obj"


def test_obj_map_d_cuts_and_d_leaves_glass_out(tmp_path):
    from prt.train.inputs.albedo_uv import match_corner_uvs
    from prt.train.inputs.materials import corner_uvs

    path = write_card_obj(tmp_path)
    geometry = load_geometry(path)
    assert geometry.object_names == ["leaf", "ground", "film"] and geometry.see_through == ["pane"]
    assert list(geometry.cut_out) == ["leaf"] and geometry.cut_out["leaf"][1] == 2
    leaf = np.flatnonzero(geometry.object_ids == 0)
    area = _area(np.asarray(geometry.mesh.vertices)[np.asarray(geometry.mesh.faces)[leaf]] * geometry.to_source[0, 0]).sum()
    assert area == pytest.approx(0.5, rel=1e-6)
    albedo_uv, unmatched = match_corner_uvs(geometry, *corner_uvs(str(path)))
    assert unmatched == 0
    alpha = _checker()[:, :, 3].astype(np.float32)[:, :, None] / 255
    assert (sample_bilinear(alpha, albedo_uv[leaf].mean(axis=1))[:, 0] >= 0.5).all()
    again = load_geometry(path)
    assert np.array_equal(again.mesh.vertices, geometry.mesh.vertices) and np.array_equal(again.mesh.faces, geometry.mesh.faces)
    summary = geometry.summary()
    assert "1 see-through (glass) parts left out, light passes them: pane" in summary and "cut along their texture's alpha" in summary


def test_a_gpu_texture_is_named_not_a_failed_build(tmp_path):
    """A colour texture only in KTX2 (KHR_texture_basisu without a fallback image) cannot be decoded
    here: the build goes on, the materials' reader warns (the factors alone), the alpha-masked part is
    drawn opaque and the build's first line says so."""
    from prt.train.inputs.materials import mesh_materials

    card_v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], np.float32)
    card_uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    card_f = np.array([[0, 2, 1], [0, 3, 2]], np.uint32)
    views, accessors, binary = pack_accessors([card_v, card_f.reshape(-1, 1), card_uv])
    ktx2 = b"\xabKTX 20\xbb\r\n\x1a\n" + bytes(64)
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(ktx2)})
    binary += ktx2 + b"\0" * ((-len(ktx2)) % 4)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"name": "leaf", "mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]}],
        "materials": [{"name": "leaf", "alphaMode": "MASK", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"extensions": {"KHR_texture_basisu": {"source": 0}}}],
        "images": [{"bufferView": 3, "mimeType": "image/ktx2"}],
        "extensionsUsed": ["KHR_texture_basisu"], "bufferViews": views, "accessors": accessors,
    }  # fmt: skip
    path = tmp_path / "ktx.glb"
    write_glb(path, document, binary)
    geometry = load_geometry(path)
    assert len(geometry.mesh.faces) == 2 and geometry.uncut == ["ktx"]  # a single part is named after its file
    assert "WARNING: 1 alpha-masked parts drawn opaque (their alpha could not be read or lined up): ktx" in geometry.summary()
    said = []
    materials = mesh_materials(str(path), geometry.object_names, {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}, said.append)
    assert any("KTX2 GPU texture" in line for line in said) and materials[0].albedo_texture is None
