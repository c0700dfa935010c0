"""Nonlinear MPC for the intersection (CasADi Opti + IPOPT), as a TorchRL policy module.

Per row of the observation batch the controller solves

    min  sum_k w_v (v_k - v_ref)^2 + w_a a_k^2 + w_j (a_k - a_{k-1})^2 - w_y y_N + w_s sum_k d^k (s_k + s_k^2)
    s.t. y_{k+1} = y_k + v_k dt + a_k dt^2 / 2,  v_{k+1} = v_k + a_k dt,
         0 <= v_k <= 2,  |a_k| <= 3.2,  s_k >= 0,
         (x_ego - px_k)^2 + (y_k - py_j,k)^2 >= (2R + sigma_k + margin)^2 - s_k   for every hypothesis j
         (the constraint is the env's cost boundary, inflated further along the horizon)

over a horizon of 30 steps (3 s). The agent is *predicted*: constant velocity from its
perceived state (for an agent in its lane the lateral velocity decays, as a driver corrects
it), plus (``predict="routes"``, the default) the lane-following hypotheses the map allows
(keep straight, turn left, turn right, and the lane shifted by +-0.45 m for an unknown
lateral deviation) at the perceived speed, each with an
uncertainty radius ``sigma_k = c |sigma_0| + min(g k dt, cap)`` (``c = sigma_scale``, 2 by
default) that grows along the horizon. The slack weight decays along the horizon (``d^k``), so
a violation predicted far ahead (by an over-inflated radius) cannot pull the ego into a
near-term one.

Why the plain formulation fails (55% success, 0% on straight-through agents in the
original study): with no prediction the constraint only sees the agent's current
position, so the ego enters the crossing just ahead of an approaching agent and is
caught; and once the distance constraint becomes infeasible IPOPT fails and the fallback
brakes inside the agent's path. Here the prediction lets the ego yield early, the slack
keeps every problem feasible, and a *yield-or-go* multi-start (warm start from the previous
solution, a "go" guess at full speed and a "yield" guess stopping before the crossing)
picks the best local solution, since the two homotopy classes (pass before / after the agent)
are separate local minima that a single warm-started solve cannot jump between.

A near-term guard (``guard_steps``, 1 s) checks a plan that needs slack: if it comes within the
un-grown safety radius of a hypothesis in the next second, the solved plan (or full braking)
with the largest near-term separation is taken instead (:meth:`NMPCController._guard`).

Failed solves (IPOPT fails on every start) fall back to braking and are counted in
:attr:`NMPCController.stats` (``fallbacks``); steps whose best plan needs slack are counted
as ``slack_steps``.

>>> import torch
>>> from mixed_traffic.intersection.nmpc import make_nmpc_policy
>>> policy = make_nmpc_policy()
>>> from tensordict import TensorDict
>>> obs = torch.tensor([[-1.25, 0.0, 4.0, 0.5, -0.8, 0.0, 0.05, 0.05]])
>>> out = policy(TensorDict({"observation": obs}, batch_size=[1]))
>>> out["action"].shape
torch.Size([1, 1])
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import torch
from tensordict.nn import TensorDictModule

EGO_X = 0.5


@dataclass
class NMPCConfig:
    """NMPC parameters (see the module docstring for the problem).

    >>> NMPCConfig(horizon=20).horizon
    20
    """

    horizon: int = 30
    dt: float = 0.1
    a_max: float = 3.2
    v_min: float = 0.0
    v_max: float = 2.0
    v_ref: float = 1.5
    radius: float = 0.3328
    margin: float = 0.08
    sigma_scale: float = 2.0  # the perceived sigma counts this many times in the safety radius
    growth_cap: float = 0.45  # the radius grows by at most this much along the horizon (m)
    slack_decay: float = 0.93  # slack weight of step k is w_slack * slack_decay^k (near-term violations weigh most)
    sigma_growth: float = 0.3  # m/s growth of the prediction's uncertainty radius
    predict: str = "routes"  # "routes" (cv + lane-following hypotheses), "cv" (constant velocity), "none"
    lateral_spread: float = 0.45  # lateral offset of the shifted lane hypotheses (m)
    tau_lat: float = 0.7  # decay time of the lateral velocity of an agent in its lane (s)
    w_v: float = 1.0
    w_a: float = 0.05
    w_j: float = 0.05
    w_y: float = 5.0
    w_slack: float = 1e3
    slack_tol: float = 1e-2
    multistart: bool = True
    guard_steps: int = 10  # near-term check of plans that need slack (0: off), see NMPCController._guard
    max_iter: int = 150
    y_goal: float = 1.25

    def validate(self) -> None:
        if not (isinstance(self.horizon, int) and 2 <= self.horizon <= 200):
            raise ValueError(f"horizon={self.horizon!r} is invalid; allowed: an integer in [2, 200]")
        if self.predict not in ("routes", "cv", "none"):
            raise ValueError(f"predict={self.predict!r} is invalid; allowed: 'routes', 'cv', 'none'")
        if not (0 <= self.v_min < self.v_max):
            raise ValueError(f"v_min={self.v_min}, v_max={self.v_max} are invalid; allowed: 0 <= v_min < v_max")
        for name in ("dt", "a_max", "radius"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid; allowed: > 0")
        if not (isinstance(self.guard_steps, int) and self.guard_steps >= 0):
            raise ValueError(f"guard_steps={self.guard_steps!r} is invalid; allowed: an integer >= 0")
        if not 0 < self.slack_decay <= 1:
            raise ValueError(f"slack_decay={self.slack_decay!r} is invalid; allowed: (0, 1]")
        for name in ("margin", "sigma_scale", "growth_cap", "lateral_spread", "tau_lat", "sigma_growth", "w_v", "w_a", "w_j", "w_y", "w_slack"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid; allowed: >= 0")


@dataclass
class NMPCStats:
    """Counters of an :class:`NMPCController` (solve times in seconds, one entry per control step)."""

    solve_times: list = field(default_factory=list)
    n_steps: int = 0
    n_fallback: int = 0
    n_ipopt_solves: int = 0
    n_ipopt_fail: int = 0
    n_slack: int = 0  # steps whose chosen plan needed slack (inside the inflated margin)
    n_guard: int = 0  # steps where the near-term guard replaced the cheapest plan

    def summary(self) -> dict:
        t = np.asarray(self.solve_times) if self.solve_times else np.zeros(1)
        return {"steps": self.n_steps, "fallbacks": self.n_fallback, "ipopt_solves": self.n_ipopt_solves,
                "ipopt_failures": self.n_ipopt_fail,
                "slack_steps": self.n_slack, "guard_steps": self.n_guard, "solve_ms_mean": 1e3 * float(t.mean()),
                "solve_ms_p95": 1e3 * float(np.percentile(t, 95)), "solve_ms_max": 1e3 * float(t.max())}


N_HYP_ROUTES = 6  # constant velocity + straight + left + right + lane shifted down / up


def predict_agent(obs: np.ndarray, cfg: NMPCConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted agent centres ``px, py`` ``[H, N]`` for ``H`` hypotheses and radii ``r`` ``[N]``.

    ``obs`` is one observation row ``[y, v, x_a, y_a, vx_a, vy_a, sx, sy]``.

    >>> px, py, r = predict_agent(np.array([-1.25, 0, 3.0, 0.5, -1.0, 0.0, 0.05, 0.05]), NMPCConfig())
    >>> px.shape, round(float(px[0, 9]), 2)
    ((6, 30), 2.0)
    """
    N, dt = cfg.horizon, cfg.dt
    x, y, vx, vy, sx, sy = (float(v) for v in obs[2:8])
    tk = dt * np.arange(1, N + 1)
    r = (2 * cfg.radius + cfg.margin + cfg.sigma_scale * math.hypot(sx, sy)
         + np.minimum(cfg.sigma_growth * tk, cfg.growth_cap))
    H = N_HYP_ROUTES if cfg.predict == "routes" else 1
    px = np.empty((H, N))
    py = np.empty((H, N))
    if cfg.predict == "none":
        px[0], py[0] = x, y
        return px, py, r
    # lane-following hypotheses from the map: the agent's lane runs west along y ~ 0.5 from the east
    approaching = x > 0.5 and vx < 0.05 and abs(y - 0.5) < 0.6
    px[0] = x + vx * tk
    if approaching and H > 1:
        # a driver in its lane corrects lateral motion: the lateral velocity decays (time constant tau_lat)
        py[0] = y + vy * cfg.tau_lat * (1.0 - np.exp(-tk / cfg.tau_lat))
    else:
        py[0] = y + vy * tk
    if H == 1:
        return px, py, r
    speed = math.hypot(vx, vy)
    s = speed * tk
    if not approaching:
        px[1:], py[1:] = px[0], py[0]
        return px, py, r
    lead = max(x - 1.5, 0.0)  # distance to the box edge
    hyps = (("straight", 0.0), ("left", 2.0), ("right", 1.0), ("shift_down", -cfg.lateral_spread),
            ("shift_up", cfg.lateral_spread))
    for j, (turn, rad) in enumerate(hyps, start=1):
        if turn == "straight" or turn.startswith("shift"):
            # keep the lane, possibly offset across it (an unknown lateral deviation)
            px[j], py[j] = x - s, np.full(N, y + (rad if turn.startswith("shift") else 0.0))
            continue
        # entering the arc at the box edge; if already past it, start the arc from the current point
        x_in = min(x, 1.5)
        u = np.clip(s - lead, 0.0, None)
        th = np.clip(u / rad, 0.0, math.pi / 2)
        after = np.clip(u - rad * math.pi / 2, 0.0, None)
        xs = np.where(s < lead, x - s, x_in - rad * np.sin(th))
        if turn == "left":
            ys = np.where(s < lead, y, (y - rad) + rad * np.cos(th) - after)
        else:
            ys = np.where(s < lead, y, (y + rad) - rad * np.cos(th) + after)
        px[j], py[j] = xs, ys
    return px, py, r


