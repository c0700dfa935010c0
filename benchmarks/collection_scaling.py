"""Collection frames/s of the training collectors, one process against worker processes, side by side.

Each configuration is the training path itself: the config composed by Hydra (the
experiment's transform chain, its actor), ``mixed_traffic.training.builders.make_collector``
with ``trainer.collector=single`` or ``multi_sync`` (``collector_workers`` processes, each
stepping ``num_envs / workers`` rows; on SUMO one simulation per process). Only
collection is timed (``next(collector)``), no learning.

Besides frames per wall-clock second, the CPU time of every process involved (this one
and the collector's workers, psutil) gives frames per CPU-second: on a machine where
other work holds the cores, wall-clock ratios say little (Linux shares the CPU between
sessions, so extra worker processes of one session gain nothing while others run);
``workers x`` the CPU-efficiency ratio bounds the speedup on idle cores ("idle-core bound").

All collectors are built first and then measured in interleaved rounds (round r times
every configuration once), so a load change on a shared machine hits all of them alike;
the figures are medians over the rounds. ``multi_async`` keeps collecting between calls,
so it is measured on its own after the interleaved rounds (``--async``).

    python benchmarks/collection_scaling.py --rounds 5 --out benchmarks/results/collection_scaling.json

Prints a Markdown table (frames/s and the ratio to one process) and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import torch

SUMO = ["experiment=ring_lagrangian_ppo", "env.backend=sumo", "env.overrides.init_spacing_range=null"]
TORCH = ["experiment=ring_lagrangian_ppo"]


def configurations(sumo_steps: int, torch_rows: int, torch_steps: int, workers: int) -> list[dict]:
    w = f"trainer.collector_workers={workers}"
    return [
        {"name": "sumo, 1 process", "backend": "sumo", "workers": 1,
         "overrides": SUMO + ["trainer.num_envs=1", f"trainer.rollout_len={sumo_steps}"]},
        {"name": f"sumo, multi_sync {workers} workers", "backend": "sumo", "workers": workers,
         "overrides": SUMO + ["trainer.collector=multi_sync", w, f"trainer.num_envs={workers}",
                              f"trainer.rollout_len={sumo_steps}"]},
        {"name": f"torch B={torch_rows}, 1 process", "backend": "torch", "workers": 1,
         "overrides": TORCH + [f"trainer.num_envs={torch_rows}", f"trainer.rollout_len={torch_steps}"]},
        {"name": f"torch B={torch_rows}, multi_sync {workers} workers", "backend": "torch", "workers": workers,
         "overrides": TORCH + ["trainer.collector=multi_sync", w, f"trainer.num_envs={torch_rows}",
                               f"trainer.rollout_len={torch_steps}"]},
    ]


def build(overrides: list[str]):
    from mixed_traffic.config import compose
    from mixed_traffic.training import check_config
    from mixed_traffic.training.builders import collector_rows, make_collector, make_transformed_env
    from mixed_traffic.training.on_policy import build_ppo

    cfg = compose(overrides + ["threads=1"])
    check_config(cfg)
    torch.manual_seed(cfg.seed)
    env = make_transformed_env(cfg, num_envs=collector_rows(cfg), seed=cfg.seed)
    actor, *_ = build_ppo(cfg, env)
    collector, fpb, _ = make_collector(cfg, env, actor)
    if cfg.trainer.collector != "single":
        env.close()  # the workers have their own envs; a SUMO spec env would hold this process's libsumo
    return env, collector, iter(collector), fpb


def cpu_seconds(procs) -> float:
    """User + system CPU time of these processes so far (psutil)."""
    total = 0.0
    for p in procs:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except Exception:  # a process that is gone
            pass
    return total


def processes(collector) -> list:
    """This process and the collector's worker processes (``collector.procs`` of the multi-process collectors)."""
    import psutil

    return [psutil.Process()] + [psutil.Process(p.pid) for p in getattr(collector, "procs", []) or []]


