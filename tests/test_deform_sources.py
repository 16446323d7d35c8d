"""Deformation sources (issue 24, the input side): mesh sequences, animated glTF, procedural
deformers, their normalisation and their one-line errors."""

from __future__ import annotations

import base64
import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from prt.runtime.errors import GeometryError, InputError, SpecError
from prt.train.deform.deform_sources import (
    bend,
    fold,
    load_gltf,
    load_sequence,
    make_sheet,
    orient_faces,
    parse_deform,
    procedural,
    twist,
)
from prt.train.deform.gltf_animation import linear_blend_skinning, sample_channel

DATA = Path(__file__).parent / "data"
CHARACTER = DATA / "character" / "minetest_character.glb"

# --------------------------------------------------------------------------------------------
# Writing small glTF files by hand (independent of the library's writer)

_CODES = {np.dtype("float32"): 5126, np.dtype("uint16"): 5123, np.dtype("uint32"): 5125, np.dtype("uint8"): 5121}
_TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


def _pack(arrays: list[np.ndarray]) -> tuple[list, list, bytes]:
    """Buffer views, accessors and the buffer bytes of arrays (one accessor each, 4-byte aligned)."""
    views, accessors, blob = [], [], b""
    for index, array in enumerate(arrays):
        array = array.reshape(len(array), -1)
        data = array.tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        accessors.append(
            {"bufferView": index, "componentType": _CODES[array.dtype], "count": len(array), "type": _TYPES[array.shape[1]]}
        )
        blob += data + b"\0" * ((-len(data)) % 4)
    return views, accessors, blob


def _write(path: Path, document: dict, arrays: list[np.ndarray], how: str = "glb") -> Path:
    """Write ``document`` with ``arrays`` as accessors 0.. as a GLB, or a .gltf (base64 or .bin)."""
    views, accessors, blob = _pack(arrays)
    document = dict(document, asset={"version": "2.0"}, bufferViews=views, accessors=accessors + document.get("accessors", []))
    if how == "glb":
        document["buffers"] = [{"byteLength": len(blob)}]
        text = json.dumps(document).encode()
        text += b" " * ((-len(text)) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(blob), 0x004E4942) + blob
        path.write_bytes(struct.pack("<III", 0x46546C67, 2, 12 + len(body)) + body)
    elif how == "base64":
        uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path.write_text(json.dumps(dict(document, buffers=[{"byteLength": len(blob), "uri": uri}])))
    else:
        path.with_suffix(".bin").write_bytes(blob)
        path.write_text(json.dumps(dict(document, buffers=[{"byteLength": len(blob), "uri": path.with_suffix(".bin").name}])))
    return path


