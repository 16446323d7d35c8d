"""Property tests of the manifest reader: any JSON value in any field of a valid manifest gives a
project error (SpecError, one line) or a valid Manifest, never another exception; and a valid
Manifest is one the renderer's own checks accept (camera, material, lighting)."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prt.runtime.camera import Camera
from prt.runtime.errors import SpecError
from prt.runtime.manifest import Manifest, load_manifest
from prt.runtime.shading import Lighting, Material

sys.path.insert(0, str(Path(__file__).resolve().parent / "hostile"))
from cases_runtime import MANIFEST, SCENE_FILES  # noqa: E402  (the corpus's tiny valid scene)

EXAMPLES = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _field_paths(value, prefix=()) -> list[tuple]:
    """Every field path of a JSON value, the value itself (``()``) included."""
    paths = [prefix]
    if isinstance(value, dict):
        for key, item in value.items():
            paths += _field_paths(item, prefix + (key,))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            paths += _field_paths(item, prefix + (i,))
    return paths


PATHS = _field_paths(MANIFEST)
# Values a careless or hostile person writes: wrong types, extremes, paths that escape or hide.
SPECIAL = st.sampled_from([
    None, True, 0, -1, 1, 3, 4, 16, 2**63, 2**64, -(2**70), 1e39, -1e39, 1e308, 3.4e38, 1e-45, -0.0, 0.5,
    float("nan"), float("inf"), "", "..", "../scene.json", "/etc/passwd", "C:\\x", "seg000.onnx", "geometry.npz",
    "seg000.onnx\x00", "a\nb", "\ud800", "mesh", "sdf", "network", "analytic", "glossy", [], {}, [0, 0, 0], [[0, 0, 0], [1, 1, 1]],
])  # fmt: skip
SCALARS = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12) | SPECIAL
JSON = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=4), max_leaves=12)


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("scene")
    for name, content in SCENE_FILES.items():
        (folder / name).write_bytes(content if isinstance(content, bytes) else content.encode())
    (folder / "scene.json").write_text(json.dumps(MANIFEST))
    return folder


def _assert_usable(m: Manifest) -> None:
    """What the renderer builds from a manifest accepts it (no exception of any kind)."""
    Camera.from_manifest(m.camera)
    mat = m.material
    Material(kind=mat.type, **{k: getattr(mat, k) for k in ("albedo", "specular", "exponent") if getattr(mat, k) is not None})
    if m.lighting.sh is not None:
        Lighting.from_sh(m.lighting.sh, rotation=m.lighting.rotation)
    assert m.segments and all(s.id == i for i, s in enumerate(m.segments))


def _check(data, folder: Path) -> None:
    try:
        manifest = Manifest.from_dict(data, folder / "scene.json")
    except SpecError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(str(folder / "scene.json"))
        return
    _assert_usable(manifest)


def test_the_valid_manifest_is_valid(scene_folder):
    _assert_usable(load_manifest(scene_folder))


@EXAMPLES
@given(path=st.sampled_from(PATHS), value=JSON)
def test_any_json_value_in_any_field(scene_folder, path, value):
    data = copy.deepcopy(MANIFEST)
    if not path:
        data = value
    else:
        parent = data
        for key in path[:-1]:
            parent = parent[key]
        parent[path[-1]] = value
    _check(data, scene_folder)


@EXAMPLES
@given(path=st.sampled_from([p for p in PATHS if p]), key=st.text(max_size=8), value=JSON, delete=st.booleans())
def test_fields_removed_or_added(scene_folder, path, key, value, delete):
    data = copy.deepcopy(MANIFEST)
    parent = data
    for k in path[:-1]:
        parent = parent[k]
    if delete:
        del parent[path[-1]]
    elif isinstance(parent[path[-1]], dict):
        parent[path[-1]][key] = value
    elif isinstance(parent[path[-1]], list):
        parent[path[-1]].append(value)
    _check(data, scene_folder)


@settings(max_examples=200, deadline=None)
@given(blob=st.binary(max_size=300) | st.text(max_size=300).map(str.encode))
def test_any_bytes_as_the_file(tmp_path_factory, blob):
    folder = tmp_path_factory.mktemp("bytes")
    (folder / "scene.json").write_bytes(blob)
    with pytest.raises(SpecError):  # nothing of 300 bytes is a valid manifest
        load_manifest(folder)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(min_value=0, max_value=len(json.dumps(MANIFEST))), junk=st.text(max_size=4))
def test_edited_text_of_a_valid_manifest(scene_folder, tmp_path_factory, cut, junk):
    text = json.dumps(MANIFEST)
    folder = tmp_path_factory.mktemp("edit")
    for name in SCENE_FILES:
        (folder / name).symlink_to(scene_folder / name)
    (folder / "scene.json").write_text(text[:cut] + junk + text[cut + 1 :], encoding="utf-8", errors="surrogatepass")
    try:
        _assert_usable(load_manifest(folder))
    except SpecError as exc:
        assert "\n" not in str(exc)
