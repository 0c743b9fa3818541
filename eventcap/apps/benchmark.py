"""``eventcap benchmark``: the paper's Table 1 and Fig. 7 on synthetic captures with exact ground truth.

Every method of ``conf/benchmark/<preset>.yaml`` (the full pipeline, baselines, ablations: rows defined by config)
runs on every sequence (motion x seed) through the normal runner and run outputs, into
``<out>/runs/<motion>-s<seed>/<method>/``, all sharing one stage cache: a second call recomputes nothing, and an
interrupted benchmark resumes where it stopped.

Measures. A method's AE and STD are the mean and (population) standard deviation of the per-frame errors (mean
per-joint error after per-frame Procrustes alignment, mm) of the evaluate stage's every-n-th tracking frames, pooled
over all its runs (all sequences have the same length, so AE is the mean of the runs' AE); AE.raw over the frames at
intensity frames, AE.nonRaw over the every-n-th frames that are not; per motion, pooled over the seeds. The data rate
is the mean over the runs of the evaluate stage's data rate named by the method's ``data``. Time per batch of each
stage comes from the cache manifests (``elapsed_s`` of the committed entries, whether computed now or earlier; a
whole-recording stage's time is divided by the run's number of batches).

Motion detail (beyond the paper; the evaluate stage's root-relative measures): AE of root-relative joints, MPJVE and
acceleration error are the mean over the runs; the end effectors' peak-speed error is the median over the pooled
(batch, end effector) pairs of the runs, and (runs) the median of the runs' own medians. ``fig_end_effector_speed.png``
shows, per motion (first seed), the speed of the end effector that moves fastest in the truth, truth against each
method (from each run's ``motion.npz``).

Uncertainty: where a run has a confidence node, its uncertainty against its error at the evaluated frames
(:func:`reliability_figures`: Spearman, sparsification area over random, 1- and 2-sigma coverage, medians, per row
and per group) and ``fig_reliability.png`` (error against uncertainty, binned, per row and group).

Writes ``table.csv`` (one row per method), ``runs.csv`` (one row per run), ``benchmark.json`` (config, runs with
their per-frame errors, table), ``fig7_per_frame_error.png``, ``fig_end_effector_speed.png`` and
``fig_reliability.png``, and prints the tables, then the first row against every other capture by capture (where it
is lower, and where not).
"""

from __future__ import annotations

import json
import logging
import math
import re
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eventcap.apps.jobs import save_figure, write_csv  # noqa: F401 (also this module's API, as before)

log = logging.getLogger("eventcap.apps.benchmark")

DATA_FIELDS = ("total_MBps", "events_MBps", "frames_MBps", "highspeed_MBps")
#: The evaluate stage's motion-detail measures a run record keeps (root-relative joints; see eventcap.analysis.metrics).
DETAIL_FIELDS = ("AE_rootrel_mm", "depth_mm", "image_plane_mm", "MPJVE_mm_s", "accel_err_m_s2", "peak_speed_err",
                 "peak_speed_err_fast", "n_fast_pairs", "velocity_window_ms", "body_error_mm", "stated_body_error_mm")
#: The fast moments: (batch, end effector) pairs whose true peak reaches this (m/s; the evaluate stage's default).
FAST_SPEED_MPS = 3.0
_METHOD_KEYS = {"name", "description", "overrides", "events_only", "data", "requires", "body", "detector"}


@dataclass(frozen=True)
class Method:
    name: str
    overrides: tuple[str, ...] = ()
    data: str = "total_MBps"
    requires: tuple[str, ...] = ()
    description: str = ""
    #: the row's overrides on a capture without intensity frames (None: the row has none, its runs are refused)
    events_only: tuple[str, ...] | None = None
    #: what the row's runs are told about a drawn person (the benchmark's ``body_overrides``): told | exact
    body: str = "told"
    #: the row's own detector (a name of the benchmark's ``detectors``) instead of the benchmark's ``detector``
    detector: str | None = None

    def overrides_for(self, frames: bool) -> tuple[str, ...] | None:
        """The row's overrides on a capture with (or without) intensity frames; None: not defined there."""
        return self.overrides if frames else self.events_only

    @property
    def slug(self) -> str:
        """The method's name as a folder name (``w/o_batch`` -> ``wo_batch``)."""
        return re.sub(r"[^A-Za-z0-9_.-]+", "", self.name.replace("/", "")) or "method"


#: What a row may be told about a drawn person: ``told`` (what a user would type), ``exact`` (the actor's body).
BODY_KINDS = ("told", "exact")


def fill_overrides(templates: Sequence[str], values: Mapping[str, Any], where: str) -> list[str]:
    """The overrides with their ``{name}`` fields filled from ``values``; one that names a value that is None
    (e.g. a height the user does not type) is left out."""
    import string

    out = []
    for o in templates:
        fields = [f for _, f, _, _ in string.Formatter().parse(str(o)) if f]
        missing = [f for f in fields if f not in values]
        if missing:
            raise ValueError(f"{where}: no value {{{missing[0]}}}; known: {', '.join(sorted(values))}")
        if any(values[f] is None for f in fields):
            continue
        out.append(str(o).format(**values))
    return out


def parse_methods(items: Sequence[Mapping[str, Any]]) -> list[Method]:
    """The ``methods`` list of a benchmark config, checked (unknown keys, duplicates, data fields)."""
    out: list[Method] = []
    for i, m in enumerate(items or []):
        if not isinstance(m, Mapping) or "name" not in m:
            raise ValueError(f"methods[{i}]: expected a mapping with a 'name', got {m!r}")
        unknown = sorted(set(m) - _METHOD_KEYS)
        if unknown:
            raise ValueError(f"methods[{i}] ({m['name']}): unknown key {unknown[0]!r}; known: "
                             f"{', '.join(sorted(_METHOD_KEYS))}")
        data = m.get("data", "total_MBps")
        if data not in DATA_FIELDS:
            raise ValueError(f"methods[{i}] ({m['name']}).data: expected one of {', '.join(DATA_FIELDS)}, got {data!r}")
        events_only = m.get("events_only")
        body = str(m.get("body") or "told")
        if body not in BODY_KINDS:
            raise ValueError(f"methods[{i}] ({m['name']}).body: expected one of {', '.join(BODY_KINDS)}, got {body!r}")
        meth = Method(name=str(m["name"]), overrides=tuple(str(o) for o in m.get("overrides") or ()), data=data,
                      requires=tuple(str(r) for r in m.get("requires") or ()),
                      description=str(m.get("description") or ""),
                      events_only=None if events_only is None else tuple(str(o) for o in events_only), body=body,
                      detector=None if m.get("detector") is None else str(m["detector"]))
        if any(meth.slug == o.slug for o in out):
            raise ValueError(f"methods[{i}]: name {meth.name!r} repeats an earlier method")
        out.append(meth)
    if not out:
        raise ValueError("methods: the benchmark needs at least one method")
    return out


# ---------------------------------------------------------------------------------------------------------------------
# Configs
# ---------------------------------------------------------------------------------------------------------------------
def split_overrides(argv: Sequence[str], bench_keys: set[str]) -> tuple[str, list[str], list[str]]:
    """``eventcap benchmark`` arguments -> (preset, benchmark overrides, overrides of every run).

    ``benchmark=NAME`` picks the preset; ``key=value`` whose top-level key is a benchmark key changes the benchmark;
    anything else is a hydra override of every run."""
    preset, bench, runs = "default", [], []
    for arg in argv:
        key = arg.split("=", 1)[0].lstrip("+~")
        if key == "benchmark" and "=" in arg:
            preset = arg.split("=", 1)[1]
        elif key.split(".")[0] in bench_keys:
            bench.append(arg)
        else:
            runs.append(arg)
    return preset, bench, runs


