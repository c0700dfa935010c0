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
    optimal sequence (``[N]`` tensors, post-step values as in a trace); ``status``: HiGHS's message;
    ``braked``: of :func:`preview_least_jerk`, the steps braked without a plan (0 otherwise)."""

    jerk: float
    accel: torch.Tensor
    speed: torch.Tensor
    gap: torch.Tensor
    status: str
    braked: int = 0


@dataclass(frozen=True)
class OwnCost:
    """A cap on the CAV's own share of the ring's stage cost (``reward="deeplcc"``,
    :func:`mixed_traffic.envs.traffic.stage_terms`): over the plan's steps,
    ``sum_t w_v (v_t - v_eq_t)^2 + w_s (g_t - s*)^2 <= budget``. The return is made of that cost
    (``1 - J / J_max`` a step), so a budget taken from a reference controller's own terms on the same head asks
    for the CAV's part of a return at least as high as that controller's. The humans' speed terms are left
    out (the program does not model them), as is the command's ``w_u a^2`` (a dropped term loosens the cap).

    Each square enters as the maximum of its tangent lines at ``gap_points`` (m from ``s_star``) and
    ``speed_points`` (m/s from ``v_eq``), a piecewise-linear under-estimate: the capped program is then a
    relaxation of the true cap, and its least jerk is still a lower bound under it; the points' spacing
    sets how loose (a spacing ``d`` under-estimates ``w (x - x0)^2`` by at most ``w d^2 / 4`` a step).

    ``v_eq``: ``[N]``, the speed the env takes errors around after each step (the head's mean over the last
    ``v_eq_window`` seconds); ``budget`` > 0.
    """

    v_eq: object
    budget: float
    weight_v: float = 1.0
    weight_s: float = 0.5
    s_star: float = 20.0
    gap_points: tuple = tuple(float(x) for x in range(-15, 22, 2))
    speed_points: tuple = tuple(float(x) for x in range(-6, 7))

    def of(self, speed, gap) -> torch.Tensor:
        """The true capped cost of a driven ``speed`` and ``gap`` (``[..., N]``), summed over the last dim."""
        v_eq = torch.as_tensor(self.v_eq, dtype=torch.float64)
        speed, gap = torch.as_tensor(speed, dtype=torch.float64), torch.as_tensor(gap, dtype=torch.float64)
        return (self.weight_v * (speed - v_eq) ** 2 + self.weight_s * (gap - self.s_star) ** 2).sum(-1)


def _check(name: str, ok: bool, allowed: str, got) -> None:
    if not ok:
        raise ValueError(f"least_jerk: {name} must be {allowed}, got {got!r}")


def least_jerk(head_speed, *, v_start: float, gap_start: float, dt: float, warmup: float, s_min: float,
               s_max: float | None, accel_bounds: tuple[float, float] = (-3.0, 3.0), gap_floor: float = 0.05,
               steady=None, rmse: float | None = None, norm: str = "l1", stop_gap: float | None = None,
               leader_brake: float | None = None, time_limit: float = 120.0, a_prev: float | None = None,
               end_speed: float | None = None, band_weight: float | None = None,
               track_weight: float | None = None, own_cost: OwnCost | None = None) -> OracleResult:
    """Solve the episode's least-jerk program (module docstring).

    Four options serve a plan over a window of an episode (:func:`preview_least_jerk`): ``a_prev`` (m/s^2),
    the command before the first step, whose change to the first command then counts as well; ``end_speed``
    (m/s >= 0), the speed the last step must end at; ``band_weight`` (> 0), the band made soft: each metre
    outside ``[s_min, s_max]`` on a step costs that much command change (m/s^2), so a plan exists whatever the
    start (``gap_floor`` stays hard); ``track_weight`` (> 0), each m/s of ``|v - v_head|`` on a step costs that
    much command change (a plan that tracks the head as well as it smooths). ``own_cost``
    (:class:`OwnCost`): the CAV's own share of the stage cost capped over the episode (the return bar).

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
    _check("time_limit", time_limit > 0, "> 0 (seconds)", time_limit)
    prog = _program(head_speed, v_start=v_start, gap_start=gap_start, dt=dt, warmup=warmup, s_min=s_min,
                    s_max=s_max, accel_bounds=accel_bounds, gap_floor=gap_floor, steady=steady, rmse=rmse,
                    norm=norm, stop_gap=stop_gap, leader_brake=leader_brake, a_prev=a_prev, end_speed=end_speed,
                    band_weight=band_weight, track_weight=track_weight, own_cost=own_cost)
    x, status = _solve(prog, time_limit=time_limit, who="least_jerk",
                       infeasible="no command sequence keeps the bars on this episode")
    N = prog.n
    tv = float(np.abs(np.diff(x[:N])).sum())  # the objective less the priced blocks (first change, band, error)
    xt = torch.as_tensor(x)
    return OracleResult(jerk=tv / ((N - 1) * dt), accel=xt[:N], speed=xt[N:2 * N], gap=xt[2 * N:3 * N],
                        status=status)


