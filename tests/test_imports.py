"""The package's import graph, read from the source with ``ast``: no cycles, and the layers import downwards only.

Every import counts, at module level or inside a function (a lazy import still ties the two modules together);
only imports under ``if TYPE_CHECKING:`` do not, since they never run.
"""

from __future__ import annotations

import ast
import textwrap
from collections.abc import Iterable, Iterator
from pathlib import Path

import pytest

import seqtrojan

PACKAGE_ROOT = Path(seqtrojan.__file__).parent

BOTTOM = ("seqtrojan.serde", "seqtrojan.errors")
"""Modules that import no other seqtrojan module."""

ABOVE_ENV = (
    "seqtrojan.agent",
    "seqtrojan.train",
    "seqtrojan.analysis",
    "seqtrojan.defense",
    "seqtrojan.report",
    "seqtrojan.experiments",
    "seqtrojan.zoo",
    "seqtrojan.jobs",
    "seqtrojan.cli",
    "seqtrojan.config",  # the experiment's config; the env reads its own through seqtrojan.serde
)
"""What seqtrojan.env must not import."""


def find_modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> source file, for every module of the package in folder ``root``."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(nodes: Iterable[ast.AST]) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement in ``nodes`` (in functions and classes too), skipping ``if TYPE_CHECKING:``."""
    for node in nodes:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            yield from _import_nodes(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        yield from _import_nodes(ast.iter_child_nodes(node))


def module_imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that module ``name`` (source file ``path``) imports, other than itself.

    ``from pkg import sub`` is an import of the submodule ``pkg.sub`` where one exists, else of ``pkg``;
    ``import a.b.c`` and ``from a.b.c import f`` are imports of the deepest of ``a.b.c``, ``a.b``, ``a`` that is a
    module of the package. (Importing a submodule runs its parent packages' ``__init__`` too; that implicit step
    is not an edge, or every package importing its own submodules would be a cycle.)
    """
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets: set[str] = set()
    for node in _import_nodes([ast.parse(path.read_text(), filename=str(path))]):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
            continue
        if node.level:
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - (node.level - 1)])
            source = f"{base}.{node.module}" if node.module else base
        else:
            source = node.module or ""
        for alias in node.names:
            targets.add(f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source)
    found = set()
    for target in targets:
        while target and target not in modules:
            target = target.rpartition(".")[0]
        if target and target != name:
            found.add(target)
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    modules = find_modules(root)
    return {name: module_imports(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as ``[a, b, ..., a]``, or None when it has none (depth-first, in name order)."""
    done: set[str] = set()  # nodes from which no cycle is reachable
    for start in sorted(graph):
        if start in done:
            continue
        path = [start]
        branches = [iter(sorted(graph[start]))]
        while path:
            nxt = next(branches[-1], None)
            if nxt is None:
                done.add(path.pop())
                branches.pop()
            elif nxt in path:
                return [*path[path.index(nxt) :], nxt]
            elif nxt not in done and nxt in graph:
                path.append(nxt)
                branches.append(iter(sorted(graph[nxt])))
    return None


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The graph between seqtrojan's subpackages and top-level modules (seqtrojan.env.core -> seqtrojan.env)."""

    def unit(module: str) -> str:
        return ".".join(module.split(".")[:2])

    units: dict[str, set[str]] = {}
    for module, targets in graph.items():
        units.setdefault(unit(module), set()).update(unit(t) for t in targets if unit(t) != unit(module))
    return units


def _layer(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(PACKAGE_ROOT)


def test_no_import_cycles(graph):
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_cycles_between_subpackages(graph):
    cycle = find_cycle(package_graph(graph))
    assert cycle is None, "subpackage import cycle: " + " -> ".join(cycle or [])


@pytest.mark.parametrize("module", BOTTOM)
def test_bottom_layer_imports_no_seqtrojan_module(graph, module):
    allowed = {"seqtrojan.errors"} if module != "seqtrojan.errors" else set()
    assert graph[module] <= allowed, f"{module} imports {sorted(graph[module] - allowed)}"


def test_env_imports_no_upper_layer(graph):
    bad = sorted(
        f"{module} -> {target}"
        for module, targets in graph.items()
        if _layer(module, ("seqtrojan.env",))
        for target in targets
        if _layer(target, ABOVE_ENV)
    )
    assert not bad, "seqtrojan.env imports upper layers: " + ", ".join(bad)


def test_graph_reads_the_real_package(graph):
    """The graph sees this package's known imports, module-level and lazy, so that the tests above can fail."""
    assert "seqtrojan.serde" in graph["seqtrojan.config"]
    assert "seqtrojan.env.config" in graph["seqtrojan.config"]
    assert "seqtrojan.env.rng" in graph["seqtrojan.env.core"]  # from seqtrojan.env import rng: the submodule
    assert "seqtrojan.env" not in graph["seqtrojan.env.core"]
    assert len(graph) > 50


def _write_package(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return root / "pkg"


def test_graph_counts_lazy_and_relative_imports_but_not_type_checking(tmp_path):
    pkg = _write_package(
        tmp_path,
        {
            "pkg/__init__.py": "from pkg.a import f\n",
            "pkg/a.py": """
                from typing import TYPE_CHECKING
                import typing
                if TYPE_CHECKING:
                    from pkg.b import g
                else:
                    import pkg.sub.d
                if typing.TYPE_CHECKING:
                    import pkg.c
                def f():
                    from .b import g
                    return g
            """,
            "pkg/b.py": "import os\nfrom pkg.sub import d\n",
            "pkg/c.py": "",
            "pkg/sub/__init__.py": "",
            "pkg/sub/d.py": "from .. import c\nfrom ..b import nothing_here\nfrom . import e\nimport pkg.sub.e.thing\n",
            "pkg/sub/e.py": "",
        },
    )
    graph = import_graph(pkg)
    assert graph == {
        "pkg": {"pkg.a"},
        "pkg.a": {"pkg.b", "pkg.sub.d"},
        "pkg.b": {"pkg.sub.d"},
        "pkg.c": set(),
        "pkg.sub": set(),
        "pkg.sub.d": {"pkg.c", "pkg.b", "pkg.sub.e"},
        "pkg.sub.e": set(),
    }
    assert find_cycle(graph) == ["pkg.b", "pkg.sub.d", "pkg.b"]
    assert package_graph(graph) == {"pkg.a": {"pkg.b", "pkg.sub"}, "pkg.b": {"pkg.sub"}, "pkg.c": set(),
                                    "pkg.sub": {"pkg.b", "pkg.c"}, "pkg": {"pkg.a"}}  # fmt: skip


def test_find_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None  # a diamond is no cycle
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"b"}}) == ["b", "c", "b"]
    assert find_cycle({"a": set(), "z": {"z2"}, "z2": {"z"}}) == ["z", "z2", "z"]
