"""Mixed scenes (prt.train.inputs.mixed): spec parsing, composition, sampling, the combined tracer, the
manifest, depth compositing in the G-buffer and both backends."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("torch")

from prt.runtime.errors import SpecError  # noqa: E402
from prt.train.inputs.mixed import ObjectSpec, compose_objects, parse_objects, rotation_matrix  # noqa: E402

QUAD = Path(__file__).parent / "data" / "ground_quad.obj"


def _psnr(a, b):
    mse = float(((a.astype(np.float64) - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(float(b.max()) ** 2 / mse)


# ----- spec parsing ------------------------------------------------------------------------------


def test_objects_parse_with_defaults_and_unique_names():
    objects = parse_objects([{"mesh": "a/ground.obj"}, {"sdf": "sphere", "scale": 0.5}, {"sdf": "sphere", "rotate": [0, 90, 0]},
                             {"neural_sdf": "b/bunny.sdf.onnx", "name": "rabbit", "material": {"type": "diffuse", "albedo": [1, 0, 0]}}])  # fmt: skip
    assert [o.kind for o in objects] == ["mesh", "sdf", "sdf", "neural_sdf"]
    assert [o.name for o in objects] == ["ground", "sphere", "sphere_2", "rabbit"]
    assert objects[1].scale == 0.5 and objects[0].translate == (0.0, 0.0, 0.0) and objects[3].material["albedo"] == [1, 0, 0]
    again = parse_objects([o.to_dict() for o in objects])  # what build.json records reads back the same
    assert [o.to_dict() for o in again] == [o.to_dict() for o in objects]


@pytest.mark.parametrize(
    "entry, where",
    [
        ("sphere", "objects[1]: expected an object"),
        ({}, "objects[1]: expected exactly one of"),
        ({"sdf": "sphere", "mesh": "x.obj"}, "objects[1]: expected exactly one of"),
        ({"sdf": "spere"}, "objects[1].sdf: unknown SDF 'spere'"),
        ({"neural_sdf": "bunny.onnx"}, "objects[1].neural_sdf: expected a '*.sdf.onnx'"),
        ({"sdf": "sphere", "scale": 0}, "objects[1].scale:"),
        ({"sdf": "sphere", "scale": True}, "objects[1].scale:"),
        ({"sdf": "sphere", "translate": [0, 1]}, "objects[1].translate:"),
        ({"sdf": "sphere", "rotate": [0, float("nan"), 0]}, "objects[1].rotate:"),
        ({"sdf": "sphere", "material": {"type": "shiny"}}, "objects[1].material"),
        ({"sdf": "sphere", "colour": 1}, "objects[1].colour: unknown field"),
        ({"sdf": "sphere", "name": "ground"}, "objects[1].name: 'ground' names an earlier object"),
    ],
)
def test_bad_object_entries_are_one_line_errors_naming_the_field(entry, where):
    with pytest.raises(SpecError) as info:
        parse_objects([{"mesh": "ground.obj", "name": "ground"}, entry])
    message = str(info.value)
    assert where in message and "\n" not in message


def test_spec_file_errors_name_the_file_and_relative_paths_resolve(tmp_path):
    from prt.train.build import load_spec

    shutil.copy(QUAD, tmp_path / "quad.obj")
    spec = tmp_path / "scene.json"
    spec.write_text(json.dumps({"objects": [{"mesh": "quad.obj"}, {"sdf": "torus", "scale": -1}]}))
    with pytest.raises(SpecError, match=r"scene\.json: objects\[1\]\.scale: expected a finite number > 0"):
        load_spec(spec)
    spec.write_text(json.dumps({"objects": [{"mesh": "missing.obj"}]}))
    with pytest.raises(SpecError, match=r"scene\.json: objects\[0\]\.mesh: no such file"):
        load_spec(spec)
    spec.write_text(json.dumps({"objects": [{"mesh": "quad.obj"}, {"sdf": "torus"}]}))
    loaded = load_spec(spec)
    assert loaded.objects[0]["mesh"] == str(tmp_path / "quad.obj") and loaded.geometry == "mixed"


def test_rotation_order_is_x_then_y_then_z():
    r = rotation_matrix([90, 90, 0])
    # x first: +y -> +z, then y: +z -> +x
    np.testing.assert_allclose(r @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)


# ----- composition and sampling ------------------------------------------------------------------


@pytest.fixture(scope="module")
def composed():
    objects = [
        ObjectSpec("mesh", str(QUAD), "ground", translate=(0.0, -0.5, 0.0)),
        ObjectSpec("sdf", "sphere", "ball", scale=0.3, translate=(0.4, -0.2, 0.0)),
        ObjectSpec("sdf", "torus", "ring", scale=0.3, rotate=(90.0, 0.0, 0.0), translate=(-0.4, -0.2, 0.0)),
    ]
    return compose_objects(objects, sdf_resolution=40)


def test_composition_fits_the_scene_box_and_places_sdfs_like_their_proxies(composed):
    g = composed
    assert g.kind == "mixed" and g.object_names == ["ground", "ball", "ring"] and g.mixed.kinds == ["mesh", "sdf", "sdf"]
    bounds = g.mesh.bounds
    assert np.abs(bounds).max() <= 0.95 + 1e-9 and np.isclose(np.abs(bounds).max(axis=0).max(), 0.95)
    # every proxy vertex lies close to the zero set of its own object's field (same placement)
    for k, sdf in g.mixed.sdfs.items():
        faces = np.asarray(g.mesh.faces)[(g.object_ids == k) & g.mixed.proxy_faces]
        assert len(faces) and np.abs(sdf.evaluate(g.mesh.vertices[np.unique(faces)])).max() < 0.03
    # the ball: unit sphere scaled by 0.3 and the global fit
    fit = 1.0 / g.to_source[0, 0]
    centre = (np.array([0.4, -0.2, 0.0]) - g.to_source[:3, 3]) * fit
    assert np.isclose(g.mixed.sdfs[1].evaluate(centre[None])[0], -0.3 * fit, atol=1e-6)


def test_sampling_is_area_uniform_and_projects_onto_each_objects_zero_set(composed):
    from prt.train.inputs.sampling import sample_surface

    g = composed
    s = sample_surface(g, 20_000, seed=3)
    area = np.bincount(g.object_ids, weights=g.mesh.area_faces, minlength=3)
    counts = np.bincount(s.object_ids, minlength=3)
    expected = area / area.sum() * len(s)
    assert np.all(np.abs(counts - expected) < 4 * np.sqrt(expected) + 5)
    for k, sdf in g.mixed.sdfs.items():
        mine = s.object_ids == k
        assert np.abs(sdf.evaluate(s.points[mine].astype(np.float64))).max() < 1e-4
        np.testing.assert_allclose(s.normals[mine], sdf.normals(s.points[mine].astype(np.float64)), atol=1e-3)
    ground = s.object_ids == 0
    assert np.ptp(s.points[ground, 1]) < 1e-6 and np.allclose(np.abs(s.normals[ground, 1]), 1.0)


def test_combined_tracer_agrees_with_embree_on_a_mesh_twin(composed):
    from prt.train.transport.transfer import EmbreeTracer, MixedTracer, make_tracer

    g = composed
    tracer = make_tracer(g)
    assert isinstance(tracer, MixedTracer)
    # twin: the mesh objects plus fine marching-cubes meshes of the SDF objects, all in Embree
    pieces = [trimesh.Trimesh(g.mesh.vertices, np.asarray(g.mesh.faces)[~g.mixed.proxy_faces], process=False)]
    pieces += [sdf.to_mesh(resolution=120) for sdf in g.mixed.sdfs.values()]
    twin = EmbreeTracer(trimesh.util.concatenate(pieces))
    rng = np.random.default_rng(0)
    n = 6000
    origins = rng.uniform(-0.9, 0.9, (n, 3)).astype(np.float32)
    outside = np.min([sdf.evaluate(origins) for sdf in g.mixed.sdfs.values()], axis=0) > 0.02
    origins = origins[outside]
    dirs = rng.normal(size=(len(origins), 3)).astype(np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hit, reference = tracer.occluded(origins, dirs), twin.occluded(origins, dirs)
    assert np.mean(hit == reference) > 0.99
    # both halves of the OR are exercised: rays only a mesh blocks and rays only an SDF blocks
    mesh_only = tracer.mesh.occluded(origins, dirs) & ~tracer.sdf.occluded(origins, dirs)
    sdf_only = ~tracer.mesh.occluded(origins, dirs) & tracer.sdf.occluded(origins, dirs)
    assert mesh_only.sum() > 100 and sdf_only.sum() > 100 and hit[mesh_only].all() and hit[sdf_only].all()


def test_mixed_glsl_matches_numpy_distance_and_object(composed, gl_ctx):
    from prt.runtime.gl import run_fragment_program

    parts = composed.mixed
    p = np.random.default_rng(4).uniform(-1.0, 1.0, (3000, 3)).astype(np.float32)
    main = "void main() { float d = scene_sdf(prt_input().xyz); f_out = vec4(d, float(prt_scene_object), 0.0, 0.0); }\n"
    out = run_fragment_program(gl_ctx, parts.glsl() + main, p, components=2)
    np.testing.assert_allclose(out[:, 0], parts.union().evaluate(p), atol=1e-5)
    assert np.mean(out[:, 1].astype(int) == parts.nearest_object(p)) > 0.999  # ties at equal distance aside


# ----- a tiny build: manifest, G-buffer compositing, backends --------------------------------------

WALL_SPEC = {
    "objects": [
        {"mesh": str(QUAD), "name": "wall", "scale": 0.5, "rotate": [90, 0, 0], "translate": [-0.25, 0.0, 0.0]},
        {"sdf": "sphere", "name": "back", "scale": 0.3, "translate": [0.3, 0.05, -0.5]},
        {"sdf": "sphere", "name": "front", "scale": 0.25, "translate": [-0.5, -0.1, 0.4],
         "material": {"type": "diffuse", "albedo": [0.9, 0.3, 0.2]}},
    ],
    "camera": {"eye": [0.0, 0.0, 3.0], "target": [0.0, 0.0, 0.0], "fov": 40},
    "samples": 2000, "validation": 1000, "rays": 16, "segments": 2, "steps": 40, "batch": 512,
    "fixed": {"hidden": 8, "layers": 1},
}  # fmt: skip


@pytest.fixture(scope="module")
def wall_scene(tmp_path_factory):
    from prt.train.build import load_spec, run_build

    base = tmp_path_factory.mktemp("mixed_scene")
    spec = base / "spec.json"
    spec.write_text(json.dumps(WALL_SPEC))
    run_build(load_spec(spec), base / "scene", threads=1, progress=False, log=lambda *a: None)
    return base / "scene"


def test_manifest_round_trip_and_version(wall_scene, tmp_path):
    from prt.export.manifest import write_manifest
    from prt.runtime.manifest import FORMAT_VERSION, load_manifest

    m = load_manifest(wall_scene / "scene.json")
    assert m.geometry.type == "mixed" and m.geometry.kinds == ["mesh", "sdf", "sdf"]
    assert m.geometry.objects == ["wall", "back", "front"] and m.geometry.triangles == 2 and m.geometry.glsl.is_file()
    raw = json.loads((wall_scene / "scene.json").read_text())
    assert raw["version"] == FORMAT_VERSION - 1 == 2  # mixed geometry needs version 2; other scenes are still written as 1
    copy = tmp_path / "copy"
    shutil.copytree(wall_scene, copy)
    write_manifest(copy / "scene.json", load_manifest(copy / "scene.json"))
    again = load_manifest(copy / "scene.json")
    assert again.geometry.to_dict(again.root) == m.geometry.to_dict(m.root)
    # a mixed geometry under the old version number is refused in one line
    raw["version"] = 1
    (copy / "scene.json").write_text(json.dumps(raw))
    with pytest.raises(SpecError, match=r"scene\.json: version: 2 was expected"):
        load_manifest(copy / "scene.json")


def test_older_manifests_still_load():
    from prt.runtime.manifest import load_manifest

    path = Path(__file__).resolve().parents[1] / "runtime" / "data" / "demo" / "scene.json"
    assert json.loads(path.read_text())["version"] == 1
    m = load_manifest(path)
    assert m.geometry.type == "mesh" and m.geometry.glsl is None


def _ray_cast_twin(scene_dir, camera, size):
    """Object id per pixel (-1: miss) by exact ray casting: the wall's triangles and the spheres."""
    from prt.runtime.manifest import load_manifest

    m = load_manifest(scene_dir / "scene.json")
    record = json.loads((scene_dir / "mixed.json").read_text())
    dirs = camera.ray_directions(size, size).reshape(-1, 3)
    eye = np.asarray(camera.eye, dtype=np.float64)
    best = np.full(len(dirs), np.inf)
    ids = np.full(len(dirs), -1)
    with np.load(m.geometry.path) as data:
        tri = data["vertices"].astype(np.float64)[data["faces"]]
        owners = data["object_ids"]
    for (a, b, c), k in zip(tri, owners):  # Moller-Trumbore
        e1, e2 = b - a, c - a
        pv = np.cross(dirs, e2)
        det = pv @ e1
        inv = 1.0 / np.where(np.abs(det) > 1e-12, det, 1e-12)
        tv = eye - a
        u = (pv @ tv) * inv
        qv = np.cross(tv, e1)
        v = (dirs @ qv) * inv
        t = (qv @ e2) * inv
        ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < best)
        best[ok], ids[ok] = t[ok], k
    for k, entry in enumerate(record["objects"]):
        if entry["render"] != "sdf":
            continue
        centre, radius = np.asarray(entry["translate"]), entry["scale"]  # unit spheres
        oc = eye - centre
        b = dirs @ oc
        disc = b * b - (oc @ oc - radius * radius)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        ok = (disc > 0) & (t > 0) & (t < best)
        best[ok], ids[ok] = t[ok], k
    return ids.reshape(size, size)


