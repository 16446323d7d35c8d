"""Hostile inputs to the runtime commands, ``prt-runtime`` (``rt-*``) and ``prt-bench`` (``bench-*``).

Every case starts from one tiny valid scene made here (a two-triangle mesh, one linear ONNX
network and its GLSL twin, 16 SH lighting rows) and breaks one thing: the JSON, a field, a
path, a file the manifest names (ONNX models are written with the ``onnx`` package, a dev
dependency; the runtime itself never imports it), or a flag.  Most fail while the manifest is
read; those that need a frame render 8x8 pixels once.  Nothing is left behind: no output
folder is created for a command that fails.
"""

from __future__ import annotations

import copy
import io
import json
import struct

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from corpus import Case

OUT = "{run}/out"  # never created by a failing case
FAST = ["--headless", "--size", "8", "--frames", "1"]
BENCH_FAST = ["--size", "8", "--views", "1", "--ref-rays", "4", "--warmup", "0", "--gemm-size", "16",
              "--backends", "onnx", "--precisions", "fp32", "--json", "{run}/report.json"]  # fmt: skip


# --------------------------------------------------------------------------- the valid scene


def _model(weight=None, bias=None, *, input_name="x", input_type=TensorProto.FLOAT, width=6, outputs=16,
           external=None, second_input=False, external_in_attribute=False) -> bytes:
    """A linear network x @ W + b as ONNX bytes (opset 17); ``external`` makes W external data at that location."""
    w = np.zeros((width, outputs), np.float32) if weight is None else weight
    b = np.full(outputs, 0.05, np.float32) if bias is None else bias
    b[0] = 0.6 if bias is None else b[0]
    w_init = numpy_helper.from_array(w, "W")
    if external is not None:
        w_init.ClearField("raw_data")
        w_init.data_location = TensorProto.EXTERNAL
        w_init.external_data.add(key="location", value=external)
        w_init.external_data.add(key="offset", value="0")
        w_init.external_data.add(key="length", value=str(w.nbytes))
    nodes = [helper.make_node("MatMul", [input_name, "W"], ["xw"]), helper.make_node("Add", ["xw", "B"], ["y"])]
    inits = [w_init]
    b_init = numpy_helper.from_array(b, "B")
    if external_in_attribute:  # B comes from a Constant node whose tensor is external
        b_init.ClearField("raw_data")
        b_init.data_location = TensorProto.EXTERNAL
        b_init.external_data.add(key="location", value="/etc/hostname")
        nodes.insert(0, helper.make_node("Constant", [], ["B"], value=b_init))
    else:
        inits.append(b_init)
    inputs = [helper.make_tensor_value_info(input_name, input_type, ["N", width])]
    if second_input:
        inputs.append(helper.make_tensor_value_info("z", TensorProto.FLOAT, ["N", width]))
    graph = helper.make_graph(nodes, "transfer", inputs, [helper.make_tensor_value_info("y", input_type, ["N", outputs])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    return model.SerializeToString()


GLSL = """// seg0_transfer: a constant transfer, the GLSL twin of the corpus's linear network.
void seg0_transfer(vec3 position, vec3 normal, out vec4 t[4]) {
    t[0] = vec4(0.6, 0.05, 0.05, 0.05);
    t[1] = vec4(0.05);
    t[2] = vec4(0.05);
    t[3] = vec4(0.05);
}
"""


def _mesh(vertices=None, faces=None) -> bytes:
    """geometry.npz: a unit quad facing the default camera (+z)."""
    v = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32) if vertices is None else vertices
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int64) if faces is None else faces
    buf = io.BytesIO()
    np.savez(buf, vertices=v, faces=f, object_ids=np.zeros(len(f), np.int32), two_sided=np.ones(len(f), bool))
    return buf.getvalue()


