"""Solver plumbing every solve shares: pinned IPOPT options, status checks, numpy callbacks, pose bounds.

The solves (the paper's batch solve, the refinement, the spline solve) build their NLPs once per run with CasADi
and evaluate their heavy terms in numpy; these are the pieces they have in common (moved from the batch-solve
plugin without change in behaviour).
"""

from __future__ import annotations

import dataclasses

import math
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from eventcap.body.skeleton import (
    DOF_NAMES,
    NUM_POSE_PARAMS,
    ROOT_ROTATION_NAMES,
    ROOT_TRANSLATION_NAMES,
    pose_bounds,
)
from eventcap.names import unknown_name_message

from .errors import EnergyError, SolveFailed

#: IPOPT return statuses accepted as success.
SUCCESS_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_NP = NUM_POSE_PARAMS
PARAM_NAMES = DOF_NAMES + ROOT_ROTATION_NAMES + ROOT_TRANSLATION_NAMES


#: the adaptive barrier's largest mu in the warm-started solves (see IpoptSettings.options)
ADAPTIVE_MU_MAX = 1e-3


@dataclass(frozen=True)
class IpoptSettings:
    """IPOPT options that are pinned for speed and reproducibility (fixed when the problem is built). The three a
    stage's config states (max_iter, tol, mumps_pivot_order) have no default here; the rest are this library's.

    Batch solves start from good estimates (interpolation, previous ICP round): a monotone barrier starting at a
    tiny ``mu_init`` keeps IPOPT from first pushing the many joint angles that sit on their limits into the
    interior (fewer iterations than the adaptive default: docs/results/implementation.md). Detection fits start from a crude guess and use IPOPT's adaptive barrier.
    """

    max_iter: int  # iteration limit per solve; reaching it is a failure (the stage's config states it)
    tol: float  # IPOPT's (scaled) convergence tolerance (the stage's config)
    mumps_pivot_order: int  # MUMPS ordering, pinned (its automatic choice may differ between machines; the config)
    acceptable_tol: float = 1e-4  # "solved to acceptable level" after acceptable_iter iterations below it
    acceptable_iter: int = 10
    mu_init: float = 1e-7  # initial barrier parameter of the (warm-started) batch solves
    bound_push: float = 1e-4  # how far batch solves move the warm start away from the bounds (relative)
    barrier: str = "monotone"  # the warm-started solves' barrier: monotone from mu_init, or IPOPT's adaptive one

    def __post_init__(self) -> None:
        if isinstance(self.max_iter, bool) or int(self.max_iter) != self.max_iter or self.max_iter < 0:
            raise ValueError(f"IpoptSettings.max_iter: expected an integer >= 0, got {self.max_iter!r}")
        for name in ("tol", "acceptable_tol", "mu_init", "bound_push"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"IpoptSettings.{name}: expected a number > 0, got {v!r}")
        if self.barrier not in ("monotone", "adaptive"):
            raise ValueError(f"IpoptSettings.barrier: expected monotone | adaptive, got {self.barrier!r}")
        if self.mumps_pivot_order not in range(8):
            raise ValueError(f"IpoptSettings.mumps_pivot_order: expected 0..7, got {self.mumps_pivot_order!r}")

    @classmethod
    def from_config(cls, config) -> IpoptSettings:
        """The pinned settings with a solve's stated options (:class:`eventcap.energy.settings.IpoptConfig`)."""
        return cls(max_iter=config.max_iter, tol=config.tol, mumps_pivot_order=config.mumps_pivot_order,
                   barrier=str(getattr(config, "barrier", "monotone")))

    def restart(self) -> IpoptSettings:
        """The settings of a solve that starts from an earlier solution: a monotone barrier from ``mu_init``."""
        return dataclasses.replace(self, barrier="monotone")

    def options(self, warm: bool) -> dict:
        """nlpsol options; ``warm``: for the warm-started batch solves (else: the detection fits)."""
        opts = {
            "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            # An ipopt.opt in the working directory would silently override everything below.
            "ipopt.option_file_name": "",
            "ipopt.linear_solver": "mumps", "ipopt.hessian_approximation": "exact",
            "ipopt.mumps_pivot_order": int(self.mumps_pivot_order),
            "ipopt.max_iter": int(self.max_iter), "ipopt.tol": float(self.tol),
            "ipopt.acceptable_tol": float(self.acceptable_tol), "ipopt.acceptable_iter": int(self.acceptable_iter),
            "calc_lam_p": False, "no_nlp_grad": True, "error_on_fail": False,
        }
        if warm and self.barrier == "adaptive":  # IPOPT's defaults: mu from 0.1, bounds pushed by 1e-2
            # The barrier never grows above ADAPTIVE_MU_MAX: from a warm start, IPOPT's own cap (1e5) let the oracle
            # raise mu and jump a window with a missed detection into a far basin (the body 15 m deep, a higher
            # energy, "Solve_Succeeded"); capped, the same window stays at the monotone solve's minimum.
            opts.update({"ipopt.mu_strategy": "adaptive", "ipopt.mu_max": ADAPTIVE_MU_MAX})
        elif warm:
            opts.update({"ipopt.mu_strategy": "monotone", "ipopt.mu_init": float(self.mu_init),
                         "ipopt.bound_push": float(self.bound_push), "ipopt.bound_frac": float(self.bound_push)})
        return opts



@dataclass(frozen=True)
class SolveStats:
    """One IPOPT solve."""

    status: str
    iterations: int
    seconds: float
    n_correspondences: int = 0