@dataclass
class _Program:
    """A linear program of :func:`least_jerk` over one head trace: ``min cost x`` s.t. ``A_ub x <= b_ub``,
    ``A_eq x = b_eq``, ``bounds``; its columns start with ``a`` (``n``), ``v`` (``n``), ``g`` (``n``) and
    ``u`` (``n - 1``, ``u_t >= |a_{t+1} - a_t|``)."""

    cost: np.ndarray
    A_ub: object
    b_ub: np.ndarray
    A_eq: object
    b_eq: np.ndarray
    bounds: list
    n: int


def _program(head_speed, *, v_start, gap_start, dt, warmup, s_min, s_max, accel_bounds, gap_floor, steady, rmse,
             norm, stop_gap, leader_brake, a_prev, end_speed, band_weight, track_weight,
             own_cost: OwnCost | None = None) -> _Program:
    """:func:`least_jerk`'s program, its arguments validated (each error names the argument)."""
    from scipy import sparse as sp

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
    _check("a_prev", a_prev is None or bool(np.isfinite(a_prev)), "None or finite", a_prev)
    _check("end_speed", end_speed is None or end_speed >= 0, "None or >= 0 (m/s)", end_speed)
    _check("band_weight", band_weight is None or band_weight > 0, "None or > 0", band_weight)
    _check("track_weight", track_weight is None or track_weight > 0, "None or > 0", track_weight)
    st = np.zeros(0, dtype=int)  # the steady samples the RMSE bar counts
    if rmse is not None:
        _check("rmse", rmse > 0, "> 0", rmse)
        _check("steady", steady is not None, "a [N] bool mask when rmse is given", steady)
        mask = torch.as_tensor(steady).flatten()
        _check("steady", mask.numel() == N, f"a mask of {N} values", mask.numel())
        st = np.flatnonzero(mask.numpy())
    S = len(st)
    if own_cost is not None:
        _check("own_cost.budget", own_cost.budget > 0, "> 0", own_cost.budget)
        n_eq = torch.as_tensor(own_cost.v_eq).numel()
        _check("own_cost.v_eq", n_eq == N, f"{N} values (one per step)", n_eq)
        _check("own_cost weights", own_cost.weight_v >= 0 and own_cost.weight_s >= 0, ">= 0",
               (own_cost.weight_v, own_cost.weight_s))
        _check("own_cost points", len(own_cost.gap_points) > 0 and len(own_cost.speed_points) > 0,
               "at least one tangent point each", (own_cost.gap_points, own_cost.speed_points))
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
    if end_speed is not None:
        bounds[2 * N - 1] = (end_speed, end_speed)
    cost = np.zeros(4 * N - 1 + S)
    cost[3 * N:4 * N - 1] = 1.0  # the total variation of the command; the mean |jerk| is it / ((N - 1) dt)
    # priced variables after e, one block per option: (size, price, [(rows over the columns above, rows over
    # the block, rhs)]); the rows above are padded once, after every block is known
    n_base = 4 * N - 1 + S

    def column(k: int):  # [N, n_base]: picks the k-th block of N columns (0: a, 1: v, 2: g)
        return sp.hstack([Z(N, k * N), eye, Z(N, n_base - (k + 1) * N)]).tocsr()
    blocks = []
    if a_prev is not None:  # u_0 >= |a_0 - a_prev|
        first = sp.csr_matrix(([1.0], ([0], [0])), shape=(1, n_base))
        one = sp.identity(1, format="csr")
        blocks.append((1, 1.0, [(first, -one, [a_prev]), (-first, -one, [-a_prev])]))
    if band_weight is not None:  # sigma_t >= the gap's distance outside the band
        lower = np.array([b[0] for b in bounds[2 * N:3 * N]])
        upper = np.array([np.inf if b[1] is None else b[1] for b in bounds[2 * N:3 * N]])
        bounds[2 * N:3 * N] = [(gap_floor, None)] * N  # only the floor stays hard; the band moves to rows with slack
        pick_g = column(2)
        groups = []
        for idx, sign, edge in ((np.flatnonzero(lower > gap_floor), -1.0, -lower),
                                (np.flatnonzero(np.isfinite(upper)), 1.0, upper)):
            if len(idx):  # sign g_t - sigma_t <= sign edge_t
                sel = sp.csr_matrix((np.ones(len(idx)), (np.arange(len(idx)), idx)), shape=(len(idx), N))
                groups.append((sign * pick_g[idx], -sel, edge[idx]))
        blocks.append((N, float(band_weight), groups))
    if track_weight is not None:  # e_t >= |v_t - v_head_t| on every step
        pick_v = column(1)
        blocks.append((N, float(track_weight), [(pick_v, -eye, vh), (-pick_v, -eye, -vh)]))
    if own_cost is not None:  # q_t >= w_s (g_t - s*)^2 and p_t >= w_v (v_t - v_eq_t)^2 by tangents; sum <= budget
        v_eq = torch.as_tensor(own_cost.v_eq, dtype=torch.float64).flatten().numpy()
        groups = []
        for col, center, points, weight, at in ((2, np.full(N, own_cost.s_star), own_cost.gap_points,
                                                 own_cost.weight_s, 0), (1, v_eq, own_cost.speed_points,
                                                                         own_cost.weight_v, N)):
            pick = column(col)
            mine = sp.hstack([Z(N, at), eye, Z(N, N - at)]).tocsr()  # q (first N) or p (last N)
            for d0 in points:  # w (x - c)^2 >= w (2 d0 (x - c) - d0^2): 2 w d0 x - y <= w (2 d0 c + d0^2)
                groups.append((2 * weight * d0 * pick, -mine, weight * (2 * d0 * center + d0 ** 2)))
        groups.append((Z(1, n_base), sp.csr_matrix(np.ones((1, 2 * N))), [float(own_cost.budget)]))
        blocks.append((2 * N, 0.0, groups))
    width = sum(n for n, _, _ in blocks)
    if width:
        rows = [sp.hstack([r, Z(r.shape[0], width)]) for r in rows]
        a_eq = sp.hstack([a_eq, Z(a_eq.shape[0], width)]).tocsr()
        offset = 0
        for n, price, groups in blocks:
            for above, own, rhs in groups:
                k = own.shape[0]
                rows.append(sp.hstack([above, Z(k, offset), own, Z(k, width - offset - n)]))
                b_ub.append(np.asarray(rhs, dtype=float))
            cost = np.concatenate([cost, np.full(n, price)])
            bounds += [(0.0, None)] * n
            offset += n
    return _Program(cost=cost, A_ub=sp.vstack(rows).tocsr(), b_ub=np.concatenate(b_ub), A_eq=a_eq, b_eq=b_eq,
                    bounds=bounds, n=N)


