"""The layout written down in docs/design.md, checked: layering, no import cycles, module size.

Imports are read from the source (``ast``), including those inside functions (a lazy import
is still a dependency) but not those under ``if TYPE_CHECKING:``.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]  # the repository root is the package ``prt``
SUBPACKAGES = ("train", "export", "runtime", "shaders", "bench")
# What each layer may import from the project (itself included); the pipeline runs one way.
ALLOWED = {
    "shaders": {"shaders"},
    "runtime": {"runtime", "shaders"},
    "export": {"export", "runtime", "shaders"},
    "train": {"train", "export", "runtime", "shaders"},
    "bench": {"bench", "train", "export", "runtime", "shaders"},
}
MAX_LINES = 800


def _modules() -> dict[str, Path]:
    """``prt.x.y`` -> file, for every module of the package (study scripts and tests excluded)."""
    found = {"prt": ROOT / "__init__.py"}
    for sub in SUBPACKAGES:
        for path in sorted((ROOT / sub).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            if not (path.parent / "__init__.py").is_file():  # scripts beside the package (studies)
                continue
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            found[".".join(("prt", *parts))] = path
    return found


MODULES = _modules()


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(name: str, path: Path, modules) -> set[str]:
    """Project modules that module ``name`` imports."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()

    def visit(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                continue
            if isinstance(child, ast.Import):
                found.update(a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[: len(base) - (child.level - 1)]
                    target = ".".join(base + ([child.module] if child.module else []))
                else:
                    target = child.module or ""
                subs = {f"{target}.{a.name}" for a in child.names} & modules.keys()  # `from . import sh`
                found.update(subs)
                if len(subs) < len(child.names):
                    found.add(target)
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8")))
    return {m for m in found if m in modules and m != name}


GRAPH = {name: _imports(name, path, MODULES) for name, path in MODULES.items()}


def _layer(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else None


def test_modules_found():
    for sub in ("train", "export", "runtime", "shaders", "bench"):
        assert f"prt.{sub}" in MODULES
    assert "prt.runtime.renderer" in MODULES


@pytest.mark.parametrize("name", sorted(n for n in MODULES if _layer(n)))
def test_layering(name):
    layer = _layer(name)
    wrong = sorted(m for m in GRAPH[name] if _layer(m) is not None and _layer(m) not in ALLOWED[layer])
    assert not wrong, f"{name} ({layer}/) imports {wrong}: see docs/design.md, Layering"


def test_no_import_cycles():
    """Tarjan's strongly connected components of the import graph: all of size one."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []
    counter = [0]

    def connect(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in GRAPH:
        if v not in index:
            connect(v)
    assert not cycles, f"import cycles: {cycles}"


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_size(name):
    lines = len(MODULES[name].read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_LINES, f"{MODULES[name].relative_to(ROOT)}: {lines} lines (split it by concern)"


def test_runtime_does_not_import_torch():
    for name, path in MODULES.items():
        if _layer(name) in ("runtime", "shaders"):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
            names |= {(n.module or "").split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level}
            assert "torch" not in names, f"{path.relative_to(ROOT)} imports torch"
