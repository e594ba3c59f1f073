"""The package's layering, read from the source: the ground floor (svelive/core) imports nothing of the project
outside itself, and no module imports, through any chain of imports (function-level ones included), itself."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("svelive", "service", "replay")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for package in PACKAGES for p in (ROOT / package).rglob("*.py")}


def _imports(path: Path, name: str, known: set[str]) -> set[str]:
    """The project's modules ``path`` imports anywhere in it (``from a import b`` counts module a.b where it is
    one, else a); TYPE_CHECKING-only imports are not imports at run time and are left out."""
    tree = ast.parse(path.read_text(), str(path))
    checking: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            checking.update(id(n) for child in node.body for n in ast.walk(child))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if id(node) in checking:
            continue
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:  # a name inside a module: the module
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(path, name, known) for name, path in modules.items()}


def test_the_ground_floor_imports_nothing_of_the_project_above_it():
    graph = _graph()
    core = {name for name in graph if name == "svelive.core" or name.startswith("svelive.core.")}
    assert len(core) >= 9
    leaks = {name: sorted(graph[name] - core - {"svelive"}) for name in sorted(core) if graph[name] - core - {"svelive"}}
    assert not leaks


def test_no_module_imports_itself_through_a_chain():
    graph = _graph()
    # Tarjan's strongly connected components; a component of two or more modules is a cycle
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in graph:
                continue
            if w not in index:
                visit(w)
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles


def test_the_import_graph_sees_imports_inside_functions(tmp_path):
    """The checks above would pass vacuously if function-level imports were missed."""
    graph = _graph()
    assert "svelive.core.camera" in graph["svelive.reconstruction.input"]
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from svelive.core.camera import Camera\n    return Camera\n")
    assert _imports(module, "m", set(graph)) == {"svelive.core.camera"}


def test_every_package_is_reachable_by_its_dotted_name():
    """A package's attribute must not shadow a subpackage: ``svelive.reconstruction`` exported the function
    ``methods``, so ``import svelive.reconstruction.methods.adaptive as x`` found the function, not the package."""
    import svelive
    import svelive.reconstruction.methods.adaptive as adaptive

    assert adaptive.__name__ == "svelive.reconstruction.methods.adaptive"
    assert callable(svelive.methods) and svelive.methods()[0] == "adaptive"
    for name in sorted(_modules()):
        parent, _, child = name.rpartition(".")
        if parent:
            module = __import__(name, fromlist=["_"])
            assert getattr(__import__(parent, fromlist=["_"]), child) is module, name
