"""``eventcap report RUNS_DIR``: one table of the jobs of a sweep (``eventcap run -m a=1,2 b=x,y``).

A job is a folder under RUNS_DIR holding ``run.json`` (or a ``.hydra/overrides.yaml`` of a job that was refused
before it ran). What sets a job apart is read from ``.hydra/overrides.yaml`` (Hydra's record of the job's command
line overrides) when every job has one, otherwise from the differences between the jobs' ``config.yaml``; the
columns are the keys whose values differ between jobs (keys under ``hydra`` are left out; those equal in every job
are printed once above the table). Jobs with the same override set (the same sweep run twice) make one row, their
metrics averaged (column ``jobs``). Metrics come from each job's ``metrics.json`` (the evaluate stage's Table-1
measures and its motion detail by default: AE of root-relative joints, MPJVE, acceleration error, and the median
relative error of the end effectors' peak speed per batch as a fraction).

Writes ``report.csv`` and ``report.png`` (AE ± STD per row; a line over the swept value when exactly one numeric key
varies) into RUNS_DIR (or ``--out``) and prints the table.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from eventcap.apps.jobs import HEADLINE_METRICS, save_figure, write_csv
from eventcap.core.runrecord import RUN_JSON, RunRecord

log = logging.getLogger("eventcap.apps.report")

#: (column title, dotted key into the metrics of the chosen node): those a run's log shows
DEFAULT_COLUMNS = HEADLINE_METRICS


class ReportError(ValueError):
    pass


@dataclass
class Job:
    path: Path
    overrides: list[str] | None
    config: dict[str, Any]
    run: RunRecord | None
    metrics: dict[str, Any]
    values: dict[str, str] = field(default_factory=dict)  # the varying keys -> value (filled by group)

    @property
    def status(self) -> str:
        if self.run is None:
            return "not run"
        return "ok" if self.run.ok else "incomplete"


def _flatten(d: Any, prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    if isinstance(d, Mapping):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        if not d and prefix:
            out[prefix[:-1]] = "{}"
    else:
        out[prefix[:-1]] = d if isinstance(d, str) else json.dumps(d)
    return out


def _load_yaml(path: Path) -> Any:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(OmegaConf.load(path), resolve=False)


def find_jobs(root: Path) -> list[Job]:
    root = Path(root)
    if not root.is_dir():
        raise ReportError(f"{root}: not a folder (expected a sweep folder such as runs/<name>/multirun_<ts>/)")
    dirs = {p.parent for p in root.rglob("run.json")} | {p.parent.parent for p in root.rglob(".hydra/overrides.yaml")}
    if not dirs:
        raise ReportError(f"{root}: no job folders (folders with run.json or .hydra/overrides.yaml) under it")
    jobs = []
    for d in dirs:
        ov_file = d / ".hydra" / "overrides.yaml"
        try:
            overrides = [str(o) for o in _load_yaml(ov_file) or []] if ov_file.is_file() else None
            config = _load_yaml(d / "config.yaml") if (d / "config.yaml").is_file() else {}
            run = RunRecord.read(d) if (d / RUN_JSON).is_file() else None
            metrics = json.loads((d / "metrics.json").read_text()) if (d / "metrics.json").is_file() else {}
        except (OSError, ValueError) as exc:  # RunRecordError is a ValueError
            raise ReportError(f"{d}: cannot read the job: {exc}") from exc
        jobs.append(Job(d, overrides, config or {}, run, metrics or {}))

    def order(j: Job):
        rel = j.path.relative_to(root).parts
        return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in rel)

    return sorted(jobs, key=order)


def _override_items(overrides: Sequence[str]) -> dict[str, str]:
    out = {}
    for o in overrides:
        key, sep, value = o.partition("=")
        key = key.lstrip("+~")
        if key.startswith("hydra.") or key.startswith("hydra/") or key == "hydra":
            continue
        out[key] = value if sep else "(deleted)" if o.startswith("~") else ""
    return out


def varying_keys(jobs: Sequence[Job]) -> tuple[list[str], dict[str, str], str]:
    """Fill each job's ``values``; return the varying keys, the settings common to all jobs and where they came from
    ("overrides" or "config")."""
    if all(j.overrides is not None for j in jobs):
        items = [_override_items(j.overrides) for j in jobs]
        source = "overrides"
    else:
        items = [_flatten({k: v for k, v in j.config.items() if k != "hydra"}) for j in jobs]
        source = "config"
    keys = list(dict.fromkeys(k for it in items for k in it))
    varying = [k for k in keys if len({it.get(k) for it in items}) > 1]
    common = {k: items[0][k] for k in keys if k not in varying and k in items[0]}
    if source == "config":
        common = {}  # the whole config: too long to print
        varying = [k for k in varying if k not in ("name",)] or varying
    for j, it in zip(jobs, items):
        j.values = {k: it.get(k, "") for k in varying}
    return varying, common, source


def _get(d: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, Mapping) or part not in d:
            return None
        d = d[part]
    return d


def choose_metrics_node(jobs: Sequence[Job], wanted: str | None) -> str | None:
    nodes = list(dict.fromkeys(k for j in jobs for k in j.metrics))
    if wanted:
        if wanted not in nodes and nodes:
            raise ReportError(f"--metrics {wanted}: no job has these metrics (have: {', '.join(nodes)})")
        return wanted
    if "evaluate.metrics" in nodes:
        return "evaluate.metrics"
    return nodes[0] if nodes else None


def build_rows(jobs: Sequence[Job], keys: Sequence[str], node: str | None,
               columns: Sequence[tuple[str, str]]) -> list[dict[str, Any]]:
    """One row per override set: the set's values, jobs, status, and the mean of each metric column."""
    groups: dict[tuple, list[Job]] = {}
    for j in jobs:
        groups.setdefault(tuple(j.values.get(k, "") for k in keys), []).append(j)
    rows = []
    for values, members in groups.items():
        row: dict[str, Any] = dict(zip(keys, values))
        row["jobs"] = len(members)
        states = sorted({m.status for m in members})
        row["status"] = states[0] if len(states) == 1 else "/".join(states)
        for title, dotted in columns:
            nums = [v for m in members if isinstance(v := _get(m.metrics.get(node) or {}, dotted), (int, float))
                    and not isinstance(v, bool) and math.isfinite(v)]
            row[title] = sum(nums) / len(nums) if nums else None
        row["folder"] = ", ".join(str(m.path) for m in members)
        rows.append(row)
    return rows


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.2f}" if abs(v) < 10 else f"{v:.1f}"
    return str(v)


