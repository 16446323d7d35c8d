"""Geometry loading: the OBJ reader, cleaning, normalisation, orientation and error messages."""

from __future__ import annotations

import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh

from prt.runtime.errors import GeometryError
from prt.train.inputs.geometry import Geometry, load_geometry
from prt.train.inputs.objfile import read_obj

DATA = Path(__file__).parent / "data"
SHARED = Path("/work/shared/data/meshes")
CORNELL = DATA / "CornellBox-Original.obj"
SPOT = DATA / "spot.obj"
CORNELL_OBJECTS = ["floor", "ceiling", "backWall", "rightWall", "leftWall", "shortBox", "tallBox", "light"]


def shared(name: str) -> Path:
    """A mesh from the shared data folder, or skip the test where it is absent."""
    path = SHARED / name
    if not path.is_file():
        pytest.skip(f"shared test mesh {path} not available")
    return path


def write_obj(path: Path, vertices, faces, *, relative: str = "", groups=None) -> Path:
    """Write an OBJ with full-precision vertices; faces may be polygons (lists of 0-based indices).

    ``relative="end"`` writes negative indices counted from the end of the vertex list;
    ``relative="interleaved"`` writes each face right after copies of its own vertices.
    ``groups`` maps a face number to the ``g`` name written before it.
    """
    vertices = np.asarray(vertices, dtype=float)

    def vertex_line(v):
        return "v " + " ".join(repr(float(x)) for x in v)

    lines = []
    if relative == "interleaved":
        for face in faces:
            lines += [vertex_line(vertices[i]) for i in face]
            lines.append("f " + " ".join(str(k - len(face)) for k in range(len(face))))
    else:
        lines += [vertex_line(v) for v in vertices]
        for number, face in enumerate(faces):
            if groups is not None and groups.get(number):
                lines.append(f"g {groups[number]}")
            base = len(vertices) if relative == "end" else -1
            lines.append("f " + " ".join(str(i - base) for i in face))
    path.write_text("\n".join(lines) + "\n")
    return path


