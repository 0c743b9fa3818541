"""Run function of the chunks stage: the recording's batches grouped into chunks of about ``seconds`` each."""

from __future__ import annotations

import numpy as np

from eventcap.artifacts import BatchPlan
from eventcap.core.stage import StageFailed


def chunk_rows(t0_us: np.ndarray, t1_us: np.ndarray, seconds: float) -> list[tuple[int, int]]:
    """(first, last) batch of each chunk: consecutive batches, a new chunk once the current one spans ``seconds``;
    a last chunk spanning less than half of that joins the one before it."""
    span_us = float(seconds) * 1e6
    rows: list[list[int]] = []
    for k in range(len(t0_us)):
        if rows and t1_us[rows[-1][1]] - t0_us[rows[-1][0]] < span_us - 0.5:
            rows[-1][1] = k
        else:
            rows.append([k, k])
    if len(rows) > 1 and t1_us[rows[-1][1]] - t0_us[rows[-1][0]] < span_us / 2:
        tail = rows.pop()
        rows[-1][1] = tail[1]
    return [(a, z) for a, z in rows]


def run_chunks(inputs, config, ctx):
    plan = inputs["batches"]
    if len(plan) == 0:
        raise StageFailed("the recording's batch plan is empty: nothing to cut into chunks", status="invalid_input")
    rows = chunk_rows(plan.t0_us, plan.t1_us, float(config.seconds))
    first = np.array([a for a, _ in rows], dtype=np.int64)
    last = np.array([z for _, z in rows], dtype=np.int64)
    ctx.log.info("%d batches in %d chunk(s) of about %g s (%s batches)", len(plan), len(rows), config.seconds,
                 ", ".join(str(z - a + 1) for a, z in rows[:8]) + (", ..." if len(rows) > 8 else ""))
    return {"chunks": BatchPlan(t0_us=np.asarray(plan.t0_us)[first].copy(), t1_us=np.asarray(plan.t1_us)[last].copy(),
                                frame0=np.asarray(plan.frame0)[first].copy())}
