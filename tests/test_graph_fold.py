"""studies/onnx_graph_fold.py's folded graph computes what the exported one does."""

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fold(bench_module):
    return bench_module("onnx_graph_fold")


@pytest.mark.parametrize("pos_freqs, normal_freqs", [(None, None), (0, 2), (4, 0), (0, 0)])
def test_folded_graph_matches_the_exported_one(fold, pos_freqs, normal_freqs):
    from prt.export.onnx_model import build_model, read_arrays

    arrays, arch = read_arrays(ROOT / "runtime" / "data" / "demo" / "segments" / "seg000.onnx")
    if pos_freqs is not None:  # other encodings: same weights, columns of layer 0 dropped to fit
        arch = dict(arch, pos_freqs=pos_freqs, normal_freqs=normal_freqs)
        F0, G0 = arrays["enc_pos_freq"].shape[1] // 3, arrays["enc_normal_freq"].shape[1] // 3
        keep = [*range(3), *range(3, 3 + 3 * pos_freqs), *range(3 + 3 * F0, 3 + 3 * F0 + 3 * pos_freqs)]
        n0 = 3 + 6 * F0
        keep += [*range(n0, n0 + 3), *range(n0 + 3, n0 + 3 + 3 * normal_freqs), *range(n0 + 3 + 3 * G0, n0 + 3 + 3 * G0 + 3 * normal_freqs)]
        arrays = dict(arrays, layer0_weight=arrays["layer0_weight"][keep],
                      enc_pos_freq=arrays["enc_pos_freq"][:, : 3 * pos_freqs], enc_normal_freq=arrays["enc_normal_freq"][:, : 3 * normal_freqs])
        arch["input_dim"] = len(keep)
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-1.2, 1.2, (2000, 3)), rng.normal(size=(2000, 3))], axis=1).astype(np.float32)
    x[:5, 3:] = 0.0  # degenerate normals take the same guarded path
    weights = {k: v for k, v in arrays.items() if k not in ("split_sizes", "clip_lo", "clip_hi", "normal_eps") and v.size}
    exported = fold.session(build_model(weights, arch).SerializeToString())
    folded = fold.session(fold.folded_model(arrays, arch))
    a, b = exported.run(None, {"x": x})[0], folded.run(None, {"x": x})[0]
    assert np.isfinite(b).all()
    np.testing.assert_allclose(b, a, atol=2e-5, rtol=0)
    assert folded.get_outputs()[0].shape[-1] == a.shape[1]