def _rz(degrees: float) -> np.ndarray:
    """Rotation about +z."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _bar() -> tuple[np.ndarray, np.ndarray]:
    """A square tube from y = 0 to y = 2 in rings at y = 0, 0.5, ..., 2 (open ends)."""
    ring = np.array([[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1], [-0.1, 0.1]])
    levels = np.linspace(0, 2, 5)
    vertices = np.array([[x, y, z] for y in levels for x, z in ring])
    faces = []
    for k in range(4):
        for s in range(4):
            a, b = 4 * k + s, 4 * k + (s + 1) % 4
            faces += [[a, b + 4, b], [a, a + 4, b + 4]]
    return vertices, np.array(faces)


def _two_joint_document(interpolation: str = "LINEAR", animations: int = 1) -> tuple[dict, list]:
    """A bar skinned to two joints (the upper one at y = 1) whose upper joint turns 90 degrees about z over 1 s."""
    vertices, faces = _bar()
    y = vertices[:, 1]
    joints = np.zeros((len(vertices), 4), dtype=np.uint16)
    joints[:, 1] = 1
    weights = np.zeros((len(vertices), 4), dtype=np.float32)
    weights[:, 0] = np.where(y < 1, 1.0, np.where(y > 1, 0.0, 0.5))
    weights[:, 1] = 1 - weights[:, 0]
    inverse_bind = np.stack([np.eye(4), np.eye(4)])
    inverse_bind[1, 1, 3] = -1.0  # joint 2 sits at y = 1
    half = math.sqrt(0.5)
    arrays = [
        vertices.astype(np.float32),
        faces.astype(np.uint32).reshape(-1, 1),
        joints,
        weights,
        inverse_bind.transpose(0, 2, 1).reshape(2, 16).astype(np.float32),  # column-major
        np.array([0.0, 1.0], dtype=np.float32),
        np.array([[0, 0, 0, 1], [0, 0, half, half]], dtype=np.float32),
    ]
    document = {
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0, "skin": 0}, {"name": "root", "children": [2]}, {"name": "upper", "translation": [0, 1, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 2, "WEIGHTS_0": 3}, "indices": 1}]}],
        "skins": [{"joints": [1, 2], "inverseBindMatrices": 4}],
        "animations": [
            {
                "name": f"turn{i}" if i else "turn",
                "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}],
                "samplers": [{"input": 5, "output": 6, "interpolation": interpolation}],
            }
            for i in range(animations)
        ],
    }
    return document, arrays


def _expected_bend(vertices: np.ndarray, degrees: float) -> np.ndarray:
    """Per-vertex loop: weight-blend of the unmoved point and its turn about (0, 1, 0)."""
    result = np.zeros_like(vertices)
    for i, p in enumerate(vertices):
        w_upper = 0.0 if p[1] < 1 else (1.0 if p[1] > 1 else 0.5)
        turned = np.array([0, 1, 0]) + _rz(degrees) @ (p - np.array([0, 1, 0]))
        result[i] = (1 - w_upper) * p + w_upper * turned
    return result


# --------------------------------------------------------------------------------------------
# Skinning and sampling against plain twins


def test_linear_blend_skinning_matches_a_per_vertex_loop():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(50, 3))
    joints = rng.integers(0, 5, size=(50, 4))
    weights = rng.random((50, 4))
    weights /= weights.sum(axis=1, keepdims=True)
    matrices = np.tile(np.eye(4), (5, 1, 1))
    matrices[:, :3, :] = rng.normal(size=(5, 3, 4))
    fast = linear_blend_skinning(points, joints, weights, matrices)
    for v in range(len(points)):
        expected = np.zeros(3)
        for k in range(4):
            expected += weights[v, k] * (matrices[joints[v, k]] @ np.r_[points[v], 1.0])[:3]
        np.testing.assert_allclose(fast[v], expected, atol=1e-12)


def test_sampling_lerps_slerps_steps_and_holds_the_ends():
    times = np.array([1.0, 2.0, 4.0])
    values = np.array([[0.0, 0, 0], [2.0, 4, 6], [4.0, 4, 4]])
    np.testing.assert_allclose(sample_channel(times, values, 1.5, "LINEAR", False), [1, 2, 3])
    np.testing.assert_allclose(sample_channel(times, values, 3.0, "LINEAR", False), [3, 4, 5])
    np.testing.assert_allclose(sample_channel(times, values, 3.9, "STEP", False), [2, 4, 6])
    np.testing.assert_allclose(sample_channel(times, values, 0.0, "LINEAR", False), values[0])
    np.testing.assert_allclose(sample_channel(times, values, 9.0, "LINEAR", False), values[-1])
    # Identity to 90 degrees about z: a quarter of the way is 22.5 degrees, also when the second
    # key is written with the opposite sign (the same rotation: the shorter arc is taken).
    quarter_turn = np.array([0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    for sign in (1, -1):
        keys = np.stack([[0, 0, 0, 1.0], sign * quarter_turn])
        q = sample_channel(np.array([0.0, 1.0]), keys, 0.25, "LINEAR", True)
        expected = np.array([0, 0, math.sin(math.radians(11.25)), math.cos(math.radians(11.25))])
        np.testing.assert_allclose(q * np.sign(q[3]), expected, atol=1e-12)


# --------------------------------------------------------------------------------------------
# glTF


@pytest.mark.parametrize("how", ["glb", "base64", "bin"])
def test_two_joint_gltf_bends_by_90_degrees(tmp_path, how):
    document, arrays = _two_joint_document()
    path = _write(tmp_path / ("bar.glb" if how == "glb" else "bar.gltf"), document, arrays, how)
    source = load_gltf(path, frames=3)
    vertices = arrays[0].astype(np.float64)
    np.testing.assert_allclose(source.rest, vertices, atol=1e-6)
    np.testing.assert_allclose(source.parameters[:, 0], [0, 0.5, 1])
    for k, degrees in enumerate([0, 45, 90]):
        np.testing.assert_allclose(source.frames[k], _expected_bend(vertices, degrees), atol=1e-6)
    top = np.argmax(vertices[:, 1] + vertices[:, 0])  # (0.1, 2, z): the tip turns to (-1, 1.1)
    np.testing.assert_allclose(source.frames[-1, top, :2], [-1.0, 1.1], atol=1e-6)
    assert source.kind == "gltf" and source.parameter_names == ("time",)
    assert source.description["animation"] == "turn" and source.description["frames"] == 3
    json.dumps(source.description)


def test_gltf_time_range_and_step_interpolation(tmp_path):
    document, arrays = _two_joint_document("STEP")
    path = _write(tmp_path / "bar.glb", document, arrays)
    source = load_gltf(path, frames=4, time_range=(0.25, 1.0))
    np.testing.assert_allclose(source.parameters[:, 0], [0.25, 0.5, 0.75, 1.0])
    vertices = arrays[0].astype(np.float64)
    np.testing.assert_allclose(source.frames[2], vertices, atol=1e-6)  # before the second key: held
    np.testing.assert_allclose(source.frames[3], _expected_bend(vertices, 90), atol=1e-6)


def test_morph_targets_follow_the_weights_channel(tmp_path):
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    target0 = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0]], dtype=np.float32)
    arrays = [
        positions,
        target0,
        np.array([0.0, 2.0], dtype=np.float32),
        np.array([0, 0, 1, 0.5], dtype=np.float32),  # weights at t = 0 and t = 2
        np.array([2], dtype=np.uint16),  # sparse target 1: vertex 2 moves by (0, 0, 1)
        np.array([[0, 0, 1]], dtype=np.float32),
    ]
    sparse_target = {
        "componentType": 5126, "count": 3, "type": "VEC3",
        "sparse": {"count": 1, "indices": {"bufferView": 4, "componentType": 5123}, "values": {"bufferView": 5}},
    }
    document = {
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": [0, 0, 5]}],
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": 0}, "targets": [{"POSITION": 1}, {"POSITION": 6}]}], "weights": [0.2, 0.0]}
        ],
        "animations": [
            {
                "name": "m",
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
                "samplers": [{"input": 2, "output": 3}],
            }
        ],
        "accessors": [sparse_target],
    }
    source = load_gltf(_write(tmp_path / "morph.glb", document, arrays), frames=3)
    offset = np.array([0, 0, 5.0])
    target1 = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(source.rest, positions + 0.2 * target0 + offset, atol=1e-6)
    np.testing.assert_allclose(source.frames[1], positions + 0.5 * target0 + 0.25 * target1 + offset, atol=1e-6)
    np.testing.assert_allclose(source.frames[2], positions + target0 + 0.5 * target1 + offset, atol=1e-6)


def test_minetest_character_walks():
    source = load_gltf(CHARACTER, "walk", frames=8)
    assert source.rest.shape == (168, 3) and source.faces.shape == (84, 3) and source.frames.shape == (8, 168, 3)
    height = np.ptp(source.rest[:, 1])
    assert 16 < height < 18  # the model is 17 units tall, feet at 0
    motion = np.linalg.norm(source.frames - source.rest, axis=2)
    legs = source.rest[:, 1] < 6.3 - 1e-6
    head = source.rest[:, 1] > 12.6 + 1e-6
    assert motion[:, legs].max() > 0.2 * height  # the legs swing
    assert motion.max() < 0.5 * height  # and nothing flies off
    # The bind pose is the rest pose: the first walk key is a step away from it, not a jump.
    assert motion[0].max() < 0.01 * height
    assert motion[:, head].max() < motion[:, legs].max()
    # Closed boxes, wound outward: positive volume.
    corners = source.rest[source.faces]
    assert np.einsum("ij,ij->", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) > 0
    clips = {name: load_gltf(CHARACTER, name, frames=2) for name in ("stand", "sit", "lay", "mine", "walk_mine")}
    assert all(c.parameters[0, 0] == 0 for c in clips.values())
    assert np.ptp(clips["lay"].frames[-1][:, 1]) < 0.5 * height  # lying down


# --------------------------------------------------------------------------------------------
# Sequences


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    header = f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
    header += f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    body = [f"{float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices] + [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text(header + "\n".join(body) + "\n")


def _twisted_bar_frames(count: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    vertices, faces = _bar()
    return vertices, faces, [twist(vertices, 20.0 * k, 1) for k in range(count)]


def test_sequence_round_trip_in_natural_order(tmp_path):
    vertices, faces, frames = _twisted_bar_frames(11)
    for k, frame in enumerate(frames):
        writer = _write_ply if k == 4 else _write_obj
        writer(tmp_path / f"frame{k}.{'ply' if k == 4 else 'obj'}", frame.astype(np.float32).astype(np.float64), faces)
    (tmp_path / "notes.txt").write_text("not a frame")
    source = load_sequence(tmp_path)
    assert source.frame_names[:3] == ("frame0.obj", "frame1.obj", "frame2.obj") and source.frame_names[-1] == "frame10.obj"
    np.testing.assert_allclose(source.frames, np.stack(frames), atol=1e-6)
    np.testing.assert_allclose(source.rest, frames[0], atol=1e-6)
    np.testing.assert_array_equal(source.parameters[:, 0], np.arange(11))
    assert source.kind == "sequence" and source.description["rest"] == "frame0.obj"
    # A rest.obj is the rest pose and no frame.
    _write_obj(tmp_path / "rest.obj", vertices + 1.0, faces)
    with_rest = load_sequence(tmp_path)
    assert len(with_rest.frames) == 11 and "rest.obj" not in with_rest.frame_names
    np.testing.assert_allclose(with_rest.rest, vertices + 1.0, atol=1e-12)


def test_sequence_keeps_every_vertex(tmp_path):
    vertices, faces = _bar()
    duplicated = np.concatenate([vertices, vertices[:3]])  # coincident and unused vertices stay
    for k in range(2):
        _write_obj(tmp_path / f"f{k}.obj", duplicated + k, faces)
    source = load_sequence(tmp_path)
    assert source.rest.shape == duplicated.shape
    np.testing.assert_allclose(source.frames[1] - source.frames[0], 1.0)


# --------------------------------------------------------------------------------------------
# Procedural deformers


def test_fold_at_0_is_rest_and_at_180_lies_over_the_mirrored_half():
    radius = 0.08
    source = procedural("fold", [0, 90, 180], radius=radius)
    vertices, _ = make_sheet()
    np.testing.assert_array_equal(source.rest, vertices)
    np.testing.assert_allclose(source.frames[0], vertices, atol=1e-15)
    flat = source.frames[2]
    x = vertices[:, 0]
    past = x > math.pi * radius + 1e-9
    assert past.sum() > 0.3 * len(x)
    np.testing.assert_allclose(flat[past, 1], 2 * radius, atol=1e-12)  # a gap of twice the radius
    np.testing.assert_allclose(flat[past, 0], math.pi * radius - x[past], atol=1e-12)  # mirrored
    np.testing.assert_allclose(flat[past, 2], vertices[past, 2])
    np.testing.assert_array_equal(flat[x <= 0], vertices[x <= 0])  # the other half stays
    # Folding bends, never stretches: every edge keeps its length, and no crease is a kink.
    edges = source.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    for frame in source.frames:
        lengths = np.linalg.norm(frame[edges[:, 0]] - frame[edges[:, 1]], axis=1)
        rest_lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
        np.testing.assert_allclose(lengths, rest_lengths, rtol=0.02)
    assert _largest_dihedral(source.frames[2], source.faces) < 60.0


def _largest_dihedral(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Largest angle in degrees between the normals of two triangles sharing an edge."""
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    owners: dict = {}
    for f, face in enumerate(faces):
        for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            owners.setdefault((min(a, b), max(a, b)), []).append(f)
    pairs = np.array([o for o in owners.values() if len(o) == 2])
    cosines = np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]])
    return float(np.degrees(np.arccos(np.clip(cosines, -1, 1))).max())


