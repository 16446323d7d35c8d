"""Many segments, one cost (issue 44): the ONNX backend's stacked models (``prt.runtime.onnx_stack``) against
the per-segment sessions they replace (the reference twin), the block layout against a plain loop, the
hand-written protobuf against ``onnx``'s checker, and the fallbacks (other architectures, other formats,
a stacked model that disagrees on its probe rows).

Tolerance: stacked and per-segment transfer agree within 1e-5 absolute (relative to max(1, |T|)); measured
0 on the demo and <= 3e-8 on a 124-segment Spot build (float rounding of the MatMul kernels)."""

from __future__ import annotations

import json
import types

import numpy as np
import onnx
import pytest

import prt.runtime.backends.onnx as onnx_backend
from prt.export.onnx_model import build_model
from prt.runtime.backends.onnx import OnnxTransfer
from prt.runtime.onnx_stack import block_layout, read_network, stack_key, stacked_model
from prt.runtime.renderer import Renderer, Scene
from prt.train.networks.network import Architecture, evaluate_numpy, head_terms

TOL = 1e-5


def _arrays(rng, hidden: int, layers: int, pos_freqs: int = 2, residual: bool = False, outputs: int = 16, log_dc: bool = False) -> dict:
    from math import pi

    def freq(k):
        b = np.zeros((3, 3 * k), np.float32)
        for j in range(k):
            b[np.arange(3), 3 * j + np.arange(3)] = 2.0**j * pi
        return b

    features = 3 + 6 * pos_freqs + 3 + 6 * 2
    sizes = [features] + [hidden] * layers + [outputs]
    out = {"enc_centre": rng.normal(size=3).astype(np.float32) * 0.2, "enc_inv_half": rng.uniform(1, 3, 3).astype(np.float32),
           "enc_pos_freq": freq(pos_freqs), "enc_normal_freq": freq(2), "out_scale": rng.uniform(0.1, 1, outputs).astype(np.float32),
           "out_offset": rng.normal(size=outputs).astype(np.float32) * 0.1}  # fmt: skip
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        key = f"layer{i}" if i < layers else "out"
        out[f"{key}_weight"] = (rng.normal(size=(a, b)) / np.sqrt(a)).astype(np.float32)
        out[f"{key}_bias"] = rng.normal(size=b).astype(np.float32) * 0.1
    if residual:
        out["out_normal_quad"] = rng.normal(size=(9, outputs)).astype(np.float32) * 0.3
    if log_dc:  # a log-DC head (prt.train.networks.network) over groups of 16
        arch = Architecture(hidden=hidden, layers=layers, pos_freqs=pos_freqs, layout="direct" if outputs == 16 else "direct+rgb", head="log-dc")
        out.update(head_terms(arch))
        mask = out["out_dc_mask"]
        out["out_scale"] = (out["out_scale"] * (1 - mask)).astype(np.float32)
        out["out_offset"] = np.where(mask > 0, rng.uniform(-4, -1, outputs), 0).astype(np.float32)
        out["out_linear"] = (1.5 * mask).astype(np.float32)
        out["out_max"] = np.where(mask > 0, rng.uniform(-1.5, 0.5, outputs), 1e4).astype(np.float32)
    return out


def _model(arrays: dict, fmt: str | None = None) -> bytes:
    layers = sum(k.startswith("layer") and k.endswith("_weight") for k in arrays)
    arch = {"hidden": arrays["out_weight"].shape[0], "layers": layers, "pos_freqs": arrays["enc_pos_freq"].shape[1] // 3,
            "normal_freqs": 2, "bands": 4, "input_dim": arrays["layer0_weight"].shape[0] if layers else 0,
            "outputs": arrays["out_bias"].shape[0]}  # fmt: skip
    model = build_model(arrays, arch)
    if fmt is not None:
        onnx.helper.set_model_props(model, {"prt.format": fmt})
    return model.SerializeToString()


def _manifest(tmp_path, models: list[bytes | None]):
    """A stand-in manifest (the engine reads sh_bands, transfer_width, segments' id, kind, model)."""
    segments = []
    for s, data in enumerate(models):
        if data is None:
            segments.append(types.SimpleNamespace(id=s, kind="analytic", model=None))
            continue
        path = tmp_path / f"seg{s:03d}.onnx"
        path.write_bytes(data)
        segments.append(types.SimpleNamespace(id=s, kind="network", model=path))
    return types.SimpleNamespace(sh_bands=4, transfer_width=16, segments=segments)


def _rows(rng, counts):
    """Rows grouped by segment: ``counts[s]`` rows of segment s, positions around the origin."""
    offsets = np.concatenate([[0], np.cumsum(counts)])
    x = rng.uniform(-1, 1, (int(offsets[-1]), 6)).astype(np.float32)
    return x, offsets