def _solve(prog: _Program, *, time_limit: float, who: str, infeasible: str) -> tuple[np.ndarray, str]:
    """The optimum of ``prog`` and HiGHS's message; ``ValueError`` naming ``who`` when it is infeasible,
    ``RuntimeError`` when HiGHS has not finished within ``time_limit`` seconds."""
    from scipy.optimize import linprog

    problem = dict(A_ub=prog.A_ub, b_ub=prog.b_ub, A_eq=prog.A_eq, b_eq=prog.b_eq, bounds=prog.bounds)
    # the interior-point solver is fast here (1-2 s); its crossover to a vertex stalled on a few episodes
    # (a near-degenerate optimum), where the dual simplex finishes instead
    for method, limit in (("highs-ipm", time_limit / 3), ("highs-ds", time_limit)):
        res = linprog(prog.cost, method=method, options={"time_limit": limit}, **problem)
        if res.status != 1:  # 1: time or iteration limit
            break
    if res.status == 2:
        raise ValueError(f"{who}: {infeasible} ({res.message})")
    if res.status != 0:
        raise RuntimeError(f"{who}: HiGHS did not finish within time_limit={time_limit} s ({res.message})")
    return res.x, res.message


def preview_least_jerk(head_speed, *, preview: float, horizon: float, v_start: float, gap_start: float, dt: float,
                       warmup: float, s_min: float, s_max: float, head_start: float | None = None,
                       accel_bounds: tuple[float, float] = (-3.0, 3.0), band_weight: float = 1.0,
                       replan: float = 0.5, stop_gap: float | None = None,
                       leader_brake: float | None = None, track_weight: float | None = None) -> OracleResult:
    """A causal CAV that sees ``preview`` seconds of the head's coming speeds and drives by least-jerk plans.

    Every ``replan`` seconds it solves :func:`least_jerk` over the next ``horizon`` seconds from its present
    speed, gap and command (``a_prev``): the head's speeds known for the first ``preview`` seconds (its plan,
    as a connected head could broadcast it) and held at the last known one after that (``preview`` 0: the
    head's present speed, all a follower that only measures it knows), the band soft (``band_weight``), the
    speed error priced when ``track_weight`` is given, and the plan ending at that held speed. It drives the
    plan's commands until the next plan, behind the head's true speeds (the env's ``"euler"`` update). ``preview`` from 0 up to the episode's length spans the causal
    controller that only measures the head and the clairvoyant sequence of :func:`least_jerk`, so the jerk
    it reaches in the band as ``preview`` grows shows how much of the head's future a jerk bar asks for.

    A follower that cannot see a head's stop coming cannot keep a gap floor by planning alone: with
    ``stop_gap`` and ``leader_brake`` each command is capped by the stopping rule of the base's stopping
    envelope and the safety layer (:func:`transforms.safety_layer.safe_accel_upper`, on the present gap and
    speeds), so the CAV stays collision-free whatever the head does within ``leader_brake``; a capped step
    starts a new plan at the next. Where a plan has no solution, the step brakes at ``accel_bounds[0]``
    (counted in ``status``).

    ``head_speed`` (``[N]``): the head's speed after each step; ``head_start``: before the first (default
    ``head_speed[0]``). Returns the driven sequence (``jerk``: its mean |jerk| over steps 1..N-1, as the
    report counts it; ``status``: the count of plans and of steps braked without one, the latter also as
    ``braked``).
    """
    from transforms.safety_layer import safe_accel_upper

    vh = torch.as_tensor(head_speed, dtype=torch.float64).flatten()
    N = vh.shape[0]
    _check("preview", preview >= 0, ">= 0 (s)", preview)
    if stop_gap is not None:
        _check("leader_brake", leader_brake is not None and leader_brake > 0, "> 0 (m/s^2) with stop_gap", leader_brake)
    _check("horizon", horizon >= max(preview, 2 * dt), f">= max(preview, {2 * dt}) (s)", horizon)
    _check("replan", dt <= replan <= horizon, f"in [{dt}, horizon] (s)", replan)
    P, H, every = int(round(preview / dt)), int(round(horizon / dt)), max(1, int(round(replan / dt)))
    lo, hi = accel_bounds
    v, gap = float(v_start), float(gap_start)
    last_seen = float(vh[0] if head_start is None else head_start)
    a_prev, plan, used = None, None, 0
    accel, speed, gaps, plans, braked = [], [], [], 0, 0
    for k in range(N):
        if plan is None or used == every:
            seen = vh[k:k + P]
            held = float(seen[-1]) if len(seen) else last_seen
            pred = torch.cat([seen, torch.full((H - len(seen),), held, dtype=torch.float64)])
            try:
                plan = least_jerk(pred, v_start=v, gap_start=max(gap, 1e-3), dt=dt, warmup=warmup - k * dt,
                                  s_min=s_min, s_max=s_max, accel_bounds=accel_bounds, a_prev=a_prev,
                                  end_speed=held, band_weight=band_weight, track_weight=track_weight).accel
            except ValueError:  # no plan from here: brake for this step and plan again at the next
                plan = torch.full((1,), float(lo), dtype=torch.float64)
                braked += 1
            used, plans = 0, plans + 1
        a = min(max(float(plan[min(used, len(plan) - 1)]), lo), hi)
        used = every if len(plan) == 1 else used + 1
        if stop_gap is not None:
            state = torch.tensor([gap, v, last_seen], dtype=torch.float64)
            cap = float(safe_accel_upper(*state, s_min=stop_gap, dt=dt, brake=-lo, leader_brake=leader_brake))
            if a > cap:
                a, used = max(cap, lo), every
        v_next = max(0.0, v + a * dt)
        executed = (v_next - v) / dt
        gap += (float(vh[k]) - v_next) * dt
        v, a_prev, last_seen = v_next, executed, float(vh[k])
        accel.append(executed), speed.append(v), gaps.append(gap)
    acc = torch.tensor(accel, dtype=torch.float64)
    return OracleResult(jerk=float(acc.diff().abs().sum()) / ((N - 1) * dt), accel=acc,
                        speed=torch.tensor(speed, dtype=torch.float64), gap=torch.tensor(gaps, dtype=torch.float64),
                        status=f"{plans} plans, {braked} steps braked without one", braked=braked)