class NMPCController(torch.nn.Module):
    """Batched NMPC: maps observations ``[B, 8]`` to accelerations ``[B, 1]`` (one IPOPT solve per row).

    Keeps a warm start per batch row; a row whose ego position jumps (a new episode) starts cold.

    >>> ctrl = NMPCController(NMPCConfig(horizon=10))
    >>> a = ctrl(torch.tensor([[-1.25, 0.0, 4.0, 0.5, -0.8, 0.0, 0.05, 0.05]]))
    >>> bool(a.abs() <= 3.2)
    True
    """

    def __init__(self, config: NMPCConfig | None = None):
        super().__init__()
        self.cfg = config or NMPCConfig()
        self.cfg.validate()
        self.stats = NMPCStats()
        self._warm: dict[int, dict] = {}
        self._build()

    def _build(self):
        c = self.cfg
        N = c.horizon
        H = N_HYP_ROUTES if c.predict == "routes" else 1
        opti = ca.Opti()
        Y = opti.variable(N + 1)
        V = opti.variable(N + 1)
        A = opti.variable(N)
        S = opti.variable(N)
        p_y0, p_v0, p_a0 = opti.parameter(), opti.parameter(), opti.parameter()
        p_px = opti.parameter(H, N)
        p_py = opti.parameter(H, N)
        p_r = opti.parameter(N)
        opti.subject_to(Y[0] == p_y0)
        opti.subject_to(V[0] == p_v0)
        for k in range(N):
            opti.subject_to(Y[k + 1] == Y[k] + V[k] * c.dt + 0.5 * A[k] * c.dt**2)
            opti.subject_to(V[k + 1] == V[k] + A[k] * c.dt)
        opti.subject_to(opti.bounded(c.v_min, V[1:], c.v_max))
        opti.subject_to(opti.bounded(-c.a_max, A, c.a_max))
        opti.subject_to(S >= 0)
        for j in range(H):
            for k in range(N):
                d2 = (EGO_X - p_px[j, k]) ** 2 + (Y[k + 1] - p_py[j, k]) ** 2
                opti.subject_to(d2 + S[k] >= p_r[k] ** 2)
        dA = ca.vertcat(A[0] - p_a0, A[1:] - A[:-1])
        w_s = c.slack_decay ** np.arange(N)
        cost = (c.w_v * ca.sumsqr(V[1:] - c.v_ref) + c.w_a * ca.sumsqr(A) + c.w_j * ca.sumsqr(dA)
                - c.w_y * Y[N] + c.w_slack * ca.dot(ca.DM(w_s), S + S**2))
        opti.minimize(cost)
        opti.solver("ipopt", {"print_time": 0, "ipopt.print_level": 0, "ipopt.sb": "yes",
                              "ipopt.max_iter": c.max_iter, "ipopt.tol": 1e-5, "ipopt.acceptable_tol": 1e-3})
        self._opti, self._vars = opti, (Y, V, A, S)
        self._pars = (p_y0, p_v0, p_a0, p_px, p_py, p_r)
        self._cost = cost

    # ------------------------------------------------------------------ guesses
    def _guess(self, y0, v0, kind):
        c = self.cfg
        N = c.horizon
        Y, V, A = np.empty(N + 1), np.empty(N + 1), np.empty(N)
        Y[0], V[0] = y0, v0
        for k in range(N):
            if kind == "go":
                a = np.clip((c.v_max - V[k]) / c.dt, -c.a_max, c.a_max)
            else:  # yield: brake to a stop
                a = np.clip(-V[k] / c.dt, -c.a_max, c.a_max)
            A[k] = a
            V[k + 1] = V[k] + a * c.dt
            Y[k + 1] = Y[k] + V[k] * c.dt + 0.5 * a * c.dt**2
        return {"Y": Y, "V": V, "A": A, "S": np.zeros(N)}

    def _solve(self, guess, par):
        opti = self._opti
        Y, V, A, S = self._vars
        for var, key in ((Y, "Y"), (V, "V"), (A, "A"), (S, "S")):
            opti.set_initial(var, guess[key])
        self.stats.n_ipopt_solves += 1
        try:
            sol = opti.solve()
        except RuntimeError:
            self.stats.n_ipopt_fail += 1
            return None
        res = {"Y": np.asarray(sol.value(Y)).ravel(), "V": np.asarray(sol.value(V)).ravel(),
               "A": np.asarray(sol.value(A)).ravel(), "S": np.asarray(sol.value(S)).ravel()}
        res["J"] = float(sol.value(self._cost))
        return res

    # ------------------------------------------------------------------ one row
    def act(self, obs: np.ndarray, row: int = 0) -> float:
        """Acceleration for one observation row (numpy ``[8]``)."""
        c = self.cfg
        t0 = time.perf_counter()
        y0, v0 = float(obs[0]), float(np.clip(obs[1], c.v_min, c.v_max))
        warm = self._warm.get(row)
        if warm is not None and abs(warm["Y"][1] - y0) > 0.2:  # new episode
            warm = None
        px, py, r = predict_agent(obs, c)
        a_prev = float(warm["A"][0]) if warm is not None else 0.0
        opti = self._opti
        p_y0, p_v0, p_a0, p_px, p_py, p_r = self._pars
        opti.set_value(p_y0, y0)
        opti.set_value(p_v0, v0)
        opti.set_value(p_a0, a_prev)
        opti.set_value(p_px, px)
        opti.set_value(p_py, py)
        opti.set_value(p_r, r)
        candidates = []
        if warm is not None:
            shifted = {k: np.concatenate([warm[k][1:], warm[k][-1:]]) for k in ("Y", "V", "A", "S")}
            shifted["Y"][0], shifted["V"][0] = y0, v0
            candidates.append(self._solve(shifted, None))
        ok = lambda s: s is not None and float(np.max(s["S"])) <= c.slack_tol  # noqa: E731
        if c.multistart and (warm is None or not ok(candidates[0]) or self._is_yielding(candidates[0], py)):
            for kind in ("go", "yield"):
                candidates.append(self._solve(self._guess(y0, v0, kind), None))
        elif warm is None:
            candidates.append(self._solve(self._guess(y0, v0, "yield"), None))
        solved = [s for s in candidates if s is not None]
        if solved:
            # the slack penalty is part of J: a plan that keeps the margin always beats one that does not
            best = min(solved, key=lambda s: s["J"])
            self.stats.n_slack += int(not ok(best))
            if not ok(best) and c.guard_steps > 0:
                best = self._guard(best, solved, y0, v0, px, py, obs)
            a = float(best["A"][0])
            self._warm[row] = best
        else:
            # every IPOPT start failed: brake (counted)
            self.stats.n_fallback += 1
            a = float(np.clip(-v0 / c.dt, -c.a_max, c.a_max))
            self._warm.pop(row, None)
        self.stats.n_steps += 1
        self.stats.solve_times.append(time.perf_counter() - t0)
        return a

    def _clearance(self, plan, px, py, r0) -> float:
        """Worst predicted separation minus ``r0`` over the first ``guard_steps`` steps of ``plan``."""
        K = min(self.cfg.guard_steps, self.cfg.horizon)
        d = np.hypot(EGO_X - px[:, :K], plan["Y"][None, 1:K + 1] - py[:, :K])
        return float(d.min() - r0)

    def _guard(self, best, solved, y0, v0, px, py, obs):
        """Near-term safety check of a plan that needs slack (the ego is inside the inflated margin).

        The slack trade-off sums violations over the whole horizon, so when waiting itself
        violates the (grown) margin for a long time, a plan that drives *into* the agent's
        near-term path can look cheaper (test episode 21: a yielding left-turner whose constant-
        velocity prediction sweeps past the waiting ego). If the chosen plan comes within the
        un-grown safety radius ``2R + margin + c |sigma|`` of any hypothesis in the next
        ``guard_steps`` steps, take, among the solved plans and a full-braking stop plan, the one
        with the largest near-term separation (counted in ``stats.n_guard``).
        """
        c = self.cfg
        sx, sy = float(obs[6]), float(obs[7])
        r0 = 2 * c.radius + c.margin + c.sigma_scale * math.hypot(sx, sy)
        if self._clearance(best, px, py, r0) >= 0.0:
            return best
        stop = self._guess(y0, v0, "yield")
        stop["J"] = np.inf
        options = solved + [stop]
        chosen = max(options, key=lambda s: (round(self._clearance(s, px, py, r0), 3), -s["J"]))
        if chosen is not best:
            self.stats.n_guard += 1
        return chosen

    def _is_yielding(self, sol, py) -> bool:
        """True when the plan stops short of the crossing (so a 'go' start is worth a try)."""
        if sol is None:
            return True
        return bool(sol["V"][-1] < 0.3 and sol["Y"][-1] < self.cfg.y_goal)

    def reset(self):
        """Forget all warm starts (start of new episodes)."""
        self._warm.clear()

    def set_rows(self, rows) -> None:
        """Identify the rows of the next call (for warm starts when a caller passes a subset of a batch)."""
        self._rows = None if rows is None else [int(r) for r in rows]

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        obs = observation.detach().cpu().numpy().reshape(-1, observation.shape[-1])
        rows = getattr(self, "_rows", None)
        if rows is None or len(rows) != len(obs):
            rows = range(len(obs))
        acts = np.array([self.act(o, row=r) for r, o in zip(rows, obs)], dtype=np.float32)
        return torch.as_tensor(acts, device=observation.device).reshape(*observation.shape[:-1], 1)


