"""The grid encoding as a build option (issue 12): ``prt-train --encoding grid [--grid ...]`` builds,
exports (ONNX + GLSL + table texture), records the grid in the manifest, and both backends render it
alike; the default (frequency) build keeps its fit-cache keys; bad values give one-line errors.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from prt.runtime.errors import SpecError
from prt.runtime.manifest import Manifest, load_manifest

DATA = Path(__file__).parent / "data"
CORNELL = DATA / "CornellBox-Original.obj"
SIZE = 96


def _train(out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "prt.train.train_cli", *args, "-o", str(out), "--no-progress", "--threads", "1"],
                          capture_output=True, text=True)  # fmt: skip


@pytest.fixture(scope="module")
def grid_scene(tmp_path_factory):
    """An SDF scene, every segment a grid network (a fixed 16 x 1 MLP), 200 steps."""
    out = tmp_path_factory.mktemp("grid") / "scene"
    proc = _train(out, "sphere_plane", "--samples", "4000", "--validation", "1000", "--rays", "64", "--steps", "200", "--batch", "1024",
                  "--segments", "3", "--no-analytic", "--encoding", "grid", "--grid", "L4-F2-T10-N4-16", "--hidden", "16", "--layers", "1")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return out / "scene.json"


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(((a.astype(np.float64) - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(float(b.max()) ** 2 / mse)


def _render_both(scene_path, material="diffuse"):
    from prt.runtime.renderer import Renderer, Scene

    scene = Scene.load(scene_path)
    images = {}
    for backend in ("onnx", "glsl"):
        with Renderer(scene, SIZE, SIZE, backend=backend) as r:
            if material == "glossy":
                r.set_material("glossy", albedo=(0.5, 0.5, 0.5), specular=(0.4, 0.4, 0.4), exponent=16)
            images[backend] = r.render()
    return images


@pytest.mark.parametrize("material", ["diffuse", "glossy"])
def test_grid_build_renders_alike_in_onnx_and_glsl(grid_scene, material):
    images = _render_both(grid_scene, material)
    assert images["onnx"].max() > 0.05
    assert _psnr(images["glsl"], images["onnx"]) >= 60.0


def test_grid_manifest_round_trips_and_records_the_grid(grid_scene):
    m = load_manifest(grid_scene)
    nets = [s for s in m.segments if s.is_network]
    assert nets and all(s.encoding == "grid" for s in nets)
    arch = nets[0].architecture
    assert arch["encoding"] == "grid" and (arch["levels"], arch["features"], arch["log2_table"]) == (4, 2, 10)
    assert (arch["base_resolution"], arch["max_resolution"], arch["hidden"], arch["layers"]) == (4, 16, 16, 1)
    assert nets[0].flops_per_fragment > 0 and nets[0].weight_bytes > 0 and nets[0].glsl_weights.is_file()
    again = Manifest.from_dict(m.to_dict(), grid_scene)
    assert [s.architecture for s in again.segments] == [s.architecture for s in m.segments]
    raw = json.loads(grid_scene.read_text())
    bad = json.loads(json.dumps(raw))
    bad["segments"][nets[0].id]["architecture"]["features"] = 9
    with pytest.raises(SpecError, match=r"segments\[\d+\]\.architecture"):
        Manifest.from_dict(bad, grid_scene)
    bad = json.loads(json.dumps(raw))
    bad["segments"][nets[0].id]["architecture"]["encoding"] = "hash"
    with pytest.raises(SpecError, match=r"segments\[\d+\]\.architecture"):
        Manifest.from_dict(bad, grid_scene)
    # the ONNX file is the grid graph of the stored arrays (fp16 tables)
    from prt.export.grid_onnx import read_arrays
    from prt.train.networks.grid_encoding import evaluate_numpy
    import onnxruntime as ort

    arrays, recorded = read_arrays(nets[0].model)
    assert recorded["kind"] == "grid"
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, (64, 3)).astype(np.float32)
    n = rng.normal(size=(64, 3)).astype(np.float32)
    sess = ort.InferenceSession(str(nets[0].model), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"x": np.concatenate([p, n], axis=1)})[0]
    assert np.abs(got - evaluate_numpy(arrays, p, n)).max() < 1e-5


def test_older_manifests_without_encoding_are_frequency_networks():
    from prt.runtime.renderer import demo_scene_path

    m = load_manifest(demo_scene_path())
    assert all(s.encoding == "freq" for s in m.segments if s.is_network)


def test_default_encoding_keeps_fit_cache_keys():
    """The frequency build's cache keys with the L1 loss are those of before the grid option (values from
    that code); the default loss ("auto") keys its own fits."""
    from prt.train.build import BuildSpec, _FitCache, _hash, spec_from_dict

    spec = BuildSpec(geometry="x", bounces=0, loss="l1")  # direct transfer: the layout the keys were taken from
    assert spec.encoding == "freq" and spec.grid is None
    cache = _FitCache(Path("fits"), "prekey", 3, spec.fit_settings())
    names = [cache._paths(a)[0].name for a in spec.architectures()]
    assert names[0] == "342a1e485ec73e5a.json" and names[-1] == "15c7ed98289bd823.json"
    default = BuildSpec(geometry="x", bounces=0)
    default_cache = _FitCache(Path("fits"), "prekey", 3, default.fit_settings())
    assert not set(names) & {default_cache._paths(a)[0].name for a in default.architectures()}
    assert _hash([a.as_dict() for a in spec.architectures()]) == "23a8fb0504017710"
    grid = spec_from_dict({"geometry": "x", "encoding": "grid", "bounces": 0})
    assert [a.label() for a in grid.architectures()] == [f"grid-L6-F2-T12-N4-32-k{k}-l{l}" for k, l in ((16, 1), (32, 2), (64, 2), (64, 3))]
    assert not set(names) & {cache._paths(a)[0].name for a in grid.architectures()}
    # --match 64x4 with grids: the reference stays the paper's frequency network, the rungs are grids
    matched = spec_from_dict({"geometry": "x", "encoding": "grid", "bounces": 0, "match": {"hidden": 64, "layers": 4}})
    assert matched.reference_architecture().label() == "k64-l4-f6"
    assert all(a.flops_per_fragment() < matched.reference_architecture().flops_per_fragment() for a in matched.architectures())


@pytest.mark.parametrize(
    "args, message",
    [
        (["--encoding", "grid", "--grid", "L6-F2"], r"grid: expected L<levels>-F<features>-T<log2 table>-N<min>-<max>"),
        (["--encoding", "grid", "--grid", "L6-F2-T12-N4-99999"], r"grid: resolutions N<min>-<max>: expected 1 <= min <= max <= 4096, got 4 and 99999"),
        (["--encoding", "grid", "--grid", "L6-F8-T12-N4-32"], r"grid: features F: expected 1 \.\. 4"),
        (["--encoding", "grid", "--grid", "L6-F2-T2-N4-32"], r"grid: table T: expected log2 of the rows per level, 4 \.\. 20, got 2"),
        (["--grid", "L6-F2-T12-N4-32"], r"grid: only with encoding 'grid'"),
        (["--encoding", "grid", "--hidden", "30", "--layers", "2"], r"fixed\.hidden: .*multiple of 4, got 30"),
    ],
)
def test_bad_grid_values_are_one_line_errors(tmp_path, args, message):
    import re

    proc = _train(tmp_path / "out", str(CORNELL), *args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("prt-train: error: ") and re.search(message, lines[0]), proc.stderr
    assert not (tmp_path / "out").exists()


def test_grid_build_with_interreflection_renders_alike(tmp_path):
    """64 outputs ("direct+rgb"): the grid's GLSL fills 16 blocks, drawn in two parts."""
    out = tmp_path / "scene"
    proc = _train(out, str(CORNELL), "--samples", "2500", "--validation", "600", "--rays", "32", "--segments", "1", "--steps", "100",
                  "--bounces", "1", "--bounce-rays", "16", "--no-analytic", "--encoding", "grid", "--grid", "L3-F2-T10-N4-12",
                  "--hidden", "16", "--layers", "1")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    m = load_manifest(out / "scene.json")
    assert m.transfer_width == 64 and all(s.encoding == "grid" for s in m.segments if s.is_network)
    images = _render_both(out / "scene.json")
    assert _psnr(images["glsl"], images["onnx"]) >= 60.0