@dataclass
class CausalResult:
    """``jerk``: the optimum, the weighted mean over the heads of each one's mean |jerk| over the counted steps
    (m/s^3); ``per_head``: that mean per head (``[L]``); ``accel``, ``speed``, ``gap``: the optimal sequences
    (``[L, N]``); ``status``: HiGHS's message."""

    jerk: float
    per_head: torch.Tensor
    accel: torch.Tensor
    speed: torch.Tensor
    gap: torch.Tensor
    status: str


def history_groups(head_speeds) -> torch.Tensor:
    """``[L, N]`` ids: ``ids[i, t] == ids[j, t]`` when heads ``i`` and ``j`` had the same speeds after steps
    ``0 .. t-1``, all a CAV that chooses step ``t``'s command from what it has measured can tell apart.

    >>> import torch
    >>> history_groups(torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 4.0], [1.0, 5.0, 5.0]])).tolist()
    [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    """
    vh = torch.as_tensor(head_speeds, dtype=torch.float64)
    L, N = vh.shape
    ids = torch.zeros(L, N, dtype=torch.long)
    for t in range(1, N):
        pairs = torch.stack([ids[:, t - 1].double(), vh[:, t - 1]], 1)
        ids[:, t] = torch.unique(pairs, dim=0, return_inverse=True)[1]
    return ids


