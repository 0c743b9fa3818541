"""The pipeline DAG as data: nodes from ``conf/pipeline/*.yaml``, checked before anything runs.

A pipeline config looks like::

    nodes:
      source: {config: source}                       # node config lives at cfg.source (default: cfg.stages.<node>)
      track:  {inputs: {recording: source.recording, batches: source.batches}}

Each node's config mapping holds ``stage: <registered stage name>`` plus that stage's parameters. Validation
reports every problem at once, each naming the node and what was expected: unknown stage, unknown port, unknown
upstream node, type mismatch, missing input, batch-wiring mistakes, and cycles.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from eventcap.artifacts import BatchPlan
from eventcap.core.config import ConfigError, build_config, check_file_settings
from eventcap.core.registry import Registry, UnknownStageError, unknown_name_message
from eventcap.core.stage import StageSpec


class PipelineError(ValueError):
    """The pipeline config is inconsistent; lists every problem found."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("invalid pipeline:\n  - " + "\n  - ".join(problems))


@dataclass(frozen=True)
class InputRef:
    node: str
    port: str

    def __str__(self) -> str:
        return f"{self.node}.{self.port}"


@dataclass(frozen=True)
class Node:
    """A validated node: its stage spec, typed config, and where each input comes from."""

    name: str
    spec: StageSpec
    config: Any
    config_path: str
    inputs: Mapping[str, InputRef]
    plan_node: str | None  # for per-batch nodes: the node whose BatchPlan output cuts this node's batches
    plan_port: str | None


def _get_path(cfg: Mapping[str, Any], dotted: str) -> Any:
    cur: Any = cfg
    for part in dotted.split("."):
        if not isinstance(cur, Mapping) or part not in cur:
            return None
        cur = cur[part]
    return cur


def build_pipeline(cfg: Mapping[str, Any], registry: Registry) -> list[Node]:
    """Validated nodes in topological order, or PipelineError listing every problem."""
    problems: list[str] = []
    pipe = cfg.get("pipeline") or {}
    raw_nodes = pipe.get("nodes") if isinstance(pipe, Mapping) else None
    if not isinstance(raw_nodes, Mapping) or not raw_nodes:
        raise PipelineError(["pipeline.nodes: expected a mapping of node name -> {config, inputs}, found none"])
    specs, configs, paths, raw_inputs = _read_nodes(cfg, raw_nodes, registry, problems)
    refs = {name: _wire_inputs(name, spec, raw_inputs[name], raw_nodes, specs, problems)
            for name, spec in specs.items()}
    order = _toposort(refs, problems)
    if problems:
        raise PipelineError(problems)
    plans = _batch_plans(order, specs, refs, problems)
    if problems:
        raise PipelineError(problems)
    return [
        Node(
            name=n, spec=specs[n], config=configs[n], config_path=paths[n], inputs=refs[n],
            plan_node=(plans[n] or (None, None))[0], plan_port=(plans[n] or (None, None))[1],
        )
        for n in order
    ]


def _read_nodes(cfg: Mapping[str, Any], raw_nodes: Mapping[str, Any], registry: Registry, problems: list[str]):
    """Each node's stage spec, typed config, config path and raw ``inputs`` mapping (nodes whose stage cannot be
    resolved have no spec; every problem is appended to ``problems``)."""
    specs: dict[str, StageSpec] = {}
    configs: dict[str, Any] = {}
    paths: dict[str, str] = {}
    raw_inputs: dict[str, Mapping[str, Any]] = {}
    for name, node in raw_nodes.items():
        node = node or {}
        unknown = set(node) - {"config", "inputs"}
        if unknown:
            problems.append(f"node {name!r}: unknown keys {sorted(unknown)}; a node has 'config' and 'inputs'")
        path = node.get("config") or f"stages.{name}"
        paths[name] = path
        raw_inputs[name] = node.get("inputs") or {}
        values = _get_path(cfg, path)
        if not isinstance(values, Mapping):
            problems.append(
                f"node {name!r}: its config {path!r} is missing from the composed config "
                f"(select a variant, e.g. {path.replace('.', '/')}=<variant>, or set 'config:' on the node)"
            )
            continue
        if "stage" not in values:
            problems.append(f"node {name!r}: config {path!r} must name its stage ('stage: <name>')")
            continue
        try:
            spec = registry.get(str(values["stage"]))
        except UnknownStageError as exc:
            problems.append(f"node {name!r} ({path}.stage): {exc}")
            continue
        specs[name] = spec
        try:
            configs[name] = build_config(spec, {k: v for k, v in values.items() if k != "stage"}, path)
            check_file_settings(spec, configs[name], path)
            check = spec.load_check()
            if check is not None:
                check(configs[name], path)
        except (ConfigError, ValueError) as exc:
            problems.append(f"node {name!r}: {exc}")
    return specs, configs, paths, raw_inputs


def _wire_inputs(name: str, spec: StageSpec, given: Mapping[str, Any], raw_nodes: Mapping[str, Any],
                 specs: Mapping[str, StageSpec], problems: list[str]) -> dict[str, InputRef]:
    """Node ``name``'s input ports -> their upstream outputs, each checked; problems are appended."""
    refs: dict[str, InputRef] = {}
    for port, src in given.items():
        ref = _wire_input(name, spec, port, src, raw_nodes, specs, problems)
        if ref is not None:
            refs[port] = ref
    for port, p in spec.inputs.items():
        if port not in given and not p.optional:
            problems.append(
                f"node {name!r}: required input {port!r} ({p.type.__name__}) is not connected; "
                f"add inputs: {{{port}: <node>.<port>}}"
            )
    return refs


