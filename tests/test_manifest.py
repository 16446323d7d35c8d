"""Scene manifest: schema, writer/loader round trip, one-line errors, the k-d tree rule."""

from __future__ import annotations

import copy
import json
import os
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
from jsonschema import Draft202012Validator
from onnx import TensorProto, helper, numpy_helper

from prt.export.manifest import relative_to_scene, write_manifest
from prt.runtime.errors import InputError, SpecError
from prt.runtime.manifest import (
    DEFAULT_CAMERA,
    FORMAT,
    FORMAT_VERSION,
    GENERATOR,
    SCENE_SCHEMA,
    CameraInfo,
    LightingInfo,
    Manifest,
    MemoryInfo,
    load_manifest,
    validate_manifest_dict,
    validate_manifest_field,
)
from prt.runtime.segmentation import segment_of


def _write_onnx(path: Path) -> None:
    """A tiny real model: float32 [N, 6] -> [N, 16] through one MatMul."""
    weight = numpy_helper.from_array(np.ones((6, 16), dtype=np.float32), name="W")
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["x", "W"], ["transfer"])],
        "segment",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 6])],
        [helper.make_tensor_value_info("transfer", TensorProto.FLOAT, ["N", 16])],
        initializer=[weight],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


# Tree used by the round trip and segment_of tests.  Object 0:
#   node 0: x <= 0 ? node 1 : node 2
#   node 1: leaf 0 -> segment 0
#   node 2: y <= 0.5 ? node 3 : node 4
#   node 3: leaf 1 -> segment 1;  node 4: leaf 2 -> segment 0
# Object 1: node 5, leaf 3 -> segment 1.  Objects without a root: nearest segment box.
NODES = [
    {"axis": 0, "split": 0.0, "left": 1, "right": 2},
    {"leaf": 0},
    {"axis": 1, "split": 0.5, "left": 3, "right": 4},
    {"leaf": 1},
    {"leaf": 2},
    {"leaf": 3},
]


