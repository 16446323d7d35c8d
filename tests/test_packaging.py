"""Packaging: the runtime imports without torch; a plain wheel holds only ``prt`` with its data."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

BLOCK_TORCH = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked in this test")
sys.meta_path.insert(0, Block())
import pkgutil, importlib
import prt.runtime
for m in pkgutil.iter_modules(prt.runtime.__path__):
    importlib.import_module("prt.runtime." + m.name)
assert not any(k == "torch" or k.startswith("torch.") for k in sys.modules), "torch got imported"
print("ok", len(list(pkgutil.iter_modules(prt.runtime.__path__))))
"""


def test_runtime_imports_with_torch_blocked():
    out = subprocess.run([sys.executable, "-c", BLOCK_TORCH], capture_output=True, text=True, cwd="/")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok")
    assert int(out.stdout.split()[1]) >= 3  # sh, envmap, errors, ... all imported


RENDER_WITHOUT_TRAINING_DEPS = """
import importlib.abc, sys
BLOCKED = ("torch", "trimesh", "embreex", "onnx", "scipy", "skimage")
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(name + " is blocked in this test")
sys.meta_path.insert(0, Block())
from prt.runtime import Scene, Renderer
from prt.runtime.backends import BACKENDS
for backend in BACKENDS:
    with Renderer(Scene.load(), 32, 32, backend=backend) as r:
        image = r.render()
    assert image.max() > 0, backend
print("rendered")
"""


def test_the_demo_renders_without_any_training_dependency():
    out = subprocess.run([sys.executable, "-c", RENDER_WITHOUT_TRAINING_DEPS], capture_output=True, text=True, cwd="/")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "rendered"


def test_runtime_sources_never_import_torch():
    offenders = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "runtime").rglob("*.py")
        if any(line.strip().startswith(("import torch", "from torch")) for line in p.read_text().splitlines())
    ]
    assert offenders == []


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(ROOT)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0 and "No module named" in proc.stderr and "wheel" in proc.stderr:
        pytest.skip("the 'wheel' package is not installed in this environment")
    assert proc.returncode == 0, proc.stderr
    (path,) = out.glob("prt_runtime-*.whl")
    return path


def test_wheel_holds_only_the_prt_package_with_shaders(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"prt", next(t for t in top if t.endswith(".dist-info"))}
    for module in ("prt/__init__.py", "prt/runtime/sh.py", "prt/runtime/backends/__init__.py", "prt/runtime/backends/onnx.py",
                   "prt/train/transport/transfer.py", "prt/train/inputs/geometry.py", "prt/train/networks/fit.py",
                   "prt/train/deform/deform_build.py", "prt/train/sdf/neural_fit.py", "prt/export/__init__.py",
                   "prt/shaders/__init__.py"):
        assert module in names, module
    assert not any(n.startswith(("prt/studies/", "prt/bench/studies/")) for n in names)  # study scripts are not shipped
    shaders = [n for n in names if n.startswith("prt/shaders/") and not n.endswith(".py")]
    assert "prt/shaders/tonemap.glsl" in shaders and "prt/shaders/viewer_blit.frag" in shaders, shaders
    assert not any(n.startswith("prt/tests/") for n in names)
    for data in ("prt/runtime/schemas/scene.schema.json", "prt/runtime/data/demo/scene.json", "prt/export/web_page/index.html",
                 "prt/export/web_page/prt-web.js", "prt/export/web_page/prt-three.js", "prt/export/web_page/three.html",
                 "prt/export/web_page/vendor/three/three.module.min.js", "prt/export/web_page/vendor/three/three.core.min.js",
                 "prt/export/web_page/vendor/three/OrbitControls.js", "prt/export/web_page/vendor/three/LightProbeGrid.js",
                 "prt/export/web_page/vendor/three/LICENSE",
                 "prt/export/web_page/vendor/three/VERSION.json", "prt/shaders/three_prt.frag", "prt/shaders/three_prt.vert",
                 "prt/runtime/data/demo/geometry.npz", "prt/runtime/data/envmaps/studio_small_03_256.hdr"):
        assert data in names, data
    assert any(n.startswith("prt/runtime/data/demo/segments/") and n.endswith(".onnx") for n in names)


TRAIN_WITHOUT_EXTRA = """
import importlib.abc, sys
BLOCKED = {blocked!r}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError("No module named " + repr(name), name=name)
sys.meta_path.insert(0, Block())
from prt.train.entry import {entry}
sys.exit({entry}(["mesh.obj", "-o", "out"]))
"""


@pytest.mark.parametrize("blocked", [("torch",), ("torch", "trimesh", "embreex", "scipy")])
@pytest.mark.parametrize("entry", ["train_main", "precompute_main"])
def test_build_commands_without_the_train_extra_say_what_to_install(tmp_path, blocked, entry):
    code = TRAIN_WITHOUT_EXTRA.format(blocked=blocked, entry=entry)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    if entry == "precompute_main" and blocked == ("torch",):  # the precompute needs no torch: it runs (and rejects the mesh)
        assert "prt-runtime[train]" not in out.stderr
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        return
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and 'pip install "prt-runtime[train]"' in lines[0], lines
    assert any(f"module {name!r} is not installed" in lines[0] for name in blocked), lines[0]
    assert not (tmp_path / "out").exists()


# What a runtime-only install (pip install prt-runtime) lacks: the [train] extra and the optional ones.
NOT_IN_RUNTIME = ("torch", "onnx", "trimesh", "embreex", "scipy", "skimage", "matplotlib", "xatlas", "fast_simplification",
                  "pygame", "imageio_ffmpeg", "ray", "mitsuba", "openvino")  # fmt: skip

ENTRY_WITHOUT_EXTRAS = """
import importlib, importlib.abc, sys
BLOCKED = {blocked!r}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError("No module named " + repr(name), name=name)
sys.meta_path.insert(0, Block())
module, function = {target!r}.split(":")
sys.exit(getattr(importlib.import_module(module), function)({argv!r}))
"""


def _console_scripts() -> dict:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def test_every_console_script_is_checked_below():
    assert set(_console_scripts()) == {"prt-precompute", "prt-train", "prt-runtime", "prt-bench", "prt-web"}


@pytest.mark.parametrize("command,argv", [(name, ["--help"]) for name in ("prt-precompute", "prt-train", "prt-runtime", "prt-bench", "prt-web")]
                         + [("prt-bench", ["deform", "--help"])])  # fmt: skip
def test_every_command_on_a_runtime_only_install_helps_or_says_what_to_install(tmp_path, command, argv):
    """Issue 44: with every extra missing, ``COMMAND --help`` prints its help, or one line naming the
    missing module and the ``pip install`` that brings it, and exit status 2; never a traceback."""
    code = ENTRY_WITHOUT_EXTRAS.format(blocked=NOT_IN_RUNTIME, target=_console_scripts()[command], argv=argv)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert "Traceback" not in out.stderr, out.stderr
    if out.returncode == 0:
        assert out.stdout.startswith("usage:") and not out.stderr.strip(), (out.stdout[:200], out.stderr)
        return
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith(f"{command}") and 'pip install "prt-runtime[train]"' in lines[0], lines[0]
    assert any(f"module {name!r} is not installed" in lines[0] for name in NOT_IN_RUNTIME), lines[0]
