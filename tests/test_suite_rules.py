"""Rules of the test suite itself, checked on the source:

- every registered stage (the ``eventcap.stages`` entry points of pyproject.toml) has a ``StageConformance`` test
  class that pytest collects;
- tests import no other test module, not ``conftest`` and no benchmark script: shared scenes live in
  ``tests/helpers`` (a package, imported as ``helpers``; its modules import each other relatively, so that a benchmark
  can import them as ``tests.helpers``), and no test puts a folder on ``sys.path`` to import from it;
- no test asserts on the wall clock (speed is measured by the benchmark scripts, not asserted in tests).

Each rule is a function over source text with a test of its own on made-up sources (it finds what it should, and
nothing else), then a test over the repository.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

from helpers.paths import ROOT, TESTS

#: the test sources: test modules, conftest, support modules and helpers (not the third-party example package)
SOURCES = sorted(p for p in TESTS.rglob("*.py") if "fixtures" not in p.relative_to(TESTS).parts)
BENCHMARKS = sorted({p.stem for p in (ROOT / "benchmarks").rglob("*.py")})
CLOCKS = {"perf_counter", "perf_counter_ns", "time", "time_ns", "monotonic", "monotonic_ns", "process_time"}


# ---------------------------------------------------------------------------------------------------------------------
# every registered stage has a conformance test
# ---------------------------------------------------------------------------------------------------------------------
def registered_stages(pyproject: Path = ROOT / "pyproject.toml") -> list[str]:
    """The names of the ``eventcap.stages`` entry points."""
    doc = tomllib.loads(pyproject.read_text(encoding="utf-8"))
    return sorted(doc["project"]["entry-points"]["eventcap.stages"])


def conformance_classes(source: str) -> dict[str, str]:
    """{class name: stage_name} of the module-level classes named Test* that derive from ``StageConformance``
    (directly or through a class of the same module) and set ``stage_name``."""
    tree = ast.parse(source)
    classes = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}

    def derives(cls: ast.ClassDef, seen: frozenset = frozenset()) -> bool:
        for b in cls.bases:
            name = b.id if isinstance(b, ast.Name) else b.attr if isinstance(b, ast.Attribute) else None
            if name == "StageConformance":
                return True
            if name in classes and name not in seen and derives(classes[name], seen | {name}):
                return True
        return False

    def stage_name(cls: ast.ClassDef) -> str | None:
        for stmt in cls.body:
            targets = stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target] if isinstance(stmt, ast.AnnAssign) \
                else []
            if any(isinstance(t, ast.Name) and t.id == "stage_name" for t in targets) and \
                    isinstance(stmt.value, ast.Constant) and isinstance(stmt.value.value, str):
                return stmt.value.value
        return None

    return {name: stage_name(c) for name, c in classes.items()
            if name.startswith("Test") and derives(c) and stage_name(c)}


def test_the_conformance_finder_follows_base_classes_and_skips_what_pytest_does_not_collect():
    source = '''
from eventcap.core.testing import StageConformance
import eventcap.core.testing as t
class _Base(StageConformance):
    def make_inputs(self): return {}
class TestA(_Base):
    stage_name = "a"
class TestB(t.StageConformance):
    stage_name: str = "b"
class Helper(StageConformance):
    stage_name = "not_collected"
class TestNoName(StageConformance):
    pass
class TestUnrelated:
    stage_name = "c"
def test_x():
    class TestInner(StageConformance):
        stage_name = "inner"
'''
    assert conformance_classes(source) == {"TestA": "a", "TestB": "b"}


def test_every_registered_stage_has_a_conformance_test():
    stages = registered_stages()
    assert len(stages) >= 26 and {"spline", "stitch", "cut", "confidence", "smpl"} <= set(stages)
    tested: dict[str, list[str]] = {}
    for path in SOURCES:
        for cls, stage in conformance_classes(path.read_text(encoding="utf-8")).items():
            tested.setdefault(stage, []).append(f"{path.relative_to(TESTS)}::{cls}")
    missing = [s for s in stages if s not in tested]
    assert not missing, (f"registered stages without a StageConformance test class (subclass "
                         f"eventcap.core.testing.StageConformance, set stage_name): {missing}")


# ---------------------------------------------------------------------------------------------------------------------
# tests import no test module and no benchmark
# ---------------------------------------------------------------------------------------------------------------------
def import_offences(source: str, benchmarks=BENCHMARKS, helper: bool = False) -> list[str]:
    """What a test source imports that it should not, as 'line N: what': a test module (``test_*``), ``conftest``,
    a benchmark script (by its file name, or through ``benchmarks``), ``tests.*`` (use ``helpers``), a folder put on
    ``sys.path``; in a module of tests/helpers (``helper``) also an absolute ``helpers`` import."""
    out = []

    def check(module: str, line: int) -> None:
        top = module.split(".")[0]
        if top.startswith("test_") or top == "conftest":
            out.append(f"line {line}: imports the test module {module!r}")
        elif top in benchmarks or top == "benchmarks":
            out.append(f"line {line}: imports the benchmark {module!r}")
        elif top == "tests":
            out.append(f"line {line}: imports {module!r}: write helpers.<module>")
        elif helper and top == "helpers":
            out.append(f"line {line}: imports {module!r} absolutely: write from .<module> import ...")

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                check(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            check(node.module, node.lineno)
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
            if name in ("__import__", "import_module") and node.args and isinstance(node.args[0], ast.Constant) \
                    and isinstance(node.args[0].value, str):
                check(node.args[0].value, node.lineno)
            elif name in ("insert", "append") and isinstance(f, ast.Attribute) and ast.unparse(f.value) == "sys.path":
                out.append(f"line {node.lineno}: puts a folder on sys.path ({ast.unparse(node)})")
    return sorted(out, key=lambda s: int(s.split()[1].rstrip(":")))


def test_the_import_rule_finds_test_modules_benchmarks_and_path_hacks_only():
    source = '''
import numpy as np
from eventcap.io import read_recording
from helpers.poses import posed_recording
from helpers import edi_scenes as scenes
import test_detect
from test_spline import scene
from conftest import TESTS
import bench_edi
from benchmarks.robustness import kill_resume
import sys
sys.path.insert(0, "benchmarks/accuracy")
def f():
    import test_refine as tr
    m = __import__("test_solve")
    n = __import__("toy_stages")
    from tests.helpers.poses import detect
'''
    assert import_offences(source, benchmarks=["bench_edi", "kill_resume"]) == [
        "line 6: imports the test module 'test_detect'",
        "line 7: imports the test module 'test_spline'",
        "line 8: imports the test module 'conftest'",
        "line 9: imports the benchmark 'bench_edi'",
        "line 10: imports the benchmark 'benchmarks.robustness'",
        "line 12: puts a folder on sys.path (sys.path.insert(0, 'benchmarks/accuracy'))",
        "line 14: imports the test module 'test_refine'",
        "line 15: imports the test module 'test_solve'",
        "line 17: imports 'tests.helpers.poses': write helpers.<module>",
    ]
    assert import_offences("from helpers.poses import detect\nfrom .poses import detect\n", helper=True) == [
        "line 1: imports 'helpers.poses' absolutely: write from .<module> import ..."]


def test_tests_import_no_test_module_and_no_benchmark():
    assert {"bench_edi", "bench_tracking", "fuzz_readers", "kill_resume"} <= set(BENCHMARKS)
    found = {}
    for path in SOURCES:
        rel = path.relative_to(TESTS)
        offences = import_offences(path.read_text(encoding="utf-8"), helper=rel.parts[0] == "helpers")
        if offences:
            found[str(rel)] = offences
    assert not found, f"shared code belongs in tests/helpers: {found}"


# ---------------------------------------------------------------------------------------------------------------------
# no test asserts on the wall clock
# ---------------------------------------------------------------------------------------------------------------------
def clock_asserts(source: str) -> list[int]:
    """Lines of the ``assert`` statements that read the clock (``time.perf_counter()``, ``time.time()``,
    ``time.monotonic()``, ...) or a name assigned from it (``t0``, ``elapsed = now - t0``, followed through
    assignments). A loop that waits with a deadline and fails with its own error is not an assert on the clock."""
    tree = ast.parse(source)

    def reads_clock(node: ast.AST, timed: set[str]) -> bool:
        for n in ast.walk(node):
            if isinstance(n, ast.Call):
                f = n.func
                if isinstance(f, ast.Attribute) and f.attr in CLOCKS and ast.unparse(f.value) == "time":
                    return True
                if isinstance(f, ast.Name) and f.id in CLOCKS - {"time"}:
                    return True
            if isinstance(n, ast.Name) and n.id in timed:
                return True
        return False

    timed: set[str] = set()
    for _ in range(3):  # names assigned from names assigned from the clock
        for n in ast.walk(tree):
            if isinstance(n, (ast.Assign, ast.AugAssign, ast.AnnAssign)) and n.value is not None \
                    and reads_clock(n.value, timed):
                targets = n.targets if isinstance(n, ast.Assign) else [n.target]
                timed |= {t.id for tgt in targets for t in ast.walk(tgt) if isinstance(t, ast.Name)}
    return sorted(n.lineno for n in ast.walk(tree) if isinstance(n, ast.Assert) and reads_clock(n.test, timed))


def test_the_clock_rule_finds_asserts_on_elapsed_time_only():
    source = '''
import time
t0 = time.perf_counter()
work()
assert time.perf_counter() - t0 < 5.0
slowest = 0.0
slowest = max(slowest, time.perf_counter() - t0)
assert slowest < 1
assert result.iterations == 3 and stats["solve_s"] > 0
deadline = time.monotonic() + 60
while time.monotonic() < deadline:
    time.sleep(0.1)
if time.monotonic() > deadline:
    raise TimeoutError("gave up waiting")
from time import monotonic
assert monotonic() > 0
'''
    assert clock_asserts(source) == [5, 8, 16]


def test_no_test_asserts_on_the_wall_clock():
    found = {str(p.relative_to(TESTS)): lines for p in SOURCES if (lines := clock_asserts(p.read_text(encoding="utf-8")))}
    assert not found, f"asserts on the wall clock (assert on behaviour, or measure speed in benchmarks/): {found}"
