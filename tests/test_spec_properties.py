"""Property tests of the build-spec reader: any JSON value in any field gives a SpecError or a
valid BuildSpec (which round-trips), never another exception."""

import json
import math

import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from prt.runtime.errors import SpecError  # noqa: E402
from prt.train.build import _TYPES, BuildSpec, load_spec, spec_from_dict  # noqa: E402

FIELDS = sorted(_TYPES)
SCALARS = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.sampled_from(["tet.obj", "", "\x00", "auto", "texture", "diffuse", "glossy"])
)
JSON = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.sampled_from(["hidden", "layers", "pos_freqs", "normal_freqs", "type", "albedo", "specular", "exponent", "eye", "target", "up", "fov"]) | st.text(max_size=8), inner, max_size=5),
    max_leaves=20,
)
PROFILE = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _check(data):
    try:
        spec = spec_from_dict(data)
    except SpecError as exc:
        message = str(exc)
        assert message and "\n" not in message
        return None
    assert isinstance(spec, BuildSpec)
    again = spec_from_dict(spec.to_dict())  # a valid spec is valid as written back
    assert json.dumps(again.to_dict(), sort_keys=True) == json.dumps(spec.to_dict(), sort_keys=True)
    for key in ("lr", "target", "match_tolerance", "delta", "merge_tolerance"):
        assert math.isfinite(spec.to_dict()[key])
    return spec


@PROFILE
@given(field=st.sampled_from(FIELDS), value=JSON)
def test_any_value_in_any_field(field, value):
    _check({"geometry": "tet.obj", field: value})


@PROFILE
@given(data=st.dictionaries(st.sampled_from(FIELDS) | st.text(max_size=10), JSON, max_size=8))
def test_any_object_of_fields(data):
    _check(data)


@PROFILE
@given(data=JSON)
def test_any_json_value_at_the_top(data):
    _check(data)


@settings(max_examples=150, deadline=None)
@given(raw=st.binary(max_size=200) | JSON.map(lambda v: json.dumps({"geometry": "tet.obj", "ladder": v}).encode()))
def test_any_file_content(tmp_path_factory, raw):
    path = tmp_path_factory.mktemp("spec") / "spec.json"
    path.write_bytes(raw)
    try:
        spec = load_spec(path)
    except SpecError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc)
    else:
        assert isinstance(spec, BuildSpec)
