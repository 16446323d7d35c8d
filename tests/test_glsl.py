"""GLSL generated from ONNX segment networks: against onnxruntime on llvmpipe, layouts, snapshots."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

from prt.export.glsl import (
    AUTO_CONST_MAX_BLOCKS,
    choose_layout,
    compile_report,
    evaluate_glsl,
    generate_glsl,
    weight_texture,
)
from prt.export.onnx_model import build_model, save_model
from prt.train.networks.network import Architecture, TransferMLP, frequency_matrix, head_terms

SNAPSHOTS = Path(__file__).parent / "snapshots"
BOUNDS = np.array([[-1.0, 0.5, -2.0], [1.5, 2.0, 0.25]])
TOLERANCE = 1e-4

# Small and odd sizes (padding, no frequencies, 9 outputs) and the paper's k=64, l=4.
CASES = {
    "k8-l2-no-freqs": (Architecture(hidden=8, layers=2, pos_freqs=0, normal_freqs=0), ("const", "texture")),
    "k18-l3-f1-n1": (Architecture(hidden=18, layers=3, pos_freqs=1, normal_freqs=1), ("const", "texture")),
    "k12-l1-f6-n2-bands3": (Architecture(hidden=12, layers=1, pos_freqs=6, normal_freqs=2, bands=3), ("const", "texture")),
    "k64-l4-f6-n2": (Architecture(hidden=64, layers=4, pos_freqs=6, normal_freqs=2), ("auto", "texture")),
    "k18-l3-f1-n1-residual": (Architecture(hidden=18, layers=3, pos_freqs=1, normal_freqs=1, residual=True), ("const", "texture")),
    # log-DC heads: exp of each group's DC, the rest times it (groups of 9 at 3 bands: DC columns off the vec4 grid)
    "k18-l3-f1-n1-logdc": (Architecture(hidden=18, layers=3, pos_freqs=1, normal_freqs=1, head="log-dc"), ("const", "texture")),
    "k12-l1-bands3-direct+rgb-logdc": (Architecture(hidden=12, layers=1, pos_freqs=6, normal_freqs=2, bands=3, layout="direct+rgb", head="log-dc"),
                                       ("const", "texture")),
}


def export_random(path: Path, arch: Architecture, seed: int = 0) -> Path:
    """Export a TransferMLP at its random init, with random biases and output scaling."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = arch.outputs
    if arch.head == "log-dc":  # DC columns: log DC = 1.5 z + offset, capped (some rows reach the cap); the rest ratios
        mask = head_terms(arch)["out_dc_mask"]
        model = TransferMLP(arch, BOUNDS, rng.uniform(0.05, 0.6, n) * (1 - mask), np.where(mask > 0, rng.uniform(-3, -1, n), 0.0),
                            1.5 * mask, np.where(mask > 0, rng.uniform(-1.5, 0.0, n), 1e4))  # fmt: skip
    else:
        model = TransferMLP(arch, BOUNDS, rng.uniform(0.05, 0.6, n), rng.uniform(-0.3, 0.3, n))
    with torch.no_grad():  # the init zeroes biases, which would leave them untested
        for layer in [*model.hidden, model.out]:
            layer.bias.uniform_(-0.3, 0.3)
    save_model(build_model(model.arrays(), arch.as_dict()), path)
    return path


def export_rational(path: Path, arch: Architecture) -> Path:
    """Export a network whose weights are exact small fractions: the same file on any machine."""
    sizes = [arch.input_dim] + [arch.hidden] * arch.layers
    values = iter(range(10**6))

    def fractions(*shape):
        count = int(np.prod(shape))
        k = np.array([next(values) for _ in range(count)])
        return (((k * 37) % 101 - 50) / 64).astype(np.float32).reshape(shape)

    arrays = {
        "enc_centre": np.array([0.25, 1.25, -0.875], dtype=np.float32),
        "enc_inv_half": np.array([0.8, 1.5, 0.5], dtype=np.float32),
        "enc_pos_freq": frequency_matrix(arch.pos_freqs),
        "enc_normal_freq": frequency_matrix(arch.normal_freqs),
        "out_weight": fractions(arch.hidden, arch.outputs),
        "out_bias": fractions(arch.outputs),
        "out_scale": np.full(arch.outputs, 0.5, dtype=np.float32),
        "out_offset": fractions(arch.outputs),
    }
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        arrays[f"layer{i}_weight"] = fractions(a, b)
        arrays[f"layer{i}_bias"] = fractions(b)
    save_model(build_model(arrays, arch.as_dict()), path)
    return path