def test_gbuffer_composites_meshes_and_sdfs_by_depth(wall_scene, gl_ctx):
    from prt.runtime.camera import Camera
    from prt.runtime.gbuffer import GBufferPass
    from prt.runtime.manifest import load_manifest

    m = load_manifest(wall_scene / "scene.json")
    camera = Camera.from_manifest(m)
    size = 64
    with GBufferPass(gl_ctx, m, size, size, object_materials=True) as gbuffer:
        gbuffer.render(camera)
        ids = gbuffer.read_material()[0].reshape(size, size)
        g = gbuffer.read(depth=True)
    twin = _ray_cast_twin(wall_scene, camera, size)
    assert np.mean(ids == twin) > 0.98
    # both orders happen: the wall hides part of the back sphere, the front sphere part of the wall
    record = json.loads((wall_scene / "mixed.json").read_text())
    back, front = (np.asarray(o["translate"]) for o in record["objects"][1:])
    assert back[2] < 0 < front[2]
    assert (twin == 0).sum() > 200 and (twin == 1).sum() > 50 and (twin == 2).sum() > 200
    for k in (0, 1, 2):
        assert np.mean(ids[twin == k] == k) > 0.95
    assert np.isfinite(g.position).all() and np.isfinite(g.normal).all() and np.isfinite(g.depth).all()
    assert (g.segment[g.covered] >= 0).all() and (g.segment[~g.covered] == -1).all()


