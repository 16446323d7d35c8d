"""Rebuild the demo scene shipped in the package (runtime/data/demo): Keenan Crane's Spot
(public domain), right-sized networks, small enough to ship.

usage: python scripts/build_demo_scene.py [--work DIR]

Runs prt-train into a work folder, then copies only what the runtime needs (scene.json,
geometry.npz, segments/*) into runtime/data/demo.  Takes about two minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "runtime" / "data" / "demo"


def main(argv=None) -> int:
    from prt.train.train_cli import main as prt_train

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=Path("/tmp/prt-demo-build"))
    args = p.parse_args(argv)
    spec = args.work.parent / "prt-demo-spec.json"
    spec.parent.mkdir(parents=True, exist_ok=True)
    spec.write_text(json.dumps({
        "geometry": str(ROOT / "tests" / "data" / "spot.obj"),
        "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]},
        "camera": {"eye": [1.6, 0.9, -2.8], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov": 40.0},
    }))  # fmt: skip
    rc = prt_train(
        [
            str(spec),
            "-o", str(args.work),
            "--name", "spot",
            "--samples", "300000",
            "--rays", "512",
            "--segments", "4",
            "--epochs", "80",
            "--target", "0.003",
        ]
    )  # fmt: skip
    if rc != 0:
        return rc
    if DEMO.exists():
        shutil.rmtree(DEMO)
    (DEMO / "segments").mkdir(parents=True)
    for name in ("scene.json", "geometry.npz", "build.json"):
        shutil.copy2(args.work / name, DEMO / name)
    for f in sorted((args.work / "segments").iterdir()):
        shutil.copy2(f, DEMO / "segments" / f.name)
    (DEMO / "LICENSE.md").write_text(
        "# Demo scene\n\nSpot by Keenan Crane, released into the public domain (see tests/data/LICENSES.md).\n"
        "Networks trained with `python scripts/build_demo_scene.py`.\n"
    )
    size = sum(f.stat().st_size for f in DEMO.rglob("*") if f.is_file())
    print(f"demo scene: {DEMO} ({size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
