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
from eventcap.core.stage import StageSpec
from eventcap.params import allowed_values, check_value, field_at, given_fields, is_group, leaves, value_at


class ConfigError(ValueError):
    """A config key or value is wrong; the message names the full key and what was expected."""


@functools.lru_cache(maxsize=128)
def _structured(config_class: type):
    """The config class as an OmegaConf schema, built once (merge copies it, never changes it)."""
    return OmegaConf.structured(config_class)


def build_config(spec: StageSpec, values: Mapping[str, Any], where: str) -> Any:
    """The stage's config dataclass from ``values`` (a plain mapping, groups as nested mappings); an unknown key, a
    renamed one (named with its new key) and a wrong type or value name ``where.<dotted key>``."""
    return build_settings(spec.config, values, where, spec.renamed, f"stage {spec.name!r}")


def build_settings(config_class: type, values: Mapping[str, Any] | None, where: str,
                   renamed: Mapping[str, str] | None = None, owner: str = "") -> Any:
    """An instance of a dataclass of declared settings (:mod:`eventcap.params`) from ``values``: every key known
    (a renamed one refused with its new key), every value of the field's type, within its choices and bounds; each
    error names ``where.<dotted key>`` and the owner (e.g. "stage 'spline'")."""
    values = dict(values or {})
    renamed = dict(renamed or {})
    tag = f" ({owner})" if owner else ""
    _check_keys(config_class, values, where, "", renamed, owner)
    try:
        merged = OmegaConf.merge(_structured(config_class), OmegaConf.create(values))
        obj = OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", "") or ""
        msg = str(exc).splitlines()[0]
        path = ".".join(p.split("[")[0] for p in key.split("."))
        field = field_at(config_class, path) if path else None
        allowed = allowed_values(field) if field is not None else None
        if allowed:  # a value of the wrong type: say what the field takes (the field, not an item of a list)
            msg = f"expected {allowed}, got {_value_in(values, path)!r}"
            key = path
        raise ConfigError(f"{where}{'.' + key if key else ''}: {msg}{tag}") from None
    for key, f in leaves(config_class):
        value = value_at(obj, key)
        if value is dataclasses.MISSING:
            raise ConfigError(f"{where}.{key}: required{' by ' + owner if owner else ''} but not set")
        choices = f.metadata.get("choices")
        if choices is not None and value not in choices:
            close = difflib.get_close_matches(str(value), [str(c) for c in choices], n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(f"{where}.{key}: expected one of {' | '.join(str(c) for c in choices)}, got "
                              f"{value!r}{tag}{hint}")
        problem = check_value(f, value)
        if problem:
            raise ConfigError(f"{where}.{key}: {problem}{tag}")
    return obj


def _check_keys(config_class: type, values: Mapping[str, Any], where: str, prefix: str,
                renamed: Mapping[str, str], owner: str) -> None:
    """ConfigError for the first key of ``values`` that the config class (a group at ``prefix``) has not: a renamed
    one names its new key, others the close matches among the group's keys."""
    fields = {f.name: f for f in dataclasses.fields(config_class)}
    tag = f" ({owner})" if owner else ""
    for key, value in values.items():
        full = f"{prefix}{key}"
        f = fields.get(str(key))
        if f is None:
            new = renamed.get(full)
            if new is not None:
                raise ConfigError(f"{where}.{full}: this setting is now {where}.{new}{tag}")
            what = (f"the config of {owner}" if owner else where) + (f", group {prefix[:-1]}" if prefix else "")
            raise ConfigError(f"{where}.{full}: " + unknown_name_message("config key", str(key), list(fields), what))
        if is_group(f):
            if not isinstance(value, Mapping) and full in renamed:  # an old setting now a group's name
                raise ConfigError(f"{where}.{full}: this setting is now {where}.{renamed[full]}{tag}")
            if not isinstance(value, Mapping):
                raise ConfigError(f"{where}.{full}: a group of settings ({', '.join(sorted(_names(f)))}); set one "
                                  f"with {where}.{full}.<key>=..., got {value!r}{tag}")
            _check_keys(f.metadata["group"], value, where, f"{full}.", renamed, owner)


def _names(f: dataclasses.Field) -> list[str]:
    return [g.name for g in dataclasses.fields(f.metadata["group"])]


def _value_in(values: Mapping[str, Any], key: str) -> Any:
    for part in key.split("."):
        if not isinstance(values, Mapping) or part not in values:
            return None
        values = values[part]
    return values


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


#: The Hydra config group holding the declared settings of the run's other parts (``/settings/<name>``: outputs,
#: executor), filled by :func:`register_settings_configs`.
SETTINGS_GROUP = "settings"


def register_settings_configs(configs: Mapping[str, type]) -> list[str]:
    """Store dataclasses of declared settings in Hydra's ConfigStore under ``/settings/<name>`` (the Hydra plugin
    does so before every composition): ``conf/config.yaml`` starts the ``outputs`` block from it and the executor
    variants start from ``/settings/executor``, stating only what differs."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    for name, cls in configs.items():
        cs.store(group=SETTINGS_GROUP, name=name, node=cls, provider="eventcap")
    return list(configs)


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
    """Only the settings that affect the stage's result (dotted keys): what goes into the cache key. A group whose
    every setting is null (unset, e.g. ``source.actor``) is left out, so adding such a group keeps the keys of the
    results made before it existed; a null setting declared with ``unset`` enters as that value, and the keys of the
    given ones are added (``given``): what the user stated changes the result even where it equals the unset value."""
    out: dict[str, Any] = {}
    for k in spec.result_fields():
        head = k.rpartition(".")[0]
        if head and _unset_group(value_at(config, head)):
            continue
        value = value_at(config, k)
        meta = field_at(type(config), k).metadata
        out[k] = _plain(meta["unset"] if value is None and "unset" in meta else value)
    given = given_fields(config)
    if given:
        out["given"] = given
    return out


def _unset_group(value: Any) -> bool:
    """Whether ``value`` is a group of settings whose every setting (nested groups opened) is null."""
    return (dataclasses.is_dataclass(value) and not isinstance(value, type)
            and all(value_at(value, k) is None for k, _ in leaves(type(value))))


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


def input_path_problem(path: str | Path) -> str | None:
    """Why ``path``, named by a setting that takes a file or folder to read, cannot be one (one ``stat``, nothing
    opened): missing, a dangling or looping link, a pipe, device or socket (opening one can wait forever), or a
    path under the kernel's folders (/proc, /sys, /dev) or the system's configuration (/etc, /boot). None when it
    is a regular file or a folder."""
    import errno
    import os
    import stat

    from eventcap.core.ownership import PRIVATE_SYSTEM_FOLDERS, PSEUDO_FILESYSTEMS, real

    p = real(path)
    for roots, what in ((PSEUDO_FILESYSTEMS, "a folder of the kernel"),
                        (PRIVATE_SYSTEM_FOLDERS, "the system's configuration (passwords, keys)")):
        for root in roots:
            if p == Path(root) or Path(root) in p.parents:
                return f"{path} is under {root}, {what}, not a file of yours: refused without reading it"
    try:
        st = os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return f"{path}: a loop of symbolic links"
        if exc.errno == errno.ENOENT:
            return (f"{path}: no such file or folder" + (f" (a link to {os.readlink(path)}, which does not exist)"
                    if os.path.islink(path) else f" (relative paths start at {Path.cwd()})"))
        return f"{path}: cannot read it ({exc.strerror or exc})"
    if stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode):
        return None
    kind = ("a named pipe (FIFO)" if stat.S_ISFIFO(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode)
            or stat.S_ISBLK(st.st_mode) else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
    return f"{path} is {kind}, not a file to read: refused without opening it"


def check_file_settings(spec: StageSpec, config: Any, where: str) -> None:
    """Every file setting that is set names a file or folder that exists and can be read (:func:`input_path_problem`),
    checked with ``stat`` before anything runs (and before the run folder exists); ConfigError naming
    ``where.<key>``. What the file holds is checked by the stage's ``check`` hook where the stage can tell cheaply
    (a calibration file, a motion's clip), else when it is read."""
    kinds = {k: f.metadata.get("file") for k, f in leaves(type(config))}
    for name in spec.file_fields():
        value = value_at(config, name)
        if value in (None, ""):
            continue
        paths = [value] if kinds.get(name) is True else list(kinds[name](value))
        for path in paths:
            problem = input_path_problem(path)
            if problem:
                raise ConfigError(f"{where}.{name}: {problem}")


def file_digests(spec: StageSpec, config: Any, where: str) -> dict[str, str]:
    """Digest of every file config field that is set (empty string / None means unused): ``file=True`` fields by
    their path, ``file=<function>`` fields by the paths the function finds in the value (none: no entry)."""
    out = {}
    kinds = {k: f.metadata.get("file") for k, f in leaves(type(config))}
    for name in spec.file_fields():
        value = value_at(config, name)
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
