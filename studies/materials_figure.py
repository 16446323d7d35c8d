"""Per-object materials and albedo textures, side by side: docs/materials.png.

usage: python studies/materials_figure.py CORNELL_SCENE SPOT_SCENE [--out docs/materials.png] [--size 384]

Panels: the Cornell box with one material for every object (what the renderer did before),
the same scene with the materials of its MTL file (red and green walls; the boxes are the
file's glossy Ks 0.725, Ns 200), and Spot with its albedo texture.  Both scenes are built by
``prt-train`` from a mesh whose MTL names the colours (Spot: an MTL with ``map_Kd
spot_texture.png``; the shared spot.obj has none).  Lighting: the bundled ``studio`` env map,
exposure 2 for the box (lit through its open side only), 1 for Spot; backend ONNX (the GLSL backend gives the same image, >= 60 dB).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from prt.runtime.renderer import Renderer, Scene
from prt.runtime.shading import to_srgb8


def _render(path, size: int, uniform: bool = False, exposure: float = 1.0) -> np.ndarray:
    with Renderer(Scene.load(path), size, size) as r:
        r.set_envmap("studio")
        if uniform:
            r.set_material("diffuse", albedo=r.material.albedo)
        return to_srgb8(r.render(), exposure)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cornell")
    p.add_argument("spot")
    p.add_argument("--out", type=Path, default=Path("docs/materials.png"))
    p.add_argument("--size", type=int, default=384)
    args = p.parse_args(argv)
    box = {"size": args.size, "exposure": 2.0}  # the box is lit through its open side only
    panels = [_render(args.cornell, uniform=True, **box), _render(args.cornell, **box), _render(args.spot, args.size)]
    gap = np.full((args.size, 8, 3), 255, np.uint8)
    iio.imwrite(args.out, np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
