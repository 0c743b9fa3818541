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

from eventcap.artifacts import Artifact, Batch, BatchPlan
from eventcap.errors import ComputationFailed
from eventcap.params import (  # noqa: F401 (the public plugin API: eventcap.core.stage.param)
    allowed_values,
    check_value,
    field_at,
    given_fields,
    given_or_unset,
    group,
    is_group,
    leaves,
    param,
    value_at,
)


@dataclass(frozen=True)
class Port:
    """A typed input or output of a stage.

    ``all_batches=True`` on an input means: the whole recording's worth of an upstream output, delivered as a lazy
    sequence (see runner.BatchSequence): every batch of a per-batch output, or the one artifact of a
    whole-recording output (a sequence of one, its ``batches`` ``[None]``), so that a stage such as ``evaluate``
    reads either. A whole-recording stage needs it to read a per-batch output; a per-batch stage may ask for it to
    see its neighbours' batches too (each of its batches then depends on all of them, and a failed upstream batch
    skips every one of its batches).

    ``window`` on an input of a per-batch stage whose type grows with the capture (its rows follow time:
    ``Artifact.time_dims``, e.g. the recording's events and frames, the latent images): each unit reads only its own
    time range, from its first batch's start to its last batch's end (both ends included), widened by ``window``
    batches of the recording on each side (an int, or a function of the stage's config giving it), instead of the
    whole capture. None: the whole artifact. ``without``: optional fields of a windowed input that the stage never
    reads (e.g. the recording's ground truth, which a method never looks at), left out (None) and not read.
    """

    type: type[Artifact]
    doc: str = ""
    optional: bool = False
    all_batches: bool = False
    window: int | Callable[[Any], int] | None = None
    without: tuple[str, ...] = ()

    def margin(self, config: Any) -> int | None:
        """The batches on each side of a unit that a windowed input reads (``window``), None when read whole."""
        if self.window is None:
            return None
        m = self.window(config) if callable(self.window) else self.window
        if not isinstance(m, int) or isinstance(m, bool) or m < 0:
            raise StageSpecError(f"Port window: expected a number of batches >= 0, got {m!r}")
        return m


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
    #: settings that moved: {old key: new dotted key}; an old key is refused naming its new one
    renamed: Mapping[str, str] = field(default_factory=dict)
    #: optional ``"module:function"`` called with the built config when the pipeline is built (before anything
    #: runs): checks that involve several keys or values taken from elsewhere (a preset); raises ``ValueError``
    #: naming the key. Single values are bounded by their ``param`` declarations, never here.
    check: str = ""
    #: a per-batch stage with two BatchPlan inputs: the input port whose plan cuts its units (the other is read as
    #: data, e.g. a chunk plan cuts the units and the recording's batches say which batches each chunk holds); when
    #: that port is not connected, the plan is found as for any per-batch stage
    plan: str = ""

    def __post_init__(self) -> None:
        where = f"stage spec {self.name!r}" + (f" ({self.origin})" if self.origin else "")
        if not self.name or not self.name.replace("_", "").isalnum() or not self.name[0].isalpha():
            raise StageSpecError(f"{where}: name must be an identifier-like word, got {self.name!r}")
        if not isinstance(self.version, int):
            raise StageSpecError(f"{where}: version must be an int you bump when outputs change")
        if not dataclasses.is_dataclass(self.config):
            raise StageSpecError(f"{where}: config must be a dataclass type, got {self.config!r}")
        self._check_settings(where)
        if ":" not in self.run:
            raise StageSpecError(f"{where}: run must be 'module:function', got {self.run!r}")
        if self.check and ":" not in self.check:
            raise StageSpecError(f"{where}: check must be 'module:function', got {self.check!r}")
        for direction, ports in (("input", self.inputs), ("output", self.outputs)):
            for pname, port in ports.items():
                if not isinstance(port, Port) or not (isinstance(port.type, type) and issubclass(port.type, Artifact)):
                    raise StageSpecError(f"{where}: {direction} {pname!r} must be Port(<Artifact type>)")
        for pname, port in self.inputs.items():
            if port.window is not None and not (self.per_batch and not port.all_batches
                                                and port.type.has_time_dims()):
                raise StageSpecError(f"{where}: input {pname!r}: window applies to an input of a per-batch stage read "
                                     f"one unit at a time whose type has time dimensions ({port.type.__name__} "
                                     f"{'has' if port.type.has_time_dims() else 'has none'})")
            optional = {f.name for f in dataclasses.fields(port.type) if f.default is None}
            bad = [f for f in port.without if f not in optional]
            if port.without and (port.window is None or bad):
                raise StageSpecError(f"{where}: input {pname!r}: without={port.without!r} applies to a windowed input "
                                     f"and names optional fields of {port.type.__name__} "
                                     f"({', '.join(sorted(optional)) or 'it has none'})")
        for pname, port in self.outputs.items():
            if port.window is not None or port.all_batches or port.optional:
                raise StageSpecError(f"{where}: output {pname!r} cannot be optional, all_batches or windowed")
        if not self.outputs:
            raise StageSpecError(f"{where}: a stage must declare at least one output")
        if self.plan and not (self.per_batch and self.plan in self.inputs
                              and issubclass(self.inputs[self.plan].type, BatchPlan)):
            raise StageSpecError(f"{where}: plan {self.plan!r} must name a BatchPlan input of a per-batch stage")
        object.__setattr__(self, "inputs", MappingProxyType(dict(self.inputs)))
        object.__setattr__(self, "outputs", MappingProxyType(dict(self.outputs)))
        object.__setattr__(self, "renamed", MappingProxyType(dict(self.renamed)))

    def _check_settings(self, where: str) -> None:
        """Every setting (groups opened) declared with param(), its default within its choices and bounds."""
        for f in dataclasses.fields(self.config):
            if "help" not in f.metadata:
                raise StageSpecError(f"{where}: config field {f.name!r} must be declared with eventcap.core.stage.param() "
                                     "or eventcap.params.group()")
        try:
            default = self.config()
        except TypeError:  # a setting without a default (the user must give it)
            default = None
        for key, f in leaves(self.config):
            if "help" not in f.metadata:
                raise StageSpecError(f"{where}: config field {key!r} must be declared with eventcap.core.stage.param()")
            value = f.default if default is None else value_at(default, key)
            if value is dataclasses.MISSING:
                continue
            choices = f.metadata.get("choices")
            if choices is not None and value not in choices:
                raise StageSpecError(f"{where}: config field {key!r}: default {value!r} is not one of its choices "
                                     f"{choices}")
            if f.metadata.get("bounds") or f.metadata.get("odd"):
                problem = check_value(f, value)
                if problem:
                    raise StageSpecError(f"{where}: config field {key!r}: its default {problem}")
        for old, new in self.renamed.items():
            if field_at(self.config, new) is None:
                raise StageSpecError(f"{where}: renamed setting {old!r} -> {new!r}: no setting {new!r}")

    # -- config ---------------------------------------------------------------------------------------------------
    def result_fields(self) -> list[str]:
        """The dotted keys of the settings that affect the result (groups opened): the cache key's."""
        return [k for k, f in leaves(self.config) if f.metadata.get("affects_result", True)]

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
        return [k for k, f in leaves(self.config) if f.metadata.get("file", False)]

    def load_check(self) -> Callable[[Any], None] | None:
        """The config check function (``check``), or None."""
        if not self.check:
            return None
        module, _, attr = self.check.partition(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise StageSpecError(f"stage {self.name!r}: cannot import its check function {self.check!r}: {exc}") \
                from exc

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