def time_batches(it, fpb: int, batches: int, procs) -> tuple[float, float]:
    """(frames per wall-clock second, frames per CPU-second of all the processes involved)."""
    c0, t0 = cpu_seconds(procs), time.perf_counter()
    for _ in range(batches):
        next(it)
    wall, cpu = time.perf_counter() - t0, cpu_seconds(procs) - c0
    return batches * fpb / wall, batches * fpb / max(cpu, 1e-9)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rounds", type=int, default=5, help="interleaved measurement rounds (median over them)")
    p.add_argument("--batches", type=int, default=3, help="collector batches timed per configuration and round")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--sumo-steps", type=int, default=200, help="SUMO: env steps per row and batch")
    p.add_argument("--torch-rows", type=int, default=256, help="torch: rows in all (split over the workers)")
    p.add_argument("--torch-steps", type=int, default=16, help="torch: env steps per row and batch")
    p.add_argument("--only", choices=["sumo", "torch"], default=None)
    p.add_argument("--async", dest="run_async", action="store_true", help="also time multi_async (on its own)")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    a = p.parse_args(argv)
    for name in ("rounds", "batches", "workers", "sumo_steps", "torch_rows", "torch_steps"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if a.torch_rows % a.workers:
        p.error(f"--torch-rows ({a.torch_rows}) must be a multiple of --workers ({a.workers})")
    torch.set_num_threads(1)
    confs = [c for c in configurations(a.sumo_steps, a.torch_rows, a.torch_steps, a.workers)
             if a.only in (None, c["backend"])]
    built = []
    # multi-process first: their spec env (closed once built) needs this process's libsumo for a moment
    for c in sorted(confs, key=lambda c: -c["workers"]):
        print(f"building {c['name']} ...", file=sys.stderr)
        env, col, it, fpb = build(c["overrides"])
        next(it)  # warm-up: first batch (workers started, envs reset)
        built.append((c, env, col, it, fpb, processes(col)))
    rates: dict[str, list[float]] = {c["name"]: [] for c in confs}
    cpu_rates: dict[str, list[float]] = {c["name"]: [] for c in confs}
    built.sort(key=lambda b: confs.index(b[0]))
    for r in range(a.rounds):
        for c, _, _, it, fpb, procs in built:
            fps, fpcs = time_batches(it, fpb, a.batches, procs)
            rates[c["name"]].append(fps)
            cpu_rates[c["name"]].append(fpcs)
        print(f"round {r + 1}/{a.rounds}: " + ", ".join(f"{k} {v[-1]:,.0f}" for k, v in rates.items()), file=sys.stderr)
    for _, env, col, _, _, _ in built:
        col.shutdown()
        if not env.is_closed:
            env.close()
    if a.run_async and a.only != "sumo":
        c = {"name": f"torch B={a.torch_rows}, multi_async {a.workers} workers", "backend": "torch",
             "workers": a.workers, "overrides": TORCH + ["trainer.collector=multi_async",
                                                         f"trainer.collector_workers={a.workers}",
                                                         f"trainer.num_envs={a.torch_rows}",
                                                         f"trainer.rollout_len={a.torch_steps}"]}
        env, col, it, fpb = build(c["overrides"])
        next(it)
        procs = processes(col)
        got = [time_batches(it, fpb, a.batches * a.workers, procs) for _ in range(a.rounds)]
        rates[c["name"]], cpu_rates[c["name"]] = [g[0] for g in got], [g[1] for g in got]
        col.shutdown()
        env.close()
        confs.append(c)
    rows = []
    base, base_cpu = {}, {}
    for c in confs:
        med, med_cpu = statistics.median(rates[c["name"]]), statistics.median(cpu_rates[c["name"]])
        if c["workers"] == 1:
            base[c["backend"]], base_cpu[c["backend"]] = med, med_cpu
        rows.append({"name": c["name"], "backend": c["backend"], "workers": c["workers"], "median_fps": med,
                     "rounds_fps": rates[c["name"]], "median_frames_per_cpu_second": med_cpu,
                     "rounds_frames_per_cpu_second": cpu_rates[c["name"]], "overrides": c["overrides"]})
    for r in rows:
        r["speedup"] = r["median_fps"] / base[r["backend"]] if r["backend"] in base else None
        # with `workers` idle cores the workers step in parallel: this bounds the wall-clock speedup
        r["idle_bound"] = (r["workers"] * r["median_frames_per_cpu_second"] / base_cpu[r["backend"]]
                           if r["backend"] in base_cpu else None)
    lines = ["| configuration | frames/s (median) | vs 1 process | frames per CPU-second | idle-core bound |",
             "|---|---|---|---|---|"]
    for r in rows:
        ratio = "-" if r["speedup"] is None else f"{r['speedup']:.2f}x"
        bound = "-" if r["idle_bound"] is None else f"{min(r['idle_bound'], r['workers']):.2f}x"
        lines.append(f"| {r['name']} | {r['median_fps']:,.0f} | {ratio} | {r['median_frames_per_cpu_second']:,.0f} "
                     f"| {bound} |")
    print("\n".join(lines))
    result = {"command": "python benchmarks/collection_scaling.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "rows": rows, "cpus": os.cpu_count(),
              "machine": platform.platform(), "torch": torch.__version__}
    if a.out:
        with open(a.out, "w") as f:
            json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
