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
