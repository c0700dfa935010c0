"""Cross-simulator agreement of the DeeP-LCC platoon: all-HDV closed loops in torch and in SUMO.

Every vehicle drives by the humans' model: the SUMO humans are SUMO's IDM with the
DeeP-LCC IDM set, the CAVs take the torch IDM acceleration on SUMO's state
(``compare.hdv_policy``). The torch platoon runs the same episode (same seed, so the
same head profile) with IDM humans (``mismatch="idm"``) and, for contrast, with the
homogeneous OVM of the Hankel data (``mismatch="none"``), both without acceleration
noise. Printed per scenario: RMS / max difference of every follower's speed and gap
over the episode, and the closed-loop cost (sum of J) and fuel of each.

    python benchmarks/sumo_platoon_agreement.py --scenarios random1 random5 brake sine --out outputs/deeplcc/agreement.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mixed_traffic import make_env  # noqa: E402
from mixed_traffic.controllers.deeplcc.closed_loop import fuel_rate  # noqa: E402
from mixed_traffic.controllers.deeplcc.compare import SCENARIOS, SECONDS, hdv_policy  # noqa: E402


def run(backend: str, mismatch: str, scenario: str, seed: int) -> dict:
    env = make_env("platoon", backend=backend, seed=seed, mismatch=mismatch, accel_noise=0.0,
                   profiles=[SCENARIOS[scenario]], randomize=False, episode_seconds=SECONDS.get(scenario, 40.0))
    try:
        with torch.no_grad():
            td = env.rollout(env.scenario.max_steps, hdv_policy(env), break_when_any_done=False)
    finally:
        env.close()
    nxt = td["next"]
    v = td["traffic", "speed"][0, :, 3:].double().numpy()
    a = nxt["traffic", "accel"][0, :, 3:].double().numpy()
    return {"speed": nxt["traffic", "speed"][0].double(), "gap": nxt["traffic", "gap"][0, :, 1:].double(),
            "cost": float(nxt["traffic", "J"].sum()), "fuel": float(fuel_rate(v, a).sum() * env.dt),
            "min_gap": float(nxt["traffic", "gap"][0, :, 1:].min()), "collision": bool(nxt["collision"].any())}


def diff(a: dict, b: dict) -> dict:
    dv, dg = a["speed"][:, 1:] - b["speed"][:, 1:], a["gap"] - b["gap"]
    return {"speed_rms": float(dv.pow(2).mean().sqrt()), "speed_max": float(dv.abs().max()),
            "gap_rms": float(dg.pow(2).mean().sqrt()), "gap_max": float(dg.abs().max()),
            "cost_diff_pct": 100.0 * (a["cost"] / b["cost"] - 1.0), "fuel_diff_pct": 100.0 * (a["fuel"] / b["fuel"] - 1.0)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", nargs="*", default=["random1", "random5", "brake", "sine"], choices=list(SCENARIOS))
    ap.add_argument("--seed", type=int, default=10_000)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res = {}
    for i, sc in enumerate(a.scenarios):
        sumo, idm, ovm = (run(b, m, sc, a.seed + i) for b, m in (("sumo", "idm"), ("torch", "idm"), ("torch", "none")))
        assert torch.equal(sumo["speed"][:, 0], idm["speed"][:, 0]), "the backends drew different head profiles"
        res[sc] = {"sumo_vs_torch_idm": diff(sumo, idm), "sumo_vs_torch_ovm": diff(sumo, ovm),
                   **{f"{k}_{name}": r[k] for name, r in (("sumo", sumo), ("torch_idm", idm), ("torch_ovm", ovm))
                      for k in ("cost", "fuel", "min_gap", "collision")}}
        d, o = res[sc]["sumo_vs_torch_idm"], res[sc]["sumo_vs_torch_ovm"]
        print(f"{sc:8s} vs torch IDM: speed rms {d['speed_rms']:.4f} max {d['speed_max']:.4f} m/s, gap rms "
              f"{d['gap_rms']:.4f} max {d['gap_max']:.4f} m, cost {d['cost_diff_pct']:+.2f}%, fuel "
              f"{d['fuel_diff_pct']:+.2f}% | vs torch OVM: speed rms {o['speed_rms']:.3f}, gap rms {o['gap_rms']:.3f}, "
              f"cost {o['cost_diff_pct']:+.1f}% | cost sumo {res[sc]['cost_sumo']:.4g} torch-idm "
              f"{res[sc]['cost_torch_idm']:.4g} torch-ovm {res[sc]['cost_torch_ovm']:.4g}")
    if a.out:
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        with open(a.out, "w") as f:
            json.dump(res, f, indent=2)
    return res


if __name__ == "__main__":
    main()
