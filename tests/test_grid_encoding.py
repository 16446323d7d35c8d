"""The multiresolution feature-grid network (train/networks/grid_encoding.py): its torch forward and ONNX
graph against the numpy reference, dense and hashed indexing, trilinear interpolation, training."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from prt.train.networks.fit import FitSettings
from prt.train.networks.grid_encoding import (
    CORNERS,
    PRIMES,
    GridArchitecture,
    GridTransfer,
    evaluate_numpy,
    fit_grid_segment,
    level_indices,
    level_resolutions,
)

UNIT_BOX = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])  # x = (p - 0.5) * 2, u = p exactly
# levels 4, 8, 16 (dense while (N + 1)^3 <= 2^10: 4 and 8), then hashed at 16
SMALL = GridArchitecture(levels=3, features=3, log2_table=10, base_resolution=4, max_resolution=16, hidden=16, layers=2, normal_freqs=1)


def _model(arch=SMALL, bounds=UNIT_BOX, seed=0):
    torch.manual_seed(seed)
    m = GridTransfer(arch, bounds, np.full(16, 0.4, np.float32), np.linspace(-0.1, 0.1, 16).astype(np.float32))
    with torch.no_grad():
        m.table.normal_()  # not the tiny initial values: every level matters in the comparison
    return m.eval()


def _inputs(n, seed=0, lo=-0.3, hi=1.3):
    rng = np.random.default_rng(seed)
    p = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    return p, nrm


def _torch(m, p, n):
    with torch.no_grad():
        return m(torch.from_numpy(np.concatenate([p, n], axis=1))).numpy()


def test_levels_dense_then_hashed():
    assert level_resolutions(3, 4, 16) == [4, 8, 16]
    assert level_resolutions(1, 8, 8) == [8]
    assert SMALL.hashed() == [False, False, True]  # 125, 729 <= 1024 < 4913
    assert SMALL.level_sizes() == [125, 729, 1024]
    assert SMALL.table_entries() == 3 * (125 + 729 + 1024)
    arrays = _model().arrays()
    assert arrays["grid_table"].shape == (125 + 729 + 1024, 3)
    assert arrays["grid_offset"].tolist() == [0, 125, 854]


def test_numpy_and_torch_agree():
    for arch, bounds in ((SMALL, UNIT_BOX), (GridArchitecture(levels=6, features=2, log2_table=12, max_resolution=96, position=False), np.array([[-0.7, 0.1, -0.2], [0.4, 0.9, 0.3]]))):
        m = _model(arch, bounds)
        p, n = _inputs(4000, lo=-1.0, hi=1.5)  # inside and outside the box (clamped)
        ref = evaluate_numpy(m.arrays(), p, n)
        assert ref.shape == (4000, 16)
        np.testing.assert_allclose(_torch(m, p, n), ref, atol=1e-5)
        with torch.no_grad():
            _, u = m.unit_position(torch.from_numpy(p))
            feats = m.grid_features(u).numpy()
        np.testing.assert_allclose(feats, evaluate_numpy(m.arrays(), p, n, features_only=True), atol=1e-5)


def test_dense_and_hashed_indices():
    rng = np.random.default_rng(1)
    c = rng.integers(0, 17, (500, 3))
    dense = level_indices(c, 16, False, 1 << 14)
    np.testing.assert_array_equal(dense, c[:, 0] + 17 * c[:, 1] + 289 * c[:, 2])
    grid = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert sorted(level_indices(grid, 4, False, 1 << 10).tolist()) == list(range(125))  # a bijection onto the level
    # hashed: 32-bit unsigned arithmetic (GLSL uint) gives the same rows as int64, mod T = & (T - 1)
    for log2 in (10, 14, 19):
        rows = level_indices(c, 16, True, 1 << log2)
        for (x, y, z), r in zip(c[:50].tolist(), rows[:50].tolist()):
            h = ((x * PRIMES[0]) & 0xFFFFFFFF) ^ ((y * PRIMES[1]) & 0xFFFFFFFF) ^ ((z * PRIMES[2]) & 0xFFFFFFFF)
            assert r == h % (1 << log2)
        assert rows.min() >= 0 and rows.max() < (1 << log2)


def test_torch_rows_match_reference_indexing():
    m = _model()
    p, _ = _inputs(300, seed=2, lo=0.0, hi=1.0)
    with torch.no_grad():
        rows, weight = m.grid_rows(torch.from_numpy(p))
    rows, weight = rows.numpy(), weight.numpy()
    np.testing.assert_allclose(weight.sum(-1), 1.0, atol=1e-6)
    arrays = m.arrays()
    for level, (res, hashed, offset) in enumerate(zip(arrays["grid_resolution"], arrays["grid_hashed"], arrays["grid_offset"])):
        i0 = np.minimum(np.floor(p * np.float32(res)), res - 1).astype(np.int64)
        want = level_indices(i0[:, None, :] + CORNERS[None], int(res), bool(hashed), SMALL.table_size) + offset
        np.testing.assert_array_equal(rows[:, level], want)


def test_interpolation_exact_at_corners_and_linear_along_an_edge():
    m = _model()
    arrays = m.arrays()
    table = arrays["grid_table"]
    rng = np.random.default_rng(3)
    for level, res in enumerate(arrays["grid_resolution"].tolist()):
        corners = rng.integers(0, res + 1, (40, 3))
        p = (corners / res).astype(np.float32)  # exact in float32 (res a power of 2)
        feats = evaluate_numpy(arrays, p, np.ones_like(p), features_only=True)[:, 3 * level : 3 * level + 3]
        rows = level_indices(corners, res, bool(arrays["grid_hashed"][level]), SMALL.table_size) + arrays["grid_offset"][level]
        np.testing.assert_allclose(feats, table[rows], atol=1e-6)
        # along the x edge from corner c to c + (1, 0, 0): (1 - t) f(c) + t f(c + e_x)
        c = np.array([[min(int(x), res - 1), int(y), int(z)] for x, y, z in corners[:5]])
        for t in (0.125, 0.25, 0.5, 0.875):
            q = ((c + [t, 0, 0]) / res).astype(np.float32)
            f = evaluate_numpy(arrays, q, np.ones_like(q), features_only=True)[:, 3 * level : 3 * level + 3]
            ends = [level_indices(c + d, res, bool(arrays["grid_hashed"][level]), SMALL.table_size) + arrays["grid_offset"][level] for d in ([0, 0, 0], [1, 0, 0])]
            np.testing.assert_allclose(f, (1 - t) * table[ends[0]] + t * table[ends[1]], atol=1e-5)
        with torch.no_grad():
            torch_feats = m.grid_features(torch.from_numpy(p)).numpy()[:, 3 * level : 3 * level + 3]
        np.testing.assert_allclose(torch_feats, table[rows], atol=1e-6)


def test_gradient_reaches_the_tables_at_the_rows_used():
    m = _model()
    p, n = _inputs(64, seed=4, lo=0.0, hi=1.0)
    x = torch.from_numpy(np.concatenate([p, n], axis=1))
    m(x).square().sum().backward()
    grad = m.table.grad
    assert grad is not None and torch.isfinite(grad).all()
    with torch.no_grad():
        rows, weight = m.grid_rows(torch.from_numpy(p))
    used = torch.zeros(len(grad), dtype=torch.bool)
    used[rows[weight > 0]] = True
    touched = grad.abs().sum(1) > 0
    assert touched.any() and not touched[~used].any()  # only rows the points read get a gradient
    assert touched[m.offsets.view(-1)[2] :].any()  # the hashed level learns too
    # and it is the true gradient: a finite difference along one used row
    row = int(torch.nonzero(touched)[0])
    eps = 1e-3
    with torch.no_grad():
        m.table[row, 0] += eps
        up = m(x).square().sum().item()
        m.table[row, 0] -= 2 * eps
        down = m(x).square().sum().item()
    assert abs((up - down) / (2 * eps) - grad[row, 0].item()) <= 1e-2 * max(1.0, abs(grad[row, 0].item()))


def test_costs():
    b = SMALL.flops_breakdown()
    # per level 18 + index (4 + 8 * 2 or 3 + 8) + 12 weights + 15 F
    assert b["grid"] == (18 + 28 + 12 + 45) * 2 + (18 + 36 + 12 + 45)
    assert b["fetches"] == 24
    k, d = 16, 3 * 3 + 3 + 3 + 6
    assert SMALL.input_dim == d
    assert b["mlp"] == 2 * d * k + 2 * k * k + 2 * k * 16 + 2 * 2 * k + 22 * 16
    assert SMALL.flops_per_fragment() == 18 + b["grid"] + (10 + 3 + 120) + b["mlp"]
    assert SMALL.mlp_weight_count() == sum(v.size for k_, v in _model().arrays().items() if k_.startswith(("layer", "out_w", "out_b")))
    assert SMALL.bytes(2, 4) == 2 * SMALL.table_entries() + 4 * (SMALL.mlp_weight_count() + 32 + 6 + 9)


def test_fit_learns_a_sharp_shadow():
    """A step in transfer along x (a shadow edge): the grid fit gets well under the best constant."""
    rng = np.random.default_rng(5)
    p = rng.uniform(0, 1, (4000, 3)).astype(np.float32)
    n = np.tile([[0.0, 1.0, 0.0]], (4000, 1)).astype(np.float32)
    t = np.zeros((4000, 16), np.float32)
    t[:, 0] = np.where(p[:, 0] > 0.37, 0.8, 0.2) + 0.1 * p[:, 2]
    vp, vn, vt = p[:500], n[:500], t[:500]
    arch = GridArchitecture(levels=4, features=2, log2_table=10, base_resolution=4, max_resolution=32, hidden=16, layers=1)
    r = fit_grid_segment(p[500:], n[500:], t[500:], vp, vn, vt, arch, UNIT_BOX, FitSettings(steps=150, batch=512, lr=1e-2), lights={"c": np.ones((16, 3))})
    constant = np.abs(vt - np.median(t, axis=0)).mean()
    assert r.val_mae < 0.25 * constant
    assert r.steps > 0 and set(r.shaded) == {"c"}
    np.testing.assert_allclose(evaluate_numpy(r.model.arrays(), vp, vn), _torch(r.model, vp, vn), atol=1e-5)


@pytest.mark.parametrize("table_dtype", ["float32", "float16"])
def test_onnx_graph_matches_numpy(tmp_path, table_dtype):
    ort = pytest.importorskip("onnxruntime")
    from prt.export.grid_onnx import OPSET, build_grid_model, read_arrays, save_grid_model

    arch = GridArchitecture(levels=5, features=2, log2_table=11, base_resolution=4, max_resolution=48, hidden=16, layers=2, normal_freqs=2)
    m = _model(arch, np.array([[-0.6, -0.2, -0.9], [0.7, 0.5, 0.2]]))
    arrays = m.arrays()
    assert arrays["grid_hashed"].tolist() == [False, False, True, True, True]
    model = build_grid_model(arrays, arch.as_dict(), table_dtype=table_dtype)
    assert {o.domain: o.version for o in model.opset_import}[""] == OPSET == 18
    path = tmp_path / "seg.onnx"
    save_grid_model(model, path)
    p, n = _inputs(3000, seed=6, lo=-1.2, hi=1.2)
    n[0] = 0.0  # a zero normal stays finite
    out = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": np.concatenate([p, n], axis=1)})[0]
    back, recorded = read_arrays(path)
    assert recorded["levels"] == 5
    if table_dtype == "float16":
        arrays = {**arrays, "grid_table": arrays["grid_table"].astype(np.float16).astype(np.float32)}
    np.testing.assert_array_equal(back["grid_table"], arrays["grid_table"])
    ref = evaluate_numpy(arrays, p, n)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, ref, atol=1e-5)
    np.testing.assert_allclose(evaluate_numpy(back, p, n), ref, atol=0)


def test_glsl_matches_numpy(gl_ctx):
    """The generated GLSL (table in a texture read with texelFetch, uint hash) against the
    numpy reference, dense and hashed levels, points outside the box, a zero normal."""
    from prt.export.grid_onnx import glsl_function, table_texture
    from prt.runtime.gl import run_fragment_program

    arch = GridArchitecture(levels=5, features=2, log2_table=11, base_resolution=4, max_resolution=48, hidden=16, layers=2, normal_freqs=2)
    m = _model(arch, np.array([[-0.6, -0.2, -0.9], [0.7, 0.5, 0.2]]))
    arrays = m.arrays()
    p, n = _inputs(2000, seed=7, lo=-1.2, hi=1.2)
    n[0] = 0.0
    frag = "\n".join([
        "#version 330",
        "uniform sampler2D u_p;",
        "uniform sampler2D u_n;",
        glsl_function(arrays, "seg0"),
        *[f"layout(location = {j}) out vec4 o{j};" for j in range(4)],
        "void main() {",
        "    ivec2 c = ivec2(gl_FragCoord.xy);",
        "    vec4 t[4];",
        "    seg0(texelFetch(u_p, c, 0).xyz, texelFetch(u_n, c, 0).xyz, t);",
        "    o0 = t[0]; o1 = t[1]; o2 = t[2]; o3 = t[3];",
        "}",
    ])  # fmt: skip
    texels, _ = table_texture(arrays)
    texture = gl_ctx.texture((texels.shape[1], texels.shape[0]), 4, texels.tobytes(), dtype="f4")
    texture.filter = (0x2600, 0x2600)  # GL_NEAREST
    try:
        out = run_fragment_program(gl_ctx, frag, {"u_p": p, "u_n": n}, components=16, attachments=4, textures={"seg0_table": texture})
    finally:
        texture.release()
    ref = evaluate_numpy(arrays, p, n)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, ref, atol=1e-5)
    psnr = 10 * np.log10(np.abs(ref).max() ** 2 / np.mean((out - ref) ** 2))
    assert psnr >= 60
