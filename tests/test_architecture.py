"""The code's imports follow the package map of docs/architecture.md.

The map is read from the document itself (its "The package map" table: one
row per layer, bottom up; the first column names the packages ``x/`` and the
top-level modules ``x.py`` of that layer), so the document and the code cannot
drift. Every import counts, at the top of a module or inside a function, and
``celld.x.y`` belongs to package ``x``. The rules:

- the map names every package and top-level module of ``celld/``, each once;
- a package imports only those of its own layer or below it;
- no packages import each other, directly or round a longer loop;
- no two files outside ``celld/sim`` import each other, directly or round a
  longer loop;
- nothing outside ``celld/sim`` imports it (``celld/cli.py`` names the
  simulator's commands by their module names, as strings).
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "celld"
ARCHITECTURE = ROOT / "docs" / "architecture.md"
# The simulator: on top, and imported by nothing outside it.
SIM = "sim/"


class Import(NamedTuple):
    """One module a file imports: where (file, line), the statement, and the module."""

    path: str  # the importing file, relative to the repository
    line: int
    text: str  # the import statement as written (unparsed)
    module: str  # the imported module, dotted: celld.config.reader


def read_layers(text: str) -> list[tuple[str, ...]]:
    """The package map's layers, bottom up: the backticked names of each row's first cell."""
    section = text.split("## The package map", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("|")]
    layers = []
    for row in rows[2:]:  # the header and its rule
        first = row.strip("|").split("|")[0]
        names = tuple(re.findall(r"`([^`]+)`", first))
        assert names, f"docs/architecture.md: a row of the package map names nothing: {row!r}"
        layers.append(names)
    return layers


def read_package(root: Path) -> tuple[dict[str, str], dict[str, str]]:
    """Every module of the package: dotted name -> its file (relative to ``root``), and -> its source."""
    files, sources = {}, {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        rel = path.relative_to(root)
        parts = rel.with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        files[name], sources[name] = rel.as_posix(), path.read_text(encoding="utf-8")
    return files, sources


def imports_of(name: str, path: str, source: str, modules: set[str]) -> list[Import]:
    """The package's own modules that one module imports, each with its statement and line."""
    is_package = path.endswith("__init__.py")
    found: list[Import] = []
    for node in ast.walk(ast.parse(source, filename=path)):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the module's own package up
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                origin = ".".join([*base, *([node.module] if node.module else [])])
            else:
                origin = node.module or ""
            # ``from celld import se3`` imports the module celld.se3; ``from celld.x import f`` imports celld.x.
            submodules = [f"{origin}.{alias.name}" for alias in node.names if f"{origin}.{alias.name}" in modules]
            plain = [alias for alias in node.names if f"{origin}.{alias.name}" not in modules]
            targets = submodules + ([origin] if plain else [])
        else:
            continue
        text = ast.unparse(node)
        for target in targets:
            if target == PACKAGE or target.startswith(PACKAGE + "."):
                # ``import celld.a.b`` names the deepest of the package's modules it reaches.
                while target not in modules and "." in target:
                    target = target.rsplit(".", 1)[0]
                found.append(Import(path, node.lineno, text, target))
    return found


def unit_of(module: str, packages: set[str]) -> str:
    """The map's unit of a module: ``x/`` for celld.x.*, ``x.py`` for the top-level module celld.x."""
    parts = module.split(".")
    if len(parts) == 1:
        return "__init__.py"
    return parts[1] + "/" if parts[1] + "/" in packages else parts[1] + ".py"


