"""The layout's import rules, read from the source with ``ast`` (nothing is imported).

- ``rasterizer`` imports neither ``service`` nor ``export`` nor ``bench``;
- ``export`` imports neither ``service`` nor ``bench``;
- ``service`` imports ``export`` only lazily (inside a function) and ``bench`` never;
- nothing imports ``bench`` but the tests (it has its own entry point, ``omnisplat-bench``);
- module-level imports form no cycle;
- no module outside ``rasterizer.splat`` / ``rasterizer.composite`` uses their ``_`` names,
  and no product module (bench included) imports or reads another module's ``_`` name;
- no product module is longer than 600 lines.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("rasterizer", "export", "service", "bench")


@dataclass(frozen=True)
class Edge:
    source: str  # importing module, dotted
    target: str  # imported module, dotted (resolved, may be a package)
    names: tuple[str, ...]  # names taken with ``from target import ...``
    top_level: bool  # at module level (not inside a function)
    line: int


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def edges(path: Path) -> list[Edge]:
    """Every import of one file, with whether it runs at import time."""
    return edges_of(path, module_name(path))


def edges_of(path: Path, module: str) -> list[Edge]:
    """:func:`edges` of a file read as the dotted module ``module``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[Edge] = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = top and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                out.extend(Edge(module, a.name, (), top, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                target = _resolve(module, path.name == "__init__.py", child)
                names = tuple(a.name for a in child.names)
                out.append(Edge(module, target, names, top, child.lineno))
                # ``from pkg import sub`` imports the submodule pkg.sub
                for name in names:
                    if (ROOT / Path(*target.split("."), f"{name}.py")).exists() or \
                            (ROOT / Path(*target.split("."), name, "__init__.py")).exists():
                        out.append(Edge(module, f"{target}.{name}", (), top, child.lineno))
            visit(child, inner)

    visit(tree, True)
    return out


def _files(*packages: str) -> list[Path]:
    return sorted(p for pkg in packages for p in (ROOT / pkg).rglob("*.py"))


ALL = {module_name(p): edges(p) for p in _files(*PACKAGES)}
TESTS = {module_name(p): edges(p) for p in _files("tests")}
MODULES = set(ALL) | set(TESTS)


def _pkg(name: str) -> str:
    return name.split(".")[0]


def test_the_packages_exist_and_are_parsed():
    assert {_pkg(m) for m in ALL} == set(PACKAGES)
    assert sum(len(e) for e in ALL.values()) > 100  # the rules below see real imports


@pytest.mark.parametrize("package, forbidden, lazy_ok", [
    ("rasterizer", ("service", "export", "bench"), False),
    ("export", ("service", "bench"), False),
    ("service", ("export",), True),
    ("service", ("bench",), False),  # not even lazily: bench has its own entry point
])
def test_imports_run_one_way(package, forbidden, lazy_ok):
    bad = [f"{m}:{e.line} imports {e.target}" for m, es in ALL.items() if _pkg(m) == package
           for e in es if _pkg(e.target) in forbidden and (e.top_level or not lazy_ok)]
    assert not bad, bad


def test_nothing_imports_bench():
    users = {m for m, es in ALL.items() if _pkg(m) != "bench" for e in es if _pkg(e.target) == "bench"}
    assert not users, users


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            strong(v)
    return found


def _graph(top_level_only: bool) -> dict[str, set[str]]:
    return {m: {e.target for e in es if e.target in ALL and e.target != m and (e.top_level or not top_level_only)
                # a package's __init__ re-exporting its own submodules is not a cycle of the design
                and not (m == _parent(e.target))}
            for m, es in ALL.items()}


def _parent(name: str) -> str:
    return name.rpartition(".")[0]


def test_no_import_cycles():
    assert not _cycles(_graph(top_level_only=True))


def test_no_cycles_among_service_modules_even_lazily():
    graph = {m: {t for t in ts if _pkg(t) == "service"} for m, ts in _graph(top_level_only=False).items()
             if _pkg(m) == "service"}
    assert not _cycles(graph)


def test_the_cycle_check_can_fail():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _module_aliases(module: str, path: Path) -> dict[str, str]:
    """Local name -> dotted module of this repo, for every ``import x.y as z`` / ``from x import mod``."""
    tree = ast.parse(path.read_text())
    out: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.asname:
                    out[a.asname] = a.name
                else:
                    out[a.name.split(".")[0]] = a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(module, path.name == "__init__.py", node)
            for a in node.names:
                out[a.asname or a.name] = f"{target}.{a.name}"
    return {k: v for k, v in out.items() if v in MODULES}


def _dotted(node: ast.AST) -> str | None:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([node.id, *reversed(parts)])


def _private_uses(modules: dict[str, list[Edge]], paths: dict[str, Path], owners: tuple[str, ...] | None):
    """``from X import _name`` and ``X._name`` where X is another module of this repo (of ``owners`` if given)."""
    bad = []
    for m, es in modules.items():
        for e in es:
            if e.target == m or e.target not in MODULES or (owners and e.target not in owners):
                continue
            bad += [f"{m}:{e.line} {e.target}.{n}" for n in e.names if n.startswith("_") and not n.startswith("__")]
        aliases = _module_aliases(m, paths[m])
        for node in ast.walk(ast.parse(paths[m].read_text())):
            if not (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")):
                continue
            name = _dotted(node.value)
            if name is None:
                continue
            head, _, rest = name.partition(".")
            target = aliases.get(head)
            if target is None:
                continue
            target = f"{target}.{rest}" if rest else target
            if target in MODULES and target != m and (not owners or target in owners):
                bad.append(f"{m}:{node.lineno} {target}.{node.attr}")
    return bad


PATHS = {module_name(p): p for p in _files(*PACKAGES, "tests")}


def test_splat_and_composite_privates_stay_inside():
    owners = ("rasterizer.splat", "rasterizer.composite")
    everyone = {**{m: es for m, es in ALL.items() if m not in owners}, **TESTS}
    assert not _private_uses(everyone, PATHS, owners)


def test_no_module_uses_another_modules_private_names():
    """rasterizer, export, service and bench: no ``from x import _y`` and no ``x._y`` of another module."""
    assert not _private_uses(ALL, PATHS, None)


def test_the_private_name_check_can_fail(tmp_path):
    src = tmp_path / "user.py"
    src.write_text("from rasterizer import geometry as geo\nfrom rasterizer.gaussians import _x\ngeo._y\n")
    found = _private_uses({"rasterizer.user": edges_of(src, "rasterizer.user")}, {"rasterizer.user": src}, None)
    assert found == ["rasterizer.user:2 rasterizer.gaussians._x", "rasterizer.user:3 rasterizer.geometry._y"]


def test_no_test_module_imports_another_test_module():
    """Shared test helpers live in conftest.py fixtures or helper modules (tests/*/_support.py)."""
    bad = [f"{m}:{e.line} imports {e.target}" for m, es in TESTS.items() for e in es
           if e.target.startswith("tests.") and e.target.rpartition(".")[2].startswith("test_")]
    assert not bad, bad


def test_dev_data_is_reached_only_through_the_conftest_fixtures():
    """A test that builds its own ``../shared/data`` path would fail (not skip) on a fresh clone."""
    import re

    pattern = re.compile(r"""["'](\.\./)?shared["'/]""")
    bad = [str(p.relative_to(ROOT)) for p in _files("tests") if p.name != "conftest.py" and pattern.search(p.read_text())]
    assert not bad, bad


#: Longest module (lines) in the product packages.
MAX_LINES = 600

def test_no_module_over_600_lines():
    long = {str(p.relative_to(ROOT)): n for p in _files(*PACKAGES)
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long

