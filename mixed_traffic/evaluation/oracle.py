"""The least jerk any CAV could have on an episode, knowing the head's whole future (a linear program).

A reference for the jerk bar of the ring: for one recorded episode (the head's speeds and the
CAV's start), the smallest whole-episode mean ``|a_t - a_{t-1}| / dt`` (the report's
``mean_abs_jerk``, :func:`~mixed_traffic.evaluation.harness.abs_jerk`) over every command
sequence that keeps the gap bars: ``gap >= gap_floor`` throughout, ``s_min <= gap <= s_max``
after the warm-up, speeds ``>= 0``, commands in the CAV's acceleration bounds. Optionally also
the steady-tracking bar on the report's steady samples: ``norm="l1"`` asks ``mean |v - v_head|
<= rmse``, implied by ``RMSE <= rmse``, so its optimum is a **lower bound** of the least jerk under
the RMSE bar; ``norm="linf"`` asks ``|v - v_head| <= rmse`` on every steady sample, which implies
it, so its optimum is **achieved** by a sequence that meets the bar (an upper bound).

The controller it describes is not causal: it sees the head's future. No causal controller can
do better on the episode; how far a causal one must stay above it is what the bound leaves
open. Only the CAV right behind the head is modelled (its gap is the head gap), under the env's
``"euler"`` update (``v' = max(0, v + a dt)``, ``x' = x + v' dt``, :func:`mixed_traffic.physics.integrate`),
so the sequence it returns, replayed through the env's integrator, gives its gaps.

Why not a TorchRL or CasADi tool: this is an L1 objective under linear constraints over a whole
episode (about 2,000 steps), which SciPy's HiGHS interior-point solver (with its crossover to an exact
vertex) solves in one to two seconds.

    >>> import torch
    >>> from mixed_traffic.evaluation.oracle import least_jerk
    >>> head = torch.cat([torch.full((100,), 10.0), torch.full((100,), 12.0)])  # a step of the head's speed
    >>> r = least_jerk(head, v_start=10.0, gap_start=20.0, dt=0.1, warmup=0.0, s_min=5.0, s_max=40.0)
    >>> round(r.jerk, 6)  # the gap may open by 20 m: no acceleration change needed at all
    0.0
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class OracleResult:
    """``jerk``: the optimum (m/s^3, the report's mean |jerk|); ``accel``, ``speed``, ``gap``: the
    optimal sequence (``[N]`` tensors, post-step values as in a trace); ``status``: HiGHS's message."""

    jerk: float
    accel: torch.Tensor
    speed: torch.Tensor
    gap: torch.Tensor
    status: str


def _check(name: str, ok: bool, allowed: str, got) -> None:
    if not ok:
        raise ValueError(f"least_jerk: {name} must be {allowed}, got {got!r}")


def least_jerk(head_speed, *, v_start: float, gap_start: float, dt: float, warmup: float, s_min: float,
               s_max: float | None, accel_bounds: tuple[float, float] = (-3.0, 3.0), gap_floor: float = 0.05,
               steady=None, rmse: float | None = None, norm: str = "l1", stop_gap: float | None = None,
               leader_brake: float | None = None, time_limit: float = 120.0) -> OracleResult:
    """Solve the episode's least-jerk program (module docstring).

    ``stop_gap`` (m; with ``leader_brake``, m/s^2 > 0): every step must also end in the stopping-safe set,
    the safety layer's ``"stopping"`` rule (:func:`transforms.safety_layer.safe_accel_upper`): if the head
    braked at ``leader_brake`` from that step on, the CAV braking at ``min(-accel_bounds[0], leader_brake)``
    would keep every future gap at or above ``stop_gap``. A causal CAV that cannot know whether the head
    will stop must keep this at every step to be collision-free whatever the head does within its braking
    bound, so the optimum is then a lower bound of the jerk of every such controller on the episode. The
    rule's convex, piecewise-linear braking distance enters as its linear pieces (those within 15 m/s of
    the head's speed at each step: a relaxation, so the bound stays a bound; the first step, whose
    pre-step head speed the trace does not hold, is left free).

    ``head_speed``: the head's speed after each step (``[N]``, a trace's ``head_speed`` row);
    ``v_start`` / ``gap_start``: the CAV's speed and gap before the first step; ``warmup``: seconds
    after which ``[s_min, s_max]`` applies (step ``t`` is at time ``(t + 1) dt``, as in a trace);
    ``steady``: ``[N]`` bool mask of the samples the RMSE bar counts (with ``rmse``).
    Raises ``ValueError`` naming the argument on bad input, and when the program is infeasible
    (no command sequence keeps the bars on this episode); ``RuntimeError`` when HiGHS has not
    finished within ``time_limit`` seconds.
    """
    from scipy import sparse as sp
    from scipy.optimize import linprog

    vh = torch.as_tensor(head_speed, dtype=torch.float64).flatten().numpy()
    N = vh.shape[0]
    _check("head_speed", N >= 2 and bool(np.isfinite(vh).all()), "at least 2 finite values", N)
    _check("dt", dt > 0, "> 0", dt)
    _check("v_start", v_start >= 0, ">= 0", v_start)
    _check("gap_start", gap_start > 0, "> 0", gap_start)
    lo, hi = accel_bounds
    _check("accel_bounds", lo < 0 < hi, "(low < 0 < high)", accel_bounds)
    _check("s_min", 0 <= s_min, ">= 0", s_min)
    _check("s_max", s_max is None or s_max > s_min, "None or > s_min", s_max)
    _check("norm", norm in ("l1", "linf"), "'l1' or 'linf'", norm)
    _check("time_limit", time_limit > 0, "> 0 (seconds)", time_limit)
    st = np.zeros(0, dtype=int)  # the steady samples the RMSE bar counts
    if rmse is not None:
        _check("rmse", rmse > 0, "> 0", rmse)
        _check("steady", steady is not None, "a [N] bool mask when rmse is given", steady)
        mask = torch.as_tensor(steady).flatten()
        _check("steady", mask.numel() == N, f"a mask of {N} values", mask.numel())
        st = np.flatnonzero(mask.numpy())
    S = len(st)
    if stop_gap is not None:
        _check("stop_gap", stop_gap >= 0, ">= 0 (m)", stop_gap)
        _check("leader_brake", leader_brake is not None and leader_brake > 0, "> 0 (m/s^2) with stop_gap",
               leader_brake)

    # variables: a (N), v (N), g (N), u (N - 1) >= |a_t - a_{t-1}|, e (S) >= |v - v_head| on steady samples
    Z = lambda r, c: sp.csr_matrix((r, c))  # noqa: E731
    eye = sp.identity(N, format="csr")
    diff = sp.diags([np.ones(N), -np.ones(N - 1)], [0, -1], format="csr")  # x_t - x_{t-1}
    a_eq = sp.vstack([sp.hstack([-dt * eye, diff, Z(N, N), Z(N, N - 1 + S)]),   # v_t - v_{t-1} = a_t dt
                      sp.hstack([Z(N, N), dt * eye, diff, Z(N, N - 1 + S)])]).tocsr()  # g_t - g_{t-1} = (vh_t - v_t) dt
    b_eq = np.concatenate([np.r_[v_start, np.zeros(N - 1)], dt * vh + np.r_[gap_start, np.zeros(N - 1)]])
    step = sp.diags([np.ones(N - 1), -np.ones(N - 1)], [1, 0], shape=(N - 1, N), format="csr")  # a_t - a_{t-1}
    rows = [sp.hstack([step, Z(N - 1, 2 * N), -sp.identity(N - 1), Z(N - 1, S)]),
            sp.hstack([-step, Z(N - 1, 2 * N), -sp.identity(N - 1), Z(N - 1, S)])]
    b_ub = [np.zeros(N - 1), np.zeros(N - 1)]
    if S:
        pick = sp.csr_matrix((np.ones(S), (np.arange(S), st)), shape=(S, N))
        rows += [sp.hstack([Z(S, N), pick, Z(S, 2 * N - 1), -sp.identity(S)]),
                 sp.hstack([Z(S, N), -pick, Z(S, 2 * N - 1), -sp.identity(S)])]
        b_ub += [vh[st], -vh[st]]
        if norm == "l1":
            rows.append(sp.hstack([Z(1, 4 * N - 1), sp.csr_matrix(np.full((1, S), 1.0 / S))]))
            b_ub.append(np.array([rmse]))
    if stop_gap is not None:
        r, bu = _stopping_rows(vh, dt=dt, stop_gap=stop_gap, brake=min(-lo, leader_brake), leader_brake=leader_brake)
        rows.append(sp.hstack([r, Z(r.shape[0], N - 1 + S)]))
        b_ub.append(bu)
    after = (np.arange(1, N + 1) * dt) >= warmup - 1e-9
    bounds = ([(lo, hi)] * N + [(0.0, None)] * N
              + [((s_min if a else gap_floor), (s_max if a and s_max is not None else None)) for a in after]
              + [(0.0, None)] * (N - 1) + [(0.0, rmse if norm == "linf" else None)] * S)
    cost = np.zeros(4 * N - 1 + S)
    cost[3 * N:4 * N - 1] = 1.0  # the total variation of the command; the mean |jerk| is it / ((N - 1) dt)
    problem = dict(A_ub=sp.vstack(rows).tocsr(), b_ub=np.concatenate(b_ub), A_eq=a_eq, b_eq=b_eq, bounds=bounds)
    # the interior-point solver is fast here (1-2 s); its crossover to a vertex stalled on a few episodes
    # (a near-degenerate optimum), where the dual simplex finishes instead
    for method, limit in (("highs-ipm", time_limit / 3), ("highs-ds", time_limit)):
        res = linprog(cost, method=method, options={"time_limit": limit}, **problem)
        if res.status != 1:  # 1: time or iteration limit
            break
    if res.status == 2:
        raise ValueError(f"least_jerk: no command sequence keeps the bars on this episode ({res.message})")
    if res.status != 0:
        raise RuntimeError(f"least_jerk: HiGHS did not finish within time_limit={time_limit} s ({res.message})")
    x = torch.as_tensor(res.x)
    return OracleResult(jerk=float(res.fun) / ((N - 1) * dt), accel=x[:N], speed=x[N:2 * N], gap=x[2 * N:3 * N],
                        status=res.message)


def _stopping_rows(vh: np.ndarray, *, dt: float, stop_gap: float, brake: float, leader_brake: float,
                   window: float = 15.0):
    """``A x <= b`` over ``x = (a, v, g)`` (``[3N]``) for steps ``1..N-1``: the post-step speed ``v_t`` within
    the stopping rule of the pre-step state ``(g_{t-1}, vh_{t-1})``. With ``vl1`` the head's speed after one
    braking step: ``v_t <= vl1 + (g_{t-1} - G) / dt`` and ``F(v_t) <= g_{t-1} - G + vl1 dt + D(vl1)``, where
    ``F(u) = u dt + D(u, b)`` is the maximum of its segment lines ``dt (m + 1) u - dt h m (m + 1) / 2``
    (``h = b dt``; ``transforms.safety_layer._max_speed_within_distance``)."""
    from scipy import sparse as sp

    from transforms.safety_layer import stopping_budget

    N = vh.shape[0]
    h = brake * dt
    head = torch.as_tensor(vh[:-1])
    vl1, c0 = (x.numpy() for x in stopping_budget(torch.zeros_like(head), head, s_min=stop_gap, dt=dt,
                                                   leader_brake=leader_brake))  # c0: the budget at gap 0
    rows, cols, vals, b = [], [], [], []
    k = 0
    for t in range(1, N):
        lines = [None] + list(range(max(0, int((vh[t - 1] - window) / h)), int((vh[t - 1] + window) / h) + 2))
        for m in lines:  # None: the next gap itself
            coef = 1.0 if m is None else dt * (m + 1)
            rhs = vl1[t - 1] * dt - stop_gap if m is None else c0[t - 1] + dt * h * m * (m + 1) / 2
            scale = dt if m is None else 1.0  # v_t dt - g_{t-1} <= vl1 dt - G
            rows += [k, k]
            cols += [N + t, 2 * N + t - 1]
            vals += [coef * scale, -1.0]
            b.append(rhs)
            k += 1
    return sp.csr_matrix((vals, (rows, cols)), shape=(k, 3 * N)), np.asarray(b)


def least_jerk_of_trace(trace, row: int, *, dt: float, warmup: float, s_min: float, s_max: float | None,
                        accel_bounds: tuple[float, float] = (-3.0, 3.0), steady=None, rmse: float | None = None,
                        norm: str = "l1", stop_gap: float | None = None,
                        leader_brake: float | None = None) -> OracleResult:
    """:func:`least_jerk` on episode ``row`` of a :class:`~mixed_traffic.evaluation.harness.Trace` (its valid
    steps); the CAV's start is recovered from its first step (``"euler"`` update)."""
    n = int(trace.valid[row].sum())
    gap, head_gap = trace.gap[row, :n].double(), trace.head_gap[row, :n].double()
    if not torch.allclose(gap, head_gap):
        raise ValueError("least_jerk_of_trace: the CAV must drive right behind the head (its gap is the head gap)")
    v, a, vh = trace.cav_speed[row, :n].double(), trace.cav_accel[row, :n].double(), trace.head_speed[row, :n].double()
    v_start = float(v[0] - a[0] * dt)
    gap_start = float(gap[0] - dt * (vh[0] - v[0]))
    mask = None if steady is None else torch.as_tensor(steady)[row, :n]
    return least_jerk(vh, v_start=max(v_start, 0.0), gap_start=gap_start, dt=dt, warmup=warmup, s_min=s_min,
                      s_max=s_max, accel_bounds=accel_bounds, steady=mask, rmse=rmse, norm=norm,
                      stop_gap=stop_gap, leader_brake=leader_brake)


def steady_mask(trace, *, dt: float, warmup: float, settle: float) -> torch.Tensor:
    """The report's steady samples (``[episodes, T]`` bool): after the warm-up, the head's
    acceleration below 0.05 m/s^2 for ``settle`` seconds (as :func:`~mixed_traffic.evaluation.harness.episode_metrics`)."""
    from mixed_traffic.evaluation.harness import steady_samples

    return steady_samples(trace.head_accel, trace.valid & (trace.time >= warmup), int(round(settle / dt)))


__all__ = ["least_jerk", "least_jerk_of_trace", "steady_mask", "OracleResult"]
