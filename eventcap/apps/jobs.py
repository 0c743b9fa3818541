"""What the apps (``eventcap run``, ``benchmark``, ``report``) share: running one composed config into a run folder,
and writing result files atomically. It lives below all of them so none imports another (cli -> benchmark -> cli
was a cycle)."""

from __future__ import annotations

import csv
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
    written = write_run_outputs(runner, result, run_dir, outputs_cfg)
    if result.metrics:
        log.info("%s", metrics_table(result.metrics))
    if written["problems"]:
        failures.append(f"{run_dir}: outputs: {'; '.join(written['problems'])}")
    if not result.ok:
        from eventcap.core.failures import failure_summary

        # the log showed each failure where it happened; the summary counts them (run.json keeps them in full)
        log.error("run incomplete: %s", failure_summary(result, first_error=False))
        failures.append(f"{run_dir}: {failure_summary(result)}")
    log.info("%s", run_folder_line(run_dir))
    return runner, result


#: The metrics a run's log and ``eventcap report`` show first: (title, dotted key into the evaluate stage's metrics).
HEADLINE_METRICS = (("AE (mm)", "AE_mm"), ("STD (mm)", "STD_mm"), ("AE.raw (mm)", "AE_raw_mm"),
                    ("AE.nonRaw (mm)", "AE_nonRaw_mm"), ("AE.rootrel (mm)", "AE_rootrel_mm"),
                    ("MPJVE (mm/s)", "MPJVE_mm_s"), ("Acc.err (m/s²)", "accel_err_m_s2"),
                    ("peak speed err", "peak_speed_err"), ("MB/s", "data_rate.total_MBps"))


def _dotted(d: Any, key: str) -> Any:
    for part in key.split("."):
        d = d.get(part) if isinstance(d, Mapping) else None
    return d


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def metrics_table(metrics: Mapping[str, Any], per_row: int = 2) -> str:
    """A run's metrics as a short table for the log: per metrics output, the :data:`HEADLINE_METRICS` it has (or
    else its first top-level numbers), ``per_row`` pairs a row, and its reason when it measured no joint error.
    Every value stays in ``metrics.json``."""
    lines = []
    for name, values in metrics.items():
        if not isinstance(values, Mapping):
            continue
        pairs = [(title, _dotted(values, key)) for title, key in HEADLINE_METRICS if _number(_dotted(values, key))]
        pairs = pairs or [(str(k), v) for k, v in values.items() if _number(v)][:12]
        lines.append(f"metrics of {name} (every value: metrics.json)" +
                     (f": {values['reason']}" if isinstance(values.get("reason"), str) else ""))
        cells = [(t, str(v) if isinstance(v, int) else f"{v:#.4g}") for t, v in pairs]
        width_t = max((len(t) for t, _ in cells), default=0)
        width_v = max((len(v) for _, v in cells), default=0)
        for i in range(0, len(cells), per_row):
            lines.append("  " + "    ".join(f"{t:<{width_t}} {v:>{width_v}}" for t, v in cells[i:i + per_row]))
    return "\n".join(lines)


def run_folder_line(run_dir: Path) -> str:
    """The line a run ends with: where its folder is (relative to the current folder when inside it) and what is in
    it, folders marked with a '/'."""
    run_dir = Path(run_dir)
    try:
        shown = run_dir.resolve().relative_to(Path.cwd().resolve())
    except ValueError:
        shown = run_dir
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in run_dir.iterdir() if not p.name.startswith("."))
    return f"run folder {shown}/: {', '.join(names) or 'empty'}"
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
    check_places(data)
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


def check_places(data: Mapping[str, Any]) -> None:
    """The settings that say where a run writes, checked writing nothing: ``name`` (a folder name inside the runs
    folder: no ``..``, not absolute) and ``cache_dir`` (a cache of the tool's, or a new or empty folder; never a
    system folder: eventcap.core.cache.check_cache_root). ConfigError naming the key."""
    from pathlib import PurePath

    from eventcap.core.cache import CacheError, check_cache_root
    from eventcap.core.config import ConfigError

    name = data.get("name")
    if name is not None:
        parts = PurePath(str(name)).parts
        if (not str(name).strip() or PurePath(str(name)).is_absolute() or any(p in ("..", ".") for p in parts)
                or "\x00" in str(name)):
            raise ConfigError(f"name={name!r}: expected the experiment's folder name inside runs/ (letters, digits, "
                              f"'-', '_'; a/b nests), not an absolute path or one with '..': runs go to "
                              f"runs/<name>/<timestamp>/ (hydra.run.dir= gives another folder)")
    try:
        check_cache_root(data.get("cache_dir") or "runs/cache")
    except CacheError as exc:
        raise ConfigError(str(exc)) from None


try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover - hydra is a dependency
    _HydraCallback = object


class RefuseBadSettings(_HydraCallback):
    """Hydra callback (``hydra.callbacks.settings`` in conf/config.yaml, listed before ``run_folder``): run
    :func:`preflight` on the composed config before the run folder is claimed, so that a refused setting leaves
    nothing on disk. It exits with status 1 and one line naming the key. Sweeps (``-m``) are checked per job, when
    each runs, and as a whole for where they write (``name``, ``cache_dir``: :func:`check_places`) before the sweep
    folder is made."""

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        import sys

        from omegaconf import OmegaConf

        try:
            check_places({k: OmegaConf.select(config, k) for k in ("name", "cache_dir")})
        except ValueError as exc:
            print(f"eventcap run: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(1) from None

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
            from eventcap.apps.compose import job_config

            data = job_config(cfg, data, overrides, announce=False)[1]
            preflight(data, overrides)
        except Exception as exc:  # noqa: BLE001 - any refusal: one line, nothing written
            if not isinstance(exc, ValueError) and not type(exc).__module__.startswith(("omegaconf", "hydra")):
                raise
            print(f"eventcap run: {exc}", file=sys.stderr, flush=True)
            raise SystemExit(1) from None


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
