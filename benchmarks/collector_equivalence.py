"""Same learning curve with any collector: PPO trained at equal frames, per collector and seed.

Trains ``experiment=ring_lagrangian_ppo`` (small budget) once per ``(collector, seed)``
through ``mixed_traffic.training.train`` (the ``mt-train`` path) and compares the logged
curves of the training reward per step: the collectors agree "within noise" when the
gap between their seed-mean curves is of the size of the seed-to-seed spread of one
collector. ``ray`` starts a local Ray with ``--workers`` CPUs.

    python benchmarks/collector_equivalence.py --collectors single ray --seeds 0 1 \\
        --out benchmarks/results/collector_equivalence.json

Prints a Markdown table (final reward per step and cost, mean ± std over seeds; mean
absolute gap between the curves) and writes JSON with the curves.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import tempfile
from pathlib import Path


def curve(run_dir: Path, key: str) -> list[tuple[int, float]]:
    f = next(Path(run_dir).glob(f"logs/*/scalars/{key}.csv"))
    with open(f) as fh:
        return [(int(float(r[0])), float(r[1])) for r in csv.reader(fh) if r]


def mean_std(xs: list[float]) -> tuple[float, float]:
    return statistics.fmean(xs), statistics.pstdev(xs) if len(xs) > 1 else 0.0


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--collectors", nargs="+", default=["single", "ray"],
                   choices=["single", "multi_sync", "multi_async", "ray"])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--frames", type=int, default=65_536)
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--rollout-len", type=int, default=32)
    p.add_argument("--last", type=int, default=5, help="iterations averaged for the final figures")
    p.add_argument("--overrides", nargs="*", default=[], help="extra Hydra overrides for every run")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    from mixed_traffic.config import compose
    from mixed_traffic.training import train

    runs: dict[str, dict[int, dict]] = {}
    root = Path(tempfile.mkdtemp(prefix="mt_collector_equivalence_"))
    for kind in a.collectors:
        for seed in a.seeds:
            cfg = compose(["experiment=ring_lagrangian_ppo", f"seed={seed}", f"trainer.collector={kind}",
                           f"trainer.collector_workers={1 if kind == 'single' else a.workers}",
                           f"trainer.total_frames={a.frames}", f"trainer.num_envs={a.num_envs}",
                           f"trainer.rollout_len={a.rollout_len}", "trainer.progress=false",
                           "trainer.checkpoint_every=0", "logger=csv", "threads=1", *a.overrides])
            out = root / f"{kind}_seed{seed}"
            res = train(cfg, out_dir=out)
            r = {k: [v for _, v in curve(out, k)] for k in ("reward_per_step", "mean_violation", "lambda")}
            r["steps"] = [s for s, _ in curve(out, "reward_per_step")]
            r["wall_seconds"] = res["summary"]["wall_seconds"]
            runs.setdefault(kind, {})[seed] = r
            print(f"{kind} seed {seed}: final reward/step {statistics.fmean(r['reward_per_step'][-a.last:]):.4f} "
                  f"({r['wall_seconds']:.0f} s)", file=sys.stderr)
    rows = []
    for kind, by_seed in runs.items():
        fin = [statistics.fmean(r["reward_per_step"][-a.last:]) for r in by_seed.values()]
        cost = [statistics.fmean(r["mean_violation"][-a.last:]) for r in by_seed.values()]
        n = min(len(r["reward_per_step"]) for r in by_seed.values())
        mean_curve = [statistics.fmean(r["reward_per_step"][i] for r in by_seed.values()) for i in range(n)]
        seed_gap = (statistics.fmean(abs(x - y) for x, y in zip(*[r["reward_per_step"][:n] for r in by_seed.values()]))
                    if len(by_seed) == 2 else None)
        rows.append({"collector": kind, "final_reward_per_step": mean_std(fin), "final_mean_violation": mean_std(cost),
                     "mean_curve": mean_curve, "seed_to_seed_gap": seed_gap,
                     "wall_seconds": statistics.fmean(r["wall_seconds"] for r in by_seed.values())})
    ref = rows[0]["mean_curve"]
    for r in rows:
        n = min(len(ref), len(r["mean_curve"]))
        r["gap_to_" + rows[0]["collector"]] = statistics.fmean(abs(x - y) for x, y in zip(ref[:n], r["mean_curve"][:n]))
    lines = [f"| collector | final reward/step (last {a.last} it.) | final mean violation | curve gap to "
             f"{rows[0]['collector']} | seed-to-seed gap | wall s |", "|---|---|---|---|---|---|"]
    for r in rows:
        (m, s), (cm, cs) = r["final_reward_per_step"], r["final_mean_violation"]
        sg = "-" if r["seed_to_seed_gap"] is None else f"{r['seed_to_seed_gap']:.4f}"
        lines.append(f"| {r['collector']} | {m:.4f} ± {s:.4f} | {cm:.4f} ± {cs:.4f} | "
                     f"{r['gap_to_' + rows[0]['collector']]:.4f} | {sg} | {r['wall_seconds']:.0f} |")
    print("\n".join(lines))
    result = {"command": "python benchmarks/collector_equivalence.py " + " ".join(sys.argv[1:] if argv is None else argv),
              "rows": rows, "runs": runs}
    if a.out:
        Path(a.out).write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