def test_bend_puts_the_centre_line_on_an_arc_of_the_angle():
    line = np.stack([np.linspace(-1, 1, 41), np.zeros(41), np.zeros(41)], axis=1)
    bar = np.concatenate([line, line + [0, 0, 0.05], line - [0, 0, 0.05], line + [0, 0.01, 0]])  # x longest; z centred on 0
    bent = bend(bar, 90.0, axis=1)
    np.testing.assert_array_equal(bend(bar, 0.0, axis=1), bar)
    radius = 2.0 / math.radians(90.0)
    centre = np.array([0.0, 0.0, radius])  # the circle's centre in (x, y, z); y untouched
    middle = bent[:41]
    np.testing.assert_allclose(np.linalg.norm(middle[:, [0, 2]] - centre[[0, 2]], axis=1), radius, atol=1e-12)
    angles = np.degrees(np.arctan2(middle[:, 0], centre[2] - middle[:, 2]))
    np.testing.assert_allclose(angles[[0, 20, 40]], [-45, 0, 45], atol=1e-9)
    steps = np.linalg.norm(np.diff(middle, axis=0), axis=1)
    np.testing.assert_allclose(steps.sum(), 2 * radius * math.sin(math.radians(90) / 80) * 40, rtol=1e-12)
    np.testing.assert_array_equal(bent[:, 1], bar[:, 1])


