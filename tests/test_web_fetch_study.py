"""studies/web_fetch_study.py's variants of a real page: each changes what it says and keeps the page's file table true."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

STUDIES = Path(__file__).resolve().parents[1] / "studies"


@pytest.fixture(scope="module")
def study(bench_module):
    sys.path.insert(0, str(STUDIES))  # the study imports its sibling `common`
    try:
        yield bench_module("web_fetch_study")
    finally:
        sys.path.remove(str(STUDIES))


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    from prt.export.web import write_web
    from prt.runtime.renderer import demo_scene_path

    out = tmp_path_factory.mktemp("web") / "page"
    write_web(demo_scene_path(), out)
    return out


@pytest.mark.parametrize("name", ["page", "computed weights", "half the fetches", "constant loop bounds", "integer texture", "fp16 pairs"])
def test_each_variant_changes_the_shader_as_named_and_keeps_the_file_table(study, page, tmp_path, name):
    out = tmp_path / "v"
    study.variant(page, out, name)
    web = json.loads((out / "web.json").read_text())
    for rel, size in web["files"].items():
        assert (out / rel).stat().st_size == size, rel
    base, text = (page / "shaders" / "transfer4.frag").read_text(), (out / "shaders" / "transfer4.frag").read_text()
    assert (text == base) == (name == "page")
    if name == "constant loop bounds":
        assert "< n_in" not in text and "< n_out" not in text
    if name in ("integer texture", "fp16 pairs"):
        assert "usampler2D prt_weights" in text and "RGBA32UI" in (out / "prt-web.js").read_text()


def test_fp16_pairs_hold_two_texels_per_texel(study, page, tmp_path):
    study.variant(page, tmp_path / "v", "fp16 pairs")
    web0, web1 = (json.loads((d / "web.json").read_text()) for d in (page, tmp_path / "v"))
    texels = np.frombuffer((page / web0["weights"]["file"]).read_bytes(), dtype="<f4").reshape(-1, 4)
    packed = np.frombuffer((tmp_path / "v" / web1["weights"]["file"]).read_bytes(), dtype="<u4").reshape(-1, 4)
    halves = np.stack([packed & 0xFFFF, packed >> 16], axis=-1).astype("<u2").view("<f2").reshape(-1, 8)
    back = halves.reshape(-1, 4)[: len(texels)].astype(np.float32)
    assert np.allclose(back, texels, rtol=1e-3, atol=1e-4)
    assert web1["weights"]["height"] == -(-((len(texels) + 1) // 2) // web0["weights"]["width"])
