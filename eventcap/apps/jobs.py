"""What the apps (``eventcap run``, ``benchmark``, ``report``) share: running one composed config into a run folder,
and writing result files atomically. It lives below all of them so none imports another (cli -> benchmark -> cli
was a cycle)."""

from __future__ import annotations

import csv
import functools
import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger("eventcap")


def run_job(data: dict, run_dir: Path, config_yaml: str, failures: list[str]):
    """Run one composed config into ``run_dir``: the pipeline, then the run outputs (motion files, video).

    Returns ``(runner, result)``, or None when the config was refused before anything ran. Problems are appended to
    ``failures`` (one line each); the caller decides the exit code. Shared by ``eventcap run`` and ``benchmark``.
    """
    from eventcap.core.cache import CacheError
    from eventcap.core.config import ConfigError
    from eventcap.apps.outputs import check_outputs_config, write_run_outputs
    from eventcap.core.pipeline import PipelineError
    from eventcap.core.registry import UnknownStageError
    from eventcap.core.runner import Runner

    try:
        preflight(data)
        runner = Runner(data)
        outputs_cfg = check_outputs_config(runner)
        result = runner.run(run_dir)
    except (PipelineError, ConfigError, UnknownStageError, CacheError, ValueError) as exc:
        log.error("%s", exc)
        failures.append(f"{run_dir}: {exc}")
        return None
    (run_dir / "config.yaml").write_text(config_yaml)
    if result.metrics:
        log.info("metrics: %s", json.dumps(result.metrics, default=str)[:2000])
    written = write_run_outputs(runner, result, run_dir, outputs_cfg)
    if written["problems"]:
        failures.append(f"{run_dir}: outputs: {'; '.join(written['problems'])}")
    if not result.ok:
        from eventcap.core.failures import failure_summary

        msg = failure_summary(result)
        log.error("run incomplete: %s", msg)
        failures.append(f"{run_dir}: {msg}")
    return runner, result


#: The top-level keys of conf/config.yaml (and its groups): any other key given with '+' is refused.
TOP_LEVEL_KEYS = ("name", "cache_dir", "batches", "log_level", "export", "outputs", "pipeline", "source", "executor",
                  "template", "stages", "experiment")


def preflight(data: Mapping[str, Any], overrides: Sequence[str] = ()) -> None:
    """Every check of a composed config that needs no stage to run, writing nothing (no run folder, no cache
    folder): the log level, unknown top-level keys, keys added with '+' that no node reads, the pipeline and each
    node's settings (bounds from the stages' config declarations, and their ``check`` hooks), the executor, the
    batch selection and the outputs. Raises ``ValueError`` (a ConfigError, PipelineError, ...) naming the key.

    ``eventcap run`` calls it from a Hydra callback before the run folder is made (:class:`RefuseBadSettings`), and
    :func:`run_job` again before running (benchmarks and tests call run_job directly)."""
    from types import SimpleNamespace

    from eventcap.apps.outputs import check_outputs_config
    from eventcap.core.config import ConfigError, log_level_number
    from eventcap.core.pipeline import build_pipeline
    from eventcap.core.registry import load_registry, unknown_name_message
    from eventcap.core.runner import ExecutorConfig, _parse_selection

    log_level_number(data.get("log_level", "INFO"))
    for key in data:
        if key not in TOP_LEVEL_KEYS and key != "hydra":
            raise ConfigError(f"{key}: " + unknown_name_message("config key", str(key), list(TOP_LEVEL_KEYS),
                                                               "the top-level config"))
    nodes = build_pipeline(data, load_registry())
    node_paths = [n.config_path for n in nodes]
    for override in overrides:
        if not override.startswith("+") or "=" not in override:
            continue
        key = override.lstrip("+").partition("=")[0]
        if "/" in key or "@" in key:  # a config group added (+stages/signal=...): Hydra checks those
            continue
        parts = key.split(".")
        read = (parts[0] in TOP_LEVEL_KEYS and parts[0] not in ("stages", "pipeline")
                or (parts[0] == "pipeline" and len(parts) > 1 and parts[1] == "nodes")
                or any(key == p or key.startswith(p + ".") for p in node_paths))
        if not read:
            raise ConfigError(f"{key}: added with '+', but nothing reads it: no node of the pipeline takes its config "
                              f"from {key.rpartition('.')[0] or key} (the nodes read: {', '.join(node_paths)})")
    ExecutorConfig.from_mapping(data.get("executor"))
    _parse_selection(data.get("batches"))
    check_outputs_config(SimpleNamespace(cfg=data, by_name={n.name: n for n in nodes}))


try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover - hydra is a dependency
    _HydraCallback = object


class RefuseBadSettings(_HydraCallback):
    """Hydra callback (``hydra.callbacks.settings`` in conf/config.yaml, listed before ``run_folder``): run
    :func:`preflight` on the composed config before the run folder is claimed, so that a refused setting leaves
    nothing on disk. It exits with status 1 and one line naming the key. Sweeps (``-m``) are checked per job, when
    each runs."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        import sys

        from hydra.core.hydra_config import HydraConfig
        from omegaconf import OmegaConf, open_dict

        HydraConfig.instance().set_config(config)  # ${hydra:...} resolves; Hydra sets it again for the job
        overrides = list(config.hydra.overrides.task or [])
        try:
            cfg = OmegaConf.masked_copy(config, [k for k in config if k != "hydra"])
            with open_dict(cfg):
                data = OmegaConf.to_container(cfg, resolve=True)
            data = job_config(cfg, data, overrides, announce=False)[1]
            preflight(data, overrides)
        except Exception as exc:  # noqa: BLE001 - any refusal: one line, nothing written
            if not isinstance(exc, ValueError) and not type(exc).__module__.startswith(("omegaconf", "hydra")):
                raise
            print(f"eventcap run: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(1) from None


def job_config(cfg, data: dict, overrides: Sequence[str], announce: bool = True):
    """The config a job runs: on a recording without intensity frames, when no pipeline was chosen, the one of
    :data:`FRAMELESS_PIPELINE` (the log says why, when ``announce``). Returns (cfg, data)."""
    from hydra import compose
    from omegaconf import OmegaConf

    if any(o.partition("=")[0].lstrip("+~") == "pipeline" for o in overrides):
        return cfg, data
    why = frameless_source(data)
    if why is None:
        return cfg, data
    if announce:
        log.info("%s: running pipeline=%s (images reconstructed from the events stand in for frames; give "
                 "pipeline=... to choose another)", why, FRAMELESS_PIPELINE)
    cfg = compose(config_name="config", overrides=[*overrides, f"pipeline={FRAMELESS_PIPELINE}"])
    return cfg, OmegaConf.to_container(cfg, resolve=True)


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


def write_csv(path: Path, rows: Sequence[Mapping[str, Any]]) -> Path:
    cols = list(dict.fromkeys(k for r in rows for k in r))
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    tmp.replace(path)
    return path


def save_figure(fig, path: Path) -> Path:
    """Write a matplotlib figure to ``path`` atomically (a partial file renamed into place) and close it."""
    import matplotlib.pyplot as plt

    tmp = path.with_name(path.stem + ".partial.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path
