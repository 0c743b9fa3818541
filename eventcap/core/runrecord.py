"""``run.json``: the record of one run, written by the runner and read by everything that looks at a finished run.

The one definition of the file's format. A run folder (``runs/<name>/<timestamp>/``) holds it beside
``config.yaml`` and ``metrics.json``::

    {
     "ok": true,                      # every node of every batch committed (nothing failed or skipped)
     "cache_dir": "/abs/runs/cache",  # the stage cache the run read and wrote
     "nodes": {                       # per pipeline node, in run order (NodeReport)
      "track": {"stage": "eklt", "per_batch": true, "cached": 0, "computed": 24, "skipped": 0,
                "skip_causes": [], "failed": [], "elapsed_s": 8.1,
                "keys": ["<cache key of batch 0>", ...], "computed_keys": [...]},
      ...},
     "outputs": {"written": {"bvh": "<path>", ...}, "skipped": {"video": "<why>"}, "problems": []}
    }

``outputs`` is added after the run by :func:`eventcap.apps.outputs.write_run_outputs` (``eventcap view`` only reads
the folder). Readers: :func:`eventcap.core.runner.load_finished_run` (``eventcap view``, the viewer's
benchmark), :mod:`eventcap.apps.report` (the status of a sweep's jobs). This module imports nothing of eventcap.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: the file's name in a run folder
RUN_JSON = "run.json"


class RunRecordError(ValueError):
    """A ``run.json`` that is missing or does not hold what this module writes (the message names file and key)."""


@dataclass
class NodeReport:
    """What one node of a run did: its cache keys, how many units were cached / computed / failed / skipped."""

    node: str
    stage: str
    per_batch: bool
    #: the cache key of the node (whole nodes) or of every batch (per-batch nodes), committed or not
    keys: list[str] = field(default_factory=list)
    computed_keys: list[str] = field(default_factory=list)
    cached: int = 0
    computed: int = 0
    #: one record per failed unit: {"batch", "key", "status", "error", ...}
    failed: list[dict[str, Any]] = field(default_factory=list)
    skipped: int = 0
    #: why each skipped unit was skipped: {"batch": index or None, "cause": "upstream failed: <node>[batch k]: ..."}
    skip_causes: list[dict[str, Any]] = field(default_factory=list)
    elapsed_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"stage": self.stage, "per_batch": self.per_batch, "cached": self.cached, "computed": self.computed,
                "skipped": self.skipped, "skip_causes": self.skip_causes, "failed": self.failed,
                "elapsed_s": round(self.elapsed_s, 3), "keys": self.keys, "computed_keys": self.computed_keys}

    @classmethod
    def from_json(cls, node: str, d: Any, where: str) -> NodeReport:
        if not isinstance(d, dict):
            raise RunRecordError(f"{where}: nodes.{node}: expected an object, got {type(d).__name__}")
        for key in ("stage", "per_batch"):
            if key not in d:
                raise RunRecordError(f"{where}: nodes.{node}: missing {key!r}")
        try:
            return cls(node, str(d["stage"]), bool(d["per_batch"]), [str(k) for k in d.get("keys") or []],
                       [str(k) for k in d.get("computed_keys") or []], int(d.get("cached", 0)),
                       int(d.get("computed", 0)), list(d.get("failed") or []), int(d.get("skipped", 0)),
                       list(d.get("skip_causes") or []), float(d.get("elapsed_s", 0.0)))
        except (TypeError, ValueError) as exc:
            raise RunRecordError(f"{where}: nodes.{node}: {exc}") from None


@dataclass
class RunRecord:
    """The content of ``run.json`` (see the module docstring)."""

    ok: bool
    cache_dir: str | None
    nodes: dict[str, NodeReport]
    #: what :mod:`eventcap.apps.outputs` wrote after the run (None until it ran)
    outputs: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        doc: dict[str, Any] = {"ok": self.ok, "cache_dir": self.cache_dir,
                               "nodes": {n: r.to_json() for n, r in self.nodes.items()}}
        if self.outputs is not None:
            doc["outputs"] = self.outputs
        return doc

    def write(self, run_dir: str | Path) -> Path:
        """Write ``RUN_DIR/run.json`` (atomically: a reader sees the old file or the new one)."""
        path = Path(run_dir) / RUN_JSON
        _write_json(path, self.to_json())
        return path

    @classmethod
    def read(cls, run_dir: str | Path) -> RunRecord:
        """The record of the run folder ``run_dir``; RunRecordError when it has none or it is malformed."""
        path = Path(run_dir) / RUN_JSON
        try:
            doc = json.loads(path.read_text())
        except FileNotFoundError:
            raise RunRecordError(f"{path}: no such file (`eventcap run` writes it into the run folder)") from None
        except (OSError, ValueError) as exc:
            raise RunRecordError(f"{path}: cannot read it: {exc}") from None
        return cls.from_json(doc, str(path))

    @classmethod
    def from_json(cls, doc: Any, where: str = RUN_JSON) -> RunRecord:
        if not isinstance(doc, dict):
            raise RunRecordError(f"{where}: expected an object, got {type(doc).__name__}")
        if "ok" not in doc:
            raise RunRecordError(f"{where}: missing 'ok'")
        nodes = doc.get("nodes") or {}
        if not isinstance(nodes, dict):
            raise RunRecordError(f"{where}: nodes: expected an object, got {type(nodes).__name__}")
        outputs = doc.get("outputs")
        return cls(bool(doc["ok"]), None if doc.get("cache_dir") is None else str(doc["cache_dir"]),
                   {str(n): NodeReport.from_json(str(n), d, where) for n, d in nodes.items()},
                   outputs if isinstance(outputs, dict) else None)

    def cache_path(self, run_dir: str | Path, default: str = "runs/cache") -> Path:
        """The run's cache folder: as recorded (absolute, or relative to the current folder), else relative to the
        folder the run was started from (the run folder is ``runs/<name>/<timestamp>/`` below it by default)."""
        return find_cache_dir(run_dir, self.cache_dir or default)


def find_cache_dir(run_dir: str | Path, cache_dir: str) -> Path:
    """``cache_dir`` of the run in ``run_dir``: as given when absolute or present from here, else the first folder
    above the run folder (up to 4 levels) that holds it."""
    p = Path(cache_dir)
    if p.is_absolute() or (p / "entries").is_dir():
        return p
    for base in list(Path(run_dir).resolve().parents)[:4]:
        if (base / p / "entries").is_dir():
            return base / p
    return p


def note_outputs(run_dir: str | Path, summary: dict[str, Any], merge: bool = False) -> None:
    """Record what the outputs step wrote under ``outputs`` of the run folder's ``run.json`` (nothing when the folder
    has none). ``merge``: add to what an earlier call recorded (``written``/``skipped`` by name, ``problems`` appended)."""
    path = Path(run_dir) / RUN_JSON
    if not path.is_file():
        return
    record = RunRecord.read(run_dir)
    old = record.outputs
    if merge and old is not None:
        summary = {**old, **summary, "written": {**old.get("written", {}), **summary["written"]},
                   "skipped": {**old.get("skipped", {}), **summary["skipped"]},
                   "problems": old.get("problems", []) + summary["problems"]}
    record.outputs = summary
    record.write(run_dir)


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    os.replace(tmp, path)