def _both(engine, x, offsets):
    engine.batched = False
    ref = engine.infer_sorted(x, offsets)
    engine.batched = True
    return ref, engine.infer_sorted(x, offsets)


def _close(a, b) -> float:
    return float(np.abs(a - b).max() / max(1.0, float(np.abs(a).max())))


def test_block_layout_equals_a_plain_loop():
    rng = np.random.default_rng(1)
    counts = rng.integers(1, 40, 9)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) + 5
    for block in (1, 4, 16, 64):
        source, member, valid = block_layout(starts, counts, block)
        src_ref, mem_ref, val_ref = [], [], []
        for j, (a, c) in enumerate(zip(starts, counts)):
            for b0 in range(0, c, block):
                mem_ref.append(j)
                row = []
                for r in range(block):
                    if b0 + r < c:
                        val_ref.append(len(src_ref) * block + r)
                    row.append(a + min(b0 + r, c - 1))
                src_ref.append(row)
        assert np.array_equal(source, src_ref) and np.array_equal(member, mem_ref) and np.array_equal(valid, val_ref)
        assert np.array_equal(source.ravel()[valid], np.concatenate([np.arange(a, a + c) for a, c in zip(starts, counts)]))


def test_stacked_model_is_valid_onnx_and_reads_back():
    rng = np.random.default_rng(2)
    members = [_arrays(rng, 8, 2, residual=True) for _ in range(3)]
    data = _model(members[0])
    arrays, meta = read_network(data)
    assert meta["prt.format"] == "prt-transfer-mlp/1"
    for k, v in members[0].items():
        assert np.array_equal(arrays[k], v), k
    model = onnx.load_model_from_string(stacked_model(members))
    onnx.checker.check_model(model, full_check=True)
    assert [i.name for i in model.graph.input] == ["x", "seg"] and model.graph.output[0].name == "transfer"


def test_demo_stacked_equals_per_segment_and_calls_no_segment_session(monkeypatch):
    manifest = Scene.load().manifest
    engine = OnnxTransfer(manifest, threads=2, slice_rows=1000, block_rows=16, stack_below=1 << 30)
    try:
        assert [list(s.segments) for s in engine.stacks] == [list(range(len(manifest.segments)))] and not engine.stack_notes
        rng = np.random.default_rng(0)
        x = rng.uniform(-1, 1, (9000, 6)).astype(np.float32)
        segment = rng.integers(-1, len(manifest.segments), 9000)
        engine.batched = False
        covered, ref = engine.compute(x, segment)
        monkeypatch.setattr(engine, "_infer", lambda *a: pytest.fail("a per-segment session ran on the stacked path"))
        engine.batched = True
        covered2, got = engine.compute(x, segment)
        assert np.array_equal(covered, covered2) and _close(ref, got) <= TOL
    finally:
        engine.close()


def test_mixed_architectures_stack_apart_and_the_rest_falls_back(tmp_path):
    rng = np.random.default_rng(3)
    models = [_model(_arrays(rng, 16, 2, residual=True)) for _ in range(5)]  # one stack
    models += [_model(_arrays(rng, 8, 1)) for _ in range(3)]  # another
    models += [None]  # analytic
    models += [_model(_arrays(rng, 8, 1, pos_freqs=3))]  # alone: its own session
    models += [_model(_arrays(rng, 8, 1), fmt="someone-else/1")]  # not our format: its own session
    engine = OnnxTransfer(_manifest(tmp_path, models), threads=2, slice_rows=200, block_rows=8, stack_below=1000)
    try:
        assert sorted(sorted(int(s) for s in st.segments) for st in engine.stacks) == [[0, 1, 2, 3, 4], [5, 6, 7]]
        counts = np.array([1, 7, 8, 9, 300, 0, 33, 1500, 20, 17, 5])  # 1500 rows >= stack_below: its own session
        x, offsets = _rows(rng, counts)
        ref, got = _both(engine, x, offsets)
        assert _close(ref, got) <= TOL
        for block in (1, 3, 64):  # any block size gives the same rows
            engine.block_rows = block
            assert _close(ref, engine.infer_sorted(x, offsets)) <= TOL
    finally:
        engine.close()
    bound = OnnxTransfer(_manifest(tmp_path, models), threads=2, bound=True, block_rows=8, stack_below=1000)  # a GPU provider's path
    try:
        calls = []
        for st in bound.stacks:
            run = st.session.run
            st.session = types.SimpleNamespace(run=lambda *a, run=run: calls.append(1) or run(*a))
        assert _close(ref, bound.infer_sorted(x, offsets)) <= TOL and len(calls) == 2  # one call per stack
    finally:
        bound.close()


