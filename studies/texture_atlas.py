"""What a UV atlas costs: xatlas (or the mesh's own UVs, with the overlap check) per mesh, size and layout.

usage: python studies/texture_atlas.py MESH [MESH ...] [--sizes 512 1024] [--json OUT]

For each mesh, :func:`prt.train.inputs.uv_atlas.build_atlas` at each texture size with one shared atlas
and with one atlas per object (texture sets): seconds, atlases, where the UVs came from, and the
share of texels the charts cover (UV G-buffer, :func:`prt.train.transport.transfer_texture.uv_gbuffer`).
The bunny lives in ../shared/data/meshes (research-only licence, not shipped).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from prt.runtime.gl import create_context
from prt.train.inputs.geometry import load_geometry
from prt.train.transport.transfer_texture import uv_gbuffer
from prt.train.inputs.uv_atlas import LAYOUTS, build_atlas


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("meshes", nargs="+")
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    ctx = create_context()
    rows = []
    for mesh in args.meshes:
        geometry = load_geometry(mesh)
        for size in args.sizes:
            for layout in LAYOUTS:
                atlas = build_atlas(geometry, size, layout, ctx=ctx, log=lambda line: None)
                _, _, covered = uv_gbuffer(ctx, np.asarray(geometry.mesh.vertices, np.float32), np.asarray(geometry.mesh.faces), atlas, size)
                row = {
                    "mesh": os.path.basename(mesh), "triangles": len(geometry.mesh.faces), "objects": geometry.n_objects,
                    "two_sided_triangles": int(geometry.two_sided.sum()), "size": size, "layout": layout,
                    "atlases": atlas.n_atlases, "uv_source": atlas.source, "seconds": round(atlas.seconds, 3),
                    "texel_utilisation": round(float(covered.mean()), 4), "note": atlas.note,
                    "load_average": round(os.getloadavg()[0], 2),
                }  # fmt: skip
                rows.append(row)
                print(f"{row['mesh']} {size} {layout}: {row['seconds']:.2f} s, {row['atlases']} atlas(es), "
                      f"{row['uv_source']}, {row['texel_utilisation']:.0%} texels covered (load {row['load_average']})")  # fmt: skip
    if args.json is not None:
        args.json.write_text(json.dumps({"atlases": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
