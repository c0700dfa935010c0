"""How often SUMO overrides the CAV's command under speed mode 95.

With ``sumo_safety=True`` (speed mode 95) SUMO caps the commanded speed at its
safe speed (Krauss, from the CAV vType) and its accel/decel bounds. This script
runs the ring for ``--seconds`` per policy and reports the fraction of steps in
which the executed acceleration differs from the commanded one (more than 1e-6 m/s
of speed), for a uniformly random policy and constant-acceleration policies.
Speed mode 0 is run as a control (it must be 0 %).

    .venv/bin/python benchmarks/sumo_override_rate.py --seconds 500 --seed 0
"""

from __future__ import annotations

import argparse
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mixed_traffic.envs import make_env  # noqa: E402


def override_rate(policy: str, seconds: float, seed: int, sumo_safety: bool = True) -> dict:
    """Run one episode of ``seconds`` with ``policy`` ("random" or a constant like "+3")."""
    env = make_env("ring", backend="sumo", seed=seed, sumo_safety=sumo_safety, episode_seconds=seconds)
    gen = torch.Generator().manual_seed(seed)
    lo, hi = env.scenario.cav_accel_bounds
    try:
        td = env.reset()
        steps, collided = 0, False
        for _ in range(env.scenario.max_steps):
            if policy == "random":
                a = lo + (hi - lo) * torch.rand(1, env.scenario.n_cav, generator=gen)
            else:
                a = torch.full((1, env.scenario.n_cav), float(policy))
            td["action"] = a
            td = env.step(td)["next"]
            steps += 1
            if bool(td["done"].any()):
                collided = bool(td["collision"].any())
                break
        return {"policy": policy, "speed_mode": 95 if sumo_safety else 0, "steps": steps,
                "overridden_steps": env.override_steps, "rate": env.override_steps / steps, "collision": collided}
    finally:
        env.close()


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=500.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--policies", nargs="+", default=["random", "-1", "0", "+1", "+2", "+3"])
    args = p.parse_args(argv)
    rows = []
    print("| policy | speed mode | steps | overridden steps | override rate | collision |")
    print("|---|---|---|---|---|---|")
    for safety in (True, False):
        for pol in args.policies:
            r = override_rate(pol, args.seconds, args.seed, safety)
            rows.append(r)
            print(f"| {r['policy']} | {r['speed_mode']} | {r['steps']} | {r['overridden_steps']} | "
                  f"{100 * r['rate']:.1f} % | {r['collision']} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
