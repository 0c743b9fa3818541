"""The import graph of eventcap/ and plugins/, read from the source (AST, imports inside functions included): no
import cycle; the folders are the layers, and imports point down only.

    python tests/test_layers.py     # prints the cycles and every breach (what the tests check)

Layers (docs/architecture.md), from the top: ``eventcap/apps`` (what a user runs), ``eventcap/core`` (the
framework) and the domain library (every other package and module of ``eventcap/``, the typed artifacts among them).
The library raises its own errors (``eventcap.errors``) and never reaches up into the framework or the apps; the
runner translates its errors. The core never imports an app. Inside the library, its packages and top-level modules
stand in one order: no two of them import each other, however indirectly (:func:`package_cycles`), so each stands
above all it imports (``python tests/test_layers.py`` prints that order).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: the folders of eventcap/ that are not the domain library, by layer
LAYER_OF_PACKAGE = {"apps": "apps", "core": "core"}
#: which layers each layer may import (besides itself)
MAY_IMPORT = {"library": {"library"}, "core": {"core", "library"}, "apps": {"apps", "core", "library"}}
#: at most this many modules directly in eventcap/ (the rest sit in the folders of their layer)
MAX_TOP_MODULES = 12
#: known breaches being removed: (module, imported) pairs. An entry that no longer occurs fails the test, so the
#: list only ever shrinks (it is empty).
PENDING: set[tuple[str, str]] = set()


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for eventcap/ and the plugin packages under plugins/."""
    out = {}
    for base, strip in ((root / "eventcap", root), (root / "plugins", root / "plugins")):
        for p in sorted(base.rglob("*.py")):
            parts = list(p.relative_to(strip).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def import_graph(mods: dict[str, Path]) -> dict[str, dict[str, int]]:
    """module -> {imported project module: line of the first import}, every import statement of the file counted
    (module level, inside functions, under ``if TYPE_CHECKING``). ``from pkg import name`` counts ``pkg`` and, when
    ``name`` is a submodule, ``pkg.name``; a module's own parent packages are left out (Python has loaded them)."""
    graph = {}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        edges: dict[str, int] = {}
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    pkg = mod if is_pkg else mod.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        pkg = pkg.rpartition(".")[0]
                    base = f"{pkg}.{node.module}" if node.module else pkg
                else:
                    base = node.module
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for name in names:
                parts = name.split(".")
                for i in range(1, len(parts) + 1):
                    target = ".".join(parts[:i])
                    if target in mods and target != mod and not mod.startswith(target + "."):
                        edges.setdefault(target, node.lineno)
        graph[mod] = edges
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def layer(mod: str) -> str:
    """'apps', 'core', 'library' or 'plugin' for a project module: its folder says it."""
    parts = mod.split(".")
    if parts[0] != "eventcap":
        return "plugin"
    if len(parts) == 1:
        return "library"  # the package itself (empty)
    return LAYER_OF_PACKAGE.get(parts[1], "library")


def breaches(graph: dict[str, dict[str, int]]) -> list[tuple[str, str, int]]:
    """(module, imported, line) of every eventcap module importing a layer above its own, or a plugin."""
    out = []
    for mod, edges in graph.items():
        own = layer(mod)
        if own == "plugin":
            continue
        for target, line in edges.items():
            if layer(target) not in MAY_IMPORT[own]:
                out.append((mod, target, line))
    return sorted(out)


def unit(mod: str) -> str:
    """The package (``eventcap.body``) or top-level module (``eventcap.camera``) of eventcap/ a module belongs to;
    a plugin's module: its plugin package."""
    parts = mod.split(".")
    return ".".join(parts[:2]) if parts[0] == "eventcap" else parts[0]


def unit_graph(graph: dict[str, dict[str, int]]) -> dict[str, dict[str, list[tuple[str, str]]]]:
    """unit -> {imported unit: [(module, imported module), ...]} between different units of eventcap/."""
    out: dict[str, dict[str, list[tuple[str, str]]]] = {}
    for mod, edges in graph.items():
        if not mod.startswith("eventcap"):
            continue
        for target in edges:
            a, b = unit(mod), unit(target)
            if a != b and a != "eventcap" and b != "eventcap":
                out.setdefault(a, {}).setdefault(b, []).append((mod, target))
    return out


def package_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The cycles between eventcap's packages and top-level modules (each a sorted list of units)."""
    return cycles({a: dict.fromkeys(bs, 1) for a, bs in unit_graph(graph).items()})


def unit_order(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The units of eventcap/ by floor, from the ground: each stands one floor above the highest unit it imports
    (only defined without package cycles)."""
    ug = unit_graph(graph)
    names = {unit(m) for m in graph if m.startswith("eventcap.")}
    floor: dict[str, int] = {}

    def height(u: str, seen: tuple[str, ...] = ()) -> int:
        if u not in floor:
            floor[u] = 1 + max((height(v, seen + (u,)) for v in ug.get(u, {}) if v not in seen), default=-1)
        return floor[u]

    for u in names:
        height(u)
    return [sorted(u for u in names if floor[u] == f) for f in range(max(floor.values()) + 1)]


def _where(mods, mod: str, line: int) -> str:
    return f"{mods[mod].relative_to(ROOT)}:{line}"


MODS = modules()
GRAPH = import_graph(MODS)


def test_the_graph_sees_imports_inside_functions_and_relative_ones():
    # eventcap/apps/outputs.py imports the viewer only inside a function; eventcap/core/runner.py has `from .cache import`
    assert "eventcap.apps.viewer" in GRAPH["eventcap.apps.outputs"]
    assert "eventcap.core.cache" in GRAPH["eventcap.core.runner"]
    assert "eventcap.body.skeleton" in GRAPH["eventcap.body.template"]  # absolute submodule import
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1}, "d": {"a": 1}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b": 1}, "b": {}}) == []


def test_no_import_cycle():
    found = cycles(GRAPH)
    lines = []
    for comp in found:
        lines += [f"{a} -> {b} ({_where(MODS, a, GRAPH[a][b])})" for a in comp for b in GRAPH[a] if b in comp]
    assert not found, "import cycles (counting imports inside functions):\n" + "\n".join(lines)


def test_the_folders_show_the_layers():
    top = sorted(p.stem for p in (ROOT / "eventcap").glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, (f"{len(top)} modules directly in eventcap/ (at most {MAX_TOP_MODULES}): "
                                         f"{top}; put each in the folder of its layer")
    assert layer("eventcap.core.runner") == "core" and layer("eventcap.apps.cli") == "apps"
    assert layer("eventcap.energy.factor") == "library" and layer("eventcap_spline.solve") == "plugin"


def test_the_packages_stand_in_one_order():
    found = package_cycles(GRAPH)
    ug = unit_graph(GRAPH)
    lines = []
    for comp in found:
        for a in comp:
            for b in comp:
                for m, t in ug.get(a, {}).get(b, [])[:3]:
                    lines.append(f"{a} -> {b}: {m} imports {t} ({_where(MODS, m, GRAPH[m][t])})")
    assert not found, ("packages (and top-level modules) of eventcap/ that import each other, however indirectly; "
                       "move what both need below them:\n" + "\n".join(lines))


def test_package_cycles_are_found():
    # the breach fixed by moving the artifact contract down: body.template -> artifact base, artifacts -> body
    graph = {"eventcap.body.template": {"eventcap.artifacts.base": 1}, "eventcap.artifacts.base": {},
             "eventcap.artifacts.recording": {"eventcap.body.template": 1}, "eventcap.camera": {}}
    assert package_cycles(graph) == [["eventcap.artifacts", "eventcap.body"]]
    graph["eventcap.body.template"] = {"eventcap.artifact": 1}
    graph["eventcap.artifact"] = {}
    assert package_cycles(graph) == []
    assert unit_order(graph) == [["eventcap.artifact", "eventcap.camera"], ["eventcap.body"], ["eventcap.artifacts"]]


def test_library_imports_nothing_of_the_orchestration():
    found = breaches(GRAPH)
    new = [f"{m} imports {t} ({_where(MODS, m, line)})" for m, t, line in found if (m, t) not in PENDING]
    assert not new, ("imports point down only (apps -> core -> artifacts, library), never to a plugin, not even inside "
                     "a function (the library raises an eventcap.errors.ComputationFailed subclass of its own; the "
                     "runner translates it):\n"
                     + "\n".join(new))
    gone = sorted(PENDING - {(m, t) for m, t, _ in found})
    assert not gone, f"fixed, remove from PENDING in tests/test_layers.py: {gone}"


def test_core_imports_no_plugin_and_plugins_not_each_other():
    bad = []
    for mod, edges in GRAPH.items():
        for target, line in edges.items():
            if layer(target) != "plugin":
                continue
            if layer(mod) != "plugin" or target.split(".")[0] != mod.split(".")[0]:
                bad.append(f"{mod} imports {target} ({_where(MODS, mod, line)})")
    assert not bad, "plugins are found through entry points only:\n" + "\n".join(bad)


@pytest.mark.parametrize("mod", ["eventcap.io.convert", "eventcap.analysis.motion"])
def test_former_breaches_stay_fixed(mod):
    # io.convert imported the cache (for pid_alive), motion the stage (for StageFailed)
    assert not [t for t in GRAPH[mod] if layer(t) in ("core", "apps")]


if __name__ == "__main__":
    comps = cycles(GRAPH)
    print(f"{len(MODS)} modules, {sum(map(len, GRAPH.values()))} import edges (imports inside functions counted)")
    print(f"import cycles: {len(comps)}")
    for comp in comps:
        for a in comp:
            for b in sorted(GRAPH[a]):
                if b in comp:
                    print(f"  {a} -> {b}  ({_where(MODS, a, GRAPH[a][b])})")
    pcs = package_cycles(GRAPH)
    print(f"cycles between the packages of eventcap/: {len(pcs)}")
    for comp in pcs:
        for a in comp:
            for b in comp:
                for m, t in unit_graph(GRAPH).get(a, {}).get(b, []):
                    print(f"  {a} -> {b}: {m} -> {t}  ({_where(MODS, m, GRAPH[m][t])})")
    if not pcs:
        print("the packages of eventcap/ by floor, from the ground:")
        for i, names in enumerate(unit_order(GRAPH), 1):
            print(f"  {i:2d}  {' '.join(n.removeprefix('eventcap.') for n in names)}")
    found = breaches(GRAPH)
    print(f"modules importing a layer above their own: {len(found)}")
    for m, t, line in found:
        print(f"  {m} -> {t}  ({_where(MODS, m, line)}){'  [pending]' if (m, t) in PENDING else ''}")
    sys.exit(1 if comps or pcs or any((m, t) not in PENDING for m, t, _ in found) else 0)