SH = [[0.8, 0.8, 0.8]] + [[0.0, 0.0, 0.0]] * 15
MANIFEST = {
    "format": "prt-scene", "version": 1, "name": "quad", "generator": "hostile corpus", "sh_bands": 4,
    "geometry": {"type": "mesh", "file": "geometry.npz", "to_source": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                 "triangles": 2, "objects": ["quad"]},
    "segmentation": {"roots": {"0": 0}, "nodes": [{"leaf": 0}], "leaf_segment": [0]},
    "segments": [{"id": 0, "kind": "network", "model": "seg000.onnx", "glsl": "seg000.glsl",
                  "bounds": [[-1, -1, -1], [1, 1, 1]],
                  "architecture": {"hidden": 1, "layers": 1, "pos_freqs": 0, "normal_freqs": 0, "input_dim": 6},
                  "flops_per_fragment": 200, "weight_bytes": 448, "samples": 1, "validation": {"coeff_mae": 0.0, "shaded_mae": {}}}],
    "lighting": {"envmap": None, "sh": SH},
    "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]},
    "camera": {"eye": [0.0, 0.0, 3.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov": 40.0},
}  # fmt: skip
SCENE_FILES = {"geometry.npz": _mesh(), "seg000.onnx": _model(), "seg000.glsl": GLSL}


def _scene(manifest=None, **files) -> dict[str, str | bytes]:
    """The valid scene's files with ``scene.json`` (a dict, or raw text/bytes) and others replaced."""
    manifest = MANIFEST if manifest is None else manifest
    text = manifest if isinstance(manifest, (str, bytes)) else json.dumps(manifest, allow_nan=True)
    out = {"scene.json": text, **SCENE_FILES}
    out.update({name.replace("__", "."): content for name, content in files.items()})
    return out


def _set(path: str, value) -> dict:
    """MANIFEST with the field at ``path`` (``"material.albedo.0"``) set to ``value`` (``_DELETE`` removes it)."""
    data = copy.deepcopy(MANIFEST)
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    parent = data
    for k in keys[:-1]:
        parent = parent[k]
    if value is _DELETE:
        del parent[keys[-1]]
    else:
        parent[keys[-1]] = value
    return data


_DELETE = object()


def _hdr(width: int, height: int) -> bytes:
    """A flat (uncompressed) Radiance RGBE image of grey texels."""
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n".encode()
    return header + struct.pack("4B", 128, 128, 128, 129) * (width * height)


# --------------------------------------------------------------------------- prt-runtime


def _rt(name: str, what: str, message: str, files=None, argv=None, exit: int = 2, leaves=None) -> Case:
    argv = ["{case}/scene.json", *FAST, "--out", OUT] if argv is None else argv
    return Case(f"rt-{name}", "prt-runtime", argv, message, what, files if files is not None else _scene(), exit, leaves or [])


# (name, field path, value, message) for one bad field of scene.json
FIELDS = [
    ("format-wrong", "format", "gltf", r"scene\.json: format: 'prt-scene' was expected"),
    ("format-missing", "format", _DELETE, r"scene\.json: \(top level\): 'format' is a required property"),
    ("version-2", "version", 2, r"scene\.json: version: 1 was expected"),
    ("name-empty", "name", "", r"scene\.json: name: .*(short|non-empty)"),
    ("sh-bands-string", "sh_bands", "4", r"scene\.json: sh_bands: '4' is not of type 'integer'"),
    ("sh-bands-zero", "sh_bands", 0, r"scene\.json: sh_bands: 0 is less than the minimum of 1"),
    ("sh-rows-wrong", "lighting.sh", SH[:9], r"scene\.json: lighting\.sh: expected 16 rows \(sh_bands 4\), got 9"),
    ("sh-value-1e39", "lighting.sh.0.0", 1e39, r"scene\.json: lighting\.sh\[0\]\[0\]: number 1e\+39 is not finite in float32"),
    ("sh-value-string", "lighting.sh.0.0", "bright", r"scene\.json: lighting\.sh\[0\]\[0\]: 'bright' is not of type 'number'"),
    ("sh-row-short", "lighting.sh.3", [1.0, 2.0], r"scene\.json: lighting\.sh\[3\]: .*(short|fewer)"),
    ("albedo-string", "material.albedo", "white", r"scene\.json: material\.albedo: 'white' is not of type 'array'"),
    ("albedo-negative", "material.albedo.1", -0.5, r"scene\.json: material\.albedo\[1\]: -0\.5 is less than the minimum of 0"),
    ("albedo-1e39", "material.albedo.0", 1e39, r"scene\.json: material\.albedo\[0\]: number 1e\+39 is not finite in float32"),
    ("albedo-two-values", "material.albedo", [0.5, 0.5], r"scene\.json: material\.albedo: .*(short|fewer)"),
    ("material-type-unknown", "material.type", "metal", r"scene\.json: material\.type: 'metal' is not one of"),
    ("material-exponent-zero", "material.exponent", 0, r"scene\.json: material\.exponent: 0 is less than or equal to the minimum of 0"),
    ("material-exponent-1e300", "material.exponent", 1e300, r"scene\.json: material\.exponent: number 1e\+300 is not finite in float32"),
    ("specular-bool", "material.specular", True, r"scene\.json: material\.specular: True is not of type 'array'"),
    ("camera-eye-1e308", "camera.eye.2", 1e308, r"scene\.json: camera\.eye\[2\]: number 1e\+308 is not finite in float32"),
    ("camera-eye-is-target", "camera.eye", [0.0, 0.0, 0.0], r"scene\.json: camera: eye and target coincide"),
    ("camera-up-parallel", "camera.up", [0.0, 0.0, 1.0], r"scene\.json: camera\.up: is zero or parallel to the view direction"),
    ("camera-eye-far", "camera.eye", [3e38, 3e38, 0.0], r"scene\.json: camera: Camera: eye and target are too far apart .* for float32"),
    ("camera-fov-180", "camera.fov", 180, r"scene\.json: camera\.fov: 180 is greater than or equal to the maximum of 180"),
    ("camera-eye-string", "camera.eye", "behind", r"scene\.json: camera\.eye: 'behind' is not of type 'array'"),
    ("camera-field-unknown", "camera.zoom", 2, r"scene\.json: camera: Additional properties are not allowed \('zoom'"),
    ("rotation-not-rotation", "lighting.rotation", [[2, 0, 0], [0, 1, 0], [0, 0, 1]], r"scene\.json: lighting\.rotation: not a rotation matrix"),
    ("segment-id-wrong", "segments.0.id", 3, r"scene\.json: segments\[0\]\.id: expected 0"),
    ("segment-kind-typo", "segments.0.kind", "netwrk", r"scene\.json: segments\[0\]\.kind: 'netwrk' is not one of"),
    ("bounds-inverted", "segments.0.bounds", [[1, 1, 1], [-1, -1, -1]], r"scene\.json: segments\[0\]\.bounds: min corner .* exceeds max corner"),
    ("bounds-nested-wrong", "segments.0.bounds", [1, 2, 3], r"scene\.json: segments\[0\]\.bounds"),
    ("samples-2-pow-64", "segments.0.samples", 2**64, r"scene\.json: segments\[0\]\.samples: integer 18446744073709551616 is out of range"),
    ("leaf-segment-out-of-range", "segmentation.leaf_segment.0", 5, r"scene\.json: segmentation\.leaf_segment\[0\]: segment 5 does not exist"),
    ("node-cycle", "segmentation.nodes", [{"axis": 0, "split": 0.0, "left": 0, "right": 0}], r"scene\.json: segmentation\.nodes\[0\]\.(left|right): node 0 is reached twice"),
    ("root-key-not-a-number", "segmentation.roots", {"zero": 0}, r"scene\.json: segmentation\.roots: 'zero' does not match"),
    ("geometry-type-unknown", "geometry.type", "pointcloud", r"scene\.json: geometry\.type: 'pointcloud' is not one of"),
    ("field-unknown", "colour", "red", r"scene\.json: \(top level\): Additional properties are not allowed \('colour'"),
    ("segments-empty", "segments", [], r"scene\.json: segments: \[\] should be non-empty"),
    ("path-absolute", "segments.0.model", "/etc/passwd", r"scene\.json: segments\[0\]\.model: path '/etc/passwd' is absolute"),
    ("path-dotdot", "segments.0.model", "../../../../../../etc/passwd", r"scene\.json: segments\[0\]\.model: path '\.\./.*' escapes the scene folder"),
    ("path-windows-drive", "geometry.file", "C:\\Windows\\win.ini", r"scene\.json: geometry\.file: path .* is absolute"),
    ("path-nul-byte", "segments.0.model", "seg000.onnx\u0000.txt", r"scene\.json: segments\[0\]\.model: path .* holds a control character"),
    ("path-newline", "segments.0.glsl", "seg000\n.glsl", r"scene\.json: segments\[0\]\.glsl: path .* holds a control character"),
    ("path-missing", "segments.0.model", "seg999.onnx", r"scene\.json: segments\[0\]\.model: file 'seg999\.onnx' does not exist"),
    ("path-is-folder", "geometry.file", ".", r"scene\.json: geometry\.file: file '\.' is not a file"),
    ("path-empty", "lighting.envmap", "", r"scene\.json: lighting\.envmap: .*"),
]

RAW = [
    ("json-broken", "{\"format\": \"prt-scene\",", r"scene\.json: invalid JSON at line 1, column"),
    ("json-empty", "", r"scene\.json: invalid JSON at line 1, column 1"),
    ("json-not-utf8", b"{\"name\": \"\xff\xfe\"}", r"scene\.json: not UTF-8 text \(byte 10\)"),
    ("json-utf16", json.dumps(MANIFEST).encode("utf-16"), r"scene\.json: not UTF-8 text"),
    ("json-nan-literal", json.dumps(_set("material.albedo.0", float("nan")), allow_nan=True), r"scene\.json: invalid manifest JSON: non-finite number NaN"),
    ("json-infinity-literal", json.dumps(_set("camera.fov", float("inf")), allow_nan=True), r"scene\.json: invalid manifest JSON: non-finite number Infinity"),
    ("json-1e999", json.dumps(MANIFEST).replace('"fov": 40.0', '"fov": 1e999'), r"scene\.json: camera\.fov: .*inf"),
    ("json-duplicate-key", json.dumps(MANIFEST).replace('"name": "quad"', '"name": "quad", "name": "other"'), r"scene\.json: invalid manifest JSON: duplicate key 'name'"),
    ("json-deeply-nested", '{"name": ' + "[" * 100000 + "]" * 100000 + "}", r"scene\.json: invalid manifest JSON: nested too deeply"),
    ("json-5000-digit-integer", json.dumps(MANIFEST).replace('"samples": 1', '"samples": ' + "9" * 5000), r"scene\.json: invalid manifest JSON: .*digits"),
    ("json-top-level-array", "[1, 2, 3]", r"scene\.json: \(top level\): \[1, 2, 3\] is not of type 'object'"),
    ("json-top-level-null", "null", r"scene\.json: \(top level\): None is not of type 'object'"),
]


def _runtime_cases() -> list[Case]:
    cases = [_rt(name, f"scene.json: {path} = {value!r:.40}", message, _scene(_set(path, value))) for name, path, value, message in FIELDS]
    cases += [_rt(name, f"scene.json: {name}", message, _scene(text)) for name, text, message in RAW]
    nan_bias = np.full(16, np.nan, np.float32)
    inf_weight = np.full((6, 16), np.finfo(np.float32).max, np.float32)
    cases += [
        # the scene argument
        _rt("scene-missing", "a scene that does not exist", r"nope/scene\.json: manifest not found",
            {}, ["{case}/nope/scene.json", *FAST, "--out", OUT]),
        _rt("scene-folder-without-manifest", "a folder with no scene.json", r"empty/scene\.json: manifest not found",
            {"empty/readme.txt": "nothing here"}, ["{case}/empty", *FAST, "--out", OUT]),
        _rt("scene-is-a-binary-file", "an ONNX file given as the scene", r"seg000\.onnx: not UTF-8 text",
            argv=["{case}/seg000.onnx", *FAST, "--out", OUT]),
        # the files a manifest names
        _rt("geometry-truncated", "geometry.npz cut in half", r"geometry\.npz: cannot read mesh",
            _scene(geometry__npz=_mesh()[: len(_mesh()) // 2])),
        _rt("geometry-garbage", "geometry.npz that is not a zip", r"geometry\.npz: cannot read mesh",
            _scene(geometry__npz=b"PK\x03\x04 not really a zip")),
        _rt("geometry-nan-vertices", "a mesh with NaN vertices", r"geometry\.npz: vertices contain NaN or Inf",
            _scene(geometry__npz=_mesh(vertices=np.full((4, 3), np.nan, np.float32)))),
        _rt("geometry-face-out-of-range", "a face indexing a missing vertex", r"geometry\.npz: faces index vertices outside",
            _scene(geometry__npz=_mesh(faces=np.array([[0, 1, 9]], np.int64)))),
        _rt("onnx-garbage", "a model file of random bytes", r"seg000\.onnx: not a valid ONNX model",
            _scene(seg000__onnx=bytes(range(256)) * 4)),
        _rt("onnx-empty", "an empty model file", r"seg000\.onnx: not a valid ONNX model \(no graph",
            _scene(seg000__onnx=b"")),
        _rt("onnx-truncated", "a model cut short", r"seg000\.onnx: not a valid ONNX model \(malformed protobuf",
            _scene(seg000__onnx=_model()[:-7])),
        _rt("onnx-external-data-escape", "weights read from ../../etc/passwd", r"seg000\.onnx: 1 tensor\(s\) keep their data in external files",
            _scene(seg000__onnx=_model(external="../../../../../../etc/passwd"))),
        _rt("onnx-external-data-absolute", "weights read from /etc/hostname", r"seg000\.onnx: 1 tensor\(s\) keep their data in external files",
            _scene(seg000__onnx=_model(external="/etc/hostname"))),
        _rt("onnx-external-data-inside", "weights in a file beside the model (also refused)", r"seg000\.onnx: 1 tensor\(s\) keep their data",
            _scene(seg000__onnx=_model(external="weights.bin"), weights__bin=np.zeros(96, np.float32).tobytes())),
        _rt("onnx-external-data-in-constant", "a Constant node whose tensor is external", r"seg000\.onnx: 1 tensor\(s\) keep their data",
            _scene(seg000__onnx=_model(external_in_attribute=True))),
        _rt("onnx-input-int64", "a model taking int64", r"seg000\.onnx: model input must be one float32 tensor \[N, 6\]",
            _scene(seg000__onnx=_model(weight=np.zeros((6, 16), np.int64), bias=np.zeros(16, np.int64), input_type=TensorProto.INT64))),
        _rt("onnx-input-width-5", "a model taking 5 values", r"seg000\.onnx: model input must be one float32 tensor \[N, 6\]",
            _scene(seg000__onnx=_model(width=5))),
        _rt("onnx-output-9", "a model giving 9 coefficients (3 bands)", r"seg000\.onnx: model output must be one float32 tensor \[N, 16\]",
            _scene(seg000__onnx=_model(outputs=9))),
        _rt("onnx-two-inputs", "a model with a second input", r"seg000\.onnx: model input must be one float32 tensor",
            _scene(seg000__onnx=_model(second_input=True))),
        _rt("onnx-nan-output", "a network that outputs NaN", r"the transfer is NaN or Inf at \d+ pixels from .*seg000\.onnx",
            _scene(seg000__onnx=_model(bias=nan_bias))),
        _rt("onnx-inf-output", "a network whose output overflows float32", r"the transfer is NaN or Inf at \d+ pixels from .*seg000\.onnx",
            _scene(seg000__onnx=_model(weight=inf_weight))),
        _rt("glsl-nan-output", "generated GLSL that outputs NaN (glsl backend)", r"the transfer is NaN or Inf at \d+ pixels .*backend glsl",
            _scene(seg000__glsl=GLSL.replace("vec4(0.6, 0.05, 0.05, 0.05)", "vec4(sqrt(-1.0 - abs(position.x)))")),
            ["{case}/scene.json", *FAST, "--backend", "glsl", "--out", OUT]),
        _rt("glsl-not-utf8", "generated GLSL in Latin-1 (glsl backend)", r"seg000\.glsl: GLSL is not UTF-8 text",
            _scene(seg000__glsl=("// Gr\u00fc\u00dfe\n" + GLSL).encode("latin-1")), ["{case}/scene.json", *FAST, "--backend", "glsl", "--out", OUT]),
        _rt("glsl-compile-error", "a typo in the generated GLSL: the error names the file and its own line",
            r"seg000\.glsl:5: GLSL compile failed \(.*\): error: .*undeclared",
            _scene(seg000__glsl=GLSL.replace("vec4(0.05);\n    t[2]", "vec4(0.05);\n    t[2] = oops;\n    t[2]")),
            ["{case}/scene.json", *FAST, "--backend", "glsl", "--out", OUT]),
        _rt("sh-bands-3", "SH lighting with 3 bands: the renderer's shaders need 4", r"scene\.json: the renderer's shaders handle 4 SH bands, the scene has 3",
            _scene(_set("sh_bands", 3) | {"lighting": {"envmap": None, "sh": SH[:9]}})),
        _rt("onnx-input-named-otherwise", "an input called 'points' instead of 'x' works", "", _scene(seg000__onnx=_model(input_name="points")),
            exit=0, leaves=["out", "out/*"]),
        # env maps
        _rt("envmap-flag-missing", "--envmap naming no file", r"nope\.hdr: env map file not found",
            argv=["{case}/scene.json", *FAST, "--envmap", "{case}/nope.hdr", "--out", OUT]),
        _rt("envmap-flag-garbage", "--envmap of random bytes", r"junk\.hdr: cannot decode \.hdr file",
            _scene(junk__hdr=bytes(range(256))), ["{case}/scene.json", *FAST, "--envmap", "{case}/junk.hdr", "--out", OUT]),
        _rt("envmap-flag-extension", "--envmap of a PNG", r"sky\.png: unsupported env map extension",
            _scene(sky__png=b"\x89PNG\r\n"), ["{case}/scene.json", *FAST, "--envmap", "{case}/sky.png", "--out", OUT]),
        _rt("envmap-not-equirect", "a 3x2 env map", r"square\.hdr: not an equirectangular env map: 3x2",
            _scene(square__hdr=_hdr(3, 2)), ["{case}/scene.json", *FAST, "--envmap", "{case}/square.hdr", "--out", OUT]),
        _rt("envmap-in-manifest-garbage", "the manifest's env map is garbage", r"sky\.hdr: cannot decode \.hdr file",
            _scene(_set("lighting", {"envmap": "sky.hdr"}), sky__hdr=b"#?RADIANCE\nnonsense")),
        # flags
        _rt("size-zero", "--size 0", r"--size: expected positive W or WxH, got '0'", argv=["{case}/scene.json", "--headless", "--size", "0", "--out", OUT]),
        _rt("size-words", "--size big", r"--size: expected W or WxH, got 'big'", argv=["{case}/scene.json", "--headless", "--size", "big", "--out", OUT]),
        _rt("size-three-numbers", "--size 4x4x4", r"--size: expected positive W or WxH", argv=["{case}/scene.json", "--headless", "--size", "4x4x4", "--out", OUT]),
        _rt("size-beyond-driver", "--size 100000: more than the GL driver allocates", r"image size 100000x100000: this OpenGL driver allows at most",
            argv=["{case}/scene.json", "--headless", "--size", "100000", "--frames", "1", "--out", OUT]),
        _rt("threads-negative", "--threads -1", r"--threads must be >= 1, got -1", argv=["{case}/scene.json", *FAST, "--threads", "-1", "--out", OUT]),
        _rt("threads-zero", "--threads 0", r"--threads must be >= 1, got 0", argv=["{case}/scene.json", *FAST, "--threads", "0", "--out", OUT]),
        _rt("frames-zero", "--frames 0", r"--frames must be >= 1, got 0", argv=["{case}/scene.json", "--headless", "--frames", "0", "--out", OUT]),
        _rt("exposure-nan", "--exposure nan", r"--exposure: expected a number >= 0 or .auto., got nan", argv=["{case}/scene.json", *FAST, "--exposure", "nan", "--out", OUT]),
        _rt("exposure-negative", "--exposure -1", r"--exposure: expected a number >= 0 or .auto., got -1", argv=["{case}/scene.json", *FAST, "--exposure", "-1", "--out", OUT]),
        _rt("exponent-inf", "--exponent inf", r"--exponent: 1 value\(s\) NaN or Inf", argv=["{case}/scene.json", *FAST, "--exponent", "inf", "--out", OUT]),
        _rt("exponent-zero", "--exponent 0", r"--exponent must be > 0", argv=["{case}/scene.json", *FAST, "--exponent", "0", "--out", OUT]),
        _rt("materials-unknown-object", "a per-object material naming no object", r"materials\[0\]\.object: 'nope' is not an object",
            _scene(_set("materials", [{"object": "nope", "type": "diffuse", "albedo": [1, 0, 0]}]))),
        _rt("materials-twice", "two materials for one object", r"materials\[1\]\.object: 'quad' has a material already",
            _scene(_set("materials", [{"object": "quad", "type": "diffuse", "albedo": [1, 0, 0]}] * 2))),
        _rt("materials-corrupt-texture", "a per-object albedo texture that is not an image", r"wood\.png: cannot read albedo texture",
            _scene(_set("materials", [{"object": "quad", "type": "diffuse", "albedo": [1, 1, 1], "albedo_texture": "wood.png"}]),
                   wood__png=b"\x89PNG\r\n\x1a\njunk")),
        _rt("materials-texture-outside", "an albedo texture path leaving the scene folder", r"albedo_texture: '\.\./wood\.png' is outside the scene folder",
            _scene(_set("materials", [{"object": "quad", "type": "diffuse", "albedo": [1, 1, 1], "albedo_texture": "../wood.png"}]))),
        _rt("object-albedo-malformed", "--object-albedo without numbers", r"--object-albedo: expected NAME=R,G,B",
            argv=["{case}/scene.json", *FAST, "--object-albedo", "quad=red", "--out", OUT]),
        _rt("object-albedo-unknown-object", "--object-albedo naming no object", r"object 'nope' is not in the scene \(objects: quad\)",
            argv=["{case}/scene.json", *FAST, "--object-albedo", "nope=1,0,0", "--out", OUT]),
        *_camera_path_cases(),
        _rt("backend-unknown", "--backend cuda", r"argument --backend: invalid choice: 'cuda'", argv=["{case}/scene.json", *FAST, "--backend", "cuda"]),
        _rt("providers-unknown", "--providers naming no provider", r"providers: FooExecutionProvider not available",
            argv=["{case}/scene.json", *FAST, "--providers", "FooExecutionProvider", "--out", OUT]),
        _rt("out-is-a-file", "--out naming a file", r"afile: cannot create the output folder",
            _scene(afile="not a folder"), ["{case}/scene.json", *FAST, "--out", "{case}/afile"]),
        _rt("out-below-a-file", "--out below a file", r"afile/frames: cannot create the output folder",
            _scene(afile="not a folder"), ["{case}/scene.json", *FAST, "--out", "{case}/afile/frames"]),
    ]
    return cases


def _path(data=None, **changes) -> str:
    """A camera-path file: a valid two-keyframe path with ``changes`` applied (raw text if ``data`` is a str)."""
    if isinstance(data, str):
        return data
    path = {"format": "prt-camera-path", "version": 1, "frames": 2,
            "keyframes": [{"eye": [0.0, 0.5, 3.0], "target": [0.0, 0.0, 0.0]}, {"eye": [3.0, 0.5, 0.0], "target": [0.0, 0.0, 0.0]}]}
    path.update(changes)
    return json.dumps(path, allow_nan=True)


def _camera_path_cases() -> list[Case]:
    """--camera-path files, the output --format, --fps, --background, --target-fps, lighting.background."""
    def run(name, what, message, text, extra=()):
        files = _scene(path__json=_path() if text is None else text)
        return _rt(name, what, message, files, ["{case}/scene.json", *FAST, "--camera-path", "{case}/path.json", *extra, "--out", OUT])

    eye = [{"eye": [0.0, 0.0, 1.0], "target": [0.0, 0.0, 0.0]}, {"eye": [0.0, 0.0, -1.0], "target": [0.0, 0.0, 0.0]}]
    return [
        _rt("camera-path-missing", "--camera-path naming no file", r"nope\.json: cannot read the camera path \(No such file",
            argv=["{case}/scene.json", *FAST, "--camera-path", "{case}/nope.json", "--out", OUT]),
        _rt("camera-path-is-folder", "--camera-path naming a folder", r": is a folder, not a camera-path file",
            argv=["{case}/scene.json", *FAST, "--camera-path", "{case}/.", "--out", OUT]),
        run("camera-path-json-broken", "a camera path cut short", r"path\.json: not valid JSON \(line 1 column", '{"format": "prt-camera-path",'),
        run("camera-path-not-utf8", "a camera path in UTF-16", r"path\.json: cannot read the camera path \(not UTF-8 text\)", _path().encode("utf-16")),
        run("camera-path-nan", "a NaN literal in a keyframe", r"path\.json: not valid JSON \(NaN is not a number JSON allows\)",
            _path(keyframes=[{"eye": [float("nan"), 0, 1], "target": [0, 0, 0]}])),
        run("camera-path-format-wrong", "a scene.json given as a camera path", r"path\.json: format: expected 'prt-camera-path', got 'prt-scene'",
            _path(format="prt-scene")),
        run("camera-path-version-2", "a camera path from a newer runtime", r"path\.json: version: expected 1 .*got 2", _path(version=2)),
        run("camera-path-field-unknown", "a field this version does not know", r"path\.json: speed: unknown field", _path(speed=2)),
        run("camera-path-top-level-array", "a bare list of keyframes", r"path\.json: a camera path must be a JSON object, got list", "[]"),
        run("camera-path-keyframes-empty", "no keyframes", r"path\.json: keyframes: expected a non-empty list", _path(keyframes=[])),
        run("camera-path-keyframe-not-object", "a keyframe that is a number", r"path\.json: keyframes\[1\]: expected an object",
            _path(keyframes=[eye[0], 7])),
        run("camera-path-eye-missing", "a keyframe without an eye", r"path\.json: keyframes\[0\]\.eye: missing", _path(keyframes=[{"target": [0, 0, 0]}])),
        run("camera-path-eye-string", "a keyframe eye that is a word", r"path\.json: keyframes\[0\]\.eye: expected 3 numbers, got 'behind'",
            _path(keyframes=[{"eye": "behind", "target": [0, 0, 0]}])),
        run("camera-path-eye-is-target", "a keyframe looking at itself", r"path\.json: keyframes\[0\]: eye and target coincide",
            _path(keyframes=[{"eye": [0, 0, 0], "target": [0, 0, 0]}])),
        run("camera-path-eye-1e39", "a keyframe beyond float32", r"path\.json: keyframes\[0\]\.eye\[2\]: number 1e\+39 is not finite in float32",
            _path(keyframes=[{"eye": [0, 0, 1e39], "target": [0, 0, 0]}])),
        run("camera-path-fov-180", "a keyframe fov of 180 degrees", r"path\.json: keyframes\[0\]: fov_y must be in \(0, 180\)",
            _path(keyframes=[{"eye": [0, 0, 1], "target": [0, 0, 0], "fov": 180}])),
        run("camera-path-frames-zero", "frames 0", r"path\.json: frames: expected an integer in 1\.\.100000, got 0", _path(frames=0)),
        run("camera-path-frames-huge", "frames 10**12", r"path\.json: frames: expected an integer in 1\.\.100000", _path(frames=10**12)),
        run("camera-path-interpolation-unknown", "interpolation 'bezier'", r"path\.json: interpolation: expected one of linear, smooth",
            _path(interpolation="bezier")),
        run("camera-path-loop-string", "loop 'yes'", r"path\.json: loop: expected true or false", _path(loop="yes")),
        run("camera-path-through-target", "a path whose middle frame sits on the target", r"path\.json: frame 1: the interpolated camera is unusable",
            _path(keyframes=eye, frames=3)),
        run("format-unknown", "--format gif", r"argument --format: invalid choice: 'gif'", None, ["--format", "gif"]),
        run("fps-zero", "--format mp4 --fps 0", r"--fps must be in \(0, 1000\], got 0", None, ["--format", "mp4", "--fps", "0"]),
        _rt("mp4-out-below-a-file", "--format mp4 into a folder below a file", r"afile: cannot create the output folder",
            _scene(afile="not a folder"), ["{case}/scene.json", *FAST, "--format", "mp4", "--out", "{case}/afile/v.mp4"]),
        _rt("exr-out-is-a-file", "--format exr into a file", r"afile: cannot create the output folder",
            _scene(afile="not a folder"), ["{case}/scene.json", *FAST, "--format", "exr", "--out", "{case}/afile"]),
        _rt("background-unknown", "--background white", r"argument --background: invalid choice: 'white'",
            argv=["{case}/scene.json", *FAST, "--background", "white"]),
        _rt("target-fps-negative", "--target-fps -5", r"--target-fps must be >= 0", argv=["{case}/scene.json", *FAST, "--target-fps", "-5", "--out", OUT]),
        _rt("background-not-boolean", "lighting.background 'yes'", r"scene\.json: lighting\.background: 'yes' is not of type 'boolean'",
            _scene(_set("lighting.background", "yes"))),
    ]


# --------------------------------------------------------------------------- prt-bench


def _bench(name: str, what: str, message: str, files=None, argv=None) -> Case:
    argv = ["{case}/scene.json", *BENCH_FAST] if argv is None else argv
    return Case(f"bench-{name}", "prt-bench", argv, message, what, files if files is not None else _scene(), 2, [])


def _bench_cases() -> list[Case]:
    return [
        _bench("scene-missing", "a scene that does not exist", r"nope/scene\.json: manifest not found \(scene skipped\)",
               {}, ["{case}/nope/scene.json", *BENCH_FAST]),
        _bench("json-broken", "broken JSON", r"scene\.json: invalid JSON at line 1.* \(scene skipped\)", _scene("{")),
        _bench("path-escape", "a model path escaping the folder", r"segments\[0\]\.model: path .* escapes the scene folder",
               _scene(_set("segments.0.model", "../../etc/passwd"))),
        _bench("albedo-1e39", "an albedo beyond float32", r"material\.albedo\[0\]: number 1e\+39 is not finite in float32",
               _scene(_set("material.albedo.0", 1e39))),
        _bench("onnx-external-data", "a model with external data", r"seg000\.onnx: 1 tensor\(s\) keep their data in external files",
               _scene(seg000__onnx=_model(external="/etc/hostname"))),
        _bench("onnx-nan-output", "a network giving NaN, found before measuring", r"seg000\.onnx: the network gives NaN or Inf transfer",
               _scene(seg000__onnx=_model(bias=np.full(16, np.nan, np.float32)))),
        _bench("onnx-wrong-input", "a model taking int64", r"seg000\.onnx: model input must be one float32 tensor",
               _scene(seg000__onnx=_model(weight=np.zeros((6, 16), np.int64), bias=np.zeros(16, np.int64), input_type=TensorProto.INT64))),
        _bench("geometry-truncated", "a truncated geometry.npz", r"geometry\.npz: cannot read mesh", _scene(geometry__npz=_mesh()[:100])),
        _bench("glsl-not-utf8", "GLSL that is not UTF-8 (glsl backend)", r"seg000\.glsl: GLSL is not UTF-8 text",
               _scene(seg000__glsl=b"// \xff\xfe\n" + GLSL.encode()),
               ["{case}/scene.json", *[a if a != "onnx" else "glsl" for a in BENCH_FAST]]),
        _bench("views-zero", "--views 0", r"--views, --size and --ref-rays must be positive", argv=["{case}/scene.json", "--views", "0"]),
        _bench("gemm-size-zero", "--gemm-size 0", r"--gemm-size must be positive, got 0", argv=["{case}/scene.json", "--gemm-size", "0"]),
        _bench("blas-threads-negative", "--blas-threads -2", r"--blas-threads must be positive, got -2", argv=["{case}/scene.json", "--blas-threads", "-2"]),
        _bench("packing-views-zero", "--packing-views 0", r"--packing-views must be positive, got 0", argv=["{case}/scene.json", "--packing-views", "0"]),
        _bench("config-budget-nan", "--config-budget nan", r"--config-budget must be a positive number of seconds, got nan",
               argv=["{case}/scene.json", "--config-budget", "nan"]),
        _bench("precision-unknown", "--precisions fp64", r"argument --precisions: invalid choice: 'fp64'", argv=["{case}/scene.json", "--precisions", "fp64"]),
    ]


def cases() -> list[Case]:
    return _runtime_cases() + _bench_cases()


assert onnx  # the case files are generated with the onnx package (dev dependency)
