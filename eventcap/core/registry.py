"""Stage discovery: the ``eventcap.stages`` entry-point group, plus ``EVENTCAP_STAGES`` for development.

An entry point's value is ``module:attribute`` where the attribute is a StageSpec, a list of them, or a zero-argument
callable returning either. The spec module must be light: it declares, it does not import heavy implementations.

``EVENTCAP_STAGES`` (entries separated by ``,``) adds stages without installing a package: each entry
is ``module:attribute`` or ``/path/to/file.py:attribute``. Stages from it override installed ones of the same name
(with a warning), so a developer can try a changed stage.

A package's Hydra configs (its pipelines, its stages' variants) are found the same way: the ``eventcap.configs``
entry-point group names a package whose folder is laid out as the project's ``conf/`` (``pipeline/<name>.yaml``,
``stages/<node>/<variant>.yaml``); :func:`plugin_config_dirs` lists them and the Hydra plugin
``hydra_plugins/eventcap_stage_configs`` puts each on Hydra's search path, after the project's own ``conf/`` (whose
configs win over a plugin's of the same name). Finding them imports the package's parents only, not its stages.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import sys
from collections.abc import Iterable
from dataclasses import replace
from importlib.metadata import entry_points
from pathlib import Path

from eventcap.names import unknown_name_message
from eventcap.core.stage import StageSpec, StageSpecError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "eventcap.stages"
ENV_VAR = "EVENTCAP_STAGES"
CONFIG_GROUP = "eventcap.configs"


class UnknownStageError(KeyError):
    """No installed stage has the requested name."""

    def __str__(self) -> str:  # KeyError quotes its argument; show the message as written
        return str(self.args[0])


class Registry:
    """The installed stages, by name. Build with :func:`load_registry`."""

    def __init__(self, specs: Iterable[StageSpec], problems: Iterable[str] = ()):
        self._specs: dict[str, StageSpec] = {}
        for spec in specs:
            self._specs[spec.name] = spec
        self.problems = list(problems)

    def __contains__(self, name: str) -> bool:
        return name in self._specs

    def names(self) -> list[str]:
        return sorted(self._specs)

    def specs(self) -> list[StageSpec]:
        return [self._specs[n] for n in self.names()]

    def get(self, name: str, *, kind: str | None = None) -> StageSpec:
        spec = self._specs.get(name)
        if spec is None:
            raise UnknownStageError(unknown_name_message("stage", name, self.names(), f"entry-point group {ENTRY_POINT_GROUP!r}"))
        if kind is not None and spec.kind != kind:
            same = [s.name for s in self.specs() if s.kind == kind]
            raise UnknownStageError(f"stage {name!r} is a {spec.kind!r} stage, not {kind!r}; {kind} stages: {', '.join(same) or 'none'}")
        return spec


def _as_specs(obj, origin: str) -> list[StageSpec]:
    if callable(obj) and not isinstance(obj, StageSpec):
        obj = obj()
    items = list(obj) if isinstance(obj, (list, tuple)) else [obj]
    out = []
    for item in items:
        if not isinstance(item, StageSpec):
            raise StageSpecError(f"{origin}: expected a StageSpec (or a list of them), got {type(item).__name__}")
        out.append(replace(item, origin=origin))
    return out


def _load_env_entry(entry: str) -> object:
    target, sep, attr = entry.rpartition(":")
    if not sep or not target or not attr:
        raise StageSpecError(f"{ENV_VAR} entry {entry!r}: expected 'module:attribute' or '/path/file.py:attribute'")
    if target.endswith(".py"):
        path = Path(target).resolve()
        if not path.is_file():
            raise StageSpecError(f"{ENV_VAR} entry {entry!r}: file {path} does not exist")
        modname = f"_eventcap_dev_{path.stem}_{abs(hash(str(path))) % 10**8}"
        if modname not in sys.modules:
            spec = importlib.util.spec_from_file_location(modname, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[modname] = module
            spec.loader.exec_module(module)
        module = sys.modules[modname]
    else:
        module = importlib.import_module(target)
    try:
        return getattr(module, attr)
    except AttributeError:
        raise StageSpecError(f"{ENV_VAR} entry {entry!r}: module has no attribute {attr!r}") from None


def load_registry(strict: bool = False) -> Registry:
    """Find every stage. A plugin that fails to load is reported (``registry.problems``), not fatal, unless strict."""
    specs: dict[str, StageSpec] = {}
    problems: list[str] = []

    def add(found: list[StageSpec], override: bool) -> None:
        for spec in found:
            if spec.name in specs and specs[spec.name].origin != spec.origin:
                if not override:
                    problems.append(
                        f"stage name {spec.name!r} is provided twice: by {specs[spec.name].origin} and {spec.origin}; "
                        f"keeping the first"
                    )
                    continue
                log.warning("stage %r from %s overrides %s (%s)", spec.name, spec.origin, specs[spec.name].origin, ENV_VAR)
            specs[spec.name] = spec

    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        origin = f"entry point {ep.name} = {ep.value}" + (f" [{ep.dist.name}]" if ep.dist else "")
        try:
            found = _as_specs(ep.load(), origin)
        except Exception as exc:  # a broken plugin must not hide the others
            problems.append(f"{origin}: failed to load: {type(exc).__name__}: {exc}")
            continue
        mismatch = [s.name for s in found if len(found) == 1 and s.name != ep.name]
        if mismatch:
            problems.append(f"{origin}: entry point name {ep.name!r} differs from the spec's name {mismatch[0]!r}")
        add(found, override=False)

    raw = os.environ.get(ENV_VAR, "")
    for entry in [e.strip() for e in raw.split(",")]:
        if not entry:
            continue
        try:
            add(_as_specs(_load_env_entry(entry), f"{ENV_VAR} {entry}"), override=True)
        except Exception as exc:
            problems.append(f"{ENV_VAR} entry {entry!r}: failed to load: {type(exc).__name__}: {exc}")

    if strict and problems:
        raise StageSpecError("problems while discovering stages:\n  " + "\n  ".join(problems))
    for p in problems:
        log.warning("%s", p)
    return Registry(specs.values(), problems)


def plugin_config_dirs() -> list[tuple[str, Path]]:
    """(provider, folder) of every ``eventcap.configs`` entry point (module doc), by entry-point name: the folder of
    the package its value names (``my_pkg.conf``). One that names no package, or a file, is reported as a warning
    and left out; the others still count."""
    out = []
    for ep in sorted(entry_points(group=CONFIG_GROUP), key=lambda e: e.name):
        origin = f"entry point {ep.name} = {ep.value} (group {CONFIG_GROUP})" + (f" [{ep.dist.name}]" if ep.dist else "")
        try:
            spec = importlib.util.find_spec(ep.value)
        except (ImportError, ValueError) as exc:
            spec, why = None, f"{type(exc).__name__}: {exc}"
        else:
            why = "no such package"
        folders = list(spec.submodule_search_locations or []) if spec is not None else []
        if not folders:
            log.warning("%s: %s; expected a package whose folder holds config groups (pipeline/, stages/<node>/)",
                        origin, why if spec is None else "a module, not a package")
            continue
        out.append((ep.dist.name if ep.dist else ep.name, Path(folders[0])))
    return out