def test_twist_turns_the_ends_by_the_angle_about_the_axis():
    vertices, _ = _bar()  # along y from 0 to 2, centred on x = z = 0
    twisted = twist(vertices, 180.0, axis=1)
    np.testing.assert_array_equal(twisted[:, 1], vertices[:, 1])
    np.testing.assert_allclose(np.linalg.norm(twisted[:, [0, 2]], axis=1), np.linalg.norm(vertices[:, [0, 2]], axis=1))
    bottom, top = vertices[:, 1] == 0, vertices[:, 1] == 2

    def turn(a, b):
        return np.degrees(np.arctan2(a[:, 0], a[:, 2]) - np.arctan2(b[:, 0], b[:, 2]))

    relative = (turn(twisted[top], vertices[top]) - turn(twisted[bottom], vertices[bottom])) % 360
    np.testing.assert_allclose(relative, 180.0, atol=1e-9)


def test_normalised_keeps_correspondence_and_bounds_every_frame():
    source = procedural("twist", [0, 90, 180], mesh=_bar(), axis="z")
    normal, transform = source.normalised()
    centre, scale = np.array(transform["centre"]), transform["scale"]
    np.testing.assert_allclose(normal.frames, (source.frames - centre) * scale)
    np.testing.assert_allclose(normal.rest, (source.rest - centre) * scale)
    every = np.concatenate([normal.rest[None], normal.frames]).reshape(-1, 3)
    assert np.abs(every).max() == pytest.approx(1.0) and np.all(np.abs(every) <= 1 + 1e-12)
    np.testing.assert_allclose(every.max(axis=0) + every.min(axis=0), 0, atol=1e-12)
    np.testing.assert_array_equal(normal.faces, source.faces)
    assert normal.frame_names == source.frame_names and normal.description == source.description
    with pytest.raises(ValueError):
        normal.frames[0, 0, 0] = 5.0  # read-only


