"""Composing a run's config for the apps: the config directory, the default command made to fit a recording, and
Hydra's errors about overrides said as the project's messages (the key, where it lives, what was meant).

Shared by ``eventcap run`` (eventcap.apps.cli) and the settings check before a run folder exists
(eventcap.apps.jobs.RefuseBadSettings); it imports neither.
"""

from __future__ import annotations

import functools
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger("eventcap")


def config_dir() -> Path:
    """The hydra config directory: $EVENTCAP_CONFIG_DIR, else ``conf/`` next to the package (source checkout)."""
    env = os.environ.get("EVENTCAP_CONFIG_DIR")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "conf")
    for c in candidates:
        if (c / "config.yaml").is_file():
            return c.resolve()
    raise SystemExit(
        f"eventcap: no config directory found (looked in {', '.join(str(c) for c in candidates)}); "
        f"set EVENTCAP_CONFIG_DIR to the project's conf/ folder"
    )


def job_config(cfg, data: dict, overrides: Sequence[str], announce: bool = True):
    """The default command on a recording, made to fit it, each change said in the log:

    - without intensity frames, when no pipeline was chosen: pipeline=events_only (images reconstructed from the
      events);
    - without ground truth, when no detector was chosen: stages/detect=blazepose (the default detector, simulated,
      makes its detections from ground truth).

    Returns (cfg, data), composed again when something changed. ``announce``: say the changes in the log (the
    settings check before the run folder exists asks without announcing; the run then says them)."""
    from hydra import compose
    from omegaconf import OmegaConf

    say = log.info if announce else (lambda *a, **k: None)
    chosen = {o.partition("=")[0].lstrip("+~") for o in overrides}
    extra: list[str] = []
    why = None if "pipeline" in chosen else frameless_source(data)
    if why is not None:
        say("%s: running pipeline=%s (images reconstructed from the events stand in for frames; give "
                 "pipeline=... to choose another)", why, FRAMELESS_PIPELINE)
        extra.append(f"pipeline={FRAMELESS_PIPELINE}")
    nodes, why = groundless_detect_nodes(data)
    nodes = [n for n in nodes if not {f"stages/{n}", f"stages.{n}.stage"} & chosen
             and (config_dir() / "stages" / n / f"{REAL_DETECTOR}.yaml").is_file()]
    src = data.get("source") or {}
    simulated = [n for n in ground_truth_detect_nodes(data) if not {f"stages/{n}", f"stages.{n}.stage"} & chosen]
    if simulated and src.get("stage") == "recording" and _holds_ground_truth(src):  # a simulated capture
        say("%s holds the ground truth of a simulated capture: %s detects from it with the simulated detector "
                 "(stages/%s=%s runs a real one on its images)", src.get("path"), simulated[0], simulated[0],
                 REAL_DETECTOR)
    if nodes:
        say("%s: detecting with %s (the default detector is simulated from ground truth; give %s to choose "
                 "another, e.g. stages/%s=file stages.%s.path=<detections made elsewhere>)", why,
                 " ".join(f"stages/{n}={REAL_DETECTOR}" for n in nodes), " ".join(f"stages/{n}=..." for n in nodes),
                 nodes[0], nodes[0])
        extra += [f"stages/{n}={REAL_DETECTOR}" for n in nodes]
    if not extra:
        return cfg, data
    try:
        cfg = compose(config_name="config", overrides=[*overrides, *extra])
    except Exception as exc:  # noqa: BLE001 - a setting of the stage given up (e.g. a key of the simulated detector)
        from eventcap.core.config import ConfigError

        argv = [*overrides, *extra]
        cause = stage_override_message(exc, argv, config_dir()) or unknown_override_message(exc, argv, config_dir()) \
            or typed_override_message(exc, argv) or \
            " ".join(f"{exc}: {exc.__cause__ or ''}".split())
        raise ConfigError(f"the settings given do not fit {' '.join(extra)}, chosen for this recording: {cause}; "
                          f"or choose yourself: {' '.join(e.split('=')[0] + '=...' for e in extra)}") from None
    return cfg, OmegaConf.to_container(cfg, resolve=True)


def _holds_ground_truth(src) -> bool:
    from eventcap.io.readers import recording_has_ground_truth

    path = Path(str(src.get("path") or ""))
    return bool(src.get("path")) and path.exists() and recording_has_ground_truth(path, src.get("format") or None)