def face_normals(geometry: Geometry) -> np.ndarray:
    corners = geometry.mesh.vertices[geometry.mesh.faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def assert_one_line_naming(error: pytest.ExceptionInfo, path) -> None:
    message = str(error.value)
    assert str(path) in message
    assert "\n" not in message and "Traceback" not in message


# --- the OBJ reader ---------------------------------------------------------------------------


def test_cornell_box_negative_indices_groups_and_bounds():
    vertices, faces, object_ids, names = read_obj(CORNELL)
    assert faces.shape == (36, 3) and faces.dtype == np.int64
    assert names == CORNELL_OBJECTS
    assert np.bincount(object_ids).tolist() == [2, 2, 2, 2, 2, 12, 12, 2]
    corners = vertices[faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1) / 2
    assert area.min() > 0.01
    used = vertices[np.unique(faces)]
    assert np.allclose(used.min(axis=0), [-1.02, 0.0, -1.04])
    assert np.allclose(used.max(axis=0), [1.0, 1.99, 0.99])


def test_relative_and_absolute_indices_give_the_same_mesh(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    absolute = write_obj(tmp_path / "abs.obj", sphere.vertices, sphere.faces)
    relative = write_obj(tmp_path / "rel.obj", sphere.vertices, sphere.faces, relative="end")
    assert "f -" in relative.read_text()
    for a, r in zip(read_obj(absolute), read_obj(relative)):
        assert np.array_equal(a, r)
    a, r = load_geometry(absolute), load_geometry(relative)
    assert np.array_equal(a.mesh.vertices, r.mesh.vertices)
    assert np.array_equal(a.mesh.faces, r.mesh.faces)

    # Each face after copies of its own vertices (as in the Cornell box): same triangles, and
    # merging the copies restores the shared vertices.
    mixed = write_obj(tmp_path / "mixed.obj", sphere.vertices, sphere.faces, relative="interleaved")
    interleaved = load_geometry(mixed)
    assert np.array_equal(interleaved.mesh.triangles, a.mesh.triangles)
    assert len(interleaved.mesh.vertices) == len(sphere.vertices) and interleaved.mesh.is_watertight


def test_corner_forms_comments_continuations_and_crlf(tmp_path):
    text = (
        "# header\r\n"
        "mtllib missing.mtl\r\n"
        "v 0 0 0\r\nv 1 0 0 1.0\r\nv 1 1 0 0.5 0.5 0.5\r\nv 0 1 0\r\n"
        "vt 0 0\r\nvn 0 0 1\r\n"
        "\r\n"
        "f 1/1 2/1/1 \\\r\n  3//1   # a triangle split over two lines\r\n"
        "f -4//1 -2/1/1 -1\r\n"
    )
    path = tmp_path / "forms.obj"
    path.write_bytes(text.encode())
    vertices, faces, object_ids, names = read_obj(path)
    assert vertices.shape == (4, 3)
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert object_ids.tolist() == [0, 0] and names == ["default"]


def test_polygons_are_fan_triangulated(tmp_path):
    square = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    pentagon = [[np.cos(a), np.sin(a), 2.0] for a in np.linspace(0, 2 * np.pi, 6)[:-1]]
    path = write_obj(tmp_path / "poly.obj", square + pentagon, [[0, 1, 2, 3], [4, 5, 6, 7, 8]])
    vertices, faces, _, _ = read_obj(path)
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [4, 7, 8]]
    geometry = load_geometry(path, normalise=False)
    assert len(geometry.mesh.faces) == 5
    pentagon_area = 5 / 2 * np.sin(2 * np.pi / 5)
    assert geometry.mesh.area == pytest.approx(1.0 + pentagon_area)


def test_groups_define_objects_and_materials_are_the_fallback(tmp_path):
    v = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
    grouped = tmp_path / "grouped.obj"
    grouped.write_text(v + "f 1 2 3\ng a\nusemtl red\nf 1 2 4\no b c\nusemtl red\nf 1 3 4\ng a\nf 2 3 4\n")
    _, _, ids, names = read_obj(grouped)
    assert names == ["default", "a", "b c"] and ids.tolist() == [0, 1, 2, 1]

    materials = tmp_path / "materials.obj"
    materials.write_text(v + "usemtl red\nf 1 2 3\nusemtl blue\nf 1 2 4\nusemtl red\nf 1 3 4\n")
    _, _, ids, names = read_obj(materials)
    assert names == ["red", "blue"] and ids.tolist() == [0, 1, 0]


def test_daffodil_material_groups_and_missing_mtl():
    path = shared("daffodil_plant.obj")
    geometry = load_geometry(path)
    assert geometry.object_names == ["08___Default", "04___Default", "01___Default", "02___Default", "03___Default"]
    assert len(geometry.mesh.faces) == 5756
    assert geometry.two_sided.any()


# --- cleaning, normalisation, orientation -----------------------------------------------------


def test_cornell_box_geometry():
    geometry = load_geometry(CORNELL)
    assert geometry.kind == "mesh" and geometry.sdf is None
    assert len(geometry.mesh.faces) == 36
    assert geometry.object_names == CORNELL_OBJECTS
    assert np.bincount(geometry.object_ids, minlength=8).min() > 0
    assert geometry.mesh.area_faces.min() > 1e-3
    bounds = geometry.source_bounds()
    assert np.allclose(bounds, [[-1.02, 0.0, -1.04], [1.0, 1.99, 0.99]])
    # The walls are open surfaces; the two boxes are closed and face outward.
    boxes = np.isin(geometry.object_ids, [5, 6])
    assert geometry.two_sided[~boxes].all() and not geometry.two_sided[boxes].any()
    floor = geometry.object_ids == 0
    assert np.allclose(face_normals(geometry)[floor], [0, 1, 0], atol=1e-2)  # the file's winding is kept
    summary = geometry.summary()
    assert "36 triangles" in summary and "8 objects" in summary and "\n" not in summary


def test_normalisation_and_to_source():
    geometry = load_geometry(CORNELL)
    vertices = geometry.mesh.vertices
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    assert (high - low).max() == pytest.approx(2.0, abs=1e-12)
    assert np.allclose((low + high) / 2, 0.0, atol=1e-12)
    assert low.min() >= -1 - 1e-12 and high.max() <= 1 + 1e-12
    assert geometry.to_source.shape == (4, 4) and geometry.scale == pytest.approx(2.03 / 2)
    # Every scene vertex maps back onto a vertex of the file.
    source_vertices, _, _, _ = read_obj(CORNELL)
    back = np.c_[vertices, np.ones(len(vertices))] @ geometry.to_source.T
    assert np.allclose(back[:, 3], 1.0)
    distance = np.linalg.norm(back[:, None, :3] - source_vertices[None], axis=2).min(axis=1)
    assert distance.max() < 1e-12

    raw = load_geometry(CORNELL, normalise=False)
    assert np.array_equal(raw.to_source, np.eye(4)) and raw.scale == 1.0
    assert np.allclose(raw.mesh.vertices, back[:, :3])


def test_tiny_and_huge_inputs_normalise_alike(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    scene = []
    for scale in (1e-6, 1.0, 1e6):
        path = write_obj(tmp_path / f"s{scale:g}.obj", sphere.vertices * scale + [3 * scale, 0, 0], sphere.faces)
        geometry = load_geometry(path)
        assert len(geometry.mesh.faces) == len(sphere.faces)
        assert geometry.scale == pytest.approx(scale, rel=1e-9)
        scene.append(geometry.mesh.vertices)
    assert np.allclose(scene[0], scene[1], atol=1e-9) and np.allclose(scene[2], scene[1], atol=1e-9)


def test_zero_area_faces_removed_with_object_ids_aligned(tmp_path):
    vertices = [[0, 0, z] for z in range(3)] + [[1, 0, z] for z in range(3)] + [[0, 1, z] for z in range(3)]
    vertices += [[2, 0, 1]]  # collinear with the z = 1 edge
    #        (a, z=0)   (b: sliver, z=1)  (b: repeated vertex)  (b, z=1)   (c: only a sliver)  (c, z=2)
    faces = [[0, 3, 6], [1, 4, 9], [1, 1, 7], [1, 4, 7], [2, 2, 5], [2, 5, 8]]
    path = write_obj(tmp_path / "slivers.obj", vertices, faces, groups={0: "a", 1: "b", 4: "c"})
    geometry = load_geometry(path, normalise=False)
    assert len(geometry.mesh.faces) == 3
    assert geometry.object_names == ["a", "b", "c"]
    assert geometry.object_ids.tolist() == [0, 1, 2]
    # Each surviving face still lies in its object's plane z = 0, 1, 2.
    z = geometry.mesh.vertices[geometry.mesh.faces][:, :, 2]
    assert np.array_equal(z, np.repeat([[0.0], [1.0], [2.0]], 3, axis=1))
    assert len(geometry.mesh.vertices) == 9  # the unreferenced collinear vertex is gone


def test_closed_mesh_with_a_sliver_stays_closed(tmp_path):
    # Split face (a, b, c) at the midpoint m of edge ab and close the crack with the zero-area
    # triangle (a, b, m): the surface is closed, and dropping the sliver must not open it.
    sphere = trimesh.creation.icosphere(subdivisions=1)
    a, b, c = sphere.faces[0]
    m = len(sphere.vertices)
    vertices = np.vstack([sphere.vertices, (sphere.vertices[a] + sphere.vertices[b]) / 2])
    faces = np.vstack([sphere.faces[1:], [[a, m, c], [m, b, c], [a, b, m]]])
    geometry = load_geometry(write_obj(tmp_path / "sliver.obj", vertices, faces))
    assert len(geometry.mesh.faces) == len(sphere.faces) + 1
    assert not geometry.two_sided.any() and geometry.mesh.volume > 0


def test_objects_left_without_faces_are_dropped(tmp_path):
    path = tmp_path / "empty_group.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\ng only_a_sliver\nf 1 2 2\ng real\nf 1 2 3\n")
    geometry = load_geometry(path)
    assert geometry.object_names == ["real"] and geometry.object_ids.tolist() == [0]


def test_nan_vertices_are_dropped(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 0\nf 1 2 3\nf 1 2 4\n")
    geometry = load_geometry(path)
    assert len(geometry.mesh.faces) == 1 and np.isfinite(geometry.mesh.vertices).all()


def test_flipped_faces_are_made_consistent_and_outward(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    faces = sphere.faces.copy()
    rng = np.random.default_rng(0)
    flip = rng.random(len(faces)) < 0.5
    faces[flip] = faces[flip][:, ::-1]
    for name, candidate in (("half.obj", faces), ("inside_out.obj", sphere.faces[:, ::-1])):
        geometry = load_geometry(write_obj(tmp_path / name, sphere.vertices + [5, 0, 0], candidate))
        outward = geometry.mesh.triangles_center - geometry.mesh.vertices.mean(axis=0)
        assert (np.einsum("ij,ij->i", face_normals(geometry), outward) > 0).all()
        assert not geometry.two_sided.any() and geometry.mesh.is_watertight


def test_two_separate_closed_objects_stay_closed(tmp_path):
    # Stacked boxes share a whole face's vertices; merging across objects would make them open.
    lower = trimesh.creation.box(extents=[1, 1, 1])
    upper = trimesh.creation.box(extents=[1, 1, 1])
    upper.apply_translation([0, 0, 1])
    scene = trimesh.Scene()
    scene.add_geometry(lower, node_name="lower", geom_name="lower")
    scene.add_geometry(upper, node_name="upper", geom_name="upper")
    path = tmp_path / "stack.glb"
    scene.export(path)
    geometry = load_geometry(path)
    assert sorted(geometry.object_names) == ["lower", "upper"]
    assert not geometry.two_sided.any()


def test_open_meshes_are_two_sided_closed_ones_not(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    upper = sphere.faces[sphere.triangles_center[:, 2] > 0]
    hemisphere = load_geometry(write_obj(tmp_path / "hemi.obj", sphere.vertices, upper))
    assert hemisphere.two_sided.all() and hemisphere.two_sided.dtype == bool

    spot = load_geometry(SPOT)
    assert len(spot.mesh.faces) == 5856
    assert not spot.two_sided.any() and spot.mesh.is_watertight and spot.mesh.volume > 0


def test_teapot_is_open():
    geometry = load_geometry(shared("utah_teapot.obj"))
    assert len(geometry.mesh.faces) == 6320 and geometry.two_sided.all()


def test_bunny_is_closed_and_outward():
    geometry = load_geometry(shared("stanford_bunny_hr.obj"))
    assert len(geometry.mesh.faces) == 59664
    assert not geometry.two_sided.any()
    assert geometry.mesh.is_watertight and geometry.mesh.volume > 0


# --- other formats ----------------------------------------------------------------------------


def test_suzanne_ply_polygons():
    geometry = load_geometry(shared("suzanne.ply"))
    assert len(geometry.mesh.faces) == 968
    assert geometry.object_names == ["suzanne"]
    assert np.abs(geometry.mesh.vertices).max() == pytest.approx(1.0)


@pytest.mark.parametrize("extension", ["ply", "stl", "off"])
def test_single_mesh_formats_round_trip(tmp_path, extension):
    box = trimesh.creation.box(extents=[2, 4, 8])
    box.apply_translation([10, 0, 0])
    path = tmp_path / f"box.{extension}"
    box.export(path)
    geometry = load_geometry(path)
    # STL stores three vertices per triangle: they must be merged back into a closed box.
    assert len(geometry.mesh.faces) == 12 and len(geometry.mesh.vertices) == 8
    assert not geometry.two_sided.any() and geometry.mesh.volume > 0
    assert np.allclose(geometry.source_bounds(), [[9, -2, -4], [11, 2, 4]])
    assert geometry.object_names == ["box"]


def test_multi_object_glb_keeps_objects_and_transforms(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), node_name="crate", geom_name="crate_mesh")
    ball = trimesh.creation.icosphere(subdivisions=1)
    lift = trimesh.transformations.translation_matrix([0, 5, 0])
    scene.add_geometry(ball, node_name="ball", geom_name="ball_mesh", transform=lift)
    path = tmp_path / "two.glb"
    scene.export(path)
    geometry = load_geometry(path)
    assert geometry.object_names == ["crate", "ball"]
    counts = np.bincount(geometry.object_ids)
    assert counts.tolist() == [12, len(ball.faces)]
    ball_source = geometry.mesh.vertices[np.unique(geometry.mesh.faces[geometry.object_ids == 1])]
    ball_source = ball_source * geometry.scale + geometry.to_source[:3, 3]
    assert np.allclose(ball_source.mean(axis=0), [0, 5, 0], atol=1e-6)


# --- SDF scenes ---------------------------------------------------------------------------------


def test_sdf_branch_uses_get_sdf(monkeypatch):
    class FakeSDF:
        name = "ball"

        def to_mesh(self, resolution=128):
            return trimesh.creation.icosphere(subdivisions=2, radius=0.5)

    def get_sdf(name):
        if name != "ball":
            raise GeometryError(f"unknown SDF scene {name!r} (known: ball)")
        return FakeSDF()

    monkeypatch.setitem(sys.modules, "prt.train.sdf", types.SimpleNamespace(get_sdf=get_sdf))
    geometry = load_geometry("ball")
    assert geometry.kind == "sdf" and isinstance(geometry.sdf, FakeSDF)
    assert np.array_equal(geometry.to_source, np.eye(4)) and geometry.object_names == ["ball"]
    assert not geometry.two_sided.any() and (geometry.object_ids == 0).all()
    assert np.abs(geometry.mesh.vertices).max() == pytest.approx(0.5)  # not rescaled
    with pytest.raises(GeometryError, match="known: ball") as error:
        load_geometry("cube")
    assert_one_line_naming(error, "cube")


def test_real_sdf_scene():
    sdf = pytest.importorskip("prt.train.sdf")
    names = sorted(getattr(sdf, "SDF_SCENES", {}))
    if not names:
        pytest.skip("prt.train.sdf lists no scenes")
    geometry = load_geometry(names[0], sdf_resolution=32)
    assert geometry.kind == "sdf" and geometry.source == names[0]
    assert np.array_equal(geometry.to_source, np.eye(4))
    assert np.abs(geometry.mesh.vertices).max() <= 1.0 and len(geometry.mesh.faces) > 100


def test_unknown_name_is_neither_file_nor_sdf():
    with pytest.raises(GeometryError, match="not a built-in SDF scene") as error:
        load_geometry("no_such_scene_name")
    assert_one_line_naming(error, "no_such_scene_name")


# --- bad inputs ---------------------------------------------------------------------------------


def test_missing_file(tmp_path):
    path = tmp_path / "missing.obj"
    with pytest.raises(GeometryError, match="no such file") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


def test_directory(tmp_path):
    with pytest.raises(GeometryError, match="directory") as error:
        load_geometry(tmp_path)
    assert_one_line_naming(error, tmp_path)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root reads any file")
def test_unreadable_file(tmp_path):
    path = write_obj(tmp_path / "locked.obj", np.eye(3), [[0, 1, 2]])
    path.chmod(0)
    with pytest.raises(GeometryError, match="cannot read") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


@pytest.mark.parametrize("name", ["empty.obj", "empty.ply", "empty.stl", "empty.glb"])
def test_empty_files(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(GeometryError, match="empty") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


def test_obj_without_faces(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("# only vertices\nv 0 0 0\nv 1 0 0\n")
    with pytest.raises(GeometryError, match="no triangles") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


@pytest.mark.parametrize("name", ["cloud.xyz", "mesh.fbx", "noextension"])
def test_unsupported_format(tmp_path, name):
    path = tmp_path / name
    path.write_text("0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(GeometryError, match="unsupported mesh format") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


@pytest.mark.parametrize("name", ["garbage.ply", "garbage.obj", "garbage.stl", "garbage.glb", "garbage.off"])
def test_garbage_bytes(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(7).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(GeometryError) as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


def test_malformed_obj_lines_name_the_line(tmp_path):
    cases = {
        "index.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n", "line 5"),
        "relative.obj": ("v 0 0 0\nv 1 0 0\nf -1 -2 -3\nv 0 1 0\n", "line 3"),
        "zero.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "line 4"),
        "coordinate.obj": ("v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\n", "line 2"),
        "short.obj": ("v 0 0\n", "line 1"),
        "corner.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 x/3\n", "line 5"),
    }
    for name, (text, where) in cases.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(GeometryError, match=where) as error:
            load_geometry(path)
        assert_one_line_naming(error, path)


def test_nan_everywhere(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v nan nan nan\nv nan 0 0\nv inf 1 0\nf 1 2 3\n")
    with pytest.raises(GeometryError, match="NaN") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)


def test_all_degenerate(tmp_path):
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(GeometryError, match="degenerate") as error:
        load_geometry(path)
    assert_one_line_naming(error, path)
