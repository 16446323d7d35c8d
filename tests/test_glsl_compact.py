"""Compact scene GLSL (export/glsl_compact.py, the glsl backend): one function per architecture
against onnxruntime / the numpy grid reference at any segment's base texel, a program whose size
does not grow with the number of segments, older per-segment scenes still rendering, and
one-line errors for files that do not fit."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from prt.export import glsl_compact as gc
from prt.runtime.errors import InputError
from prt.runtime.manifest import load_manifest
from prt.train.networks.grid_encoding import GridArchitecture, GridTransfer, evaluate_numpy
from prt.train.networks.network import Architecture

sys.path.insert(0, str(Path(__file__).parent))
from test_glsl import export_random, hard_inputs, onnxruntime_transfer  # noqa: E402

FREQ = {
    "k8-l2-no-freqs": Architecture(hidden=8, layers=2, pos_freqs=0, normal_freqs=0),
    "k18-l3-f1-n1": Architecture(hidden=18, layers=3, pos_freqs=1, normal_freqs=1),
    "k12-l1-bands3": Architecture(hidden=12, layers=1, pos_freqs=6, normal_freqs=2, bands=3),
    "k64-l4": Architecture(hidden=64, layers=4, pos_freqs=6, normal_freqs=2),
    "k16-l2-direct+rgb": Architecture(hidden=16, layers=2, pos_freqs=6, normal_freqs=2, layout="direct+rgb"),
    # residual networks: + q(n) @ out_normal_quad (the direct part only with bounces; 9 coefficients at 3 bands)
    "k18-l3-residual": Architecture(hidden=18, layers=3, pos_freqs=1, normal_freqs=1, residual=True),
    "k12-l1-bands3-direct+rgb-residual": Architecture(hidden=12, layers=1, pos_freqs=6, normal_freqs=2, bands=3, layout="direct+rgb", residual=True),
    # log-DC heads: out_linear and out_max after out_offset, then exp of each group's DC (groups of 9 at 3 bands)
    "k16-l2-direct+rgb-logdc": Architecture(hidden=16, layers=2, pos_freqs=6, normal_freqs=2, layout="direct+rgb", head="log-dc"),
    "k12-l1-bands3-direct+rgb-logdc": Architecture(hidden=12, layers=1, pos_freqs=6, normal_freqs=2, bands=3, layout="direct+rgb", head="log-dc"),
}


def _psnr(out, ref) -> float:
    return float(10 * np.log10(np.abs(ref).max() ** 2 / max(np.mean((out - ref) ** 2), 1e-30)))


@pytest.mark.parametrize("name", list(FREQ))
def test_freq_function_matches_onnxruntime_at_any_base(gl_ctx, tmp_path, name):
    """The shared function of an architecture evaluates each segment of it from its own texels:
    here the second of two segments (base > 0), against onnxruntime on its own file."""
    arch = FREQ[name]
    first, second = export_random(tmp_path / "a.onnx", arch, seed=1), export_random(tmp_path / "b.onnx", arch, seed=2)
    source = gc.freq_source(second)
    assert source == gc.freq_source(first), "the source must depend only on the architecture"
    x = hard_inputs(600)
    out = gc.evaluate_compact(gl_ctx, source, [gc.freq_texels(first), gc.freq_texels(second)], x, segment=1)
    ref = onnxruntime_transfer(second, x)
    out = out[:, : ref.shape[1]]
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, ref, atol=1e-4)
    assert _psnr(out, ref) >= 60
    assert np.abs(out - onnxruntime_transfer(first, x)).max() > 1e-3, "the other segment's weights give other values"


def test_largest_network_stays_under_llvmpipes_loop_cap(gl_ctx, tmp_path):
    """k = 128, l = 4 with 64 outputs: its loop iterations are under the margin and the GLSL
    agrees with onnxruntime (a hit cap would stop the loops and give other values)."""
    arch = Architecture(hidden=128, layers=4, pos_freqs=6, normal_freqs=2, layout="direct+rgb")
    path = export_random(tmp_path / "big.onnx", arch)
    source = gc.freq_source(path)
    shape = {"encoding": "freq", "groups": 16, "hidden": 32, "outputs": 16, "layers": 4}
    assert gc.loop_iterations(shape) < gc.MAX_LOOP_ITERATIONS < 65_535
    assert f"runs {gc.loop_iterations(shape)} loop iterations" in " ".join(source.split())
    x = hard_inputs(200)
    out = gc.evaluate_compact(gl_ctx, source, gc.freq_texels(path), x)
    ref = onnxruntime_transfer(path, x)
    assert _psnr(out[:, : ref.shape[1]], ref) >= 60


def test_loop_iteration_count_is_what_the_loops_run():
    """The count against a direct tally of the generated loops (hidden 2 blocks, 1 layer)."""
    # encode: none counted (unrolled); first layer 2 outputs x (3 inputs + 1); out 4 x (2 + 1)
    assert gc.loop_iterations({"encoding": "freq", "groups": 3, "hidden": 2, "outputs": 4, "layers": 1}) == 2 * 4 + 4 * 3 + 10
    # levels x (1 + 8 corners); per layer 2 bias/activation loops over out/4 + in x (out/4 + 1); the tanh loop
    grid = {"encoding": "grid", "levels": 2, "layers": [(8, 16), (16, 16)]}
    assert gc.loop_iterations(grid) == 18 + (8 + 8 * 5) + (8 + 16 * 5) + 4


GRID = GridArchitecture(levels=5, features=2, log2_table=11, base_resolution=4, max_resolution=48, hidden=16, layers=2, normal_freqs=2)


def _grid_arrays(seed, arch=GRID, box=((-0.6, -0.2, -0.9), (0.7, 0.5, 0.2))):
    import torch

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    m = GridTransfer(arch, np.array(box), rng.uniform(0.1, 0.5, 16).astype(np.float32), rng.uniform(-0.1, 0.1, 16).astype(np.float32))
    with torch.no_grad():
        m.table.normal_()
    return m.eval().arrays()


def test_grid_function_matches_numpy_at_any_base(gl_ctx):
    """Two grid segments of one architecture (different boxes, tables, output scaling) in one
    texture; the second's values from the shared function against the numpy reference."""
    a = _grid_arrays(1)
    b = _grid_arrays(2, box=((-1.0, -0.5, -0.3), (0.2, 0.9, 1.0)))
    source = gc.grid_source(b)
    assert source == gc.grid_source(a)
    rng = np.random.default_rng(7)
    p = rng.uniform(-1.2, 1.2, (1500, 3)).astype(np.float32)
    n = rng.normal(size=(1500, 3)).astype(np.float32)
    n[0] = 0.0
    out = gc.evaluate_compact(gl_ctx, source, [gc.grid_texels(a), gc.grid_texels(b)], np.concatenate([p, n], axis=1), segment=1)
    ref = evaluate_numpy(b, p, n)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, ref, atol=1e-5)
    assert _psnr(out, ref) >= 60


