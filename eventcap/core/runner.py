"""Runs a validated pipeline: cache lookups, per-batch fan-out, failures, progress and the run summary.

The runner owns all I/O: a task (one node, or one batch of a per-batch node) loads its inputs from the cache, calls the
stage's pure run function and commits the outputs atomically. The same task function runs in-process (``serial``) or
in worker processes (``processes``), so results do not depend on the executor. Resuming is running the same command
again: every committed node and batch is a cache hit.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import socket
import time
import traceback
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eventcap.artifact import forget_windows
from eventcap.artifacts import Artifact, ArtifactError, Batch, BatchPlan, Metrics
from eventcap.core.cache import Cache, CacheCorruptError, Entry, EntryLock, explain_difference, make_key
from eventcap.core.config import ConfigError, build_config, build_settings, config_to_dict, file_digests, result_config
from eventcap.params import param
from eventcap.errors import ComputationFailed
from eventcap.memo import ProcessCache, clear_process_caches, memoize
from eventcap.core.pipeline import Node, build_pipeline
from eventcap.core.registry import Registry, load_registry
from eventcap.core.runrecord import NodeReport, RunRecord, RunRecordError
from eventcap.core.stage import StageContext, StageSpec

log = logging.getLogger("eventcap.core.runner")

#: Threads per worker for BLAS/OpenMP; pinned because oversubscription on small machines makes small products many
#: times slower (docs/results/implementation.md).
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


# ---------------------------------------------------------------------------------------------------------------------
# Tasks: picklable descriptions of one unit of work, executed by execute_task in any process.
# ---------------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InputRefSpec:
    """Where a task reads one input: a single entry, or all batches of a per-batch upstream node (``all_batches``;
    with ``whole``, the one entry of a whole-recording upstream node, read as a sequence of one). ``window``: only
    the rows within (t0_us, t1_us) of the entry's time dimensions (``Port.window``), read for this task alone."""

    stage: str
    port: str
    keys: tuple[str, ...]
    all_batches: bool = False
    plan: tuple[tuple[int, int, int, int], ...] = ()  # (index, t0_us, t1_us, frame0) per key when all_batches
    whole: bool = False
    window: tuple[int, int] | None = None
    without: tuple[str, ...] = ()


@dataclass(frozen=True)
class Task:
    cache_root: str
    node: str
    stage: str
    config: dict[str, Any]
    config_path: str
    inputs: dict[str, InputRefSpec]
    key: str
    doc: dict[str, Any]
    batch: Batch | None = None
    n_batches: int = 0
    #: another run is computing this entry: return "busy" at once instead of waiting for it (the driver runs the
    #: task again later, after the others)
    defer_if_busy: bool = False
    #: the worker checks that its stage is the driver's before computing (:func:`_same_stage_as_driver`): set for
    #: tasks sent to Dask, whose workers may run on other machines from other installs
    check_install: bool = False


@dataclass
class TaskResult:
    node: str
    key: str
    batch: int | None
    status: str  # "computed" | "failed" | "loaded" (committed by another run meanwhile) | "busy" (see Task)
    elapsed_s: float = 0.0
    error: str = ""
    failure_status: str = ""


class BatchSequence(Sequence):
    """All batches of a per-batch output, loaded one at a time from the cache (the driver never holds them all);
    ``batches`` names them. A whole-recording output is a sequence of one, its ``batches`` ``[None]``."""

    def __init__(self, cache: Cache, ref: InputRefSpec, cls: type[Artifact]):
        self._cache, self._ref, self._cls = cache, ref, cls
        self.batches: list[Batch | None] = [None] if ref.whole else [Batch(*row) for row in ref.plan]

    def __len__(self) -> int:
        return len(self._ref.keys)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return _load(str(self._cache.root), self._ref.stage, self._ref.keys[i], self._ref.port, self._cls)


@memoize("runner.cache_at", maxsize=16)
def _cache_at(root: str) -> Cache:
    return Cache(root)


def unit_window(plan: BatchPlan, unit: Batch, margin: int) -> tuple[int, int]:
    """(t0_us, t1_us) of a unit (a batch, or a chunk of batches) with ``margin`` batches of ``plan`` on each side:
    the batches of the plan that overlap the unit, widened by ``margin`` rows (within the plan); the unit's own
    range when none overlaps."""
    t0, t1 = np.asarray(plan.t0_us), np.asarray(plan.t1_us)
    over = np.flatnonzero((t0 < unit.t1_us) & (t1 > unit.t0_us))
    if over.size == 0:
        return int(unit.t0_us), int(unit.t1_us)
    a, z = max(int(over[0]) - margin, 0), min(int(over[-1]) + margin, len(plan) - 1)
    return min(int(t0[a]), int(unit.t0_us)), max(int(t1[z]), int(unit.t1_us))


def artifact_nbytes(a: Artifact) -> int:
    """The bytes of an artifact's arrays (its children's included)."""
    n = sum(int(v.nbytes) for f in type(a).array_fields() if (v := getattr(a, f)) is not None)
    return n + sum(artifact_nbytes(v) for f in type(a).child_fields() if (v := getattr(a, f)) is not None)


#: Artifacts this process loaded or committed, by (cache root, stage, key, port): a node's outputs are read by the
#: nodes after it without reading them back. Bounded by count and by their arrays' bytes; the bytes bound is well
#: above a long capture's recording: a recording evicted by smaller entries would be read again by every task that
#: needs it (docs/results/implementation.md). A capture-long artifact (one with time dimensions: the recording, the
#: latent images) stays only while the tasks read it whole: a task drops those it does not read whole before it
#: loads its inputs (:func:`_drop_capture_artifacts`), so a chunk's solver never sits beside the whole recording.
#: Windowed inputs (``Port.window``) are read for their task alone and never kept here.
_ARTIFACTS = ProcessCache("runner.inputs", maxsize=32, max_bytes=2 << 30, weigh=artifact_nbytes)


def _drop_capture_artifacts(keep: set[tuple]) -> int:
    """Drop from the memo the capture-long artifacts (``Artifact.has_time_dims``) not under a key in ``keep``;
    returns how many were dropped."""
    return _ARTIFACTS.discard(lambda key, value: key not in keep and type(value).has_time_dims())


