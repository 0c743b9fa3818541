"""A solve as a sum of factors: the poses' parametrisation, the assembly of every factor's derivatives, IPOPT.

    min_x  Σ_f f(P_f x_U, x_f) + λ_damp ‖x - x_ref‖²     s.t.  lower <= x_U <= upper (per pose parameter)

x_U are the pose variables, one 33-vector per *unit*: a cubic B-spline's control points (:class:`SplinePoses`,
the spline solve) or one pose per frame (:class:`FramePoses`, the paper's batch solve and the refinement). Each
factor f (:mod:`eventcap.energy.factor`) sees the poses (or a derivative of them) at its own samples, S_f = P_f x_U
with P_f the parametrisation's basis at the factor's sample times, and its own auxiliary variables x_f (E_3D's t').
Everything is linear in x_U, so the chain rule is a product with the basis: g_U = P_fᵀ g_S, H_U = P_fᵀ H_S P_f.
Factors' Hessians are block diagonal in their samples, or block tridiagonal (E_cor); the basis of a cubic B-spline
has 4 neighbouring control points per sample, so the problem's Hessian is block banded: units i and j interact only
when |i - j| <= band (3 for a spline, 4 when a factor couples samples a knot interval apart; 0 or 1 per frame),
plus the auxiliary variables. λ_damp ‖x - x_ref‖² (not a term of the pose energy: a proximal pull of every
variable towards the solve's start, as Levenberg-Marquardt damps) keeps directions nothing observes from drifting.

Built once per (template, camera, layout, factors, settings): IPOPT sees the sum through numpy callbacks (value,
gradient, exact Hessian in the declared block-banded sparsity). The factors own each window's data (they collect
it, and relinearise at each ICP round: :mod:`.factor`); the problem only sets the span of the poses and the bases
at the factors' samples (:meth:`FactorProblem.set_window`) and the proximal term's reference.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import casadi as ca
import numpy as np
from scipy import sparse

from eventcap.body.skeleton import NUM_POSE_PARAMS

from .errors import EnergyError
from .factor import Factor
from .ipopt import IpoptSettings, NumpyCallback, SolveStats, checked_bounds, run_ipopt
from .spline import UniformCubicBSpline

_NP = NUM_POSE_PARAMS


class SplinePoses:
    """Poses as a uniform cubic B-spline: the units are its n_seg + 3 control points (:mod:`.spline`)."""

    kind = "spline"

    def __init__(self, n_seg: int, spline: UniformCubicBSpline | None = None):
        self.n_seg = int(n_seg)
        self.n_units = self.n_seg + 3
        self.spline: UniformCubicBSpline | None = None
        if spline is not None:
            self.set_span(spline)

    def band(self, couples: bool) -> int:
        # a sample touches 4 neighbouring control points; two coupled samples at most one knot interval apart, 5
        return 4 if couples else 3

    def set_span(self, spline: UniformCubicBSpline) -> None:
        if spline.n_seg != self.n_seg:
            raise EnergyError(f"the problem was built for {self.n_seg} knot intervals, got {spline.n_seg}")
        self.spline = spline

    def basis(self, t_us: np.ndarray, deriv: int) -> np.ndarray:
        return self.spline.basis(t_us, deriv)

    def poses(self, U: np.ndarray, t_us: np.ndarray, deriv: int = 0) -> np.ndarray:
        return self.spline.evaluate(U, t_us, deriv)


class FramePoses:
    """One pose per frame: the units are the poses at the frame times; a factor's samples must be frames."""

    kind = "frames"

    def __init__(self, n_frames: int):
        self.n_units = int(n_frames)
        self.t_us = np.zeros(self.n_units, dtype=np.int64)

    def band(self, couples: bool) -> int:
        return 1 if couples else 0

    def set_span(self, t_us: np.ndarray) -> None:
        t = np.asarray(t_us, dtype=np.int64)
        if t.shape != (self.n_units,):
            raise EnergyError(f"the problem was built for {self.n_units} frames, got {t.shape}")
        self.t_us = t

    def rows(self, t_us: np.ndarray) -> np.ndarray:
        t = np.asarray(t_us, dtype=np.int64).ravel()
        idx = np.searchsorted(self.t_us, t)
        ok = (idx < self.n_units) & (self.t_us[np.minimum(idx, self.n_units - 1)] == t)
        if not ok.all():
            raise EnergyError(f"per-frame poses: a factor samples t = {t[~ok][:3].tolist()} us, which is no frame")
        return idx

    def basis(self, t_us: np.ndarray, deriv: int) -> np.ndarray:
        if deriv:
            raise EnergyError("per-frame poses have no derivative: a factor on velocities needs a spline")
        idx = self.rows(t_us)
        B = np.zeros((idx.size, self.n_units))
        B[np.arange(idx.size), idx] = 1.0
        return B

    def poses(self, U: np.ndarray, t_us: np.ndarray, deriv: int = 0) -> np.ndarray:
        return self.basis(t_us, deriv) @ U