def causal_least_jerk(head_speeds, *, v_start: float, gap_start: float, dt: float, warmup: float, s_min: float,
                      s_max: float | None, weights=None, count_from: int = 0, count_to: int | None = None,
                      accel_bounds: tuple[float, float] = (-3.0, 3.0), gap_floor: float = 0.05,
                      stop_gap: float | None = None, leader_brake: float | None = None, a_prev: float | None = None,
                      end_speeds=None, steady=None, rmse: float | None = None, norm: str = "l1",
                      own_costs=None, time_limit: float = 600.0) -> CausalResult:
    """The least jerk of any **causal** CAV over a set of head futures: a lower bound, where
    :func:`least_jerk` (which knows the head's future) is not one, of what a controller that only measures
    the head can reach.

    The heads (``[L, N]``, each row one head's speeds after each step, all from the same start) stand for a
    distribution over what the head may do (``weights``, default uniform). One command sequence per head,
    each in :func:`least_jerk`'s bars (the band after ``warmup``, ``gap_floor``, the acceleration bounds,
    optionally the stopping-safe set), with the constraint that makes them one controller: step ``t``'s
    command is the same for heads whose speeds agree on steps ``0 .. t-1`` (:func:`history_groups`), since a
    CAV cannot tell them apart when it chooses it. The objective is the weighted mean of each head's mean
    |jerk| over steps ``count_from .. count_to - 1`` (default: to the last step; step 0 counts with ``a_prev``,
    the command before it, as in :func:`least_jerk`). Steps outside are free but
    keep the bars: a settling prefix before, and after, a tail that stops the plan from saving jerk by
    leaving a speed step unanswered at the end. That tail, though, can answer it with any jerk; so a plan can
    also be made to end settled, ``end_speeds`` (``[L]``, e.g. each head's last speed), and count every step.

    ``steady`` (``[L, N]`` bool, each head's steady samples, e.g. the report's:
    :func:`~mixed_traffic.evaluation.harness.steady_samples` of the head's accelerations) with
    ``rmse`` (m/s) adds :func:`least_jerk`'s speed bar on each head: the mean |v - v_head| over its steady samples
    at most ``rmse`` (``norm`` ``"l1"``, implied by an RMSE at most ``rmse``, so the bound stays a bound for the
    RMSE bar), or every such sample within ``rmse`` (``"linf"``). ``own_costs`` (``L`` :class:`OwnCost`, one per
    head, or None): each head's own-cost cap (the return bar against a reference controller's own terms on it).

    Every causal controller that keeps these bars on all ``L`` heads has, averaged with ``weights`` over them,
    at least this mean |jerk| over the counted steps, whatever else it observes (the CAV's own state follows
    from its commands and the head's speeds). Heads built as a tree (the head's choice revealed step by step,
    e.g. a speed step drawn from a few values every period) make the bound tight for that distribution;
    heads that differ from the first step make it :func:`least_jerk`'s mean.

    Raises ``ValueError`` naming the argument on bad input or when no causal controller keeps the bars on
    every head; ``RuntimeError`` when HiGHS has not finished within ``time_limit`` seconds.

        >>> import torch
        >>> slow, fast = torch.full((300,), 10.0), torch.full((300,), 10.0)
        >>> slow[100:], fast[100:] = 9.0, 13.0  # after 10 s the head steps down or up: the CAV cannot know which
        >>> kw = dict(v_start=10.0, gap_start=20.0, dt=0.1, warmup=0.0, s_min=15.0, s_max=25.0)
        >>> r = causal_least_jerk(torch.stack([slow, fast]), **kw)
        >>> seen = [least_jerk(h, **kw).jerk for h in (slow, fast)]  # each knowing its own future
        >>> round(r.jerk, 4), round(sum(seen) / 2, 4)  # not knowing the step costs jerk
        (0.0242, 0.0013)
        >>> torch.allclose(r.accel[0, :101], r.accel[1, :101])  # one command until the head's speeds differ
        True
    """
    from scipy import sparse as sp

    vh = torch.as_tensor(head_speeds, dtype=torch.float64)
    if vh.ndim != 2 or vh.shape[0] < 1 or vh.shape[1] < 2:
        raise ValueError(f"causal_least_jerk: head_speeds must be [L, N] with L >= 1, N >= 2, got {tuple(vh.shape)}")
    L, N = vh.shape
    w = torch.full((L,), 1.0 / L, dtype=torch.float64) if weights is None else torch.as_tensor(weights, dtype=torch.float64)
    if w.shape != (L,) or not bool((w >= 0).all()) or not float(w.sum()) > 0:
        raise ValueError(f"causal_least_jerk: weights must be {L} values >= 0 with a positive sum, got {w.tolist()}")
    w = w / w.sum()
    count_to = N if count_to is None else count_to
    if not 0 <= count_from < count_to - 1 or count_to > N:
        raise ValueError(f"causal_least_jerk: count_from and count_to must satisfy 0 <= count_from < count_to - 1, "
                         f"count_to <= {N} (step indices), got {count_from} and {count_to}")
    _check("time_limit", time_limit > 0, "> 0 (seconds)", time_limit)
    ends = [None] * L if end_speeds is None else torch.as_tensor(end_speeds, dtype=torch.float64).flatten().tolist()
    if len(ends) != L:
        raise ValueError(f"causal_least_jerk: end_speeds must be None or {L} values (m/s >= 0), got {len(ends)}")
    masks = [None] * L
    caps = [None] * L if own_costs is None else list(own_costs)
    if len(caps) != L:
        raise ValueError(f"causal_least_jerk: own_costs must be None or {L} OwnCost (one per head), got {len(caps)}")
    if rmse is not None:
        _check("steady", steady is not None, "an [L, N] bool mask when rmse is given", steady)
        st = torch.as_tensor(steady)
        if tuple(st.shape) != (L, N):
            raise ValueError(f"causal_least_jerk: steady must be [{L}, {N}] (one mask per head), got {tuple(st.shape)}")
        masks = list(st)
    step = np.arange(1, N)  # u_t is the change into step t + 1
    counted = (step >= count_from) & (step < count_to)
    with_prev = a_prev is not None and count_from == 0  # the change from a_prev into step 0 counts too
    n_counted = int(counted.sum()) + with_prev
    progs = [_program(vh[i], v_start=v_start, gap_start=gap_start, dt=dt, warmup=warmup, s_min=s_min, s_max=s_max,
                      accel_bounds=accel_bounds, gap_floor=gap_floor, steady=masks[i], rmse=rmse, norm=norm,
                      stop_gap=stop_gap, leader_brake=leader_brake, a_prev=a_prev, end_speed=ends[i],
                      band_weight=None, track_weight=None, own_cost=caps[i]) for i in range(L)]
    # each head's columns (_program's order): a, v, g, u (N - 1), e (one per steady sample), then a_prev's when
    # given, then the own-cost block (q, p) when capped
    widths = [len(p.cost) for p in progs]
    offsets = np.r_[0, np.cumsum(widths)[:-1]]

    def counted_columns(i: int) -> np.ndarray:
        """Head ``i``'s cost mask: ``u`` on the counted steps only, ``a_prev``'s column (the first priced block,
        right after ``e``) only when its change counts; the own-cost block after it is free anyway."""
        mask = np.ones(widths[i])
        mask[3 * N:4 * N - 1] = counted
        if a_prev is not None and not with_prev:
            mask[4 * N - 1 + (0 if masks[i] is None else int(torch.as_tensor(masks[i]).sum()))] = 0.0
        return mask
    cost = np.concatenate([p.cost * counted_columns(i) * float(w[i]) / (n_counted * dt) for i, p in enumerate(progs)])
    # one controller: a_t of every head equals a_t of the first head with the same history
    ids = history_groups(vh).numpy()
    rows, cols, vals = [], [], []
    k = 0
    for t in range(N):
        leader = {}
        for i in range(L):
            j = leader.setdefault(ids[i, t], i)
            if j != i:
                rows += [k, k]
                cols += [offsets[i] + t, offsets[j] + t]
                vals += [1.0, -1.0]
                k += 1
    same = sp.csr_matrix((vals, (rows, cols)), shape=(k, sum(widths)))
    prog = _Program(cost=cost, A_ub=sp.block_diag([p.A_ub for p in progs], format="csr"),
                    b_ub=np.concatenate([p.b_ub for p in progs]),
                    A_eq=sp.vstack([sp.block_diag([p.A_eq for p in progs], format="csr"), same]).tocsr(),
                    b_eq=np.concatenate([*(p.b_eq for p in progs), np.zeros(k)]),
                    bounds=[b for p in progs for b in p.bounds], n=N)
    x, status = _solve(prog, time_limit=time_limit, who="causal_least_jerk",
                       infeasible="no causal command sequence keeps the bars on every head")
    x = torch.stack([torch.as_tensor(x[o:o + 3 * N]) for o in offsets])  # each head's a, v, g
    accel = x[:, :N]
    change = accel.diff(dim=1, prepend=accel[:, :1] if a_prev is None else torch.full((L, 1), float(a_prev))).abs()
    per_head = (change * torch.as_tensor(np.r_[float(with_prev), counted])).sum(1) / (n_counted * dt)
    return CausalResult(jerk=float((per_head * w).sum()), per_head=per_head, accel=accel, speed=x[:, N:2 * N],
                        gap=x[:, 2 * N:3 * N], status=status)


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
    vh, v_start, gap_start, _ = start_of_trace(trace, row, dt=dt)
    mask = None if steady is None else torch.as_tensor(steady)[row, :len(vh)]
    return least_jerk(vh, v_start=v_start, gap_start=gap_start, dt=dt, warmup=warmup, s_min=s_min,
                      s_max=s_max, accel_bounds=accel_bounds, steady=mask, rmse=rmse, norm=norm,
                      stop_gap=stop_gap, leader_brake=leader_brake)