def hard_inputs(count: int, seed: int = 0) -> np.ndarray:
    """(count, 6) positions in, on and far outside the box; normals of many lengths."""
    rng = np.random.default_rng(seed)
    lo, hi = BOUNDS
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    positions = centre + half * rng.uniform(-3, 3, size=(count, 3))  # a third inside the box
    positions[:8] = [lo, hi, centre, centre + 1e4, centre - 1e4, lo - 1e-3, hi + 1e-3, [3e7, -1e6, 0]]
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    normals = directions * 10 ** rng.uniform(-3, 1.7, size=(count, 1))  # lengths 0.001 .. 50
    normals[:6] = [[0, 0, 0], [0, 0, 1], [0, -1, 0], [50, 0, 0], [1e-3, 0, 0], [0.6, 0.8, 0]]
    return np.concatenate([positions, normals], axis=1).astype(np.float32)


def onnxruntime_transfer(path: Path, x: np.ndarray) -> np.ndarray:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3  # without frequencies the graph leaves unused initialisers: a warning
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    return export_random(tmp_path_factory.mktemp("glsl") / "small.onnx", Architecture(hidden=8, layers=2, pos_freqs=2))


@pytest.mark.gl
@pytest.mark.parametrize(
    ("name", "layout"), [(name, layout) for name, (_, layouts) in CASES.items() for layout in layouts]
)
def test_glsl_matches_onnxruntime(gl_ctx, tmp_path, name, layout):
    arch = CASES[name][0]
    path = export_random(tmp_path / f"{name}.onnx", arch)
    x = hard_inputs(2000)
    expected = onnxruntime_transfer(path, x)
    got = evaluate_glsl(gl_ctx, path, x, layout=layout)
    assert got.shape == expected.shape == (len(x), arch.outputs)
    worst = float(np.abs(got - expected).max())
    assert worst <= TOLERANCE, f"{name} ({layout}): worst |GLSL - onnxruntime| = {worst:.3g}"


@pytest.mark.parametrize("layout", ["const", "texture"])
def test_generated_source_matches_snapshot(tmp_path, layout):
    path = export_rational(tmp_path / "mlp_small.onnx", Architecture(hidden=6, layers=1, pos_freqs=1, normal_freqs=1))
    source = generate_glsl(path, layout=layout)
    snapshot = SNAPSHOTS / ("mlp_small.glsl" if layout == "const" else f"mlp_small_{layout}.glsl")
    if os.environ.get("PRT_UPDATE_SNAPSHOTS") == "1":
        snapshot.parent.mkdir(exist_ok=True)
        snapshot.write_text(source, encoding="utf-8")
    assert snapshot.exists(), f"{snapshot} is missing: run with PRT_UPDATE_SNAPSHOTS=1 to write it"
    assert source == snapshot.read_text(encoding="utf-8"), f"regenerate with PRT_UPDATE_SNAPSHOTS=1 if intended: {snapshot}"


@pytest.mark.parametrize("freqs", [(0, 0), (2, 0), (0, 3), (6, 2)])
@pytest.mark.parametrize("layout", ["const", "texture"])
def test_every_placeholder_is_filled(tmp_path, freqs, layout):
    arch = Architecture(hidden=4, layers=2, pos_freqs=freqs[0], normal_freqs=freqs[1])
    source = generate_glsl(export_rational(tmp_path / "m.onnx", arch), function_name="seg_3", layout=layout)
    assert "$" not in source  # GLSL never uses '$': any left is an unfilled placeholder
    assert "void seg_3(vec3 position, vec3 normal, out vec4 t[4])" in source
    declared = re.findall(r"^(?:const |uniform )?\w+ (\w+)", source, flags=re.MULTILINE)  # globals
    assert declared and all(name == "seg_3" or name.startswith("seg_3_") for name in declared), declared