def test_orientation_turns_a_split_cube_outward_without_touching_vertices():
    # A unit cube with 4 own vertices per side (as exporters split at UV seams), all wound inward.
    vertices, faces = [], []
    for axis in range(3):
        for side in (-0.5, 0.5):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            base = len(vertices)
            for a, b in ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)):
                p = np.zeros(3)
                p[axis], p[u], p[v] = side, a, b
                vertices.append(p)
            quad = [[base, base + 1, base + 2], [base, base + 2, base + 3]]
            outward = side > 0  # (u, v, axis) is right-handed: u x v = +axis
            faces += quad if not outward else [f[::-1] for f in quad]
    vertices, faces = np.array(vertices), np.array(faces)
    oriented = orient_faces(vertices, faces)
    corners = vertices[oriented]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert np.all(np.einsum("ij,ij->i", normals, corners.mean(axis=1)) > 0)
    np.testing.assert_array_equal(np.sort(oriented, axis=1), np.sort(faces, axis=1))


# --------------------------------------------------------------------------------------------
# The --deform spec


def test_parse_deform_builds_each_kind(tmp_path):
    fold_source = parse_deform("fold:angle=0..175,frames=5,radius=0.1", "sheet")
    np.testing.assert_allclose(fold_source.parameters[:, 0], np.linspace(0, 175, 5))
    assert fold_source.description["options"] == {"radius": 0.1} and fold_source.frame_names[-1] == "fold angle=175"
    mesh = tmp_path / "bar.obj"
    _write_obj(mesh, *_bar())
    bent = parse_deform("bend:angle=0..90,frames=3,axis=x", mesh)
    np.testing.assert_allclose(bent.frames[1], bend(bent.rest, 45.0, 0))
    assert len(parse_deform("twist:angle=0..180", mesh).frames) == 16  # default frame count
    document, arrays = _two_joint_document()
    glb = _write(tmp_path / "bar.glb", document, arrays)
    clip = parse_deform("gltf:animation=turn,frames=3,start=0.5", glb)
    np.testing.assert_allclose(clip.parameters[:, 0], [0.5, 0.75, 1.0])
    for k in range(2):
        _write_obj(tmp_path / f"seq{k}.obj", _bar()[0] * (1 + k), _bar()[1])
    (tmp_path / "bar.obj").unlink()
    (tmp_path / "bar.glb").unlink()
    assert parse_deform("sequence", tmp_path).frames.shape == (2, 20, 3)


