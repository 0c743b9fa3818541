"""Process caches (eventcap.memo): built once per key, keyed by value (never by identity), bounded, cleared together."""

from __future__ import annotations

import numpy as np
import pytest

from eventcap.memo import ProcessCache, clear_process_caches, memoize, process_caches, value_key


def test_builds_once_per_key_and_says_so():
    cache = ProcessCache("test_memo.once")
    calls = []

    def build(v):
        calls.append(v)
        return v * 2

    assert cache.get(("a", 1), lambda: build(1)) == (2, True)
    assert cache.get(("a", 1), lambda: build(99)) == (2, False)
    assert cache.get(("a", 2), lambda: build(2)) == (4, True)
    assert calls == [1, 2] and len(cache) == 2 and ("a", 1) in cache


def test_least_recently_used_entry_goes_first():
    cache = ProcessCache("test_memo.lru", maxsize=2)
    cache.get(1, lambda: "one")
    cache.get(2, lambda: "two")
    cache.get(1, lambda: "again")  # 1 is now the most recently used
    cache.get(3, lambda: "three")
    assert 1 in cache and 3 in cache and 2 not in cache and len(cache) == 2
    with pytest.raises(ValueError, match="maxsize must be >= 1 or None, got 0"):
        ProcessCache("test_memo.bad", maxsize=0)


def test_a_failed_build_stores_nothing():
    cache = ProcessCache("test_memo.fail")

    def boom():
        raise RuntimeError("no")

    with pytest.raises(RuntimeError):
        cache.get("k", boom)
    assert "k" not in cache and cache.get("k", lambda: 5) == (5, True)


def test_keys_are_values_not_identities():
    cache = ProcessCache("test_memo.keys")

    class Plain:  # hashed by id(): a later object may get the id of one that is gone
        pass

    with pytest.raises(TypeError, match=r"key part Plain is hashed by identity \(its id\), not by value"):
        cache.get(("x", Plain()), lambda: 1)
    with pytest.raises(TypeError, match=r"unhashable key part ndarray; use eventcap.memo.value_key"):
        cache.get((np.zeros(2),), lambda: 1)
    a, b = np.arange(6.0).reshape(2, 3), np.arange(6.0).reshape(2, 3)
    assert a is not b and value_key(a, {"y": 1, "x": [1, 2]}) == value_key(b, {"x": (1, 2), "y": 1})
    assert value_key(a) != value_key(a.reshape(3, 2)) != value_key(a.astype(np.float32))
    assert value_key(a) != value_key(a + 1e-12)
    # classes, paths, frozen dataclasses and None are values too
    cache.get((int, None, "p"), lambda: 1)


def test_memoize_and_clearing_every_cache():
    calls = []

    @memoize("test_memo.square", maxsize=4)
    def square(x, scale=1):
        calls.append(x)
        return x * x * scale

    assert square(3) == 9 and square(3) == 9 and square(3, scale=2) == 18 and calls == [3, 3]
    other = ProcessCache("test_memo.other")
    other.get("k", lambda: 1)
    cleared = clear_process_caches()
    assert cleared["test_memo.square"] == 2 and cleared["test_memo.other"] == 1
    assert len(square.cache) == 0 and len(other) == 0
    assert square(3) == 9 and calls == [3, 3, 3]
    import eventcap.core.runner  # noqa: F401  (its caches register when it is imported)

    names = {c.name for c in process_caches()}
    assert {"test_memo.square", "test_memo.other", "runner.inputs", "runner.registry"} <= names


def test_the_runner_reset_clears_them_all():
    from eventcap.core.runner import reset_process_caches

    cache = ProcessCache("test_memo.reset")
    cache.get("k", lambda: 1)
    reset_process_caches()
    assert len(cache) == 0


#: every process cache of the solves (module: names)
SOLVE_CACHES = {"eventcap.energy.kernels": {"energy.kernels"},
                "eventcap_solve._impl": {"eventcap_solve.problems"},
                "eventcap_refine._impl": {"eventcap_refine.problems"},
                "eventcap_spline._impl": {"eventcap_spline.solvers", "eventcap_spline.capture_templates",
                                          "eventcap_spline.capture_floors"},
                "eventcap_spline.solve": {"eventcap_spline.frame_fits"}}


def test_the_solves_caches_are_process_caches_and_the_reset_empties_them():
    import importlib

    from eventcap.core.runner import reset_process_caches

    by_name = {}
    for module, names in SOLVE_CACHES.items():
        importlib.import_module(module)
        found = {c.name: c for c in process_caches() if c.name in names}
        assert set(found) == names, f"{module}: {sorted(names - set(found))} not a ProcessCache"
        by_name.update(found)
    for name, cache in by_name.items():
        cache.get(("test", name), lambda: 1)
    reset_process_caches()
    assert {n: len(c) for n, c in by_name.items()} == dict.fromkeys(by_name, 0)
    assert all(c.maxsize is not None for c in by_name.values()), "every cache of the solves is bounded"


def _module_dict_caches(path) -> list[str]:
    """Module-level names bound to an empty dict, list or set that a function of the module fills or empties."""
    import ast

    tree = ast.parse(path.read_text())
    empty = set()
    for node in tree.body:
        target, value = (node.target, node.value) if isinstance(node, ast.AnnAssign) else (
            (node.targets[0], node.value) if isinstance(node, ast.Assign) and len(node.targets) == 1 else (None, None))
        if isinstance(target, ast.Name) and (
                isinstance(value, (ast.Dict, ast.List, ast.Set)) and not getattr(value, "keys", getattr(value, "elts", [1]))
                or isinstance(value, ast.Call) and isinstance(value.func, ast.Name)
                and value.func.id in ("dict", "list", "set", "OrderedDict") and not value.args):
            empty.add(target.id)
    found = set()
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Store) and isinstance(node.value, ast.Name):
                name = node.value.id
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and isinstance(
                    node.func.value, ast.Name) and node.func.attr in ("clear", "setdefault", "update", "append", "pop",
                                                                       "add", "popitem"):
                name = node.func.value.id
            else:
                continue
            if name in empty:
                found.add(name)
    return sorted(found)


#: module-level containers filled at run time that are state, not memos (nothing to rebuild them from)
NOT_CACHES = {
    "eventcap/energy/factor.py: FACTORS",  # the factor classes, registered as each class is defined
    "eventcap/core/rundir.py: _HELD",  # the run folders this process holds locked (their open lock files)
    "eventcap/apps/cli.py: _RUN_FAILURES",  # the jobs of this command that failed (its exit code)
}


def test_no_module_level_dict_serves_as_a_cache():
    from helpers.paths import ROOT

    found = {f"{p.relative_to(ROOT)}: {name}" for base in ("eventcap", "plugins")
             for p in sorted((ROOT / base).rglob("*.py")) for name in _module_dict_caches(p)}
    assert NOT_CACHES <= found, f"no longer module-level state, remove from NOT_CACHES: {sorted(NOT_CACHES - found)}"
    bad = sorted(found - NOT_CACHES)
    assert not bad, ("module-level containers filled at run time: make each an eventcap.memo.ProcessCache (bounded, "
                     "keyed by value, emptied by clear_process_caches):\n" + "\n".join(bad))


def test_the_scan_finds_a_bare_dict_cache(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("_C: dict = {}\nTABLE = {'a': 1}\n_L = []\n\ndef get(k):\n    if k not in _C:\n        _C[k] = k\n"
                   "    _L.append(k)\n    return TABLE[k]\n")
    assert _module_dict_caches(src) == ["_C", "_L"]
