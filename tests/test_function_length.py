"""No function (nested ones included, decorators counted) of 100 lines or more in eventcap/ and plugins/.

    python tests/test_function_length.py [N]     # the N longest functions (default 10)
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 100
#: known long functions being split elsewhere (the solver rework): "path:qualified name". An entry that is no longer
#: too long fails the test, so the list only ever shrinks.
PENDING: set[str] = set()


def function_lengths(root: Path = ROOT) -> list[tuple[int, str]]:
    """(lines, "path:qualified.name") of every function of eventcap/ and plugins/, longest first."""
    rows: list[tuple[int, str]] = []
    for path in sorted([*(root / "eventcap").rglob("*.py"), *(root / "plugins").rglob("*.py")]):
        rel = path.relative_to(root).as_posix()
        _walk(ast.parse(path.read_text(), rel), f"{rel}:", rows)
    return sorted(rows, reverse=True)


def _walk(node: ast.AST, prefix: str, rows: list[tuple[int, str]]) -> None:
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
            start = min([child.lineno] + [d.lineno for d in child.decorator_list])
            rows.append((child.end_lineno - start + 1, f"{prefix}{child.name}"))
            _walk(child, f"{prefix}{child.name}.", rows)
        elif isinstance(child, ast.ClassDef):
            _walk(child, f"{prefix}{child.name}.", rows)
        else:
            _walk(child, prefix, rows)


def test_the_scan_counts_nested_functions_and_decorators(tmp_path):
    pkg = tmp_path / "eventcap"
    pkg.mkdir()
    (tmp_path / "plugins").mkdir()
    body = "\n".join(f"        x{i} = {i}" for i in range(5))
    (pkg / "m.py").write_text(f"import numba\n\n\ndef outer():\n    @numba.njit\n    def inner():\n{body}\n"
                              f"    return inner\n")
    # outer: def + decorator + def + 5 lines + return; inner from its decorator
    assert function_lengths(tmp_path) == [(9, "eventcap/m.py:outer"), (7, "eventcap/m.py:outer.inner")]


def test_no_function_of_100_lines_or_more():
    rows = function_lengths()
    long = [f"{name}: {n} lines" for n, name in rows if n >= LIMIT and name not in PENDING]
    assert not long, f"functions of {LIMIT} lines or more (split them by what they do):\n" + "\n".join(long)
    fixed = sorted(PENDING - {name for n, name in rows if n >= LIMIT})
    assert not fixed, f"no longer too long, remove from PENDING in tests/test_function_length.py: {fixed}"


if __name__ == "__main__":
    for n, name in function_lengths()[: int(sys.argv[1]) if len(sys.argv) > 1 else 10]:
        print(f"{n:5d}  {name}{'  [pending]' if name in PENDING else ''}")