def test_baked_literals_read_back_as_the_texture_values(tmp_path):
    """The const layout writes the texture's values, in its order, as exact float32 literals."""
    path = export_random(tmp_path / "m.onnx", Architecture(hidden=10, layers=2, pos_freqs=3, normal_freqs=1))
    source = generate_glsl(path, layout="const")
    items = re.findall(r"^    (?:vec4|mat3x4|mat4)\((.*)\),?$", source, flags=re.MULTILINE)
    baked = np.array([np.float32(v) for item in items for v in item.split(", ")], dtype=np.float32)
    texels, meta = weight_texture(path)
    assert np.array_equal(baked.view(np.uint32), texels.reshape(-1, 4)[: meta["texels"]].reshape(-1).view(np.uint32))
    assert not re.search(r"\b(inf|nan)\b", source)


def test_texture_layout_depends_only_on_the_architecture(tmp_path):
    arch = Architecture(hidden=12, layers=2, pos_freqs=2, normal_freqs=1)
    a, b = export_random(tmp_path / "a.onnx", arch, seed=1), export_random(tmp_path / "b.onnx", arch, seed=2)
    assert generate_glsl(a, layout="texture") == generate_glsl(b, layout="texture")
    assert generate_glsl(a, layout="const") != generate_glsl(b, layout="const")
    (ta, meta), (tb, _) = weight_texture(a), weight_texture(b)
    assert ta.shape == (meta["height"], meta["width"], 4) and ta.dtype == np.float32
    assert not np.array_equal(ta, tb)
    tensors = meta["tensors"]
    assert tensors["enc_centre"]["offset"] == 0 and tensors["layer0_weight"]["type"] == "mat4"
    last = tensors["out_offset"]
    assert last["offset"] + last["count"] == meta["texels"] <= meta["width"] * meta["height"]


def test_auto_bakes_small_networks_and_textures_large_ones(small):
    assert choose_layout(Architecture(hidden=32, layers=3).as_dict()) == "const"
    assert choose_layout(Architecture(hidden=128, layers=4).as_dict()) == "texture"
    assert choose_layout(Architecture(hidden=128, layers=2).as_dict()) == "texture"
    assert "const mat4 prt_transfer_layer0_weight_data" in generate_glsl(small)
    assert "uniform sampler2D prt_transfer_weights;" in generate_glsl(small, layout="texture")
    assert AUTO_CONST_MAX_BLOCKS > 0


@pytest.mark.gl
def test_several_networks_share_one_shader(gl_ctx, small, tmp_path):
    other = export_random(tmp_path / "other.onnx", Architecture(hidden=8, layers=2, pos_freqs=2), seed=5)
    source = generate_glsl(small, "seg0", "const") + generate_glsl(other, "seg1", "const")
    source += generate_glsl(small, "seg2", "texture")
    report = compile_report(gl_ctx, source, function_name="seg1")
    assert report["total_s"] > 0 and report["source_chars"] == len(source)


def test_bad_arguments_are_refused(small, tmp_path):
    with pytest.raises(ValueError, match="layout"):
        generate_glsl(small, layout="uniform")
    for name in ("gl_net", "two__under", "1net", "a-b"):
        with pytest.raises(ValueError, match="function_name"):
            generate_glsl(small, function_name=name)
    arch = Architecture(hidden=4, layers=1, pos_freqs=0, normal_freqs=0)
    model = TransferMLP(arch, BOUNDS, np.ones(16), np.zeros(16))
    arrays = model.arrays()
    arrays["layer0_bias"][1] = np.inf
    save_model(build_model(arrays, arch.as_dict()), tmp_path / "inf.onnx")
    with pytest.raises(ValueError, match="non-finite"):
        generate_glsl(tmp_path / "inf.onnx")
