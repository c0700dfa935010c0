"""Benchmarks of the DeeP-LCC QP solver and the NNMPC surrogate (``mt-bench qp`` / ``mt-bench nnmpc``).

Both collect realistic QP instances first: the exact controller drives the
platoon through a hard brake and a ±5 m/s random perturbation, and instances are
taken evenly from those runs (so some have binding constraints). All timings are
medians measured in one process, side by side.

    mt-bench qp --instances 12            # ours (cold / warm) vs cvxopt dense, and the accuracy
    mt-bench nnmpc --checkpoint outputs/deeplcc/nnmpc.pt
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import torch

from mixed_traffic.controllers.deeplcc.closed_loop import EVAL_SCENARIOS, QPController, run_closed_loop
from mixed_traffic.controllers.deeplcc.platoon import PlatoonConfig
from mixed_traffic.controllers.deeplcc.precollect import precollect
from mixed_traffic.controllers.deeplcc.qp import DeepLCCSolver, QPParams, solve_cvxopt


def collect_instances(solver: DeepLCCSolver, cfg: PlatoonConfig, seconds: float = 20.0, seed: int = 0) -> list[tuple]:
    """Closed-loop QP instances ``(uini, yini, eini)`` from a brake and a random ±5 run, in visiting order."""
    inst = []
    for i, name in enumerate(("brake", "random5")):
        spec = EVAL_SCENARIOS[name]
        v = spec.head_speed(cfg.dt, 1, torch.Generator().manual_seed(seed + i))
        v = v[:, : int(round(seconds / cfg.dt)) + 1]
        out = run_closed_loop(QPController([solver]), v, cfg, 20, adaptive_v_star=spec.adaptive_v_star,
                              record=True, generator=torch.Generator().manual_seed(seed + 10 + i))
        inst += [(out["uini"][0, k], out["yini"][0, k], out["eini"][0, k]) for k in range(out["u"].shape[1])]
    return inst


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def setup(preset: str, seed: int, hdv_model: str = "ovm"):
    cfg = PlatoonConfig(hdv_model=hdv_model)
    t0 = time.perf_counter()
    [h] = precollect(cfg, generator=torch.Generator().manual_seed(seed))
    t1 = time.perf_counter()
    solver = DeepLCCSolver(h, QPParams.preset(preset))
    t2 = time.perf_counter()
    return cfg, solver, {"precollect_s": t1 - t0, "factorise_s": t2 - t1}


def time_warm_solves(solver, instances) -> list[float]:
    """Seconds per solve along a trajectory, warm-started from the previous one (how the controller runs)."""
    solver.reset_warm_start()
    times = []
    for args in instances:
        t0 = time.perf_counter()
        solver.solve(*args)
        times.append(time.perf_counter() - t0)
    return times


def bench_qp(instances: int = 12, preset: str = "dataset", seed: int = 0, repeats: int = 3) -> dict:
    """Median solve time of ours (cold, warm) vs cvxopt dense (default and tight tolerances), same instances."""
    cfg, solver, prep = setup(preset, seed)
    allinst = collect_instances(solver, cfg, seed=seed)
    warm_ts = time_warm_solves(solver, allinst)
    picks = np.linspace(0, len(allinst) - 1, instances).round().astype(int)
    # make sure instances with binding constraints are included
    active = [i for i, a in enumerate(allinst) if solver.solve(*a, warm_start=False).active]
    picks = sorted(set(picks.tolist()) | set(active[: max(1, instances // 4)]))
    rows = []
    for i in picks:
        args = allinst[i]
        ours = _median_time(lambda args=args: solver.solve(*args, warm_start=False), repeats * 10)
        res = solver.solve(*args, warm_start=False)
        t0 = time.perf_counter()
        u_def, st_def = solve_cvxopt(solver.qp, *args, tol=1e-7, reltol=1e-6)  # cvxopt's default tolerances
        t_def = time.perf_counter() - t0
        t0 = time.perf_counter()
        u_tight, st_tight = solve_cvxopt(solver.qp, *args, tol=1e-10, reltol=1e-16)
        t_tight = time.perf_counter() - t0
        rows.append({"instance": int(i), "active": len(res.active), "ours_s": ours, "cvxopt_default_s": t_def,
                     "cvxopt_tight_s": t_tight, "err_vs_tight": float(np.abs(res.u - u_tight[:2]).max()),
                     "cvxopt_default_err_vs_tight": float(np.abs(u_def[:2] - u_tight[:2]).max()),
                     "status_tight": st_tight})
    med = lambda k: statistics.median(r[k] for r in rows)  # noqa: E731
    return {
        "preset": preset, "instances": len(rows), "with_active_constraints": sum(r["active"] > 0 for r in rows),
        "ours_cold_median_s": med("ours_s"), "ours_warm_median_s": statistics.median(warm_ts),
        "cvxopt_default_median_s": med("cvxopt_default_s"), "cvxopt_tight_median_s": med("cvxopt_tight_s"),
        "speedup_vs_cvxopt_default": med("cvxopt_default_s") / med("ours_s"),
        "speedup_vs_cvxopt_tight": med("cvxopt_tight_s") / med("ours_s"),
        "max_err_vs_tight": max(r["err_vs_tight"] for r in rows),
        "cvxopt_default_max_err_vs_tight": max(r["cvxopt_default_err_vs_tight"] for r in rows),
        "stats": solver.stats.as_dict(), **prep, "rows": rows,
    }


def bench_nnmpc(checkpoint: str | None = None, preset: str = "dataset", seed: int = 0, calls: int = 2000) -> dict:
    """Per-step inference time of the NNMPC (B=1, and amortised at B=1024) vs the QP (warm, per step)."""
    from mixed_traffic.controllers.deeplcc.nnmpc import NNMPC

    torch.set_num_threads(1)
    net = NNMPC.load(checkpoint) if checkpoint else NNMPC()
    cfg, solver, _ = setup(preset, seed)
    inst = collect_instances(solver, cfg, seconds=10.0, seed=seed)
    qp_ts = time_warm_solves(solver, inst)
    x1 = torch.as_tensor(np.concatenate(inst[len(inst) // 2])[None], dtype=torch.float32)
    xb = torch.as_tensor(np.stack([np.concatenate(a) for a in inst[:1024]]), dtype=torch.float32)
    with torch.inference_mode():
        for _ in range(50):
            net.forward_flat(x1)
        nn1 = _median_time(lambda: net.forward_flat(x1), calls)
        nnb = _median_time(lambda: net.forward_flat(xb), 50) / len(xb)
    qp = statistics.median(qp_ts)
    return {"qp_warm_median_s": qp, "nn_b1_median_s": nn1, "nn_batched_per_sample_s": nnb, "batch": len(xb),
            "speedup_b1": qp / nn1, "speedup_batched": qp / nnb, "torch_threads": torch.get_num_threads()}


def _print(res: dict, keys) -> None:
    print("| metric | value |\n|---|---|")
    for k in keys:
        v = res[k]
        print(f"| {k} | {v:.3g} |" if isinstance(v, float) else f"| {k} | {v} |")


def main_qp(argv=None) -> dict:
    """``mt-bench qp [--instances N] [--preset dataset|reference] [--seed S] [--out PATH]``."""
    ap = argparse.ArgumentParser(prog="mt-bench qp", description=main_qp.__doc__)
    ap.add_argument("--instances", type=int, default=12)
    ap.add_argument("--preset", default="dataset", choices=["dataset", "reference"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res = bench_qp(a.instances, a.preset, a.seed, a.repeats)
    _print(res, [k for k in res if k not in ("rows", "stats")])
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=2)
    return res


def main_nnmpc(argv=None) -> dict:
    """``mt-bench nnmpc [--checkpoint PATH] [--preset ...] [--out PATH]``."""
    ap = argparse.ArgumentParser(prog="mt-bench nnmpc", description=main_nnmpc.__doc__)
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--preset", default="dataset", choices=["dataset", "reference"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--calls", type=int, default=2000)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res = bench_nnmpc(a.checkpoint, a.preset, a.seed, a.calls)
    _print(res, list(res))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=2)
    return res




def model_mismatch(seed: int = 12345, preset: str = "dataset", scenarios=None) -> dict:
    """IDM humans driven by the QP built from OVM data (mismatch) vs from IDM data (matched)."""
    from mixed_traffic.controllers.deeplcc.closed_loop import evaluate

    out = {}
    idm = PlatoonConfig(hdv_model="idm")
    for data_model in ("ovm", "idm"):
        [h] = precollect(PlatoonConfig(hdv_model=data_model), generator=torch.Generator().manual_seed(seed))
        out[f"hankel_{data_model}"] = evaluate(QPController([DeepLCCSolver(h, QPParams.preset(preset))]), idm, scenarios)
    out["no_control"] = evaluate(lambda u, y, e: np.zeros((len(u), 2)), idm, scenarios)
    return out


def main_mismatch(argv=None) -> dict:
    """``python -m mixed_traffic.controllers.deeplcc.bench mismatch [--out PATH]``: IDM humans, OVM vs IDM data."""
    ap = argparse.ArgumentParser(prog="mismatch", description=main_mismatch.__doc__)
    ap.add_argument("--seed", type=int, default=12345)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res = model_mismatch(a.seed)
    print("| scenario | " + " | ".join(f"{k} cost / collision" for k in res) + " |")
    print("|---|" + "---|" * len(res))
    for sc in next(iter(res.values())):
        print(f"| {sc} | " + " | ".join(f"{r[sc]['cost']:.4g} / {int(r[sc]['collisions'])}" for r in res.values()) + " |")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=2)
    return res


if __name__ == "__main__":
    import sys

    {"qp": main_qp, "nnmpc": main_nnmpc, "mismatch": main_mismatch}[sys.argv[1]](sys.argv[2:])
