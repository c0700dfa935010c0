r"""The DeeP-LCC quadratic program and a fast exact solver for it.

Decision variable ``g`` (one weight per Hankel column, ``M`` of them)::

    min_g  ||Yf g||_Q^2 + ||Uf g||_R^2 + lambda_g ||g||^2 + lambda_y ||Yp g - yini||^2
    s.t.   [Up; Ep; Ef] g = [uini; eini; 0]
           acel_min <= Uf g <= acel_max
           spacing_min - s* <= Sf Yf g <= spacing_max - s*

with ``Q = blkdiag(weight_v I_n, weight_s I_m)`` per instant, ``R = weight_u I_m``
and ``Sf`` picking the CAV spacing errors. In the standard form
``min 1/2 g'Hg + f'g`` (half the cost above plus a constant, the same minimiser):
``H = Yf'QYf + Uf'RUf + lambda_g I + lambda_y Yp'Yp`` and ``f = -lambda_y Yp' yini``.

What is constant across control steps: ``H``, the equality matrix and the
inequality matrix ``A = [Uf; Sf Yf]`` (only ``yini``, ``uini``, ``eini`` change).
:class:`DeepLCCSolver` therefore factorises the KKT matrix of the equality-only
problem once per Hankel set and projects everything onto the 200 inequality rows:

    A g = a0 - S nu,   a0 = lambda_y Gy yini + Gc c,   S = A K^{-1}_{gg} A'

where ``nu`` holds signed multipliers of the active rows. A primal-dual active-set
loop over these rows, warm-started from the previous step's active set, then
costs a 200x310 product plus a few tiny solves per step. Its answer is verified
(primal and dual feasibility) before it is returned; when the loop does not
converge the reduced dual problem is solved with cvxopt; if that fails too, the
documented safe action (the equality-only optimum clipped to the acceleration
bounds) is returned. Every fallback is counted in :class:`QPStats`. NaN/inf inputs are
not solved: the safe action ``u = 0`` comes back with status ``"invalid_input"``. A state
whose measured CAV spacing already lies outside ``[spacing_min, spacing_max]`` is solved
and flagged (``QPResult.infeasible_state``, ``QPStats.infeasible_states``). Hankel data
that is not persistently exciting is refused when the solver is built.

>>> import numpy as np, torch
>>> from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
>>> from mixed_traffic.controllers.deeplcc.precollect import precollect
>>> [h] = precollect(PlatoonConfig(), T=400, t_ini=5, n=10, generator=torch.Generator().manual_seed(0))
>>> solver = DeepLCCSolver(h, QPParams.preset("dataset"))
>>> res = solver.solve(np.zeros(10), np.zeros(50), np.zeros(5))
>>> res.u.shape, res.status
((2,), 'optimal')
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

from mixed_traffic.controllers.deeplcc.hankel import HankelData

PRESETS = {
    # values used for dataset generation
    "dataset": dict(lambda_g=1.0, lambda_y=1e3),
    # values of the public DeeP-LCC reference's closed-loop simulations
    "reference": dict(lambda_g=100.0, lambda_y=1e4),
}


@dataclass(frozen=True)
class QPParams:
    """Weights, regularisation and constraints of the DeeP-LCC QP."""

    weight_v: float = 1.0
    weight_s: float = 0.5
    weight_u: float = 0.1
    lambda_g: float = 1.0
    lambda_y: float = 1e3
    acel_max: float = 2.0
    dcel_max: float = -5.0
    spacing_min: float = 5.0
    spacing_max: float = 40.0
    s_star: float = 20.0

    def __post_init__(self):
        def bad(name, allowed):
            raise ValueError(f"QPParams: {name}={getattr(self, name)!r} is invalid; allowed: {allowed}")

        for name in ("weight_v", "weight_s", "weight_u", "lambda_y"):
            if not getattr(self, name) >= 0:
                bad(name, ">= 0")
        if not self.lambda_g > 0:
            bad("lambda_g", "> 0 (it makes the Hessian positive definite)")
        if not self.dcel_max < 0 < self.acel_max:
            bad("dcel_max", f"dcel_max < 0 < acel_max ({self.acel_max})")
        if not 0 <= self.spacing_min < self.s_star < self.spacing_max:
            bad("spacing_min", f"0 <= spacing_min < s_star ({self.s_star}) < spacing_max ({self.spacing_max})")

    @classmethod
    def preset(cls, name: str, **overrides) -> QPParams:
        """``"dataset"`` (lambda_g 1, lambda_y 1e3) or ``"reference"`` (lambda_g 100, lambda_y 1e4)."""
        if name not in PRESETS:
            raise ValueError(f"QPParams.preset: unknown name {name!r}; allowed: {sorted(PRESETS)}")
        return cls(**{**PRESETS[name], **overrides})

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, s: str) -> QPParams:
        return cls(**json.loads(s))


@dataclass(frozen=True)
class QPMatrices:
    """Standard form ``min 1/2 g'Hg + (Fy yini)'g  s.t.  B g = c,  lb <= A g <= ub``."""

    H: np.ndarray
    Fy: np.ndarray  # f = Fy @ yini
    B: np.ndarray
    A: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    m: int
    p: int
    t_ini: int
    n: int

    def rhs(self, uini: np.ndarray, eini: np.ndarray) -> np.ndarray:
        return np.concatenate([np.ravel(uini), np.ravel(eini), np.zeros(self.n)])


def build_qp(h: HankelData, params: QPParams) -> QPMatrices:
    """Assemble the QP matrices of one Hankel set (inputs/outputs time-major)."""
    m, p, n, t_ini = h.m, h.p, h.n, h.t_ini
    n_v = p - m
    q_diag = np.tile(np.r_[np.full(n_v, params.weight_v), np.full(m, params.weight_s)], n)
    r_diag = np.full(m * n, params.weight_u)
    M = h.columns
    H = (h.Yf.T @ (q_diag[:, None] * h.Yf) + h.Uf.T @ (r_diag[:, None] * h.Uf)
         + params.lambda_y * (h.Yp.T @ h.Yp) + params.lambda_g * np.eye(M))
    H = 0.5 * (H + H.T)
    spacing_rows = np.concatenate([np.arange(k * p + n_v, (k + 1) * p) for k in range(n)])
    A = np.vstack([h.Uf, h.Yf[spacing_rows]])
    lb = np.r_[np.full(m * n, params.dcel_max), np.full(m * n, params.spacing_min - params.s_star)]
    ub = np.r_[np.full(m * n, params.acel_max), np.full(m * n, params.spacing_max - params.s_star)]
    return QPMatrices(H=H, Fy=-params.lambda_y * h.Yp.T, B=np.vstack([h.Up, h.Ep, h.Ef]), A=A, lb=lb, ub=ub,
                      m=m, p=p, t_ini=t_ini, n=n)


def solve_cvxopt(qp: QPMatrices, uini, yini, eini, tol: float = 1e-10, reltol: float = 1e-10,
                 maxiters: int = 200) -> tuple[np.ndarray, str]:
    """Independent general-purpose dense interior-point solve -> ``(u_all (m*N,), status)``.

    cvxopt stops when the absolute gap <= ``tol`` OR the relative gap <= ``reltol``;
    the objective is ~1e6-1e7 here, so a relative gap of 1e-10 still leaves an
    absolute gap near 1e-3 (u off by up to ~1e-2 along the flat directions).
    ``reltol=1e-16`` makes the absolute gap decide (the accurate reference).
    """
    from cvxopt import matrix, solvers

    opts = {"show_progress": False, "abstol": tol, "reltol": reltol, "feastol": tol, "maxiters": maxiters}
    G = np.vstack([qp.A, -qp.A])
    hh = np.r_[qp.ub, -qp.lb]
    sol = solvers.qp(matrix(qp.H), matrix(qp.Fy @ np.ravel(yini)), matrix(G), matrix(hh),
                     matrix(qp.B), matrix(qp.rhs(uini, eini)), options=opts)
    g = np.array(sol["x"]).ravel()
    return qp.A[: qp.m * qp.n] @ g, sol["status"]


@dataclass
class QPStats:
    """Counters of a solver's history (never reset silently)."""

    solves: int = 0
    iterations: int = 0
    dual_fallbacks: int = 0  # active-set loop did not converge; reduced dual solved with cvxopt
    safe_actions: int = 0  # no verified solution; the safe action was returned
    invalid_inputs: int = 0  # NaN/inf in uini/yini/eini: the safe action (0 m/s^2) was returned without solving
    infeasible_states: int = 0  # the measured CAV spacing is already outside [spacing_min, spacing_max]
    max_active: int = 0
    active_hist: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class QPResult:
    u: np.ndarray  # first control action (m,)
    u_all: np.ndarray  # whole optimal input sequence (m*N,)
    status: str  # "optimal", "dual_fallback", "safe_action" or "invalid_input"
    active: tuple  # ((row, sign), ...) active inequality rows
    iterations: int
    # the measured spacing of a CAV is already outside [spacing_min, spacing_max]: the constraint
    # cannot hold from the current state (the solution is still returned, flagged and counted)
    infeasible_state: bool = False