def _wire_input(name: str, spec: StageSpec, port: str, src: Any, raw_nodes: Mapping[str, Any],
                specs: Mapping[str, StageSpec], problems: list[str]) -> InputRef | None:
    """The upstream output ``src`` ('<node>.<port>') of input ``port``, or None with the problem appended (nothing
    is appended for an upstream node whose own problem was already reported)."""
    if port not in spec.inputs:
        problems.append(
            f"node {name!r}: " + unknown_name_message("input port", port, list(spec.inputs), f"stage {spec.name!r}")
        )
        return None
    if not isinstance(src, str) or src.count(".") != 1:
        problems.append(f"node {name!r}: input {port!r} must be '<node>.<port>', got {src!r}")
        return None
    up, up_port = src.split(".")
    if up not in raw_nodes:
        problems.append(f"node {name!r}: input {port!r} <- {src!r}: " + unknown_name_message("node", up, list(raw_nodes)))
        return None
    if up not in specs:
        return None  # already reported
    up_spec = specs[up]
    if up_port not in up_spec.outputs:
        problems.append(
            f"node {name!r}: input {port!r} <- {src!r}: "
            + unknown_name_message("output port", up_port, list(up_spec.outputs), f"node {up!r} (stage {up_spec.name!r})")
        )
        return None
    want, have = spec.inputs[port], up_spec.outputs[up_port]
    if not issubclass(have.type, want.type):
        problems.append(
            f"node {name!r}: input {port!r} expects {want.type.__name__}, but {src} is a {have.type.__name__}"
        )
        return None
    if up_spec.per_batch and not spec.per_batch and not want.all_batches:
        problems.append(
            f"node {name!r}: input {port!r} <- {src} is produced per batch, but stage {spec.name!r} runs on the "
            f"whole recording and its port is not declared all_batches=True"
        )
        return None
    return InputRef(up, up_port)


def _batch_plans(order: list[str], specs: Mapping[str, StageSpec], refs: Mapping[str, Mapping[str, InputRef]],
                 problems: list[str]) -> dict[str, tuple[str, str] | None]:
    """For each per-batch node, the (node, port) of the BatchPlan that cuts its batches (None for whole nodes);
    a per-batch node with no plan or with two different plans is a problem. An input that reads all batches of a
    per-batch upstream cuts only when no other input does (a chunk's solve reads every batch's tracks)."""
    plans: dict[str, tuple[str, str] | None] = {}
    for name in order:
        spec = specs[name]
        if not spec.per_batch:
            plans[name] = None
            continue
        candidates = set()
        ports = refs[name]
        if spec.plan and spec.plan in ports:  # the stage names the plan that cuts it; its other plans are data
            ports = {p: r for p, r in ports.items() if p == spec.plan or not issubclass(spec.inputs[p].type, BatchPlan)}
        read_all = set()  # the plans of inputs read whole (all batches): they cut only when nothing else does
        for port, ref in ports.items():
            if specs[ref.node].outputs[ref.port].type is BatchPlan or issubclass(spec.inputs[port].type, BatchPlan):
                candidates.add((ref.node, ref.port))
            elif specs[ref.node].per_batch:
                (read_all if spec.inputs[port].all_batches else candidates).add(plans[ref.node])
        candidates = candidates or read_all
        if not candidates:
            problems.append(
                f"node {name!r}: stage {spec.name!r} runs per batch, so it needs a BatchPlan input "
                f"(e.g. batches: source.batches) or an input from another per-batch node"
            )
        elif len(candidates) > 1:
            problems.append(
                f"node {name!r}: its inputs are cut into batches by different plans: "
                + ", ".join(f"{n}.{p}" for n, p in sorted(candidates))
            )
        plans[name] = next(iter(candidates)) if len(candidates) == 1 else None
    return plans


def _toposort(refs: dict[str, dict[str, InputRef]], problems: list[str]) -> list[str]:
    deps = {n: {r.node for r in ins.values() if r.node in refs} for n, ins in refs.items()}
    order: list[str] = []
    ready = sorted(n for n, d in deps.items() if not d)
    remaining = {n: set(d) for n, d in deps.items() if d}
    while ready:
        n = ready.pop(0)
        order.append(n)
        for m in sorted(remaining):
            remaining[m].discard(n)
            if not remaining[m]:
                del remaining[m]
                ready.append(m)
    if remaining:
        cycle = _find_cycle({n: remaining[n] for n in remaining})
        problems.append("cycle in the pipeline: " + " -> ".join(cycle) + " (a node cannot depend on its own output)")
    return order


def _find_cycle(deps: dict[str, set[str]]) -> list[str]:
    start = sorted(deps)[0]
    path, seen = [start], {start: 0}
    while True:
        nxt = sorted(d for d in deps[path[-1]] if d in deps)[0]
        if nxt in seen:
            return path[seen[nxt]:] + [nxt]
        seen[nxt] = len(path)
        path.append(nxt)
