"""One episode of a ring case, step by step: what the residual's base commands and why, and what is executed.

Where a scorecard says a policy lost a case by a spike in its command, this shows the step it happened on and which
part of the deployed controller made it: per step the CAV's gap, speed, its leader's speed and acceleration, the
base's law inside the stopping envelope (``law``), the envelope's bound (``bound``, ``StoppingEnvelope.bound``), its
arrival term where it is on (``arrival``, ``StoppingEnvelope.arrival``; ``transforms.residual.arrive_gain``), the
base's command (``base``), the policy's raw residual (``residual``, before its weight and fades) and the executed
acceleration (``executed``). The run's deployed chain without the safety layer, as the scorecard's layer-free rows::

    python benchmarks/ring_trace.py --checkpoint outputs/results/arrive_seed0 --case brake_to_standstill \\
        --seed 3000 --seconds 80 --window 54.8 56.6
    python benchmarks/ring_trace.py --experiment ring_lagrangian_ppo_gentle --case brake_from_15_late \\
        --seed 13000 --seconds 120 --window 104 108 --set transforms.residual.arrive_gain=null

``--experiment`` traces an experiment's deployed controller with its learned residual at zero, before anything is
trained. ``--set`` changes the run's transforms at deploy time (as in ``ring_generalization.py``). Prints the table
and, with ``--out``, writes it as CSV.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

COLUMNS = ("time", "gap", "speed", "leader_speed", "leader_accel", "law", "bound", "arrival", "base", "residual",
           "executed")


def trace(env, policy, *, episode: int, window: tuple[float, float]) -> list[dict]:
    """Step ``env`` (a deployed ring chain with a ``ResidualAction`` whose base sits inside a stopping envelope) under
    ``policy`` for its whole episode; the rows of :data:`COLUMNS` of row ``episode`` within ``window`` (s)."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mixed_traffic.training.plain_actor import deterministic_action
    from transforms import ResidualAction

    residual = next((t for t in env.transform.transforms if isinstance(t, ResidualAction)), None)
    envelope = getattr(getattr(residual, "base", None), "module", None)
    envelope = getattr(envelope, "envelope", envelope)
    if residual is None or not hasattr(envelope, "bound"):
        raise ValueError("the run's chain has no residual over a base inside a stopping envelope "
                         "(transforms.residual_idm with transforms.residual.stop_gap)")
    act, sc, rows = deterministic_action(policy), env.base_env.scenario, []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        for i in range(sc.max_steps):
            td = act(td)
            gap, v, vl = (td["cav", k][episode].reshape(-1)[:1] for k in ("gap", "speed", "leader_speed"))
            la = td.get(("cav", "leader_accel"), None)
            extra = () if la is None or not envelope.reads_leader_accel else (la[episode].reshape(-1)[:1],)
            law = envelope.law(gap, v, vl, *extra)
            arrival = envelope.arrival(gap, v, vl) if getattr(envelope, "arrive_gain", None) is not None else None
            bound = envelope.bound(gap, v, vl)
            out, td = env.step_and_maybe_reset(td) if i < sc.max_steps - 1 else (env.step(td), None)
            t = round(i * sc.dt, 6)
            if window[0] - 1e-9 <= t <= window[1] + 1e-9:
                nxt = out["next"]
                rows.append({"time": t, "gap": float(gap), "speed": float(v), "leader_speed": float(vl),
                             "leader_accel": math.nan if la is None else float(la[episode].reshape(-1)[0]),
                             "law": float(law), "bound": float(bound),
                             "arrival": math.nan if arrival is None else float(arrival),
                             "base": float(nxt["residual", "base_action"][episode].reshape(-1)[0]),
                             "residual": float(out["action"][episode].reshape(-1)[0]),
                             "executed": float(nxt["cav", "accel"][episode].reshape(-1)[0])})
            if td is None:
                break
    return rows


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="final.pt or a run directory")
    src.add_argument("--experiment", help="an experiment's deployed controller, its learned residual at zero")
    p.add_argument("--case", required=True, help="a case of ring_generalization.py (e.g. brake_to_standstill)")
    p.add_argument("--seed", type=int, default=3000, help="evaluation seed (default 3000, the tuning seed)")
    p.add_argument("--episodes", type=int, default=4, help="episodes drawn, as the screen draws them (default 4)")
    p.add_argument("--episode", type=int, default=0, help="the episode traced (default 0)")
    p.add_argument("--seconds", type=float, default=200.0)
    p.add_argument("--window", type=float, nargs=2, default=(0.0, math.inf), metavar=("T0", "T1"),
                   help="the seconds printed (default: the whole episode)")
    p.add_argument("--set", nargs="+", default=[], metavar="transforms.KEY=VALUE",
                   help="deploy-time settings of the run's transforms (as ring_generalization.py --set)")
    p.add_argument("--out", default=None, help="also write the rows to this CSV file")
    a = p.parse_args(argv)
    import ring_generalization as gen

    all_cases = gen.cases(a.seconds)
    if a.case not in all_cases:
        raise SystemExit(f"--case: {a.case!r} is not a case; allowed: {sorted(all_cases)}")
    if not 0 <= a.episode < a.episodes:
        raise SystemExit(f"--episode: {a.episode} is invalid; allowed: 0..{a.episodes - 1} (--episodes {a.episodes})")
    if not a.window[0] <= a.window[1]:
        raise SystemExit(f"--window: {list(a.window)} is invalid; allowed: T0 <= T1 (s)")

    import torch

    from mixed_traffic.config import compose
    from mixed_traffic.evaluation.harness import profile_env
    from mixed_traffic.evaluation.policies import checkpoint_config, policy_factory_from_state, zero_residual_factory

    torch.set_num_threads(1)
    if a.checkpoint is not None:
        run_cfg, state = checkpoint_config(a.checkpoint)
    else:
        run_cfg, state = compose([f"experiment={a.experiment}"]), None
    if a.set:
        run_cfg = gen.apply_set(run_cfg, gen.parse_set(a.set))  # a bad item exits naming it
    case = all_cases[a.case]
    cfg = gen.case_config(run_cfg, case, episodes=a.episodes, seconds=a.seconds, seed=a.seed)
    env = profile_env(cfg, case["profile"], episodes=a.episodes, seed=a.seed, without=("safety_layer",))
    try:
        factory = zero_residual_factory(run_cfg) if state is None else policy_factory_from_state(run_cfg, state)
        policy = factory(env)
        torch.manual_seed(a.seed)  # as the evaluation harness does before its rollout
        rows = trace(env, policy, episode=a.episode, window=tuple(a.window))
    except ValueError as e:
        raise SystemExit(f"{a.checkpoint or a.experiment}: {e}") from None
    print(" ".join(f"{c:>12}" for c in COLUMNS))
    for r in rows:
        print(" ".join(f"{r[c]:12.3f}" for c in COLUMNS))
    if a.out is not None:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        with open(a.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
    return rows


if __name__ == "__main__":
    main()
