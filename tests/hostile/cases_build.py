"""Hostile inputs to the build commands, ``prt-train`` (``train-*``) and ``prt-precompute`` (``pre-*``).

Every case fails in the checks made before any work (spec, flags, output folder, geometry), so
each runs in well under a second and leaves nothing behind: no output folder is created.
"""

from __future__ import annotations

import json

from corpus import Case

TET = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
OUT = "{run}/out"  # never created by a failing case

# Bad mesh files: (name, file name, content, message).  Each is tried by both commands.
MESHES = [
    ("mesh-empty", "empty.obj", "", r"empty\.obj: empty file"),
    ("mesh-binary-obj", "garbage.obj", bytes(range(256)) * 8, r"garbage\.obj"),
    ("mesh-nan-vertices", "nan.obj", "v nan 0 0\nv 0 nan 0\nv 0 0 nan\nf 1 2 3\n", r"nan\.obj: every triangle has a NaN"),
    ("mesh-inf-vertices", "inf.obj", "v inf 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n", r"inf\.obj: every triangle has a NaN or infinite"),
    ("mesh-index-out-of-range", "index.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", r"index\.obj"),
    ("mesh-index-zero", "zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"zero\.obj"),
    ("mesh-no-faces", "points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"points\.obj"),
    ("mesh-collinear", "line.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", r"line\.obj: every triangle is degenerate"),
    ("mesh-repeated-vertex", "repeat.obj", "v 0 0 0\nv 1 0 0\nf 1 1 2\n", r"repeat\.obj: every triangle is degenerate"),
    ("mesh-wrong-extension", "tet.txt", TET, r"tet\.txt: unsupported mesh format '\.txt'"),
    ("mesh-no-extension", "tetmesh", TET, r"tetmesh: unsupported mesh format \(no extension\)"),
    ("mesh-garbage-stl", "garbage.stl", b"\x00\x01binary junk" * 10, r"garbage\.stl: not an STL file"),
    ("mesh-garbage-ply", "garbage.ply", b"ply\nformat nonsense\n\xff\xfe", r"garbage\.ply: cannot read PLY file"),
    ("mesh-garbage-glb", "garbage.glb", b"glTF\x02\x00\x00\x00junk", r"garbage\.glb: cannot read GLB file"),
    ("mesh-text-garbage-obj", "words.obj", "this is not a mesh\nf a b c\n", r"words\.obj"),
]


def _mesh_cases() -> list[Case]:
    cases = []
    for name, file, content, message in MESHES:
        files = {file: content}
        cases.append(Case(f"train-{name}", "prt-train", ["{case}/" + file, "-o", OUT, "--no-progress"], message, f"prt-train: {name}", files))
        cases.append(Case(f"pre-{name}", "prt-precompute", ["{case}/" + file, "-o", OUT, "--no-progress"], message, f"prt-precompute: {name}", files))
    cases += [
        Case("train-mesh-missing", "prt-train", ["{case}/nope.obj", "-o", OUT], r"nope\.obj: no such file", "a mesh that does not exist"),
        Case("pre-mesh-missing", "prt-precompute", ["{case}/nope.obj", "-o", OUT], r"nope\.obj: no such file", "a mesh that does not exist"),
        Case("train-mesh-is-folder", "prt-train", ["{case}/meshdir", "-o", OUT], r"meshdir: is a directory", "a folder as the mesh",
             {"meshdir/tet.obj": TET}),
        Case("pre-mesh-is-folder", "prt-precompute", ["{case}/meshdir", "-o", OUT], r"meshdir: is a directory", "a folder as the mesh",
             {"meshdir/tet.obj": TET}),
        Case("train-mesh-bad-mtl", "prt-train", ["{case}/tet.obj", "-o", OUT], r"bad\.mtl, line 2: Kd values must be numbers",
             "an MTL file with a malformed Kd line", {"tet.obj": "mtllib bad.mtl\nusemtl red\n" + TET, "bad.mtl": "newmtl red\nKd red 0 0\n"}),
        Case("train-mesh-negative-mtl", "prt-train", ["{case}/tet.obj", "-o", OUT], r"neg\.mtl, line 2: Ks needs finite numbers >= 0",
             "an MTL file with a negative Ks", {"tet.obj": "mtllib neg.mtl\nusemtl red\n" + TET, "neg.mtl": "newmtl red\nKs -1 0 0\n"}),
        Case("train-mesh-corrupt-texture", "prt-train", ["{case}/tet.obj", "-o", OUT], r"wood\.png: cannot read albedo texture",
             "an MTL map_Kd naming a corrupt image", {"tet.obj": "mtllib t.mtl\nusemtl wood\n" + TET,
                                                      "t.mtl": "newmtl wood\nKd 1 1 1\nmap_Kd wood.png\n", "wood.png": b"\x89PNG\r\n\x1a\njunk"}),
        Case("train-not-an-sdf-name", "prt-train", ["nosuchscene", "-o", OUT], r"nosuchscene: no such file and not a built-in SDF scene",
             "a name that is neither a file nor an SDF scene"),
        Case("pre-not-an-sdf-name", "prt-precompute", ["nosuchscene", "-o", OUT], r"nosuchscene: no such file and not a built-in SDF scene",
             "a name that is neither a file nor an SDF scene"),
    ]
    return cases


# Bad build specs: (name, spec fields or raw text/bytes, message).  The geometry is a good mesh.
def _spec(**fields) -> str:
    return json.dumps({"geometry": "tet.obj", **fields})


SPECS = [
    ("not-json", "{geometry: tet.obj", r"spec\.json: not valid JSON"),
    ("empty-file", "", r"spec\.json: not valid JSON"),
    ("not-utf8", b'{"geometry": "tet\xff.obj"}', r"spec\.json: not UTF-8"),
    ("utf16", json.dumps({"geometry": "tet.obj"}).encode("utf-16"), r"spec\.json: not UTF-8"),
    ("top-level-array", "[1, 2, 3]", r"spec\.json: expected a JSON object"),
    ("top-level-string", '"tet.obj"', r"spec\.json: expected a JSON object"),
    ("deeply-nested", '{"geometry": "tet.obj", "ladder": ' + "[" * 100000 + "]" * 100000 + "}", r"spec\.json: not valid JSON"),
    ("integer-of-5000-digits", '{"geometry": "tet.obj", "samples": ' + "9" * 5000 + "}", r"spec\.json: not usable JSON"),
    ("missing-geometry", "{}", r"spec\.json: geometry: missing"),
    ("geometry-empty", _spec(geometry=""), r"spec\.json: geometry: expected a mesh file"),
    ("geometry-nul-byte", _spec(geometry="tet\u0000.obj"), r"spec\.json: geometry: expected a mesh file"),
    ("geometry-number", _spec(geometry=42), r"spec\.json: geometry: expected str"),
    ("unknown-field", _spec(sampels=1000), r"spec\.json: sampels: unknown field"),
    ("samples-string", _spec(samples="1000"), r"spec\.json: samples: expected int"),
    ("samples-float", _spec(samples=1000.5), r"spec\.json: samples: expected int"),
    ("samples-bool", _spec(samples=True), r"spec\.json: samples: expected int"),
    ("samples-zero", _spec(samples=0), r"spec\.json: samples: expected an integer >= 1"),
    ("samples-negative", _spec(samples=-5), r"spec\.json: samples: expected an integer >= 1"),
    ("samples-huge", _spec(samples=10**15), r"spec\.json: samples: .* GiB; at most"),
    ("samples-400-digits", '{"geometry": "tet.obj", "samples": 1' + "0" * 400 + "}", r"spec\.json: samples: .* GiB; at most"),
    ("samples-null", _spec(samples=None), r"spec\.json: samples: expected int"),
    ("validation-negative", _spec(validation=-1), r"spec\.json: validation: expected an integer >= 0"),
    ("rays-huge", _spec(rays=10**9), r"spec\.json: rays: expected 1 \.\. 65536"),
    ("bands-nine", _spec(bands=9), r"spec\.json: bands: expected 1 \.\. 8"),
    ("segments-zero", _spec(segments=0), r"spec\.json: segments: expected 1"),
    ("seed-negative", _spec(seed=-1), r"spec\.json: seed: expected 0"),
    ("epochs-zero", _spec(epochs=0), r"spec\.json: epochs: expected 1"),
    ("steps-string", _spec(steps="many"), r"spec\.json: steps: expected int \| None"),
    ("batch-huge", _spec(batch=10**12), r"spec\.json: batch: expected 1"),
    ("lr-nan", '{"geometry": "tet.obj", "lr": NaN}', r"spec\.json: lr: expected a finite positive number"),
    ("lr-infinity", '{"geometry": "tet.obj", "lr": Infinity}', r"spec\.json: lr: expected a finite positive number"),
    ("lr-1e999", '{"geometry": "tet.obj", "lr": 1e999}', r"spec\.json: lr: expected a finite positive number"),
    ("lr-negative", _spec(lr=-0.01), r"spec\.json: lr: expected a finite positive number"),
    ("lr-zero", _spec(lr=0), r"spec\.json: lr: expected a finite positive number"),
    ("lr-string", _spec(lr="0.01"), r"spec\.json: lr: expected float"),
    ("target-negative", _spec(target=-0.1), r"spec\.json: target: expected a finite non-negative number"),
    ("target-nan", '{"geometry": "tet.obj", "target": NaN}', r"spec\.json: target: expected a finite non-negative number"),
    ("match-tolerance-nan", '{"geometry": "tet.obj", "match_tolerance": NaN}', r"spec\.json: match_tolerance: expected a share"),
    ("match-tolerance-two", _spec(match_tolerance=2), r"spec\.json: match_tolerance: expected a share"),
    ("merge-tolerance-negative", _spec(merge_tolerance=-1), r"spec\.json: merge_tolerance: expected a finite non-negative"),
    ("delta-nan", '{"geometry": "tet.obj", "delta": NaN}', r"spec\.json: delta: expected a finite non-negative"),
    ("ladder-empty", _spec(ladder=[]), r"spec\.json: ladder: empty"),
    ("ladder-object", _spec(ladder={"hidden": 4}), r"spec\.json: ladder: expected list"),
    ("ladder-string-rung", _spec(ladder=["64x4"]), r"spec\.json: ladder\[0\]: expected an object"),
    ("ladder-unknown-key", _spec(ladder=[{"width": 4}]), r"spec\.json: ladder\[0\]\.width: unknown field"),
    ("ladder-hidden-zero", _spec(ladder=[{"hidden": 0, "layers": 2}]), r"spec\.json: ladder\[0\]\.hidden: expected a positive integer"),
    ("ladder-hidden-huge", _spec(ladder=[{"hidden": 10**9, "layers": 2}]), r"spec\.json: ladder\[0\]\.hidden: at most 4096"),
    ("ladder-layers-float", _spec(ladder=[{"hidden": 16, "layers": 2.5}]), r"spec\.json: ladder\[0\]\.layers: expected a positive integer"),
    ("fixed-freqs-negative", _spec(fixed={"hidden": 16, "layers": 2, "pos_freqs": -1}), r"spec\.json: fixed\.pos_freqs: expected a non-negative"),
    ("fixed-and-match", _spec(fixed={"hidden": 16, "layers": 2}, match={"hidden": 64, "layers": 4}), r"spec\.json: match: cannot be combined with fixed"),
    ("material-string", _spec(material="red"), r"spec\.json: material: expected dict"),
    ("material-no-albedo", _spec(material={"type": "diffuse"}), r"spec\.json: material: .*albedo"),
    ("material-unknown-type", _spec(material={"type": "metal", "albedo": [1, 1, 1]}), r"spec\.json: material\.type"),
    ("material-albedo-overflows-float32", _spec(material={"type": "diffuse", "albedo": [1, 1, 1e39]}), r"spec\.json: material\.albedo\[2\]: expected a finite number"),
    ("material-albedo-nan", '{"geometry": "tet.obj", "material": {"type": "diffuse", "albedo": [NaN, 0, 0]}}', r"spec\.json: material\.albedo"),
    ("material-exponent-zero", _spec(material={"type": "glossy", "albedo": [1, 1, 1], "exponent": 0}), r"spec\.json: material\.exponent"),
    ("camera-eye-at-target", _spec(camera={"eye": [0, 0, 0], "target": [0, 0, 0]}), r"spec\.json: camera: eye and target coincide"),
    ("camera-up-along-view", _spec(camera={"eye": [0, 0, 3], "up": [0, 0, 1]}), r"spec\.json: camera: up .* parallel"),
    ("camera-fov-200", _spec(camera={"fov": 200}), r"spec\.json: camera\.fov"),
    ("camera-at-1e308", _spec(camera={"eye": [0, 0, 1e308]}), r"spec\.json: camera\.eye\[2\]: expected a finite number"),
    ("camera-unknown-field", _spec(camera={"zoom": 2}), r"spec\.json: camera"),
    ("glsl-layout-bad", _spec(glsl_layout="fast"), r"spec\.json: glsl_layout: expected 'auto'"),
    ("bf16-string", _spec(bf16="yes"), r"spec\.json: bf16: expected bool"),
    ("analytic-number", _spec(analytic=1), r"spec\.json: analytic: expected bool"),
    ("bounces-float", _spec(bounces=2.5), r"spec\.json: bounces: expected int"),
    ("bounces-true", _spec(bounces=True), r"spec\.json: bounces: expected int"),
    ("bounces-huge", _spec(bounces=10**30), r"spec\.json: bounces: expected 0 \.\. 16"),
    ("encoding-unknown", _spec(encoding="hash"), r"spec\.json: encoding: expected 'freq' \(the paper's frequency-encoded MLP\), 'grid'"),
    ("encoding-auto-with-fixed", _spec(encoding="auto", fixed={"hidden": 16, "layers": 2}), r"spec\.json: fixed: not with encoding 'auto'"),
    ("target-db-negative", _spec(target_db=-1), r"spec\.json: target_db: expected a PSNR in dB, 0 < dB <= 100, got -1"),
    ("target-db-string", _spec(target_db="40"), r"spec\.json: target_db: expected"),
    ("target-db-with-match", _spec(target_db=40, match={"hidden": 64, "layers": 4}), r"spec\.json: target_db: cannot be combined with match"),
    ("encoding-number", _spec(encoding=1), r"spec\.json: encoding: expected str"),
    ("grid-without-encoding", _spec(grid="L6-F2-T12-N4-32"), r"spec\.json: grid: only with encoding 'grid'"),
    ("grid-malformed", _spec(encoding="grid", grid="6 levels"), r"spec\.json: grid: expected L<levels>-F<features>-T<log2 table>-N<min>-<max>"),
    ("grid-features-five", _spec(encoding="grid", grid="L6-F5-T12-N4-32"), r"spec\.json: grid: features F: expected 1 \.\. 4"),
    ("grid-table-huge", _spec(encoding="grid", grid="L6-F2-T40-N4-32"), r"spec\.json: grid: table T: expected log2"),
    ("grid-resolutions-reversed", _spec(encoding="grid", grid="L6-F2-T12-N32-4"), r"spec\.json: grid: resolutions N<min>-<max>: expected 1 <= min <= max"),
    ("grid-number", _spec(encoding="grid", grid=6), r"spec\.json: grid: expected str \| None"),
    ("grid-fixed-pos-freqs", _spec(encoding="grid", fixed={"hidden": 16, "layers": 2, "pos_freqs": 4}), r"spec\.json: fixed\.pos_freqs: not used by the grid encoding"),
    ("grid-hidden-not-multiple-of-4", _spec(encoding="grid", ladder=[{"hidden": 10, "layers": 2}]), r"spec\.json: ladder\[0\]\.hidden: .*multiple of 4"),
    ("grid-glsl-const", _spec(encoding="grid", glsl_layout="const"), r"spec\.json: glsl_layout: 'const' is not supported with encoding 'grid'"),
    ("grid-time-budget", _spec(encoding="grid", time_budget=10), r"spec\.json: time_budget: 10 is not supported with encoding 'grid'"),
]


def _spec_cases() -> list[Case]:
    return [
        Case(f"train-spec-{name}", "prt-train", ["{case}/spec.json", "-o", OUT, "--no-progress"], message,
             f"prt-train: build spec {name}", {"spec.json": content, "tet.obj": TET})
        for name, content, message in SPECS
    ] + [
        Case("train-spec-missing", "prt-train", ["{case}/nope.json", "-o", OUT], r"nope\.json: no such file", "a spec that does not exist"),
        Case("train-spec-is-folder", "prt-train", ["{case}/specs.json", "-o", OUT], r"specs\.json: cannot read", "a folder named like a spec",
             {"specs.json/inner.txt": "x"}),
    ]


# Bad flags: (name, command, extra argv, message).  The input is a good mesh.
FLAGS = [
    ("train-threads-negative", "prt-train", ["--threads", "-1"], r"--threads: expected a positive integer"),
    ("train-threads-zero", "prt-train", ["--threads", "0"], r"--threads: expected a positive integer"),
    ("train-lr-nan", "prt-train", ["--lr", "nan"], r"lr: expected a finite positive number"),
    ("train-lr-negative", "prt-train", ["--lr", "-1"], r"lr: expected a finite positive number"),
    ("train-target-negative", "prt-train", ["--target", "-0.5"], r"target: expected a finite non-negative number"),
    ("train-target-inf", "prt-train", ["--target", "inf"], r"target: expected a finite non-negative number"),
    ("train-validation-negative", "prt-train", ["--validation", "-10"], r"validation: expected an integer >= 0"),
    ("train-samples-huge", "prt-train", ["--samples", str(10**14)], r"samples: .* GiB; at most"),
    ("train-samples-not-a-number", "prt-train", ["--samples", "many"], r"argument --samples: invalid int value"),
    ("train-match-tolerance-nan", "prt-train", ["--match-tolerance", "nan"], r"match_tolerance: expected a share"),
    ("train-match-malformed", "prt-train", ["--match", "64by4"], r"--match: expected KxL"),
    ("train-hidden-without-layers", "prt-train", ["--hidden", "16"], r"--hidden and --layers go together"),
    ("train-hidden-zero", "prt-train", ["--hidden", "0", "--layers", "2"], r"fixed\.hidden: expected a positive integer"),
    ("train-epochs-negative", "prt-train", ["--epochs", "-3"], r"epochs: expected 1"),
    ("train-steps-zero", "prt-train", ["--steps", "0"], r"steps: expected 1"),
    ("train-time-budget-nan", "prt-train", ["--time-budget", "nan"], r"time_budget: expected a finite positive number"),
    ("train-time-budget-zero", "prt-train", ["--time-budget", "0"], r"time_budget: expected a finite positive number"),
    ("train-unknown-flag", "prt-train", ["--sampels", "10"], r"unrecognized arguments: --sampels"),
    ("train-encoding-unknown", "prt-train", ["--encoding", "hash"], r"argument --encoding: invalid choice: 'hash'"),
    ("train-target-db-nan", "prt-train", ["--target-db", "nan"], r"target_db: expected a PSNR in dB"),
    ("train-grid-malformed", "prt-train", ["--encoding", "grid", "--grid", "L6F2"], r"grid: expected L<levels>-F<features>-T<log2 table>-N<min>-<max>"),
    ("train-grid-levels-zero", "prt-train", ["--encoding", "grid", "--grid", "L0-F2-T12-N4-32"], r"grid: levels L: expected 1 \.\. 16, got 0"),
    ("train-grid-without-encoding", "prt-train", ["--grid", "L6-F2-T12-N4-32"], r"grid: only with encoding 'grid'"),
    ("train-grid-pos-freqs", "prt-train", ["--encoding", "grid", "--hidden", "16", "--layers", "2", "--pos-freqs", "4"],
     r"fixed\.pos_freqs: not used by the grid encoding"),
    ("train-grid-bf16", "prt-train", ["--encoding", "grid", "--bf16"], r"bf16: True is not supported with encoding 'grid'"),
    ("train-bounces-negative", "prt-train", ["--bounces", "-1"], r"bounces: expected 0 \.\. 16"),
    ("train-bounces-huge", "prt-train", ["--bounces", str(10**9)], r"bounces: expected 0 \.\. 16"),
    ("train-bounces-not-a-number", "prt-train", ["--bounces", "two"], r"argument --bounces: expected a number of bounces or 'auto', got 'two'"),
    ("train-bounce-rays-zero", "prt-train", ["--bounces", "2", "--bounce-rays", "0"], r"bounce_rays: expected 1 \.\. 4096"),
    ("train-sdf-size-malformed", "prt-train", ["--neural-sdf", "--sdf-size", "64by4"], r"--sdf-size: expected KxL"),
    ("train-sdf-size-too-deep", "prt-train", ["--neural-sdf", "--sdf-size", "64x40"], r"--sdf-size: expected 1 <= K"),
    ("train-sdf-samples-few", "prt-train", ["--neural-sdf", "--sdf-samples", "10"], r"--sdf-samples >= 1000"),
    ("pre-samples-zero", "prt-precompute", ["--samples", "0"], r"--samples: expected an integer >= 1"),
    ("pre-samples-negative", "prt-precompute", ["--samples", "-100"], r"--samples: expected an integer >= 1"),
    ("pre-samples-huge", "prt-precompute", ["--samples", str(10**14)], r"--samples: .* GiB; at most"),
    ("pre-validation-negative", "prt-precompute", ["--validation", "-1"], r"--validation: expected an integer >= 0"),
    ("pre-rays-zero", "prt-precompute", ["--rays", "0"], r"--rays: expected 1"),
    ("pre-rays-huge", "prt-precompute", ["--rays", str(10**8)], r"--rays: expected 1 \.\. 65536"),
    ("pre-bands-zero", "prt-precompute", ["--bands", "0"], r"--bands: expected 1 \.\. 8"),
    ("pre-bands-nine", "prt-precompute", ["--bands", "9"], r"--bands: expected 1 \.\. 8"),
    ("pre-segments-zero", "prt-precompute", ["--segments", "0"], r"--segments: expected 1"),
    ("pre-seed-negative", "prt-precompute", ["--seed", "-7"], r"--seed: expected 0"),
    ("pre-delta-nan", "prt-precompute", ["--delta", "nan"], r"--delta: expected a finite non-negative"),
    ("pre-delta-negative", "prt-precompute", ["--delta", "-0.1"], r"--delta: expected a finite non-negative"),
    ("pre-merge-tolerance-inf", "prt-precompute", ["--merge-tolerance", "inf"], r"--merge-tolerance: expected a finite non-negative"),
    ("pre-threads-zero", "prt-precompute", ["--threads", "0"], r"--threads: expected a positive integer"),
    ("pre-threads-negative", "prt-precompute", ["--threads", "-4"], r"--threads: expected a positive integer"),
    ("pre-rays-not-a-number", "prt-precompute", ["--rays", "1e3"], r"argument --rays: invalid int value"),
    ("pre-unknown-flag", "prt-precompute", ["--ray", "16", "--bogus"], r"unrecognized arguments: --bogus"),
]


def _flag_cases() -> list[Case]:
    cases = [
        Case(name, command, ["{case}/tet.obj", "-o", OUT, "--no-progress", *extra], message, f"{command} {' '.join(extra)}", {"tet.obj": TET})
        for name, command, extra, message in FLAGS
    ]
    cases += [
        Case("pre-no-output", "prt-precompute", ["{case}/tet.obj"], r"INPUT and -o OUTDIR are required", "no -o", {"tet.obj": TET}),
        Case("pre-no-input", "prt-precompute", ["-o", OUT], r"INPUT and -o OUTDIR are required", "no input"),
        Case("train-no-output", "prt-train", ["{case}/tet.obj"], r"the following arguments are required: -o", "no -o", {"tet.obj": TET}),
        Case("pre-envmap-missing", "prt-precompute", ["{case}/tet.obj", "-o", OUT, "--envmap", "{case}/sky.hdr"], r"sky\.hdr",
             "an env map that does not exist", {"tet.obj": TET}),
        Case("pre-envmap-garbage", "prt-precompute", ["{case}/tet.obj", "-o", OUT, "--envmap", "{case}/sky.hdr"], r"sky\.hdr",
             "an env map of random bytes", {"tet.obj": TET, "sky.hdr": bytes(range(256)) * 4}),
    ]
    return cases


# Output folders that are not ours: the user's files must survive (the harness checks every input byte).
MARKER = ".prt-build"
USER_FILES = {"out/notes.txt": "my notes\n", "out/scene.json": '{"mine": true}\n', "out/build.json": "{}\n"}


def _folder_cases() -> list[Case]:
    cases = []
    for prefix, command, kind, other in (("train", "prt-train", "scene", "precompute"), ("pre", "prt-precompute", "precompute", "scene")):
        argv = ["{case}/tet.obj", "-o", "{case}/out", "--no-progress"]
        cases += [
            Case(f"{prefix}-out-not-ours", command, argv, r"out: not empty and not a prt build folder .*--force",
                 "an output folder holding someone's files", {"tet.obj": TET, **USER_FILES}),
            Case(f"{prefix}-out-other-kind", command, argv, rf"out: holds a {other} build, not a {kind} build",
                 f"an output folder holding a {other} build", {"tet.obj": TET, f"out/{MARKER}": json.dumps({"format": "prt-build", "version": 1, "kind": other})}),
            Case(f"{prefix}-out-marker-foreign", command, argv, r"out: its \.prt-build marker is unreadable or not ours",
                 "an output folder whose marker is someone else's", {"tet.obj": TET, f"out/{MARKER}": "<xml/>", "out/data.bin": b"\x00" * 16}),
            Case(f"{prefix}-out-is-a-file", command, ["{case}/tet.obj", "-o", "{case}/tet.obj"], r"tet\.obj: output exists and is not a folder",
                 "the mesh itself as the output folder", {"tet.obj": TET}),
            Case(f"{prefix}-out-under-a-file", command, ["{case}/tet.obj", "-o", "{case}/tet.obj/out"], r"tet\.obj/out: cannot create the output folder",
                 "an output folder inside a file", {"tet.obj": TET}),
        ]
    return cases


def cases() -> list[Case]:
    return _mesh_cases() + _spec_cases() + _flag_cases() + _folder_cases()
