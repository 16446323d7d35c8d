"""Speed against error of the PRT renderer, with baselines, precision variants and the machine limit.

usage::

    prt-bench scene.json [more scenes] [--json out.json] [--md out.md]
        [--plot out.png] [--views 30] [--size 512 [256 ...]] [--ref-rays 1024] [--warmup 3]
        [--precisions fp32 fp16 fp16-mlp int8] [--backends onnx glsl vertex] [--cache DIR]
        [--gemm-size 4096] [--blas-threads N] [--config-budget SECONDS] [--packing-views N]

For every scene, a camera trajectory of ``--views`` views orbits the manifest camera about its
target (the paper's Table 1 protocol).  Every configuration (backend ``onnx`` at each ONNX
precision, backend ``glsl``, and the vertex-space baseline; material diffuse and glossy; each
``--size``) renders all views after ``--warmup`` frames (or, under ``--config-budget``, as
many views as the budget allows at the warm-up's frame time, at least 4, spread over the
orbit; the record's ``views`` says how many), and is compared with a ray-traced reference of
the same G-buffer.

Reference
    The G-buffer of each view (the renderer's own, so pixels match), ground-truth transfer
    ray traced at every covered pixel with :func:`prt.train.compute_transfer` (``--ref-rays``
    cosine-weighted rays; the same geometry the scene was built from: ``geometry.npz``, or the
    SDF scene by name), shaded with :func:`prt.runtime.shading.shade` under the renderer's
    lighting and material.  Cached by content (points, normals, rays, seed, geometry) as
    ``.npz`` in ``transfer/`` of the cache folder (default: ``<json stem>_cache`` next to
    ``--json``), so scenes built from one mesh share their references.  Its own noise is reported:
    PSNR between two references with different seeds (frame spins) at view 0.

Metrics
    On tone-mapped images (:func:`prt.runtime.shading.tonemap`, values in [0, 1]), averaged
    over views (PSNR: the mean of the per-view dB): ``mae`` and ``psnr`` over covered pixels,
    ``ssim`` the SSIM map (skimage, data_range 1, 7x7 window) averaged over covered pixels,
    ``psnr_whole`` over the whole image (background counts, as in the paper).  PSNR is capped
    at 100 dB (identical images).

Baselines
    ``vertex``: Sloan-style per-vertex transfer, ray traced at the mesh vertices (area-weighted
    vertex normals; open surfaces get a second set for their back side), interpolated by the
    rasteriser (4 RGBA32F targets), shaded like the rest; mesh scenes only.  Packing: the
    networks run on every pixel (each network segment's session sees all H*W pixels, the
    right one is picked per pixel afterwards) against the packed path (covered pixels only,
    batched by segment), both through :class:`prt.runtime.onnx_backend.OnnxTransfer`.

Precisions
    ``fp32``: the exported models.  ``fp16``: every float tensor and operator in half
    precision, float32 input and output (Cast nodes at the edges).  ``fp16-mlp``: the same for
    the MLP only, the input encoding kept in float32.  ``int8``: dynamic quantisation
    (``onnxruntime.quantization.quantize_dynamic``, QInt8 weights, MatMulInteger); ONNX
    Runtime's dynamic quantiser leaves Gemm alone, so each layer's Gemm is first rewritten as
    MatMul + Add, and only the MLP's MatMuls are quantised (the encoding's frequency MatMuls
    stay float32).

JSON report (``--json``)
    ``tool``, ``created`` (ISO time), ``settings`` (the arguments), ``machine``: ``cpu``,
    ``cores``, ``gl_renderer``, ``onnxruntime``, ``numpy``, ``gemm_size``, ``gemm_numpy_gflops``
    and ``gemm_onnxruntime_gflops`` (float32 n x n GEMM through numpy's BLAS and through ONNX
    Runtime's MatMul on all cores, medians of 3), ``machine_gflops`` (the higher of the two: the
    machine's limit), ``resumed`` (the scenes taken from checkpoints of an earlier run, each
    with ``scene`` and ``measured``: their records keep that run's ``machine_gflops``; empty
    when every scene was measured in this run), ``load_average`` (1-minute load at the start),
    ``other_cpu_share`` (CPU time other processes used during the run, as a share of all
    cores' time; Linux only, else None): other work makes every timing slower and noisier.

    ``scenes``: one entry per scene: ``scene``, ``path``, ``geometry`` (``type``, ``source``
    used, ``checksum``, ``matches_build_source``: the vertex checksum of ``build.json``'s
    source re-loaded against ``geometry.npz``, or None), ``networks``, ``weight_bytes``,
    ``reference`` (``rays``, ``seed``, ``cache``, ``noise_psnr``: {size: {material: dB}},
    ``noise_note``), ``packing``: one entry per size with ``resolution``, ``all_pixels``,
    ``covered_pixels`` (median), ``network_segments``, ``naive_rows_per_segment``
    ({segment: rows}, each H*W),
    ``naive_total_rows``, ``naive_inference_ms``, ``packed_inference_ms`` (medians over
    the views, or ``--packing-views`` of them spread over the orbit), ``packing_views``, ``packing_speedup`` (naive / packed), ``pixel_ratio`` (all / covered pixels),
    ``work_ratio`` (naive rows / covered pixels), ``naive_max_abs_diff`` (naive vs packed
    transfer on covered pixels), ``network_profile`` (ONNX Runtime's profiler on one slice of
    the largest network segment of the first view, one thread: ``segment``, ``rows``,
    ``run_us``, ``op_us`` per op type, ``gemm_share``: the share of the run in the MLP's
    Gemms; the rest is the encoding and element-wise ops); ``vertex_baseline`` (``vertices``, ``back_vertices``,
    ``weight_bytes``, ``coverage_agreement`` or ``note`` when skipped), ``error_images``
    (the ``--images`` figures of this scene, one per size: view 0's reference and each
    configuration's error map; empty without ``--images``), ``measured`` (ISO time
    the scene was measured) and ``checkpoint`` (where its measurement is kept: a later run with
    the same scene files and settings takes it from there instead of measuring again, unless
    ``--fresh``; its records then keep the ``machine_gflops`` of the run that measured them).

    ``records``: one per configuration, with ``scene``, ``backend`` (onnx, glsl, vertex),
    ``precision`` (fp32, fp16, fp16-mlp, int8), ``material``, ``resolution`` (``"WxH"``),
    ``width``, ``height``, ``views``, ``fps`` (1000 / median frame ms), ``frame_ms``,
    ``stages_ms`` (median per stage), ``network_ms`` (inference / network stage; 0 for
    vertex), ``mae``, ``psnr``, ``ssim``, ``psnr_whole``, ``weight_bytes`` (ONNX initialiser
    bytes of the models run; the fp32 models' for glsl; 16 float32 per vertex for vertex),
    ``flops_per_fragment`` (manifest FLOPs, weighted by the covered pixels of each segment;
    the manifest counts a multiply-add as 2 and each sin, cos or tanh as about 20),
    ``covered_pixels`` (median), ``achieved_gflops`` (FLOPs of the covered pixels / network
    seconds, median over views), ``machine_gflops``, ``machine_percent``,
    ``transfer_max_abs_diff`` (transfer against the fp32 ONNX path at view 0, covered pixels),
    ``ref_rays``, ``ref_noise_psnr``, ``label``, ``pareto`` (on the FPS-PSNR Pareto front of
    its scene, resolution and material).

    ``pareto``: {``"scene WxH material"``: [labels on the front, by increasing FPS]}: only
    configurations with the same reference image compete.

Markdown (``--md``): the records as a table, then packing, reference noise and machine lines.
Plot (``--plot``): FPS (log) against PSNR, one panel per scene and resolution, one labelled
point per configuration, the Pareto front of each material ringed and connected.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import datetime
import hashlib
import json
import logging
import os
import platform
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

PRECISIONS = ("fp32", "fp16", "fp16-mlp", "int8")
MATERIALS = ("diffuse", "glossy")
# The glossy material of the paper's comparisons: albedo stays the scene's.
GLOSSY = {"specular": (0.3, 0.3, 0.3), "exponent": 16.0}
# Identical images would give infinite PSNR; JSON has no infinity.
PSNR_CAP = 100.0
# Columns of the packed G-buffer holding position xyz and normal xyz.
PACKED_COLUMNS = (0, 1, 2, 4, 5, 6)

# The report's keys (documented in the module docstring; the tests hold the output to them).
REPORT_KEYS = ("tool", "created", "settings", "machine", "scenes", "records", "pareto")
MACHINE_KEYS = ("cpu", "cores", "gl_renderer", "onnxruntime", "numpy", "gemm_size", "gemm_numpy_gflops",
                "gemm_onnxruntime_gflops", "machine_gflops", "resumed", "load_average", "other_cpu_share")
SCENE_KEYS = ("scene", "path", "geometry", "networks", "weight_bytes", "reference", "packing", "vertex_baseline",
              "error_images", "measured", "checkpoint")  # fmt: skip
PACKING_KEYS = (
    "resolution", "all_pixels", "covered_pixels", "network_segments", "naive_rows_per_segment", "naive_total_rows",
    "naive_inference_ms", "packed_inference_ms", "packing_speedup", "pixel_ratio", "work_ratio", "naive_max_abs_diff",
    "packing_views", "network_profile",
)  # fmt: skip
RECORD_KEYS = (
    "scene", "backend", "precision", "material", "resolution", "width", "height", "views", "fps", "frame_ms",
    "stages_ms", "network_ms", "mae", "psnr", "ssim", "psnr_whole", "weight_bytes", "flops_per_fragment",
    "covered_pixels", "achieved_gflops", "machine_gflops", "machine_percent", "transfer_max_abs_diff", "ref_rays",
    "ref_noise_psnr", "label", "pareto",
)  # fmt: skip


# =========================================================================== precision variants


def _float_types(model):
    """Element type of every tensor of ``model`` (inputs, initialisers, inferred intermediates)."""
    import onnx

    inferred = onnx.shape_inference.infer_shapes(model)
    types = {}
    for vi in (*inferred.graph.input, *inferred.graph.value_info, *inferred.graph.output):
        types[vi.name] = vi.type.tensor_type.elem_type
    for init in inferred.graph.initializer:
        types[init.name] = init.data_type
    return types


def encoding_nodes(model) -> set[int]:
    """Indices of the nodes that compute the first Gemm's input (the input encoding).

    Parameters
    ----------
    model : onnx.ModelProto
        A transfer network as exported by ``prt.export`` (encoding, then Gemm layers).

    Returns
    -------
    set of int
        Node indices (in graph order) that are ancestors of the first Gemm's data input.
    """
    nodes = list(model.graph.node)
    producer = {out: i for i, node in enumerate(nodes) for out in node.output}
    first_gemm = next(i for i, node in enumerate(nodes) if node.op_type == "Gemm")
    todo, found = [nodes[first_gemm].input[0]], set()
    while todo:
        i = producer.get(todo.pop())
        if i is not None and i not in found:
            found.add(i)
            todo.extend(nodes[i].input)
    return found


def convert_to_fp16(model, keep_fp32=frozenset()):
    """A float16 copy of an ONNX model whose input and output stay float32.

    Float initialisers read only by converted nodes are stored as float16; a Cast is inserted
    wherever a tensor crosses between a float16 and a float32 node, and after every output.

    Parameters
    ----------
    model : onnx.ModelProto
    keep_fp32 : set of int
        Indices of nodes to leave in float32 (e.g. :func:`encoding_nodes`).

    Returns
    -------
    onnx.ModelProto
        A checked model with the same input and output names and types.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    f32, f16 = TensorProto.FLOAT, TensorProto.FLOAT16
    model = copy.deepcopy(model)
    graph = model.graph
    original = _float_types(model)
    half = [node.op_type != "Cast" and i not in keep_fp32 for i, node in enumerate(graph.node)]

    readers = defaultdict(list)
    for node, is_half in zip(graph.node, half):
        for name in node.input:
            readers[name].append(is_half)
    stored = {vi.name: vi.type.tensor_type.elem_type for vi in graph.input}  # type in the new graph
    for init in graph.initializer:
        if init.data_type == f32 and readers[init.name] and all(readers[init.name]):
            init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init).astype(np.float16), init.name))
        stored[init.name] = init.data_type

    nodes, casts = [], {}

    def typed(name: str, want: int) -> str:
        if stored[name] == want:
            return name
        if (name, want) not in casts:
            cast = f"{name}_as_{'fp16' if want == f16 else 'fp32'}"
            nodes.append(helper.make_node("Cast", [name], [cast], to=want, name=cast))
            stored[cast] = want
            casts[name, want] = cast
        return casts[name, want]

    for node, is_half in zip(graph.node, half):
        want = f16 if is_half else f32
        new = copy.deepcopy(node)
        for k, name in enumerate(new.input):
            if name and original.get(name) == f32:
                new.input[k] = typed(name, want)
        for attr in new.attribute:  # Constant nodes carry their value as an attribute
            if is_half and attr.type == onnx.AttributeProto.TENSOR and attr.t.data_type == f32:
                attr.t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(attr.t).astype(np.float16), attr.t.name))
        for name in new.output:
            stored[name] = want if original.get(name) == f32 else original.get(name, 0)
        nodes.append(new)

    for out in graph.output:
        if stored[out.name] == f16:  # rename the float16 result, cast it back under the output's name
            inner = out.name + "_fp16"
            for node in nodes:
                node.input[:] = [inner if n == out.name else n for n in node.input]
                node.output[:] = [inner if n == out.name else n for n in node.output]
            nodes.append(helper.make_node("Cast", [inner], [out.name], to=f32, name=out.name + "_as_fp32"))
    graph.ClearField("node")
    graph.node.extend(nodes)
    graph.ClearField("value_info")
    onnx.checker.check_model(model)
    return model


