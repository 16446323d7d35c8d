"""Hostile mixed-scene specs (``objects``, :mod:`prt.train.inputs.mixed`) for ``prt-train`` (``train-objects-*``).

All fail in the spec checks, before any geometry is loaded; nothing is left behind.
"""

from __future__ import annotations

import json

from corpus import Case

QUAD = "v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n"
OUT = "{run}/out"

# (name, objects, message): each is the spec {"objects": objects}
OBJECTS = [
    ("empty", [], r"spec\.json: objects: expected a non-empty list"),
    ("not-a-list", {"mesh": "quad.obj"}, r"spec\.json: objects: expected list\[dict\] \| None"),
    ("entry-string", ["quad.obj"], r"spec\.json: objects\[0\]: expected an object"),
    ("two-kinds", [{"mesh": "quad.obj", "sdf": "sphere"}], r"spec\.json: objects\[0\]: expected exactly one of"),
    ("unknown-sdf", [{"sdf": "blob"}], r"spec\.json: objects\[0\]\.sdf: unknown SDF 'blob'"),
    ("neural-not-onnx", [{"neural_sdf": "quad.obj"}], r"spec\.json: objects\[0\]\.neural_sdf: expected a '\*\.sdf\.onnx' network"),
    ("scale-negative", [{"mesh": "quad.obj"}, {"sdf": "sphere", "scale": -2}], r"spec\.json: objects\[1\]\.scale: expected a finite number > 0"),
    ("translate-short", [{"sdf": "sphere", "translate": [1, 2]}], r"spec\.json: objects\[0\]\.translate: expected 3 finite numbers"),
    ("rotate-text", [{"sdf": "sphere", "rotate": "90"}], r"spec\.json: objects\[0\]\.rotate: expected 3 finite numbers"),
    ("material-bad", [{"sdf": "sphere", "material": {"type": "shiny"}}], r"spec\.json: objects\[0\]\.material"),
    ("unknown-field", [{"sdf": "sphere", "colour": [1, 0, 0]}], r"spec\.json: objects\[0\]\.colour: unknown field"),
    ("name-twice", [{"mesh": "quad.obj", "name": "a"}, {"sdf": "sphere", "name": "a"}], r"spec\.json: objects\[1\]\.name: 'a' names an earlier object"),
    ("mesh-missing", [{"mesh": "nope.obj"}, {"sdf": "sphere"}], r"spec\.json: objects\[0\]\.mesh: no such file"),
]


def cases() -> list[Case]:
    return [
        Case(f"train-objects-{name}", "prt-train", ["{case}/spec.json", "-o", OUT, "--no-progress"], message,
             f"prt-train: mixed-scene spec, objects {name}", {"spec.json": json.dumps({"objects": objects}), "quad.obj": QUAD})
        for name, objects, message in OBJECTS
    ]  # fmt: skip
