"""Where the ring's extra return over IDM comes from, and what it costs in safety-layer work.

The ring's stage cost charges every follower's speed error against ``v_eq``, the head's
speed averaged over 20 s, not against the head's current speed. A CAV that follows the
lagging average instead of its leader earns more return than IDM, but its gap then swings
with the head's changes. This script measures that trade-off with a one-parameter family
of classical controllers,

    a = clip(IDM(gap, v, v_leader) + k (v_eq - v), -3, 3),

``k = 0`` being IDM itself, run behind the safety layer of ``experiment=ring_lagrangian_ppo``
(return, intervention rate, jerk) and without it from the standard start (collisions,
min gap after the warm-up, max head gap), on the four evaluation profiles and the
training profile ``random_ramps``, same episodes for every ``k``. A learned residual over
IDM can only earn what this frontier offers within the layer's budget.

    python benchmarks/ring_return_frontier.py --gains 0 0.3 0.6 --episodes 8 \\
        --out outputs/results/ring_return_frontier
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

PROFILES = ("random_steps", "emergency_brake", "eudc", "sine", "random_ramps")


def make_factory(gain: float):
    from tensordict.nn import TensorDictModule
    from torch import nn

    from mixed_traffic.controllers.classic import CarFollowingCAV, action_bounds
    from mixed_traffic.physics import IDMParams

    class IDMTrackingAverage(nn.Module):
        """IDM plus ``gain`` times the CAV's speed error against the averaged head speed."""

        def __init__(self, low: float, high: float):
            super().__init__()
            self.idm = CarFollowingCAV("idm", IDMParams(), low, high)
            self.low, self.high = low, high

        def forward(self, gap, speed, leader_speed, v_eq):
            return (self.idm(gap, speed, leader_speed) + gain * (v_eq - speed)).clamp(self.low, self.high)

    def factory(env):
        low, high = action_bounds(env)
        return TensorDictModule(IDMTrackingAverage(low, high),
                                in_keys=[("cav", "gap"), ("cav", "speed"), ("cav", "leader_speed"), ("traffic", "v_eq")],
                                out_keys=["action"])

    return factory


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gains", type=float, nargs="+", default=[0.0, 0.3, 0.6], help="k values (0 = IDM)")
    p.add_argument("--episodes", type=int, default=8, help="episodes per profile")
    p.add_argument("--seed", type=int, default=1000, help="evaluation seed")
    p.add_argument("--out", default="outputs/results/ring_return_frontier", help="output directory")
    args = p.parse_args(argv)
    if args.episodes < 1:
        p.error(f"--episodes {args.episodes} is invalid; allowed: >= 1")

    from mixed_traffic.config import compose
    from mixed_traffic.evaluation.harness import evaluate

    cfg = compose(["experiment=ring_lagrangian_ppo", "transforms=safe_priced", "eval.without_layer=true",
                   "eval.close_starts=[]", "trainer.progress=false"])
    rows = []
    for k in args.gains:
        rep, _ = evaluate(cfg, policy_factory=make_factory(k), profiles=list(PROFILES), episodes=args.episodes,
                          seed=args.seed)
        for prof in PROFILES:
            m = rep["profiles"][prof]["metrics"]
            free = next(iter(rep["without_layer"][prof].values()))
            fm = free["metrics"]
            rows.append({
                "k": k, "profile": prof,
                "return": m["return"]["mean"], "intervention": m["safety_clip_rate"]["mean"],
                "jerk": m["mean_abs_jerk"]["mean"], "collisions": rep["profiles"][prof]["collisions"],
                "free_return": fm["return"]["mean"], "free_collisions": free["collisions"],
                "free_min_gap_after": fm["min_gap_after"]["min"], "free_max_head_gap": fm["max_head_gap"]["max"],
            })
        print(f"k = {k:g} done", flush=True)
    head = ("| k | profile | return (layer) | intervention | jerk (m/s3) | collisions | return (no layer) "
            "| collisions (no layer) | min gap after warm-up (m) | max head gap (m) |\n" + "|---" * 10 + "|")
    lines = [head] + [
        f"| {r['k']:g} | {r['profile']} | {r['return']:.1f} | {r['intervention']:.3f} | {r['jerk']:.3f} | "
        f"{r['collisions']} | {r['free_return']:.1f} | {r['free_collisions']} | {r['free_min_gap_after']:.2f} | "
        f"{r['free_max_head_gap']:.1f} |" for r in rows]
    table = "\n".join(lines)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "frontier.md").write_text(f"{args.episodes} episodes per profile, evaluation seed {args.seed}\n\n{table}\n")
    (out / "frontier.json").write_text(json.dumps(rows, indent=1))
    print(table)


if __name__ == "__main__":
    main()