_SCENE = {
    "format": "prt-scene",
    "version": 1,
    "name": "bunny",
    "generator": "prt-train 0.1.0",
    "sh_bands": 4,
    "geometry": {
        "type": "mesh",
        "file": "geometry.npz",
        "to_source": [[2, 0, 0, 1], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]],
        "triangles": 12,
        "objects": ["body", "base"],
    },
    "segmentation": {"roots": {"0": 0, "1": 5}, "nodes": NODES, "leaf_segment": [0, 1, 0, 1]},
    "segments": [
        {
            "id": 0,
            "kind": "network",
            "model": "segments/seg000.onnx",
            "glsl": "segments/seg000.glsl",
            "bounds": [[-1.0, -1.0, -1.0], [-0.5, 1.0, 1.0]],
            "architecture": {"hidden": 64, "layers": 4, "pos_freqs": 6, "normal_freqs": 2, "input_dim": 54},
            "flops_per_fragment": 30000,
            "weight_bytes": 40000,
            "samples": 120000,
            "validation": {"coeff_mae": 0.003, "shaded_mae": {"studio": 0.01}},
        },
        {
            "id": 1,
            "kind": "analytic",
            "bounds": [[0.5, -1.0, -1.0], [1.0, 0.5, 1.0]],
            "samples": 5000,
            "validation": {"coeff_mae": 0.002, "shaded_mae": {}},
        },
    ],
    "lighting": {"envmap": "envmaps/sky.hdr", "sh": [[0.1, 0.2, 0.3]] * 16},
    "material": {"type": "glossy", "albedo": [0.8, 0.7, 0.6], "specular": [0.04, 0.04, 0.04], "exponent": 32},
    "camera": {"eye": [0.0, 1.0, 3.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov": 45.0},
    "memory": {"weight_bytes": 40000, "vertex_storage_bytes": 456},
}


def _scene_data() -> dict:
    """A fresh copy of the valid manifest (tests edit it freely)."""
    return copy.deepcopy(_SCENE)


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    """A valid scene folder with real files; returns the folder (scene.json written)."""
    root = tmp_path / "scene"
    (root / "segments").mkdir(parents=True)
    (root / "envmaps").mkdir()
    _write_onnx(root / "segments" / "seg000.onnx")
    (root / "segments" / "seg000.glsl").write_text("vec4 seg000(vec3 p, vec3 n) { return vec4(0.0); }\n")
    np.savez(root / "geometry.npz", vertices=np.zeros((8, 3), np.float32), faces=np.zeros((12, 3), np.int32))
    (root / "envmaps" / "sky.hdr").write_bytes(b"#?RADIANCE\n")
    write_manifest(root / "scene.json", _scene_data())
    return root


def _edit(root: Path, change) -> Path:
    """Rewrite scene.json after applying ``change`` to its dict (bypassing the writer's checks)."""
    path = root / "scene.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))
    return path


def _spec_error(path: Path) -> str:
    with pytest.raises(SpecError) as info:
        load_manifest(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: ")
    return message


# --------------------------------------------------------------------------- schema / round trip


def test_schema_is_valid_draft_2020_12():
    Draft202012Validator.check_schema(SCENE_SCHEMA)
    assert SCENE_SCHEMA["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    # the schema pins the format the model writes
    assert SCENE_SCHEMA["properties"]["format"]["const"] == FORMAT
    # version 2 adds mixed geometry; other scenes keep writing 1, so older runtimes read them
    assert SCENE_SCHEMA["properties"]["version"]["enum"] == [1, 2, FORMAT_VERSION] and FORMAT_VERSION == 3  # 3: deformable objects


def test_round_trip(scene: Path):
    m = load_manifest(scene / "scene.json")
    assert isinstance(m, Manifest)
    assert m.raw == _scene_data()
    root = scene.resolve()
    assert m.root == root and m.path == root / "scene.json"
    assert m.name == "bunny" and m.generator == "prt-train 0.1.0" and m.sh_bands == 4

    assert m.geometry.type == "mesh" and m.geometry.objects == ["body", "base"]
    assert m.geometry.path == root / "geometry.npz" and m.geometry.triangles == 12
    np.testing.assert_array_equal(m.geometry.to_source, _SCENE["geometry"]["to_source"])
    seg0, seg1 = m.segments
    assert seg0.model == root / "segments" / "seg000.onnx" and seg0.model.is_absolute()
    assert seg0.glsl == root / "segments" / "seg000.glsl"
    assert seg0.is_network and seg0.architecture["input_dim"] == 54
    assert (seg0.flops_per_fragment, seg0.weight_bytes, seg0.samples) == (30000, 40000, 120000)
    np.testing.assert_array_equal(seg0.bounds, [[-1, -1, -1], [-0.5, 1, 1]])
    assert seg0.validation == {"coeff_mae": 0.003, "shaded_mae": {"studio": 0.01}}
    assert seg1.kind == "analytic" and seg1.model is None and seg1.glsl is None and seg1.architecture is None
    assert (seg1.flops_per_fragment, seg1.weight_bytes) == (0, 0)
    assert m.bounds.shape == (2, 2, 3)

    assert m.segmentation["roots"] == {0: 0, 1: 5}
    assert m.segmentation["leaf_segment"].tolist() == [0, 1, 0, 1]
    assert m.lighting.envmap == root / "envmaps" / "sky.hdr"
    assert m.lighting.sh.shape == (16, 3) and m.lighting.rotation is None
    assert m.material.type == "glossy" and m.material.exponent == 32.0
    np.testing.assert_array_equal(m.material.albedo, [0.8, 0.7, 0.6])
    np.testing.assert_array_equal(m.camera.eye, [0, 1, 3])
    assert m.camera.fov == 45.0
    assert m.memory == MemoryInfo(weight_bytes=40000, vertex_storage_bytes=456)
    for p in [m.geometry.path, seg0.model, seg0.glsl, m.lighting.envmap]:
        assert p.is_absolute() and p.is_relative_to(root) and p.is_file()


def test_loading_the_folder_and_optional_fields(scene: Path):
    def drop_optional(d):
        del d["camera"], d["memory"], d["generator"], d["lighting"]["envmap"], d["lighting"]["sh"]
        del d["segments"][0]["glsl"]

    _edit(scene, drop_optional)
    m = load_manifest(scene)  # the folder works as well as the file
    assert m.generator is None and m.memory is None and m.segments[0].glsl is None
    assert m.lighting == LightingInfo(envmap=None, sh=None, rotation=None)
    np.testing.assert_array_equal(m.camera.eye, DEFAULT_CAMERA["eye"])
    np.testing.assert_array_equal(m.camera.up, (0, 1, 0))
    assert m.camera.fov == 40.0


def test_written_file_is_ordered_stable_and_atomic(scene: Path):
    path = scene / "scene.json"
    text = path.read_text()
    assert list(json.loads(text))[:5] == ["format", "version", "name", "generator", "sh_bands"]
    assert '"bounds": [[-1.0, -1.0, -1.0], [-0.5, 1.0, 1.0]]' in text  # short arrays on one line
    shuffled = dict(reversed(list(_scene_data().items())))
    write_manifest(scene, shuffled)  # a folder names scene.json inside it
    assert path.read_text() == text
    assert sorted(p.name for p in scene.iterdir()) == ["envmaps", "geometry.npz", "scene.json", "segments"]


def test_model_round_trip_is_byte_identical(scene: Path, tmp_path: Path):
    """load -> to_dict -> write gives the same bytes; the writer accepts the model itself."""
    path = scene / "scene.json"
    text = path.read_text()
    m = load_manifest(scene)
    assert m.to_dict() == _scene_data() and m.generator == GENERATOR  # ints come back as floats
    write_manifest(path, m)
    once = path.read_text()
    assert json.loads(once) == json.loads(text)
    write_manifest(path, load_manifest(scene))
    assert path.read_text() == once
    # Written elsewhere, the model's files are referenced relative to the new folder.
    other = tmp_path / "other"
    other.mkdir()
    write_manifest(other / "scene.json", m, check_files=False)
    raw = json.loads((other / "scene.json").read_text())
    assert raw["segments"][0]["model"] == os.path.relpath(m.segments[0].model, other.resolve())


def test_demo_scene_round_trips_byte_identical(tmp_path: Path):
    demo = tmp_path / "demo"
    shutil.copytree(Path(__file__).resolve().parents[1] / "runtime" / "data" / "demo", demo)
    text = (demo / "scene.json").read_bytes()
    write_manifest(demo / "scene.json", load_manifest(demo))
    assert (demo / "scene.json").read_bytes() == text


def test_model_defaults_and_part_checks():
    camera = CameraInfo()
    assert camera.to_dict() == {k: list(v) if isinstance(v, tuple) else v for k, v in DEFAULT_CAMERA.items()}
    validate_manifest_field("camera", {"fov": 30.0})
    with pytest.raises(SpecError, match=r"^out/scene\.json: material: 'albedo' is a required property$"):
        validate_manifest_field("material", {"type": "diffuse"}, "out/scene.json")
    data = _scene_data()
    del data["material"]["albedo"]
    with pytest.raises(SpecError, match=r"^scene\.json: material: 'albedo' is a required property$"):
        validate_manifest_dict(data)  # the same message as for the whole manifest


def test_writer_converts_numpy_and_paths(scene: Path):
    data = _scene_data()
    data["segments"][0]["bounds"] = np.array(data["segments"][0]["bounds"], dtype=np.float64)
    data["segments"][0]["samples"] = np.int64(120000)
    data["segments"][0]["model"] = Path("segments") / "seg000.onnx"
    data["segmentation"]["roots"] = {np.int64(0): 0, 1: np.int32(5)}
    data["lighting"]["sh"] = np.full((16, 3), 0.1, dtype=np.float32)
    write_manifest(scene / "scene.json", data)
    raw = load_manifest(scene).raw
    assert raw["segmentation"]["roots"] == {"0": 0, "1": 5}
    assert raw["segments"][0]["model"] == "segments/seg000.onnx"
    assert raw["segments"][0]["bounds"] == _scene_data()["segments"][0]["bounds"]


def test_writer_checks_before_writing(scene: Path):
    path = scene / "scene.json"
    before = path.read_text()
    bad = _scene_data()
    bad["segments"][1]["kind"] = "netwrk"
    with pytest.raises(SpecError, match=r"segments\[1\]\.kind: 'netwrk' is not one of"):
        write_manifest(path, bad)
    missing = _scene_data()
    missing["segments"][0]["model"] = "segments/nope.onnx"
    with pytest.raises(SpecError, match=r"segments\[0\]\.model: file 'segments/nope.onnx' does not exist"):
        write_manifest(path, missing)
    nan = _scene_data()
    nan["segments"][0]["validation"]["coeff_mae"] = float("nan")
    with pytest.raises(SpecError, match=r"segments\[0\]\.validation\.coeff_mae: non-finite"):
        write_manifest(path, nan)
    assert path.read_text() == before
    assert len(list(scene.iterdir())) == 4  # no temporary left behind
    write_manifest(path, missing, check_files=False)  # allowed when the files come later
    with pytest.raises(SpecError, match="does not exist"):
        load_manifest(path)


def test_validate_manifest_dict_in_memory():
    validate_manifest_dict(_scene_data())
    data = _scene_data()
    data["sh_bands"] = 3
    with pytest.raises(SpecError, match=r"^scene\.json: lighting\.sh: expected 9 rows \(sh_bands 3\), got 16$"):
        validate_manifest_dict(data)
    with pytest.raises(SpecError, match=r"^mine\.json: \(top level\): \[\] is not of type 'object'$"):
        validate_manifest_dict([], source="mine.json")


# --------------------------------------------------------------------------- load errors


def test_missing_manifest(tmp_path: Path):
    path = tmp_path / "scene.json"
    assert _spec_error(path) == f"{path}: manifest not found"


def test_bad_json_gives_line_and_column(scene: Path):
    path = scene / "scene.json"
    path.write_text('{\n  "format": "prt-scene",\n  "version" 1\n}\n')
    assert "invalid JSON at line 3, column 13" in _spec_error(path)


def test_non_finite_numbers_are_rejected(scene: Path):
    path = scene / "scene.json"
    path.write_text(path.read_text().replace('"coeff_mae": 0.003', '"coeff_mae": NaN'))
    assert "non-finite number NaN" in _spec_error(path)


# (edit of the dict, expected "field: message" after the file name)
SCHEMA_AND_SEMANTIC_CASES = {
    "wrong version": (lambda d: d.update(version=2), "version: 1 was expected"),
    "unknown kind": (
        lambda d: d["segments"][1].update(kind="netwrk"),
        "segments[1].kind: 'netwrk' is not one of ['network', 'analytic']",
    ),
    "network without model": (
        lambda d: d["segments"][0].pop("model"),
        "segments[0]: 'model' is a required property",
    ),
    "analytic with model": (
        lambda d: d["segments"][1].update(model="segments/seg000.onnx"),
        "segments[1].model: not allowed here",
    ),
    "unknown field": (
        lambda d: d["material"].update(roughness=0.5),
        "material: Additional properties are not allowed ('roughness' was unexpected)",
    ),
    "fov out of range": (lambda d: d["camera"].update(fov=180), "camera.fov: 180 is greater than or equal to"),
    "ids out of order": (lambda d: d["segments"][1].update(id=2), "segments[1].id: expected 1"),
    "leaf_segment to missing segment": (
        lambda d: d["segmentation"]["leaf_segment"].__setitem__(2, 7),
        "segmentation.leaf_segment[2]: segment 7 does not exist (there are 2)",
    ),
    "bad child index": (
        lambda d: d["segmentation"]["nodes"][2].update(right=9),
        "segmentation.nodes[2].right: node 9 does not exist (there are 6)",
    ),
    "bad leaf index": (
        lambda d: d["segmentation"]["nodes"][5].update(leaf=4),
        "segmentation.nodes[5].leaf: leaf 4 does not exist",
    ),
    "bad root": (
        lambda d: d["segmentation"]["roots"].update({"1": 6}),
        'segmentation.roots["1"]: node 6 does not exist',
    ),
    "cycle": (
        lambda d: d["segmentation"]["nodes"][2].update(left=0),
        "segmentation.nodes[2].left: node 0 is reached twice",
    ),
    "inverted bounds": (
        lambda d: d["segments"][0]["bounds"].reverse(),
        "segments[0].bounds: min corner",
    ),
    "up parallel to view": (
        lambda d: d["camera"].update(up=[0.0, -2.0, -6.0]),
        "camera.up: is zero or parallel to the view direction",
    ),
}


@pytest.mark.parametrize("case", list(SCHEMA_AND_SEMANTIC_CASES))
def test_invalid_manifest(scene: Path, case: str):
    change, expected = SCHEMA_AND_SEMANTIC_CASES[case]
    path = _edit(scene, change)
    message = _spec_error(path)
    assert message.startswith(f"{path}: {expected}"), message


def test_missing_model_file(scene: Path):
    (scene / "segments" / "seg000.onnx").unlink()
    message = _spec_error(scene / "scene.json")
    assert "segments[0].model: file 'segments/seg000.onnx' does not exist" in message


@pytest.mark.parametrize(
    "field, rel, expected",
    [
        ("model", "../escape.onnx", "segments[0].model: path '../escape.onnx' escapes the scene folder"),
        ("model", "segments/../../escape.onnx", "escapes the scene folder"),
        ("glsl", "/etc/passwd", "segments[0].glsl: path '/etc/passwd' is absolute"),
        ("model", "C:/models/seg.onnx", "is absolute"),
    ],
)
def test_paths_must_stay_inside(scene: Path, field: str, rel: str, expected: str):
    (scene.parent / "escape.onnx").write_bytes(b"")  # it exists: only its location is wrong
    path = _edit(scene, lambda d: d["segments"][0].update({field: rel}))
    assert expected in _spec_error(path)


def test_symlink_pointing_outside(scene: Path):
    outside = scene.parent / "outside.onnx"
    _write_onnx(outside)
    os.symlink(outside, scene / "segments" / "linked.onnx")
    path = _edit(scene, lambda d: d["segments"][0].update(model="segments/linked.onnx"))
    assert "segments[0].model: path 'segments/linked.onnx' escapes the scene folder" in _spec_error(path)
    # A symlinked folder escapes the same way.
    os.symlink(scene.parent, scene / "up")

    def through_folder_link(d):
        d["segments"][0]["model"] = "segments/seg000.onnx"
        d["lighting"]["envmap"] = "up/outside.onnx"

    path = _edit(scene, through_folder_link)
    assert "lighting.envmap: path 'up/outside.onnx' escapes the scene folder" in _spec_error(path)


def test_symlink_inside_is_fine(scene: Path):
    os.symlink(scene / "segments" / "seg000.onnx", scene / "alias.onnx")
    _edit(scene, lambda d: d["segments"][0].update(model="alias.onnx"))
    assert load_manifest(scene).segments[0].model == (scene / "segments" / "seg000.onnx").resolve()


# --------------------------------------------------------------------------- segment_of


def test_segment_of_matches_hand_computed_tree(scene: Path):
    m = load_manifest(scene)
    points = np.array(
        [
            [-0.3, 0.9, 0.0],  # object 0: x <= 0 -> leaf 0 -> segment 0
            [0.0, 0.9, 0.0],  # on the split plane goes left -> segment 0
            [0.4, 0.2, 0.0],  # x > 0, y <= 0.5 -> leaf 1 -> segment 1
            [0.4, 0.5, 0.0],  # y on the plane -> leaf 1 -> segment 1
            [0.4, 0.7, 0.0],  # y > 0.5 -> leaf 2 -> segment 0
            [-0.9, -0.9, 0.0],  # object 1: single leaf 3 -> segment 1
            [-0.6, 0.0, 0.0],  # object 7, no root: inside box 0 -> segment 0
            [0.9, 0.9, 0.0],  # object 7: 0.4 above box 1, 1.4 right of box 0 -> segment 1
        ]
    )
    ids = np.array([0, 0, 0, 0, 0, 1, 7, 7])
    expected = [0, 0, 1, 1, 0, 1, 0, 1]
    got = segment_of(m, points, ids)
    assert got.dtype == np.int64 and got.tolist() == expected
    # Order independence: the vectorised descent must not mix points up.
    perm = np.random.default_rng(0).permutation(len(ids))
    assert segment_of(m, points[perm], ids[perm]).tolist() == np.array(expected)[perm].tolist()
    assert segment_of(m, np.zeros((0, 3)), np.zeros(0, dtype=np.int64)).shape == (0,)


def test_segment_of_rejects_bad_shapes(scene: Path):
    m = load_manifest(scene)
    with pytest.raises(InputError, match=r"points must have shape \(N, 3\)"):
        segment_of(m, np.zeros((4, 2)), np.zeros(4, dtype=int))
    with pytest.raises(InputError, match="object_ids must have shape"):
        segment_of(m, np.zeros((4, 3)), np.zeros(3, dtype=int))


# --------------------------------------------------------------------------- relative_to_scene


def test_relative_to_scene(scene: Path):
    assert relative_to_scene(scene / "segments" / "seg000.onnx", scene) == "segments/seg000.onnx"
    with pytest.raises(SpecError, match="not a file inside the scene folder"):
        relative_to_scene(scene.parent / "escape.onnx", scene)
    with pytest.raises(SpecError, match="not a file inside the scene folder"):
        relative_to_scene(scene / ".." / "escape.onnx", scene)
    with pytest.raises(SpecError, match="not a file inside the scene folder"):
        relative_to_scene(scene, scene)
    os.symlink(scene.parent, scene / "up")
    with pytest.raises(SpecError, match="resolves outside the scene folder"):
        relative_to_scene(scene / "up" / "escape.onnx", scene)


def test_schema_and_data_are_not_mutated_by_loading(scene: Path):
    schema = copy.deepcopy(SCENE_SCHEMA)
    load_manifest(scene)
    assert SCENE_SCHEMA == schema