def _load(root: str, stage: str, key: str, port: str, cls: type[Artifact],
          window: tuple[int, int] | None = None, without: tuple[str, ...] = ()) -> Artifact:
    def read() -> Artifact:
        cache = _cache_at(root)
        entry = cache.lookup(stage, key)
        if entry is None:
            raise CacheCorruptError(f"input {stage}/{key} ({port}) is not in the cache at {root}")
        return cache.load(entry, port, cls, window, without)

    if window is not None:  # one task's part of the capture: read for it alone
        return read()
    value, _ = _ARTIFACTS.get((root, stage, key, port), read)
    if not isinstance(value, cls):  # kept as another type than this reader declares: read it as that
        return read()
    return value


@memoize("runner.registry", maxsize=1)
def _registry() -> Registry:
    return load_registry()


def execute_task(task: Task) -> TaskResult:
    """Load inputs, run the stage, commit or record the failure. Never raises for a stage's own error.

    The entry's lock is held while computing: when another run (or worker) is computing the same entry, this waits
    for it (or, with ``task.defer_if_busy``, returns "busy") and then returns "loaded" if it was committed."""
    t0 = time.perf_counter()
    bidx = task.batch.index if task.batch is not None else None
    what = f"{task.node}" + (f" batch {bidx}" if bidx is not None else "")
    lock = EntryLock(task.cache_root, task.key)

    def waiting(holder: str, waited_s: float) -> None:
        log.info("%s: waiting for another run computing entry %s/%s (%s; %.0f s so far)", what, task.stage,
                 task.key[:12], holder, waited_s)

    try:
        if not lock.acquire(blocking=not task.defer_if_busy, owner=f"node {what}", on_wait=waiting):
            return TaskResult(task.node, task.key, bidx, "busy")
    except OSError as exc:  # no lock here (e.g. a read-only cache): computing still reports the real problem
        log.warning("%s: cannot lock cache entry %s (%s); computing it without the lock", what, task.key[:12], exc)
    try:
        if _committed_meanwhile(task):
            return TaskResult(task.node, task.key, bidx, "loaded", time.perf_counter() - t0)
        return _compute(task, t0, bidx)
    finally:
        lock.release()


def _committed_meanwhile(task: Task) -> bool:
    """Whether a good entry for the task's key exists now (committed by another run while this one waited)."""
    cache = _cache_at(task.cache_root)
    entry = cache.lookup(task.stage, task.key)
    if entry is None:
        return False
    try:
        spec = _registry().get(task.stage)
        want = {p: port.type.schema_signature() for p, port in spec.outputs.items()}
        if want != {p: o.get("schema") for p, o in entry.manifest["outputs"].items()}:
            return False  # written by other code; the driver's next lookup quarantines it
        cache.verify(entry)
    except CacheCorruptError as exc:
        cache.quarantine(entry.path, str(exc))
        return False
    return True


def _compute(task: Task, t0: float, bidx: int | None) -> TaskResult:
    cache = _cache_at(task.cache_root)
    try:
        spec = _registry().get(task.stage)
        config = build_config(spec, task.config, task.config_path)
        if task.check_install:
            _same_stage_as_driver(task, spec, config)
        _drop_capture_artifacts({(task.cache_root, r.stage, k, r.port) for r in task.inputs.values()
                                 if r.window is None for k in r.keys})
        inputs: dict[str, Any] = {}
        for port, ref in task.inputs.items():
            cls = spec.inputs[port].type
            if ref.all_batches:
                inputs[port] = BatchSequence(cache, ref, cls)
            else:
                inputs[port] = _load(task.cache_root, ref.stage, ref.keys[0], ref.port, cls, ref.window, ref.without)
        ctx = StageContext(node=task.node, stage=task.stage, batch=task.batch,
                           log=logging.getLogger(f"eventcap.core.stage.{task.node}"),
                           progress=_ProgressLog(task.node) if task.batch is None else None)
        outputs = spec.load_run()(inputs, config, ctx)
        _check_outputs(spec, task.node, outputs)
        info = {"node": task.node, "batch": task.batch.as_key() if task.batch else None,
                "elapsed_s": round(time.perf_counter() - t0, 6)}
        if ctx.stats:
            info["stats"] = json.loads(json.dumps(ctx.stats, default=float))
        cache.commit(task.stage, task.key, task.doc, outputs, info)
        for port, artifact in outputs.items():  # what the next nodes read, without reading it back
            _ARTIFACTS.put((task.cache_root, task.stage, task.key, port), artifact)
        return TaskResult(task.node, task.key, bidx, "computed", time.perf_counter() - t0)
    except Exception as exc:  # recorded, reported, never cached as success
        # a stage's StageFailed and the library's own ComputationFailed errors (eventcap.errors, the energy's
        # SolveFailed and EnergyError among them) carry their status
        status = exc.status if isinstance(exc, ComputationFailed) else type(exc).__name__
        record = {"node": task.node, "batch": task.batch.as_key() if task.batch else None, "status": status,
                  "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(),
                  "details": getattr(exc, "details", {})}
        try:
            cache.record_failure(task.stage, task.key, task.doc, record)
        except OSError as werr:  # the failure itself is still reported to the driver
            log.error("could not record failure of %s: %s", task.node, werr)
        return TaskResult(task.node, task.key, bidx, "failed", time.perf_counter() - t0,
                          f"{type(exc).__name__}: {exc}", status)


class WorkerMismatch(ComputationFailed):
    """A worker whose installed stage is not the one the driver keyed the task with (another version of eventcap or
    of a plugin, other defaults, other data files): what it would compute is not what the key says."""


def _same_stage_as_driver(task: Task, spec: StageSpec, config: Any) -> None:
    """Refuse to compute a task on a worker whose stage differs from the driver's: the stage's name, version, full
    config (its defaults included) and data files' digests, as this process sees them, must equal those the driver
    put in the task's key document. Only a worker on another machine or another install can differ (a Dask worker
    started from another checkout); the driver's own processes always agree."""
    mine = base_doc(spec, config, task.config_path)
    theirs = {k: task.doc.get(k) for k in mine}
    if mine == theirs:
        return
    differ = [k for k in mine if mine[k] != theirs[k]]
    detail = "; ".join(
        f"{k}: here {mine[k]!r}, the driver's {theirs[k]!r}" if k in ("stage", "version") else
        f"{k}: here differs at {', '.join(sorted(_differing_keys(mine[k], theirs[k]))[:5]) or 'the whole value'}"
        for k in differ)
    raise WorkerMismatch(f"{task.node}: this worker ({socket.gethostname()}, pid {os.getpid()}) has another stage "
                         f"{task.stage!r} than the driver ({detail}); install the same eventcap and plugins, from "
                         f"the same commit, with the same data files, on every worker", status="worker_mismatch")