def test_functions_are_named_after_the_architecture(tmp_path):
    names = set()
    for name, arch in FREQ.items():
        source = gc.freq_source(export_random(tmp_path / f"{name}.onnx", arch))
        names.add(gc._format_fields(source)[0])
    names.add(gc._format_fields(gc.grid_source(_grid_arrays(0)))[0])
    assert len(names) == len(FREQ) + 1


# -- the backend --


@pytest.fixture(scope="module")
def segment_files(tmp_path_factory):
    """Two architectures' compact files and a per-segment (texture layout) file of the first."""
    from prt.export.glsl import generate_glsl, weight_texture

    folder = tmp_path_factory.mktemp("compact")
    files = {}
    for key, arch, seed in (("a", FREQ["k18-l3-f1-n1"], 3), ("b", FREQ["k64-l4"], 4)):
        model = export_random(folder / f"{key}.onnx", arch, seed=seed)
        (folder / f"{key}.glsl").write_text(gc.freq_source(model))
        np.save(folder / f"{key}_weights.npy", gc.weights_array(gc.freq_texels(model)))
        files[key] = model
    return folder, files, generate_glsl, weight_texture


def _manifest(folder, kinds, blocks=4):
    """A stand-in manifest: segment i of kind "a" / "b" (compact files) or "analytic"."""
    segments = []
    for i, kind in enumerate(kinds):
        if kind == "analytic":
            segments.append(SimpleNamespace(id=i, kind="analytic", glsl=None, glsl_weights=None, encoding=None))
        else:
            segments.append(SimpleNamespace(id=i, kind="network", glsl=folder / f"{kind}.glsl", glsl_weights=folder / f"{kind}_weights.npy", encoding="freq"))
    return SimpleNamespace(path=folder / "scene.json", segments=segments, transfer_width=4 * blocks)


