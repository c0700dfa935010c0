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
classical controller (IDM_cav: ``s0`` 7, ``v0`` 40, ``b`` 2) and the ``--experiment``'s classical base, which
is the policy above 20 m/s (its learned residual is faded out there).

The tree is small (``options ** depth`` futures, the options being ``--speeds`` and a hold when ``--p-hold``
> 0, of ``(depth + 1) epoch + tail`` seconds), so the bound is for this distribution and this horizon; a
controller that must keep room for the next step of a long episode may pay more. The program grows quickly
with the tree (35,000 steps in all solve in about 90 s). Writes ``OUT/causal_bound.json`` and
``OUT/causal_bound.md``::

    python benchmarks/ring_causal_bound.py --out outputs/results/causal_bound/random_timing_d3       # ~4 min
    python benchmarks/ring_causal_bound.py --relative --speeds -4 -1.333 1.333 4 --epoch 15 --p-hold 0 \
        --depth 2 --stop-gap 5 --out outputs/results/causal_bound/relative_d2_stop5                 # ~2 min
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

CLASSICAL = {"IDM-as-CAV": {}, "IDM_cav (s0 7, v0 40, b 2)": {"s0": 7.0, "v0": 40.0, "b": 2.0}}


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
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)
    for name, ok, allowed in (("--depth", a.depth >= 1, ">= 1"), ("--epoch", a.epoch > 0, "> 0 (s)"),
                              ("--tail", a.tail >= 0, ">= 0 (s)"), ("--p-hold", 0 <= a.p_hold < 1, "in [0, 1)"),
                              ("--v0", a.v0 >= 0, ">= 0 (m/s)"),
                              ("--speeds", a.relative or a.ramps or min(a.speeds) >= 0, ">= 0 (m/s)"),
                              ("--stop-gap", a.stop_gap is None or a.stop_gap >= 0, ">= 0 (m)"),
                              ("--time-limit", a.time_limit > 0, "> 0 (s)")):
        if not ok:
            raise SystemExit(f"{name} is invalid; allowed: {allowed}")
    if a.relative and a.ramps:
        raise SystemExit("--relative and --ramps: give one of them")

    import torch

    from mixed_traffic import make_env
    from mixed_traffic.config import compose
    from mixed_traffic.controllers.classic import make_classic_policy
    from mixed_traffic.evaluation.harness import Trace, eval_scenario
    from mixed_traffic.evaluation.oracle import causal_least_jerk, least_jerk
    from mixed_traffic.evaluation.replay import replay
    from mixed_traffic.training.builders import residual_base
    from mixed_traffic.validation import validate_config

    torch.set_num_threads(1)
    cfg = validate_config(compose([f"experiment={a.experiment}", *a.set]))
    sc = eval_scenario(cfg, cfg.eval.profiles[0])
    dt, s_min, s_max = sc.dt, float(cfg.eval.s_min), float(cfg.eval.s_max)
    if not s_min <= a.gap <= s_max:
        raise SystemExit(f"--gap = {a.gap} is invalid; allowed: in the band [{s_min}, {s_max}] m")
    tree = dict(speeds=a.speeds, v0=a.v0, epoch=a.epoch, depth=a.depth, p_hold=a.p_hold, tail=a.tail, dt=dt,
                head_bounds=tuple(sc.head_accel_bounds), relative=a.relative, ramps=a.ramps)
    heads, w, choices = step_tree(**tree)
    L, N = heads.shape
    kw = dict(v_start=a.v0, gap_start=a.gap, dt=dt, warmup=0.0, s_min=s_min, s_max=s_max,
              accel_bounds=tuple(sc.cav_accel_bounds), a_prev=0.0)
    if a.stop_gap is not None:
        kw.update(stop_gap=a.stop_gap, leader_brake=-float(sc.head_accel_bounds[0]))
    t0 = time.perf_counter()
    if not a.replay_only:
        print(f"{L} head futures of {N * dt:.0f} s ({L * N} steps): solving ...", flush=True)
        bound = causal_least_jerk(heads, weights=w, end_speeds=heads[:, -1], time_limit=a.time_limit, **kw)
    solve_s = time.perf_counter() - t0

    def mean_jerk(accel: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
        """Per future: mean |a_t - a_{t-1}| / dt over the N counted steps (the command before them: ``before``)."""
        return torch.cat([before[:, None], accel], 1).diff(dim=1).abs().sum(1) / (N * dt)

    rows = {}
    if not a.replay_only:
        clair = torch.stack([least_jerk(h, end_speed=float(h[-1]), **kw).accel for h in heads])
        rows = {"causal bound": {"jerk": bound.jerk, "per_future": bound.per_head,
                                 "gaps": (float(bound.gap.min()), float(bound.gap.max()))},
                "clairvoyant": {"jerk": float((mean_jerk(clair, torch.zeros(L)) * w).sum())}}
    P = int(round(60.0 / dt))  # the replayed controllers settle behind the head at v0 first
    hp = torch.cat([heads.new_full((L, P), a.v0), heads], 1)
    zero = torch.zeros(L, hp.shape[1])
    trace = Trace(time=(torch.arange(hp.shape[1]) + 1).expand(L, -1) * dt, head_speed=hp.float(),
                  cav_speed=zero + a.v0, cav_accel=zero, head_accel=torch.cat([zero[:, :1], hp.diff(dim=1).float() / dt], 1),
                  gap=zero + a.gap, head_gap=zero + a.gap, valid=torch.ones_like(zero, dtype=torch.bool), raw_accel=zero)
    env = make_env("ring", batch_size=1, seed=0)
    laws = {name: make_classic_policy("idm", env, **over).module.double() for name, over in CLASSICAL.items()}
    laws[f"{a.experiment}'s base{' (' + ' '.join(a.set) + ')' if a.set else ''}"] = \
        residual_base(cfg.transforms.residual, env).module.double()
    lo, hi = sc.cav_accel_bounds
    for name, law in laws.items():
        m = replay(law, trace, dt=dt, low=lo, high=hi, warmup=0.0, settle=float(cfg.eval.settle_seconds))
        per = mean_jerk(m["accel"][:, P:], m["accel"][:, P - 1])
        gap = m["gap"][:, P:]
        rows[name] = {"jerk": float((per * w).sum()), "per_future": per, "gaps": (float(gap.min()), float(gap.max())),
                      "collisions": int((gap <= 0).any(1).sum())}
    ref = rows["IDM-as-CAV"]["jerk"]
    lines = [f"{L} futures of {N * dt:.0f} s: the head at {a.v0} m/s decides {a.depth} times, every {a.epoch} s, to keep "
             f"its {'acceleration' if a.ramps else 'target'} (p = {a.p_hold:.3f}) or "
             f"{'ramp at' if a.ramps else 'step by' if a.relative else 'step to'} one of {a.speeds} "
             f"{'m/s^2' if a.ramps else 'm/s'}; "
             f"band [{s_min}, {s_max}] m{'' if a.stop_gap is None else f', stopping-safe at {a.stop_gap:g} m'}; "
             + ("controllers replayed only" if a.replay_only else f"solved in {solve_s:.0f} s ({bound.status})"), "",
             "| controller | mean |jerk| (m/s^3) | − IDM-as-CAV's | gaps (m) |", "|---|---|---|---|"]
    for name, r in rows.items():
        g = r.get("gaps")
        lines.append(f"| {name} | {r['jerk']:.4f} | {100 * (r['jerk'] / ref - 1):+.1f} % | "
                     f"{'' if g is None else f'{g[0]:.2f}–{g[1]:.2f}'} |")
    md = "\n".join(lines)
    print(md)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "causal_bound.md").write_text(md + "\n")
    result = {"args": vars(a), "solve_s": solve_s, "status": None if a.replay_only else bound.status, "choices": choices,
              "weights": w.tolist(), "rows": {k: {kk: (vv.tolist() if isinstance(vv, torch.Tensor) else vv)
                                                  for kk, vv in r.items()} for k, r in rows.items()}}
    (out / "causal_bound.json").write_text(json.dumps(result, indent=1))
    if a.plot and not a.replay_only:
        plot(a.plot, heads, bound, choices, dt, "the least-jerk causal CAV on a tree of head futures"
             + ("" if a.stop_gap is None else f", stopping-safe at {a.stop_gap:g} m"))
    return result


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
        ax[2].plot(t, bound.gap[i], color=line.get_color(), label=" → ".join("hold" if x is None else f"{x:g}" for x in choices[i]))
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
