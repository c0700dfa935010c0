"""Random classical controllers against the ring's bars, on the held-out cases and two evaluation profiles.

Draws ``--settings`` parameter settings of one family and runs each without a layer on the same
episodes as IDM-as-CAV (the reference of the jerk and return bars; evaluation seed 2000 for the
held-out cases of ``ring_generalization.py``, the run's ``eval.seed`` for the profiles):

- ``idm``: IDM with a (0.6-2.5 m/s^2), b (1-5), T (0.4-1.5 s), s0 (5-8 m), v0 (30-80 m/s or 60),
  delta (2/4/6/8) and, in 70 % of the draws, the steady-gap cap ``gap_max`` (18-34 m);
- ``soft``: ``controller=soft``, a linear follower ``ks (gap - s0 - h v) + kv (v_lead - v)`` under
  an IDM envelope (the lower of the two commands; IDM with v0 = 60 m/s and its own T, s0_idm, a, b),
  a controller outside the IDM family that can let the gap float inside the band
  (:func:`mixed_traffic.physics.soft_follower_accel`).

Per case a setting meets the bars when it has 0 collisions, gaps in [s_min, s_max] after the
warm-up, steady RMSE <= ``eval.rmse_bar``, jerk <= IDM-as-CAV's and return >= IDM-as-CAV's. Prints,
per case, how many settings keep the band and the least jerk among them, and the settings that meet
most bars. Writes ``OUT/frontier.jsonl`` (one line per setting) and ``OUT/frontier.json``::

    python benchmarks/ring_classical_frontier.py --checkpoint outputs/results/ring_eng5_seed1 --family idm \\
        --settings 100 --out outputs/results/classical_frontier_idm
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import torch  # noqa: E402

CASES = ("fast_steps", "stop_and_go", "brake_to_standstill", "random_steps", "emergency_brake")


def draw(family: str, rng: random.Random) -> dict:
    u = lambda lo, hi, nd=2: round(rng.uniform(lo, hi), nd)  # noqa: E731
    if family == "idm":
        p = dict(a=u(0.6, 2.5), b=u(1.0, 5.0), T=u(0.4, 1.5), s0=u(5.0, 8.0),
                 v0=round(rng.choice([rng.uniform(30, 80), 60.0]), 1), delta=rng.choice([2.0, 4.0, 6.0, 8.0]))
        if rng.random() < 0.7:
            p["gap_max"] = u(18, 34, 1)
        return p
    return dict(ks=u(0.02, 0.15, 3), kv=u(0.1, 0.8), s0=u(5, 9), h=u(0.4, 1.2), T=u(0.2, 1.0), s0_idm=u(3, 7),
                a=u(1, 3), b=u(1.5, 4))


def factory(family: str, params: dict | None):
    """``controller=<family>:<params>`` (IDM-as-CAV with ``params=None``)."""
    from mixed_traffic.evaluation.policies import classic_factory

    if params is None:
        return classic_factory("idm")
    return classic_factory(f"{family}:" + ";".join(f"{k}={v}" for k, v in params.items()))


def run(run_cfg, fac, *, episodes: int, seed: int = 2000, names=CASES, profiles_at_seed: bool = False) -> dict:
    """One row per case of ``names``, no layer. Held-out cases run at ``seed``; the run's evaluation
    profiles at the run's own ``eval.seed`` unless ``profiles_at_seed``."""
    from omegaconf import open_dict
    from ring_generalization import named_config

    from mixed_traffic.evaluation import classical_chain
    from mixed_traffic.evaluation.harness import evaluate

    out = {}
    for name in names:
        cfg, prof = named_config(run_cfg, name, episodes=episodes, seconds=200.0, seed=seed)
        with open_dict(cfg):
            cfg.transforms.chain, cfg.eval.without_layer = classical_chain(run_cfg.transforms.chain), False
            if profiles_at_seed:
                cfg.eval.seed = seed
        rep = evaluate(cfg, policy_factory=fac)[0]
        m = rep["profiles"][prof]["metrics"]
        out[name] = {"collisions": rep["profiles"][prof]["collisions"], "min_gap": m["min_gap_after"]["min"],
                     "max_head_gap": m["max_head_gap"]["max"], "steady_rmse": m["speed_rmse_steady"]["mean"],
                     "jerk": m["mean_abs_jerk"]["mean"], "return": m["return"]["mean"]}
    return out


