"""The least jerk any causal CAV can have in the band behind a head whose steps it cannot foresee.

``ring_jerk_oracle.py`` gives the clairvoyant floor (the CAV knows the head's whole future) and planners that
see part of it. Neither bounds what a follower that only measures the head can do. This does, on a tree of
head futures (:func:`mixed_traffic.evaluation.oracle.causal_least_jerk`):

- the head drives at ``--v0``; at each of ``--depth`` decision times, every ``--epoch`` seconds, it keeps its
  target speed (probability ``--p-hold``) or steps to one of ``--speeds`` (equal shares of the rest), ramping
  at its own bounds as the ring's head does (``TrafficScenario.head_accel_bounds``); a ``--tail`` follows the
  last decision;
- one command sequence per head future, the CAV starting steady at ``--v0`` with gap ``--gap`` and ending at
  the head's last speed, inside ``[s_min, s_max]`` (the evaluation's 5-40 m) throughout, and with
  ``--stop-gap G`` in the stopping-safe set at every step (no head braking within its bound could bring the
  gap below G m; the default's base keeps it with 5 m, IDM-as-CAV does not); the commands of futures the CAV
  cannot yet tell apart (the head's speeds so far agree) are one;
- the objective, every step counted: the futures' weighted mean of the mean |jerk| (the report's metric).

So no causal controller that keeps the band on these futures has, averaged over them, less jerk; and the
optimal sequences are such a controller, on these futures. Beside it, on the same futures: the clairvoyant
figure (each future known in advance; :func:`~mixed_traffic.evaluation.oracle.least_jerk` with the same
start, end and count) and controllers replayed behind the same heads (:mod:`mixed_traffic.evaluation.replay`)
after a 60-s settling prefix at ``--v0`` that is not counted: IDM-as-CAV (the jerk bar's reference), the best
classical controller without V2V (IDM_cav: ``s0`` 7, ``v0`` 40, ``b`` 2), CACC (the ring's best setting,
:class:`~mixed_traffic.physics.CACCParams`, fed the head's acceleration of the last step) and the
``--experiment``'s classical base, which is the policy above 20 m/s (its learned residual is faded out there).

``--stops`` builds a head that stops and drives off instead, as stop_and_go's: from a standstill it drives off
``--depth`` times to one of ``--speeds``, holds it one of ``--holds`` seconds, brakes to a standstill and
stands one of ``--stop`` seconds, all at ``--rate``; the CAV starts stopped ``--gap`` behind. ``--rmse R`` adds the steady
speed bar: on each future's steady samples (the report's: the head's acceleration under 0.05 m/s^2 for the
settle time; a last hold counts for ``--holds[0]`` s, as the others) the mean |speed error| at most R (a
relaxation of the steady RMSE bar R, so still a bound), or with ``--rmse-norm linf`` every sample within R
(stricter than the bar: the optimum is then a causal controller that meets it, on these futures). Every
row also gives its steady RMSE.

``--own-cost RATIO`` adds the return: each future's own stage cost, the CAV's speed and gap terms of the
ring's reward (:class:`~mixed_traffic.evaluation.oracle.OwnCost`), at most RATIO times IDM-as-CAV's on the
same future, the CAV starting from IDM-as-CAV's settled gap (a relaxation by tangent lines, so still a bound).
Every row gives its own cost against IDM-as-CAV's (the futures' mean of the ratios; below 1: the CAV's part
of the return is higher), and its whole return against IDM-as-CAV's: the ring's reward summed over the counted
steps, with the two humans behind the CAV replayed by the env's car-following model behind its speeds.

The tree is small (``options ** depth`` futures, the options being ``--speeds`` and a hold when ``--p-hold``
> 0, of ``(depth + 1) epoch + tail`` seconds), so the bound is for this distribution and this horizon; a
controller that must keep room for the next step of a long episode may pay more. The program grows quickly
with the tree (35,000 steps in all solve in about 90 s). Writes ``OUT/causal_bound.json`` and
``OUT/causal_bound.md``::

    python benchmarks/ring_causal_bound.py --out outputs/results/causal_bound/random_timing_d3       # ~4 min
    python benchmarks/ring_causal_bound.py --relative --speeds -4 -1.333 1.333 4 --epoch 15 --p-hold 0 \
        --depth 2 --stop-gap 5 --out outputs/results/causal_bound/relative_d2_stop5                 # ~2 min
    python benchmarks/ring_causal_bound.py --stops --speeds 10 15 20 --depth 2 --gap 8 --stop-gap 5 \
        --rmse 0.2 --rmse-norm linf --out outputs/results/causal_bound/stops_d2_stop5_rmse_linf      # ~1 min
    python benchmarks/ring_causal_bound.py --depth 2 --stop-gap 5 --v0 20 --speeds 17.333 20 22.667 --own-cost 1 \
        --out outputs/results/causal_bound/rt20_d2_stop5_own1                                          # ~3 min
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# the classical controllers replayed beside the bound: name -> (model, parameters); CACC reads the head's acceleration
CLASSICAL = {"IDM-as-CAV": ("idm", {}), "IDM_cav (s0 7, v0 40, b 2)": ("idm", {"s0": 7.0, "v0": 40.0, "b": 2.0}),
             "CACC": ("cacc", {})}


def step_tree(*, speeds, v0: float, epoch: float, depth: int, p_hold: float, tail: float, dt: float,
              head_bounds: tuple[float, float], relative: bool = False, ramps: bool = False):
    """``(heads [L, N], weights [L], choices)``: the head's speeds after each step of every future, each
    future's probability, and its choice at each decision (None: hold).
    ``relative``: ``speeds`` are changes of the head's target speed, not target speeds. ``ramps``: they are
    accelerations (m/s^2) the head holds until the next decision (a hold keeps the last one), and it holds
    its speed after the last decision's epoch: smooth heads like a sine's, where steps are the other case."""
    import torch

    options = ([None] if p_hold > 0 else []) + list(speeds)  # a choice of probability 0 is no future
    share = ([p_hold] if p_hold > 0 else []) + [(1.0 - p_hold) / len(speeds)] * len(speeds)
    futures = list(itertools.product(range(len(options)), repeat=depth))
    n = int(round(((depth + 1) * epoch + tail) / dt))
    decide = {int(round((k + 1) * epoch / dt)): k for k in range(depth)}  # step index -> decision
    lo, hi = head_bounds
    heads = torch.zeros(len(futures), n, dtype=torch.float64)
    end = int(round((depth + 1) * epoch / dt))  # ramps: the head holds its speed from here on
    for i, future in enumerate(futures):
        v = target = v0
        accel = 0.0
        for t in range(n):
            k = decide.get(t + 1)  # the target of time (t + 1) dt drives step t, as in the env
            if k is not None and options[future[k]] is not None:
                if ramps:
                    accel = options[future[k]]
                else:
                    target = max(0.0, target + options[future[k]]) if relative else options[future[k]]
            if ramps:
                v = max(0.0, v + min(max(accel if t + 1 < end else 0.0, lo), hi) * dt)
            else:
                v = max(0.0, v + min(max((target - v) / dt, lo), hi) * dt)
            heads[i, t] = v
    weights = torch.tensor([[share[c] for c in f] for f in futures], dtype=torch.float64).prod(1)
    return heads, weights, [[options[c] for c in f] for f in futures]


def stop_tree(*, speeds, depth: int, rate: float, holds, stops, tail: float, dt: float):
    """``(heads [L, N], weights [L], choices)`` of a head that stops and drives off, as stop_and_go's: from a
    standstill it drives off ``depth`` times at ``rate`` (m/s^2) to one of ``speeds``, holds it one of ``holds``
    seconds, brakes at ``rate`` to a standstill and stands one of ``stops`` seconds (equal shares of each); the
    last drive-off holds its speed ``holds[0] + tail`` s instead. The CAV learns the speed the head drives off
    to only when the head stops accelerating short of the others, how long it holds only when it brakes, how
    long it stands only when it drives off. ``choices``: per future, ``(speed, seconds held, seconds
    stood)`` per drive-off (the last: ``(speed, seconds held)``)."""
    import torch

    options = list(itertools.product(*([float(x) for x in xs] for xs in (speeds, holds, stops))))
    last_options = [(v, float(holds[0]) + tail) for v in speeds]  # nothing follows the last hold: one length
    futures = [[*first, last] for first in itertools.product(options, repeat=depth - 1) for last in last_options]
    plans = []
    for future in futures:  # (target, seconds held after reaching it) per phase
        phases = []
        for v, held, *stood in future:
            phases += [(v, held)] + ([(0.0, stood[0])] if stood else [])
        plans.append(phases)

    def drive(phases) -> list[float]:
        v, out = 0.0, []
        for target, held in phases:
            while v != target:  # at +-rate, the last step onto the target exactly; rounded, so that heads
                # driving off to different speeds agree to the bit until the slower one stops (history_groups)
                v = target if abs(target - v) <= rate * dt + 1e-9 else round(v + math.copysign(rate * dt, target - v), 9)
                out.append(v)
            out += [v] * int(round(held / dt))
        return out

    runs = [drive(ph) for ph in plans]
    n = max(len(r) for r in runs)  # the shorter futures hold their last speed to the longest one's end
    heads = torch.tensor([r + [r[-1]] * (n - len(r)) for r in runs], dtype=torch.float64)
    weights = torch.full((len(futures),), 1.0 / len(futures), dtype=torch.float64)
    return heads, weights, futures


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--speeds", type=float, nargs="+", default=[21.333, 24.0, 26.667],
                   help="the speeds the head may step to (default: the centres of thirds of fast_steps' 20-28 m/s)")
    p.add_argument("--relative", action="store_true",
                   help="--speeds are changes of the head's target speed (e.g. -2.667 2.667): the head's next step is "
                        "as likely up as down wherever it drives, so its speed tells the CAV nothing of it")
    p.add_argument("--ramps", action="store_true",
                   help="--speeds are accelerations (e.g. -0.6 0 0.6 m/s^2) the head holds until its next decision: "
                        "smooth heads like sine_fast's (24 +- 4 m/s over 40 s: at most 0.63 m/s^2)")
    p.add_argument("--stops", action="store_true",
                   help="a head that stops and drives off (stop_and_go's): from a standstill it drives off --depth times "
                        "to one of --speeds (m/s), holds it one of --holds s, brakes to a standstill and stands one of --stop s, ramps "
                        "at --rate; --v0, --epoch and --p-hold do not apply (the CAV starts stopped, --gap behind)")
    p.add_argument("--rate", type=float, default=2.0, help="with --stops: the head's ramps (m/s^2; stop_and_go: 2)")
    p.add_argument("--holds", type=float, nargs="+", default=[10.0],
                   help="with --stops: how long the head may hold each speed (s, equal shares; stop_and_go: 10)")
    p.add_argument("--stop", type=float, nargs="+", default=[6.0],
                   help="with --stops: how long the head may stand at each stop (s, equal shares; stop_and_go: 6)")
    p.add_argument("--rmse", type=float, default=None, metavar="R",
                   help="the bound's and the clairvoyant CAV's mean |speed error| on each future's steady samples (the "
                        "report's: the head's acceleration under 0.05 m/s^2 for the settle time) at most R m/s, implied by "
                        "the steady-RMSE bar R (0.2), so the bound stays one for controllers that meet that bar too")
    p.add_argument("--rmse-norm", choices=("l1", "linf"), default="l1",
                   help="with --rmse: l1 (the mean |error|, the bound above) or linf (every steady sample within R m/s: "
                        "stricter than the RMSE bar, so the optimum is then a causal controller that meets it, not a bound)")
    p.add_argument("--own-cost", type=float, default=None, metavar="RATIO",
                   help="cap each future's own stage cost (the CAV's speed and gap terms of the return) at RATIO times "
                        "IDM-as-CAV's on it; the CAV then starts from IDM-as-CAV's settled gap, not --gap")
    p.add_argument("--v0", type=float, default=24.0, help="the head's and the CAV's speed at the start (m/s)")
    p.add_argument("--gap", type=float, default=22.5, help="the CAV's gap at the start (m)")
    p.add_argument("--epoch", type=float, default=5.0, help="seconds between the head's decisions")
    p.add_argument("--depth", type=int, default=3, help="the head's decisions")
    p.add_argument("--p-hold", type=float, default=2 / 3,
                   help="probability that the head keeps its target at a decision (2/3 with 5-s epochs: a step "
                        "every 15 s on average, as fast_steps)")
    p.add_argument("--tail", type=float, default=20.0, help="seconds after the last decision's epoch")
    p.add_argument("--stop-gap", type=float, default=None, metavar="G",
                   help="the bound's CAV must also keep the stopping-safe set of G m at every step (the rule of the "
                        "base's envelope and the safety layer, the head braking at its bound), as a controller that no "
                        "braking head can bring below G m must (the default's base: --stop-gap 5)")
    p.add_argument("--experiment", default="ring_lagrangian_ppo_wide_band", help="whose base is replayed")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="Hydra overrides of the replayed base")
    p.add_argument("--replay-only", action="store_true",
                   help="replay the controllers only (no programs): to set another --set base beside a bound already solved")
    p.add_argument("--time-limit", type=float, default=1800.0, help="HiGHS's limit (s)")
    p.add_argument("--plot", default=None, help="PNG: a few futures' head speed, the bound's speed, command and gap")
    p.add_argument("--plot-future", type=int, default=None, metavar="K",
                   help="with --plot: also PLOT_futureK.png, future K (its index in the JSON's choices) with the bound "
                        "beside IDM-as-CAV and the replayed base")
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    for name, ok, allowed in (("--depth", a.depth >= 1, ">= 1"), ("--epoch", a.epoch > 0, "> 0 (s)"),
                              ("--tail", a.tail >= 0, ">= 0 (s)"), ("--p-hold", 0 <= a.p_hold < 1, "in [0, 1)"),
                              ("--v0", a.v0 >= 0, ">= 0 (m/s)"),
                              ("--speeds", a.relative or a.ramps or min(a.speeds) >= 0, ">= 0 (m/s)"),
                              ("--stop-gap", a.stop_gap is None or a.stop_gap >= 0, ">= 0 (m)"),
                              ("--rate", a.rate > 0, "> 0 (m/s^2)"), ("--holds", min(a.holds) >= 0, ">= 0 (s)"),
                              ("--stop", min(a.stop) >= 0, ">= 0 (s)"), ("--rmse", a.rmse is None or a.rmse > 0, "> 0 (m/s)"),
                              ("--own-cost", a.own_cost is None or a.own_cost > 0, "> 0"),
                              ("--time-limit", a.time_limit > 0, "> 0 (s)")):
        if not ok:
            raise SystemExit(f"{name} is invalid; allowed: {allowed}")
    if a.relative + a.ramps + a.stops > 1:
        raise SystemExit("--relative, --ramps and --stops: give one of them")
    if a.stops and min(a.speeds) <= 0:
        raise SystemExit(f"--speeds {a.speeds} is invalid with --stops; allowed: speeds > 0 (m/s) to drive off to")
    if a.stops:
        a.v0 = 0.0

    import torch

    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.evaluation.harness import Trace, eval_scenario, steady_samples
    from mixed_traffic.evaluation.oracle import OwnCost, causal_least_jerk, least_jerk
    from mixed_traffic.evaluation.replay import replay
    from mixed_traffic.training.builders import residual_base
    from mixed_traffic.validation import validate_config

    torch.set_num_threads(1)
    cfg = validate_config(compose([f"experiment={a.experiment}", *a.set]))
    sc = eval_scenario(cfg, cfg.eval.profiles[0])
    dt, s_min, s_max = sc.dt, float(cfg.eval.s_min), float(cfg.eval.s_max)
    if not s_min <= a.gap <= s_max:
        raise SystemExit(f"--gap = {a.gap} is invalid; allowed: in the band [{s_min}, {s_max}] m")
    if a.stops:
        heads, w, choices = stop_tree(speeds=a.speeds, depth=a.depth, rate=a.rate, holds=a.holds, stops=a.stop,
                                      tail=a.tail, dt=dt)
    else:
        heads, w, choices = step_tree(speeds=a.speeds, v0=a.v0, epoch=a.epoch, depth=a.depth, p_hold=a.p_hold,
                                      tail=a.tail, dt=dt, head_bounds=tuple(sc.head_accel_bounds),
                                      relative=a.relative, ramps=a.ramps)
    L, N = heads.shape
    if a.plot_future is not None and not (a.plot and 0 <= a.plot_future < L):
        raise SystemExit(f"--plot-future = {a.plot_future} is invalid; allowed: with --plot, a future's index in "
                         f"[0, {L - 1}]")
    # each future's steady samples, as the report counts them (from the head's speed before the first step: v0)
    head_accel = torch.cat([heads.new_full((L, 1), a.v0), heads], 1).diff(dim=1) / dt
    steady = steady_samples(head_accel, torch.ones(L, N, dtype=torch.bool), int(round(cfg.eval.settle_seconds / dt)))
    if a.stops:  # the last hold counts as long as the others (--holds[0] s), not through the tail that lets it settle
        step = torch.arange(N)
        reached = torch.where(head_accel != 0, step, torch.zeros_like(step)).max(1).values + 1
        steady &= step[None] < (reached + int(round(a.holds[0] / dt)))[:, None]
    bar = {} if a.rmse is None else {"steady": steady, "rmse": a.rmse, "norm": a.rmse_norm}

    def steady_rmse(speed: torch.Tensor) -> torch.Tensor:
        """Per future: the RMSE of the speed against the head's on its steady samples (nan: none)."""
        return (((speed - heads) ** 2 * steady).sum(1) / steady.sum(1)).sqrt()
    kw = dict(v_start=a.v0, gap_start=a.gap, dt=dt, warmup=0.0, s_min=s_min, s_max=s_max,
              accel_bounds=tuple(sc.cav_accel_bounds), a_prev=0.0)
    if a.stop_gap is not None:
        kw.update(stop_gap=a.stop_gap, leader_brake=-float(sc.head_accel_bounds[0]))

    def weighted(x: torch.Tensor, weights: torch.Tensor) -> float:
        """The futures' weighted mean of ``x``, over those where it is defined (nan when none)."""
        ok = ~x.isnan()
        return float((x[ok] * weights[ok]).sum() / weights[ok].sum()) if bool(ok.any()) else float("nan")

    def mean_jerk(accel: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
        """Per future: mean |a_t - a_{t-1}| / dt over the N counted steps (the command before them: ``before``)."""
        return torch.cat([before[:, None], accel], 1).diff(dim=1).abs().sum(1) / (N * dt)

    P = int(round(60.0 / dt))  # the replayed controllers settle behind the head at v0 first
    hp = torch.cat([heads.new_full((L, P), a.v0), heads], 1)
    zero = torch.zeros(L, hp.shape[1])
    trace = Trace(time=(torch.arange(hp.shape[1]) + 1).expand(L, -1) * dt, head_speed=hp.float(),
                  cav_speed=zero + a.v0, cav_accel=zero, head_accel=torch.cat([zero[:, :1], hp.diff(dim=1).float() / dt], 1),
                  gap=zero + a.gap, head_gap=zero + a.gap, valid=torch.ones_like(zero, dtype=torch.bool), raw_accel=zero)
    # the env's v_eq after each counted step: the head's mean over the last v_eq_window seconds (the prefix at v0)
    W = max(1, int(round(sc.v_eq_window / dt)))
    csum = torch.cat([hp.new_zeros(L, 1), hp.cumsum(1)], 1)
    idx = torch.arange(P, hp.shape[1])
    v_eq = (csum[:, idx + 1] - csum[:, (idx + 1 - W).clamp_min(0)]) / (idx + 1).clamp_max(W)

    def own_cap(i: int, budget: float) -> OwnCost:
        return OwnCost(v_eq=v_eq[i], budget=budget, weight_v=sc.weight_v, weight_s=sc.weight_s, s_star=sc.s_star)

    def own(speed: torch.Tensor, gap: torch.Tensor) -> torch.Tensor:
        """Per future: the CAV's own stage cost (speed and gap terms) over the counted steps."""
        return torch.stack([own_cap(i, 1.0).of(speed[i], gap[i]) for i in range(L)])

    def full_return(speed: torch.Tensor, accel: torch.Tensor, gap: torch.Tensor) -> torch.Tensor:
        return return_with_humans(sc, heads, v_eq, speed, accel, gap, v0=a.v0)

    env = make_env("ring", batch_size=1, seed=0)
    laws = {name: make_classic_policy(model, env, **over).module.double() for name, (model, over) in CLASSICAL.items()}
    laws[f"{a.experiment}'s base{' (' + ' '.join(a.set) + ')' if a.set else ''}"] = \
        residual_base(cfg.transforms.residual, env).module.double()
    lo, hi = sc.cav_accel_bounds
    driven, replayed = {}, {}  # name -> (speed, command, gap) after the prefix; its row
    for name, law in laws.items():
        m = replay(law, trace, dt=dt, low=lo, high=hi, warmup=0.0, settle=float(cfg.eval.settle_seconds))
        speed, accel, gap = driven[name] = (m["speed"][:, P:], m["accel"][:, P:], m["gap"][:, P:])
        per, per_rmse = mean_jerk(accel, m["accel"][:, P - 1]), steady_rmse(speed)
        replayed[name] = {"jerk": float((per * w).sum()), "per_future": per,
                          "gaps": (float(gap.min()), float(gap.max())), "collisions": int((gap <= 0).any(1).sum()),
                          "rmse": weighted(per_rmse, w), "rmse_per_future": per_rmse,
                          "own_cost_per_future": own(speed, gap), "return_per_future": full_return(speed, accel, gap)}
    caps = None
    if a.own_cost is not None:  # the reference's own cost per future, and the bound from the reference's start
        ref_cost = replayed["IDM-as-CAV"]["own_cost_per_future"]
        caps = [own_cap(i, a.own_cost * float(ref_cost[i])) for i in range(L)]
        settled = driven["IDM-as-CAV"][2][:, 0] - dt * (heads[:, 0] - driven["IDM-as-CAV"][0][:, 0])
        kw["gap_start"] = float(settled[0])
        print(f"own cost capped at {a.own_cost:g} x IDM-as-CAV's; the bound starts from its settled gap "
              f"{kw['gap_start']:.2f} m", flush=True)
    t0 = time.perf_counter()
    stop_excess = None
    if not a.replay_only:
        print(f"{L} head futures of {N * dt:.0f} s ({L * N} steps): solving ...", flush=True)
        bound = causal_least_jerk(heads, weights=w, end_speeds=heads[:, -1], time_limit=a.time_limit,
                                  own_costs=caps, **bar, **kw)
    solve_s = time.perf_counter() - t0

    rows = {}
    if not a.replay_only:
        clair = [least_jerk(h, end_speed=float(h[-1]), **({} if a.rmse is None else {**bar, "steady": steady[i]}),
                            own_cost=None if caps is None else caps[i], **kw) for i, h in enumerate(heads)]
        if a.stop_gap is not None:  # the program keeps the stopping rule as linear pieces near the head's speed:
            # check the optimum against the rule itself (safe_accel_upper), from the second step on
            from transforms.safety_layer import safe_accel_upper

            cap = safe_accel_upper(bound.gap[:, :-1], bound.speed[:, :-1], heads[:, :-1], s_min=a.stop_gap, dt=dt,
                                   brake=-float(sc.cav_accel_bounds[0]), leader_brake=kw["leader_brake"])
            stop_excess = float((bound.accel[:, 1:] - cap).max())
        bound_rmse = steady_rmse(bound.speed)
        c_speed, c_accel, c_gap = (torch.stack([getattr(c, k) for c in clair]) for k in ("speed", "accel", "gap"))
        rows = {"causal bound": {"jerk": bound.jerk, "per_future": bound.per_head,
                                 "gaps": (float(bound.gap.min()), float(bound.gap.max())),
                                 "rmse": weighted(bound_rmse, w), "rmse_per_future": bound_rmse,
                                 "own_cost_per_future": own(bound.speed, bound.gap),
                                 "return_per_future": full_return(bound.speed, bound.accel, bound.gap)},
                "clairvoyant": {"jerk": float((mean_jerk(c_accel, torch.zeros(L)) * w).sum()),
                                "rmse": weighted(steady_rmse(c_speed), w),
                                "own_cost_per_future": own(c_speed, c_gap),
                                "return_per_future": full_return(c_speed, c_accel, c_gap)}}
    rows.update(replayed)
    own_note = ("" if a.own_cost is None else
                f", own cost <= {a.own_cost:g} x IDM-as-CAV's (from its settled gap, {kw['gap_start']:.2f} m)")
    ref = rows["IDM-as-CAV"]["jerk"]
    ref_own = rows["IDM-as-CAV"]["own_cost_per_future"]
    for r in rows.values():  # the own cost against IDM-as-CAV's, the futures' weighted mean of the ratios
        r["own_cost"] = float((r["own_cost_per_future"] / ref_own * w).sum())
        r["return"] = float(((r["return_per_future"] - rows["IDM-as-CAV"]["return_per_future"]) * w).sum())
    checked = ("" if stop_excess is None else
               f" (the bound's largest command above the rule's own cap: {stop_excess:.1e} m/s^2)")
    if a.stops:
        head = (f"from a standstill the head drives off {a.depth} time{'s' if a.depth > 1 else ''} at {a.rate} m/s^2 to one of {a.speeds} m/s, "
                f"holds it {' or '.join(f'{h:g}' for h in a.holds)} s and stands {' or '.join(f'{x:g}' for x in a.stop)} s")
    else:
        head = (f"the head at {a.v0} m/s decides {a.depth} times, every {a.epoch} s, to keep "
                f"its {'acceleration' if a.ramps else 'target'} (p = {a.p_hold:.3f}) or "
                f"{'ramp at' if a.ramps else 'step by' if a.relative else 'step to'} one of {a.speeds} "
                f"{'m/s^2' if a.ramps else 'm/s'}")
    lines = [f"{L} futures of {N * dt:.0f} s: {head}; band [{s_min}, {s_max}] m"
             f"{'' if a.stop_gap is None else f', stopping-safe at {a.stop_gap:g} m'}"
             f"{checked}"
             f"{'' if a.rmse is None else f', speed error on steady samples ({a.rmse_norm}) <= {a.rmse:g} m/s'}"
             f"{own_note}; "
             + ("controllers replayed only" if a.replay_only else f"solved in {solve_s:.0f} s ({bound.status})"), "",
             "| controller | mean |jerk| (m/s^3) | − IDM-as-CAV's | gaps (m) | steady RMSE (m/s) | own cost / IDM-as-CAV's "
             "| return − IDM-as-CAV's (humans replayed) |", "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        g = r.get("gaps")
        lines.append(f"| {name} | {r['jerk']:.4f} | {100 * (r['jerk'] / ref - 1):+.1f} % | "
                     f"{'' if g is None else f'{g[0]:.2f}–{g[1]:.2f}'} | {r['rmse']:.3f} | {r['own_cost']:.3f} | {r['return']:+.2f} |")
    md = "\n".join(lines)
    print(md)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "causal_bound.md").write_text(md + "\n")
    result = {"args": vars(a), "solve_s": solve_s, "status": None if a.replay_only else bound.status,
              "stop_rule_excess": stop_excess, "choices": choices,
              "weights": w.tolist(), "rows": {k: {kk: (vv.tolist() if isinstance(vv, torch.Tensor) else vv)
                                                  for kk, vv in r.items()} for k, r in rows.items()}}
    (out / "causal_bound.json").write_text(json.dumps(result, indent=1))
    if a.plot and not a.replay_only:
        title = ("the least-jerk causal CAV on a tree of head futures"
                 + ("" if a.stop_gap is None else f", stopping-safe at {a.stop_gap:g} m")
                 + ("" if a.rmse is None else f", steady speed error ({a.rmse_norm}) <= {a.rmse:g} m/s"))
        plot(a.plot, heads, bound, choices, dt, title)
        if a.plot_future is not None:
            k = a.plot_future
            base_name = list(laws)[-1]
            plot_future(str(Path(a.plot).with_suffix("")) + f"_future{k}.png", heads[k], dt,
                        {"causal bound": (bound.speed[k], bound.accel[k], bound.gap[k]),
                         "IDM-as-CAV": tuple(x[k] for x in driven["IDM-as-CAV"]),
                         "the base": tuple(x[k] for x in driven[base_name])},
                        steady[k], f"future {k}: " + " → ".join(map(choice_label, choices[k])))
    return result


def return_with_humans(sc, heads, v_eq, speed, accel, gap, *, v0: float):
    """Per future (``[L]``): the return of the ring's reward over the steps of ``speed``, ``accel`` and ``gap``
    (``[L, N]``: the CAV's speed and executed command after each step, its gap to the head), behind ``heads``
    (``[L, N]``) with ``v_eq`` (``[L, N]``): ``NonNegativeReward`` over the env's stage cost
    (:func:`~mixed_traffic.envs.traffic.stage_terms`). The humans behind the CAV are replayed by the env's
    car-following model (``sc.hdv_model``, ``sc.hdv_defaults()``) behind the CAV's speeds, each starting steady
    at ``v0`` at the model's equilibrium gap (``sc.equilibrium_gap``), under the env's ``"euler"`` update, as the
    env would drive them."""
    import torch

    from mixed_traffic.envs.traffic import stage_terms
    from mixed_traffic.physics import car_following_accel

    n, cav = sc.n_vehicles, list(sc.cav_indices)
    if cav != [1]:
        raise SystemExit(f"the return with the humans needs one CAV right behind the head, got {cav}")
    params = dataclasses.asdict(sc.hdv_defaults())
    L, N = speed.shape
    dt, f64 = sc.dt, torch.float64
    s_eq = sc.equilibrium_gap(float(v0))
    speed, accel, gap, heads, v_eq = (t.to(f64) for t in (speed, accel, gap, heads, v_eq))
    x_cav = torch.cumsum(speed * dt, 1)  # the CAV's position after each step (0 before the first)
    x = torch.stack([torch.full((L,), -k * (s_eq + sc.vehicle_length), dtype=f64) for k in range(1, n - 1)], 1)
    v = torch.full((L, n - 2), float(v0), dtype=f64)
    ret = torch.zeros(L, dtype=f64)
    lead_x, lead_v = torch.zeros(L, dtype=f64), torch.full((L,), float(v0), dtype=f64)
    for t in range(N):
        ahead_x = torch.cat([lead_x[:, None], x[:, :-1]], 1)
        ahead_v = torch.cat([lead_v[:, None], v[:, :-1]], 1)
        v = (v + car_following_accel(sc.hdv_model, ahead_x - x - sc.vehicle_length, v, ahead_v, params) * dt).clamp_min(0.0)
        x = x + v * dt
        lead_x, lead_v = x_cav[:, t], speed[:, t]
        all_speed = torch.cat([heads[:, t, None], speed[:, t, None], v], 1)
        all_gap = torch.cat([gap[:, t, None], gap[:, t, None],
                             torch.cat([lead_x[:, None], x[:, :-1]], 1) - x - sc.vehicle_length], 1)
        j, _ = stage_terms(sc, all_speed, all_gap, accel[:, t, None], v_eq[:, t, None])
        ret += (sc.J_max - j[:, 0]).clamp_min(0.0) / sc.J_max
    return ret


def choice_label(choice) -> str:
    """A head's decision as the plot's legend names it: a hold, a value, or (--stops) a speed, how long held and
    how long stood after it."""
    if choice is None:
        return "hold"
    if not isinstance(choice, (tuple, list)):
        return f"{choice:g}"
    return f"{choice[0]:g} m/s {choice[1]:g} s" + (f", stands {choice[2]:g} s" if len(choice) > 2 else "")


def plot_future(path: str, head, dt: float, drivers: dict, steady, title: str) -> None:
    """One future: the head's and each driver's speed (the steady samples shaded), command and gap."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    t = (torch.arange(head.shape[0]) + 1) * dt
    fig, ax = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    ax[0].fill_between(t, 0, float(head.max()) * 1.1, where=steady.bool(), color="0.9", step="mid",
                       label="steady samples")
    ax[0].plot(t, head, "k--", lw=0.9, label="head")
    for name, (speed, accel, gap) in drivers.items():
        line, = ax[0].plot(t, speed, lw=1.2, label=name)
        ax[1].plot(t, accel, lw=1.0, color=line.get_color())
        ax[2].plot(t, gap, lw=1.0, color=line.get_color())
    ax[0].set_ylabel("speed (m/s)")
    ax[1].set_ylabel("command (m/s²)")
    ax[2].set_ylabel("gap (m)")
    ax[2].set_xlabel("time (s)")
    ax[0].legend(fontsize=7)
    ax[0].set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot(path: str, heads, bound, choices, dt: float, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    t = (torch.arange(heads.shape[1]) + 1) * dt
    # per first choice, the futures that then keep choosing the first and the last option (up to 8 in all)
    pick = []
    for first in dict.fromkeys(c[0] for c in choices):
        group = [i for i, c in enumerate(choices) if c[0] == first]
        pick += [i for i in dict.fromkeys((group[0], group[-1])) if len(pick) < 8]
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i in pick:
        line, = ax[0].plot(t, heads[i], "--", lw=0.8)
        ax[0].plot(t, bound.speed[i], lw=1.3, color=line.get_color())
        ax[1].plot(t, bound.accel[i], color=line.get_color())
        ax[2].plot(t, bound.gap[i], color=line.get_color(), label=" → ".join(map(choice_label, choices[i])))
    ax[0].set_ylabel("speed (m/s)\nhead dashed")
    ax[1].set_ylabel("command (m/s²)")
    ax[2].set_ylabel("gap (m)")
    ax[2].set_xlabel("time (s)")
    ax[2].legend(fontsize=7, title="the head's decisions", title_fontsize=7)
    ax[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
