"""SUMO's speed mode 95 on the torch backend against real SUMO (libsumo).

Two measurements, for command sequences that SUMO leaves alone (uniform random in the
action bounds), that it overrides in 83-99 % of steps (constant +1 / +2 / +3 m/s^2) and
for a closed-loop policy (an IDM with a short headway, ``T = 0.5 s``, which SUMO's
safe speed caps at times):

1. **one step**: on a SUMO run under speed mode 95, before every step
   :func:`mixed_traffic.physics.sumo_speed_mode_95` predicts from SUMO's own state
   what SUMO will execute; reported: share of steps with the same override decision and
   the largest |predicted - executed| CAV acceleration. This isolates the function.
2. **both backends**: the torch backend (``sumo_safety=True``) and SUMO run the same
   episode (same seed: same head profile and start) with the same commands; reported:
   share of steps with the same override decision, override counts, and the RMS / max
   difference of the executed CAV acceleration and of the CAV speed. This includes the
   backends' other differences (the human drivers' and head's dynamics in float32 torch
   against SUMO's own).

    .venv/bin/python benchmarks/sumo_speed_mode_agreement.py --seconds 100 --seeds 0 1 2

>>> from benchmarks.sumo_speed_mode_agreement import one_step, both_backends  # doctest: +SKIP
>>> one_step("+3", seconds=10.0, seed=0)["decision_agreement"]  # doctest: +SKIP
1.0
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mixed_traffic.envs import make_env  # noqa: E402
from mixed_traffic.physics import IDMParams, KraussParams, idm_accel, sumo_speed_mode_95  # noqa: E402

POLICIES = ("random", "+1", "+2", "+3", "idm_T0.5")
TIGHT_IDM = IDMParams(T=0.5, s0=2.0, a=3.0, b=3.0)


def command(policy: str, td, gen: torch.Generator, bounds: tuple[float, float]) -> torch.Tensor:
    """The CAV command ``[1, n_cav]`` of ``policy`` for the observation ``td``."""
    lo, hi = bounds
    shape = td["cav", "speed"].shape
    if policy == "random":
        return lo + (hi - lo) * torch.rand(shape, generator=gen)
    if policy == "idm_T0.5":
        p = TIGHT_IDM
        a = idm_accel(td["cav", "gap"], td["cav", "speed"], td["cav", "leader_speed"], v0=p.v0, T=p.T, a=p.a, b=p.b,
                      delta=p.delta, s0=p.s0)
        return a.clamp(lo, hi)
    return torch.full(shape, float(policy))


def one_step(policy: str, seconds: float = 100.0, seed: int = 0, **overrides) -> dict:
    """Predict each SUMO step's executed CAV acceleration from SUMO's state before it (see the module docstring)."""
    env = make_env("ring", backend="sumo", seed=seed, sumo_safety=True, episode_seconds=seconds, **overrides)
    sc = env.scenario
    lo, hi = sc.cav_accel_bounds
    ci = list(sc.cav_indices)
    lead = [i - 1 for i in ci]
    decel = np.full(sc.n_vehicles, -lo)
    decel[0] = -sc.head_accel_bounds[0]
    for i in sc.hdv_indices:
        decel[i] = env.hdv_params["b"][i]
    gen = torch.Generator().manual_seed(seed)
    same, err, n, n_sumo, n_pred = 0, [], 0, 0, 0
    try:
        td = env.reset()
        for _ in range(sc.max_steps):
            gap, v = env._gaps(), env.vel.copy()
            a = command(policy, td, gen, (lo, hi)).double().clamp(lo, hi)
            t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)  # noqa: E731
            a_pred, over = sumo_speed_mode_95(a[0], t(gap[ci]), t(v[ci]), t(v[lead]), accel_max=hi, decel=-lo,
                                              leader_decel=t(decel[lead]), dt=sc.dt,
                                              params=KraussParams(emergency_decel=max(-lo, 9.0)))
            td["action"] = a.float()
            td = env.step(td)["next"]
            sumo_over = td["cav", "override"][0].bool()
            same += int(bool((sumo_over == over).all()))
            n_sumo += int(sumo_over.any())
            n_pred += int(over.any())
            err.append(float((a_pred - torch.as_tensor(env.acc[ci])).abs().max()))
            n += 1
            if bool(td["done"].any()):
                break
    finally:
        env.close()
    return {"policy": policy, "seed": seed, "steps": n, "decision_agreement": same / n, "sumo_overridden": n_sumo,
            "predicted_overridden": n_pred, "max_abs_accel_error": max(err)}


def run(backend: str, policy: str, seconds: float, seed: int, **overrides) -> dict:
    env = make_env("ring", backend=backend, seed=seed, sumo_safety=True, episode_seconds=seconds, **overrides)
    sc = env.scenario
    gen = torch.Generator().manual_seed(seed)
    rows = {"accel": [], "speed": [], "override": [], "collision": []}
    try:
        td = env.reset()
        for _ in range(sc.max_steps):
            td["action"] = command(policy, td, gen, sc.cav_accel_bounds)
            td = env.step(td)["next"]
            rows["accel"].append(td["cav", "accel"][0].double().numpy())
            rows["speed"].append(td["cav", "speed"][0].double().numpy())
            rows["override"].append(td["cav", "override"][0].bool().numpy())
            rows["collision"].append(bool(td["collision"].any()))
            if bool(td["done"].any()):
                break
    finally:
        env.close()
    return {k: np.array(v) for k, v in rows.items()}


def both_backends(policy: str, seconds: float = 100.0, seed: int = 0, **overrides) -> dict:
    """The same episode and commands on both backends (see the module docstring)."""
    tr = run("torch", policy, seconds, seed, **overrides)
    su = run("sumo", policy, seconds, seed, **overrides)
    n = min(len(tr["accel"]), len(su["accel"]))
    da = tr["accel"][:n] - su["accel"][:n]
    dv = tr["speed"][:n] - su["speed"][:n]
    same = (tr["override"][:n] == su["override"][:n]).all(-1)
    return {"policy": policy, "seed": seed, "steps": n, "decision_agreement": float(same.mean()),
            "torch_overridden": int(tr["override"][:n].any(-1).sum()), "sumo_overridden": int(su["override"][:n].any(-1).sum()),
            "accel_rms": float(np.sqrt(np.mean(da**2))), "accel_max": float(np.abs(da).max()),
            "speed_rms": float(np.sqrt(np.mean(dv**2))), "speed_max": float(np.abs(dv).max()),
            "collision_torch": bool(tr["collision"].any()), "collision_sumo": bool(su["collision"].any())}


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=100.0)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--policies", nargs="+", default=list(POLICIES))
    args = p.parse_args(argv)
    out = {"one_step": [], "both": []}
    print("One step (prediction from SUMO's own state):\n")
    print("| policy | seed | steps | same decision | SUMO overridden | predicted overridden | max abs Δa (m/s2) |")
    print("|---|---|---|---|---|---|---|")
    for pol in args.policies:
        for s in args.seeds:
            r = one_step(pol, args.seconds, s)
            out["one_step"].append(r)
            print(f"| {pol} | {s} | {r['steps']} | {100 * r['decision_agreement']:.2f} % | {r['sumo_overridden']} | "
                  f"{r['predicted_overridden']} | {r['max_abs_accel_error']:.1e} |", flush=True)
    print("\nBoth backends, same episode and commands:\n")
    print("| policy | seed | steps | same decision | torch overridden | SUMO overridden | CAV accel RMS / max diff (m/s2) "
          "| CAV speed RMS / max diff (m/s) | collision torch / SUMO |")
    print("|---|---|---|---|---|---|---|---|---|")
    for pol in args.policies:
        for s in args.seeds:
            r = both_backends(pol, args.seconds, s)
            out["both"].append(r)
            print(f"| {pol} | {s} | {r['steps']} | {100 * r['decision_agreement']:.2f} % | {r['torch_overridden']} | "
                  f"{r['sumo_overridden']} | {r['accel_rms']:.2e} / {r['accel_max']:.2e} | {r['speed_rms']:.2e} / "
                  f"{r['speed_max']:.2e} | {r['collision_torch']} / {r['collision_sumo']} |", flush=True)
    return out


if __name__ == "__main__":
    main()
