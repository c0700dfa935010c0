"""Cross-simulator agreement: the ring in the torch backend and in SUMO, side by side.

Both backends run the same scenario and seed (so the same head profile and initial
state); the CAV is driven in both by the same closed-loop controller (IDM as CAV,
reading ``("cav", "gap")``, ``("cav", "speed")`` and ``("cav", "leader_speed")``).
The script prints the RMS and maximum differences of every follower's speed and gap
and writes a plot.

    .venv/bin/python benchmarks/sumo_agreement.py --seconds 120 --seeds 0 1 2 3 4 \
        --out docs/img/sumo_agreement.png

>>> from benchmarks.sumo_agreement import run_pair, compare  # doctest: +SKIP
>>> t, torch_traj, sumo_traj = run_pair(seconds=5.0, seed=0)  # doctest: +SKIP
>>> compare(torch_traj, sumo_traj)["speed_rms"] < 0.5  # doctest: +SKIP
True
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from mixed_traffic.envs import make_env  # noqa: E402
from mixed_traffic.physics import IDMParams, idm_accel  # noqa: E402


def idm_cav_action(td, bounds=(-3.0, 3.0), params: IDMParams = IDMParams()) -> torch.Tensor:
    """IDM-as-CAV: the CAV's command from the env's own ("cav", ...) entries."""
    a = idm_accel(td["cav", "gap"], td["cav", "speed"], td["cav", "leader_speed"],
                  v0=params.v0, T=params.T, a=params.a, b=params.b, delta=params.delta, s0=params.s0)
    return a.clamp(*bounds)


def constant_action(td, value: float = 0.0) -> torch.Tensor:
    return torch.full_like(td["cav", "speed"], value)


def run_backend(backend: str, seconds: float, seed: int, controller=idm_cav_action, **overrides) -> dict:
    """Roll one episode of ``seconds`` in ``backend``; return numpy trajectories (time first)."""
    steps = int(round(seconds / overrides.get("dt", 0.1)))
    env = make_env("ring", backend=backend, seed=seed, episode_seconds=max(seconds, 1.0), **overrides)
    try:
        td = env.reset()
        rows = {"speed": [], "gap": [], "pos": [], "accel": [], "cav_accel": [], "collision": []}

        def record(x):
            rows["speed"].append(x["traffic", "speed"][0].double().numpy())
            rows["gap"].append(x["traffic", "gap"][0].double().numpy())
            rows["pos"].append(x["traffic", "pos"][0].double().numpy())
            rows["accel"].append(x["traffic", "accel"][0].double().numpy())
            rows["cav_accel"].append(x["cav", "accel"][0].double().numpy())
            rows["collision"].append(bool(x["collision"][0, 0]))

        record(td)
        for _ in range(steps):
            td["action"] = controller(td)
            td = env.step(td)["next"]
            record(td)
            if bool(td["done"].any()):
                break
    finally:
        env.close()
    return {k: np.array(v) for k, v in rows.items()}


def run_pair(seconds: float = 120.0, seed: int = 0, controller=idm_cav_action, **overrides):
    """The same episode in both backends: ``(time, torch_traj, sumo_traj)``."""
    tr = run_backend("torch", seconds, seed, controller, **overrides)
    su = run_backend("sumo", seconds, seed, controller, **overrides)
    n = min(len(tr["speed"]), len(su["speed"]))
    tr = {k: v[:n] for k, v in tr.items()}
    su = {k: v[:n] for k, v in su.items()}
    dt = overrides.get("dt", 0.1)
    return np.arange(n) * dt, tr, su


def compare(tr: dict, su: dict) -> dict:
    """RMS / max differences over all followers (index >= 1) and all times."""
    dv = tr["speed"][:, 1:] - su["speed"][:, 1:]
    dg = tr["gap"][:, 1:] - su["gap"][:, 1:]
    dh = tr["speed"][:, 0] - su["speed"][:, 0]
    return {
        "speed_rms": float(np.sqrt(np.mean(dv**2))), "speed_max": float(np.abs(dv).max()),
        "gap_rms": float(np.sqrt(np.mean(dg**2))), "gap_max": float(np.abs(dg).max()),
        "head_speed_max": float(np.abs(dh).max()),
        "speed_rms_per_vehicle": np.sqrt(np.mean(dv**2, axis=0)).round(6).tolist(),
    }


def plot(t, tr, su, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = tr["speed"].shape[1]
    fig, axes = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i in range(n):
        c = colors[i % len(colors)]
        lab = "head" if i == 0 else f"veh {i}"
        axes[0].plot(t, tr["speed"][:, i], color=c, lw=1.5, label=f"{lab} torch")
        axes[0].plot(t, su["speed"][:, i], color=c, lw=1.0, ls="--", label=f"{lab} SUMO")
        axes[1].plot(t, tr["gap"][:, i], color=c, lw=1.5)
        axes[1].plot(t, su["gap"][:, i], color=c, lw=1.0, ls="--")
        if i > 0:
            axes[2].plot(t, tr["speed"][:, i] - su["speed"][:, i], color=c, lw=1.0, label=lab)
    axes[0].set_ylabel("speed (m/s)")
    axes[0].legend(ncol=4, fontsize=7)
    axes[1].set_ylabel("gap to leader (m)")
    axes[2].set_ylabel("speed torch - SUMO (m/s)")
    axes[2].set_xlabel("time (s)")
    axes[2].legend(ncol=4, fontsize=7)
    axes[0].set_title(title)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seconds", type=float, default=120.0)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--controller", choices=["idm", "constant"], default="idm")
    p.add_argument("--out", default="docs/img/sumo_agreement.png", help="plot of the first seed ('' for none)")
    args = p.parse_args(argv)
    ctrl = idm_cav_action if args.controller == "idm" else constant_action
    rows = []
    print("| seed | speed RMS (m/s) | speed max | gap RMS (m) | gap max | head speed max |")
    print("|---|---|---|---|---|---|")
    for k, seed in enumerate(args.seeds):
        t, tr, su = run_pair(args.seconds, seed, ctrl)
        res = compare(tr, su)
        rows.append(res)
        print(f"| {seed} | {res['speed_rms']:.4f} | {res['speed_max']:.4f} | {res['gap_rms']:.4f} | "
              f"{res['gap_max']:.4f} | {res['head_speed_max']:.4f} |", flush=True)
        if k == 0 and args.out:
            plot(t, tr, su, args.out, f"ring, seed {seed}, CAV = {args.controller}: torch (solid) vs SUMO (dashed); "
                 f"RMS speed diff {res['speed_rms']:.3g} m/s")
            print(f"plot: {args.out}")
    return rows


if __name__ == "__main__":
    main()
