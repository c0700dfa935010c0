"""A ring experiment's residual base driving alone, against IDM-as-CAV, on a tuning seed no report uses.

The base of ``transforms.residual`` (the learned residual at zero, no safety layer) is built from
``--experiment`` plus any Hydra ``--set`` overrides, so a base can be tried before anything is trained.
It runs on the held-out case types of ``ring_generalization.py`` and on the evaluation profiles
(4 episodes each; held-out cases 200 s, the profiles their own length), with evaluation seed ``--seed``
(default 3000: not the held-out cases' 2000 nor the evaluation profiles' 1000). Prints one line per
case: collisions, the smallest gap after the warm-up, the largest head gap, the steady RMSE, the jerk
against IDM-as-CAV's on the same episodes and the return's difference; ``--out`` writes them as JSON::

    python benchmarks/ring_base_probe.py --experiment ring_lagrangian_ppo_tight
    python benchmarks/ring_base_probe.py --experiment ring_lagrangian_ppo_tight \\
        --set transforms.residual.params.kv_closing_near=0.0 transforms.residual.params.kv=0.805

This is how the bases of ``experiment=ring_lagrangian_ppo_tight`` and ``experiment=ring_lagrangian_ppo_band``
were picked (docs/results.md)::

    python benchmarks/ring_base_probe.py --experiment ring_lagrangian_ppo_band \\
        --set transforms.residual.top_speed.params.match_gap_max=30 --cases fast_steps eudc
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

NAMES = ("stop_and_go", "brake_to_standstill", "fast_steps", "random_steps", "emergency_brake", "eudc", "sine",
         "brake_from_25", "wide_steps", "sine_fast", "stop_and_go_15")


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--experiment", required=True, help="a ring experiment with a residual base")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="Hydra overrides of the experiment")
    p.add_argument("--cases", nargs="+", default=list(NAMES), help=f"subset of {list(NAMES)}")
    p.add_argument("--seed", type=int, default=3000, help="evaluation seed (default 3000, a tuning seed)")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    a = p.parse_args(argv)
    unknown = set(a.cases) - set(NAMES)
    if unknown:
        raise SystemExit(f"--cases: {sorted(unknown)} are not cases; allowed: {list(NAMES)}")

    import torch
    from ring_classical_frontier import run

    from mixed_traffic.config import compose
    from mixed_traffic.evaluation.policies import classic_factory, residual_base_factory
    from mixed_traffic.validation import validate_config

    torch.set_num_threads(1)
    cfg = validate_config(compose([f"experiment={a.experiment}", *a.set]))
    factory = residual_base_factory(cfg)  # fails here, naming residual_idm, for a chain without a base
    ref, res = (run(cfg, fac, episodes=a.episodes, seed=a.seed, names=a.cases, profiles_at_seed=True)
                for fac in (classic_factory("idm"), factory))
    print(f"{a.experiment} {' '.join(a.set)}: the base alone, seed {a.seed}, {a.episodes} episodes a case")
    for name, r in res.items():
        q = ref[name]
        print(f"  {name:20s} collisions {r['collisions']}  gaps {r['min_gap']:5.2f}-{r['max_head_gap']:4.1f} m  "
              f"RMSE {r['steady_rmse']:.3f}  jerk {100 * (r['jerk'] / q['jerk'] - 1):+5.1f} %  "
              f"return {r['return'] - q['return']:+6.1f}  (IDM: gaps {q['min_gap']:.2f}-{q['max_head_gap']:.1f})")
    out = {"experiment": a.experiment, "overrides": a.set, "seed": a.seed, "base": res, "idm_as_cav": ref}
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
