"""``prt-web SCENE -o OUT``: a built scene as a static web page that renders on the viewer's own GPU.

The folder it writes opens from any static file server (``python3 -m http.server -d OUT``) with
no build step, no CDN and no network access beyond that server:

- ``index.html`` and ``prt-web.js`` (one ES module; package data in ``export/web_page/``);
- ``three.html``, ``prt-three.js`` (an ES module: the scene as three.js meshes with a material
  that runs its networks, ``docs/guides/three.md``) and ``vendor/three/`` (three.js
  :data:`THREE_VERSION` from npm, minified, with its MIT licence: nothing comes from a CDN);
- ``web.json``: what the page reads (format :data:`WEB_FORMAT`, version :data:`WEB_VERSION`): the
  scene's name and size, camera, segment tables, uniforms, lighting data, the file table (each
  file's size, which the page checks);
- ``geometry.bin``, ``weights.bin`` (and ``albedo.bin``, ``poses.bin``, ``envmaps/*.rgbe``):
  little-endian arrays (:mod:`prt.export.web_assets`);
- ``shaders/*``: GLSL ES 3.00 assembled from the runtime's own shader files and the scene's
  generated network GLSL (the ``glsl`` backend's program, in the WebGL2 dialect); ``three*.vert``,
  ``three*.frag``: the three.js material's stages (``web.json``'s ``three.programs``).

The page runs the ``glsl`` backend's frame: G-buffer, transfer pass (the networks), shading,
background, tone mapping; its contract (query parameters, ``#prt-capture``, ``data-prt-state``)
is in ``docs/guides/web.md``.

A folder is written only when it is new, empty, or an earlier output of this command (its marker
file ``.prt-web``); every file is written atomically and the marker first, so an interrupted run
leaves a folder the next run may overwrite.  Bad input (a missing or broken scene, a manifest of
a newer version, an SDF scene) is one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from importlib import resources
from pathlib import Path

from ..runtime.errors import PRTError
from ..runtime.files import atomic_write_bytes, atomic_write_json

__all__ = ["WEB_FORMAT", "WEB_VERSION", "MARKER", "PAGE_FILES", "THREE_FILES", "THREE_VERSION", "VENDOR_FILES", "build_parser", "main",
           "write_web"]  # fmt: skip

WEB_FORMAT = "prt-web"
WEB_VERSION = 1
"""Format of ``web.json``; the page refuses a newer version with one line."""
MARKER = ".prt-web"
PAGE_FILES = ("index.html", "prt-web.js")
"""The page's own static files (package data under ``export/web_page/``)."""
THREE_FILES = ("three.html", "prt-three.js")
"""The three.js module and its example page (package data under ``export/web_page/``)."""
THREE_VERSION = "0.185.1"
"""The three.js shipped in ``vendor/three/`` (``npm pack three@0.185.1``; ``VERSION.json`` there)."""
VENDOR_FILES = ("three.module.min.js", "three.core.min.js", "OrbitControls.js", "LightProbeGrid.js", "LICENSE", "VERSION.json")
"""three.js's files in ``export/web_page/vendor/three/``, written to ``vendor/three/`` of the output."""
GENERATOR = "prt-web 0.1.0"


class WebOutputError(PRTError):
    """An output folder prt-web will not write into (one line)."""


def check_output(out: Path, force: bool = False) -> None:
    """Refuse a folder that is not new, empty or ours (the ``.prt-web`` marker); creates nothing."""
    if out.exists() and not out.is_dir():
        raise WebOutputError(f"{out}: output exists and is not a folder")
    if not out.exists() or force:
        return
    try:
        empty = next(out.iterdir(), None) is None
    except OSError as exc:
        raise WebOutputError(f"{out}: cannot read the output folder ({exc.strerror or exc})") from None
    if empty:
        return
    try:
        marker = json.loads((out / MARKER).read_bytes())
    except (OSError, ValueError):
        marker = None
    if not (isinstance(marker, dict) and marker.get("format") == WEB_FORMAT):
        raise WebOutputError(f"{out}: not empty and not a prt-web output (no {MARKER}); files of the same names would be overwritten: "
                             "choose an empty or new folder, or pass --force")  # fmt: skip


def page_file(name: str) -> bytes:
    """A static file of the page (``index.html``, ``prt-web.js``, ``vendor/three/...``)."""
    return resources.files(__package__).joinpath("web_page", *name.split("/")).read_bytes()