def gemm_to_matmul(model):
    """Rewrite each Gemm with an initialiser weight as MatMul + Add (dynamic quantisation skips Gemm).

    Parameters
    ----------
    model : onnx.ModelProto

    Returns
    -------
    model : onnx.ModelProto
        A copy; ``alpha``, ``beta`` and ``transB`` are folded into the new initialisers.
    matmuls : list of str
        Names of the MatMul nodes that replaced a Gemm.
    """
    from onnx import helper, numpy_helper

    model = copy.deepcopy(model)
    graph = model.graph
    inits = {t.name: t for t in graph.initializer}
    nodes, matmuls = [], []
    for node in graph.node:
        attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
        if node.op_type != "Gemm" or attrs.get("transA", 0) or node.input[1] not in inits:
            nodes.append(node)
            continue
        out = node.output[0]
        weight = numpy_helper.to_array(inits[node.input[1]]).astype(np.float32)
        weight = (weight.T if attrs.get("transB", 0) else weight) * attrs.get("alpha", 1.0)
        graph.initializer.append(numpy_helper.from_array(np.ascontiguousarray(weight), f"{out}_matmul_weight"))
        name = f"{out}_matmul"
        product = out if len(node.input) < 3 or not node.input[2] else f"{out}_product"
        nodes.append(helper.make_node("MatMul", [node.input[0], f"{out}_matmul_weight"], [product], name=name))
        matmuls.append(name)
        if product != out:
            bias = numpy_helper.to_array(inits[node.input[2]]).astype(np.float32) * attrs.get("beta", 1.0)
            graph.initializer.append(numpy_helper.from_array(bias, f"{out}_bias"))
            nodes.append(helper.make_node("Add", [product, f"{out}_bias"], [out], name=f"{out}_add"))
    graph.ClearField("node")
    graph.node.extend(nodes)
    used = {name for node in nodes for name in node.input}
    kept = [t for t in graph.initializer if t.name in used]
    graph.ClearField("initializer")
    graph.initializer.extend(kept)
    return model, matmuls


def quantize_int8(model, path: Path) -> None:
    """Write a dynamically quantised (QInt8 weights, MatMulInteger) copy of ``model`` to ``path``.

    Parameters
    ----------
    model : onnx.ModelProto
        A transfer network; its layers' Gemms are quantised, its encoding stays float32.
    path : Path
    """
    from onnxruntime.quantization import QuantType, quantize_dynamic

    prepared, matmuls = gemm_to_matmul(model)
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the quantiser's advice to run its pre-processing is noise here
    try:
        quantize_dynamic(
            prepared, str(path), op_types_to_quantize=["MatMul"], nodes_to_quantize=matmuls,
            weight_type=QuantType.QInt8, per_channel=True, extra_options={"MatMulConstBOnly": True},
        )  # fmt: skip
    finally:
        root.setLevel(level)


def build_variant(source: Path, precision: str, path: Path) -> Path:
    """Write the ``precision`` variant of the ONNX model ``source`` to ``path`` (unless present).

    Parameters
    ----------
    source : Path
        An exported float32 transfer network.
    precision : {"fp16", "fp16-mlp", "int8"}
    path : Path

    Returns
    -------
    Path
        ``path``.
    """
    import onnx

    from prt.runtime.files import atomic_write_bytes

    if path.is_file():
        return path
    model = onnx.load(str(source))
    if precision == "int8":
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # a rename: never half a model
        try:
            quantize_int8(model, partial)
            os.replace(partial, path)
        finally:
            partial.unlink(missing_ok=True)
        return path
    keep = encoding_nodes(model) if precision == "fp16-mlp" else set()
    atomic_write_bytes(path, convert_to_fp16(model, keep).SerializeToString())
    return path


def variant_manifest(manifest, precision: str, folder: Path):
    """The manifest with its network segments' models replaced by their ``precision`` variants.

    Parameters
    ----------
    manifest : prt.runtime.manifest.Manifest
    precision : str
        One of :data:`PRECISIONS`; ``"fp32"`` returns ``manifest`` itself.
    folder : Path
        Where the variant models are built (keyed by the source models' contents).

    Returns
    -------
    Manifest
    """
    if precision == "fp32":
        return manifest
    segments = []
    for seg in manifest.segments:
        if seg.kind == "network":
            digest = hashlib.sha1(seg.model.read_bytes()).hexdigest()[:12]
            target = folder / f"{seg.model.stem}-{digest}-{precision}.onnx"
            seg = dataclasses.replace(seg, model=build_variant(seg.model, precision, target))
        segments.append(seg)
    return dataclasses.replace(manifest, segments=segments)


def model_weight_bytes(manifest) -> int:
    """Bytes of every initialiser of the network segments' ONNX models."""
    import onnx

    total = 0
    for seg in manifest.segments:
        if seg.kind == "network":
            model = onnx.load(str(seg.model))
            total += sum(onnx.numpy_helper.to_array(t).nbytes for t in model.graph.initializer)
    return int(total)


# =========================================================================== geometry, cameras


def _mesh_checksum(vertices, faces) -> str:
    """sha1 of float32 vertices and uint32 faces: equal exactly when the normalised meshes are."""
    digest = hashlib.sha1(np.ascontiguousarray(vertices, dtype=np.float32).tobytes())
    digest.update(np.ascontiguousarray(faces, dtype=np.uint32).tobytes())
    return digest.hexdigest()