def test_log_dc_heads_stack_apart_from_linear_ones_and_match_their_files(tmp_path):
    """A log-DC head (issue 43): its segments' stack gives their own sessions' rows (and the numpy
    twin's), and a linear network of the same size is not stacked with them."""
    rng = np.random.default_rng(6)
    heads = [_arrays(rng, 16, 2, outputs=64, log_dc=True) for _ in range(4)]
    models = [_model(a) for a in heads] + [_model(_arrays(rng, 16, 2, outputs=64)) for _ in range(2)]
    manifest = _manifest(tmp_path, models)
    manifest.transfer_width = 64
    engine = OnnxTransfer(manifest, threads=2, slice_rows=200, block_rows=8, stack_below=1000)
    try:
        assert sorted(sorted(int(s) for s in st.segments) for st in engine.stacks) == [[0, 1, 2, 3], [4, 5]] and not engine.stack_notes
        counts = np.array([5, 40, 1, 90, 12, 30])
        x, offsets = _rows(rng, counts)
        ref, got = _both(engine, x, offsets)
        assert _close(ref, got) <= TOL
        for s, a in enumerate(heads):  # the file's graph is the numpy twin's head
            rows = slice(offsets[s], offsets[s + 1])
            twin = evaluate_numpy(a, x[rows, :3], x[rows, 3:])
            assert np.abs(ref[rows] - twin).max() <= 1e-5 * max(1.0, float(np.abs(twin).max()))
            dc = ref[rows][:, ::16]
            assert (dc > 0).all() and (dc <= np.exp(a["out_max"][::16]) * (1 + 1e-5)).all()  # exp of the capped log DC
    finally:
        engine.close()


def test_a_stacked_model_that_disagrees_is_not_used(tmp_path, monkeypatch):
    rng = np.random.default_rng(4)
    models = [_model(_arrays(rng, 8, 1)) for _ in range(4)]

    def wrong(members, name="stack"):  # the stack of other weights
        return stacked_model([{**m, "out_bias": m["out_bias"] + 0.5} for m in members], name)

    monkeypatch.setattr(onnx_backend, "stacked_model", wrong)
    engine = OnnxTransfer(_manifest(tmp_path, models), threads=1)
    try:
        assert not engine.stacks and "differs from their own" in engine.stack_notes[0]
        x, offsets = _rows(rng, [10, 20, 30, 40])
        ref, got = _both(engine, x, offsets)
        assert np.array_equal(ref, got)
    finally:
        engine.close()


def test_stack_key_refuses_what_it_cannot_stack():
    rng = np.random.default_rng(5)
    arrays = _arrays(rng, 8, 1)
    assert stack_key(arrays, {"prt.format": "prt-transfer-mlp/1"}) is not None
    assert stack_key(arrays, {"prt.format": "prt-transfer-grid/1"}) is None
    assert stack_key({**arrays, "code_weight": np.zeros((3, 8), np.float32)}, {"prt.format": "prt-transfer-mlp/1"}) is None
    assert stack_key({**arrays, "extra": np.zeros(1, np.float32)}, {"prt.format": "prt-transfer-mlp/1"}) is None
    assert read_network(b"\xff") is None  # not protobuf


def test_renderer_frames_match_with_and_without_stacks():
    """The demo's frame, every pixel and interpolated, stacked against per-segment."""
    scene = Scene.load()
    for interpolate in (None, 0.1):
        with Renderer(scene, 48, 48, "onnx", threads=2, interpolate=interpolate) as r:
            engine = r._backend().engine
            engine.stack_below = 1 << 30
            engine.batched = False
            ref = r.render()
            engine.batched = True
            r.set_camera_object(r.camera)  # a new view: the networks run again
            got = r.render()
            assert np.abs(ref - got).max() <= TOL * max(1.0, float(np.abs(ref).max()))


def test_many_segments_study_records_both_paths(bench_module, tmp_path):
    """studies/many_segments_bench.py on the demo as both scenes (tiny): each configuration's frame times,
    the ratio, and the inference pairs, stacked against per-segment."""
    from prt.runtime.renderer import demo_scene_path

    study = bench_module("many_segments_bench")
    out = tmp_path / "ms.json"
    scene = str(demo_scene_path())
    assert study.main([scene, scene, "--size", "32", "--glsl-size", "16", "--rounds", "1", "--frames", "1",
                       "--glsl-frames", "1", "--pairs", "2", "--json", str(out)]) == 0  # fmt: skip
    record = json.loads(out.read_text())
    assert set(record["rows"]) == {"onnx per-segment", "onnx stacked", "glsl"}
    for row in record["rows"].values():
        assert row["ratio"] > 0 and all(s["frames"] == 1 and s["frame_ms"] > 0 for s in row["scenes"])
    assert record["stacks"] == [[3], [3]] and record["provenance"]["date"]
    assert all(r["per_segment_ms"] > 0 and r["stacked_ms"] > 0 for r in record["inference"]["scenes"]) and record["inference"]["ratio_stacked"] > 0