def _differing_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """The dotted keys at which two nested dicts differ (the top key when either is not a dict)."""
    if not isinstance(a, Mapping) or not isinstance(b, Mapping):
        return [prefix] if a != b and prefix else []
    out = []
    for k in sorted(set(a) | set(b), key=str):
        out += _differing_keys(a.get(k), b.get(k), f"{prefix}.{k}" if prefix else str(k))
    return out


class _ProgressLog:
    """Progress of a long whole-recording stage: a log line every 10 s or 25 %, whichever comes first."""

    def __init__(self, node: str):
        self.node, self.t0, self.last_t, self.last_frac = node, time.perf_counter(), time.perf_counter(), 0.0

    def __call__(self, done: int, total: int) -> None:
        frac = done / total if total else 1.0
        now = time.perf_counter()
        if frac >= 1.0 or now - self.last_t >= 10.0 or frac - self.last_frac >= 0.25:
            eta = (now - self.t0) * (1 - frac) / frac if frac > 0 else float("nan")
            log.info("%s: %3.0f%% (%.1f s elapsed, ~%.0f s left)", self.node, 100 * frac, now - self.t0, eta)
            self.last_t, self.last_frac = now, frac


def _check_outputs(spec: StageSpec, node: str, outputs: Any) -> None:
    if not isinstance(outputs, Mapping):
        raise ArtifactError(f"node {node!r}: stage {spec.name!r} returned {type(outputs).__name__}, expected a dict of outputs")
    if set(outputs) != set(spec.outputs):
        raise ArtifactError(
            f"node {node!r}: stage {spec.name!r} returned outputs {sorted(outputs)}, declared {sorted(spec.outputs)}"
        )
    for port, value in outputs.items():
        want = spec.outputs[port].type
        if not isinstance(value, want):
            raise ArtifactError(f"node {node!r}: output {port!r} must be a {want.__name__}, got {type(value).__name__}")


def base_doc(spec: StageSpec, config: Any, where: str) -> dict[str, Any]:
    """The part of a cache key document that comes from the stage itself: name, version, config, file digests."""
    return {
        "stage": spec.name,
        "version": spec.version,
        "config": result_config(spec, config),
        "files": file_digests(spec, config, where),
    }


# ---------------------------------------------------------------------------------------------------------------------
# Executors
# ---------------------------------------------------------------------------------------------------------------------
@dataclass
class ExecutorConfig:
    """The ``executor:`` settings of a run (conf/executor/<kind>.yaml state only what differs from these)."""

    kind: str = param("serial", choices=("serial", "processes", "dask"),
                      help="serial (in this process) | processes (a local pool over batches) | dask (a LocalCluster, "
                           "or the scheduler at address)")
    workers: int = param(2, ge=1, le=256, help="processes / dask LocalCluster: worker processes")
    threads_per_worker: int = param(1, ge=1, help="BLAS/OpenMP/numba threads per worker")
    address: str | None = param(None, help="dask: the scheduler's address, tcp://host:8786 (null: start a "
                                           "LocalCluster on this machine)")
    retries: int = param(2, ge=0, help="dask: resubmissions of a task whose worker raised an infrastructure error")

    #: seconds to wait for a TCP connection to ``address`` before the run is refused
    CONNECT_TIMEOUT_S = 3.0

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any] | None) -> ExecutorConfig:
        """Checked executor settings: every key and value named as ``executor.<key>`` with what it takes, before
        anything runs (a dask scheduler that cannot be reached included)."""
        cfg = build_settings(cls, values, "executor")
        if cfg.address is not None:
            if not isinstance(cfg.address, str) or not cfg.address.strip():
                raise ValueError(f"executor.address: expected a scheduler address such as tcp://host:8786, or null, "
                                 f"got {cfg.address!r}")
            if cfg.kind == "dask":
                _check_reachable(cfg.address, cfg.CONNECT_TIMEOUT_S)
        return cfg


def _check_reachable(address: str, timeout_s: float) -> None:
    """Refuse a Dask scheduler address that is malformed or does not accept a TCP connection within timeout_s."""
    import socket
    from urllib.parse import urlsplit

    url = urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        host, port = url.hostname, url.port
    except ValueError:
        host, port = None, None
    if url.scheme not in ("tcp", "tls") or not host or port is None:
        raise ValueError(f"executor.address: expected tcp://host:port (e.g. tcp://scheduler:8786), got {address!r}")
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise ValueError(f"executor.address: no Dask scheduler reachable at {address} ({exc.strerror or exc}; "
                         f"waited at most {timeout_s:g} s); start one (dask scheduler) or set executor.address=null "
                         f"for a LocalCluster") from None


class _DaskPool:
    """A dask.distributed client that looks like an executor to the runner (submit + as_completed)."""

    def __init__(self, client, retries: int):
        self.client, self.retries = client, retries

    def map_unordered(self, fn, tasks: list[Task]) -> Iterator[TaskResult]:
        from distributed import as_completed

        # the waiting pass gets keys of its own: the scheduler would hand back the first pass's "busy" result
        tasks = [dataclasses.replace(t, check_install=True) for t in tasks]  # workers may be other installs
        futures = [self.client.submit(fn, t, key=f"{t.node}-b{t.batch.index if t.batch else 'all'}-{t.key[:12]}"
                                      f"{'' if t.defer_if_busy else '-wait'}", retries=self.retries, pure=False)
                   for t in tasks]
        for fut in as_completed(futures):
            yield fut.result()
            fut.release()  # results are small, but nothing stays held on the scheduler either