def strongly_connected(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


class Code(NamedTuple):
    """The package as the checks see it."""

    units: set[str]  # x/ and x.py under celld/, and __init__.py (the package root)
    imports: list[Import]
    unit_of_path: dict[str, str]
    path_of_module: dict[str, str]


def scan(files: Mapping[str, str], sources: Mapping[str, str]) -> Code:
    """``files``: dotted module -> path; ``sources``: dotted module -> source."""
    packages = {m.split(".")[1] + "/" for m, p in files.items() if m.count(".") >= 1 and p.count("/") >= 2}
    modules = set(files)
    imports = [imp for m in sorted(sources) for imp in imports_of(m, files[m], sources[m], modules)]
    units = {unit_of(m, packages) for m in modules}
    return Code(units, imports, {files[m]: unit_of(m, packages) for m in modules}, dict(files))


def _where(imp: Import) -> str:
    return f"{imp.path}:{imp.line}: `{imp.text}`"


def check_map(code: Code, layers: list[tuple[str, ...]]) -> list[str]:
    """The map names every package and top-level module once, and nothing else."""
    named = [n for layer in layers for n in layer]
    problems = [f"the package map names {n} more than once" for n in sorted({n for n in named if named.count(n) > 1})]
    problems += [f"the package map does not name {u} (celld/{u})" for u in sorted(code.units - set(named))]
    problems += [f"the package map names {n}, which celld/ does not have" for n in sorted(set(named) - code.units)]
    return problems


def check_layers(code: Code, layers: list[tuple[str, ...]]) -> list[str]:
    """No import of a package the map puts above the importer."""
    rank = {n: i for i, layer in enumerate(layers) for n in layer}
    problems = []
    for imp in code.imports:
        src, dst = code.unit_of_path[imp.path], code.unit_of_path[code.path_of_module[imp.module]]
        if src in rank and dst in rank and rank[dst] > rank[src]:
            problems.append(f"{_where(imp)}: {src} imports {dst}, which the package map puts above it")
    return problems


def check_sim(code: Code) -> list[str]:
    """Nothing outside the simulator imports it."""
    return [
        f"{_where(imp)}: imports the simulator from outside it"
        for imp in code.imports
        if code.unit_of_path[imp.path] != SIM and code.unit_of_path[code.path_of_module[imp.module]] == SIM
    ]


def check_package_cycles(code: Code) -> list[str]:
    """No packages import each other, directly or round a longer loop."""
    edges: dict[tuple[str, str], Import] = {}
    for imp in code.imports:
        src, dst = code.unit_of_path[imp.path], code.unit_of_path[code.path_of_module[imp.module]]
        if src != dst:
            edges.setdefault((src, dst), imp)
    graph: dict[str, set[str]] = {}
    for src, dst in edges:
        graph.setdefault(src, set()).add(dst)
    problems = []
    for component in strongly_connected(graph):
        inside = sorted((s, d) for s, d in edges if s in component and d in component)
        problems.append(
            f"packages {', '.join(component)} import each other: " + "; ".join(f"{s} -> {d} at {_where(edges[s, d])}" for s, d in inside)
        )
    return problems


def check_file_cycles(code: Code) -> list[str]:
    """No two files outside the simulator import each other, directly or round a longer loop."""
    graph: dict[str, set[str]] = {}
    edges: dict[tuple[str, str], Import] = {}
    for imp in code.imports:
        src, dst = imp.path, code.path_of_module[imp.module]
        if src == dst or SIM in (code.unit_of_path[src], code.unit_of_path[dst]):
            continue
        graph.setdefault(src, set()).add(dst)
        edges.setdefault((src, dst), imp)
    problems = []
    for component in strongly_connected(graph):
        inside = sorted((s, d) for s, d in edges if s in component and d in component)
        problems.append(f"files {', '.join(component)} import each other: " + "; ".join(_where(edges[e]) for e in inside))
    return problems


@pytest.fixture(scope="module")
def layers() -> list[tuple[str, ...]]:
    return read_layers(ARCHITECTURE.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def code() -> Code:
    return scan(*read_package(ROOT))


def test_the_map_names_every_package_and_module_once(code: Code, layers: list[tuple[str, ...]]) -> None:
    problems = check_map(code, layers)
    assert not problems, "\n".join(problems)


def test_a_package_imports_only_its_own_layer_and_those_below(code: Code, layers: list[tuple[str, ...]]) -> None:
    problems = check_layers(code, layers)
    assert not problems, "\n".join(problems)


def test_the_simulator_is_on_top_and_imported_by_nothing_outside_it(code: Code, layers: list[tuple[str, ...]]) -> None:
    assert SIM in layers[-1] or SIM in layers[-2], "the package map puts sim/ on top (below only the CLI root)"
    problems = check_sim(code)
    assert not problems, "\n".join(problems)


def test_no_packages_import_each_other(code: Code) -> None:
    problems = check_package_cycles(code)
    assert not problems, "\n".join(problems)


def test_no_files_outside_the_simulator_import_each_other(code: Code) -> None:
    problems = check_file_cycles(code)
    assert not problems, "\n".join(problems)


# The checks themselves, on a made-up package.
_TOY_FILES = {
    "celld": "celld/__init__.py",
    "celld.errors": "celld/errors.py",
    "celld.low": "celld/low/__init__.py",
    "celld.low.a": "celld/low/a.py",
    "celld.low.b": "celld/low/b.py",
    "celld.high": "celld/high/__init__.py",
    "celld.high.c": "celld/high/c.py",
    "celld.sim": "celld/sim/__init__.py",
    "celld.sim.d": "celld/sim/d.py",
    "celld.sim.e": "celld/sim/e.py",
}
_TOY_LAYERS = [("__init__.py", "errors.py"), ("low/",), ("high/",), ("sim/",)]


def _toy(**sources: str) -> Code:
    full = {m: "" for m in _TOY_FILES}
    full.update({m.replace("__", "."): s for m, s in sources.items()})
    return scan(_TOY_FILES, full)


def test_the_checks_pass_a_package_that_follows_its_map() -> None:
    toy = _toy(
        celld__low__a="from celld import errors\n",
        celld__high__c="from celld.low import a\n",
        celld__sim__d="from celld.high.c import x\nfrom celld.sim import e\n",
        celld__sim__e="from celld.sim.d import y\n",  # a circle inside the simulator is its own business
    )
    assert check_map(toy, _TOY_LAYERS) == []
    assert check_layers(toy, _TOY_LAYERS) == check_sim(toy) == check_package_cycles(toy) == []
    assert check_file_cycles(toy) == []


def test_the_checks_name_the_file_the_line_and_the_import() -> None:
    toy = _toy(celld__low__b="import numpy\n\n\ndef f():\n    from celld.high import c\n")
    assert check_layers(toy, _TOY_LAYERS) == [
        "celld/low/b.py:5: `from celld.high import c`: low/ imports high/, which the package map puts above it"
    ]
    assert check_map(toy, [*_TOY_LAYERS, ("gone.py",)]) == ["the package map names gone.py, which celld/ does not have"]
    assert check_map(toy, _TOY_LAYERS[1:]) == [
        "the package map does not name __init__.py (celld/__init__.py)",
        "the package map does not name errors.py (celld/errors.py)",
    ]


def test_the_checks_find_circles_of_packages_and_of_files() -> None:
    toy = _toy(
        celld__low__a="from celld.low.b import f\n",
        celld__low__b="from celld.high.c import g\n",
        celld__high__c="from .. import errors\nfrom celld.low import a\nimport celld.sim.d\n",
    )
    assert check_package_cycles(toy) == [
        "packages high/, low/ import each other: high/ -> low/ at celld/high/c.py:2: `from celld.low import a`; "
        "low/ -> high/ at celld/low/b.py:1: `from celld.high.c import g`"
    ]
    circle = "celld/high/c.py, celld/low/a.py, celld/low/b.py"
    assert check_file_cycles(toy) == [
        f"files {circle} import each other: celld/high/c.py:2: `from celld.low import a`; "
        "celld/low/a.py:1: `from celld.low.b import f`; celld/low/b.py:1: `from celld.high.c import g`"
    ]
    assert check_sim(toy) == ["celld/high/c.py:3: `import celld.sim.d`: imports the simulator from outside it"]
