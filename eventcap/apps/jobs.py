"""What the apps (``eventcap run``, ``benchmark``, ``report``) share: running one composed config into a run folder,
and writing result files atomically. It lives below all of them so none imports another (cli -> benchmark -> cli
was a cycle)."""

from __future__ import annotations

import csv
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