class NumpyCallback(ca.Callback):
    """A CasADi function of one dense vector evaluated by numpy (IPOPT calls it through CasADi).

    Inputs and outputs are exchanged through CasADi's buffers (no DM conversion: ~3 ms per Hessian saved).
    ``fn(v)`` returns one array per output: its nonzeros in CasADi's (column-major) order.
    """

    def __init__(self, name: str, n_in: int, sparsity_out: list, fn):
        ca.Callback.__init__(self)
        self._n_in, self._sp_out, self._fn = n_in, sparsity_out, fn
        self.construct(name, {})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return len(self._sp_out)

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self._n_in, 1)

    def get_sparsity_out(self, i):
        return self._sp_out[i]

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        outs = self._fn(np.frombuffer(arg[0], dtype=np.float64))
        for r, o in zip(res, outs):
            np.frombuffer(r, dtype=np.float64)[:] = o
        return 0


def block_tridiagonal_triu(n_blocks: int, size: int):
    """Sparsity of the upper triangle of a block-tridiagonal matrix, and how to fill it from numpy blocks.

    Returns (sparsity, (diag_index, upper_index, order)): with ``v = concat(diag[diag_index], upper[upper_index])``
    for diag (B, size, size) and upper (B-1, size, size) [block (i, i+1)], ``v[order]`` are the nonzeros in
    CasADi's (column-major) order.
    """
    rows, cols, src = [], [], []
    n_diag = 0
    diag_idx = ([], [], [])
    up_idx = ([], [], [])
    for b in range(n_blocks):
        for c in range(size):
            for r in range(c + 1):
                rows.append(b * size + r), cols.append(b * size + c), src.append(n_diag)
                diag_idx[0].append(b), diag_idx[1].append(r), diag_idx[2].append(c)
                n_diag += 1
    n_up = 0
    for b in range(n_blocks - 1):
        for c in range(size):
            for r in range(size):
                rows.append(b * size + r), cols.append((b + 1) * size + c), src.append(-1 - n_up)
                up_idx[0].append(b), up_idx[1].append(r), up_idx[2].append(c)
                n_up += 1
    rows, cols, src = np.array(rows), np.array(cols), np.array(src)
    src = np.where(src >= 0, src, n_diag - 1 - src)
    order = np.lexsort((rows, cols))  # column-major: by column, then row
    sp = ca.Sparsity.triplet(n_blocks * size, n_blocks * size, rows[order].tolist(), cols[order].tolist())
    return sp, (tuple(np.array(i) for i in diag_idx), tuple(np.array(i) for i in up_idx), src[order])



class _BoundsError(EnergyError):
    def __init__(self, message: str):
        super().__init__(message, status="invalid_bounds")


def checked_bounds(lower, upper, who: str) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (33,) of the pose parameters: the given ones, or :func:`skeleton.pose_bounds` for None; checked for
    shape and order (errors name ``who`` and the first offending parameter)."""
    lo, hi = pose_bounds()
    lower = lo if lower is None else np.asarray(lower, dtype=np.float64)
    upper = hi if upper is None else np.asarray(upper, dtype=np.float64)
    if lower.shape != (_NP,) or upper.shape != (_NP,):
        raise ValueError(f"{who}: lower/upper bounds must have shape (33,), got {lower.shape}, {upper.shape}")
    bad = np.flatnonzero(~(lower <= upper))
    if bad.size:
        k = int(bad[0])
        raise _BoundsError(f"{who}: lower bound above upper bound for pose parameter {k} ({PARAM_NAMES[k]}): "
                           f"{lower[k]} > {upper[k]}")
    return lower, upper



def bounds_with(limits, where: str = "stages.solve.limits") -> tuple[np.ndarray, np.ndarray]:
    """Default joint limits (skeleton.pose_bounds) with the config's overrides {name: [min, max]} applied;
    EnergyError (status "invalid_bounds") naming ``where`` for an unknown name or a malformed pair."""
    lo, hi = pose_bounds()
    for name, pair in (limits or {}).items():
        if name not in PARAM_NAMES:
            raise _BoundsError(f"{where}: " + unknown_name_message("pose parameter", name, list(PARAM_NAMES)))
        if len(pair) != 2:
            raise _BoundsError(f"{where}.{name}: expected [min, max], got {list(pair)}")
        k = PARAM_NAMES.index(name)
        lo[k], hi[k] = float(pair[0]), float(pair[1])
    return checked_bounds(lo, hi, where)


def run_ipopt(solver, x0, p, lbx, ubx, what: str) -> tuple[np.ndarray, SolveStats]:
    """One IPOPT solve through a built nlpsol; SolveFailed (with IPOPT's status) unless it succeeded with finite
    values. Returns (x, stats)."""
    t0 = time.perf_counter()
    try:
        res = solver(x0=x0, p=p, lbx=lbx, ubx=ubx)
    except RuntimeError as exc:  # CasADi refuses ill-posed input (e.g. lbx > ubx) before IPOPT runs
        raise SolveFailed(f"{what}: the solver refused the problem: {exc}", status="Invalid_Problem_Definition",
                          details={"error": str(exc)}) from exc
    st = solver.stats()
    status = str(st.get("return_status", "unknown"))
    stats = SolveStats(status=status, iterations=int(st.get("iter_count", 0)),
                       seconds=time.perf_counter() - t0)
    if status not in SUCCESS_STATUSES:
        raise SolveFailed(f"{what}: IPOPT did not converge (status {status} after {stats.iterations} "
                          f"iterations)", status=status, details={"iterations": stats.iterations})
    x = np.asarray(res["x"], dtype=np.float64).ravel()
    if not np.all(np.isfinite(x)):
        raise SolveFailed(f"{what}: IPOPT returned non-finite poses (status {status})", status="non_finite")
    return x, stats