def load_scene_geometry(manifest):
    """The geometry a scene was built from, for ray tracing its reference.

    Mesh scenes use ``geometry.npz`` (exactly what the G-buffer rasterises) and, where
    ``build.json`` names a source file that still exists, check that re-loading it gives the
    same normalised mesh.  SDF scenes are re-loaded by name.

    Parameters
    ----------
    manifest : prt.runtime.manifest.Manifest

    Returns
    -------
    geometry : prt.train.geometry.Geometry
    info : dict
        ``type``, ``source``, ``checksum``, ``matches_build_source`` (bool, or None when the
        check could not be made).
    """
    import trimesh

    from prt.train.geometry import Geometry, load_geometry

    if manifest.geometry["type"] == "sdf":
        name = manifest.geometry["name"]
        geometry = load_geometry(name)
        return geometry, {"type": "sdf", "source": name, "checksum": None, "matches_build_source": None}
    path = Path(manifest.geometry["path"])
    with np.load(path) as data:
        vertices, faces = data["vertices"], data["faces"]
        n_faces = len(faces)
        object_ids = data["object_ids"] if "object_ids" in data else np.zeros(n_faces, dtype=np.int32)
        two_sided = data["two_sided"] if "two_sided" in data else np.zeros(n_faces, dtype=bool)
    names = list(manifest.geometry.get("objects") or [f"object{i}" for i in range(int(object_ids.max()) + 1)])
    geometry = Geometry(
        mesh=trimesh.Trimesh(vertices=vertices.astype(np.float64), faces=faces.astype(np.int64), process=False),
        object_ids=object_ids.astype(np.int64), object_names=names, two_sided=two_sided.astype(bool),
        to_source=np.asarray(manifest.geometry["to_source"], dtype=np.float64), source=str(path), sdf=None,
    )  # fmt: skip
    checksum = _mesh_checksum(vertices, faces)
    matches = None
    build = manifest.root / "build.json"
    if build.is_file():
        source = json.loads(build.read_text()).get("source")
        if source and Path(source).is_file():
            again = load_geometry(source)
            matches = _mesh_checksum(again.mesh.vertices, again.mesh.faces) == checksum
    return geometry, {"type": "mesh", "source": str(path), "checksum": checksum, "matches_build_source": matches}


def orbit_cameras(manifest, views: int) -> list:
    """``views`` cameras evenly spaced on a full orbit of the manifest camera about its target."""
    from prt.runtime.camera import Camera

    start = Camera.from_manifest(manifest.camera)
    return [start.orbit(2.0 * np.pi * i / views) for i in range(views)]


# =========================================================================== reference


def cached_transfer(cache: Path, tag: str, geometry, tracer, points, normals, rays: int, seed: int, geometry_id: str):
    """Ray-traced transfer at ``points``, read from ``cache`` when computed before.

    Parameters
    ----------
    cache : Path
        Folder of ``.npz`` files, keyed by a hash of every input.
    tag : str
        Readable start of the file name (scene, view, size).
    geometry, tracer :
        For :func:`prt.train.compute_transfer`.
    points, normals : (N, 3) float32
    rays, seed : int
    geometry_id : str
        Identity of the geometry (checksum or SDF name), part of the key.

    Returns
    -------
    transfer : (N, 16) float32
    seconds : float
        Time spent computing (0 when read from the cache).
    """
    from prt.runtime.files import atomic_save_npz
    from prt.train import compute_transfer

    points = np.ascontiguousarray(points, dtype=np.float32)
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    digest = hashlib.sha1(points.tobytes() + normals.tobytes() + f"|{rays}|{seed}|{geometry_id}|v1".encode())
    path = cache / f"{tag}-r{rays}-s{seed}-{digest.hexdigest()[:12]}.npz"
    if path.is_file():
        with np.load(path) as data:
            return data["transfer"], 0.0
    t0 = time.perf_counter()
    transfer = compute_transfer(geometry, points, normals, rays=rays, seed=seed, tracer=tracer)
    seconds = time.perf_counter() - t0
    atomic_save_npz(path, transfer=transfer)
    return transfer, seconds


def shade_image(transfer, gbuffer, eye, lighting, material) -> np.ndarray:
    """Linear (H, W, 3) image of ``transfer`` (M, 16) at the covered pixels of ``gbuffer``."""
    from prt.runtime.shading import shade

    covered = gbuffer.covered
    image = np.zeros(covered.shape + (3,), dtype=np.float32)
    position = gbuffer.position[covered]
    image[covered] = shade(transfer, gbuffer.normal[covered], np.asarray(eye)[None, :] - position, lighting, material)
    return image


# =========================================================================== metrics


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] images, capped at :data:`PSNR_CAP`."""
    return PSNR_CAP if mse <= 10.0 ** (-PSNR_CAP / 10.0) else float(-10.0 * np.log10(mse))


def image_metrics(image, reference, covered) -> dict:
    """Errors of a tone-mapped image against the tone-mapped reference.

    Parameters
    ----------
    image, reference : (H, W, 3) arrays in [0, 1]
    covered : (H, W) bool
        Pixels the scene covers.

    Returns
    -------
    dict
        ``mae``, ``psnr`` (covered pixels), ``ssim`` (SSIM map averaged over covered pixels),
        ``psnr_whole`` (every pixel).
    """
    from skimage.metrics import structural_similarity

    image = np.asarray(image, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    diff = image[covered] - reference[covered]
    _, ssim_map = structural_similarity(reference, image, data_range=1.0, channel_axis=-1, full=True)
    return {
        "mae": float(np.abs(diff).mean()),
        "psnr": psnr_from_mse(float((diff**2).mean())),
        "ssim": float(ssim_map[covered].mean()),
        "psnr_whole": psnr_from_mse(float(((image - reference) ** 2).mean())),
    }


def pareto_front(points) -> list[int]:
    """Indices of the points no other point beats in both coordinates (both maximised).

    Parameters
    ----------
    points : sequence of (x, y)
        E.g. (FPS, PSNR).

    Returns
    -------
    list of int
        The non-dominated points, by increasing x (ties: by decreasing y).  A point is dominated
        when another is at least as good in both coordinates and better in one.
    """
    pts = [(float(x), float(y)) for x, y in points]
    front = [
        i for i, (x, y) in enumerate(pts)
        if not any(u >= x and v >= y and (u > x or v > y) for u, v in pts)
    ]  # fmt: skip
    return sorted(front, key=lambda i: (pts[i][0], -pts[i][1]))


# =========================================================================== machine limit


def _gemm_rate(product, n: int, repeats: int) -> float:
    """GFLOP/s of ``product()``, an n x n x n GEMM: median of ``repeats`` after one warm-up."""
    product()  # warm-up: thread pool start, page faults of the output
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        product()
        times.append(time.perf_counter() - t0)
    return float(2.0 * n**3 / np.median(times) / 1e9)


def gemm_gflops(n: int = 4096, repeats: int = 3) -> float:
    """Single-precision GEMM throughput of numpy's BLAS: median GFLOP/s of ``repeats`` n x n products."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    return _gemm_rate(lambda: a @ b, n, repeats)


def ort_gemm_gflops(n: int = 4096, repeats: int = 3, threads: int | None = None) -> float:
    """Single-precision GEMM throughput of ONNX Runtime's CPU MatMul (MLAS) on all cores.

    The same library and kernels family the network stage runs on; on CPUs whose numpy BLAS
    picks an older kernel (OpenBLAS uses its AVX2 kernels on some AVX-512 parts) this is the
    higher of the two, so the honest machine limit is the maximum (``machine_gemm``).
    """
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(1)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["a", "b"], ["c"])], "gemm",
        [helper.make_tensor_value_info("a", TensorProto.FLOAT, [n, n])],
        [helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])],
        [numpy_helper.from_array(b, "b")],
    )  # fmt: skip
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads or os.cpu_count() or 1
    sess = ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    return _gemm_rate(lambda: sess.run(None, {"a": a}), n, repeats)


def machine_gemm(n: int = 4096, repeats: int = 3) -> dict:
    """The machine's float32 GEMM limit: numpy's BLAS and ONNX Runtime's MLAS, and the higher one.

    Returns ``{"numpy": GFLOP/s, "onnxruntime": GFLOP/s, "best": max of the two}``.
    """
    measured = {"numpy": gemm_gflops(n, repeats), "onnxruntime": ort_gemm_gflops(n, repeats)}
    return {**{k: round(v, 2) for k, v in measured.items()}, "best": round(max(measured.values()), 2)}


def _busy_seconds():
    """(CPU seconds all processes have been busy, CPU seconds of this process), or None off Linux."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:9]]
    except (OSError, ValueError, IndexError):
        return None
    idle = fields[3] + fields[4]  # idle and iowait
    own = os.times()
    return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK"), own.user + own.system


def _other_cpu_share(start, wall: float):
    """Share of all cores' time that other processes were busy since ``start`` (see _busy_seconds)."""
    end = _busy_seconds()
    if start is None or end is None or wall <= 0:
        return None
    others = (end[0] - start[0]) - (end[1] - start[1])
    return round(max(others, 0.0) / (wall * (os.cpu_count() or 1)), 3)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


# =========================================================================== vertex baseline

_VERTEX_SHADER = """
#version 330
uniform mat4 u_view_projection;
in vec3 in_position;
in vec4 in_f0; in vec4 in_f1; in vec4 in_f2; in vec4 in_f3;  // transfer of the front side
in vec4 in_b0; in vec4 in_b1; in vec4 in_b2; in vec4 in_b3;  // of the back side (open surfaces)
in int in_two_sided;
out vec4 v_f0; out vec4 v_f1; out vec4 v_f2; out vec4 v_f3;
out vec4 v_b0; out vec4 v_b1; out vec4 v_b2; out vec4 v_b3;
flat out int v_two_sided;
void main() {
    v_f0 = in_f0; v_f1 = in_f1; v_f2 = in_f2; v_f3 = in_f3;
    v_b0 = in_b0; v_b1 = in_b1; v_b2 = in_b2; v_b3 = in_b3;
    v_two_sided = in_two_sided;
    gl_Position = u_view_projection * vec4(in_position, 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330
in vec4 v_f0; in vec4 v_f1; in vec4 v_f2; in vec4 v_f3;
in vec4 v_b0; in vec4 v_b1; in vec4 v_b2; in vec4 v_b3;
flat in int v_two_sided;
layout(location = 0) out vec4 o_t0;
layout(location = 1) out vec4 o_t1;
layout(location = 2) out vec4 o_t2;
layout(location = 3) out vec4 o_t3;
void main() {
    // The G-buffer's rule: back faces of closed surfaces are hidden, open ones show their back.
    if (v_two_sided == 0 && !gl_FrontFacing) discard;
    bool back = !gl_FrontFacing;
    o_t0 = back ? v_b0 : v_f0;
    o_t1 = back ? v_b1 : v_f1;
    o_t2 = back ? v_b2 : v_f2;
    o_t3 = back ? v_b3 : v_f3;
}
"""


