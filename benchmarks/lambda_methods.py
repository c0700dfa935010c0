"""Lagrange multiplier updates side by side: lambda's path and the constraint over training.

Reads the CSV scalars of ``mt-train`` runs (``<run>/logs/<name>/scalars/{lambda,mean_violation,
safety_clip_rate,collisions,reward_per_step}.csv``) and reports, per run and per method over
seeds: lambda at the end, its oscillation (std of lambda over the second half of training and
the number of direction changes of its batch-to-batch steps), the priced cost over the second
half (mean, and the share of batches above the budget) and the training collisions. Used in
``docs/results.md``::

    for m in pid dual_ascent; do for s in 0 1 2; do
      mt-train experiment=ring_lagrangian_ppo seed=$s loss.lambda_method=$m eval.after_train=false \\
               hydra.run.dir=outputs/runs/lam_${m}_s$s; done; done
    python benchmarks/lambda_methods.py outputs/runs/lam_*_s* --budget 0.01
"""

from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

import yaml


def _series(run: Path, name: str) -> list[float]:
    files = sorted(run.glob(f"logs/*/scalars/{name}.csv"))
    if not files:
        raise FileNotFoundError(f"{run}: no logs/*/scalars/{name}.csv; allowed: an mt-train run directory "
                                "(logger=csv)")
    with files[0].open() as f:
        return [float(row[1]) for row in csv.reader(f) if len(row) >= 2]


def summarise(run: Path, budget: float) -> dict:
    lam, cost = _series(run, "lambda"), _series(run, "mean_violation")
    clip, coll = _series(run, "safety_clip_rate"), _series(run, "collisions")
    half = len(lam) // 2
    steps = [b - a for a, b in zip(lam[half:], lam[half + 1:])]
    flips = sum(1 for a, b in zip(steps, steps[1:]) if a * b < 0)
    cfg = yaml.safe_load((run / "config.yaml").read_text()) if (run / "config.yaml").exists() else {}
    return {"run": run.name, "method": (cfg.get("loss") or {}).get("lambda_method", "?"), "seed": cfg.get("seed"),
            "lambda_end": lam[-1], "lambda_max": max(lam), "lambda_std_2nd_half": statistics.pstdev(lam[half:]),
            "lambda_direction_changes_2nd_half": flips, "cost_2nd_half": statistics.fmean(cost[half:]),
            "share_above_budget_2nd_half": sum(c > budget for c in cost[half:]) / max(1, len(cost) - half),
            "clip_rate_2nd_half": statistics.fmean(clip[half:]), "training_collisions": sum(coll)}


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--budget", type=float, default=0.01, help="the cost limit (loss.violation_tolerance)")
    a = ap.parse_args(argv)
    rows = [summarise(r, a.budget) for r in a.runs]
    keys = ["method", "seed", "lambda_end", "lambda_max", "lambda_std_2nd_half", "lambda_direction_changes_2nd_half",
            "cost_2nd_half", "share_above_budget_2nd_half", "clip_rate_2nd_half", "training_collisions"]
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in sorted(rows, key=lambda r: (r["method"], r["seed"] if r["seed"] is not None else -1)):
        print("| " + " | ".join(f"{r[k]:.3g}" if isinstance(r[k], float) else str(r[k]) for k in keys) + " |")
    return rows


if __name__ == "__main__":
    main()