def format_table(rows: Sequence[Mapping[str, Any]], keys: Sequence[str], columns: Sequence[tuple[str, str]]) -> str:
    head = [*keys, *(t for t, _ in columns), "jobs", "status"]
    body = [[_fmt(r.get(c)) for c in head] for r in rows]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body)]
    n_keys = len(keys)

    def line(cells):
        return "  ".join(str(c).ljust(w) if i < n_keys else str(c).rjust(w) for i, (c, w) in
                         enumerate(zip(cells, widths)))

    return "\n".join([line(head), "  ".join("-" * w for w in widths), *(line(r) for r in body)])


def plot_rows(path: Path, rows: Sequence[Mapping[str, Any]], keys: Sequence[str], y: str = "AE (mm)",
              err: str | None = "STD (mm)", title: str = "") -> Path | None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("no plot: matplotlib is not installed (pip install matplotlib)")
        return None
    pts = [r for r in rows if r.get(y) is not None]
    if not pts:
        log.warning("no plot: no job has %s", y)
        return None

    def number(v):
        try:
            return float(v)
        except (TypeError, ValueError):
            return None

    as_line = len(keys) == 1 and all(number(r[keys[0]]) is not None for r in pts)
    fig, ax = plt.subplots(figsize=(6, 3.5) if as_line else (7, max(2.5, 0.35 * len(pts) + 1.2)))
    label = y + (f" ± {err.split(' ')[0]}" if err else "")
    if as_line:
        pts = sorted(pts, key=lambda r: number(r[keys[0]]))
        ax.errorbar([number(r[keys[0]]) for r in pts], [r[y] for r in pts],
                    yerr=[r.get(err) or 0.0 for r in pts] if err else None, marker="o", capsize=3)
        ax.set_xlabel(keys[0])
        ax.set_ylabel(label)
    else:
        labels = [" ".join(f"{k}={r[k]}" for k in keys) or str(i) for i, r in enumerate(pts)]
        ax.barh(range(len(pts)), [r[y] for r in pts], xerr=[r.get(err) or 0.0 for r in pts] if err else None,
                capsize=3, color="tab:blue", alpha=0.8)
        ax.set_yticks(range(len(pts)), labels, fontsize=7)
        ax.invert_yaxis()
        ax.set_xlabel(label)
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def report(root: Path, out: Path | None = None, metrics: str | None = None,
           extra_columns: Sequence[str] = (), plot: bool = True, echo=print) -> dict[str, Any]:
    root = Path(root)
    jobs = find_jobs(root)
    keys, common, source = varying_keys(jobs)
    node = choose_metrics_node(jobs, metrics)
    columns = [*DEFAULT_COLUMNS, *((c, c) for c in extra_columns)]
    rows = build_rows(jobs, keys, node, columns)
    out = Path(out) if out else root
    out.mkdir(parents=True, exist_ok=True)
    files = {"csv": write_csv(out / "report.csv", rows)}
    echo(f"{root}: {len(jobs)} job(s), {len(rows)} override set(s); the jobs differ in "
         f"{', '.join(keys) or 'nothing'} (from {'.hydra/overrides.yaml' if source == 'overrides' else 'config.yaml'})"
         f"; metrics: {node or 'none'}")
    if common:
        echo("common to all jobs: " + " ".join(f"{k}={v}" for k, v in common.items()))
    echo(format_table(rows, keys, columns))
    if plot:
        p = plot_rows(out / "report.png", rows, keys, title=f"{root.name}: {node or ''}")
        if p is not None:
            files["plot"] = p
    echo("wrote " + ", ".join(str(p) for p in files.values()))
    return {"rows": rows, "keys": keys, "common": common, "source": source, "metrics": node, "files": files}
