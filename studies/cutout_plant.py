"""A synthetic plant of alpha-masked leaf cards, as GLB: quads (glTF ``alphaMode`` MASK, a square
texture whose alpha is an ellipse, the leaf) around stems on a ground box; for the cut-outs of
``prt.train.inputs.cutout`` (the build guide, *Cut-outs*).  The defaults (24 leaves on one stem,
a 128x128 texture) are the recorded plant; ``--leaves 240 --stems 5`` a bush.

usage: python studies/cutout_plant.py OUT.glb [--leaves N] [--stems N] [--size PIXELS] [--seed N]
"""

from __future__ import annotations

import argparse

import imageio.v3 as iio
import numpy as np

from prt.train.deform.gltf_animation import pack_accessors, write_glb

BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)  # fmt: skip


def leaf_texture(size: int) -> np.ndarray:
    """RGBA: green, alpha an ellipse along x (u) filling the square."""
    y, x = np.mgrid[0:size, 0:size] + 0.5
    c = size / 2
    leaf = ((x - c) / (size * 60 / 128)) ** 2 + ((y - c) / (size * 26 / 128)) ** 2 < 1
    image = np.zeros((size, size, 4), np.uint8)
    image[..., 0], image[..., 1], image[..., 2] = 40, 150, 40
    image[..., 3] = np.where(leaf, 255, 0)
    return image


def cards(leaves: int, stems: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """Leaf quads up ``stems`` stems (one at the origin; more on a circle): vertices, faces, UVs, stem bases."""
    bases = [np.zeros(3)] if stems == 1 else [0.5 * np.array([np.cos(a), 0.0, np.sin(a)]) for a in np.arange(stems) * 2 * np.pi / stems]
    per_stem = leaves // stems
    verts, faces, uvs = [], [], []
    for base in bases:
        for k in range(per_stem):
            h = 0.2 + 1.2 * k / per_stem
            ang = rng.uniform(0, 2 * np.pi)
            tilt = rng.uniform(0.2, 0.7)
            d = np.array([np.cos(ang), 0, np.sin(ang)])
            side = np.array([-np.sin(ang), 0, np.cos(ang)])
            along = d * np.cos(tilt) + np.array([0, 1, 0]) * np.sin(tilt)
            c0 = base + np.array([0, h, 0])
            quad = [c0 - 0.12 * side, c0 - 0.12 * side + 0.5 * along, c0 + 0.12 * side + 0.5 * along, c0 + 0.12 * side]
            verts.append(np.array(quad))
            uvs.append(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]))  # u along the leaf (x of the image), v across
            faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * len(faces))
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs), bases


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out")
    p.add_argument("--leaves", type=int, default=24)
    p.add_argument("--stems", type=int, default=1)
    p.add_argument("--size", type=int, default=128, help="leaf texture size in pixels")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    V, F, UV, bases = cards(args.leaves, args.stems, np.random.default_rng(args.seed))
    stem_v = np.concatenate([np.array([[x, y, z] for x in (-0.02, 0.02) for y in (0, 1.5) for z in (-0.02, 0.02)]) + b for b in bases])
    stem_f = np.concatenate([BOX_F + 8 * k for k in range(len(bases))])
    ground_v = np.array([[x, y, z] for x in (-1.5, 1.5) for y in (-0.1, 0) for z in (-1.5, 1.5)], np.float32)
    arrays = [V.astype(np.float32), F.astype(np.uint32).reshape(-1, 1), UV.astype(np.float32), stem_v.astype(np.float32),
              stem_f.astype(np.uint32).reshape(-1, 1), ground_v]  # fmt: skip
    ground_f = 4 if len(bases) == 1 else len(arrays)  # one stem: the ground's box shares the stem's indices
    if len(bases) > 1:
        arrays.append(BOX_F.reshape(-1, 1))
    views, accessors, binary = pack_accessors(arrays)
    png = iio.imwrite("<bytes>", leaf_texture(args.size), extension=".png")
    views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)})
    binary += png + b"\0" * ((-len(png)) % 4)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [{"name": "leaves", "mesh": 0}, {"name": "stem", "mesh": 1}, {"name": "ground", "mesh": 2}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]},
                   {"primitives": [{"attributes": {"POSITION": 3}, "indices": 4, "material": 1}]},
                   {"primitives": [{"attributes": {"POSITION": 5}, "indices": ground_f, "material": 2}]}],
        "materials": [{"name": "leaf", "alphaMode": "MASK", "doubleSided": True, "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0}},
                      {"name": "stem", "pbrMetallicRoughness": {"baseColorFactor": [0.3, 0.5, 0.2, 1], "metallicFactor": 0}},
                      {"name": "soil", "pbrMetallicRoughness": {"baseColorFactor": [0.45, 0.35, 0.25, 1], "metallicFactor": 0}}],
        "textures": [{"source": 0}], "images": [{"bufferView": len(arrays), "mimeType": "image/png"}],
        "bufferViews": views, "accessors": accessors,
    }  # fmt: skip
    write_glb(args.out, document, binary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