class DeepLCCSolver:
    """Exact DeeP-LCC QP solver reusing one KKT factorisation per Hankel set.

    ``solve(uini, yini, eini)`` takes flat time-major vectors (``(m*t_ini,)``,
    ``(p*t_ini,)``, ``(t_ini,)``) and returns a :class:`QPResult`.
    """

    def __init__(self, h: HankelData, params: QPParams, *, max_iter: int = 60, tol: float = 1e-9, refine: int = 2):
        self.params, self.max_iter, self.tol = params, max_iter, tol
        h.check_excitation()
        qp = build_qp(h, params)
        self.qp = qp
        M, nb, na, ny = qp.H.shape[0], qp.B.shape[0], qp.A.shape[0], qp.Fy.shape[1]
        K = np.zeros((M + nb, M + nb))
        K[:M, :M], K[:M, M:], K[M:, :M] = qp.H, qp.B.T, qp.B
        rhs = np.zeros((M + nb, na + ny + nb))
        rhs[:M, :na] = qp.A.T
        rhs[:M, na:na + ny] = -qp.Fy  # -f = lambda_y Yp' yini
        rhs[M:, na + ny:] = np.eye(nb)
        lu = sla.lu_factor(K, check_finite=False)
        Z = sla.lu_solve(lu, rhs, check_finite=False)
        for _ in range(refine):  # iterative refinement: the Hessian is badly conditioned
            Z += sla.lu_solve(lu, rhs - K @ Z, check_finite=False)
        Z = Z[:M]
        AZ = qp.A @ Z
        self.S = 0.5 * (AZ[:, :na] + AZ[:, :na].T)  # A K^-1_gg A'
        self.G = np.ascontiguousarray(AZ[:, na:])  # a0 = G @ [yini; c]
        self.Zg = Z  # kept for full solutions (g) on request
        self.lb, self.ub = qp.lb, qp.ub
        self.m, self.n_u = qp.m, qp.m * qp.n
        self.stats = QPStats()
        self._warm: tuple = ()

    def reset_warm_start(self) -> None:
        self._warm = ()

    def _a0(self, uini, yini, eini) -> np.ndarray:
        x = np.concatenate([np.ravel(yini), np.ravel(uini), np.ravel(eini), np.zeros(self.qp.n)])
        return self.G @ x

    def _active_set(self, a0: np.ndarray, start: tuple):
        """Primal-dual active-set loop on the reduced problem; returns (z = A g, active, iters) or None."""
        S, lb, ub, tol = self.S, self.lb, self.ub, self.tol
        W = list(start)
        for it in range(1, self.max_iter + 1):
            if W:
                rows = np.array([r for r, _ in W])
                sig = np.array([s for _, s in W], dtype=float)
                bound = np.where(sig > 0, ub[rows], lb[rows])
                try:
                    nu = np.linalg.solve(S[np.ix_(rows, rows)], a0[rows] - bound)
                except np.linalg.LinAlgError:
                    return None
                mu = sig * nu
                k = int(np.argmin(mu))
                if mu[k] < -tol:
                    W.pop(k)
                    continue
                z = a0 - S[:, rows] @ nu
            else:
                z = a0
            viol = np.maximum(z - ub, lb - z)
            if W:
                viol[rows] = -np.inf
            j = int(np.argmax(viol))
            if viol[j] <= tol * max(1.0, abs(ub[j]), abs(lb[j])):
                return z, tuple(W), it
            W.append((j, 1 if z[j] > ub[j] else -1))
        return None

    def _dual_fallback(self, a0: np.ndarray):
        """Reduced dual: min_{mu>=0} 1/2 mu'S1 mu - mu'(A1 g0 - b1), with A1 = [A; -A]."""
        from cvxopt import matrix, solvers

        S, na = self.S, self.S.shape[0]
        S1 = np.block([[S, -S], [-S, S]]) + 1e-12 * np.eye(2 * na)
        q = -np.r_[a0 - self.ub, self.lb - a0]
        sol = solvers.qp(matrix(S1), matrix(q), matrix(-np.eye(2 * na)), matrix(np.zeros(2 * na)),
                         options={"show_progress": False, "abstol": 1e-12, "reltol": 1e-12, "feastol": 1e-12})
        if sol["status"] != "optimal":
            return None
        mu = np.array(sol["x"]).ravel()
        z = a0 - S @ (mu[:na] - mu[na:])
        if np.any(z > self.ub + 1e-6) or np.any(z < self.lb - 1e-6):
            return None
        return z

    def solve(self, uini, yini, eini, warm_start: bool = True, warm: tuple | None = None) -> QPResult:
        """Solve one instance; ``warm`` overrides the stored warm-start active set.

        Non-finite inputs are not solved: the safe action ``u = 0`` (hold speed) is returned
        with status ``"invalid_input"`` and counted (``stats.invalid_inputs``, ``stats.safe_actions``).
        """
        self.stats.solves += 1
        uini, yini, eini = np.ravel(uini), np.ravel(yini), np.ravel(eini)
        if not (np.all(np.isfinite(uini)) and np.all(np.isfinite(yini)) and np.all(np.isfinite(eini))):
            self.stats.invalid_inputs += 1
            self.stats.safe_actions += 1
            self._warm = ()
            u_all = np.clip(np.zeros(self.n_u), self.params.dcel_max, self.params.acel_max)
            return QPResult(u=u_all[: self.m].copy(), u_all=u_all, status="invalid_input", active=(), iterations=0)
        infeasible = self._state_outside(yini)
        if infeasible:
            self.stats.infeasible_states += 1
        a0 = self._a0(uini, yini, eini)
        if warm is not None:
            self._warm = tuple(warm)
        out = self._active_set(a0, self._warm if warm_start else ())
        if out is None and warm_start and self._warm:
            out = self._active_set(a0, ())
        if out is not None:
            z, W, it = out
            self._warm = W
            self.stats.iterations += it
            self.stats.max_active = max(self.stats.max_active, len(W))
            self.stats.active_hist[len(W)] = self.stats.active_hist.get(len(W), 0) + 1
            u_all = z[: self.n_u]
            return QPResult(u=u_all[: self.m].copy(), u_all=u_all.copy(), status="optimal", active=W, iterations=it,
                            infeasible_state=infeasible)
        self._warm = ()
        z = self._dual_fallback(a0)
        if z is not None:
            self.stats.dual_fallbacks += 1
            u_all = z[: self.n_u]
            return QPResult(u=u_all[: self.m].copy(), u_all=u_all.copy(), status="dual_fallback", active=(),
                            iterations=self.max_iter, infeasible_state=infeasible)
        self.stats.safe_actions += 1
        u_all = np.clip(a0[: self.n_u], self.params.dcel_max, self.params.acel_max)
        return QPResult(u=u_all[: self.m].copy(), u_all=u_all, status="safe_action", active=(), iterations=self.max_iter,
                        infeasible_state=infeasible)

    def _state_outside(self, yini: np.ndarray) -> bool:
        """The last instant's CAV spacing errors lie outside [spacing_min, spacing_max] - s_star."""
        qp, pr = self.qp, self.params
        last = yini[(qp.t_ini - 1) * qp.p:][qp.p - qp.m:]
        return bool(np.any(last < pr.spacing_min - pr.s_star - 1e-9) or np.any(last > pr.spacing_max - pr.s_star + 1e-9))

    def solve_g(self, uini, yini, eini) -> np.ndarray:
        """The full optimal ``g`` (for inspection; slower than :meth:`solve`)."""
        res = self.solve(uini, yini, eini, warm_start=False)
        na = self.S.shape[0]
        x = np.concatenate([np.ravel(yini), np.ravel(uini), np.ravel(eini), np.zeros(self.qp.n)])
        g = self.Zg[:, na:] @ x
        if res.active:
            rows = np.array([r for r, _ in res.active])
            sig = np.array([s for _, s in res.active], dtype=float)
            bound = np.where(sig > 0, self.ub[rows], self.lb[rows])
            nu = np.linalg.solve(self.S[np.ix_(rows, rows)], self._a0(uini, yini, eini)[rows] - bound)
            g = g - self.Zg[:, rows] @ nu
        return g