def start_of_trace(trace, row: int, *, dt: float) -> tuple[torch.Tensor, float, float, float]:
    """``(head_speed, v_start, gap_start, head_start)`` of episode ``row`` of a trace (its valid steps): the
    head's speeds after each step, and the CAV's speed, its gap and the head's speed before the first step,
    recovered from that step (``"euler"`` update). The CAV must drive right behind the head."""
    n = int(trace.valid[row].sum())
    gap, head_gap = trace.gap[row, :n].double(), trace.head_gap[row, :n].double()
    if not torch.allclose(gap, head_gap):
        raise ValueError("start_of_trace: the CAV must drive right behind the head (its gap is the head gap)")
    v, a, vh = trace.cav_speed[row, :n].double(), trace.cav_accel[row, :n].double(), trace.head_speed[row, :n].double()
    head_start = float(vh[0] - trace.head_accel[row, 0].double() * dt)
    return vh, max(float(v[0] - a[0] * dt), 0.0), float(gap[0] - dt * (vh[0] - v[0])), max(head_start, 0.0)


def steady_mask(trace, *, dt: float, warmup: float, settle: float) -> torch.Tensor:
    """The report's steady samples (``[episodes, T]`` bool): after the warm-up, the head's
    acceleration below 0.05 m/s^2 for ``settle`` seconds (as :func:`~mixed_traffic.evaluation.harness.episode_metrics`)."""
    from mixed_traffic.evaluation.harness import steady_samples

    return steady_samples(trace.head_accel, trace.valid & (trace.time >= warmup), int(round(settle / dt)))


__all__ = ["OwnCost", "causal_least_jerk", "history_groups", "least_jerk", "least_jerk_of_trace", "preview_least_jerk", "start_of_trace", "steady_mask", "CausalResult", "OracleResult"]