def vertex_normals(vertices, faces) -> np.ndarray:
    """(V, 3) area-weighted vertex normals (unit; zero for unused vertices)."""
    corners = np.asarray(vertices, dtype=np.float64)[faces]
    weighted = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # 2 x area x normal
    normals = np.zeros((len(vertices), 3))
    for k in range(3):
        np.add.at(normals, faces[:, k], weighted)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


class VertexPRT:
    """Per-vertex transfer (Sloan et al. 2002) interpolated across triangles by the rasteriser.

    Parameters
    ----------
    ctx : moderngl.Context
    geometry : prt.train.geometry.Geometry
        A mesh scene (not an SDF).
    front, back : (V, 16) float32
        Transfer at each vertex for its normal and for the reversed normal (used by open
        surfaces seen from behind).
    width, height : int

    Attributes
    ----------
    timings : dict
        ``raster`` and ``readback`` milliseconds of the last :meth:`render`.
    """

    def __init__(self, ctx, geometry, front, back, width: int, height: int):
        import moderngl

        self.ctx, self.width, self.height = ctx, int(width), int(height)
        faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
        record = np.dtype([("p", "<f4", 3), ("f", "<f4", 16), ("b", "<f4", 16), ("s", "<i4")])
        corners = np.empty((len(faces), 3), dtype=record)  # unindexed: sidedness is per face
        corners["p"] = np.asarray(geometry.mesh.vertices, dtype=np.float32)[faces]
        corners["f"] = front[faces]
        corners["b"] = back[faces]
        corners["s"] = np.asarray(geometry.two_sided, dtype=np.int32)[:, None]
        self.program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self.vbo = ctx.buffer(corners.tobytes())
        names = ["in_position", *(f"in_f{k}" for k in range(4)), *(f"in_b{k}" for k in range(4)), "in_two_sided"]
        self.vao = ctx.vertex_array(self.program, [(self.vbo, "3f 4f 4f 4f 4f 4f 4f 4f 4f 1i", *names)])
        self.count = 3 * len(faces)
        self.textures = [ctx.texture((self.width, self.height), 4, dtype="f4") for _ in range(4)]
        for tex in self.textures:
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.depth = ctx.depth_texture((self.width, self.height))
        self.fbo = ctx.framebuffer(self.textures, self.depth)
        self._staging = np.empty((4, self.height, self.width, 4), dtype=np.float32)
        self.timings: dict[str, float] = {}

    def render(self, camera):
        """Rasterise the interpolated transfer seen by ``camera``.

        Returns
        -------
        transfer : (H, W, 16) float32, row 0 at the top
        drawn : (H, W) bool, pixels a triangle covers
        """
        import moderngl

        t0 = time.perf_counter()
        self.program["u_view_projection"].write(camera.view_projection(self.width / self.height).T.astype(np.float32).tobytes())
        self.fbo.use()  # every pass of the renderer binds its own target, so none is restored
        self.ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.vao.render(moderngl.TRIANGLES, vertices=self.count)
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.ctx.finish()
        t1 = time.perf_counter()
        for k in range(4):
            self.fbo.read_into(self._staging[k], components=4, attachment=k, dtype="f4")
        transfer = np.ascontiguousarray(self._staging[:, ::-1].transpose(1, 2, 0, 3).reshape(self.height, self.width, 16))
        t2 = time.perf_counter()
        depth = np.frombuffer(self.fbo.read(attachment=-1, components=1, dtype="f4"), dtype=np.float32)
        self.timings = {"raster": 1e3 * (t1 - t0), "readback": 1e3 * (t2 - t1)}
        return transfer, depth.reshape(self.height, self.width)[::-1] < 1.0

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.program, self.fbo, self.depth, *self.textures):
            obj.release()


def vertex_transfer(geometry, tracer, rays: int, cache: Path, geometry_id: str):
    """Transfer at the mesh vertices: front (area-weighted normal) and back (reversed normal).

    Returns
    -------
    front, back : (V, 16) float32
        ``back`` equals ``front`` at vertices no open (two-sided) face uses.
    back_vertices : int
        Vertices that needed a second, back-side transfer vector.
    """
    vertices = np.asarray(geometry.mesh.vertices, dtype=np.float32)
    faces = np.asarray(geometry.mesh.faces, dtype=np.int64)
    normals = vertex_normals(vertices, faces).astype(np.float32)
    front, _ = cached_transfer(cache, "vertices-front", geometry, tracer, vertices, normals, rays, 0, geometry_id)
    back = front.copy()
    open_vertices = np.unique(faces[np.asarray(geometry.two_sided, dtype=bool)])
    if len(open_vertices):
        back[open_vertices], _ = cached_transfer(
            cache, "vertices-back", geometry, tracer, vertices[open_vertices], -normals[open_vertices], rays, 0, geometry_id
        )
    return front, back, int(len(open_vertices))


# =========================================================================== packing baseline


def naive_transfer(onnx, packed: np.ndarray, segment: np.ndarray):
    """Every network segment's model on every pixel, the right one picked per pixel afterwards.

    Parameters
    ----------
    onnx : prt.runtime.onnx_backend.OnnxTransfer
    packed : (P, 8) float32
        The packed G-buffer (all pixels, background included).
    segment : (P,) int
        Segment id per pixel, -1 on background.

    Returns
    -------
    transfer : (P, 16) float32
        Zero on background.
    inference_ms : float
        Total network time.
    rows_per_segment : dict of int to int
        Rows each network segment's model ran on (always P).
    """
    transfer = np.zeros((len(packed), onnx.n), dtype=np.float32)
    inference_ms, rows_per_segment = 0.0, {}
    for s in onnx.sessions:
        rows, values = onnx.compute(packed, np.full(len(packed), s, dtype=np.int32), columns=PACKED_COLUMNS)
        inference_ms += onnx.timings["inference"]
        rows_per_segment[s] = len(rows)
        mine = segment == s
        transfer[mine] = values[mine]
    for s in onnx.analytic:  # no network: the analytic segments cost the same either way
        mine = np.flatnonzero(segment == s)
        _, values = onnx.compute(packed[mine], np.full(len(mine), s, dtype=np.int32), columns=PACKED_COLUMNS)
        transfer[mine] = values
    return transfer, inference_ms, rows_per_segment


def packing_baseline(manifest, gbuffer_pass, cameras, log) -> dict:
    """Naive (all pixels through every network) against packed (covered pixels, by segment).

    Parameters
    ----------
    manifest : Manifest
    gbuffer_pass : prt.runtime.gbuffer.GBufferPass
        At the resolution to measure.
    cameras : list of Camera
    log : callable

    Returns
    -------
    dict
        See the module docstring (``scenes[].packing[]``).
    """
    from prt.runtime.onnx_backend import OnnxTransfer

    onnx = OnnxTransfer(manifest)
    naive_ms, packed_ms, covered_counts, diffs, rows = [], [], [], [], {}
    profile = None
    try:
        for i, camera in enumerate([cameras[0], *cameras]):  # the first pass warms the sessions up
            gbuffer_pass.render(camera)
            packed = gbuffer_pass.read_packed().copy()
            segment = packed[:, 7].astype(np.int32)
            covered, transfer = onnx.compute(packed, segment, columns=PACKED_COLUMNS)
            packed_time = onnx.timings["inference"]
            everywhere, naive_time, rows = naive_transfer(onnx, packed, segment)
            if i == 0:
                continue
            if profile is None:  # the first measured view: its largest network segment, one slice
                seg_cov = segment[covered]
                ids, counts = np.unique(seg_cov[np.isin(seg_cov, list(onnx.sessions))], return_counts=True)
                if len(ids):
                    s = int(ids[np.argmax(counts)])
                    x = packed[covered[seg_cov == s]][:, list(PACKED_COLUMNS)][: onnx.slice_rows]
                    model = next(seg.model for seg in manifest.segments if seg.id == s)
                    profile = {"segment": s, **profile_network(model, x)}
            packed_ms.append(packed_time)
            naive_ms.append(naive_time)
            covered_counts.append(len(covered))
            diffs.append(float(np.abs(everywhere[covered] - transfer).max(initial=0.0)))
    finally:
        onnx.close()
    all_pixels = gbuffer_pass.width * gbuffer_pass.height
    covered = float(np.median(covered_counts))
    naive, packed = float(np.median(naive_ms)), float(np.median(packed_ms))  # medians over the views
    result = {
        "resolution": f"{gbuffer_pass.width}x{gbuffer_pass.height}",
        "all_pixels": all_pixels,
        "covered_pixels": covered,
        "network_segments": len(rows),
        "naive_rows_per_segment": {str(s): n for s, n in rows.items()},
        "naive_total_rows": int(sum(rows.values())),
        "naive_inference_ms": round(naive, 3),
        "packed_inference_ms": round(packed, 3),
        "packing_speedup": round(naive / packed, 2) if packed > 0 else None,
        "pixel_ratio": round(all_pixels / covered, 2) if covered else None,
        "work_ratio": round(sum(rows.values()) / covered, 2) if covered else None,
        "naive_max_abs_diff": float(max(diffs, default=0.0)),
        "packing_views": len(packed_ms),
        "network_profile": profile,
    }
    log(
        f"  packing {result['resolution']}: naive {naive:.1f} ms ({len(rows)} x {all_pixels} rows) vs packed "
        f"{packed:.1f} ms ({covered:.0f} rows): {result['packing_speedup']}x; all/covered pixels {result['pixel_ratio']}x"
    )
    return result