# --------------------------------------------------------------------------------------------
# Bad input: one line, the right error, naming the file and field


def _one_line(error_type, call, *fragments):
    with pytest.raises(error_type) as caught:
        call()
    message = str(caught.value)
    assert "\n" not in message and all(f in message for f in fragments), message
    return message


def test_topology_changes_are_refused_naming_file_and_frame(tmp_path):
    vertices, faces, frames = _twisted_bar_frames(3)
    for k, frame in enumerate(frames):
        _write_obj(tmp_path / f"a{k}.obj", frame, faces)
    _write_obj(tmp_path / "a2.obj", np.concatenate([frames[2], [[0, 0, 0]]]), faces)
    _one_line(GeometryError, lambda: load_sequence(tmp_path), "a2.obj", "frame 2", "21 vertices", "a0.obj has 20")
    swapped = faces.copy()
    swapped[5] = swapped[5][[1, 0, 2]]
    _write_obj(tmp_path / "a2.obj", frames[2], swapped)
    _one_line(GeometryError, lambda: load_sequence(tmp_path), "a2.obj", "frame 2", "triangle 5")
    _write_obj(tmp_path / "a2.obj", frames[2], faces[:-1])
    _one_line(GeometryError, lambda: load_sequence(tmp_path), "a2.obj", "31 triangles")


def test_nan_vertices_are_refused_with_a_count(tmp_path):
    vertices, faces, frames = _twisted_bar_frames(3)
    frames[1][[2, 7]] = np.nan
    for k, frame in enumerate(frames):
        _write_obj(tmp_path / f"b{k}.obj", frame, faces)
    _one_line(GeometryError, lambda: load_sequence(tmp_path), "b1.obj", "frame 1", "2 of 20 vertices", "NaN")
    bad = vertices.copy()
    bad[0, 0] = np.inf
    _one_line(GeometryError, lambda: procedural("bend", [0, 10], mesh=(bad, faces), path="m.obj"), "m.obj", "1 of 20")