#: The pipeline a recording without intensity frames runs when the user chose none (conf/pipeline/events_only.yaml).
FRAMELESS_PIPELINE = "events_only"


def frameless_source(data: Mapping[str, Any]) -> str | None:
    """Why the composed config's source yields no intensity frames (a sentence for the log), or None when it has
    them or cannot tell (then the run says so itself). A synthetic camera without frames (its preset's, or
    source.frames=false), a recording asked to leave its frames out, or a file without any."""
    src = data.get("source") or {}
    stage = src.get("stage")
    if src.get("frames") is False:
        return "source.frames=false: the recording's intensity frames are left out"
    if stage == "synthetic" and src.get("frames") is None and src.get("camera"):
        from eventcap.camera_presets import load_preset

        try:
            preset = load_preset(str(src["camera"]))
        except ValueError:
            return None  # refused with its reason when the source runs
        return None if preset.frames else f"camera {preset.name} ({preset.sensor}) has no intensity frames"
    if stage == "recording" and src.get("path") not in (None, "", "???"):
        try:
            has = _has_frames(str(src["path"]), str(src.get("format") or ""))
        except (OSError, ValueError):
            return None  # the source stage reports what is wrong with the file
        return None if has else f"{src['path']} holds no intensity frames (an event-only recording)"
    return None


#: The detector a recording without ground truth runs when the user chose none (conf/stages/detect/blazepose.yaml).
REAL_DETECTOR = "blazepose"
#: Stages that make their detections from the recording's ground truth (conf/stages/detect/simulated.yaml).
GROUND_TRUTH_DETECTORS = ("simulated",)


def ground_truth_detect_nodes(data: Mapping[str, Any]) -> list[str]:
    """The composed pipeline's nodes that run a detector made from ground truth (the simulated one)."""
    nodes = []
    for name, node in ((data.get("pipeline") or {}).get("nodes") or {}).items():
        where = (node or {}).get("config") or f"stages.{name}"
        cfg: Any = data
        for part in str(where).split("."):
            cfg = cfg.get(part) if isinstance(cfg, Mapping) else None
        if isinstance(cfg, Mapping) and cfg.get("stage") in GROUND_TRUTH_DETECTORS:
            nodes.append(name)
    return nodes


def groundless_detect_nodes(data: Mapping[str, Any]) -> tuple[list[str], str | None]:
    """The pipeline's nodes running a detector made from ground truth (the simulated one) on a source without any,
    and why the source has none (a sentence for the log); ``([], None)`` when the source has ground truth (a
    synthetic capture, a simulated recording in the project's format) or cannot be read (the source stage then
    says what is wrong with it)."""
    src = data.get("source") or {}
    if src.get("stage") != "recording" or src.get("path") in (None, "", "???"):
        return [], None
    from eventcap.io.readers import recording_has_ground_truth

    path = Path(str(src["path"]))
    if not path.exists() or recording_has_ground_truth(path, src.get("format") or None):
        return [], None
    return ground_truth_detect_nodes(data), f"{path} has no ground truth (a recording from a camera, not a " \
                                            f"simulated capture)"
def _has_frames(path: str, fmt: str) -> bool:
    """Whether the recording holds intensity frames, decoded once per file version (the settings check before the
    run and the run itself both ask)."""
    import os

    st = os.stat(path)
    return _has_frames_of(path, fmt, st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=8)
def _has_frames_of(path: str, fmt: str, mtime_ns: int, size: int) -> bool:
    from eventcap.io.readers import recording_has_frames

    return recording_has_frames(path, fmt or None)


