"""Process caches: values a process builds once and reuses (solver problems, loaded assets, the stage registry...),
keyed by value, bounded, and cleared together.

Every module-level cache of the project is a :class:`ProcessCache` (or a function wrapped by :func:`memoize`), so
that :func:`clear_process_caches` empties them all (tests; ``eventcap.core.runner.reset_process_caches`` after the stages
or files on disk changed) and none is keyed by ``id()``: an id is reused once its object is gone, and a cache keyed by
it hands a later object the value built for another. Keys are values: numbers, strings, bytes, paths, classes, frozen
dataclasses and tuples of them; :func:`value_key` turns arrays and mappings into such keys. A key part hashed by
identity (a plain object) is refused.

This module imports nothing of eventcap: the library, the orchestration and the plugins all use it.
"""

from __future__ import annotations

import functools
import hashlib
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable, Mapping
from typing import Any, TypeVar

import numpy as np

T = TypeVar("T")

#: every process cache of this process (weakly held: a cache of a module that was reloaded goes with it)
_ALL: weakref.WeakSet[ProcessCache] = weakref.WeakSet()
_ALL_LOCK = threading.Lock()


class ProcessCache:
    """A named memo of this process (name: ``module.what``): ``get(key, build)`` returns the value stored under ``key`` or builds and stores
    it. At most ``maxsize`` entries (least recently used dropped first; None = unbounded). Thread-safe; ``build`` runs
    outside the lock (two threads may build the same value; the first stored wins)."""

    def __init__(self, name: str, maxsize: int | None = None, max_bytes: int | None = None,
                 weigh: Callable[[Any], int] | None = None):
        if maxsize is not None and maxsize < 1:
            raise ValueError(f"ProcessCache {name!r}: maxsize must be >= 1 or None, got {maxsize}")
        if (max_bytes is None) != (weigh is None):
            raise ValueError(f"ProcessCache {name!r}: max_bytes and weigh go together")
        self.name = name
        self.maxsize = maxsize
        #: with ``weigh`` (a value's size in bytes): least recently used entries are dropped while the entries
        #: weigh more than ``max_bytes`` together (the newest is always kept)
        self.max_bytes, self._weigh = max_bytes, weigh
        self._bytes = 0
        self._data: OrderedDict[Hashable, Any] = OrderedDict()
        self._lock = threading.Lock()
        with _ALL_LOCK:
            _ALL.add(self)

    def get(self, key: Hashable, build: Callable[[], T]) -> tuple[T, bool]:
        """``(value, built_now)``: the value under ``key``, built by ``build()`` when absent. A ``build`` that
        raises stores nothing."""
        _check_key(key, self.name)
        with self._lock:
            if key in self._data:
                self._data.move_to_end(key)
                return self._data[key], False
        value = build()
        with self._lock:
            if key in self._data:  # another thread built it meanwhile: keep the first
                return self._data[key], False
            self._store(key, value)
        return value, True

    def put(self, key: Hashable, value: Any) -> None:
        """Store ``value`` under ``key`` (replacing what is there)."""
        _check_key(key, self.name)
        with self._lock:
            if key in self._data:
                self._bytes -= self._size(self._data.pop(key))
            self._store(key, value)

    def _size(self, value: Any) -> int:
        return int(self._weigh(value)) if self._weigh is not None else 0

    def _store(self, key: Hashable, value: Any) -> None:
        self._data[key] = value
        self._bytes += self._size(value)
        while len(self._data) > 1 and ((self.maxsize is not None and len(self._data) > self.maxsize)
                                       or (self.max_bytes is not None and self._bytes > self.max_bytes)):
            self._bytes -= self._size(self._data.popitem(last=False)[1])

    def __contains__(self, key: Hashable) -> bool:
        with self._lock:
            return key in self._data

    def __len__(self) -> int:
        with self._lock:
            return len(self._data)

    def discard(self, drop: Callable[[Hashable, Any], bool]) -> int:
        """Drop the entries for which ``drop(key, value)`` is true; returns how many were dropped."""
        with self._lock:
            gone = [k for k, v in self._data.items() if drop(k, v)]
            for k in gone:
                self._bytes -= self._size(self._data.pop(k))
        return len(gone)

    def clear(self) -> int:
        """Drop every entry; returns how many there were."""
        with self._lock:
            n = len(self._data)
            self._data.clear()
            self._bytes = 0
        return n

    def __repr__(self) -> str:
        return f"ProcessCache({self.name!r}, {len(self)} entries, maxsize={self.maxsize})"


def memoize(name: str, maxsize: int | None = None):
    """Decorator: the function's results cached per (positional and keyword) arguments in a ProcessCache ``name``;
    the wrapper has ``cache_clear()`` and ``cache`` (the ProcessCache)."""

    def wrap(fn):
        cache = ProcessCache(name, maxsize)

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            key = (args, tuple(sorted(kwargs.items()))) if kwargs else args
            return cache.get(key, lambda: fn(*args, **kwargs))[0]

        wrapper.cache = cache
        wrapper.cache_clear = cache.clear
        return wrapper

    return wrap


def value_key(*parts: Any) -> tuple:
    """A hashable key from values: arrays become (dtype, shape, SHA-1 of the bytes), mappings sorted (key, value)
    tuples, lists and tuples tuples, recursively; anything else must be hashable by value already."""
    return tuple(_value(p) for p in parts)


def _value(p: Any) -> Hashable:
    if isinstance(p, np.ndarray):
        a = np.ascontiguousarray(p)
        return ("ndarray", a.dtype.str, a.shape, hashlib.sha1(a.tobytes()).hexdigest())
    if isinstance(p, Mapping):
        return ("mapping", tuple(sorted((str(k), _value(v)) for k, v in p.items())))
    if isinstance(p, (list, tuple)):
        return tuple(_value(v) for v in p)
    _check_key(p, "value_key")
    return p


def _check_key(key: Any, where: str) -> None:
    """Refuse keys that are unhashable or hashed by identity (a plain object: its hash is its id)."""
    if isinstance(key, (tuple, frozenset)):
        for part in key:
            _check_key(part, where)
        return
    if isinstance(key, type) or key is None:
        return  # a class is one object for the life of the process, and the cache holds it
    h = getattr(type(key), "__hash__", None)
    if h is None:
        raise TypeError(f"{where}: unhashable key part {type(key).__name__}; use eventcap.memo.value_key(...)")
    if h is object.__hash__:
        raise TypeError(f"{where}: key part {type(key).__name__} is hashed by identity (its id), not by value; key by "
                        f"the values it holds (eventcap.memo.value_key)")


def process_caches() -> list[ProcessCache]:
    """Every process cache alive in this process, by name."""
    with _ALL_LOCK:
        return sorted(_ALL, key=lambda c: c.name)


def clear_process_caches(prefix: str = "") -> dict[str, int]:
    """Empty every process cache (those whose name starts with ``prefix``); returns how many entries each held, by
    name."""
    out: dict[str, int] = {}
    for cache in process_caches():
        if not cache.name.startswith(prefix):
            continue
        out[cache.name] = out.get(cache.name, 0) + cache.clear()
    return out