def make_nmpc_policy(config: NMPCConfig | None = None, **kwargs) -> TensorDictModule:
    """A TensorDictModule reading ``observation`` and writing ``action`` (the NMPC's acceleration).

    ``kwargs`` override :class:`NMPCConfig` fields. The controller (and its ``stats``) is
    ``policy.module``.

    >>> policy = make_nmpc_policy(horizon=30, predict="routes")
    >>> policy.module.cfg.horizon
    30
    """
    return TensorDictModule(NMPCController(nmpc_config(config, **kwargs)), in_keys=["observation"],
                            out_keys=["action"])


def nmpc_config(config: NMPCConfig | None = None, **kwargs) -> NMPCConfig:
    """``config`` (default ``NMPCConfig()``) with the fields ``kwargs`` replaced, validated; builds no solver.

    >>> nmpc_config(margin=0.25).margin
    0.25
    """
    cfg = config or NMPCConfig()
    for k, v in kwargs.items():
        if not hasattr(cfg, k):
            raise ValueError(f"{k} is not an NMPCConfig field; allowed: {sorted(cfg.__dataclass_fields__)}")
        setattr(cfg, k, v)
    cfg.validate()
    return cfg


__all__ = ["NMPCConfig", "NMPCController", "NMPCStats", "make_nmpc_policy", "nmpc_config", "predict_agent"]
