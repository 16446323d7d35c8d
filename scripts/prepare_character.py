"""Derive ``tests/data/character/minetest_character.glb`` from assimp's conversion of Minetest's
player model (origin and licence: ``tests/data/character/LICENSE.md``).

usage: python scripts/prepare_character.py CONVERTED.glb [--out PATH]

``CONVERTED.glb`` is ``assimp export character.b3d character.glb -fglb2`` (assimp 5.2.5).  It
holds one animation, ``anim``, with every clip of the game concatenated, key ``i`` at time
``(i + 1) / 60`` s.  This writes the same mesh, skin and nodes with that animation split into the
clips the game plays (``player_api/init.lua``), each clip's keys re-timed to start at 0 (the
file's 1/60 s spacing kept), and cleans up what the conversion added: the deprecated
``KHR_materials_pbrSpecularGlossiness`` material extension, the unused ``FB_ngon_encoding``
declaration, the accessors of the long animation, and channels that hold their node's rest
value through a whole clip (the nodes keep that value without them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from prt.train.deform.gltf_animation import AnimatedScene, pack_accessors, read_gltf, write_glb

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "data" / "character" / "minetest_character.glb"
# Key index ranges (inclusive) of Minetest Game's player_api/init.lua.
CLIPS = {"stand": (0, 79), "sit": (81, 160), "lay": (162, 166), "walk": (168, 187), "mine": (189, 198), "walk_mine": (200, 219)}
_MESH_ATTRIBUTES = ("POSITION", "NORMAL", "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0")


def split_document(source_path: Path) -> tuple[dict, bytes]:
    """The cleaned document and its binary buffer.

    Parameters
    ----------
    source_path : Path
        The converted GLB (one mesh with one primitive, one skin, one animation).

    Returns
    -------
    document : dict
        glTF JSON without ``buffers`` (:func:`write_glb` adds it).
    binary : bytes
    """
    gltf = read_gltf(source_path)
    document = gltf.document
    (mesh,) = document["meshes"]
    (primitive,) = mesh["primitives"]
    (skin,) = document["skins"]
    (animation,) = document["animations"]
    arrays, names = [], {}

    def add(key, values, dtype):
        names[key] = len(arrays)
        arrays.append(np.asarray(values).astype(dtype))

    joint_type = np.uint8 if document["accessors"][primitive["attributes"]["JOINTS_0"]]["componentType"] == 5121 else np.uint16
    dtypes = {"JOINTS_0": joint_type}
    for attribute in _MESH_ATTRIBUTES:
        add(attribute, gltf.accessor(primitive["attributes"][attribute]), dtypes.get(attribute, np.float32))
    add("indices", gltf.accessor(primitive["indices"]).reshape(-1, 1), np.uint32)
    add("inverse_bind", gltf.accessor(skin["inverseBindMatrices"]), np.float32)

    clip = AnimatedScene(gltf).clip(animation.get("name"))
    animations = []
    for name, (first, last) in CLIPS.items():
        channels, samplers = [], []
        for node, path, times, values, _ in clip.channels:
            if _holds_rest(document["nodes"][node], path, values[first : last + 1]):
                continue
            if len(times) <= last:
                raise SystemExit(f"{source_path}: node {node} {path} has {len(times)} keys, clip {name} needs {last + 1}")
            key = f"{name}:{node}:{path}"
            add(key + ":in", times[first : last + 1] - times[first], np.float32)
            add(key + ":out", values[first : last + 1], np.float32)
            samplers.append({"input": names[key + ":in"], "output": names[key + ":out"], "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})
        animations.append({"name": name, "channels": channels, "samplers": samplers})

    views, accessors, binary = pack_accessors(arrays)
    materials = [{k: v for k, v in m.items() if k != "extensions"} for m in document.get("materials", [])]
    primitive_out = {
        "mode": 4,
        "indices": names["indices"],
        "attributes": {a: names[a] for a in _MESH_ATTRIBUTES},
    }
    if "material" in primitive:
        primitive_out["material"] = primitive["material"]
    cleaned = {
        "asset": {
            "version": "2.0",
            "generator": f"{document['asset'].get('generator', 'assimp')}; prt scripts/prepare_character.py",
        },
        "scene": document.get("scene", 0),
        "scenes": document["scenes"],
        "nodes": document["nodes"],
        "meshes": [{"primitives": [primitive_out]}],
        "skins": [dict(skin, inverseBindMatrices=names["inverse_bind"])],
        "materials": materials,
        "animations": animations,
        "bufferViews": views,
        "accessors": accessors,
    }
    return cleaned, binary


def _holds_rest(node: dict, path: str, values: np.ndarray) -> bool:
    """Whether a channel's keys over a clip all equal the node's rest value (a quaternion up to sign)."""
    rest = np.asarray(node.get(path, {"translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1]}[path]))
    if path == "rotation":
        values = values * np.where(values @ rest < 0, -1.0, 1.0)[:, None]
    return bool(np.all(np.abs(values - rest) < 1e-6 * max(1.0, float(np.abs(rest).max()))))


def main(argv: list[str] | None = None) -> int:
    """Command line: read the converted GLB, write the split one."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("converted", type=Path, help="assimp's character.glb")
    parser.add_argument("--out", type=Path, default=OUT, help=f"output GLB (default {OUT.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    document, binary = split_document(args.converted)
    write_glb(args.out, document, binary)
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes, clips {', '.join(CLIPS)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