def test_both_backends_render_the_mixed_scene_alike_without_nan(wall_scene, gl_ctx):
    from prt.runtime.camera import Camera
    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(wall_scene / "scene.json")
    images = {}
    for backend in ("onnx", "glsl"):
        with Renderer(scene, 48, 48, backend=backend, ctx=gl_ctx) as r:
            images[backend] = r.render()
            # grazing: the eye in the wall's plane, looking along it
            r.set_camera_object(Camera(eye=[-2.5, 0.0, 0.0], target=[0.0, 0.0, 0.0], up=[0, 1, 0], fov_y=40))
            grazing = r.render()
            assert np.isfinite(grazing).all()
    assert np.isfinite(images["glsl"]).all() and images["onnx"].max() > 0.05
    assert _psnr(images["glsl"], images["onnx"]) >= 60.0


def test_bounces_with_a_mixed_scene_is_a_one_line_error(tmp_path, capsys):
    from prt.train import train_cli

    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"objects": [{"mesh": str(QUAD)}, {"sdf": "sphere", "scale": 0.3}], "bounces": 1, "samples": 1000}))
    assert train_cli.main([str(spec), "-o", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "bounces: interreflection needs a triangle mesh" in err and "'mixed' is a mixed scene" in err and "\n" not in err


def test_bench_reference_rebuilds_the_same_tracer(wall_scene):
    """prt-bench's reference geometry (geometry.npz + mixed.json) traces exactly as the build's did."""
    from prt.bench.reference import load_scene_geometry
    from prt.runtime.manifest import load_manifest
    from prt.train.inputs.mixed import compose_objects, parse_objects
    from prt.train.transport.transfer import make_tracer

    geometry, info = load_scene_geometry(load_manifest(wall_scene / "scene.json"))
    assert geometry.kind == "mixed" and info["type"] == "mixed" and info["checksum"]
    built = compose_objects(parse_objects(WALL_SPEC["objects"]))  # the build's proxy resolution: the same global fit
    rng = np.random.default_rng(5)
    origins = rng.uniform(-1.0, 1.0, (3000, 3)).astype(np.float32)
    dirs = rng.normal(size=(3000, 3)).astype(np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ours, theirs = make_tracer(geometry).occluded(origins, dirs), make_tracer(built).occluded(origins, dirs)
    assert ours.any() and (~ours).any() and np.array_equal(ours, theirs)


def test_objects_of_meshes_only_compose_into_a_plain_mesh_scene():
    g = compose_objects([ObjectSpec("mesh", str(QUAD), "a"), ObjectSpec("mesh", str(QUAD), "b", scale=0.5, translate=(0.0, 1.0, 0.0))])
    assert g.kind == "mesh" and g.object_names == ["a", "b"] and np.bincount(g.object_ids).tolist() == [2, 2]
    assert np.isclose(np.ptp(g.mesh.vertices[:, 1]), 1.0 * 0.95)  # the global fit: largest half extent (x, z: 1) -> 0.95


def test_neural_object_is_skipped_by_its_box_bound_without_changing_the_field(tmp_path, gl_ctx):
    """A neural SDF object: numpy, the culled GLSL (network skipped where its box is farther than
    the nearest other object) and the objects agree; the box is a lower bound of the object."""
    from prt.runtime.gl import run_fragment_program
    from prt.train.inputs.mixed import _lower_bound
    from prt.train.sdf.neural import fit_neural_sdf

    net = tmp_path / "ball.sdf.onnx"
    fit_neural_sdf(trimesh.creation.icosphere(subdivisions=2, radius=0.8), net, size=(8, 2), samples=4000, steps=100, batch=1024,
                   log=lambda *a: None)  # fmt: skip
    g = compose_objects([ObjectSpec("mesh", str(QUAD), "ground", translate=(0.0, -0.5, 0.0)),
                         ObjectSpec("neural_sdf", str(net), "blob", scale=0.4, rotate=(0.0, 30.0, 0.0), translate=(-0.3, -0.1, 0.0)),
                         ObjectSpec("sdf", "sphere", "ball", scale=0.2, translate=(0.5, -0.3, 0.0))], sdf_resolution=24)  # fmt: skip
    parts = g.mixed
    p = np.random.default_rng(6).uniform(-1.0, 1.0, (4000, 3)).astype(np.float32)
    bound = _lower_bound(parts.sdfs[1])
    assert bound is not None and _lower_bound(parts.sdfs[2]) is None
    assert np.all(bound.evaluate(p.astype(np.float64)) <= parts.sdfs[1].evaluate(p.astype(np.float64)) + 1e-9)
    source = parts.glsl()
    assert "scene_sdf_o1_bound(p) < best" in source
    main = "void main() { float d = scene_sdf(prt_input().xyz); f_out = vec4(d, float(prt_scene_object), 0.0, 0.0); }\n"
    out = run_fragment_program(gl_ctx, source + main, p, components=2)
    np.testing.assert_allclose(out[:, 0], parts.union().evaluate(p), atol=2e-5)
    assert np.mean(out[:, 1].astype(int) == parts.nearest_object(p)) > 0.999