def write_web(scene_path, out, *, force: bool = False) -> dict:
    """Write the page of the built scene ``scene_path`` (a ``scene.json`` or its folder) into ``out``.

    Returns
    -------
    dict
        ``{"files": {relative path: bytes}, "payload_bytes": int, "out": Path}``; the payload is
        every file the page loads.

    Raises
    ------
    PRTError
        One line: the scene cannot be read or drawn in a page, or ``out`` is not ours.
    """
    from ..runtime.renderer import Scene
    from .web_assets import scene_assets

    out = Path(out)
    check_output(out, force)
    scene = Scene.load(scene_path)
    assets = scene_assets(scene)
    files: dict[str, bytes] = {name: page_file(name) for name in PAGE_FILES}
    files.update(assets.arrays)
    files.update({f"shaders/{name}": text.encode() for name, text in assets.programs.items()})
    three: dict[str, bytes] = {name: page_file(name) for name in THREE_FILES}  # what only three.html loads
    three.update({f"vendor/three/{name}": page_file(f"vendor/three/{name}") for name in VENDOR_FILES})
    three.update({f"shaders/{name}": text.encode() for name, text in assets.three_programs.items()})
    table = {name: len(data) for name, data in {**files, **three}.items()}
    web = {"format": WEB_FORMAT, "version": WEB_VERSION, "generator": GENERATOR, **assets.info, "files": table,
           "programs": {name: f"shaders/{name}" for name in assets.programs},
           "three": {"version": THREE_VERSION, "module": "prt-three.js", "page": "three.html",
                     "vendor": {name: f"vendor/three/{name}" for name in VENDOR_FILES},
                     "programs": {name: f"shaders/{name}" for name in assets.three_programs}}}  # fmt: skip
    shared = sum(len(v) for v in assets.arrays.values())
    index_bytes = sum(len(v) for v in files.values())
    unloaded = ("vendor/three/LICENSE", "vendor/three/VERSION.json", "vendor/three/LightProbeGrid.js")  # (the last with grid=1 only)
    three_bytes = shared + sum(len(v) for k, v in three.items() if k not in unloaded)
    web["scene"]["payload_bytes"] = web["three"]["payload_bytes"] = 0
    while True:  # each payload counts web.json itself, which holds the figures: their fixed point (two rounds)
        text = json.dumps(web, separators=(",", ":")).encode()
        totals = (index_bytes + len(text), three_bytes + len(text))
        if totals == (web["scene"]["payload_bytes"], web["three"]["payload_bytes"]):
            break
        web["scene"]["payload_bytes"], web["three"]["payload_bytes"] = totals
    files.update(three)
    try:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / MARKER, {"format": WEB_FORMAT, "version": WEB_VERSION})
        for name, data in files.items():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(out / name, data)
        atomic_write_bytes(out / "web.json", text)  # last: a page finds web.json only when the rest is there
    except OSError as exc:
        raise WebOutputError(f"{out}: cannot write the page ({exc.strerror or exc})") from None
    files["web.json"] = text
    return {"files": {k: len(v) for k, v in files.items()}, "payload_bytes": web["scene"]["payload_bytes"],
            "three_payload_bytes": web["three"]["payload_bytes"], "out": out}  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="prt-web",
        description="Write a built scene as a static web page (WebGL2) that renders it on the viewer's GPU; "
        "serve the folder with any static file server, e.g. python3 -m http.server -d OUT.",
    )
    parser.add_argument("scene", help="the built scene: its scene.json or its folder")
    parser.add_argument("-o", "--out", required=True, help="output folder (new, empty, or an earlier prt-web output)")
    parser.add_argument("--force", action="store_true", help="write into a non-empty folder that is not a prt-web output")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        report = write_web(args.scene, args.out, force=args.force)
    except PRTError as exc:
        print(f"prt-web: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    out = report["out"]
    print(f"prt-web: wrote {out} ({len(report['files'])} files, {report['payload_bytes'] / 1e6:.2f} MB the page loads)")
    print(f"serve it with:  python3 -m http.server -d {out} 8000   then open http://127.0.0.1:8000/")
    print(f"the scene in three.js {THREE_VERSION}: http://127.0.0.1:8000/three.html ({report['three_payload_bytes'] / 1e6:.2f} MB; docs/guides/three.md)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
