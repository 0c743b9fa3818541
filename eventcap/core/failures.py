"""The one line a run ends with when it is incomplete: what failed, counted by cause, with the first examples.

A run that failed in hundreds of batches used to end with every failed and skipped unit listed (one 3,762-character
line) and the advice to run the same command again, which cannot help when the failure is deterministic (the same
inputs fail the same way). :func:`failure_summary` groups the failures of each node by their status (the stage's
``StageFailed.status`` or the exception's type), counts them against the node's batches, names the first few
batches of each cause, quotes the first error once (in full: it often ends with the stage's advice), counts the
nodes skipped because of them, and gives advice only for causes where it can help (:data:`ADVICE`). ``run.json``
keeps every failure in full.
"""

from __future__ import annotations

from collections import Counter

#: Advice for a failure status, given only where it changes what a user does. Transient causes (a killed worker,
#: no memory, an interrupted run) go away by running again (committed results are reused); deterministic ones do not.
ADVICE: dict[str, str] = {
    "BrokenProcessPool": "a worker process died (killed or out of memory): run the same command again, committed "
                         "results are reused",
    "MemoryError": "out of memory: fewer workers (executor.workers) or a shorter window (source.t_end_s), then run "
                   "again; committed results are reused",
    "KeyboardInterrupt": "interrupted: run the same command again to resume",
    "missing_detections": "no usable detection at those batches' frames: the detect node's log names the images "
                          "without a person",
    "no_detections": "no usable detection at those batches' frames: the detect node's log names the images without "
                     "a person",
    # no_person, too_few_detections: the detect stage's own message says what to look at
}


def _batches(indices: list[int], examples: int) -> str:
    shown = ", ".join(str(i) for i in indices[:examples])
    return shown + (", ..." if len(indices) > examples else "")


def _node_total(rep) -> int:
    """Units of a node: its batches (cached, computed, failed, skipped) or 1 for a whole node."""
    return rep.cached + rep.computed + len(rep.failed) + rep.skipped if rep.per_batch else 1


def _failed_part(name: str, rep, examples: int) -> str:
    counts = Counter(f["status"] or "failed" for f in rep.failed)
    if not rep.per_batch or all(f.get("batch") is None for f in rep.failed):
        return f"{name} failed ({', '.join(counts)})"
    causes = []
    for status, n in counts.most_common():
        idx = sorted(f["batch"] for f in rep.failed if (f["status"] or "failed") == status and f["batch"] is not None)
        word = "batch" if len(idx) == 1 else "batches"
        causes.append(f"{n} {status} ({word} {_batches(idx, examples)})")
    return f"{name} failed in {len(rep.failed)} of {_node_total(rep)} batches: {', '.join(causes)}"


def _skipped_part(result, failed_nodes: list[str]) -> str:
    """Skipped nodes, grouped and counted: those downstream of this run's failures by name only, others with their
    cause (in full)."""
    downstream, other = [], {}
    for name, rep in result.nodes.items():
        if not rep.skipped:
            continue
        what = f"{name} ({rep.skipped} of {_node_total(rep)} batches)" if rep.per_batch and rep.skip_causes and \
            rep.skip_causes[0].get("batch") is not None else name
        causes = [c["cause"] for c in rep.skip_causes] or [""]
        roots = [c.removeprefix("upstream failed: ") for c in causes]
        if any(r.split(":")[0].split("[")[0] in failed_nodes for r in roots):
            downstream.append(what)
        else:
            other.setdefault(" ".join(str(causes[0]).split()), []).append(what)
    parts = []
    if downstream:
        parts.append(f"skipped because of it: {_nodes(downstream)}")
    parts += [f"skipped: {_nodes(names)} ({cause})" if cause else f"skipped: {_nodes(names)}"
              for cause, names in other.items()]
    return "; ".join(parts)


def _nodes(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{len(names)} nodes ({', '.join(names)})"


def failure_summary(result, examples: int = 3, first_error: bool = True) -> str:
    """One line saying why a run is incomplete (``result``: a :class:`eventcap.core.runner.RunResult`).

    ``solve failed in 187 of 201 batches: 180 missing_detections (batches 3, 4, 5, ...), 7
    Maximum_Iterations_Exceeded (batches 12, 40, 41, ...); skipped because of it: 2 nodes (refine (187 of 201
    batches), evaluate); first error: solve[batch 3]: ...``, then advice for the causes :data:`ADVICE` knows. Empty
    for a complete run. Nothing in it is cut: the first error often ends with the stage's advice.
    ``first_error=False`` names the first error's node without quoting it (the run's log showed it in full where
    it happened)."""
    failed_nodes = [n for n, r in result.nodes.items() if r.failed]
    parts = [_failed_part(n, result.nodes[n], examples) for n in failed_nodes]
    skipped = _skipped_part(result, failed_nodes)
    if skipped:
        parts.append(skipped)
    if failed_nodes:
        first = result.nodes[failed_nodes[0]].failed
        f0 = min(first, key=lambda f: -1 if f.get("batch") is None else f["batch"])
        where = failed_nodes[0] + (f"[batch {f0['batch']}]" if f0.get("batch") is not None else "")
        error = " ".join(str(f0.get("error", "")).split())
        parts.append(f"first error: {where}: {error}" if first_error else f"the first error is above ({where})")
    statuses = dict.fromkeys(f["status"] for r in result.nodes.values() for f in r.failed)
    advice = [ADVICE[s] for s in statuses if s in ADVICE]
    if advice:
        parts.append("advice: " + "; ".join(advice))
    parts.append("every failure in full: run.json")
    return "; ".join(parts)
