"""The stage contract: a small spec object a plugin exposes through the ``eventcap.stages`` entry-point group.

A spec names the stage, its kind, a hand-bumped ``version``, a config dataclass whose fields say whether they affect
the result, typed input and output ports, whether it runs per batch, and the run function as a ``"module:function"``
string imported only when the stage runs (so listing stages imports no solver)::

    SPEC = StageSpec(
        name="edi", kind="sharpen", version=1, description="EDI deblurring of intensity frames (Eq. 2)",
        config=EdiConfig, inputs={"recording": Port(Recording)}, outputs={"latent": Port(LatentFrames)},
        run="eventcap_sharpen._impl:run_edi",
    )

The run function is pure: ``run(inputs: dict[str, Artifact], config, ctx: StageContext) -> dict[str, Artifact]``.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from eventcap.artifacts import Artifact, Batch
from eventcap.errors import ComputationFailed


def param(default: Any = dataclasses.MISSING, *, help: str, affects_result: bool = True,
          file: bool | Callable[[Any], list[str]] = False,
          default_factory: Any = dataclasses.MISSING, choices: tuple[Any, ...] | None = None,
          ge: float | None = None, gt: float | None = None, le: float | None = None, lt: float | None = None,
          finite: bool = True, odd: bool = False, unset: Any = dataclasses.MISSING):
    """A config field. ``affects_result=False`` keeps it out of the cache key (e.g. logging, sleeps, workers).

    ``unset=<value>`` (with a null default) makes a field the user may leave unsaid: null means "not given", the
    stage then uses ``value`` (:func:`given_or_unset`) and may treat what was given differently from what was not
    (a template's stated height is kept, an unstated one estimated). While null, the key material holds ``value``,
    as before the field could be null; the names of the given ones are added to the key (``given``).

    ``file=True`` marks a path whose *content digest* enters the cache key (input recordings, templates).
    ``file=<function>`` is for a field whose value only sometimes names files (a motion name or a clip's path):
    the function maps the value to the paths it refers to ([] for none), and their digests enter the key.
    ``choices`` lists the only values the field takes. A number (or each number of a list) is bounded by
    ``ge`` (>=), ``gt`` (>), ``le`` (<=), ``lt`` (<); ``finite=False`` lets it be inf (NaN never passes); ``odd``
    asks for an odd integer. Integers are integers by the field's type. Any other value is refused when the
    pipeline is built, before anything runs (not once per batch by the stage), with the key and what is allowed
    (:func:`check_value`).
    """
    meta = {"help": help, "affects_result": affects_result, "file": file}
    if choices is not None:
        meta["choices"] = tuple(choices)
    bounds = {k: v for k, v in (("ge", ge), ("gt", gt), ("le", le), ("lt", lt)) if v is not None}
    if bounds:
        meta["bounds"] = bounds
    if not finite:
        meta["finite"] = False
    if odd:
        meta["odd"] = True
    if unset is not dataclasses.MISSING:
        meta["unset"] = unset
    if default_factory is not dataclasses.MISSING:
        return field(default_factory=default_factory, metadata=meta)
    return field(default=default, metadata=meta)


def given_or_unset(config: Any, name: str) -> Any:
    """The value of field ``name`` of a config: as given, or its ``unset`` value (see :func:`param`) when null."""
    value = getattr(config, name)
    if value is not None:
        return value
    f = next(f for f in dataclasses.fields(config) if f.name == name)
    return f.metadata.get("unset")


def given_fields(config: Any) -> list[str]:
    """The fields declared with ``unset`` (:func:`param`) that the config gives (not null), in declaration order."""
    return [f.name for f in dataclasses.fields(config) if "unset" in f.metadata and getattr(config, f.name) is not None]


def _allowed(meta: Mapping[str, Any], integer: bool) -> str:
    """What a bounded field allows, in words: 'an integer >= 1', 'a finite number in (0, 1]', ..."""
    b = meta.get("bounds", {})
    kind = ("an odd integer" if meta.get("odd") else "an integer") if integer else \
        ("a number" if meta.get("finite", True) is False else "a finite number")
    lo = ("[", b["ge"]) if "ge" in b else ("(", b["gt"]) if "gt" in b else None
    hi = ("]", b["le"]) if "le" in b else (")", b["lt"]) if "lt" in b else None
    if lo and hi:
        return f"{kind} in {lo[0]}{lo[1]:g}, {hi[1]:g}{hi[0]}"
    if lo:
        return f"{kind} {'>=' if lo[0] == '[' else '>'} {lo[1]:g}"
    if hi:
        return f"{kind} {'<=' if hi[0] == ']' else '<'} {hi[1]:g}"
    return kind


def _is_integer_field(f: dataclasses.Field) -> bool:
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    return t in ("int", "list[int]", "int | None", "tuple[int, ...]")


def allowed_values(f: dataclasses.Field) -> str | None:
    """What a numeric or boolean config field takes, in words (None for other fields)."""
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    if t in ("bool", "bool | None"):
        return "true or false"
    if t in ("int", "float", "int | None", "float | None"):
        return _allowed(f.metadata, _is_integer_field(f)) + (" or null" if "None" in t else "")
    if t in ("list[int]", "list[float]"):
        return "a list, each item " + _allowed(f.metadata, _is_integer_field(f))
    return None


def check_value(f: dataclasses.Field, value: Any) -> str | None:
    """Why ``value`` is not allowed in config field ``f`` (declared with :func:`param`), or None when it is.

    Numbers (and the numbers of a list) must be finite (unless ``finite=False``; NaN never passes), integers when
    the field is an integer, and within the field's declared bounds. Booleans, strings and None are left to the
    field's type and choices."""
    meta = f.metadata
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            problem = check_value(f, v)
            if problem:
                return f"{problem} (item {i} of {list(value)!r})"
        return None
    if value is None or isinstance(value, (bool, str)) or not isinstance(value, (int, float)):
        return None
    integer = _is_integer_field(f)
    bounds = meta.get("bounds", {})
    bad = (value != value  # NaN
           or (meta.get("finite", True) and value in (float("inf"), float("-inf")))
           or (integer and float(value) != int(value))
           or (meta.get("odd") and int(value) % 2 == 0)
           or ("ge" in bounds and not value >= bounds["ge"]) or ("gt" in bounds and not value > bounds["gt"])
           or ("le" in bounds and not value <= bounds["le"]) or ("lt" in bounds and not value < bounds["lt"]))
    if bad:
        return f"expected {_allowed(meta, integer)}, got {value!r}"
    return None


@dataclass(frozen=True)
class Port:
    """A typed input or output of a stage.

    ``all_batches=True`` on an input means: all batches of a per-batch upstream output, delivered as a lazy
    sequence (see runner.BatchSequence). A whole-recording stage needs it to read a per-batch output; a per-batch
    stage may ask for it to see its neighbours' batches too (each of its batches then depends on all of them, and a
    failed upstream batch skips every one of its batches).
    """

    type: type[Artifact]
    doc: str = ""
    optional: bool = False
    all_batches: bool = False


class StageSpecError(TypeError):
    """A stage spec is malformed (a plugin bug, reported with the plugin's name)."""


@dataclass(frozen=True)
class StageSpec:
    """Everything the framework needs to know about a stage, without importing its implementation."""

    name: str
    kind: str
    version: int
    description: str
    config: type
    inputs: Mapping[str, Port]
    outputs: Mapping[str, Port]
    run: str
    per_batch: bool = False
    origin: str = ""  # where the registry found it (filled by the registry)
    #: The input ports a config reads, ``uses(config) -> names`` (None: every input). An input a config does not
    #: read is neither loaded nor part of the node's cache key: e.g. the synthetic source filming an actor of its
    #: own does not recompute its capture when the template changes.
    uses: Callable[[Any], Collection[str]] | None = None

    def __post_init__(self) -> None:
        where = f"stage spec {self.name!r}" + (f" ({self.origin})" if self.origin else "")
        if not self.name or not self.name.replace("_", "").isalnum() or not self.name[0].isalpha():
            raise StageSpecError(f"{where}: name must be an identifier-like word, got {self.name!r}")
        if not isinstance(self.version, int):
            raise StageSpecError(f"{where}: version must be an int you bump when outputs change")
        if not dataclasses.is_dataclass(self.config):
            raise StageSpecError(f"{where}: config must be a dataclass type, got {self.config!r}")
        for f in dataclasses.fields(self.config):
            if "help" not in f.metadata:
                raise StageSpecError(f"{where}: config field {f.name!r} must be declared with eventcap.core.stage.param()")
            choices = f.metadata.get("choices")
            if choices is not None and f.default is not dataclasses.MISSING and f.default not in choices:
                raise StageSpecError(f"{where}: config field {f.name!r}: default {f.default!r} is not one of its "
                                     f"choices {choices}")
            if f.default is not dataclasses.MISSING and (f.metadata.get("bounds") or f.metadata.get("odd")):
                problem = check_value(f, f.default)
                if problem:
                    raise StageSpecError(f"{where}: config field {f.name!r}: its default {problem}")
        if ":" not in self.run:
            raise StageSpecError(f"{where}: run must be 'module:function', got {self.run!r}")
        for direction, ports in (("input", self.inputs), ("output", self.outputs)):
            for pname, port in ports.items():
                if not isinstance(port, Port) or not (isinstance(port.type, type) and issubclass(port.type, Artifact)):
                    raise StageSpecError(f"{where}: {direction} {pname!r} must be Port(<Artifact type>)")
        for pname, port in self.outputs.items():
            if port.all_batches or port.optional:
                raise StageSpecError(f"{where}: output {pname!r} cannot be optional or all_batches")
        if not self.outputs:
            raise StageSpecError(f"{where}: a stage must declare at least one output")
        object.__setattr__(self, "inputs", MappingProxyType(dict(self.inputs)))
        object.__setattr__(self, "outputs", MappingProxyType(dict(self.outputs)))

    # -- config ---------------------------------------------------------------------------------------------------
    def result_fields(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self.config) if f.metadata.get("affects_result", True)]

    def used_inputs(self, config: Any) -> list[str]:
        """The input ports ``config`` reads (see ``uses``), in declaration order."""
        if self.uses is None:
            return list(self.inputs)
        used = set(self.uses(config))
        unknown = sorted(used - set(self.inputs))
        if unknown:
            raise StageSpecError(f"stage spec {self.name!r}: uses() names unknown input(s) {unknown}")
        return [p for p in self.inputs if p in used]

    def file_fields(self) -> list[str]:
        return [f.name for f in dataclasses.fields(self.config) if f.metadata.get("file", False)]

    def load_run(self) -> Callable[..., Mapping[str, Artifact]]:
        module, _, attr = self.run.partition(":")
        try:
            fn = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise StageSpecError(f"stage {self.name!r}: cannot import its run function {self.run!r}: {exc}") from exc
        return fn


@dataclass
class StageContext:
    """What the runner gives a running stage besides inputs and config."""

    node: str
    stage: str
    batch: Batch | None = None
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("eventcap.core.stage"))
    progress: Callable[[int, int], None] | None = None
    #: Diagnostics of this computation (timings, solver iterations...): JSON-serialisable, recorded in the cache
    #: manifest of the result (``eventcap cache explain``), not part of the outputs or their key.
    stats: dict[str, Any] = field(default_factory=dict)

    def rng(self, seed: int, *extra: int) -> np.random.Generator:
        """A generator seeded by (seed, batch index, extra...) so batches get independent, reproducible streams."""
        parts = [int(seed)] + ([self.batch.index] if self.batch is not None else []) + [int(e) for e in extra]
        return np.random.default_rng(parts)

    def report(self, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(done, total)


class StageFailed(ComputationFailed):
    """Raised by a stage whose computation did not succeed (e.g. a solver status); recorded, never cached.

    The domain library raises its own subclasses of :class:`eventcap.errors.ComputationFailed`, which the runner
    records the same way."""
