"""Train the NNMPC on a DeeP-LCC dataset and compare it with the QP in closed loop.

    python -m mixed_traffic.controllers.deeplcc.train --dataset outputs/deeplcc/dataset.npz \
        --out outputs/deeplcc/nnmpc --relabel --dagger-rounds 3

Steps: (1) behaviour cloning on the stored labels; (2) with ``--relabel``, the
stored states are relabelled by the deployed QP (one Hankel set, ``--eval-seed``)
so every label comes from the controller being imitated; (3) DAgger rounds: the
network drives the training scenario mix, the deployed QP labels what it visits,
retrain on the aggregate. After each stage: offline MSE/MAE/max error on the
held-out split and closed-loop cost/fuel/velocity error against the QP on the
five evaluation scenarios. Everything lands in ``<out>/results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from mixed_traffic.controllers.deeplcc.closed_loop import EVAL_SCENARIOS, QPController, evaluate
from mixed_traffic.controllers.deeplcc.dataset import DatasetConfig, episode_scenario, load_dataset, nn_inputs
from mixed_traffic.controllers.deeplcc.nnmpc import (
    NNMPC,
    TrainConfig,
    dagger,
    numpy_controller,
    offline_metrics,
    qp_gain,
    split,
    train_nnmpc,
)
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.controllers.deeplcc.precollect import precollect
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams


def deployed_solver(seed: int, preset: str = "dataset", hdv_model: str = "ovm", T: int = 2000,
                    backend: str = "torch") -> tuple[PlatoonConfig, DeepLCCSolver]:
    """The QP controller the surrogate imitates: one Hankel set pre-collected with ``seed``.

    ``backend="sumo"`` pre-collects it in SUMO (:class:`~mixed_traffic.envs.sumo_platoon.SumoPlatoon`,
    IDM humans without noise; ``hdv_model`` must then be ``"idm"``); SUMO is closed afterwards.
    """
    if backend not in ("torch", "sumo"):
        raise ValueError(f"backend: {backend!r} is invalid; allowed: 'torch', 'sumo'")
    gen = torch.Generator().manual_seed(seed)
    if backend == "torch":
        cfg = PlatoonConfig(hdv_model=hdv_model)
        [h] = precollect(cfg, T=T, generator=gen)
    else:
        from mixed_traffic.envs.sumo_platoon import SumoPlatoon

        cfg = PlatoonConfig(hdv_model=hdv_model, accel_noise=0.0)
        sim = SumoPlatoon(cfg, seconds=T * cfg.dt)
        try:
            [h] = precollect(cfg, T=T, generator=gen, simulator=sim)
        finally:
            sim.close()
    return cfg, DeepLCCSolver(h, QPParams.preset(preset))


def relabel(solver: DeepLCCSolver, x: np.ndarray) -> np.ndarray:
    """QP labels of every state ``x (N, 260)`` (warm-started in stored order)."""
    solver.reset_warm_start()
    m, p, t = solver.m, solver.qp.p, solver.qp.t_ini
    return np.stack([solver.solve(r[: m * t], r[m * t: m * t + p * t], r[m * t + p * t:]).u for r in x.astype(np.float64)])


def compare(net, qp_results: dict, cfg: PlatoonConfig, seed: int, scenarios=None) -> dict:
    nn_res = evaluate(numpy_controller(net), cfg, scenarios, seed=seed)
    out = {}
    for name, r in nn_res.items():
        q = qp_results[name]
        out[name] = {"qp_cost": q["cost"], "nn_cost": r["cost"], "cost_diff_pct": 100 * (r["cost"] / q["cost"] - 1),
                     "qp_fuel": q["fuel"], "nn_fuel": r["fuel"], "qp_velocity_error": q["velocity_error"],
                     "nn_velocity_error": r["velocity_error"], "nn_collision": bool(r["collisions"]),
                     "qp_collision": bool(q["collisions"]), "nn_min_gap": r["min_gap"], "qp_min_gap": q["min_gap"]}
    return out


def table(cmp: dict) -> str:
    lines = ["| scenario | QP cost | NN cost | diff % | QP fuel | NN fuel | QP vel.err | NN vel.err | NN collision |",
             "|---|---|---|---|---|---|---|---|---|"]
    for n, r in cmp.items():
        lines.append(f"| {n} | {r['qp_cost']:.4g} | {r['nn_cost']:.4g} | {r['cost_diff_pct']:+.2f} | {r['qp_fuel']:.1f} | "
                     f"{r['nn_fuel']:.1f} | {r['qp_velocity_error']:.4f} | {r['nn_velocity_error']:.4f} | {r['nn_collision']} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m mixed_traffic.controllers.deeplcc.train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--eval-seed", type=int, default=12345, help="seed of the deployed QP's Hankel set")
    ap.add_argument("--scenario-seed", type=int, default=0)
    ap.add_argument("--relabel", action="store_true")
    ap.add_argument("--gain-feature", action="store_true",
                    help="add the deployed QP's equality-only first action as an input (262 features)")
    ap.add_argument("--residual", action="store_true",
                    help="output clamp(QP linear part + MLP correction) (implies the gain feature)")
    ap.add_argument("--skip-stored", action="store_true",
                    help="with --relabel: train only on the deployed QP's labels (no stage on the stored labels)")
    ap.add_argument("--init", default=None, help="start from this NNMPC checkpoint (skips the stored-label stage)")
    ap.add_argument("--dagger-rounds", type=int, default=0)
    ap.add_argument("--dagger-episodes", type=int, default=6)
    ap.add_argument("--max-epochs", type=int, default=200)
    ap.add_argument("--patience", type=int, default=20)
    ap.add_argument("--max-seconds", type=float, default=None, help="wall-clock budget per training stage")
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--scenarios", nargs="*", default=list(EVAL_SCENARIOS))
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    os.makedirs(a.out, exist_ok=True)
    t_start = time.perf_counter()
    data = load_dataset(a.dataset, hankel=False)
    x, y = nn_inputs(data), data["u_opt"].astype(np.float32)
    ds_cfg = json.loads(str(data["config"])) if "config" in data else {}
    cfg, solver = deployed_solver(a.eval_seed, ds_cfg.get("qp_preset", "dataset"), ds_cfg.get("hdv_model", "ovm"))
    tc = TrainConfig(max_epochs=a.max_epochs, patience=a.patience, batch_size=a.batch_size, max_seconds=a.max_seconds)
    results = {"dataset": a.dataset, "samples": len(x), "eval_seed": a.eval_seed, "stages": {}}
    qp_res = evaluate(QPController([solver]), cfg, a.scenarios, seed=a.scenario_seed)
    results["qp"] = qp_res

    def stage(name, net, hist, xs, ys):
        _, va = split(len(xs), tc.val_fraction, tc.seed)
        off = offline_metrics(net, xs[va], ys[va])
        cmp = compare(net, qp_res, cfg, a.scenario_seed, a.scenarios)
        results["stages"][name] = {"offline": off, "closed_loop": cmp, "epochs": hist.get("epochs"),
                                   "train_seconds": hist.get("seconds"), "samples": len(xs)}
        net.save(os.path.join(a.out, f"nnmpc_{name}.pt"), stage=name)
        print(f"\n## {name}: offline MSE {off['mse']:.2e}, MAE {off['mae']:.3f}, max {off['max_error']:.3f} "
              f"({hist.get('epochs')} epochs, {hist.get('seconds') or 0:.0f} s)\n{table(cmp)}", flush=True)
        with open(os.path.join(a.out, "results.json"), "w") as f:
            json.dump(results, f, indent=2, default=float)

    gain = qp_gain(solver) if (a.gain_feature or a.residual) else None
    results.update(gain_feature=gain is not None, residual=a.residual)
    net = NNMPC.load(a.init) if a.init else None
    if net is None and not (a.relabel and a.skip_stored):
        net, hist = train_nnmpc(x, y, tc, gain=gain, residual=a.residual)
        stage("bc", net, hist, x, y)
    if a.relabel:
        t0 = time.perf_counter()
        y = relabel(solver, x).astype(np.float32)
        results["relabel_seconds"] = time.perf_counter() - t0
        net, hist = train_nnmpc(x, y, tc, net=net, gain=gain, residual=a.residual)
        stage("bc_relabelled", net, hist, x, y)
    if a.dagger_rounds:
        dcfg = DatasetConfig()
        rng = np.random.default_rng(a.scenario_seed + 99)
        kinds = ["random1", "random3", "random5", "brake", "sine3", "sine5"]
        specs = [episode_scenario(k, dcfg, rng) for k in kinds]
        net, x, y, dh = dagger(net, solver, x, y, cfg, specs, rounds=a.dagger_rounds,
                               episodes_per_round=a.dagger_episodes, train_cfg=tc, seed=a.scenario_seed + 7)
        results["dagger"] = dh
        stage("dagger", net, {"epochs": dh[-1]["epochs"], "seconds": None}, x, y)
    results["wall_seconds"] = time.perf_counter() - t_start
    with open(os.path.join(a.out, "results.json"), "w") as f:
        json.dump(results, f, indent=2, default=float)
    return results


if __name__ == "__main__":
    main()