def stage_override_message(exc: BaseException, argv: list[str], cdir: str | Path) -> str | None:
    """Hydra's "Could not override" of a node's settings as the project's message, or None for any other error: a
    key (``stages.<x>.<key>``) or a variant (``stages/<x>=...``) of a node the composed pipeline does not have
    names the node that runs what was meant, or says which pipelines have it; a key that moved names its new key."""
    m = re.match(r"Could not override 'stages([./])([^'.@/]+)((?:\.[^'@]*)?)'", str(exc))
    if type(exc).__name__ != "ConfigCompositionException" or m is None:
        return None
    sep, name, rest = m.group(1), m.group(2), m.group(3).lstrip(".")
    nodes, pipeline = _pipeline_nodes(argv, cdir, f"stages{sep}{name}")
    if not nodes:
        return None
    key = f"stages{sep}{name}" + (f".{rest}" if rest else "")
    if name in nodes:  # the node exists: a key that moved?
        from eventcap.core.registry import load_registry

        try:
            spec = load_registry().get(nodes[name])
        except Exception:  # noqa: BLE001 - an unknown stage is reported by the pipeline check
            return None
        new = spec.renamed.get(rest)
        if new is None:
            return None
        return (f"{key}: this setting is now stages.{name}.{new} (stage {spec.name!r}; `eventcap stages {name}` "
                f"lists its settings)")
    runs = [n for n, st in nodes.items() if st == name]
    if runs:
        where = runs[0]
        tail = f".{rest}" if rest else ".<key>"
        try:
            from eventcap.core.registry import load_registry

            tail = f".{load_registry().get(name).renamed.get(rest, rest)}" if rest else tail
        except Exception:  # noqa: BLE001 - the key as given
            pass
        return (f"{key}: the pipeline {pipeline!r} has no node {name!r}; its node {where!r} runs stage {name!r}: "
                f"set stages.{where}{tail} (`eventcap stages {where}` lists its settings)")
    others = _pipelines_with_node(cdir, name)
    has = f"; pipeline={' | '.join(others)} has one" if others else ""
    return (f"{key}: the pipeline {pipeline!r} runs no node {name!r} (its nodes: {', '.join(nodes)}){has}: the "
            f"setting would do nothing")


