"""FollowerStopper's set point on the ring_wave scenario: how close to uniform flow it can drive.

For every ring length and set-point ratio (``U = ratio x`` the ring's uniform-flow speed;
ratio 0 = the all-human ring) the torch backend runs ``--episodes`` episodes and reports the
wave metrics after the warm-up (mean speed / uniform-flow speed, speed std, hard brakes per
veh-km, fuel per veh-km, min gap, collisions). Used in ``docs/wave.md``::

    python benchmarks/wave_set_point.py --ring-lengths 210 220 230 260 270 285 --ratios 0 0.85 0.9 0.93 0.95 0.97
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from tqdm.auto import tqdm

from mixed_traffic import make_env
from mixed_traffic.controllers.dampers import make_damper
from mixed_traffic.evaluation.waves import uniform_flow_speed, wave_metrics


def run(ring_length: float, ratio: float, *, episodes: int, seed: int, seconds: float, warmup: float) -> dict:
    env = make_env("ring_wave", batch_size=episodes, seed=seed, ring_length=ring_length, episode_seconds=seconds)
    policy = make_damper("follower_stopper", env, u_ratio=ratio) if ratio > 0 else make_damper("human", env, seed=seed)
    with torch.no_grad():
        td = env.rollout(env.scenario.max_steps, policy, break_when_any_done=False)
    per_episode = wave_metrics(td, dt=env.scenario.dt, warmup=warmup)
    m = {k: float(v.mean()) for k, v in per_episode.items()}
    m["min_gap"] = float(per_episode["min_gap"].min())
    m["speed_ratio"] = m["mean_speed"] / uniform_flow_speed(env.scenario, ring_length)
    return m


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ring-lengths", type=float, nargs="+", default=[230.0])
    ap.add_argument("--ratios", type=float, nargs="+", default=[0.0, 0.9, 0.93, 1.0])
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--warmup", type=float, default=300.0)
    ap.add_argument("--out", default="outputs/wave_set_point.json")
    a = ap.parse_args(argv)
    if any(r < 0 for r in a.ratios):
        ap.error(f"--ratios {a.ratios} is invalid; allowed: 0 (all-human) or set-point ratios > 0")
    if not 0 <= a.warmup < a.seconds:
        ap.error(f"--warmup {a.warmup} is invalid; allowed: 0 <= warmup < --seconds ({a.seconds})")
    out = {}
    cells = [(L, r) for L in a.ring_lengths for r in a.ratios]
    for L, r in tqdm(cells, desc="ring x set point", unit="cell"):
        m = run(L, r, episodes=a.episodes, seed=a.seed, seconds=a.seconds, warmup=a.warmup)
        out[f"{L:g}_{r:g}"] = m
        tqdm.write(f"{L:g} m, ratio {r:g}: speed/uniform {m['speed_ratio']:.3f}, std {m['speed_std']:.2f} m/s, "
                   f"hard brakes {m['hard_brakes_per_vkm']:.1f}/veh-km, fuel {m['fuel_ml_per_vkm']:.1f} mL/veh-km, "
                   f"collisions {m['collision'] * a.episodes:.0f}")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
