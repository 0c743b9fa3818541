"""Declaring settings: a config field with its help, unit, range and whether it affects a result, and groups of them.

A stage's config is a dataclass whose every field is declared with :func:`param` (a setting) or :func:`group` (a
nested dataclass of settings, e.g. one energy term's weight and settings: ``stages.solve.terms.cor.sigma_px``).
The framework checks every value against its declaration before anything runs (:func:`check_value`), and the
domain library declares the settings of its own pieces (an energy term, the IPOPT options) the same way, so a
setting is stated once, wherever it is used. A leaf module: it imports nothing of eventcap.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from dataclasses import field
from typing import Any


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


def given_or_unset(config: Any, key: str) -> Any:
    """The value of setting ``key`` (dotted) of a config: as given, or its ``unset`` value (see :func:`param`) when
    null."""
    value = value_at(config, key)
    if value is not None:
        return value
    f = field_at(type(config), key)
    return None if f is None else f.metadata.get("unset")


def given_fields(config: Any) -> list[str]:
    """The dotted keys of the settings declared with ``unset`` (:func:`param`) that the config gives (not null),
    in declaration order."""
    return [k for k, f in leaves(type(config)) if "unset" in f.metadata and value_at(config, k) is not None]


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


#: A number beyond this size, in a field that declares no bound on that side, is refused: no setting means it, and
#: such values overflow the integer microseconds and counts they become (source.duration_s=1e308).
MAX_MAGNITUDE = 1e9


def check_value(f: dataclasses.Field, value: Any) -> str | None:
    """Why ``value`` is not allowed in config field ``f`` (declared with :func:`param`), or None when it is.

    Numbers (and the numbers of a list) must be finite (unless ``finite=False``; NaN never passes), integers when
    the field is an integer, within the field's declared bounds, and no larger in size than
    :data:`MAX_MAGNITUDE` on a side the field does not bound itself. Booleans, strings and None are left to the
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
    if value == value and value not in (float("inf"), float("-inf")) and (
            (value > MAX_MAGNITUDE and "le" not in bounds and "lt" not in bounds)
            or (value < -MAX_MAGNITUDE and "ge" not in bounds and "gt" not in bounds)):
        return (f"expected {_allowed(meta, integer)}, no larger than {MAX_MAGNITUDE:g} in size (a bound every setting "
                f"without its own has), got {value!r}")
    bad = (value != value  # NaN
           or (meta.get("finite", True) and value in (float("inf"), float("-inf")))
           or (integer and float(value) != int(value))
           or (meta.get("odd") and int(value) % 2 == 0)
           or ("ge" in bounds and not value >= bounds["ge"]) or ("gt" in bounds and not value > bounds["gt"])
           or ("le" in bounds and not value <= bounds["le"]) or ("lt" in bounds and not value < bounds["lt"]))
    if bad:
        return f"expected {_allowed(meta, integer)}, got {value!r}"
    return None


def group(config_class: type, *, help: str, **defaults: Any):
    """A nested group of settings: a field holding a ``config_class`` instance (a dataclass declared with
    :func:`param` fields), built with ``defaults`` changed from that class's (what this stage states differently),
    e.g. ``cor: CorConfig = group(CorConfig, weight=500.0, help="E_cor ...")``."""
    if not dataclasses.is_dataclass(config_class):
        raise TypeError(f"group: expected a dataclass of settings, got {config_class!r}")
    names = {f.name for f in dataclasses.fields(config_class)}
    unknown = sorted(set(defaults) - names)
    if unknown:
        raise TypeError(f"group({config_class.__name__}): no setting named {unknown} (settings: {sorted(names)})")

    def make():
        return config_class(**defaults)

    return field(default_factory=make, metadata={"help": help, "group": config_class})


def is_group(f: dataclasses.Field) -> bool:
    """Whether a config field is a nested group of settings (declared with :func:`group`)."""
    return "group" in f.metadata


def leaves(config_class: type, prefix: str = "") -> Iterator[tuple[str, dataclasses.Field]]:
    """(dotted key, field) of every setting of a config class, groups opened (in declaration order)."""
    for f in dataclasses.fields(config_class):
        if is_group(f):
            yield from leaves(f.metadata["group"], f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def nest(*changes: Mapping[str, Any]) -> dict[str, Any]:
    """Settings given by dotted keys ({"terms.sil.weight": 50}) and nested mappings, merged in order into one nested
    mapping (what a config is built from)."""
    out: dict[str, Any] = {}
    for mapping in changes:
        for key, value in mapping.items():
            *groups, leaf = str(key).split(".")
            d = out
            for g in groups:
                d = d.setdefault(g, {})
            if isinstance(value, Mapping) and isinstance(d.get(leaf), dict):
                d[leaf] = nest(d[leaf], value)
            else:
                d[leaf] = dict(nest(value)) if isinstance(value, Mapping) else value
    return out


def value_at(config: Any, key: str) -> Any:
    """The value of a dotted key in a config instance."""
    for part in key.split("."):
        config = getattr(config, part)
    return config


def field_at(config_class: type, key: str) -> dataclasses.Field | None:
    """The field of a dotted key in a config class (None when there is none)."""
    head, _, rest = key.partition(".")
    f = next((f for f in dataclasses.fields(config_class) if f.name == head), None)
    if f is None or not rest:
        return f
    return field_at(f.metadata["group"], rest) if is_group(f) else None


__all__ = ["allowed_values", "check_value", "field_at", "given_fields", "given_or_unset", "group", "is_group", "leaves",
           "nest", "param", "value_at"]