def compose_benchmark(config_dir: Path, preset: str, overrides: Sequence[str]) -> dict[str, Any]:
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    if not (config_dir / "benchmark" / f"{preset}.yaml").is_file():
        have = sorted(p.stem for p in (config_dir / "benchmark").glob("*.yaml"))
        raise ValueError(f"benchmark={preset}: no conf/benchmark/{preset}.yaml (presets: {', '.join(have)})")
    with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
        cfg = compose(config_name=f"benchmark/{preset}", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def compose_run(config_dir: Path, overrides: Sequence[str]) -> tuple[dict[str, Any], str]:
    """The run config (plain data) and its YAML, as ``eventcap run <overrides>`` would compose it."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True), OmegaConf.to_yaml(cfg, resolve=True)


# ---------------------------------------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SuiteCapture:
    """One capture of a suite: a (motion, seed) of a listed suite, or a capture drawn from its seed (``draws``)."""

    motion: str
    seed: int
    label: str  # its folder under <out>/runs/
    overrides: tuple[str, ...]  # the run overrides that make it
    frames: bool = True  # it has intensity frames; else the rows' events_only overrides apply
    group: str | None = None  # a generated suite's group
    drawn: dict[str, Any] | None = None  # a generated suite: what was drawn (eventcap.apps.open_suite.Capture)
    description: str = ""
    #: what a row is told about the drawn person, by the row's ``body`` (told | exact); empty: no person drawn
    body: dict[str, tuple[str, ...]] = field(default_factory=dict)
    #: the values its overrides are filled with ({motion}, {seed}, ...): a row's own detector is filled with them
    values: dict[str, Any] = field(default_factory=dict)
    #: the overrides of the benchmark's detector among ``overrides`` (a row with a detector of its own drops them)
    detector: tuple[str, ...] = ()


@dataclass
class Benchmark:
    cfg: dict[str, Any]
    config_dir: Path
    run_overrides: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        c = self.cfg
        self.methods = parse_methods(c.get("methods"))
        detectors = c.get("detectors") or {}
        for m in self.methods:
            if m.detector is not None and m.detector not in detectors:
                raise ValueError(f"methods ({m.name}).detector: expected one of {sorted(detectors)} (benchmark key "
                                 f"detectors), got {m.detector!r}")
        only = c.get("only")
        if only is not None:
            only = [only] if isinstance(only, str) else [str(o) for o in only]
            known = [m.name for m in self.methods]
            unknown = [o for o in only if o not in known]
            if unknown or not only:
                raise ValueError(f"only: expected names of methods ({', '.join(known)}), got {only!r}")
            self.methods = [m for m in self.methods if m.name in only]
        self.out = Path(c["out"])
        self.draws, self.purpose, self.groups, self.real = None, None, {}, {}
        if c.get("recordings") is not None:
            self._real_suite()
            return
        if c.get("draws") is not None:
            self._generated_suite()
            return
        self.motions = [str(m) for m in c["motions"]]
        self.seeds = [int(s) for s in c["seeds"]]
        if not self.motions or not self.seeds:
            raise ValueError("motions and seeds: the benchmark needs at least one of each")
        self.captures = [SuiteCapture(mo, s, f"{mo}-s{s}", tuple(self.sequence_overrides(mo, s)),
                                      values=self.sequence_values(mo, s),
                                      detector=tuple(self.detector_overrides(None, self.sequence_values(mo, s))))
                         for mo in self.motions for s in self.seeds]

    def _generated_suite(self) -> None:
        """Captures drawn from their seeds (eventcap/apps/open_suite.py), the seeds those of the suite's purpose."""
        from eventcap.camera_presets import preset_names
        from eventcap.apps.open_suite import draw_capture, parse_draws, suite_seeds

        c = self.cfg
        self.draws = parse_draws(c["draws"])
        self.purpose = str(c.get("purpose") or "tuning")
        self.seeds = suite_seeds(self.purpose, c.get("seeds"))
        per_camera = c.get("camera_overrides") or {}
        unknown = sorted(set(per_camera) - set(preset_names()))
        if unknown:
            raise ValueError(f"camera_overrides: unknown camera {unknown[0]!r}; expected one of "
                             f"{', '.join(preset_names())}")
        self.groups = {name: g.label for name, g in self.draws.groups.items()}
        self.captures = []
        for seed in self.seeds:
            cap = draw_capture(seed, self.draws, float(c["duration_s"]))
            ov = [*self.sequence_overrides(cap.motion, seed, cap.values()), *map(str, per_camera.get(cap.camera) or ())]
            body = {}
            if cap.actor_height_m is not None:
                told = c.get("body_overrides") or {}
                body = {kind: tuple(fill_overrides(told.get(kind) or (), cap.values(), f"body_overrides.{kind}"))
                        for kind in BODY_KINDS}
            values = self.sequence_values(cap.motion, seed, cap.values())
            self.captures.append(SuiteCapture(cap.motion, seed, cap.label, tuple(ov), cap.frames, cap.group,
                                              cap.values(), cap.describe(), body, values,
                                              tuple(self.detector_overrides(None, values))))
        self.motions = list(dict.fromkeys(cap.motion for cap in self.captures))

    def _real_suite(self) -> None:
        """Public recordings of people (eventcap/apps/real_suite.py): one capture per recording, no ground truth."""
        from eventcap.apps.real_suite import parse_recordings

        root = self.config_dir.parent
        recs = parse_recordings(self.cfg["recordings"], Path(str(self.cfg.get("data_dir") or "runs/real-data")), root)
        select = self.cfg.get("select")
        if select:
            select = [select] if isinstance(select, str) else [str(x) for x in select]
            unknown = [x for x in select if x not in {r.name for r in recs}]
            if unknown:
                raise ValueError(f"select: no recording {unknown[0]!r}; known: {', '.join(r.name for r in recs)}")
            recs = [r for r in recs if r.name in select]
        self.real = {r.name: r for r in recs}
        self.seeds, self.motions = [0], [r.name for r in recs]
        self.captures = [SuiteCapture(r.name, 0, r.name, ("source=recording", f"source.path={r.path}", *r.overrides),
                                      description=r.shows) for r in recs]

    def sequence_values(self, motion: str, seed: int, drawn: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """What a capture's overrides are filled with: the suite's ``sequence_values`` (e.g. the frame rate), what
        was drawn, its motion, seed and duration."""
        return {**(self.cfg.get("sequence_values") or {}), **(drawn or {}), "motion": motion, "seed": seed,
                "duration_s": self.cfg["duration_s"]}

    def detector_overrides(self, name: str | None, values: Mapping[str, Any]) -> list[str]:
        """The overrides of detector ``name`` of the benchmark's ``detectors`` (None: the benchmark's ``detector``),
        filled with a capture's values."""
        detectors = self.cfg.get("detectors") or {}
        detector = self.cfg.get("detector") if name is None else name
        if detector is not None and detector not in detectors:
            where = "detector" if name is None else f"the row's detector {name!r}"
            raise ValueError(f"{where}: expected one of {sorted(detectors)} (benchmark key detectors), got "
                             f"{detector!r}")
        chosen = detectors.get(detector) or () if detector is not None else ()
        return fill_overrides(chosen, values, f"detectors.{detector}")

    def sequence_overrides(self, motion: str, seed: int, drawn: Mapping[str, Any] | None = None) -> list[str]:
        values = self.sequence_values(motion, seed, drawn)
        return [*fill_overrides(self.cfg.get("sequence_overrides") or (), values, "sequence_overrides"),
                *self.detector_overrides(None, values)]

    def base_overrides(self) -> list[str]:
        return [f"cache_dir={self.cfg['cache_dir']}", *map(str, self.cfg.get("overrides") or ()), *self.run_overrides]

    def active_methods(self) -> tuple[list[Method], dict[str, str]]:
        """Methods whose required nodes their own pipeline has (composed with the common overrides and the method's
        own), and why others not. A row whose runs would be those of an earlier row (the same composed config on
        every kind of capture of the suite, e.g. ``pipeline=spline`` while the default is the spline; its own detector
        and what it is told about a drawn person included) is left out too, naming that row: it would only print its
        twin's figures again. The common overrides are composed once
        first: a bad one stops here."""
        compose_run(self.config_dir, self.base_overrides())
        kinds = sorted({cap.frames for cap in self.captures}, reverse=True)  # with frames first
        active, left_out, seen = [], {}, {}
        for m in self.methods:
            composed = {}
            for frames in kinds:
                own = m.overrides_for(frames)
                cap = next(c for c in self.captures if c.frames == frames)
                mine = [] if m.detector is None else self.detector_overrides(m.detector, cap.values)
                composed[frames] = None if own is None else \
                    compose_run(self.config_dir, [*self.base_overrides(), *mine, *own, *cap.body.get(m.body, ())])[0]
            nodes = set()
            for data in composed.values():
                nodes |= set(((data or {}).get("pipeline") or {}).get("nodes") or {})
            missing = [r for r in m.requires if r not in nodes]
            same = seen.get(json.dumps([composed[k] for k in kinds], sort_keys=True, default=str))
            if missing:
                left_out[m.name] = f"the pipeline has no node {', '.join(repr(r) for r in missing)}"
            elif same is not None:
                left_out[m.name] = f"the same runs as {same!r}: its overrides compose the same config"
            else:
                seen[json.dumps([composed[k] for k in kinds], sort_keys=True, default=str)] = m.name
                active.append(m)
        return active, left_out

    def run(self, echo=print) -> dict[str, Any]:
        methods, left_out = self.active_methods()
        for name, why in left_out.items():
            echo(f"method {name}: left out ({why})")
        jobs = [(cap, m) for cap in self.captures for m in methods]
        what = (f"{len(self.captures)} generated capture(s) (seeds {self.purpose}: {_seed_ranges(self.seeds)})"
                if self.draws else f"{len(self.motions)} motion(s) x {len(self.seeds)} seed(s)")
        echo(f"benchmark {self.cfg['name']}: {what} x {len(methods)} method(s) = {len(jobs)} runs of "
             f"{self.cfg['duration_s']} s; cache {self.cfg['cache_dir']}; results in {self.out}")
        if self.purpose == "check":
            from eventcap.apps.open_suite import CHECK_NOTE

            echo(f"benchmark {self.cfg['name']}: {CHECK_NOTE}")
        records = []
        t_all = time.perf_counter()
        for k, (cap, method) in enumerate(jobs, 1):
            records.append(self.run_one(cap, method))
            echo(progress_line(k, len(jobs), records[-1]))
        echo(f"{len(jobs)} runs in {time.perf_counter() - t_all:.1f} s "
             f"({sum(r.get('computed', 0) for r in records)} cache entries computed, "
             f"{sum(r.get('cached', 0) for r in records)} reused)")
        names = [m.name for m in methods]
        results = {"config": self.cfg, "run_overrides": self.run_overrides, "methods_left_out": left_out,
                   "methods": names, "motions": self.motions, "seeds": self.seeds, "runs": records,
                   "table": aggregate(records, names, [] if self.draws else self.motions),
                   "per_capture": per_capture(records, names), "failures": failed_runs(records),
                   "uncertainty": reliability_figures(records, names)}
        if self.draws:
            from eventcap.apps.open_suite import CHECK_NOTE

            results["purpose"] = self.purpose
            results["note"] = CHECK_NOTE if self.purpose == "check" else "the tuning seeds (0-19)"
            results["captures"] = [{"label": c.label, "seed": c.seed, "group": c.group, "frames": c.frames,
                                    "drawn": c.drawn, "description": c.description} for c in self.captures]
            results["groups"] = group_tables(records, names, self.groups)
        return results

    def run_one(self, cap: SuiteCapture, method: Method) -> dict[str, Any]:
        """One row on one capture, through the normal runner and run outputs; a row without overrides for this kind
        of capture, a refused config or a failed run is recorded with its reason, never dropped."""
        from eventcap.apps.jobs import run_job

        run_dir = self.out / "runs" / cap.label / method.slug
        own = method.overrides_for(cap.frames)
        ov = self.row_overrides(cap, method)
        rec: dict[str, Any] = {"motion": cap.motion, "seed": cap.seed, "method": method.name, "run_dir": str(run_dir),
                               "overrides": ov, "ok": False, "error": None, "capture": cap.label, "group": cap.group,
                               "frames_camera": cap.frames}
        t0 = time.perf_counter()
        failures: list[str] = []
        real = self.real.get(cap.label)
        if own is None:
            got, failures = None, [f"refused: the row {method.name} has no variant for event-only cameras "
                                   "(its events_only overrides)"]
        elif real is not None and not real.path.is_file():
            got, failures = None, [f"not on disk: {real.path} ({real.fetch or 'see docs/results/real.md'})"]
        elif real is not None:
            from eventcap.apps.real_suite import compose_recording_run

            try:
                data, yaml_text = compose_recording_run(self.config_dir, ov)
                run_dir.mkdir(parents=True, exist_ok=True)
                got = run_job(data, run_dir, yaml_text, failures)
            except Exception as exc:  # noqa: BLE001 - a bad recording fails its run, not the benchmark
                got, failures = None, [f"{type(exc).__name__}: {exc}"]
        else:
            try:
                data, yaml_text = self._compose_row(ov, tuple(own))
                run_dir.mkdir(parents=True, exist_ok=True)
                got = run_job(data, run_dir, yaml_text, failures)
            except Exception as exc:  # noqa: BLE001 - a bad method config fails its runs, not the benchmark
                got, failures = None, [f"{type(exc).__name__}: {exc}"]
        if real is not None:
            from eventcap.apps.real_suite import real_figures

            rec.update(motion_name=cap.label, person=real.person, sensor=real.sensor, licence=real.licence)
            rec.update(real_figures(got[0], got[1], run_dir) if got is not None else real_figures(None, None, run_dir))
        if got is None:
            rec["error"] = _short_reason("; ".join(failures) or "refused", run_dir)
        elif real is not None:
            rec.update(collect_run(*got, self.cfg["metrics"], self.cfg["errors"], method.data))
            rec["error"] = _short_reason(_first_failure(got[1]) or "; ".join(failures), run_dir) or None
        else:
            rec.update(collect_run(*got, self.cfg["metrics"], self.cfg["errors"], method.data))
            if self.cfg.get("speed_figure", True) and cap.seed == self.seeds[0]:
                rec["speed"] = speed_series(got[0], got[1], run_dir, self.cfg.get("recording", "source.recording"),
                                            float((got[1].metrics.get(self.cfg["metrics"]) or {}).get(
                                                "velocity_window_ms") or 10.0))
            rec["error"] = _short_reason("; ".join(failures), run_dir) or None
        rec["wall_s"] = time.perf_counter() - t0
        return rec


    def row_overrides(self, cap: SuiteCapture, method: Method) -> list[str]:
        """The overrides of one row's run on one capture: the capture's (with the row's own detector instead of the
        benchmark's, when it names one), every run's, the row's own, what the row is told about the person."""
        made = list(cap.overrides)
        if method.detector is not None:
            made = [o for o in made if o not in cap.detector] + self.detector_overrides(method.detector, cap.values)
        return [*made, *self.base_overrides(), *(method.overrides_for(cap.frames) or ()),
                *cap.body.get(method.body, ())]

    def _compose_row(self, overrides: list[str], own: tuple[str, ...] = ()):
        """The run's config; the benchmark's detector choice (detectors.<detector>) is left out of a pipeline without
        a detect node (a row's own overrides never are)."""
        try:
            return compose_run(self.config_dir, overrides)
        except Exception as exc:  # noqa: BLE001 - Hydra: a group the pipeline does not have
            if "stages/detect" not in str(exc) and "stages.detect" not in str(exc):
                raise
            mine = set(own)
            return compose_run(self.config_dir, [o for o in overrides if o in mine
                                                 or not o.startswith(("stages/detect=", "stages.detect."))])


def _first_failure(result) -> str:
    """The first failure of a run, as its node logged it (the cause of a refusal)."""
    for name, rep in result.nodes.items():
        for f in rep.failed:
            return f"{name}: {f.get('error') or f.get('status') or 'failed'}"
    return ""


def _short_reason(text: str, run_dir: Path) -> str:
    """A failure line without the run folder it names (the record has it)."""
    return text.replace(f"{run_dir}: ", "")


def _seed_ranges(seeds: Sequence[int]) -> str:
    """``[0, 1, 2, 5]`` -> ``0-2, 5``."""
    out, run = [], []
    for s in sorted(seeds):
        if run and s != run[-1] + 1:
            out.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
            run = []
        run.append(s)
    if run:
        out.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
    return ", ".join(out)


def progress_line(k: int, n: int, rec: Mapping[str, Any]) -> str:
    head = (f"[{k}/{n}] {rec['capture']} ({rec['group']}, {rec['motion']}) {rec['method']}:" if rec.get("group")
            else f"[{k}/{n}] {rec['motion']} seed {rec['seed']} {rec['method']}:")
    if rec.get("computed") is None:
        return f"{head} FAILED ({rec.get('error')}) in {rec['wall_s']:.1f} s"
    ae = rec.get("AE_mm")
    state = "ok" if rec["ok"] else f"incomplete ({rec.get('error')})"
    return (f"{head} {rec['computed']} computed, {rec['cached']} cached, "
            f"AE {_num(ae)} mm, {rec['wall_s']:.1f} s, {state}")


def collect_run(runner, result, metrics_out: str, errors_out: str, data_field: str) -> dict[str, Any]:
    """One run's record: status, cache counts, Table-1 metrics, per-frame errors, time per batch per stage."""
    from eventcap.artifacts.pose import JointErrors

    rec: dict[str, Any] = {"ok": result.ok, "computed": result.computed_keys(),
                           "cached": sum(r.cached for r in result.nodes.values()),
                           "failed": [f"{n} batch {f['batch']}" if f["batch"] is not None else n
                                      for n, r in result.nodes.items() for f in r.failed]}
    m = result.metrics.get(metrics_out) or {}
    dr = m.get("data_rate") or {}
    rec.update({"AE_mm": m.get("AE_mm"), "STD_mm": m.get("STD_mm"), "AE_raw_mm": m.get("AE_raw_mm"),
                "AE_nonRaw_mm": m.get("AE_nonRaw_mm"), "data_MBps": dr.get(data_field), "data_field": data_field})
    rec.update({k: m.get(k) for k in DETAIL_FIELDS})
    for k in ("peak_speed_errors", "peak_speed_signed", "peak_speed_true_mps"):
        rec[k] = m.get(k)
    rec["frames"] = None
    node = errors_out.partition(".")[0]
    if node in runner.by_name:
        got = runner.load_output(result, errors_out)
        if got and isinstance(got[None], JointErrors) and got[None].t_us.size:
            e = got[None]
            rec["frames"] = {"t_us": e.t_us.tolist(), "err_mm": (1000.0 * e.error_m.mean(axis=1)).round(6).tolist(),
                             "sampled": e.sampled.tolist(), "raw": e.raw.tolist()}
    rec["reliability"] = uncertainty_pairs(runner, result, errors_out)
    rec.update(stage_times(runner, result))
    return rec


def uncertainty_pairs(runner, result, errors_out: str, confidence_out: str = "confidence.confidence"):
    """A run's (frame, joint) pairs at the evaluated frames for the reliability figures: ``u_mm`` the confidence
    stage's uncertainty and ``err_mm`` the evaluate stage's error there (F x 24 lists, 0.1 mm); None when the run
    has no uncertainty or no errors."""
    from eventcap.artifacts.pose import JointConfidence, JointErrors

    node = confidence_out.partition(".")[0]
    if node not in runner.by_name or errors_out.partition(".")[0] not in runner.by_name:
        return None
    try:
        c, e = runner.load_output(result, confidence_out), runner.load_output(result, errors_out)
    except Exception:  # noqa: BLE001 - a node that did not finish leaves no pairs, the run is still recorded
        return None
    c, e = (c or {}).get(None), (e or {}).get(None)
    if not isinstance(c, JointConfidence) or not isinstance(e, JointErrors) or not e.t_us.size:
        return None
    k = np.searchsorted(c.t_us, e.t_us)
    if (k >= c.t_us.size).any() or not np.array_equal(c.t_us[k], e.t_us):
        return None
    u = np.asarray(c.uncertainty_mm, np.float64)[k]
    return {"u_mm": np.round(u, 1).tolist(), "err_mm": np.round(1000.0 * e.error_m, 1).tolist()}


def _reliability_arrays(records: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    u = [np.asarray(r["reliability"]["u_mm"], np.float64).ravel() for r in records if r.get("reliability")]
    e = [np.asarray(r["reliability"]["err_mm"], np.float64).ravel() for r in records if r.get("reliability")]
    if not u:
        return np.zeros(0), np.zeros(0)
    u, e = np.concatenate(u), np.concatenate(e)
    ok = np.isfinite(u) & np.isfinite(e)
    return u[ok], e[ok]


def reliability_figures(records: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    """Does each row's uncertainty mean something (eventcap.analysis.uncertainty): per row, and per group of a
    generated suite, over the pooled (evaluated frame, joint) pairs of its runs: Spearman(uncertainty, error), the
    sparsification area over a random ranking's, the shares of errors within 1 and 2 uncertainties, the medians."""
    from eventcap.analysis.uncertainty import coverage, sparsification, spearman

    out: dict[str, Any] = {}
    for name in methods:
        rows = [r for r in records if r["method"] == name and r.get("reliability")]
        if not rows:
            continue
        parts = {"all": rows}
        groups = sorted({r.get("group") for r in rows if r.get("group")})
        if len(groups) > 1:
            parts.update({g: [r for r in rows if r.get("group") == g] for g in groups})
        out[name] = {}
        for g, sel in parts.items():
            u, e = _reliability_arrays(sel)
            if u.size < 3:
                continue
            out[name][g] = {"runs": len(sel), "pairs": int(u.size), "spearman": spearman(u, e),
                            "ause_ratio": sparsification(u, e)["ratio"], "cover1": coverage(u, e, 1.0),
                            "cover2": coverage(u, e, 2.0), "u_median_mm": float(np.median(u)),
                            "error_median_mm": float(np.median(e))}
    return out


def format_reliability(figures: Mapping[str, Any]) -> str:
    """The reliability figures as a table (one line per row and group)."""
    if not figures:
        return ""
    lines = ["Uncertainty against error (pairs: evaluated frame x joint; targets: Spearman >= 0.5, AUSE <= 0.4 x "
             "random, 2-sigma 90-97 %, median u within 2 x median error)",
             f"{'row':<24}{'group':<14}{'runs':>5}{'pairs':>7}{'spearman':>9}{'ause/rnd':>9}{'1-sigma':>8}"
             f"{'2-sigma':>8}{'u med':>7}{'err med':>8}"]
    for name, groups in figures.items():
        for g, f in groups.items():
            lines.append(f"{name:<24}{g:<14}{f['runs']:>5}{f['pairs']:>7}{f['spearman']:>9.2f}"
                         f"{f['ause_ratio']:>9.2f}{100 * f['cover1']:>7.1f}%{100 * f['cover2']:>7.1f}%"
                         f"{f['u_median_mm']:>7.1f}{f['error_median_mm']:>8.1f}")
    return "\n".join(lines)


def plot_reliability(path: Path, records: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> Path | None:
    """The reliability plot: per row (and per group of a generated suite), the error against the uncertainty over
    the runs' (evaluated frame, joint) pairs, in 10 quantile bins of the uncertainty: the mean and 90th percentile
    of the error per bin, with the lines error = u and error = 2 u (a calibrated uncertainty keeps the 90th
    percentile near 2 u and the mean rising with u)."""
    panels = []
    for name in methods:
        rows = [r for r in records if r["method"] == name and r.get("reliability")]
        groups = sorted({r.get("group") for r in rows if r.get("group")})
        for g in (groups if len(groups) > 1 else [None]):
            sel = [r for r in rows if g is None or r.get("group") == g]
            u, e = _reliability_arrays(sel)
            if u.size >= 20:
                panels.append((f"{name}" + (f", {g}" if g else "") + f" ({len(sel)} runs)", u, e))
    if not panels:
        return None
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("no plot: matplotlib is not installed (pip install matplotlib)")
        return None
    cols = min(3, len(panels))
    rows_n = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(4.3 * cols, 3.8 * rows_n), squeeze=False)
    for ax, (title, u, e) in zip(axes.flat, panels):
        edges = np.unique(np.quantile(u, np.linspace(0, 1, 11)))
        b = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, max(edges.size - 2, 0))
        bins = [i for i in range(max(edges.size - 1, 1)) if (b == i).any()]
        mu = np.array([u[b == i].mean() for i in bins])
        me = np.array([e[b == i].mean() for i in bins])
        q90 = np.array([np.quantile(e[b == i], 0.9) for i in bins])
        step = max(1, u.size // 3000)
        ax.scatter(u[::step], e[::step], s=2, alpha=0.15, color="grey", label="(frame, joint) pairs")
        ax.plot(mu, me, "o-", color="C0", label="mean error per bin")
        ax.plot(mu, q90, "s--", color="C1", label="90th percentile per bin")
        top = float(max(np.quantile(u, 0.98), np.quantile(e, 0.98) / 2.0, 1e-3) * 1.1)
        ax.plot([0, top], [0, top], "k:", lw=1, label="error = u")
        ax.plot([0, top], [0, 2 * top], color="0.5", lw=1, ls="-.", label="error = 2 u")
        ax.set_xlim(0, top)
        ax.set_ylim(0, 2.2 * top)
        ax.set_xlabel("uncertainty u (mm)", fontsize=8)
        ax.set_ylabel("error after rigid alignment (mm)", fontsize=8)
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="upper left")
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.suptitle("Reliability: error against the run's uncertainty (10 quantile bins of u)", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def speed_series(runner, result, run_dir: Path, recording_out: str, window_ms: float) -> dict[str, Any] | None:
    """For the speed figure: the root-relative speed over time of the end effector that moves fastest in the truth,
    true and estimated (from the run's ``motion.npz``), by the evaluate stage's central differences."""
    from eventcap.analysis.metrics import END_EFFECTORS, motion_detail, truth_at

    npz = run_dir / "motion.npz"
    node = recording_out.partition(".")[0]
    if not npz.is_file() or node not in runner.by_name:
        return None
    try:
        got = runner.load_output(result, recording_out)
        gt = got[None].ground_truth if got else None
        if gt is None:
            return None
        with np.load(npz) as z:
            t_us, joints = np.asarray(z["t_us"], np.int64), np.asarray(z["joints"], np.float64)
        true, inside = truth_at(gt.t_us, gt.joints, t_us)
        from eventcap.body.skeleton import JOINT_INDEX

        ee = tuple(JOINT_INDEX[n] for n in END_EFFECTORS)
        d = motion_detail(t_us[inside], joints[inside], true, window_ms * 1000.0, None, ee)
    except Exception as exc:  # noqa: BLE001 - a figure must not fail the benchmark
        log.warning("no speed series for %s: %s", run_dir, exc)
        return None
    ok = d["valid"]
    if not ok.any():
        return None
    j = int(np.argmax(np.nanmax(d["speed_true"][ok], axis=0)))
    return {"joint": END_EFFECTORS[j], "t_us": t_us[inside][ok].tolist(),
            "true_mps": d["speed_true"][ok, j].round(4).tolist(), "pred_mps": d["speed_pred"][ok, j].round(4).tolist()}


def stage_times(runner, result) -> dict[str, Any]:
    """Seconds per batch of every node (from the cache manifests) and the medians of numeric per-batch stats."""
    per_batch = [r for r in result.nodes.values() if r.per_batch]
    n_batches = max((len(r.keys) for r in per_batch), default=1) or 1
    times: dict[str, float] = {}
    stats: dict[str, dict[str, float]] = {}
    for name, rep in result.nodes.items():
        node = runner.by_name[name]
        elapsed, node_stats = [], {}
        for key in rep.keys:
            entry = runner.cache.lookup(node.spec.name, key)
            if entry is None:
                continue
            elapsed.append(float(entry.manifest.get("elapsed_s", float("nan"))))
            for k, v in (entry.manifest.get("stats") or {}).items():
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    node_stats.setdefault(k, []).append(float(v))
        if not elapsed:
            continue
        times[name] = float(np.mean(elapsed)) if rep.per_batch else float(np.sum(elapsed)) / n_batches
        if node_stats:
            stats[name] = {k: float(np.median(v)) for k, v in node_stats.items()}
    return {"n_batches": n_batches, "s_per_batch": times, "stats": stats}


# ---------------------------------------------------------------------------------------------------------------------
# Aggregation (pure: records in, table out)
# ---------------------------------------------------------------------------------------------------------------------
def _pool(records: Sequence[Mapping[str, Any]], which: str) -> np.ndarray:
    out = []
    for r in records:
        f = r.get("frames")
        if not f:
            continue
        e = np.asarray(f["err_mm"], dtype=np.float64)
        s, raw = np.asarray(f["sampled"], bool), np.asarray(f["raw"], bool)
        mask = {"all": s, "raw": raw, "nonRaw": s & ~raw}[which]
        out.append(e[mask])
    return np.concatenate(out) if out else np.zeros(0)


def _mean_std(x: np.ndarray) -> tuple[float | None, float | None]:
    return (float(x.mean()), float(x.std())) if x.size else (None, None)


def _mean_of(records: Sequence[Mapping[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in records if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
    return float(np.mean(vals)) if vals else None


def _pairs(records: Sequence[Mapping[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """Every (batch, end effector) pair of the runs that kept them: true peak speeds (m/s) and signed relative
    errors, pooled."""
    t, e = [], []
    for r in records:
        for tr, er in zip(r.get("peak_speed_true_mps") or [], r.get("peak_speed_signed") or []):
            for a, b in zip(tr, er):
                if a is not None and b is not None:
                    t.append(a)
                    e.append(b)
    return np.asarray(t, dtype=np.float64), np.asarray(e, dtype=np.float64)


def detail_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Motion detail over runs: AE of root-relative joints, MPJVE and acceleration error as the mean over the runs
    (runs of one suite have the same length), the peak-speed error as the median over the pooled (batch, end
    effector) pairs of all runs (a fraction), and as the median of the runs' own medians (``peak_speed_err_runs``:
    each capture counts once, however many fast moments it has); the fast-peak error (``peak_speed_err_fast``) over
    the pooled pairs whose true peak reaches :data:`FAST_SPEED_MPS` (``n_fast_pairs`` of them), and the signed
    error per true-speed bin (``peak_speed_signed_by_bin``)."""
    from eventcap.analysis.metrics import signed_by_speed

    out: dict[str, Any] = {k: _mean_of(records, k) for k in ("AE_rootrel_mm", "depth_mm", "image_plane_mm",
                                                             "MPJVE_mm_s", "accel_err_m_s2")}
    vals = [r["peak_speed_err"] for r in records if r.get("peak_speed_err") is not None]
    out["peak_speed_err_runs"] = float(np.median(vals)) if vals else None
    pairs = [v for r in records for row in (r.get("peak_speed_errors") or []) for v in row if v is not None]
    # records from before the pairs were kept: the median of the runs' own medians
    out["peak_speed_err"] = float(np.median(pairs)) if pairs else out["peak_speed_err_runs"]
    true, signed = _pairs(records)
    fast = true >= FAST_SPEED_MPS
    out["n_fast_pairs"] = int(fast.sum())
    out["peak_speed_err_fast"] = float(np.median(np.abs(signed[fast]))) if fast.any() else None
    out["peak_speed_signed_by_bin"] = signed_by_speed(true, signed) if true.size else {}
    return out


#: The measures compared capture by capture (:func:`per_capture`): lower is better for each.
CAPTURE_MEASURES = (("AE_mm", "AE"), ("AE_rootrel_mm", "AE.rootrel"), ("depth_mm", "depth"), ("MPJVE_mm_s", "MPJVE"),
                    ("peak_speed_err", "peak"), ("peak_speed_err_fast", "fast peak"))


def per_capture(records: Sequence[Mapping[str, Any]], methods: Sequence[str]) -> dict[str, Any]:
    """The first method against each other one, capture by capture (motion, seed): for each measure of
    :data:`CAPTURE_MEASURES`, on how many of the captures both measured the first is lower, and the captures where
    it is not, with both values; and (``unmeasured``) the captures where the first has no AE but the other has (it
    failed or was refused there). Means over a suite can hide a capture lost; this does not."""
    if len(methods) < 2:
        return {"reference": methods[0] if methods else None, "against": {}}
    ref, others = methods[0], methods[1:]
    by = {(r["motion"], r["seed"], r["method"]): r for r in records}
    caps = sorted({(m, s) for m, s, _ in by})
    value = lambda c, method, key: (by.get((*c, method)) or {}).get(key)  # noqa: E731 - None: not measured
    against = {}
    for name in others:
        res = {}
        for key, _ in CAPTURE_MEASURES:
            both = [(c, value(c, ref, key), value(c, name, key)) for c in caps
                    if value(c, ref, key) is not None and value(c, name, key) is not None]
            res[key] = {"lower": sum(a < b for _, a, b in both), "of": len(both),
                        "not_lower": [{"motion": c[0], "seed": c[1], ref: a, name: b} for c, a, b in both if a >= b]}
        against[name] = res
    unmeasured = {name: [{"motion": c[0], "seed": c[1], name: value(c, name, "AE_mm")} for c in caps
                         if value(c, ref, "AE_mm") is None and value(c, name, "AE_mm") is not None]
                  for name in others}
    return {"reference": ref, "against": against, "unmeasured": {k: v for k, v in unmeasured.items() if v}}


def failed_runs(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Every run that failed, was refused or is incomplete, with its reason (in the order they ran)."""
    return [{"capture": r.get("capture") or f"{r['motion']}-s{r['seed']}", "group": r.get("group"),
             "motion": r["motion"], "seed": r["seed"], "method": r["method"],
             "state": "incomplete" if r.get("computed") is not None else "failed",
             "evaluated": bool(r.get("frames")), "reason": r.get("error") or "unknown"}
            for r in records if not r.get("ok")]


def group_tables(records: Sequence[Mapping[str, Any]], methods: Sequence[str],
                 groups: Mapping[str, str]) -> dict[str, dict[str, Any]]:
    """Per group of a generated suite: its label, captures, Table 1 and the per-capture comparison."""
    out = {}
    for name, label in groups.items():
        mine = [r for r in records if r.get("group") == name]
        out[name] = {"label": label, "captures": len({r["seed"] for r in mine}),
                     "table": aggregate(mine, methods, []), "per_capture": per_capture(mine, methods)}
    return out


def aggregate(records: Sequence[Mapping[str, Any]], methods: Sequence[str], motions: Sequence[str]) -> list[dict]:
    """One row per method: pooled AE ± STD (all / raw / nonRaw), per motion, data rate, time per batch per stage."""
    rows = []
    for name in methods:
        mine = [r for r in records if r["method"] == name]
        good = [r for r in mine if r.get("frames")]
        row: dict[str, Any] = {"method": name, "runs": len(mine), "evaluated": len(good),
                               "incomplete": sum(1 for r in mine if not r.get("ok"))}
        for which, key in (("all", "AE"), ("raw", "AE_raw"), ("nonRaw", "AE_nonRaw")):
            row[f"{key}_mm"], row[f"{key}_STD_mm"] = _mean_std(_pool(good, which))
        row.update(detail_summary(good))
        rates = [r["data_MBps"] for r in mine if r.get("data_MBps") is not None]
        row["data_MBps"] = float(np.mean(rates)) if rates else None
        row["per_motion"] = {}
        for motion in motions:
            ae, sd = _mean_std(_pool([r for r in good if r["motion"] == motion], "all"))
            row["per_motion"][motion] = {"AE_mm": ae, "STD_mm": sd,
                                         **detail_summary([r for r in good if r["motion"] == motion])}
        nodes: dict[str, list[float]] = {}
        stats: dict[str, list[float]] = {}
        for r in mine:
            for n, s in (r.get("s_per_batch") or {}).items():
                nodes.setdefault(n, []).append(s)
            for n, st in (r.get("stats") or {}).items():
                for k in ("solve_s", "iterations"):
                    if k in st:
                        stats.setdefault(f"{n}.{k}", []).append(st[k])
        row["s_per_batch"] = {n: float(np.mean(v)) for n, v in nodes.items()}
        row["stats"] = {k: float(np.median(v)) for k, v in stats.items()}
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------------------------------
# Presentation
# ---------------------------------------------------------------------------------------------------------------------
def _num(x, digits: int = 1) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _pct(x) -> str:
    return "n/a" if x is None else f"{100.0 * x:.0f}%"


def _pm(mean, std) -> str:
    return "n/a" if mean is None else f"{mean:.1f} ± {std:.1f}"


def _grid(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    fmt = lambda cells: "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w)  # noqa: E731
                                  for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([fmt(header), "  ".join("-" * w for w in widths), *(fmt(r) for r in rows)])


def format_per_capture(comparison: Mapping[str, Any]) -> str:
    """The printed comparison of :func:`per_capture`: a row per method, the captures where the reference is lower
    per measure, then each capture where it is not."""
    ref, against = comparison.get("reference"), comparison.get("against") or {}
    if not against:
        return ""
    head = ["method", *(label for _, label in CAPTURE_MEASURES)]
    rows = [[name, *(f"{res[k]['lower']}/{res[k]['of']}" for k, _ in CAPTURE_MEASURES)] for name, res in against.items()]
    lines = [f"Per capture: where {ref} is lower than each method (captures, of those both measured)",
             _grid(head, rows)]
    fmt = {"peak_speed_err": _pct, "peak_speed_err_fast": _pct, "MPJVE_mm_s": lambda v: _num(v, 0)}
    for name, res in against.items():
        for key, label in CAPTURE_MEASURES:
            f = fmt.get(key, _num)
            for c in res[key]["not_lower"]:
                lines.append(f"  {ref} not lower than {name}: {c['motion']} seed {c['seed']} {label} "
                             f"{f(c[ref])} against {f(c[name])}")
    for name, caps in (comparison.get("unmeasured") or {}).items():
        for c in caps:
            lines.append(f"  {ref} has no result where {name} has: {c['motion']} seed {c['seed']} (AE {_num(c[name])} "
                         "mm; the reason: failed or refused runs)")
    return "\n".join(lines)


def format_tables(table: Sequence[Mapping[str, Any]], motions: Sequence[str], note: str = "",
                  comparison: Mapping[str, Any] | None = None, times: bool = True) -> str:
    """The printed report: Table 1, AE per motion and motion detail per motion (when ``motions``), time per batch
    per stage (when ``times``), and the first method against the others capture by capture (``comparison``,
    :func:`per_capture`)."""
    parts = []
    head = ["method", "AE.all (mm)", "AE.raw (mm)", "AE.nonRaw (mm)", "AE.rootrel (mm)", "depth (mm)",
            "image plane (mm)", "MPJVE (mm/s)",
            "Acc.err (m/s²)", "peak speed err", "(runs)", "fast peak (pairs)", "Size.sec (MB/s)", "runs"]
    rows = [[r["method"], _pm(r["AE_mm"], r["AE_STD_mm"]), _pm(r["AE_raw_mm"], r["AE_raw_STD_mm"]),
             _pm(r["AE_nonRaw_mm"], r["AE_nonRaw_STD_mm"]), _num(r.get("AE_rootrel_mm")), _num(r.get("depth_mm")),
             _num(r.get("image_plane_mm")), _num(r.get("MPJVE_mm_s"), 0),
             _num(r.get("accel_err_m_s2"), 1), _pct(r.get("peak_speed_err")), _pct(r.get("peak_speed_err_runs")),
             f"{_pct(r.get('peak_speed_err_fast'))} ({r.get('n_fast_pairs') or 0})",
             _num(r["data_MBps"], 2), f"{r['evaluated']}/{r['runs']}"] for r in table]
    parts.append("Table 1" + (f" ({note})" if note else "") + "\n" + _grid(head, rows)
                 + "\n(peak speed err: the median over every run's (batch, end effector) pairs; (runs): the median of "
                   f"the runs' own medians; fast peak: over the pairs whose true peak reaches {FAST_SPEED_MPS:g} m/s)")
    if motions:
        parts.extend(_per_motion_tables(table, motions))
    if times:
        parts.append(_time_table(table))
    if comparison:
        parts.append(format_per_capture(comparison))
    return "\n\n".join(p for p in parts if p)


def _per_motion_tables(table: Sequence[Mapping[str, Any]], motions: Sequence[str]) -> list[str]:
    head = ["method", *motions]
    rows = [[r["method"], *(_pm(r["per_motion"][m]["AE_mm"], r["per_motion"][m]["STD_mm"]) for m in motions)]
            for r in table]
    out = ["AE per motion (mm, mean ± STD over the frames of all seeds)\n" + _grid(head, rows)]
    rows = [[r["method"], *(f"{_num(r['per_motion'][m].get('AE_rootrel_mm'))} / "
                            f"{_num(r['per_motion'][m].get('MPJVE_mm_s'), 0)} / "
                            f"{_pct(r['per_motion'][m].get('peak_speed_err'))}" for m in motions)] for r in table]
    out.append("Per motion: AE of root-relative joints (mm) / MPJVE (mm/s) / median peak-speed error per batch "
               "of the end effectors\n" + _grid(head, rows))
    return out


def _time_table(table: Sequence[Mapping[str, Any]]) -> str:
    nodes = list(dict.fromkeys(n for r in table for n in r["s_per_batch"]))
    stats = list(dict.fromkeys(k for r in table for k in r["stats"]))
    head = ["method", *nodes, "sum", *stats]
    rows = [[r["method"], *(_num(r["s_per_batch"].get(n), 3) for n in nodes),
             _num(sum(r["s_per_batch"].values()), 2), *(_num(r["stats"].get(k), 2) for k in stats)] for r in table]
    return ("Time per batch (s; mean over runs, from the cache manifests; whole-recording stages divided by the "
            "batches; last columns: medians of the stage's own statistics)\n" + _grid(head, rows))


def format_generated(results: Mapping[str, Any]) -> str:
    """The printed report of a generated suite: what its seeds are for, Table 1 and the per-capture comparison per
    group, all captures pooled (with the time per batch), every capture with what was drawn and each row's result,
    and every run that failed or was refused with its reason."""
    parts = [f"{results['config']['name']}: {results['note']}"]
    seq = f"{results['config']['duration_s']} s each; AE after Procrustes, every 10th tracking frame"
    for name, g in results["groups"].items():
        parts.append(f"== Group {name}: {g['label']}, {g['captures']} capture(s)\n"
                     + format_tables(g["table"], [], f"{name}; {seq}", g["per_capture"], times=False))
    parts.append(f"== All {len(results['captures'])} captures pooled\n"
                 + format_tables(results["table"], [], seq, None, times=True))
    parts.append(format_reliability(results.get("uncertainty") or {}))
    parts.append(format_captures(results["captures"], results["runs"], results["methods"]))
    parts.append(format_failures(results["failures"]))
    return "\n\n".join(p for p in parts if p)


def format_captures(captures: Sequence[Mapping[str, Any]], records: Sequence[Mapping[str, Any]],
                    methods: Sequence[str]) -> str:
    """One line per capture (what was drawn), then each row's AE / MPJVE / peak-speed error, or why it has none."""
    by = {(r["seed"], r["method"]): r for r in records}
    lines = ["Captures (what was drawn; per row: AE mm / MPJVE mm/s / peak-speed error, or why not)"]
    for c in captures:
        lines.append(f"{c['label']} [{c['group']}] {c['description']}")
        cells = []
        for m in methods:
            r = by.get((c["seed"], m))
            if r is None:
                continue
            if r.get("frames"):
                cells.append(f"{m} {_num(r.get('AE_mm'))} / {_num(r.get('MPJVE_mm_s'), 0)} / "
                             f"{_pct(r.get('peak_speed_err'))}" + ("" if r.get("ok") else " (incomplete)"))
            else:
                cells.append(f"{m} none")
        lines.append("    " + "; ".join(cells))
    return "\n".join(lines)


def format_failures(failures: Sequence[Mapping[str, Any]]) -> str:
    """Every run that failed, was refused or is incomplete, with its reason."""
    if not failures:
        return "Failed or refused runs: none"
    lines = [f"Failed, refused or incomplete runs ({len(failures)}; 'incomplete, evaluated': measured on what ran)"]
    for f in failures:
        state = f["state"] + (", evaluated" if f["evaluated"] else "")
        group = f" [{f['group']}]" if f.get("group") else ""
        lines.append(f"  {f['capture']}{group} {f['motion']} {f['method']}: {state}: {f['reason']}")
    return "\n".join(lines)


def table_csv_rows(table: Sequence[Mapping[str, Any]], motions: Sequence[str]) -> list[dict[str, Any]]:
    out = []
    for r in table:
        row = {k: r.get(k) for k in ("method", "runs", "evaluated", "incomplete", "AE_mm", "AE_STD_mm", "AE_raw_mm",
                                     "AE_raw_STD_mm", "AE_nonRaw_mm", "AE_nonRaw_STD_mm", "AE_rootrel_mm",
                                     "depth_mm", "image_plane_mm", "MPJVE_mm_s", "accel_err_m_s2", "peak_speed_err", "peak_speed_err_runs",
                                     "data_MBps")}
        for m in motions:
            pm = r["per_motion"][m]
            row[f"AE_{m}_mm"] = pm["AE_mm"]
            row[f"STD_{m}_mm"] = pm["STD_mm"]
            for k in ("AE_rootrel_mm", "depth_mm", "image_plane_mm", "MPJVE_mm_s", "peak_speed_err"):
                row[f"{k}.{m}"] = pm.get(k)
        row.update({f"s_per_batch.{n}": v for n, v in r["s_per_batch"].items()})
        row.update(r["stats"])
        out.append(row)
    return out


def run_csv_rows(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for r in records:
        row = {k: r.get(k) for k in ("motion", "seed", "method", "ok", "computed", "cached", "wall_s", "AE_mm",
                                     "STD_mm", "AE_raw_mm", "AE_nonRaw_mm", *DETAIL_FIELDS, "data_MBps", "data_field",
                                     "n_batches")}
        row.update({f"s_per_batch.{n}": v for n, v in (r.get("s_per_batch") or {}).items()})
        row["error"] = r.get("error") or ""
        row["run_dir"] = r.get("run_dir")
        out.append(row)
    return out


def capture_csv_rows(results: Mapping[str, Any]) -> list[dict[str, Any]]:
    """A generated suite: one row per capture, what was drawn and each row's AE, MPJVE, peak-speed error or reason."""
    by = {(r["seed"], r["method"]): r for r in results["runs"]}
    out = []
    for c in results["captures"]:
        row = {"capture": c["label"], "group": c["group"], **(c.get("drawn") or {})}
        for m in results["methods"]:
            r = by.get((c["seed"], m)) or {}
            row.update({f"{m}.AE_mm": r.get("AE_mm"), f"{m}.MPJVE_mm_s": r.get("MPJVE_mm_s"),
                        f"{m}.peak_speed_err": r.get("peak_speed_err"), f"{m}.ok": r.get("ok"),
                        f"{m}.error": r.get("error") or ""})
        out.append(row)
    return out


def plot_per_frame_errors(path: Path, records: Sequence[Mapping[str, Any]], methods: Sequence[str],
                          motions: Sequence[str]) -> Path | None:
    """Fig. 7: the per-frame AE (every-n-th frames) over time of each method, one panel per motion (first seed)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("no plot: matplotlib is not installed (pip install matplotlib)")
        return None
    cols = 2 if len(motions) > 1 else 1
    rows = math.ceil(len(motions) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6.5 * cols, 2.8 * rows), squeeze=False)
    for ax, motion in zip(axes.flat, motions):
        seeds = sorted({r["seed"] for r in records if r["motion"] == motion})
        for name in methods:
            r = next((r for r in records if r["motion"] == motion and r["method"] == name and r.get("frames")
                      and r["seed"] == (seeds[0] if seeds else None)), None)
            if r is None:
                continue
            f = r["frames"]
            s = np.asarray(f["sampled"], bool)
            t = np.asarray(f["t_us"], np.float64)[s] / 1000.0
            e = np.asarray(f["err_mm"], np.float64)[s]
            ax.plot(t, e, label=f"{name} ({e.mean():.1f})", lw=1.2)
            if name == methods[0] or not ax.lines[:-1]:  # intensity frame times, once per panel
                for tr in np.asarray(f["t_us"], np.float64)[np.asarray(f["raw"], bool)] / 1000.0:
                    ax.axvline(tr, color="0.6", lw=0.6, ls=":", zorder=0)
        ax.set_title(f"{motion}, seed {seeds[0] if seeds else '-'}", fontsize=9)
        ax.set_xlabel("time (ms)", fontsize=8)
        ax.set_ylabel("AE (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(motions):]:
        ax.axis("off")
    fig.suptitle("Per-frame mean joint error after Procrustes alignment (every 10th tracking frame; legend: mean; "
                 "dotted: intensity frames)",
                 fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_speeds(path: Path, records: Sequence[Mapping[str, Any]], methods: Sequence[str],
                motions: Sequence[str]) -> Path | None:
    """Per motion (first seed): the speed over time of its fastest end effector (root-relative, as in the MPJVE),
    the truth against each method."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log.warning("no plot: matplotlib is not installed (pip install matplotlib)")
        return None
    have = [m for m in motions if any(r["motion"] == m and r.get("speed") for r in records)]
    if not have:
        return None
    fig, axes = plt.subplots(len(have), 1, figsize=(11, 2.9 * len(have)), squeeze=False)
    for ax, motion in zip(axes[:, 0], have):
        runs = [r for r in records if r["motion"] == motion and r.get("speed")]
        first = runs[0]["speed"]
        t0 = first["t_us"][0]
        ax.plot((np.asarray(first["t_us"]) - t0) / 1000.0, first["true_mps"], color="k", lw=2.2, label="truth",
                zorder=5)
        colors = plt.get_cmap("tab10").colors
        for i, name in enumerate(methods):
            r = next((r for r in runs if r["method"] == name), None)
            if r is None:
                continue
            sp = r["speed"]
            ax.plot((np.asarray(sp["t_us"]) - t0) / 1000.0, sp["pred_mps"], lw=1.6 if i < 4 else 0.9,
                    alpha=0.9, color=colors[i % len(colors)], ls="-" if i < 4 else "--",
                    label=f"{name} (MPJVE {_num(r.get('MPJVE_mm_s'), 0)} mm/s)")
        # spikes of the noisiest methods would flatten the truth: the axis stops at 3x its peak
        ax.set_ylim(0.0, max(3.0 * float(np.max(first["true_mps"])), 1.0))
        ax.set_title(f"{motion}, seed {runs[0]['seed']}: speed of {first['joint']} relative to the pelvis", fontsize=9)
        ax.set_xlabel("time (ms)", fontsize=8)
        ax.set_ylabel("speed (m/s)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=3, loc="upper right")
    fig.suptitle("End-effector speed (central differences over the evaluate stage's window), truth against each "
                 "method; y axis up to 3x the true peak (or 1 m/s)", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    return save_figure(fig, path)


def write_results(out: Path, results: Mapping[str, Any], plot: bool = True) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    generated = "groups" in results
    files = {"table": write_csv(out / "table.csv", table_csv_rows(results["table"],
                                                                  [] if generated else results["motions"])),
             "runs": write_csv(out / "runs.csv", run_csv_rows(results["runs"]))}
    if generated:
        files["groups"] = write_csv(out / "table_groups.csv", [{"group": name, **row} for name, g in
                                                               results["groups"].items()
                                                               for row in table_csv_rows(g["table"], [])])
        files["captures"] = write_csv(out / "captures.csv", capture_csv_rows(results))
        files["report"] = out / "report.txt"
        (out / "report.txt").write_text(format_generated(results) + "\n")
    tmp = out / ".benchmark.json.partial"
    tmp.write_text(json.dumps(results, indent=1, default=str))
    tmp.replace(out / "benchmark.json")
    files["json"] = out / "benchmark.json"
    if plot:
        p = plot_per_frame_errors(out / "fig7_per_frame_error.png", results["runs"], results["methods"],
                                  results["motions"])
        if p is not None:
            files["plot"] = p
        p = plot_speeds(out / "fig_end_effector_speed.png", results["runs"], results["methods"], results["motions"])
        if p is not None:
            files["speed_plot"] = p
        p = plot_reliability(out / "fig_reliability.png", results["runs"], results["methods"])
        if p is not None:
            files["reliability_plot"] = p
    return files


def main(argv: Sequence[str], config_dir: Path) -> int:
    """``eventcap benchmark [benchmark=PRESET] [benchmark key=value ...] [run overrides ...]``."""
    preset, _, _ = split_overrides(argv, set())
    probe = compose_benchmark(config_dir, preset, [])  # the preset's own keys (a generated suite has more)
    preset, bench_ov, run_ov = split_overrides(argv, set(probe))
    cfg = compose_benchmark(config_dir, preset, bench_ov)
    logging.getLogger().setLevel(str(cfg.get("log_level", "WARNING")).upper())
    logging.getLogger("eventcap.apps.benchmark").setLevel(logging.INFO)
    bench = Benchmark(cfg, config_dir, run_ov)
    try:
        bench.active_methods()  # composes the common run overrides once: a bad one stops here, not in every run
    except Exception as exc:
        if type(exc).__module__.startswith(("hydra", "omegaconf")):
            raise ValueError(f"{exc}\n(arguments that are not benchmark keys are overrides of every run; the "
                             f"benchmark keys: {', '.join(sorted(probe))}, benchmark=PRESET)") from exc
        raise
    from eventcap.core.rundir import RunFolderBusy, claim, release

    try:  # held until the benchmark ends: two benchmarks writing into one folder would mix their runs and tables
        claim(bench.out, what="benchmark", key="out")
    except RunFolderBusy as exc:
        raise ValueError(f"{exc} (a benchmark's folder is out=..., runs/benchmark/<name> by default)") from None
    try:
        results = bench.run(echo=lambda s: print(s, flush=True))
        files = write_results(bench.out, results, plot=bool(cfg.get("plot", True)))
    finally:
        release(bench.out)
    seq = (f"{len(bench.motions)} motion(s) x {len(bench.seeds)} seed(s) x {cfg['duration_s']} s; AE after "
           f"Procrustes, every 10th tracking frame")
    print()
    if bench.real:
        from eventcap.apps.real_suite import format_real

        text = format_real(results["runs"])
        (bench.out / "report.txt").write_text(text + "\n")
        print(text)
    elif bench.draws:
        print(format_generated(results))
    else:
        print(format_tables(results["table"], bench.motions, seq, results.get("per_capture")))
        if results.get("uncertainty"):
            print()
            print(format_reliability(results["uncertainty"]))
    print()
    print("wrote " + ", ".join(str(p) for p in files.values()))
    bad = results["failures"]
    if bad:
        print(f"{len(bad)} run(s) incomplete, failed or refused: "
              + "; ".join(f"{f['capture']} {f['method']}: {f['reason']}" for f in bad[:5])
              + (" (all listed above)" if bench.draws else ""), file=sys.stderr)
        return 1
    return 0