def _pipeline_nodes(argv: list[str], cdir, failing: str) -> tuple[dict[str, str], str]:
    """The stage of every node of the pipeline composed without the overrides of ``failing`` (a node's key or
    group), and the pipeline's name; ({}, "") when it cannot be composed."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    rest = [a for a in argv if "=" in a and not a.startswith("-")
            and not a.partition("=")[0].lstrip("+~").startswith((failing + ".", failing + "=", failing))]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(cdir), version_base="1.3"):
            cfg = compose(config_name="config", overrides=rest, return_hydra_config=True)
    except Exception:  # noqa: BLE001 - best effort: Hydra's own message then
        return {}, ""
    stages = cfg.get("stages") or {}
    nodes = {str(n): str((stages.get(n) or {}).get("stage", n)) for n in cfg.pipeline.nodes
             if n not in ("template", "source")}
    return nodes, str(cfg.hydra.runtime.choices.get("pipeline", "default"))


def _pipelines_with_node(cdir, name: str) -> list[str]:
    """The pipelines (conf/pipeline/*.yaml) that have a node ``name``."""
    import yaml

    out = []
    for p in sorted((Path(cdir) / "pipeline").glob("*.yaml")):
        d = yaml.safe_load(p.read_text()) or {}
        nodes = (d.get("pipeline", d) or {}).get("nodes") or {}
        if name in nodes:
            out.append(p.stem)
    return out


def unknown_override_message(exc: BaseException, argv: list[str], cdir: str | Path) -> str | None:
    """Hydra's "Could not override 'a.b.c' ... Key 'c' is not in struct" as the project's message, or None for any
    other error: the key, where it lives (the config group's choice and its file) and the closest known keys.

    A stage node's keys are those of its YAML file and of the stage's config dataclass (fields the file does not
    list are still parameters: those are given with '+')."""
    import difflib

    from omegaconf.errors import OmegaConfBaseException

    cause = exc.__cause__
    # a plain node says "Key 'k' is not in struct", a stage's structured node "Key 'k' not in '<Config>Node'"
    if not (type(exc).__name__ == "ConfigCompositionException" and str(exc).startswith("Could not override")
            and isinstance(cause, OmegaConfBaseException)
            and ("is not in struct" in str(cause) or re.search(r"Key '[^']*' not in '", str(cause)))):
        return None
    key = str(getattr(cause, "key", "") or "")
    full_key = str(getattr(cause, "full_key", "") or key)
    if not key:
        return None
    parent = full_key.rpartition(".")[0]
    override_key = str(exc).split("'")[1] if str(exc).count("'") >= 2 else full_key
    known, stage_fields, stage_name, where_file = _known_keys(parent, override_key, argv, cdir)
    from eventcap.core.registry import unknown_name_message

    where = (parent or "the top-level config") + (f" ({where_file})" if where_file else "")
    if key in stage_fields:
        value = next((a.partition("=")[2] for a in argv if a.partition("=")[0].lstrip("+") == override_key), "...")
        return (f"{full_key}: a parameter of stage {stage_name!r} that {where_file or parent} does not list; give it "
                f"with a '+': +{override_key}={value}")
    available = sorted(set(known) | set(stage_fields))
    msg = f"{full_key}: " + unknown_name_message("config key", key, available, where)
    if not difflib.get_close_matches(key, available, n=1, cutoff=0.6) and parent:
        msg += f". To add a new key anyway: +{override_key}=..."
    return msg


def typed_override_message(exc: BaseException, argv: list[str]) -> str | None:
    """Hydra's "Error merging override k=v ... could not be converted" for a stage's key as the project's message
    (what the key takes, as eventcap.core.stage.allowed_values says it), or None for any other error."""
    import dataclasses

    from omegaconf.errors import ValidationError

    cause = exc.__cause__
    if not (type(exc).__name__ == "ConfigCompositionException" and isinstance(cause, ValidationError)):
        return None
    full_key = str(getattr(cause, "full_key", "") or "")
    node_type = getattr(getattr(cause, "object_type", None), "__name__", "")
    if not (full_key and node_type.endswith("Node")):
        return None
    from eventcap.core.registry import load_registry
    from eventcap.core.stage import allowed_values

    key = full_key.rpartition(".")[2]
    for spec in load_registry().specs():
        if spec.config.__name__ == node_type[:-len("Node")]:
            field = next((f for f in dataclasses.fields(spec.config) if f.name == key), None)
            allowed = allowed_values(field) if field is not None else None
            if allowed:
                value = next((a.partition("=")[2] for a in argv if a.partition("=")[0].lstrip("+") == full_key),
                             "?")
                return f"{full_key}: expected {allowed}, got {value!r} (stage {spec.name!r})"
    return None


def _known_keys(parent: str, override_key: str, argv: list[str], cdir) -> tuple[list[str], list[str], str, str]:
    """Keys at ``parent`` of the config composed without the failing override, the stage's config fields when
    ``parent`` is a stage node's config, that stage's name, and the file (config group choice) ``parent`` comes
    from. Best effort: whatever cannot be composed is left empty."""
    import dataclasses

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    rest = [a for a in argv if "=" in a and not a.startswith("-") and a.partition("=")[0].lstrip("+~") != override_key]
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()  # a failed hydra.main may leave it initialised
    cfg = None
    for overrides in (rest, [a for a in rest if not a.startswith("hydra.") or a.startswith("hydra.searchpath")], []):
        try:
            with initialize_config_dir(config_dir=str(cdir), version_base="1.3"):
                cfg = compose(config_name="config", overrides=overrides, return_hydra_config=True)
            break
        except Exception:  # noqa: BLE001 - e.g. sweep values (a=1,2): fall back to the defaults
            continue
    if cfg is None:
        return [], [], "", ""
    node = OmegaConf.select(cfg, parent) if parent else cfg
    known = [str(k) for k in node.keys() if str(k) != "hydra"] if OmegaConf.is_dict(node) else []
    choices = dict(cfg.hydra.runtime.choices)
    where_file = str(Path(cdir) / "config.yaml")
    parts = parent.split(".") if parent else []
    for n in range(len(parts), 0, -1):
        group = "/".join(parts[:n])
        if choices.get(group):
            where_file = f"config group {group}={choices[group]}: {Path(cdir) / group / choices[group]}.yaml"
            break
    stage_fields: list[str] = []
    stage_name = ""
    if OmegaConf.is_dict(node) and "stage" in node:
        try:
            from eventcap.core.registry import load_registry

            spec = load_registry().get(str(node["stage"]))
            stage_fields, stage_name = [f.name for f in dataclasses.fields(spec.config)], spec.name
        except Exception:  # noqa: BLE001 - an unknown stage is reported by the run itself
            pass
    return known, stage_fields, stage_name, where_file


#: Top-level keys and config groups of conf/config.yaml: a bare ``key=value`` naming one of them is never a source's.
