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

    from eventcap.core.config import log_level_number

    try:
        log_level_number(data.get("log_level", "INFO"))
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
        from eventcap.io.readers import recording_has_frames

        try:
            has = recording_has_frames(src["path"], src.get("format") or None)
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