def bars(row: dict, ref: dict, e) -> dict:
    band = row["collisions"] == 0 and row["min_gap"] >= e.s_min and row["max_head_gap"] <= e.s_max
    return {"band": band, "rmse": row["steady_rmse"] <= e.rmse_bar, "jerk": row["jerk"] <= ref["jerk"],
            "return": row["return"] >= ref["return"]}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", required=True, help="a ring run (its config gives the scenario and the bars)")
    p.add_argument("--family", choices=("idm", "soft"), default="idm")
    p.add_argument("--settings", type=int, default=100)
    p.add_argument("--seed", type=int, default=1, help="seed of the draws")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--out", required=True)
    p.add_argument("--summarize", action="store_true", help="only summarize OUT/frontier.jsonl of an earlier run")
    a = p.parse_args(argv)

    from tqdm import tqdm

    from mixed_traffic.evaluation.policies import checkpoint_config

    torch.set_num_threads(1)
    run_cfg, _ = checkpoint_config(a.checkpoint)
    e = run_cfg.eval
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    ref = run(run_cfg, factory(a.family, None), episodes=a.episodes)
    rows = []
    if a.summarize:
        rows = [json.loads(line) for line in open(out / "frontier.jsonl")]
    else:
        rng = random.Random(a.seed)
        with open(out / "frontier.jsonl", "w") as f:
            for _ in tqdm(range(a.settings), desc=f"{a.family} settings"):
                params = draw(a.family, rng)
                res = run(run_cfg, factory(a.family, params), episodes=a.episodes)
                met = {c: bars(res[c], ref[c], e) for c in CASES}
                rows.append({"params": params, "results": res, "bars": met})
                f.write(json.dumps(rows[-1]) + "\n")
                f.flush()
    summary = {"family": a.family, "settings": len(rows), "idm_as_cav": ref, "cases": {}}

    def least(keep, c):
        best = min(keep, key=lambda r: r["results"][c]["jerk"], default=None)
        if best is None:
            return None, None, "none"
        jerk = best["results"][c]["jerk"]
        return jerk, best["params"], f"{jerk:.4f} ({100 * (jerk / ref[c]['jerk'] - 1):+.1f} % against IDM-as-CAV's)"

    for c in CASES:
        keep = [r for r in rows if r["bars"][c]["band"]]
        keep_rmse = [r for r in keep if r["bars"][c]["rmse"]]
        j1, p1, t1 = least(keep, c)
        j2, p2, t2 = least(keep_rmse, c)
        summary["cases"][c] = {"keep_band": len(keep), "keep_band_and_rmse": len(keep_rmse),
                               "meet_all": sum(all(r["bars"][c].values()) for r in rows),
                               "least_jerk_in_band": j1, "its_params": p1,
                               "least_jerk_in_band_and_rmse": j2, "its_params_rmse": p2}
        print(f"{c}: {len(keep)} of {len(rows)} keep the band, least jerk among them {t1}; {len(keep_rmse)} keep "
              f"the band and the steady RMSE, least jerk {t2}; every bar met by {summary['cases'][c]['meet_all']}")
    score = lambda r: sum(sum(v.values()) for v in r["bars"].values())  # noqa: E731
    summary["top"] = [{"params": r["params"], "bars_met": score(r), "bars": r["bars"]}
                      for r in sorted(rows, key=score, reverse=True)[:5]]
    total = 4 * len(CASES)
    for r in summary["top"]:
        print(f"{r['bars_met']} of {total} bars: {r['params']}")
    (out / "frontier.json").write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