def coupling_band(poses: SplinePoses | FramePoses, t_us: np.ndarray) -> int:
    """How many units apart the Hessian blocks of a factor coupling neighbouring samples at t_us (and of any factor
    at its own samples) reach: 3 for a spline whose coupled samples never straddle a knot (samples on the knots:
    the fourth basis function is exactly 0 there), 4 when they do; 1 per frame."""
    if isinstance(poses, FramePoses):
        return 1
    B = poses.basis(np.asarray(t_us), 0) != 0
    if B.shape[0] < 2:
        return 3
    first = B.argmax(1)
    last = B.shape[1] - 1 - B[:, ::-1].argmax(1)
    return max(3, int(np.max(last[1:] - first[:-1])))


class SparseBasis:
    """A factor's basis (n samples x n_units; S = B @ U) kept as each sample's few nonzero units (4 neighbouring
    control points of a cubic spline, one frame per sample of a per-frame problem), so that the poses at the samples,
    the gradient's chain rule and the Hessian's assembly cost as much as the samples, not samples x units."""

    def __init__(self, B: np.ndarray):
        B = np.asarray(B, dtype=np.float64)
        self.dense = B
        self.n, self.n_units = B.shape
        nz = B != 0
        k = max(1, int(nz.sum(axis=1).max(initial=0)))
        self.cols = np.zeros((self.n, k), dtype=np.int64)
        self.vals = np.zeros((self.n, k))
        for s in range(self.n):  # a few per row; the problem sets its bases once per window
            c = np.flatnonzero(nz[s])
            self.cols[s, :c.size], self.vals[s, :c.size] = c, B[s, c]
            if c.size < k:
                self.cols[s, c.size:] = c[-1] if c.size else 0
        self.k = k
        self._scatter = {}

    def apply(self, U: np.ndarray) -> np.ndarray:
        """B @ U for U (n_units, p)."""
        return np.einsum("sk,skp->sp", self.vals, U[self.cols])

    def transpose_apply(self, G: np.ndarray) -> np.ndarray:
        """Bᵀ @ G for G (n, p)."""
        return self.dense.T @ G if self.n_units * self.n < 4096 else self._scatter_rows(
            [(self.cols[:, a], self.vals[:, a]) for a in range(self.k)], G)

    def _scatter_rows(self, parts, G: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n_units, G.shape[1]))
        for cols, w in parts:
            M = sparse.csr_matrix((w, (cols, np.arange(self.n))), shape=(self.n_units, self.n))
            out += M @ G
        return out

    def pair_matrices(self, band: int) -> list[tuple[int, sparse.csr_matrix]]:
        """(d, M) with M (n_units, n) sparse such that block (i, i + d) of Σ_s B_s,· ⊗ B_s,· D_s is (M @ D)[i] (the
        samples' own blocks, D (n, 33·33)), for every unit distance 0 <= d <= band."""
        key = ("pairs", band)
        if key not in self._scatter:
            out = {}
            for a in range(self.k):
                for b in range(self.k):
                    i, j = self.cols[:, a], self.cols[:, b]
                    w = self.vals[:, a] * self.vals[:, b]
                    d = j - i
                    keep = (d >= 0) & (d <= band) & (w != 0)
                    if a != b:  # a pair of distinct entries: each unordered pair once (its ordered twin has d < 0)
                        keep &= (d > 0) | (a < b)
                    for dd in np.unique(d[keep]):
                        m = keep & (d == dd)
                        M = sparse.csr_matrix((w[m], (i[m], np.flatnonzero(m))), shape=(self.n_units, self.n))
                        out[int(dd)] = out[int(dd)] + M if int(dd) in out else M
            self._scatter[key] = sorted(out.items())
        return self._scatter[key]

    def neighbour_matrices(self, band: int) -> list[tuple[int, sparse.csr_matrix, sparse.csr_matrix]]:
        """(d, M, Mt) with M, Mt (n_units, n - 1) sparse such that block (i, i + d) of the coupling of neighbouring
        samples (k, k + 1) with blocks Up_k (n - 1, 33·33) is (M @ Up + Mt @ Upᵀ)[i]: sample k's unit i with sample
        k + 1's unit i + d, and sample k + 1's unit i with sample k's unit i + d (the transposed block)."""
        key = ("neighbours", band)
        if key not in self._scatter:
            n1 = self.n - 1
            out: dict[int, list] = {}
            for a in range(self.k):
                for b in range(self.k):
                    i, j = self.cols[:-1, a], self.cols[1:, b]  # sample k's unit i, sample k + 1's unit j
                    w = self.vals[:-1, a] * self.vals[1:, b]
                    for flip in (False, True):
                        lo, hi = (j, i) if flip else (i, j)
                        d = hi - lo
                        keep = (d >= 0) & (d <= band) & (w != 0)
                        for dd in np.unique(d[keep]):
                            m = keep & (d == dd)
                            M = sparse.csr_matrix((w[m], (lo[m], np.flatnonzero(m))), shape=(self.n_units, n1))
                            slot = out.setdefault(int(dd), [None, None])
                            k = 1 if flip else 0
                            slot[k] = M if slot[k] is None else slot[k] + M
            empty = sparse.csr_matrix((self.n_units, n1))
            self._scatter[key] = sorted((dd, m if m is not None else empty, mt if mt is not None else empty)
                                        for dd, (m, mt) in out.items())
        return self._scatter[key]


