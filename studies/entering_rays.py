"""How many bounce rays enter the surface they leave (issue 38; ``interreflection.entering``).

usage: python studies/entering_rays.py MESH [MESH ...] [--samples 20000] [--rays 64] [--json OUT]

Samples carry the G-buffer's interpolated normal; their cosine hemisphere reaches below the plane
of their own flat face.  Per mesh (normalised as a build loads it): the share of cosine rays
(``--rays`` per sample, spun frames) below the own face's plane, the share of them that hit
something from an origin lifted 1e-4 along the normal (before the rule they gathered that light;
mostly the face itself, ``self_hit``), and the share that slip past the face's edge and miss.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from prt.bench.provenance import provenance
from prt.runtime.files import atomic_write_json
from prt.train.inputs.geometry import load_geometry
from prt.train.inputs.sampling import sample_surface
from prt.train.transport.interreflection import entering, face_normals
from prt.train.transport.transfer import cosine_directions, make_tracer, orthonormal_frames


def measure(path: str, samples: int, rays: int) -> dict:
    geometry = load_geometry(path)
    s = sample_surface(geometry, samples, seed=0)
    tracer = make_tracer(geometry)
    frames = orthonormal_frames(s.normals, np.random.default_rng(0).uniform(0.0, 2.0 * np.pi, len(s.normals)))
    dirs = np.einsum("mk,pck->pmc", cosine_directions(rays), frames)
    below = entering(dirs, s.normals, s.face_index, face_normals(tracer))
    origins = np.repeat((s.points + tracer.offset * s.normals).astype(np.float32), rays, axis=0)
    result = tracer._scene.run(origins, dirs.reshape(-1, 3).astype(np.float32), output=1)
    faces = result["primID"].reshape(-1, rays)
    return {"mesh": Path(path).name, "vertices": len(geometry.mesh.vertices), "triangles": len(geometry.mesh.faces),
            "below_own_face": round(float(below.mean()), 5), "below_and_hit": round(float((below & (faces >= 0)).mean()), 5),
            "self_hit": round(float((below & (faces == s.face_index[:, None])).mean()), 5),
            "below_and_miss": round(float((below & (faces < 0)).mean()), 5)}  # fmt: skip


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("meshes", nargs="+")
    p.add_argument("--samples", type=int, default=20000)
    p.add_argument("--rays", type=int, default=64)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    rows = []
    for mesh in args.meshes:
        rows.append(measure(mesh, args.samples, args.rays))
        print(json.dumps(rows[-1]), flush=True)
    if args.json:
        atomic_write_json(args.json, {"provenance": provenance(), "samples": args.samples, "rays": args.rays, "meshes": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
