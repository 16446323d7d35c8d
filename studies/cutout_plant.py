"""A synthetic plant of alpha-masked leaf cards, as GLB: 24 quads (glTF ``alphaMode`` MASK, a 128x128
texture whose alpha is an ellipse, the leaf) around a stem on a ground box; for the cut-outs of
``prt.train.inputs.cutout`` (the build guide, *Cut-outs*).

usage: python studies/cutout_plant.py OUT.glb
"""
import sys, numpy as np, imageio.v3 as iio
from prt.train.deform.gltf_animation import pack_accessors, write_glb
rng = np.random.default_rng(0)
S = 128
y, x = np.mgrid[0:S, 0:S] + 0.5
leaf = ((x - 64) / 60) ** 2 + ((y - 64) / 26) ** 2 < 1
img = np.zeros((S, S, 4), np.uint8); img[..., 0] = 40; img[..., 1] = 150; img[..., 2] = 40; img[..., 3] = np.where(leaf, 255, 0)
verts, faces, uvs = [], [], []
for k in range(24):
    h = 0.2 + 1.2 * k / 24
    ang = rng.uniform(0, 2 * np.pi); tilt = rng.uniform(0.2, 0.7)
    d = np.array([np.cos(ang), 0, np.sin(ang)]); side = np.array([-np.sin(ang), 0, np.cos(ang)])
    up = np.array([0, 1, 0])
    along = d * np.cos(tilt) + up * np.sin(tilt)
    c0 = np.array([0, h, 0])
    quad = [c0 - 0.12 * side, c0 - 0.12 * side + 0.5 * along, c0 + 0.12 * side + 0.5 * along, c0 + 0.12 * side]
    base = len(verts) * 4
    verts.append(np.array(quad)); uvs.append(np.array([[0, 0], [1, 0], [1, 1], [0, 1]]))
    faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k)
V = np.concatenate(verts).astype(np.float32); F = np.concatenate(faces).astype(np.uint32); UV = np.concatenate(uvs).astype(np.float32)
# leaf cards: u along the leaf (x of the image), v across
stem_v = np.array([[x, yy, z] for x in (-0.02, 0.02) for yy in (0, 1.5) for z in (-0.02, 0.02)], np.float32)
BOX_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)
ground_v = np.array([[x, yy, z] for x in (-1.5, 1.5) for yy in (-0.1, 0) for z in (-1.5, 1.5)], np.float32)
arrays = [V, F.reshape(-1, 1), UV, stem_v, BOX_F.reshape(-1, 1), ground_v]
views, accessors, binary = pack_accessors(arrays)
png = iio.imwrite("<bytes>", img, extension=".png")
views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(png)}); binary += png + b"\0" * ((-len(png)) % 4)
doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
       "nodes": [{"name": "leaves", "mesh": 0}, {"name": "stem", "mesh": 1}, {"name": "ground", "mesh": 2}],
       "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 2}, "indices": 1, "material": 0}]},
                  {"primitives": [{"attributes": {"POSITION": 3}, "indices": 4, "material": 1}]},
                  {"primitives": [{"attributes": {"POSITION": 5}, "indices": 4, "material": 2}]}],
       "materials": [{"name": "leaf", "alphaMode": "MASK", "doubleSided": True, "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0}},
                     {"name": "stem", "pbrMetallicRoughness": {"baseColorFactor": [0.3, 0.5, 0.2, 1], "metallicFactor": 0}},
                     {"name": "soil", "pbrMetallicRoughness": {"baseColorFactor": [0.45, 0.35, 0.25, 1], "metallicFactor": 0}}],
       "textures": [{"source": 0}], "images": [{"bufferView": len(arrays), "mimeType": "image/png"}],
       "bufferViews": views, "accessors": accessors}
write_glb(sys.argv[1], doc, binary)
