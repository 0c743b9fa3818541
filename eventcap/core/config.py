"""Turning a node's config mapping into the stage's typed config dataclass, and back into cache-key material."""

from __future__ import annotations

import dataclasses
import difflib
import functools
import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from eventcap.core.registry import unknown_name_message
from eventcap.core.stage import StageSpec, allowed_values, check_value, given_fields


class ConfigError(ValueError):
    """A config key or value is wrong; the message names the full key and what was expected."""


@functools.lru_cache(maxsize=128)
def _structured(config_class: type):
    """The config class as an OmegaConf schema, built once (merge copies it, never changes it)."""
    return OmegaConf.structured(config_class)


def build_config(spec: StageSpec, values: Mapping[str, Any], where: str) -> Any:
    """The stage's config dataclass from ``values`` (a plain mapping); unknown keys and wrong types name ``where.key``."""
    known = [f.name for f in dataclasses.fields(spec.config)]
    for key in values:
        if key not in known:
            raise ConfigError(
                f"{where}.{key}: " + unknown_name_message("config key", key, known, f"the config of stage {spec.name!r}")
            )
    try:
        merged = OmegaConf.merge(_structured(spec.config), OmegaConf.create(dict(values)))
        obj = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", "") or ""
        msg = str(exc).splitlines()[0]
        field = next((f for f in dataclasses.fields(spec.config) if f.name == key.split(".")[0].split("[")[0]), None)
        allowed = allowed_values(field) if field is not None else None
        if allowed:  # a value of the wrong type: say what the field takes (the field, not an item of a list)
            msg = f"expected {allowed}, got {values.get(field.name)!r}"
            key = field.name
        raise ConfigError(f"{where}{'.' + key if key else ''}: {msg} (stage {spec.name!r})") from None
    missing = [f.name for f in dataclasses.fields(obj) if getattr(obj, f.name) is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{where}.{missing[0]}: required by stage {spec.name!r} but not set")
    _check_fields(obj, where, spec.name)
    return obj


def _check_fields(obj: Any, where: str, stage: str) -> None:
    """Choices and bounds of every field of ``obj``, and of the fields of its nested groups (``where.group.key``)."""
    for f in dataclasses.fields(obj):
        choices = f.metadata.get("choices")
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            _check_fields(value, f"{where}.{f.name}", stage)
            continue
        if choices is not None and value not in choices:
            close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"{where}.{f.name}: expected one of {' | '.join(str(c) for c in choices)}, got "
                              f"{value!r} (stage {stage!r}){hint}")
        problem = check_value(f, value)
        if problem:
            raise ConfigError(f"{where}.{f.name}: {problem} (stage {stage!r})")


#: The values ``log_level`` takes (case-insensitive).
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def log_level_number(value: Any) -> int:
    """The logging level of the top-level ``log_level`` setting, or a ConfigError naming the key and the levels."""
    import logging

    name = str(value).upper() if isinstance(value, str) else None
    if name not in LOG_LEVELS:
        raise ConfigError(f"log_level: expected one of {' | '.join(LOG_LEVELS)}, got {value!r}")
    return getattr(logging, name)


#: The Hydra config group holding every installed stage's config (``/stage/<name>``), filled by
#: :func:`register_stage_configs`: a stage variant's YAML (conf/stages/<node>/<variant>.yaml) starts from it with
#: ``defaults: [/stage/<name>@_here_, _self_]`` and states only what differs.
STAGE_GROUP = "stage"


def register_stage_configs() -> list[str]:
    """Store every installed stage's config dataclass (plus its ``stage`` key) in Hydra's ConfigStore under
    ``/stage/<name>`` (the Hydra plugin hydra_plugins/eventcap_stage_configs does so before every composition): the stage's spec is the one place its defaults are stated, and a
    composed config still holds every key (``eventcap run --cfg job`` shows them, a run's config.yaml records
    them, and an override ``stages.<node>.<key>=...`` needs no '+'). Returns the registered names."""
    from hydra.core.config_store import ConfigStore

    from eventcap.core.registry import load_registry

    cs = ConfigStore.instance()
    names = []
    for spec in load_registry().specs():
        node = dataclasses.make_dataclass(
            f"{spec.config.__name__}Node", [("stage", str, dataclasses.field(default=spec.name))],
            bases=(spec.config,))
        cs.store(group=STAGE_GROUP, name=spec.name, node=node, provider="eventcap")
        names.append(spec.name)
    return names


def config_to_dict(config: Any) -> dict[str, Any]:
    """All fields as plain JSON-able values."""
    return {k: _plain(v) for k, v in dataclasses.asdict(config).items()}


def _plain(v):
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, Path):
        return str(v)
    if hasattr(v, "value") and hasattr(v, "name") and type(v).__class__.__name__ == "EnumMeta":
        return v.name
    return v


def result_config(spec: StageSpec, config: Any) -> dict[str, Any]:
    """Only the fields that affect the stage's result: what goes into the cache key. A nested group whose every
    value is null (unset, e.g. ``source.actor``) is left out, so adding such a group keeps the keys of the results
    made before it existed."""
    full = config_to_dict(config)
    out: dict[str, Any] = {}
    meta = {f.name: f.metadata for f in dataclasses.fields(config)}
    for k in spec.result_fields():
        if _unset_group(getattr(config, k)):
            continue
        out[k] = _plain(meta[k]["unset"]) if "unset" in meta[k] and full[k] is None else full[k]
    given = given_fields(config)
    if given:  # what the user stated changes the result even where it equals the unset value
        out["given"] = given
    return out


def _unset_group(value: Any) -> bool:
    return (dataclasses.is_dataclass(value) and not isinstance(value, type)
            and all(getattr(value, f.name) is None for f in dataclasses.fields(value)))


def file_digest(path: str | Path, chunk: int = 1 << 22) -> str:
    """Content digest of a file or a directory tree (sorted relative paths + contents); mtimes never matter."""
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        for f in sorted(q for q in p.rglob("*") if q.is_file()):
            h.update(str(f.relative_to(p)).encode() + b"\0")
            h.update(file_digest(f).encode())
        return h.hexdigest()
    if not p.is_file():
        raise ConfigError(f"file not found: {p}")
    with open(p, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def file_digests(spec: StageSpec, config: Any, where: str) -> dict[str, str]:
    """Digest of every file config field that is set (empty string / None means unused): ``file=True`` fields by
    their path, ``file=<function>`` fields by the paths the function finds in the value (none: no entry)."""
    out = {}
    kinds = {f.name: f.metadata.get("file") for f in dataclasses.fields(config)}
    for name in spec.file_fields():
        value = getattr(config, name)
        if value in (None, ""):
            continue
        paths = [value] if kinds.get(name) is True else list(kinds[name](value))
        try:
            digests = [file_digest(p) for p in paths]
        except ConfigError as exc:
            raise ConfigError(f"{where}.{name}: {exc}") from None
        if kinds.get(name) is True:
            out[name] = digests[0]
        elif digests:  # several files or a value that only sometimes names one: one digest of all, in order
            out[name] = hashlib.sha256("".join(digests).encode()).hexdigest()
    return out