def test_program_size_does_not_grow_with_segments(gl_ctx, segment_files):
    """8 or 32 segments of two architectures make the program of 2: one function each (only the
    uniform arrays' length changes), which is what bounds llvmpipe's JIT time."""
    from prt.runtime.backends.glsl import GlslBackend

    folder = segment_files[0]
    sizes = {}
    for count in (2, 8, 32):
        kinds = ["a", "b"] * (count // 2)
        kinds[-1] = "analytic"
        backend = GlslBackend(gl_ctx, _manifest(folder, kinds))
        try:
            sizes[count] = backend.source_chars
            assert len(backend.functions) == (2 if count > 2 else 1)
        finally:
            backend.release()
    assert 0 <= sizes[32] - sizes[8] <= 2, sizes  # "#define PRT_SEGMENTS 8" -> "32"
    assert sizes[8] > sizes[2], sizes  # the second architecture's function


def test_bad_compact_files_are_one_line_errors(gl_ctx, segment_files, tmp_path):
    from prt.runtime.backends.glsl import GlslBackend
    from prt.runtime.gl import ShaderCompileError

    folder = tmp_path / "bad"
    shutil.copytree(segment_files[0], folder)
    # weights of the other architecture: the header does not fit the function
    shutil.copy(folder / "b_weights.npy", folder / "a_weights.npy")
    with pytest.raises(InputError, match=r"a_weights\.npy: does not fit a\.glsl") as info:
        GlslBackend(gl_ctx, _manifest(folder, ["a"]))
    assert "\n" not in str(info.value)
    # a format this runtime does not read
    text = (segment_files[0] / "a.glsl").read_text().replace("// prt-glsl compact 1 ", "// prt-glsl compact 2 ")
    (folder / "a.glsl").write_text(text)
    with pytest.raises(InputError, match=r"a\.glsl: not a compact GLSL file this runtime reads"):
        GlslBackend(gl_ctx, _manifest(folder, ["a"]))
    # 4 output blocks where the scene's transfer has 16 (interreflection)
    with pytest.raises(InputError, match=r"b\.glsl: the network gives 4 vec4 blocks, the scene's transfer has 16"):
        GlslBackend(gl_ctx, _manifest(folder, ["b"], blocks=16))
    # two files claiming one function with different code
    (folder / "c.glsl").write_text((segment_files[0] / "b.glsl").read_text() + "// edited\n")
    shutil.copy(folder / "b_weights.npy", folder / "c_weights.npy")
    with pytest.raises(ShaderCompileError, match=r"c\.glsl: error: defines prt_freq_\w+ unlike .*b\.glsl"):
        GlslBackend(gl_ctx, _manifest(folder, ["b", "c"]))


def _render(scene_path, backend, size=48):
    from prt.runtime.renderer import Renderer, Scene

    with Renderer(Scene.load(scene_path), size, size, backend=backend) as r:
        return r.render()


def test_older_per_segment_files_and_compact_ones_render_alike(gl_ctx, tmp_path):
    """The demo with its first segment's GLSL as the older export wrote it (a function of its own,
    weight texture layout) and the others compact, in one program: against the onnx backend."""
    from prt.export.glsl_compact import write_segment_glsl
    from prt.export.manifest import write_manifest
    from prt.runtime.backends.glsl import GlslBackend
    from prt.runtime.renderer import demo_scene_path

    folder = tmp_path / "demo"
    shutil.copytree(demo_scene_path().parent, folder)
    scene = folder / "scene.json"
    manifest = load_manifest(scene)
    networks = [seg for seg in manifest.segments if seg.is_network]
    for i, seg in enumerate(networks):
        write_segment_glsl(seg, "texture" if i == 0 else "compact")
    write_manifest(scene, manifest)
    assert "prt-glsl compact" not in networks[0].glsl.read_text() and "prt-glsl compact" in networks[1].glsl.read_text()
    backend = GlslBackend(gl_ctx, load_manifest(scene))
    try:
        assert backend.functions[-1] == f"seg{networks[0].id}_transfer" and len(backend.functions) == 2
    finally:
        backend.release()
    assert _psnr(_render(scene, "glsl"), _render(scene, "onnx")) >= 60