class _ProcessPool:
    """A local process pool that is started again when a worker dies (``kill -9``, the OOM killer): the batches it
    was running are submitted again, at most ``MAX_RESTARTS`` times per run (a worker dying every time is a bug)."""

    MAX_RESTARTS = 3

    def __init__(self, make):
        self._make, self.pool, self.restarts = make, make(), 0

    def submit(self, fn, *args):
        return self.pool.submit(fn, *args)

    def restart(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.pool = self._make()
        self.restarts += 1


def _init_worker(level: int, parent_pid: int | None = None) -> None:
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if parent_pid is not None:  # a worker never outlives its driver, even a driver killed by kill -9
        from eventcap.core.lifeline import die_with_parent

        die_with_parent(parent_pid)


@contextmanager
def _executor(cfg: ExecutorConfig) -> Iterator[Any]:
    if cfg.kind == "serial":
        yield None
        return
    if cfg.kind not in ("processes", "dask"):
        raise ValueError(f"executor.kind: expected 'serial', 'processes' or 'dask', got {cfg.kind!r}")
    import multiprocessing as mp

    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update({k: str(cfg.threads_per_worker) for k in THREAD_ENV})
    try:
        if cfg.kind == "processes":
            # spawn, not fork: zarr and tqdm run background threads, and forking a threaded process can deadlock.
            pool = _ProcessPool(lambda: ProcessPoolExecutor(
                max_workers=cfg.workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                initargs=(logging.getLogger().level, os.getpid())))
            try:
                yield pool
            finally:
                pool.pool.shutdown()
        else:
            yield from _dask(cfg)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _dask(cfg: ExecutorConfig) -> Iterator[_DaskPool]:
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError("executor=dask needs dask.distributed: pip install 'dask[distributed]'") from None
    if cfg.address:
        log.info("dask: connecting to the scheduler at %s", cfg.address)
        with Client(cfg.address, timeout="30s") as client:
            yield _DaskPool(client, cfg.retries)
        return
    log.info("dask: starting a LocalCluster with %d workers x %d thread", cfg.workers, 1)
    for attempt in range(1, cfg.retries + 2):  # a worker killed while the cluster starts fails the whole start
        try:
            cluster = LocalCluster(n_workers=cfg.workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.WARNING)
            break
        except RuntimeError as exc:
            if attempt > cfg.retries:
                raise ValueError(f"executor=dask: the LocalCluster did not start ({attempt} attempts): {exc}") from exc
            log.warning("dask: the LocalCluster did not start (%s); trying again", exc)
    with cluster, Client(cluster) as client:
        yield _DaskPool(client, cfg.retries)


# ---------------------------------------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------------------------------------
@dataclass
class RunResult:
    nodes: dict[str, NodeReport]
    metrics: dict[str, Any]
    #: cache key of each whole node that got one (also when it then failed: see ``nodes``)
    node_keys: dict[str, str] = field(default_factory=dict)
    #: per-batch nodes: batch index -> cache key, for the committed batches only
    batch_keys: dict[str, dict[int, str]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(not r.failed and not r.skipped for r in self.nodes.values())

    def computed_keys(self) -> int:
        return sum(r.computed for r in self.nodes.values())

    def committed(self, node: str) -> dict[int | None, str]:
        """The committed cache entries of a node: ``{None: key}`` for a whole node that succeeded, ``{batch index:
        key}`` for the committed batches of a per-batch node, ``{}`` when nothing of it was committed."""
        rep = self.nodes.get(node)
        if rep is None:
            raise KeyError(f"node {node!r} is not in this run (nodes: {', '.join(self.nodes)})")
        if rep.per_batch:
            return dict(sorted(self.batch_keys.get(node, {}).items()))
        if rep.failed or rep.skipped or node not in self.node_keys:
            return {}
        return {None: self.node_keys[node]}


class Runner:
    """Executes the pipeline described by a composed config mapping (see conf/config.yaml)."""

    def __init__(self, cfg: Mapping[str, Any], registry: Registry | None = None):
        self.cfg = cfg
        self.registry = registry or load_registry()
        self.nodes = build_pipeline(cfg, self.registry)
        self.by_name = {n.name: n for n in self.nodes}
        # the tasks' own instance (in this process): an entry is checked against its manifest once
        self.cache = _cache_at(str(Cache(cfg.get("cache_dir") or "runs/cache").root))
        self.executor = ExecutorConfig.from_mapping(cfg.get("executor"))
        self.selection = _parse_selection(cfg.get("batches"))
        #: ``batches=`` selects rows of the first batch plan the pipeline cuts by (the recording's batches); a plan
        #: made from it (chunks of batches) runs the rows that overlap the selected batches
        self.primary_plan = next(((n.plan_node, n.plan_port) for n in self.nodes if n.spec.per_batch and n.plan_node
                                  and not self.by_name[n.plan_node].spec.per_batch), None)

    def _base_doc(self, node: Node) -> dict[str, Any]:
        return base_doc(node.spec, node.config, node.config_path)

    def run(self, run_dir: str | Path | None = None) -> RunResult:
        # every run checks what it reads against the manifests again (files may have changed between runs)
        self.cache.forget_verified()
        _ARTIFACTS.clear()
        forget_windows()
        self.cache.clean_orphans()
        reports: dict[str, NodeReport] = {}
        node_keys: dict[str, str] = {}  # node-level key (whole nodes: the entry key)
        batch_keys: dict[str, dict[int, str]] = {}  # per-batch nodes: batch index -> key (only successful ones)
        plans: dict[str, list[Batch]] = {}
        # (node, batch index or None) -> the failure a failed or skipped unit goes back to: "<node>[batch k]: <cause>"
        self._roots: dict[tuple[str, int | None], str] = {}
        t_run = time.perf_counter()
        # batches= is checked against each batch plan as soon as the plan exists, before the nodes after it run
        plan_ports = dict([self.primary_plan]) if self.primary_plan else {}
        not_run: str | None = None  # why the nodes after a refused batch selection do not run
        with _executor(self.executor) as pool:
            for i, node in enumerate(self.nodes, 1):
                t0 = time.perf_counter()
                rep = NodeReport(node.name, node.spec.name, node.spec.per_batch)
                reports[node.name] = rep
                label = f"[{i}/{len(self.nodes)}] {node.name} ({node.spec.name} v{node.spec.version})"
                if not_run is not None:
                    rep.skipped = 1
                    rep.skip_causes.append({"batch": None, "cause": not_run})
                    self._roots[(node.name, None)] = not_run
                    plans.setdefault(node.name, [])
                    batch_keys.setdefault(node.name, {})
                    log.debug("%s: skipped, %s", label, not_run)  # counted once in the run's closing summary
                    continue
                try:
                    if not node.spec.per_batch:
                        root = self._upstream_root(node, None)
                        if root is not None:
                            self._skip(rep, None, root, label)
                            continue
                        self._run_whole(node, self._base_doc(node), node_keys, batch_keys, plans, rep, label)
                    else:
                        self._run_batches(node, node_keys, batch_keys, plans, rep, label, pool)
                    if node.name in plan_ports and self.selection is not None and not rep.failed and not rep.skipped:
                        not_run = self._check_selection(node, plan_ports[node.name], node_keys)
                        if not_run is not None:
                            log.error("%s", not_run)
                except Exception as exc:  # noqa: BLE001 - the driver's own failure for this node (a config that
                    # cannot be keyed, a missing file, an unreadable plan): recorded, and the run goes on
                    self._fail_node(node, rep, label, exc)
                    plans.setdefault(node.name, [])
                    batch_keys.setdefault(node.name, {})
                finally:
                    rep.elapsed_s = time.perf_counter() - t0
                    self._release_memos(i)
        self.cache.clean_orphans()  # also those of writers killed just before this run started
        try:
            metrics = self._collect_metrics(reports, node_keys)
        except Exception as exc:  # noqa: BLE001 - the summary is still written
            log.error("metrics could not be collected: %s: %s", type(exc).__name__, exc)
            metrics = {}
        result = RunResult(reports, metrics, dict(node_keys), {n: dict(k) for n, k in batch_keys.items()})
        n_comp = result.computed_keys()
        n_hit = sum(r.cached for r in reports.values())
        n_fail = sum(len(r.failed) for r in reports.values())
        n_skip = sum(r.skipped for r in reports.values())
        log.info("run finished in %.1f s: %d computed, %d cached, %d failed%s", time.perf_counter() - t_run,
                 n_comp, n_hit, n_fail, f", {n_skip} skipped" if n_skip else "")
        if run_dir is not None:
            self._write_summary(Path(run_dir), result, node_keys, batch_keys)
        return result

    def _release_memos(self, done: int) -> None:
        """Once the last node whose stage runs from a package has run (``done`` nodes have), empty that package's
        process memos (``<package>.*``: a solve's built solvers, hundreds of MB): the nodes after it (evaluate,
        confidence) read the whole recording, and should not do so beside them."""
        import gc

        def package(node: Node) -> str:
            module = node.spec.run.partition(":")[0]
            return module.rpartition(".")[0] or module

        later = {package(n) for n in self.nodes[done:]}
        pkg = package(self.nodes[done - 1])
        if pkg in later or pkg in ("eventcap", "eventcap.core"):
            return
        dropped = {k: v for k, v in clear_process_caches(pkg + ".").items() if v}
        if dropped:
            gc.collect()  # a built solver holds reference cycles
            log.debug("released the process memos of %s: %s", pkg, dropped)

    # -- failures and skips ---------------------------------------------------------------------------------------
    def _check_selection(self, plan_node: Node, port: str, node_keys) -> str | None:
        """Why ``batches=`` cannot be cut from the batch plan ``plan_node.port`` (None when it can). 'N' asks for at
        most the first N batches; 'start:stop' must lie within the plan."""
        plan = _load(str(self.cache.root), plan_node.spec.name, node_keys[plan_node.name], port, BatchPlan)
        n = len(plan)
        start, stop = self.selection
        first_n = start == 0 and stop is not None and not str(self.cfg.get("batches")).count(":")
        if n == 0:
            return None  # an empty plan is reported by each per-batch node
        if (start or 0) >= n or (not first_n and stop is not None and stop > n):
            return (f"batches={self.cfg.get('batches')!r} is out of range: the batch plan {plan_node.name}.{port} has "
                    f"{n} batch{'es' if n != 1 else ''} (0..{n - 1}); give N <= {n} (the first N) or 'start:stop' "
                    f"within 0:{n}")
        if first_n and stop > n:
            log.warning("batches=%s: the batch plan %s.%s has only %d batches; running all of them", stop,
                        plan_node.name, port, n)
        return None

    def _upstream_root(self, node: Node, batch: int | None) -> str | None:
        """The failure a unit of ``node`` (a whole node: ``batch`` None) cannot run without, or ``None``.

        A whole upstream node, or a per-batch upstream node as a whole (no plan, no batches), counts for every
        unit; a per-batch upstream's batch counts for the same batch of a per-batch node, and any of its batches for
        a whole node or an ``all_batches`` input (which read all of them)."""
        for port, ref in node.inputs.items():
            up = ref.node
            if (up, None) in self._roots:
                return self._roots[(up, None)]
            if not self.by_name[up].spec.per_batch:
                continue
            every = node.spec.inputs[port].all_batches
            if batch is not None and node.spec.per_batch and not every:
                if (up, batch) in self._roots:
                    return self._roots[(up, batch)]
            elif every or (batch is None and not node.spec.per_batch):
                bad = sorted(k for (n, k) in self._roots if n == up and k is not None)
                if bad:
                    more = f" (and {len(bad) - 1} more failed or skipped batch(es) of {up})" if len(bad) > 1 else ""
                    return self._roots[(up, bad[0])] + more
        if node.spec.per_batch and batch is None and (node.plan_node, None) in self._roots:
            return self._roots[(node.plan_node, None)]
        return None

    def _skip(self, rep: NodeReport, batch: int | None, root: str, label: str | None) -> None:
        rep.skipped += 1
        cause = f"upstream failed: {root}"
        rep.skip_causes.append({"batch": batch, "cause": cause})
        self._roots[(rep.node, batch)] = root
        if label is not None:  # the failure was logged where it happened; the skips are counted in the run's summary
            log.debug("%s: skipped, %s", label, cause)

    def _fail_node(self, node: Node, rep: NodeReport, label: str, exc: BaseException) -> None:
        error = f"{type(exc).__name__}: {exc}"
        rep.failed.append({"batch": None, "status": type(exc).__name__, "error": error, "key": ""})
        self._roots[(node.name, None)] = f"{node.name}: {error}"
        log.error("%s: FAILED (%s): %s", label, type(exc).__name__, error)

    def load_output(self, result: RunResult, output: str) -> dict[int | None, Artifact]:
        """The committed artifacts of output ``node.port`` of a finished run, read from the cache: ``{None:
        artifact}`` for a whole node, ``{batch index: artifact}`` (committed batches, in order) for a per-batch node;
        ``{}`` when the node committed nothing (it failed or was skipped)."""
        node_name, _, port = str(output).partition(".")
        node = self.by_name.get(node_name)
        if node is None or port not in node.spec.outputs:
            raise ValueError(f"{output!r} is not '<node>.<port>' of this pipeline (nodes: {', '.join(self.by_name)})")
        cls = node.spec.outputs[port].type
        return {i: _load(str(self.cache.root), node.spec.name, key, port, cls)
                for i, key in result.committed(node_name).items()}

    def _input_specs(self, node: Node, node_keys, batch_keys, plans, batch: Batch | None) -> tuple[dict, dict]:
        """Input references for a task and the matching key material."""
        refs, keydoc = {}, {}
        used = node.spec.used_inputs(node.config)
        for port, ref in node.inputs.items():
            if port not in used:  # not read with this config: not loaded, not in the key
                continue
            up = self.by_name[ref.node]
            if up.spec.per_batch and node.spec.per_batch and not node.spec.inputs[port].all_batches:
                k = batch_keys[ref.node][batch.index]
                refs[port] = InputRefSpec(up.spec.name, ref.port, (k,))
                keydoc[port] = k
            elif up.spec.per_batch:
                sel = plans[ref.node]
                keys = tuple(batch_keys[ref.node][b.index] for b in sel)
                refs[port] = InputRefSpec(up.spec.name, ref.port, keys, True,
                                          tuple((b.index, b.t0_us, b.t1_us, b.frame0) for b in sel))
                keydoc[port] = node_keys[ref.node]
                if self.selection is not None:
                    keydoc[port] = {"node_key": node_keys[ref.node], "batches": [b.index for b in sel]}
            else:
                every = node.spec.inputs[port].all_batches  # a whole output read as a sequence of one
                margin = node.spec.inputs[port].margin(node.config) if batch is not None else None
                window = self._window(batch, margin, node_keys) if margin is not None else None
                refs[port] = InputRefSpec(up.spec.name, ref.port, (node_keys[ref.node],), every, whole=every,
                                          window=window, without=node.spec.inputs[port].without if window else ())
                keydoc[port] = node_keys[ref.node]  # the window follows from the unit and the config: not keyed
        return refs, keydoc

    def _window(self, unit: Batch, margin: int, node_keys) -> tuple[int, int] | None:
        """The time range a unit's windowed inputs read (``Port.window``): from the unit's start to its end, widened
        by ``margin`` batches of the recording's plan (all of it, whatever ``batches=`` selects) on each side;
        None (read whole) when the pipeline has no recording plan."""
        if self.primary_plan is None:
            return None
        plan_node, port = self.by_name[self.primary_plan[0]], self.primary_plan[1]
        plan = _load(str(self.cache.root), plan_node.spec.name, node_keys[plan_node.name], port, BatchPlan)
        return unit_window(plan, unit, margin)

    def _why(self, node: Node, doc: dict[str, Any], batch: int | None) -> str:
        old = self.cache.latest_for(node.spec.name, node.name, batch)
        if old is None:
            return "no earlier result for this node"
        diff = explain_difference(old["doc"], doc)
        return "; ".join(diff[:4]) + (" ..." if len(diff) > 4 else "") if diff else "entry was removed"

    def _run_whole(self, node, base, node_keys, batch_keys, plans, rep, label) -> None:
        refs, keydoc = self._input_specs(node, node_keys, batch_keys, plans, None)
        doc = {**base, "inputs": keydoc}
        key = make_key(doc)
        node_keys[node.name] = key
        rep.keys = [key]
        entry = self._lookup(node.spec.name, key)
        if entry is not None:
            rep.cached = 1
            log.info("%s: cached (key %s, computed %s)", label, key[:12], entry.manifest.get("created"))
            return
        log.info("%s: computing (key %s; cache miss: %s)", label, key[:12], self._why(node, doc, None))
        task = Task(str(self.cache.root), node.name, node.spec.name, config_to_dict(node.config), node.config_path,
                    refs, key, doc)
        res = execute_task(task)
        if res.status == "computed":
            rep.computed = 1
            rep.computed_keys.append(key)
            log.info("%s: computed in %.2f s", label, res.elapsed_s)
        elif res.status == "loaded":
            rep.cached = 1
            log.info("%s: committed by another run meanwhile (waited %.2f s): loaded, not recomputed", label,
                     res.elapsed_s)
        else:
            rep.failed.append({"batch": None, "status": res.failure_status, "error": res.error, "key": key})
            self._roots[(node.name, None)] = f"{node.name}: {res.error}"
            log.error("%s: FAILED (%s): %s", label, res.failure_status, res.error)

    def _lookup(self, stage: str, key: str) -> Entry | None:
        entry = self.cache.lookup(stage, key)
        if entry is None:
            return None
        spec = self.registry.get(stage)
        want = {p: port.type.schema_signature() for p, port in spec.outputs.items()}
        have = {p: o.get("schema") for p, o in entry.manifest["outputs"].items()}
        if want != have:
            self.cache.quarantine(entry.path, f"written with other output schemas {have}, this code writes {want}")
            return None
        try:
            self.cache.verify(entry)
        except CacheCorruptError as exc:
            self.cache.quarantine(entry.path, str(exc))
            return None
        return entry

    def _plan_for(self, node: Node, node_keys, select: bool = True) -> list[Batch]:
        plan_node = self.by_name[node.plan_node]
        plan = _load(str(self.cache.root), plan_node.spec.name, node_keys[plan_node.name], node.plan_port, BatchPlan)
        batches = plan.batches()
        if select and self.selection is not None:
            start, stop = self.selection
            if (node.plan_node, node.plan_port) == self.primary_plan or self.primary_plan is None:
                return batches[start:stop]
            first = self.by_name[self.primary_plan[0]]
            chosen = _load(str(self.cache.root), first.spec.name, node_keys[first.name], self.primary_plan[1],
                           BatchPlan).batches()[start:stop]
            if not chosen:
                return []
            t0, t1 = chosen[0].t0_us, chosen[-1].t1_us
            batches = [b for b in batches if b.t0_us < t1 and b.t1_us > t0]
        return batches

    def _run_batches(self, node, node_keys, batch_keys, plans, rep, label, pool) -> None:
        from tqdm import tqdm

        plans[node.name] = []
        batch_keys[node.name] = {}
        root = self._upstream_root(node, None)
        if root is not None:
            self._skip(rep, None, root, label)
            return
        base = self._base_doc(node)
        batches = self._plan_for(node, node_keys)
        plans[node.name] = batches
        if not batches:
            n_plan = len(self._plan_for(node, node_keys, select=False))
            why = (f"the batch plan of {node.plan_node} is empty" if not n_plan else
                   f"batches={self.cfg.get('batches')!r} selects none of the {n_plan} batches of {node.plan_node}")
            rep.skipped = 1
            rep.skip_causes.append({"batch": None, "cause": f"no batches to run: {why}"})
            self._roots[(node.name, None)] = f"{node.name}: no batches to run: {why}"
            log.error("%s: skipped, no batches to run: %s", label, why)
            return
        # Node-level key: the per-batch upstreams enter by their node-level keys; used by whole-recording consumers.
        used = node.spec.used_inputs(node.config)
        node_doc = {**base, "inputs": {p: node_keys[r.node] for p, r in node.inputs.items() if p in used}}
        node_keys[node.name] = make_key(node_doc)
        keys: dict[int, str] = {}
        batch_keys[node.name] = keys
        todo: list[Task] = []
        same = [r for p, r in node.inputs.items()  # per-batch inputs read batch by batch
                if self.by_name[r.node].spec.per_batch and not node.spec.inputs[p].all_batches]
        for b in batches:
            root = self._upstream_root(node, b.index)
            if root is None and any(b.index not in batch_keys.get(r.node, {}) for r in same):
                root = next(f"{r.node}[batch {b.index}]: not in the upstream node's batch plan"
                            for r in same if b.index not in batch_keys.get(r.node, {}))
            if root is not None:
                self._skip(rep, b.index, root, None)
                log.debug("%s: batch %d skipped, upstream failed: %s", node.name, b.index, root)
                continue
            refs, keydoc = self._input_specs(node, node_keys, batch_keys, plans, b)
            doc = {**base, "inputs": keydoc, "batch": b.as_key()}
            key = make_key(doc)
            rep.keys.append(key)
            if self._lookup(node.spec.name, key) is not None:
                keys[b.index] = key
                rep.cached += 1
                continue
            todo.append(Task(str(self.cache.root), node.name, node.spec.name, config_to_dict(node.config),
                             node.config_path, refs, key, doc, b, len(batches)))
        why = f"; cache miss: {self._why(node, todo[0].doc, todo[0].batch.index)}" if todo else ""
        log.info("%s: %d batches: %d cached, %d to compute%s%s", label, len(batches), rep.cached, len(todo),
                 f", {rep.skipped} skipped (upstream failed)" if rep.skipped else "", why)
        if not todo:
            return
        bar = tqdm(total=len(batches), initial=rep.cached, desc=node.name, unit="batch", leave=False,
                   disable=None, dynamic_ncols=True)
        try:
            for res in self._execute(todo, pool):
                bar.update(1)
                if res.status == "computed":
                    keys[res.batch] = res.key
                    rep.computed += 1
                    rep.computed_keys.append(res.key)
                    log.info("%s: batch %d/%d computed in %.2f s", node.name, res.batch + 1, len(batches), res.elapsed_s)
                elif res.status == "loaded":
                    keys[res.batch] = res.key
                    rep.cached += 1
                    log.info("%s: batch %d/%d committed by another run meanwhile (waited %.2f s): loaded, not "
                             "recomputed", node.name, res.batch + 1, len(batches), res.elapsed_s)
                else:
                    first = next((f["batch"] for f in rep.failed if f["status"] == res.failure_status), None)
                    rep.failed.append({"batch": res.batch, "status": res.failure_status, "error": res.error,
                                       "key": res.key})
                    self._roots[(node.name, res.batch)] = f"{node.name}[batch {res.batch}]: {res.error}"
                    if first is None:
                        log.error("%s: batch %d FAILED (%s): %s", node.name, res.batch, res.failure_status, res.error)
                    else:  # one cause's error in full once; every one is in run.json
                        log.error("%s: batch %d FAILED (%s, as batch %d)", node.name, res.batch, res.failure_status,
                                  first)
        finally:
            bar.close()

    def _execute(self, tasks: list[Task], pool) -> Iterator[TaskResult]:
        """Results of ``tasks`` as they finish. Tasks whose entry another run is computing right now are put off
        until the others are done (this run computes what nobody else does first), then waited for."""
        later = {}
        for res in self._execute_pass([dataclasses.replace(t, defer_if_busy=True) for t in tasks], pool):
            if res.status == "busy":
                later[res.key] = res
            else:
                yield res
        if later:
            todo = [t for t in tasks if t.key in later]
            log.info("%s: %d batch(es) being computed by another run: waiting for them", todo[0].node, len(todo))
            yield from self._execute_pass(todo, pool)

    def _execute_pass(self, tasks: list[Task], pool) -> Iterator[TaskResult]:
        if pool is None:
            for t in tasks:
                yield execute_task(t)
            return
        if isinstance(pool, _DaskPool):
            yield from pool.map_unordered(execute_task, tasks)
            return
        pending = {pool.submit(execute_task, t): t for t in tasks}
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            lost = []
            for fut in done:
                task = pending.pop(fut)
                try:
                    yield fut.result()
                except BrokenProcessPool:
                    lost.append(task)
            if not lost:
                continue
            for fut in [f for f in pending if f.done() and not f.cancelled() and f.exception() is None]:  # finished before the break
                yield pending.pop(fut).result()
            lost += list(pending.values())
            if pool.restarts >= pool.MAX_RESTARTS:
                raise BrokenProcessPool(f"a worker process died {pool.restarts + 1} times in this run (killed, or out "
                                        f"of memory?); giving up")
            log.warning("a worker process died (killed, or out of memory?): starting the pool again and resubmitting "
                        "%d task(s) of %s", len(lost), lost[0].node)
            pool.restart()
            pending = {pool.submit(execute_task, t): t for t in lost}

    # -- outputs --------------------------------------------------------------------------------------------------
    def _collect_metrics(self, reports, node_keys) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for node in self.nodes:
            if node.spec.per_batch or node.name not in node_keys or reports[node.name].failed or reports[node.name].skipped:
                continue
            for port, p in node.spec.outputs.items():
                if issubclass(p.type, Metrics):
                    m = _load(str(self.cache.root), node.spec.name, node_keys[node.name], port, Metrics)
                    out[f"{node.name}.{port}"] = m.values
        return out

    def _write_summary(self, run_dir: Path, result: RunResult, node_keys, batch_keys) -> None:
        run_dir.mkdir(parents=True, exist_ok=True)
        RunRecord(result.ok, str(self.cache.root), dict(result.nodes)).write(run_dir)
        self._export(run_dir, node_keys, batch_keys, result)
        if result.metrics:  # a run that measured nothing writes no metrics.json (run.json says why)
            (run_dir / "metrics.json").write_text(json.dumps(result.metrics, indent=1, default=str))

    def _export(self, run_dir: Path, node_keys, batch_keys, result: RunResult) -> None:
        """Copy the outputs named in ``export`` (``node.port``) into the run folder as standalone zarr groups:
        ``<node>.<port>.zarr``, or for a per-batch node ``<node>.<port>/batch<NNNN>.zarr`` per committed batch."""
        import shutil

        for item in self.cfg.get("export") or []:
            node_name, _, port = str(item).partition(".")
            node = self.by_name.get(node_name)
            if node is None or port not in node.spec.outputs:
                raise ValueError(f"export: {item!r} is not '<node>.<port>' of this pipeline")
            if node_name not in node_keys or (not node.spec.per_batch and (
                    result.nodes[node_name].failed or result.nodes[node_name].skipped)):
                log.warning("export: %s not available (the node did not succeed)", item)
                continue
            if node.spec.per_batch:
                items = [(run_dir / f"{node_name}.{port}" / f"batch{i:04d}.zarr", k)
                         for i, k in sorted(batch_keys[node_name].items())]
            else:
                items = [(run_dir / f"{node_name}.{port}.zarr", node_keys[node_name])]
            for dest, key in items:
                entry = self.cache.lookup(node.spec.name, key)
                shutil.rmtree(dest, ignore_errors=True)
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copytree(entry.path / "data" / port, dest)
            log.info("exported %s to %s", item, items[0][0].parent if node.spec.per_batch else items[0][0])


def _parse_selection(value) -> tuple[int | None, int | None] | None:
    """``batches=`` config: null (all), ``N`` (first N) or ``start:stop``. A selection that is empty whatever the
    plan (N=0, stop <= start) or negative is refused here, before anything runs; one beyond the plan is refused
    once the plan exists (:meth:`Runner._check_selection`)."""
    if value in (None, "", "all"):
        return None
    expected = "expected null (every batch), N (the first N batches) or 'start:stop' with 0 <= start < stop"
    sel = None
    if isinstance(value, int) and not isinstance(value, bool):
        sel = (0, value)
    elif isinstance(value, str) and ":" in value:
        a, _, b = value.partition(":")
        try:
            sel = (int(a) if a.strip() else None, int(b) if b.strip() else None)
        except ValueError:
            pass
    elif isinstance(value, str) and value.strip().lstrip("-").isdigit():
        sel = (0, int(value))
    if sel is None:
        raise ConfigError(f"batches={value!r}: {expected}")
    start, stop = sel
    if (start is not None and start < 0) or (stop is not None and stop < 0):
        raise ConfigError(f"batches={value!r}: batch indices count from 0 (no negative indices); {expected}")
    if stop is not None and stop <= (start or 0):
        what = f"N={stop} selects no batch" if ":" not in str(value) else \
            f"an empty slice (stop {stop} is not after start {start or 0})"
        raise ConfigError(f"batches={value!r}: {what}; {expected}")
    return sel


def load_finished_run(run_dir: str | Path) -> tuple[Runner, RunResult]:
    """``(runner, result)`` of a finished run folder, rebuilt from its ``config.yaml`` and ``run.json`` without
    running anything: every committed output the run recorded is read back from the cache. RunRecordError (naming
    the file and what to do) when the folder is not a finished run or its cache entries are gone."""
    import yaml

    run_dir = Path(run_dir)
    cfg_path, summary_path = run_dir / "config.yaml", run_dir / "run.json"
    for p in (cfg_path, summary_path):
        if not p.is_file():
            raise RunRecordError(f"{run_dir}: not a finished run folder (no {p.name}; `eventcap run` writes it)")
    cfg = yaml.safe_load(cfg_path.read_text()) or {}
    record = RunRecord.read(run_dir)
    cache_dir = record.cache_path(run_dir, cfg.get("cache_dir") or "runs/cache")
    cfg["cache_dir"] = str(cache_dir)
    try:
        runner = Runner(cfg)
    except Exception as exc:  # noqa: BLE001 - e.g. a stage no longer installed
        raise RunRecordError(f"{cfg_path}: cannot rebuild the run's pipeline: {exc}") from exc
    cache = Cache(cache_dir)
    node_keys, batch_keys, missing = {}, {}, []
    for name, rep in record.nodes.items():
        if name not in runner.by_name:
            raise RunRecordError(f"{summary_path}: node {name!r} is not in the pipeline of {cfg_path}")
        failed_keys = {f.get("key") for f in rep.failed}
        if not rep.per_batch:
            if rep.keys and not rep.failed and not rep.skipped:
                node_keys[name] = rep.keys[0]
                if cache.lookup(rep.stage, rep.keys[0]) is None:
                    missing.append(name)
            continue
        committed = {}
        for key in rep.keys:
            if key in failed_keys:
                continue
            entry = cache.lookup(rep.stage, key)
            if entry is None:
                missing.append(f"{name} ({key[:12]})")
                continue
            committed[int(entry.manifest["batch"]["index"])] = key
        batch_keys[name] = dict(sorted(committed.items()))
    if missing:
        raise RunRecordError(f"{run_dir}: {len(missing)} of the run's cache entries are gone from {cache_dir} "
                             f"({', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}); run the same command "
                             f"again to restore them (the overrides are in {run_dir / '.hydra' / 'overrides.yaml'}), "
                             f"or use `eventcap view {run_dir} --recompute`")
    metrics = {}
    if (run_dir / "metrics.json").is_file():
        metrics = json.loads((run_dir / "metrics.json").read_text())
    return runner, RunResult(record.nodes, metrics, node_keys, batch_keys)


def reset_process_caches() -> None:
    """Forget every process cache (eventcap.memo): the registry, caches and loaded inputs, the stages' built problems
    (after changing EVENTCAP_STAGES or files on disk)."""
    clear_process_caches()
