"""The recording readers, registered as stages and factors are: each declares its format once, in a
:class:`ReaderSpec` (name, extensions, signature, time counters, what it reads, where its code is), and everything
that needs a format asks the registry: detection by content and extension (:mod:`eventcap.io.detect`), opening a
reader (:func:`eventcap.io.readers.open_source`), the time checks' counter wraps (:mod:`eventcap.io.checks`), the
help of ``source.format`` and ``eventcap convert``, the fuzz corpus (tests/helpers/fuzz_readers.py) and the format
table of docs/io-robustness.md.

Where readers come from, in this order (a later one of the same name replaces an earlier one, with a warning):

* the readers of this package: each module of :data:`BUILTIN` declares ``READERS`` (a list of specs);
* installed packages: the ``eventcap.readers`` entry-point group (``name = "module:attribute"``, the attribute a
  ReaderSpec or a list of them);
* ``EVENTCAP_READERS`` (entries separated by ``,``, each ``module:attribute`` or ``/path/to/file.py:attribute``):
  a reader tried without installing it.

A new reader is one module (a :class:`eventcap.io.source.Source` subclass and its spec) and a test; the worked
example is tests/fixtures/readers/nmnist.py, registered by tests/test_reader_registry.py. The spec is declarative and
light: a reader's code is imported only when a file of its format is read.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from eventcap.memo import ProcessCache

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "eventcap.readers"
ENV_VAR = "EVENTCAP_READERS"
#: The modules of this package that declare readers (``READERS``).
BUILTIN = ("eventcap.io.aedat4", "eventcap.io.aedat_legacy", "eventcap.io.hdf5", "eventcap.io.rpg",
           "eventcap.io.prophesee", "eventcap.io.arrays")


@dataclass(frozen=True)
class ReaderSpec:
    """One format a reader takes.

    ``source`` ("module:callable") opens a file: ``callable(path, time_unit=..., columns=...)`` returns a
    :class:`eventcap.io.source.Source` (``columns`` only when the format takes it). ``detect`` ("module:callable",
    optional) tells the format of a file whose first bytes start with ``magic`` (or, with no magic, of any file
    that no signature claimed): ``callable(head: bytes, path) -> format name | None`` (the first 64 bytes), or a
    RecordingError (an unsupported version). A folder format's ``detect`` is called with ``head`` None.
    ``sample`` ("module:callable", optional) writes a small valid file of the format from a RawRecording:
    ``callable(folder, recording) -> path`` (the fuzz corpus is made of these).
    """

    name: str
    description: str
    source: str | Callable[..., Any]
    extensions: tuple[str, ...] = ()
    #: what its files start with (one or more signatures; empty: no signature)
    magic: tuple[bytes, ...] = ()
    magic_name: str = ""
    detect: str | Callable[..., Any] = ""
    #: ranges (µs) of the format's time counters: a jump of about one of them is a decoder's wrap, undone
    wraps_us: tuple[int, ...] = ()
    #: unnamed columns (``columns=``) and a unit-less time column (``time_unit=``) apply
    columns: bool = False
    folder: bool = False
    #: declares the sensor size (else it is inferred from the events' coordinates)
    declares_size: bool = True
    extras: str = ""
    library: str = ""
    sample: str | Callable[..., Any] = ""
    origin: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        problems = []
        if not self.name or not self.name.replace("_", "").isalnum() or self.name != self.name.lower():
            problems.append(f"name {self.name!r}: lower-case letters, digits and '_'")
        for label, value in (("source", self.source), ("detect", self.detect), ("sample", self.sample)):
            if value and not callable(value) and ":" not in str(value):
                problems.append(f"{label} {value!r}: expected 'module:callable' (or the callable)")
        if not self.source:
            problems.append("source: required")
        if not self.description:
            problems.append("description: required (one line: what the format is)")
        if any(not e.startswith(".") or e != e.lower() for e in self.extensions):
            problems.append(f"extensions {self.extensions}: lower case, each starting with '.'")
        if self.magic and not self.magic_name:
            problems.append("magic_name: required with magic (\"an AEDAT4\", for messages)")
        if problems:
            raise ValueError(f"reader {self.name!r}: " + "; ".join(problems))

    def load(self, attr: str = "source") -> Callable[..., Any]:
        """The callable named by ``source`` (or ``detect``, ``sample``), imported now (a plugin's module may give
        the callable itself)."""
        target = getattr(self, attr)
        if callable(target):
            return target
        module, _, name = target.partition(":")
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError) as exc:
            raise ImportError(f"reader {self.name!r}: cannot import its {attr} {target!r}: {exc}") from exc


class ReaderRegistry:
    """The registered readers, by format name."""

    def __init__(self, specs: Iterable[ReaderSpec]):
        self._specs: dict[str, ReaderSpec] = {}
        for spec in specs:
            old = self._specs.get(spec.name)
            if old is not None and old.origin != spec.origin:
                log.warning("reader %r from %s replaces the one from %s", spec.name, spec.origin, old.origin)
            self._specs[spec.name] = spec

    def names(self) -> list[str]:
        """The format names ``format=`` takes, in registration order."""
        return list(self._specs)

    def specs(self) -> list[ReaderSpec]:
        return list(self._specs.values())

    def __contains__(self, name: str) -> bool:
        return self.find(name) is not None

    def find(self, name: str) -> ReaderSpec | None:
        return self._specs.get(str(name).lower())

    def get(self, name: str) -> ReaderSpec:
        spec = self.find(name)
        if spec is None:
            from eventcap.names import unknown_name_message

            raise ValueError(unknown_name_message("format", str(name), self.names(), "the recording readers"))
        return spec

    def by_extension(self, suffix: str) -> list[ReaderSpec]:
        return [s for s in self._specs.values() if suffix.lower() in s.extensions]

    def extensions(self) -> list[str]:
        return sorted({e for s in self._specs.values() for e in s.extensions})

    def wraps_us(self, name: str) -> tuple[int, ...]:
        spec = self.find(name)
        return spec.wraps_us if spec is not None else ()

    def column_formats(self) -> tuple[str, ...]:
        return tuple(s.name for s in self._specs.values() if s.columns)

    def describe(self) -> str:
        """One line per format: what ``format=`` takes (for help and messages)."""
        return "; ".join(f"{s.name} ({s.description})" for s in self._specs.values())


def _specs_of(value: Any, origin: str) -> list[ReaderSpec]:
    value = value() if callable(value) and not isinstance(value, ReaderSpec) else value
    items = [value] if isinstance(value, ReaderSpec) else list(value)
    out = []
    for item in items:
        if not isinstance(item, ReaderSpec):
            raise TypeError(f"{origin}: expected ReaderSpec(s), got {type(item).__name__}")
        out.append(ReaderSpec(**{**item.__dict__, "origin": origin}))
    return out


def _load_target(target: str):
    module, _, attr = target.rpartition(":")
    if module.endswith(".py") or os.sep in module:
        path = Path(module).expanduser()
        name = f"eventcap_reader_{path.stem}"
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise ImportError(f"cannot load {path}")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    else:
        mod = importlib.import_module(module)
    return getattr(mod, attr)


def discover() -> ReaderRegistry:
    """Every reader: this package's, installed packages' (entry points) and ``EVENTCAP_READERS``'. A reader that
    cannot be loaded is skipped with a warning naming it (the others still work)."""
    specs: list[ReaderSpec] = []
    for module in BUILTIN:
        specs += _specs_of(importlib.import_module(module).READERS, module)
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            specs += _specs_of(ep.load(), f"entry point {ep.name} ({ep.value})")
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not hide the others
            log.warning("reader entry point %s (%s) skipped: %s", ep.name, ep.value, exc)
    for target in [t.strip() for t in os.environ.get(ENV_VAR, "").split(",") if t.strip()]:
        try:
            specs += _specs_of(_load_target(target), f"{ENV_VAR} {target}")
        except Exception as exc:  # noqa: BLE001
            log.warning("%s entry %s skipped: %s", ENV_VAR, target, exc)
    return ReaderRegistry(specs)


#: The registry by the value of EVENTCAP_READERS when it was discovered.
_REGISTRY = ProcessCache("io.readers", maxsize=4)


def readers() -> ReaderRegistry:
    """The registry, discovered once per process (again when ``EVENTCAP_READERS`` changed, or after
    :func:`forget_readers` / ``eventcap.memo.clear_process_caches``)."""
    return _REGISTRY.get(os.environ.get(ENV_VAR, ""), discover)[0]


def forget_readers() -> None:
    """Discover the readers again when next asked (after installing one, or in tests)."""
    _REGISTRY.clear()