def test_gltf_animation_errors(tmp_path):
    document, arrays = _two_joint_document(animations=2)
    glb = _write(tmp_path / "bar.glb", document, arrays)
    _one_line(GeometryError, lambda: load_gltf(glb, "walk"), "bar.glb", "'walk'", "turn, turn1")
    _one_line(GeometryError, lambda: load_gltf(glb), "bar.glb", "2 animations", "turn, turn1")
    clips = "stand, sit, lay, walk, mine, walk_mine"
    _one_line(GeometryError, lambda: load_gltf(CHARACTER, "run"), "minetest_character.glb", clips)
    rigid = dict(document, nodes=[{"mesh": 0}] + document["nodes"][1:])
    del rigid["skins"]
    rigid_path = _write(tmp_path / "rigid.glb", rigid, arrays)
    _one_line(GeometryError, lambda: load_gltf(rigid_path, "turn"), "rigid.glb", "no skin and no morph targets")
    cubic, cubic_arrays = _two_joint_document("CUBICSPLINE")
    cubic_path = _write(tmp_path / "cubic.glb", cubic, cubic_arrays)
    _one_line(GeometryError, lambda: load_gltf(cubic_path), "cubic.glb", "CUBICSPLINE")
    broken = dict(document, nodes=[{"mesh": 3, "skin": 0}] + document["nodes"][1:])
    broken_path = _write(tmp_path / "broken.glb", broken, arrays)
    _one_line(GeometryError, lambda: load_gltf(broken_path, "turn"), "broken.glb", "malformed glTF")
    (tmp_path / "junk.glb").write_bytes(b"glTF\x02\x00\x00\x00")
    _one_line(GeometryError, lambda: load_gltf(tmp_path / "junk.glb"), "junk.glb")
    _one_line(SpecError, lambda: load_gltf(glb, "turn", frames=1), "frames")
    _one_line(SpecError, lambda: load_gltf(glb, "turn", time_range=(1.0, 0.5)), "bar.glb", "empty")
    _one_line(SpecError, lambda: load_gltf(glb, "turn", time_range=("a", 1)), "bar.glb", "time_range")


def test_folder_and_spec_errors(tmp_path):
    _one_line(GeometryError, lambda: load_sequence(tmp_path), str(tmp_path), "0 mesh frames")
    _write_obj(tmp_path / "only.obj", *_bar())
    _one_line(GeometryError, lambda: load_sequence(tmp_path), "1 mesh frames", "at least 2")
    _one_line(GeometryError, lambda: load_sequence(tmp_path / "only.obj"), "not a folder")
    mesh = str(tmp_path / "only.obj")
    _one_line(SpecError, lambda: parse_deform("melt:angle=0..9", mesh), "'melt'", "bend")
    _one_line(SpecError, lambda: parse_deform("bend:angle=0..x", mesh), "angle", "'x' is not a number")
    _one_line(SpecError, lambda: parse_deform("bend:angle=90", mesh), "angle", "not a range")
    _one_line(SpecError, lambda: parse_deform("bend:angle", mesh), "'angle' is not key=value")
    _one_line(SpecError, lambda: parse_deform("bend:frames=4", mesh), "angle: missing")
    _one_line(SpecError, lambda: parse_deform("twist:angle=0..9,frames=two", mesh), "frames", "not an integer")
    _one_line(SpecError, lambda: parse_deform("twist:angle=0..9,frames=1", mesh), "frames", ">= 2")
    _one_line(SpecError, lambda: parse_deform("twist:angle=0..9,axis=w", mesh), "axis", "'w'")
    _one_line(SpecError, lambda: parse_deform("fold:angle=0..9,colour=red", "sheet"), "'colour'", "radius")
    _one_line(SpecError, lambda: parse_deform("fold:angle=0..270", "sheet"), "0..180")
    _one_line(SpecError, lambda: parse_deform("fold:angle=0..90,radius=-1", "sheet"), "radius")
    _one_line(SpecError, lambda: parse_deform("sequence:frames=3", tmp_path), "unknown option 'frames'")
    _one_line(GeometryError, lambda: parse_deform("bend:angle=0..9", tmp_path / "none.obj"), "none.obj", "no such file")
    _one_line(SpecError, lambda: procedural("fold", [10]), "at least 2")
    assert issubclass(SpecError, InputError) and issubclass(GeometryError, InputError)


def test_gltf_cut_out_materials_are_named_as_drawn_opaque(tmp_path):
    """A skinned primitive with an alpha-masked material keeps its vertices (the skin's), so the
    deformable build cannot cut it: the source names it for the build's warning line."""
    document, arrays = _two_joint_document()
    plain = load_gltf(_write(tmp_path / "plain.glb", document, arrays, "glb"), frames=2)
    assert "drawn_opaque" not in plain.description
    document["materials"] = [{"alphaMode": "MASK", "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1]}}]
    document["meshes"][0]["primitives"][0]["material"] = 0
    masked = load_gltf(_write(tmp_path / "masked.glb", document, arrays, "glb"), frames=2)
    assert masked.description["drawn_opaque"] == ["mesh 0 primitive 0"]
    np.testing.assert_allclose(masked.rest, plain.rest)