def profile_network(model_path, x: np.ndarray, repeats: int = 30) -> dict:
    """Where one network's time goes: ONNX Runtime's own profiler, one thread, ``x`` as one call.

    Returns ``{"rows", "run_us"`` (median model run), ``"op_us"`` ({op type: median microseconds
    per run}), ``"gemm_share"`` (share of the run spent in the MLP's matrix products: Gemm and
    the FusedGemm ORT makes of Gemm + LeakyRelu; the encoding's tiny MatMuls are not counted)``}``.
    """
    import onnxruntime as ort

    with tempfile.TemporaryDirectory(prefix="prt_profile_") as folder:
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.intra_op_num_threads = 1
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(folder) / "profile")
        sess = ort.InferenceSession(str(model_path), opts, providers=["CPUExecutionProvider"])
        feed = {"x": np.ascontiguousarray(x, dtype=np.float32)}
        for _ in range(3):
            sess.run(None, feed)  # warm-up runs are profiled too; dropped below by run index
        for _ in range(repeats):
            sess.run(None, feed)
        events = json.loads(Path(sess.end_profiling()).read_text())
    runs = sorted((e for e in events if e.get("name") == "model_run"), key=lambda e: e["ts"])
    kept = runs[3:]
    nodes = [e for e in events if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time")]
    per_run = []  # {op type: microseconds} of each kept run: medians resist a preempted op or two
    for run in kept:
        ops: dict[str, float] = {}
        for e in nodes:
            if run["ts"] <= e["ts"] <= run["ts"] + run["dur"]:
                op = e.get("args", {}).get("op_name", "?")
                ops[op] = ops.get(op, 0.0) + e["dur"]
        per_run.append(ops)
    names = {op for ops in per_run for op in ops}
    op_us = {op: float(np.median([ops.get(op, 0.0) for ops in per_run])) for op in names}
    run_us = float(np.median([e["dur"] for e in kept])) if kept else 0.0
    gemm = sum(v for k, v in op_us.items() if k in ("Gemm", "FusedGemm"))
    return {
        "rows": int(len(x)),
        "run_us": round(run_us, 1),
        "op_us": {k: round(v, 1) for k, v in sorted(op_us.items(), key=lambda kv: -kv[1])},
        "gemm_share": round(gemm / run_us, 3) if run_us else None,
    }


# =========================================================================== the benchmark


@dataclasses.dataclass
class Settings:
    """What to measure (the command line's options)."""

    views: int = 30
    sizes: tuple = (512,)
    ref_rays: int = 1024
    warmup: int = 3
    config_budget: float | None = None  # seconds of frames per configuration (slow ones measure fewer views)
    packing_views: int | None = None  # views of the naive-vs-packed baseline (None: all), spread over the orbit
    precisions: tuple = PRECISIONS
    backends: tuple = ("onnx", "glsl", "vertex")
    cache: Path | None = None
    gemm_size: int = 4096
    seed: int = 0
    blas_threads: int | None = None
    fresh: bool = False  # re-measure scenes a checkpoint already holds
    images: Path | None = None  # folder for the error-map figures (None: none)


def _materials(manifest) -> dict:
    """The diffuse and glossy materials, both with the scene's albedo."""
    from prt.runtime.shading import Material

    albedo = tuple(float(a) for a in manifest.material["albedo"])
    return {"diffuse": Material("diffuse", albedo=albedo), "glossy": Material("glossy", albedo=albedo, **GLOSSY)}


def _segment_flops(manifest, segment_image) -> float:
    """Manifest FLOPs of evaluating the networks at every covered pixel of a segment-id image."""
    counts = np.bincount(segment_image[segment_image >= 0].ravel(), minlength=len(manifest.segments))
    return float(sum(counts[s.id] * s.flops_per_fragment for s in manifest.segments if s.kind == "network"))


@dataclasses.dataclass
class _View:
    """What every configuration of one view shares: camera, G-buffer, references, network FLOPs."""

    camera: object
    gbuffer: object
    references: dict  # material name -> tone-mapped (H, W, 3) reference image
    flops: float


def _summarise(stage_lists, metric_lists, gflops, frame_ms) -> dict:
    """Medians of timings, means of metrics over views."""
    frame = float(np.median(frame_ms))
    stages = {k: round(float(np.median(v)), 3) for k, v in stage_lists.items() if k != "frame"}
    out = {"fps": round(1000.0 / frame, 2), "frame_ms": round(frame, 3), "stages_ms": stages}
    out.update({k: float(np.mean(v)) for k, v in metric_lists.items()})
    out["achieved_gflops"] = round(float(np.median(gflops)), 3) if gflops else 0.0
    return out


def budget_views(views: list, budget_s: float | None, frame_s: float | None, least: int = 4) -> list:
    """The views one configuration measures under a time budget (``--config-budget``).

    All of them without a budget (or before any frame was timed); else as many as
    ``budget_s / frame_s`` allow, at least ``least``, spread evenly over the orbit and always
    starting at view 0 (whose transfer the precision variants are compared on).
    """
    if budget_s is None or frame_s is None or frame_s <= 0:
        return list(views)
    return spread(views, int(max(least, budget_s // frame_s)))


def spread(views: list, n: int | None) -> list:
    """``n`` of ``views`` evenly over the orbit, starting at view 0 (all when ``n`` is None or too many)."""
    if n is None or n >= len(views):
        return list(views)
    picks = np.unique(np.round(np.linspace(0, len(views) - 1, n)).astype(int)) if n > 1 else np.array([0])
    return [views[i] for i in picks]


def _measure_renderer(renderer, views, material_name, material, settings, transfer_fp32=None) -> tuple[dict, np.ndarray]:
    """Render every view with one material after warm-up; timings, metrics and view 0's transfer."""
    from prt.runtime.shading import tonemap

    kw = {"albedo": material.albedo}
    if material.kind == "glossy":
        kw.update(specular=material.specular, exponent=material.exponent)
    renderer.set_material(material.kind, **kw)
    warm_s = None
    for i in range(settings.warmup):  # sessions, shader compilation, caches; a new view each time
        renderer.set_camera_object(views[0].camera.orbit(0.01 * (i + 1)))
        t0 = time.perf_counter()
        renderer.render()
        warm_s = time.perf_counter() - t0
    measured = budget_views(views, settings.config_budget, warm_s)
    stages, metrics, gflops, frames = defaultdict(list), defaultdict(list), [], []
    transfer0 = None
    for k, view in enumerate(measured):
        renderer.set_camera_object(view.camera)
        image = renderer.render()
        for name, ms in renderer.timings.items():
            stages[name].append(ms)
        frames.append(renderer.timings["frame"])
        network_ms = renderer.timings.get("inference", renderer.timings.get("network", 0.0))
        if network_ms > 0:
            gflops.append(view.flops / (network_ms * 1e-3) / 1e9)
        for name, value in image_metrics(tonemap(image), view.references[material_name], view.gbuffer.covered).items():
            metrics[name].append(value)
        if k == 0:
            transfer0 = renderer.render_transfer()[view.gbuffer.covered]  # cached: no network runs
            image0 = tonemap(image)
    summary = _summarise(stages, metrics, gflops, frames)
    summary["network_ms"] = summary["stages_ms"].get("inference", summary["stages_ms"].get("network", 0.0))
    summary["views"] = len(measured)
    summary["_image0"] = image0  # for the error maps; not part of the record
    if transfer_fp32 is not None:
        summary["transfer_max_abs_diff"] = float(np.abs(transfer0 - transfer_fp32).max(initial=0.0))
    return summary, transfer0


def _measure_vertex(vertex, gbuffer_pass, views, material_name, material, lighting, settings) -> dict:
    """The vertex baseline's frames: G-buffer pass + transfer raster + CPU shading, and its errors."""
    from prt.runtime.shading import shade, tonemap

    def frame(camera):
        t0 = time.perf_counter()
        gbuffer_pass.render(camera)
        packed = gbuffer_pass.read_packed()
        t1 = time.perf_counter()
        transfer, _ = vertex.render(camera)
        t2 = time.perf_counter()
        covered = np.flatnonzero(packed[:, 3] > 0.5)
        rows, t = packed[covered], transfer.reshape(-1, 16)[covered]
        if material.kind == "diffuse":  # the renderer's own float32 fast path
            radiance = np.maximum(t @ (lighting.sh * np.asarray(material.albedo)).astype(np.float32), 0.0)
        else:
            radiance = shade(t, rows[:, 4:7], camera.eye[None, :] - rows[:, 0:3], lighting, material)
        image = np.zeros((len(packed), 3), dtype=np.float32)
        image[covered] = radiance
        t3 = time.perf_counter()
        timings = {"gbuffer": 1e3 * (t1 - t0), **vertex.timings, "shade": 1e3 * (t3 - t2)}
        timings["frame"] = 1e3 * (t3 - t0)
        return image.reshape(vertex.height, vertex.width, 3), timings

    for i in range(settings.warmup):
        frame(views[0].camera.orbit(0.01 * (i + 1)))
    stages, metrics, frames = defaultdict(list), defaultdict(list), []
    image0 = None
    for view in views:
        image, timings = frame(view.camera)
        image0 = tonemap(image) if image0 is None else image0
        for name, ms in timings.items():
            stages[name].append(ms)
        frames.append(timings["frame"])
        for name, value in image_metrics(tonemap(image), view.references[material_name], view.gbuffer.covered).items():
            metrics[name].append(value)
    summary = _summarise(stages, metrics, [], frames)
    summary["network_ms"] = 0.0
    summary["_image0"] = image0
    return summary


class SceneBench:
    """Every configuration of one scene (see the module docstring).

    Parameters
    ----------
    scene_path : path-like
    settings : Settings
    ctx : moderngl.Context
        Shared by every renderer of the run.
    machine_gflops : float
    log : callable
    """

    def __init__(self, scene_path, settings: Settings, ctx, machine_gflops: float, log):
        from prt.runtime.renderer import Scene
        from prt.train.transfer import make_tracer

        self.settings, self.ctx, self.machine_gflops, self.log = settings, ctx, machine_gflops, log
        self.scene = Scene.load(scene_path)
        manifest = self.manifest = self.scene.manifest
        self.geometry, geo_info = load_scene_geometry(manifest)
        if geo_info["matches_build_source"] is False:
            log(f"  warning: {manifest.root / 'build.json'}'s source no longer gives geometry.npz's mesh; using geometry.npz")
        self.geometry_id = geo_info["checksum"] or f"sdf:{geo_info['source']}"
        self.tracer = make_tracer(self.geometry)
        self.cache = settings.cache / manifest.name  # this scene's precision variants
        # Ray-traced transfer is keyed by its inputs (points, normals, rays, seed, geometry), so
        # scenes of one mesh (k = 64, k = 128, right-sized) share their references and vertices.
        self.transfer_cache = settings.cache / "transfer"
        self.cameras = orbit_cameras(manifest, settings.views)
        self.materials = _materials(manifest)
        self.variants = {p: variant_manifest(manifest, p, self.cache / "models") for p in settings.precisions}
        self.weights = {p: model_weight_bytes(m) for p, m in self.variants.items()}
        self.vertex_data, vertex_info = self._vertex_transfer()
        self.entry = {
            "scene": manifest.name, "path": str(manifest.path), "geometry": geo_info,
            "networks": sum(s.kind == "network" for s in manifest.segments), "weight_bytes": self.weights["fp32"],
            "reference": {"rays": settings.ref_rays, "seed": settings.seed, "cache": str(self.transfer_cache), "noise_psnr": {},
                          "noise_note": "PSNR between two references with different seeds at view 0 (covered pixels); "
                                        "each is ~3 dB closer to the converged image than this"},
            "packing": [], "vertex_baseline": vertex_info, "error_images": [],
        }  # fmt: skip
        self.records: list[dict] = []
        self.images: dict = defaultdict(list)  # (resolution, material) -> [(label, view 0 image, its PSNR)]

    def run(self) -> tuple[dict, list]:
        """Measure every size; returns the ``scenes[]`` entry and the ``records[]`` of this scene."""
        from prt.runtime.renderer import Renderer

        for size in self.settings.sizes:
            # This renderer's G-buffer defines the pixels; every other renderer draws the same ones.
            with Renderer(self.scene, size, size, backend="onnx", ctx=self.ctx) as base:
                views = self._references(base, size)
                if self.entry["networks"] and "onnx" in self.settings.backends:
                    cameras = spread(self.cameras, self.settings.packing_views)
                    self.entry["packing"].append(packing_baseline(self.manifest, base.gbuffer, cameras, self.log))
                self._network_records(size, views)
                if self.vertex_data is not None:
                    self._vertex_records(size, views, base.gbuffer, base.lighting)
                if self.settings.images is not None:
                    path = Path(self.settings.images) / f"{self.manifest.name}-{size}x{size}.png"
                    error_figure(views[0], {m: self.images[(f"{size}x{size}", m)] for m in self.materials}, path,
                                 f"{self.manifest.name} {size}x{size}, view 0")  # fmt: skip
                    self.entry["error_images"].append(str(path))
                    self.log(f"  error maps: {path}")
        return self.entry, self.records

    # ------------------------------------------------------------------ pieces

    def _vertex_transfer(self):
        """Per-vertex transfer of the vertex baseline and its ``vertex_baseline`` entry."""
        if self.geometry.sdf is not None:
            return None, {"note": "skipped: SDF scene (no vertices)"}
        if "vertex" not in self.settings.backends:
            return None, {"note": "skipped (--backends)"}
        front, back, back_vertices = vertex_transfer(self.geometry, self.tracer, self.settings.ref_rays, self.transfer_cache, self.geometry_id)
        n_vertices = len(self.geometry.mesh.vertices)
        info = {"vertices": n_vertices, "back_vertices": back_vertices,
                "weight_bytes": 16 * 4 * (n_vertices + back_vertices), "rays": self.settings.ref_rays}  # fmt: skip
        return (front, back), info

    def _references(self, renderer, size: int) -> list:
        """The views at ``size``: G-buffers, reference images (cached transfer) and the reference's noise."""
        from prt.runtime.shading import tonemap

        settings, resolution = self.settings, f"{size}x{size}"
        views, seconds = [], 0.0
        for v, camera in enumerate(self.cameras):
            renderer.set_camera_object(camera)
            gbuffer = renderer.gbuffer_image()
            points, normals = gbuffer.position[gbuffer.covered], gbuffer.normal[gbuffer.covered]
            tag = f"view{v:03d}-{resolution}"
            images = {}
            # A second seed (other frame spins) at view 0 measures the reference's own noise.
            for seed in (settings.seed, settings.seed + 1) if v == 0 else (settings.seed,):
                transfer, spent = cached_transfer(
                    self.transfer_cache, tag, self.geometry, self.tracer, points, normals, settings.ref_rays, seed, self.geometry_id
                )
                seconds += spent
                images[seed] = {
                    m: tonemap(shade_image(transfer, gbuffer, camera.eye, renderer.lighting, material))
                    for m, material in self.materials.items()
                }
            references = images[settings.seed]
            if v == 0:
                other = images[settings.seed + 1]
                self.entry["reference"]["noise_psnr"][resolution] = {
                    m: round(image_metrics(other[m], references[m], gbuffer.covered)["psnr"], 2) for m in references
                }
            views.append(_View(camera, gbuffer, references, _segment_flops(self.manifest, gbuffer.segment)))
        self.log(
            f"  reference {resolution}: {len(views)} views x {settings.ref_rays} rays ({seconds:.1f} s computed, "
            f"rest cached); noise PSNR {self.entry['reference']['noise_psnr'][resolution]}"
        )
        return views

    def _common(self, size: int, views: list) -> dict:
        """The fields every record of this scene and size shares."""
        covered = [int(v.gbuffer.covered.sum()) for v in views]
        flops = sum(v.flops for v in views)
        return {
            "scene": self.manifest.name, "resolution": f"{size}x{size}", "width": size, "height": size,
            "views": len(views), "covered_pixels": float(np.median(covered)),
            "flops_per_fragment": round(flops / sum(covered), 1) if sum(covered) else 0.0,
            "machine_gflops": round(self.machine_gflops, 2), "ref_rays": self.settings.ref_rays,
        }  # fmt: skip

    def _add(self, common: dict, backend: str, precision: str, material: str, summary: dict, weight_bytes: int) -> None:
        noise = self.entry["reference"]["noise_psnr"][common["resolution"]][material]
        image0 = summary.pop("_image0", None)
        record = _record(common, backend, precision, material, summary, weight_bytes, noise, self.log)
        self.records.append(record)
        if image0 is not None:
            self.images[(common["resolution"], material)].append((record["label"], image0))

    def _network_records(self, size: int, views: list) -> None:
        """The ONNX backend at every precision, then the GLSL backend, each with both materials."""
        from prt.runtime.renderer import Renderer, Scene

        configs = [("onnx", p) for p in self.settings.precisions] if "onnx" in self.settings.backends else []
        if "glsl" in self.settings.backends:
            configs.append(("glsl", "fp32"))
        common = self._common(size, views)
        transfer_fp32 = None  # view 0's transfer on the fp32 ONNX path, what the others are compared with
        for backend, precision in configs:
            scene = Scene(self.variants[precision]) if backend == "onnx" else self.scene
            with Renderer(scene, size, size, backend=backend, ctx=self.ctx) as renderer:
                for name, material in self.materials.items():
                    summary, transfer0 = _measure_renderer(renderer, views, name, material, self.settings, transfer_fp32)
                    if (backend, precision) == ("onnx", "fp32"):
                        transfer_fp32 = transfer0
                        summary["transfer_max_abs_diff"] = 0.0
                    self._add(common, backend, precision, name, summary, self.weights[precision])

    def _vertex_records(self, size: int, views: list, gbuffer_pass, lighting) -> None:
        """The vertex baseline with both materials, and how well its pixels match the G-buffer's."""
        resolution = f"{size}x{size}"
        info = self.entry["vertex_baseline"]
        common = {**self._common(size, views), "flops_per_fragment": 0.0}
        vertex = VertexPRT(self.ctx, self.geometry, *self.vertex_data, size, size)
        try:
            agreement = []
            for view in views:
                drawn = vertex.render(view.camera)[1]
                covered = view.gbuffer.covered
                agreement.append(np.logical_and(drawn, covered).sum() / max(covered.sum(), 1))
            info.setdefault("coverage_agreement", {})[resolution] = round(float(np.min(agreement)), 5)
            for name, material in self.materials.items():
                summary = _measure_vertex(vertex, gbuffer_pass, views, name, material, lighting, self.settings)
                summary.update(achieved_gflops=0.0, transfer_max_abs_diff=None)
                self._add(common, "vertex", "fp32", name, summary, info["weight_bytes"])
        finally:
            vertex.release()


def _record(common, backend, precision, material, summary, weight_bytes, noise_psnr, log) -> dict:
    """One configuration's JSON record (rounded), printed as a progress line."""
    record = {**common, "backend": backend, "precision": precision, "material": material, **summary}
    for key in ("mae", "ssim"):
        record[key] = round(record[key], 6)
    for key in ("psnr", "psnr_whole"):
        record[key] = round(record[key], 3)
    record["weight_bytes"] = int(weight_bytes)
    gflops = record.get("achieved_gflops", 0.0)
    record["machine_percent"] = round(100.0 * gflops / record["machine_gflops"], 3) if record["machine_gflops"] else None
    record["ref_noise_psnr"] = noise_psnr
    record["label"] = f"{backend} {precision} {material}" if backend == "onnx" else f"{backend} {material}"
    record.setdefault("transfer_max_abs_diff", None)
    log(
        f"  {record['scene']} {record['resolution']} {record['label']}: {record['fps']:.1f} FPS "
        f"({record['frame_ms']:.1f} ms, network {record['network_ms']:.1f} ms), PSNR {record['psnr']:.2f} dB "
        f"(whole {record['psnr_whole']:.2f}), SSIM {record['ssim']:.4f}, MAE {record['mae']:.4f}"
    )
    return record


def _group_key(record: dict) -> str:
    """Configurations compete only with the same scene, resolution and material (the same reference)."""
    return f"{record['scene']} {record['resolution']} {record['material']}"


def mark_pareto(records: list) -> dict:
    """Set ``record["pareto"]`` per (scene, resolution, material); return each front's labels."""
    groups = defaultdict(list)
    for r in records:
        groups[_group_key(r)].append(r)
    fronts = {}
    for name, group in groups.items():
        front = pareto_front([(r["fps"], r["psnr"]) for r in group])
        for i, r in enumerate(group):
            r["pareto"] = i in front
        fronts[name] = [group[i]["label"] for i in front]
    return fronts


ERROR_MAP_MAX = 0.05  # |error| (tone-mapped, channel mean) at the top of the error maps' colour scale


def error_figure(view, images: dict, path: Path, title: str) -> None:
    """View 0's reference and each configuration's error map, one row per material (PNG).

    ``images``: material -> [(label, tone-mapped image)].  Every error map shares one colour
    scale (0 to :data:`ERROR_MAP_MAX`), so panels compare at a glance; each title gives the
    view's PSNR over covered pixels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    covered = view.gbuffer.covered
    rows = [m for m in images if images[m]]
    cols = 1 + max((len(images[m]) for m in rows), default=0)
    panel = max(2.6, covered.shape[1] / 70)  # inches: about one image pixel per figure pixel or more, at 100 dpi
    fig, axes = plt.subplots(len(rows), cols, figsize=(panel * cols + 0.8, (panel + 0.3) * len(rows) + 0.3), squeeze=False,
                             layout="constrained")
    shown = None
    for i, material in enumerate(rows):
        reference = view.references[material]
        axes[i, 0].imshow(np.clip(reference, 0, 1))
        axes[i, 0].set_title(f"reference ({material})", fontsize=9)
        for j, (label, image) in enumerate(images[material], start=1):
            error = np.abs(image - reference).mean(axis=2)
            error[~covered] = np.nan
            shown = axes[i, j].imshow(error, cmap="magma", vmin=0.0, vmax=ERROR_MAP_MAX)
            axes[i, j].set_facecolor("#d0d0d0")
            psnr = image_metrics(image, reference, covered)["psnr"]
            axes[i, j].set_title(f"{label.replace(f' {material}', '')}: {psnr:.1f} dB", fontsize=9)
        for ax in axes[i]:
            ax.set_xticks([])
            ax.set_yticks([])
        for ax in axes[i, len(images[material]) + 1:]:
            ax.set_visible(False)
    fig.suptitle(f"{title}: |error| of tone-mapped images (grey: not covered)", fontsize=10)
    if shown is not None:
        fig.colorbar(shown, ax=axes, shrink=0.8, label="|error|")
    _save_figure(fig, path, dpi=100)


# Settings that change what a scene's measurement is (the cache only says where things live).
_CHECKPOINT_SETTINGS = ("views", "sizes", "ref_rays", "warmup", "config_budget", "packing_views", "precisions",
                        "backends", "gemm_size", "seed", "blas_threads")  # fmt: skip


def scene_checkpoint(scene_path, settings: Settings) -> Path:
    """Where one scene's finished measurement is kept, keyed by its files and the settings.

    The key covers ``scene.json`` and every file it names (models, generated GLSL, weight
    textures, geometry, environment map) plus ``geometry.npz``, so a rebuilt scene or other
    settings never reuse an old measurement.
    """
    from prt.runtime.manifest import load_manifest

    manifest = load_manifest(scene_path)
    digest = hashlib.sha256()
    files = [manifest.path, manifest.geometry.get("path"), manifest.lighting.get("envmap"), manifest.root / "geometry.npz"]
    for segment in manifest.segments:
        files += [segment.model, segment.glsl, segment.glsl_weights]
    for f in dict.fromkeys(Path(f) for f in files if f is not None and Path(f).is_file()):
        digest.update(f.name.encode())
        digest.update(f.read_bytes())
    options = {k: getattr(settings, k) for k in _CHECKPOINT_SETTINGS}
    if settings.images is not None:  # (only then, so keys made before --images existed still match)
        options["images"] = str(settings.images)
    options["prt"] = _prt_version()  # a new release measures again
    digest.update(json.dumps(options, sort_keys=True, default=list).encode())
    return settings.cache / "results" / f"{manifest.name}-{digest.hexdigest()[:16]}.json"


def _prt_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("prt-runtime")
    except PackageNotFoundError:
        return "unknown"


def _save_figure(fig, path, dpi: int) -> None:
    """PNG through a temporary file and a rename (an interrupted run leaves no half image)."""
    import io

    import matplotlib.pyplot as plt

    from prt.runtime.files import atomic_write_bytes

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())


def run(scene_paths, settings: Settings, log=print) -> dict:
    """Benchmark every scene; the report described in the module docstring.

    Parameters
    ----------
    scene_paths : list of path-like
    settings : Settings
    log : callable
        Receives one progress line at a time.

    Returns
    -------
    dict
    """
    import onnxruntime
    from threadpoolctl import threadpool_limits

    from prt.runtime.files import atomic_write_json

    from prt.runtime.gl import create_context

    settings.cache = Path(settings.cache or Path(tempfile.gettempdir()) / "prt_bench_cache")
    load_start = os.getloadavg()[0]
    if load_start > 0.5:
        log(f"note: load average {load_start:.2f} at the start: other work on this machine will slow the timings")
    busy_start = _busy_seconds()
    t0 = time.perf_counter()
    gemm = machine_gemm(settings.gemm_size)
    machine_gflops = gemm["best"]
    log(f"machine: float32 GEMM {settings.gemm_size}^3: numpy {gemm['numpy']:.1f}, onnxruntime {gemm['onnxruntime']:.1f} GFLOP/s "
        f"({time.perf_counter() - t0:.1f} s); the limit is the higher")
    ctx = create_context()
    try:
        machine = {
            "cpu": _cpu_name(), "cores": os.cpu_count(), "gl_renderer": ctx.info.get("GL_RENDERER"),
            "onnxruntime": onnxruntime.__version__, "numpy": np.__version__,
            "gemm_size": settings.gemm_size, "gemm_numpy_gflops": gemm["numpy"],
            "gemm_onnxruntime_gflops": gemm["onnxruntime"], "machine_gflops": machine_gflops,
        }  # fmt: skip
        scenes, records, resumed = [], [], []
        # numpy's BLAS threads also run the renderer's small shading products (None: as found).
        limits = threadpool_limits(limits=settings.blas_threads, user_api="blas") if settings.blas_threads else None
        try:
            for path in scene_paths:
                # Each finished scene is kept, so an interrupted run resumes at the scene it was on.
                checkpoint = scene_checkpoint(path, settings)
                if checkpoint.exists() and not settings.fresh:
                    kept = json.loads(checkpoint.read_text())
                    entry, recs = kept["scene"], kept["records"]
                    entry.setdefault("error_images", [])
                    resumed.append({"scene": entry["scene"], "measured": entry["measured"]})
                    log(f"scene {path}: measured at {entry['measured']} (against a {recs[0]['machine_gflops'] if recs else '?'} "
                        f"GFLOP/s limit), kept in {checkpoint}; --fresh measures it again")  # fmt: skip
                else:
                    log(f"scene {path}")
                    entry, recs = SceneBench(path, settings, ctx, machine_gflops, log).run()
                    entry["measured"] = datetime.datetime.now().isoformat(timespec="seconds")
                    entry["checkpoint"] = str(checkpoint)
                    atomic_write_json(checkpoint, {"scene": entry, "records": recs})
                scenes.append(entry)
                records.extend(recs)
        finally:
            if limits is not None:
                limits.restore_original_limits()
    finally:
        ctx.release()
    machine["resumed"] = resumed
    machine["load_average"] = round(load_start, 2)
    machine["other_cpu_share"] = _other_cpu_share(busy_start, time.perf_counter() - t0)
    fronts = mark_pareto(records)
    config = {k: (str(v) if isinstance(v, Path) else list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()}
    return {
        "tool": "prt-bench", "created": datetime.datetime.now().isoformat(timespec="seconds"),
        "settings": config, "machine": machine, "scenes": scenes, "records": records, "pareto": fronts,
    }  # fmt: skip


# =========================================================================== output


def markdown(report: dict) -> str:
    """The report as Markdown: the configurations' table, then packing, reference and machine lines."""
    machine = report["machine"]
    lines = [
        "| scene | size | backend | precision | material | FPS | frame ms | network ms | PSNR (covered) | PSNR (whole) "
        "| SSIM | MAE | weights (bytes) | network GFLOP/s (% of GEMM) | Pareto |",
        "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|:-:|",
    ]
    settings_views = report["settings"]["views"]
    for r in report["records"]:
        gflops = f"{r['achieved_gflops']:.1f} ({r['machine_percent']:.1f} %)" if r["achieved_gflops"] else "-"
        fps = f"{r['fps']:.1f}" + (f" ({r['views']} views)" if r["views"] != settings_views else "")
        lines.append(
            f"| {r['scene']} | {r['resolution']} | {r['backend']} | {r['precision']} | {r['material']} | {fps} "
            f"| {r['frame_ms']:.1f} | {r['network_ms']:.1f} | {r['psnr']:.2f} | {r['psnr_whole']:.2f} | {r['ssim']:.4f} "
            f"| {r['mae']:.4f} | {r['weight_bytes']:,} | {gflops} | {'*' if r.get('pareto') else ''} |"
        )
    lines.append("")
    for s in report["scenes"]:
        ref = s["reference"]
        lines.append(f"**{s['scene']}**: reference {ref['rays']} rays per pixel; its noise (two seeds, view 0): "
                     + "; ".join(f"{res}: " + ", ".join(f"{m} {db:.1f} dB" for m, db in d.items()) for res, d in ref["noise_psnr"].items()))  # fmt: skip
        for p in s["packing"]:
            lines.append(
                f"- packing {p['resolution']} ({p.get('packing_views', '?')} views): naive {p['naive_inference_ms']:.1f} ms ({p['network_segments']} networks x "
                f"{p['all_pixels']:,} pixels) vs packed {p['packed_inference_ms']:.1f} ms ({p['covered_pixels']:,.0f} covered): "
                f"speed-up {p['packing_speedup']}x; all / covered pixels {p['pixel_ratio']}x, naive rows / covered {p['work_ratio']}x"
            )
            prof = p.get("network_profile")
            if prof:
                top = ", ".join(f"{op} {us / prof['run_us']:.0%}" for op, us in list(prof["op_us"].items())[:6])
                lines.append(f"- network profile (segment {prof['segment']}, {prof['rows']:,} rows, one thread): {prof['run_us']:.0f} us per call, "
                             f"{prof['gemm_share']:.0%} in the MLP's Gemms; {top}")  # fmt: skip
        vb = s["vertex_baseline"]
        if "note" in vb:
            lines.append(f"- vertex baseline: {vb['note']}")
        elif vb:
            lines.append(f"- vertex baseline: {vb['vertices']:,} vertices (+{vb['back_vertices']:,} back sides) x 16 float32 = "
                         f"{vb['weight_bytes']:,} bytes vs {s['weight_bytes']:,} bytes of network weights (fp32 ONNX initialisers)")  # fmt: skip
    gemm = f"numpy {machine['gemm_numpy_gflops']:.1f}, onnxruntime {machine['gemm_onnxruntime_gflops']:.1f}" if "gemm_numpy_gflops" in machine else "numpy"
    if machine.get("resumed"):
        times = sorted(r["measured"] for r in machine["resumed"])
        lines.append(f"\n{len(times)} of {len(report['scenes'])} scenes taken from checkpoints of an earlier run "
                     f"(measured {times[0]} to {times[-1]}); their records keep that run's GEMM limit.")  # fmt: skip
    lines.append(f"\nMachine: {machine['cpu']}, {machine['cores']} cores, {machine['gl_renderer']}; float32 GEMM "
                 f"({machine['gemm_size']}^3; {gemm}): limit {machine['machine_gflops']:.1f} GFLOP/s.")  # fmt: skip
    settings = report["settings"]
    lines.append(f"Settings: {settings['views']} views, warm-up {settings['warmup']} frames, numpy BLAS threads while "
                 f"rendering: {settings['blas_threads'] or 'as found'}.")  # fmt: skip
    if machine.get("other_cpu_share") is not None:
        lines.append(f"Load: {machine['load_average']:.2f} at the start; other processes used "
                     f"{100 * machine['other_cpu_share']:.0f} % of the cores' time during the run.")  # fmt: skip
    return "\n".join(lines) + "\n"


def plot(report: dict, path: Path) -> None:
    """FPS (log) against PSNR, one panel per scene and resolution, Pareto fronts connected."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, NullFormatter

    groups = defaultdict(list)
    for r in report["records"]:
        groups[f"{r['scene']} {r['resolution']}"].append(r)
    cols = min(3, len(groups))  # a grid, so a many-scene report stays readable
    rows = -(-len(groups) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(8.5 * cols, 6.0 * rows), squeeze=False)
    for ax in axes.flat[len(groups):]:
        ax.set_visible(False)
    colours = {"onnx": "tab:blue", "glsl": "tab:orange", "vertex": "tab:green"}
    markers = {"diffuse": "o", "glossy": "s"}
    for ax, (name, group) in zip(axes.flat, groups.items()):
        for r in group:
            ax.scatter(r["fps"], r["psnr"], c=colours.get(r["backend"], "grey"), marker=markers[r["material"]], s=36, zorder=3)
        for material, style in (("diffuse", "-"), ("glossy", "--")):
            same = [r for r in group if r["material"] == material]
            front = [same[i] for i in pareto_front([(r["fps"], r["psnr"]) for r in same])]
            ax.plot([r["fps"] for r in front], [r["psnr"] for r in front], style, color="crimson", lw=1.2, zorder=2)
            ax.scatter([r["fps"] for r in front], [r["psnr"] for r in front], s=150, facecolors="none", edgecolors="crimson", zorder=4)
        ax.set_xscale("log")
        ax.margins(x=0.25, y=0.2)  # room for the labels
        ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        fps = [r["fps"] for r in group if r["fps"] > 0]
        if fps and max(fps) / min(fps) < 20:  # minor labels only where they fit (one or two decades)
            ax.xaxis.set_minor_formatter(FormatStrFormatter("%g"))
            ax.tick_params(axis="x", which="minor", labelsize=7)
        else:
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("FPS (log scale)")
        ax.set_ylabel("PSNR over covered pixels (dB)")
        ax.set_title(f"{name}: speed against error")
        ax.grid(True, which="both", alpha=0.3)
        handles = [plt.Line2D([], [], color=c, marker="o", ls="", label=b) for b, c in colours.items()]
        handles += [plt.Line2D([], [], color="k", marker=m, ls="", label=k) for k, m in markers.items()]
        handles.append(plt.Line2D([], [], color="crimson", marker="o", mfc="none", label="Pareto front, diffuse"))
        handles.append(plt.Line2D([], [], color="crimson", ls="--", marker="o", mfc="none", label="Pareto front, glossy"))
        ax.legend(handles=handles, fontsize=8, loc="best")
    fig.tight_layout()  # before the labels: they are placed in final display coordinates
    fig.canvas.draw()
    for ax, group in zip(axes.flat, groups.values()):
        _place_labels(fig, ax, [(r["fps"], r["psnr"], r["label"]) for r in group])
    _save_figure(fig, path, dpi=120)


def _place_labels(fig, ax, points) -> None:
    """Label each point at the nearby offset where its text covers the least of other labels and markers.

    Labels pushed beyond the first ring of offsets get a thin leader line to their point.
    """
    from matplotlib.transforms import Bbox

    near = [(6, 4), (6, -11), (-6, 4), (-6, -11)]
    far = [(dx, dy) for dy in (16, -23, 28, -35, 40, -47) for dx in (10, -10)]
    renderer = fig.canvas.get_renderer()
    inside = ax.get_window_extent(renderer)
    placed = []
    for x, y, _ in points:  # markers count as occupied space
        px, py = ax.transData.transform((x, y))
        placed.append(Bbox([[px - 6, py - 6], [px + 6, py + 6]]))

    def cost(box) -> float:
        covered = sum(b.width * b.height for b in (Bbox.intersection(box, other) for other in placed) if b is not None)
        clipped = box.width * box.height - (lambda b: b.width * b.height if b is not None else 0.0)(Bbox.intersection(box, inside))
        return covered + 10.0 * clipped  # text outside the axes is worse than touching a neighbour

    for x, y, text in sorted(points, key=lambda p: (-p[1], p[0])):
        best = None
        for k, (dx, dy) in enumerate(near + far):
            leader = dict(arrowstyle="-", lw=0.5, color="grey", shrinkA=0, shrinkB=4) if k >= len(near) else None
            label = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=7,
                                ha="left" if dx > 0 else "right", arrowprops=leader)  # fmt: skip
            box = label.get_window_extent(renderer).expanded(1.02, 1.15)
            score = cost(box)
            if best is None or score < best[0]:
                if best is not None:
                    best[1].remove()
                best = (score, label, box)
            else:
                label.remove()
            if score == 0.0:
                break
        placed.append(best[2])


# =========================================================================== command line


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="+", type=Path, help="scene.json files (or their folders)")
    p.add_argument("--json", type=Path, default=None, help="write the JSON report here")
    p.add_argument("--md", type=Path, default=None, help="write the Markdown table here")
    p.add_argument("--plot", type=Path, default=None, help="write the FPS-PSNR plot (PNG) here")
    p.add_argument("--views", type=int, default=30, help="orbit views per configuration (default 30)")
    p.add_argument("--size", type=int, nargs="+", default=[512], help="image sizes, square (default 512)")
    p.add_argument("--ref-rays", type=int, default=1024, help="rays per pixel of the reference (default 1024)")
    p.add_argument("--warmup", type=int, default=3, help="frames before timing each configuration (default 3)")
    p.add_argument("--packing-views", type=int, default=None, metavar="N",
                   help="views of the naive-vs-packed baseline, spread over the orbit (default: all; the naive path "
                        "runs every pixel through every network, seconds per view at 512x512)")  # fmt: skip
    p.add_argument("--config-budget", type=float, default=None, metavar="SECONDS",
                   help="time budget of one configuration's frames: one slower than budget/views per frame (the GLSL "
                        "backend at k = 128 on llvmpipe) measures fewer views, at least 4, spread over the orbit; "
                        "its record's 'views' says how many (default: every view)")  # fmt: skip
    p.add_argument("--precisions", nargs="+", choices=PRECISIONS, default=list(PRECISIONS))
    p.add_argument("--backends", nargs="+", choices=("onnx", "glsl", "vertex"), default=["onnx", "glsl", "vertex"])
    p.add_argument("--cache", type=Path, default=None, help="reference / variant cache (default: next to --json)")
    p.add_argument("--gemm-size", type=int, default=4096, help="matrix size of the machine-limit GEMM (default 4096)")
    p.add_argument("--blas-threads", type=int, default=None,
                   help="limit numpy's BLAS threads while rendering (default: leave as found)")  # fmt: skip
    p.add_argument("--images", type=Path, default=None, metavar="DIR",
                   help="write one PNG per scene and size into DIR: view 0's reference and every configuration's "
                        "error map, on one colour scale")  # fmt: skip
    p.add_argument("--fresh", action="store_true",
                   help="measure every scene again (default: a scene measured earlier with the same files and "
                        "settings is taken from its checkpoint in the cache, so an interrupted run resumes)")  # fmt: skip
    args = p.parse_args(argv)
    if args.views < 1 or min(args.size) < 1 or args.ref_rays < 1 or args.warmup < 0:
        p.error("--views, --size and --ref-rays must be positive, --warmup >= 0")
    if "fp32" not in args.precisions:
        args.precisions = ["fp32", *args.precisions]  # the other precisions are compared with it
    return args


def main(argv=None) -> int:
    from prt.runtime.files import atomic_write_bytes, atomic_write_json

    args = parse_args(argv)
    cache = args.cache
    if cache is None and args.json is not None:
        cache = args.json.parent / f"{args.json.stem}_cache"
    settings = Settings(
        views=args.views, sizes=tuple(args.size), ref_rays=args.ref_rays, warmup=args.warmup, config_budget=args.config_budget,
        packing_views=args.packing_views,
        precisions=tuple(dict.fromkeys(args.precisions)), backends=tuple(args.backends), cache=cache,
        gemm_size=args.gemm_size, blas_threads=args.blas_threads, fresh=args.fresh, images=args.images,
    )  # fmt: skip
    report = run(args.scenes, settings)
    text = markdown(report)
    print(text)
    if args.json:
        atomic_write_json(args.json, report)
    if args.md:
        atomic_write_bytes(args.md, text.encode())
    if args.plot:
        plot(report, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
