"""OpenVINO against ONNX Runtime as the ONNX backend's inference engine, on the same ONNX files.

usage: python studies/openvino_engine.py [--scene scene.json] [--size 512] [--views 20] [--json OUT]

Needs ``pip install "prt-runtime[openvino]"``.  Renderers of one scene share a GL context; the
``onnx`` backend's engine is ONNX Runtime (threads 2 and 1) or :class:`OpenVinoTransfer`
(float32 or bfloat16 inference precision hint, threads 1 and 2).  Every configuration renders
the same orbit views, interleaved (the order reversed every other view), and the script prints
median inference and frame milliseconds, each engine's speed relative to ONNX Runtime at 2
threads, the largest difference of its image from ONNX Runtime's, and the load average.

Verdict of issue 18 (AMD EPYC, 2 cores, load 11-13 from other work): OpenVINO 2026.4 ran the
demo's networks at 512x512 0.47-0.55x as fast as ONNX Runtime at 2 threads, in frames (threads 1
and 2, fp32 and bf16), and 0.52-0.57x on 4096-row slices of one network (static shapes included)
against ONNX Runtime at one thread; at the same PSNR in prt-bench (256x256, 4 views) for fp32 and
0.02 dB lower for bf16.  Not adopted.  The issue reported 1.17-1.41x on another CPU (AMX): rerun this there.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from prt.runtime.backends.onnx import OnnxTransfer
from prt.runtime.camera import orbit_views
from prt.runtime.errors import InputError
from prt.runtime.gl import create_context
from prt.runtime.renderer import Renderer, Scene, demo_scene_path

PRECISIONS = {"fp32": "f32", "bf16": "bf16"}


class OpenVinoTransfer(OnnxTransfer):
    """The networks of a scene as OpenVINO compiled models, behind :class:`OnnxTransfer`'s interface.

    One compiled model per network segment on the CPU device (latency hint, ``threads`` inference
    threads, no pinning), called once per segment batch: OpenVINO threads inside the call.
    """

    def __init__(self, manifest, threads: int | None = None, precision: str = "fp32"):
        try:
            import openvino
        except ImportError:
            raise InputError('OpenVINO is not installed: pip install "prt-runtime[openvino]"') from None
        self._ov, self._core, self.precision = openvino, openvino.Core(), precision
        super().__init__(manifest, threads=threads, slice_rows=1 << 30)

    def _open(self, model: bytes, path):
        network = self._core.read_model(model=model, weights=self._ov.Tensor(np.zeros(0, np.uint8)))
        config = {"INFERENCE_NUM_THREADS": self.threads, "INFERENCE_PRECISION_HINT": PRECISIONS[self.precision],
                  "PERFORMANCE_HINT": "LATENCY", "ENABLE_CPU_PINNING": False}  # fmt: skip
        compiled = self._core.compile_model(network, "CPU", config)
        return compiled.create_infer_request(), compiled.inputs[0].any_name

    def _concurrent_slices(self) -> bool:
        return False

    def _infer(self, s: int, rows: np.ndarray) -> np.ndarray:
        request = self.sessions[s]
        request.infer({0: rows})
        return np.array(request.get_output_tensor(0).data, dtype=np.float32, copy=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", type=Path, default=demo_scene_path())
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--views", type=int, default=20)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    scene = Scene.load(args.scene)
    ctx = create_context()
    configs = [("onnxruntime", "fp32", 2), ("onnxruntime", "fp32", 1)] + [
        ("openvino", precision, threads) for precision in PRECISIONS for threads in (1, 2)]  # fmt: skip
    renderers = {}
    for engine, precision, threads in configs:
        r = Renderer(scene, args.size, args.size, backend="onnx", threads=threads, ctx=ctx)
        if engine == "openvino":
            backend = r._backend()
            backend.engine.close()
            backend.engine = OpenVinoTransfer(scene.manifest, threads=threads, precision=precision)
        r.render()  # warm-up
        renderers[(engine, precision, threads)] = r
    views = list(orbit_views(next(iter(renderers.values())).camera, args.views))
    load_before = os.getloadavg()
    times = {c: {"inference": [], "frame": []} for c in configs}
    diff = dict.fromkeys(configs, 0.0)
    for i, view in enumerate(views):
        images = {}
        for c in configs if i % 2 == 0 else configs[::-1]:
            r = renderers[c]
            r.set_camera_object(view)
            images[c] = r.render()
            for k in times[c]:
                times[c][k].append(r.timings[k])
        for c in configs:
            diff[c] = max(diff[c], float(np.abs(images[c] - images[configs[0]]).max()))
    base = float(np.median(times[configs[0]]["inference"]))
    rows = []
    print(f"{scene.name} {args.size}x{args.size}, {len(views)} views interleaved; load {load_before} -> {os.getloadavg()}")
    for c in configs:
        inference, frame = (float(np.median(times[c][k])) for k in ("inference", "frame"))
        rows.append({"engine": c[0], "precision": c[1], "threads": c[2], "inference_ms": inference, "frame_ms": frame,
                     "speed_vs_ort2": base / inference, "image_max_abs_diff": diff[c]})  # fmt: skip
        print(f"  {c[0]:12s} {c[1]} threads {c[2]}: inference {inference:7.1f} ms ({base / inference:4.2f}x), "
              f"frame {frame:7.1f} ms, image max |diff| {diff[c]:.2e}")
    for r in renderers.values():
        r.close()
    if args.json:
        args.json.write_text(json.dumps({"load": load_before, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