class FactorProblem:
    """The NLP of a sum of factors over a pose parametrisation (module doc), built once.

    factors: built for the layout this problem serves (:func:`eventcap.energy.terms.factors_from_config`);
    damp: λ_damp; damp_aux: whether the proximal pull also holds the auxiliary variables; lower/upper: the pose
    parameters' bounds (33,), applied to every unit (exact for a spline: its basis is a convex combination);
    band: how many units apart the Hessian's blocks reach (default: the parametrisation's, :func:`coupling_band`
    tells what a window needs; a window whose factors reach further is refused)."""

    def __init__(self, poses: SplinePoses | FramePoses, factors: Sequence[Factor], settings: IpoptSettings,
                 lower=None, upper=None, *, damp: float, damp_aux: bool = True, name: str = "factors",
                 band: int | None = None):
        t0 = time.perf_counter()
        self.poses, self.factors, self.settings = poses, list(factors), settings
        names = [f.name for f in self.factors]
        if len(set(names)) != len(names):
            raise EnergyError(f"{name}: a factor appears twice among {names}")
        self.lower, self.upper = checked_bounds(lower, upper, name)
        self.damp, self.damp_aux, self.name = float(damp), bool(damp_aux), name
        self.n_units = poses.n_units
        self.nU = self.n_units * _NP
        # each factor's auxiliary variables, one block after another behind the pose variables
        self.aux_slices, o = [], self.nU
        for f in self.factors:
            k = f.n * f.aux_size
            self.aux_slices.append(slice(o, o + k) if k else None)
            o += k
        self.nx, self.nA = o, o - self.nU
        self.band = poses.band(any(f.couples_neighbours for f in self.factors)) if band is None else int(band)
        self._build_sparsity()
        self._bases: list[np.ndarray] | None = None
        self._cache: dict = {}
        self.x_ref = np.zeros(self.nx)
        self._build_solver()
        self.build_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ structure
    def _build_sparsity(self) -> None:
        """Upper-triangular sparsity: unit blocks (i, i + d), d <= band; every (unit, aux) entry; the aux upper
        triangle. ``_gather`` picks each nonzero (in CasADi's column-major order) from the concatenation
        [band blocks (n, band + 1, 33, 33), unit-aux (nU, nA), aux-aux (nA, nA)] raveled."""
        n, b, nU, nA = self.n_units, self.band, self.nU, self.nA
        i = np.repeat(np.arange(n), b + 1)
        d = np.tile(np.arange(b + 1), n)
        keep = i + d < n
        i, d = i[keep], d[keep]
        p, q = np.meshgrid(np.arange(_NP), np.arange(_NP), indexing="ij")
        r = (i[:, None, None] * _NP + p[None]).ravel()
        c = ((i + d)[:, None, None] * _NP + q[None]).ravel()
        src = ((i * (b + 1) + d)[:, None, None] * _NP * _NP + (p * _NP + q)[None]).ravel()
        up = r <= c
        r, c, src = r[up], c[up], src[up]
        base = n * (b + 1) * _NP * _NP
        ru, cu = np.meshgrid(np.arange(nU), np.arange(nA), indexing="ij")
        ra, ca_ = np.triu_indices(nA)
        rows = np.concatenate([r, ru.ravel(), nU + ra])
        cols = np.concatenate([c, nU + cu.ravel(), nU + ca_])
        srcs = np.concatenate([src, base + (ru * nA + cu).ravel(), base + nU * nA + ra * nA + ca_])
        order = np.lexsort((rows, cols))
        self._sparsity = ca.Sparsity.triplet(self.nx, self.nx, rows[order].tolist(), cols[order].tolist())
        self._gather = srcs[order]

    def _build_solver(self) -> None:
        nx = self.nx
        self._callbacks = [
            NumpyCallback(f"E_{self.name}", nx, [ca.Sparsity.dense(1, 1)], lambda v: [self.evaluate(v, 0)["value"]]),
            NumpyCallback(f"E_{self.name}_grad", nx, [ca.Sparsity.dense(1, 1), ca.Sparsity.dense(nx, 1)],
                          lambda v: [self.evaluate(v, 1)["value"], self.evaluate(v, 1)["grad"]]),
            NumpyCallback(f"E_{self.name}_hess", nx, [self._sparsity], lambda v: [self.hessian_values(v)]),
        ]
        cb_f, cb_g, cb_h = self._callbacks
        X, P = ca.MX.sym("x", nx), ca.MX.sym("p", 0)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", 0)
        val, grad = cb_g(X)
        grad_f = ca.Function("grad_f", [X, P], [val, grad], ["x", "p"], ["f", "grad_f_x"])
        hess_lag = ca.Function("hess_lag", [X, P, lam_f, lam_g], [lam_f * cb_h(X)],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        #: Objective, gradient and upper-triangular Hessian exactly as IPOPT sees them (for derivative checks).
        self.objective = ca.Function("objective", [X], [cb_f(X)])
        self.gradient = ca.Function("gradient", [X], [val, grad])
        self.hessian = ca.Function("hessian", [X], [cb_h(X)])
        opts = dict(self.settings.options(True), grad_f=grad_f, hess_lag=hess_lag)
        self.solver = ca.nlpsol(self.name, "ipopt", {"x": X, "p": P, "f": cb_f(X)}, opts)
        #: the solver of a solve that restarts from a solution (a later ICP round): a monotone barrier from a tiny
        #: mu (the same one unless the settings choose another barrier for the first solve)
        self.restart_solver = self.solver
        if self.settings.barrier != "monotone":
            again = dict(self.settings.restart().options(True), grad_f=grad_f, hess_lag=hess_lag)
            self.restart_solver = ca.nlpsol(f"{self.name}_again", "ipopt", {"x": X, "p": P, "f": cb_f(X)}, again)

    # ------------------------------------------------------------------ data of one window
    def set_window(self, span, x_ref: np.ndarray | None = None) -> None:
        """Set the span of the poses (a UniformCubicBSpline, or the frame times) for a window whose data every
        factor has collected (:meth:`Factor.collect`, which fixes their sample times): the bases at their samples.
        x_ref: the proximal term's reference (:meth:`set_reference`)."""
        self.poses.set_span(span)
        bases = []
        for f in self.factors:
            B = self.poses.basis(f.t_us, f.derivative)
            if B.shape[0] != f.n:
                raise EnergyError(f"{self.name}: factor {f.name} has {B.shape[0]} sample times, built for {f.n}")
            if f.couples_neighbours and f.n > 1:
                nz = B != 0
                first = np.where(nz.any(1), nz.argmax(1), 0)
                last = np.where(nz.any(1), self.n_units - 1 - nz[:, ::-1].argmax(1), 0)
                reach = int(np.max(last[1:] - first[:-1], initial=0))
                if reach > self.band:
                    raise EnergyError(f"{self.name}: factor {f.name} couples samples {reach} units apart; the problem "
                                      f"was built for {self.band}")
            bases.append(SparseBasis(B))
        self._bases = bases
        self._cache = {}
        if x_ref is not None:
            self.set_reference(x_ref)

    def set_reference(self, x_ref: np.ndarray) -> None:
        """The proximal term's reference x_ref (nx,): each solve's start. Also call it after the factors
        relinearized (:meth:`Factor.relinearize`): evaluations cached before are forgotten."""
        x_ref = np.asarray(x_ref, dtype=np.float64)
        if x_ref.shape != (self.nx,):
            raise EnergyError(f"{self.name}: expected x_ref of shape ({self.nx},), got {x_ref.shape}")
        self.x_ref = x_ref
        self._cache = {}

    def start(self, units: np.ndarray, inputs) -> np.ndarray:
        """The decision vector of the pose units (n_units, 33) with every factor's auxiliary variables at its start
        (:meth:`Factor.start_aux` for these window inputs; zeros when it has none)."""
        x = np.zeros(self.nx)
        x[:self.nU] = np.asarray(units, dtype=np.float64).ravel()
        for f, sl in zip(self.factors, self.aux_slices):
            if sl is not None:
                a = f.start_aux(inputs)
                if a is not None:
                    x[sl] = np.asarray(a, dtype=np.float64).ravel()
        return x

    def aux(self, x) -> dict[str, np.ndarray]:
        """Each factor's auxiliary variables (n, aux_size) at x, by name (factors without any left out)."""
        _, aux = self.split(np.asarray(x, dtype=np.float64))
        return {f.name: a.copy() for f, a in zip(self.factors, aux) if a is not None}

    def with_aux(self, x: np.ndarray, aux: dict[str, np.ndarray]) -> np.ndarray:
        """x with the auxiliary variables of the named factors replaced (rows with a NaN kept as they are)."""
        x = np.array(x, dtype=np.float64)
        for f, sl in zip(self.factors, self.aux_slices):
            if sl is None or f.name not in aux:
                continue
            a = np.asarray(aux[f.name], dtype=np.float64)
            if a.shape != (f.n, f.aux_size):
                raise EnergyError(f"{self.name}: factor {f.name}'s auxiliary variables: expected {(f.n, f.aux_size)}, "
                                  f"got {a.shape}")
            cur = x[sl].reshape(f.n, f.aux_size)
            keep = np.isfinite(a).all(axis=1)
            cur[keep] = a[keep]
            x[sl] = cur.ravel()
        return x

    # ------------------------------------------------------------------ evaluation
    def split(self, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray | None]]:
        """The pose units (n_units, 33) and each factor's auxiliary variables (n, aux_size) of x."""
        U = x[:self.nU].reshape(self.n_units, _NP)
        aux = [None if sl is None else x[sl].reshape(f.n, f.aux_size) for f, sl in zip(self.factors, self.aux_slices)]
        return U, aux

    def evaluate(self, x, order: int) -> dict:
        """Value (order 0) or value and gradient (order >= 1) of the energy at x, per factor too (cached per x)."""
        if self._bases is None:
            raise RuntimeError(f"{self.name}: set_window() must be called before evaluating the energy")
        x = np.asarray(x, dtype=np.float64)
        key = x.tobytes()
        c = self._cache
        if c.get("key") == key and c.get("order", -1) >= order:
            return c
        U, aux = self.split(x)
        lins = [f.linearize(B.apply(U), a, min(order, 1)) for f, B, a in zip(self.factors, self._bases, aux)]
        dx = x - self.x_ref
        if not self.damp_aux:
            dx[self.nU:] = 0.0
        damp = float(dx @ dx)
        out = {"key": key, "order": order, "terms": {f.name: lin.value for f, lin in zip(self.factors, lins)},
               "damp": damp, "value": sum(lin.value for lin in lins) + self.damp * damp, "lins": lins}
        if order >= 1:
            grad = (2.0 * self.damp) * dx
            gU = grad[:self.nU].reshape(self.n_units, _NP)
            for lin, B, sl in zip(lins, self._bases, self.aux_slices):
                gU += B.transpose_apply(lin.grad)
                if sl is not None:
                    grad[sl] += lin.aux_grad.ravel()
            out["grad"] = grad
        self._cache = out
        return out

    def hessian_parts(self, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Hessian at x in three parts: unit blocks (n_units, band + 1, 33, 33) with [i, d] = block (i, i + d),
        the (unit, aux) block (nU, nA) and the aux block (nA, nA)."""
        x = np.asarray(x, dtype=np.float64)
        U, aux = self.split(x)
        n, b = self.n_units, self.band
        Hb = np.zeros((n, b + 1, _NP, _NP))
        Hua = np.zeros((self.nU, self.nA))
        Haa = np.zeros((self.nA, self.nA))
        for f, B, a, sl in zip(self.factors, self._bases, aux, self.aux_slices):
            lin = f.linearize(B.apply(U), a, 2)
            if lin.diag is not None:
                D = lin.diag.reshape(f.n, -1)
                for d, M in B.pair_matrices(b):
                    if d < n:
                        Hb[:n - d, d] += (M @ D)[:n - d].reshape(n - d, _NP, _NP)
            if lin.upper is not None and f.n > 1:
                Up = lin.upper.reshape(f.n - 1, -1)
                Ut = lin.upper.transpose(0, 2, 1).reshape(f.n - 1, -1)
                for d, M, Mt in B.neighbour_matrices(b):
                    if d < n:
                        Hb[:n - d, d] += (M @ Up + Mt @ Ut)[:n - d].reshape(n - d, _NP, _NP)
            if sl is not None:
                k = f.aux_size
                o = sl.start - self.nU
                Hua[:, o:o + f.n * k] += np.einsum("si,spa->ipsa", B.dense, lin.cross).reshape(self.nU, f.n * k)
                for s in range(f.n):
                    Haa[o + s * k:o + (s + 1) * k, o + s * k:o + (s + 1) * k] += lin.aux_diag[s]
        if self.damp:
            idx = np.arange(_NP)
            Hb[:, 0, idx, idx] += 2.0 * self.damp
            if self.damp_aux:
                Haa[np.diag_indices(self.nA)] += 2.0 * self.damp
        return Hb, Hua, Haa

    def hessian_values(self, x) -> np.ndarray:
        """The Hessian's nonzeros in the declared sparsity's order (what IPOPT gets)."""
        Hb, Hua, Haa = self.hessian_parts(x)
        return np.concatenate([Hb.ravel(), Hua.ravel(), Haa.ravel()])[self._gather]

    def dense_hessian(self, x) -> np.ndarray:
        """The full symmetric Hessian (for checks)."""
        Hb, Hua, Haa = self.hessian_parts(x)
        n, b, nU = self.n_units, self.band, self.nU
        H = np.zeros((self.nx, self.nx))
        for i in range(n):
            for d in range(min(b, n - 1 - i) + 1):
                j = i + d
                H[i * _NP:(i + 1) * _NP, j * _NP:(j + 1) * _NP] = Hb[i, d]
                H[j * _NP:(j + 1) * _NP, i * _NP:(i + 1) * _NP] = Hb[i, d].T
        H[:nU, nU:], H[nU:, :nU], H[nU:, nU:] = Hua, Hua.T, Haa
        return H

    def terms(self, x) -> dict[str, float]:
        """Each factor's unweighted value at x (what solves report), by name."""
        U, aux = self.split(np.asarray(x, dtype=np.float64))
        return {f.name: f.unweighted(B.apply(U), a) for f, B, a in zip(self.factors, self._bases, aux)}

    def factor(self, name: str) -> Factor | None:
        return next((f for f in self.factors if f.name == name), None)

    # ------------------------------------------------------------------ solving
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lbx = np.concatenate([np.tile(self.lower, self.n_units), np.full(self.nA, -np.inf)])
        ubx = np.concatenate([np.tile(self.upper, self.n_units), np.full(self.nA, np.inf)])
        return lbx, ubx

    def solve(self, x0: np.ndarray, what: str, fixed_units: Sequence[int] = (),
              restart: bool = False) -> tuple[np.ndarray, SolveStats]:
        """One IPOPT solve from x0 (clipped into the bounds); fixed_units stay where x0 has them. restart: x0 is an
        earlier solve's solution (a later ICP round): the barrier for a solve that starts there."""
        lbx, ubx = self.bounds()
        x0 = np.clip(np.asarray(x0, dtype=np.float64), lbx, ubx)
        for u in fixed_units:
            sl = slice(u * _NP, (u + 1) * _NP)
            lbx[sl] = ubx[sl] = x0[sl]
        return run_ipopt(self.restart_solver if restart else self.solver, x0, np.zeros(0), lbx, ubx, what)


__all__ = ["FactorProblem", "FramePoses", "SplinePoses", "coupling_band"]
