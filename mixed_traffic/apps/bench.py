"""``mt-bench``: throughput benchmarks of the project's environments and controllers.

Subcommands:
  env     frames/s of the car-following envs: bare ``rollout`` with random actions and a
          TorchRL ``Collector`` with a TanhNormal actor, for several batch sizes;
          ``--backend sumo`` or ``both`` adds the SUMO ring (1 process and a 2-worker
          ``ParallelEnv``) and the torch/SUMO ratio.
  qp      DeeP-LCC QP solve time against a dense interior-point reference.
  nnmpc   NNMPC inference time against the QP.

Every figure is a median over ``--repeats`` runs measured in one process. Results are
printed as a Markdown table and, with ``--out``, written to JSON.

    mt-bench env --batch-sizes 1 64 1024 4096 --repeats 5
"""

from __future__ import annotations

import argparse
import cProfile
import importlib
import io
import json
import pstats
import statistics
import sys
import time
from functools import partial

import torch

EXTERNAL = {
    "qp": "mixed_traffic.controllers.deeplcc.bench:main_qp",
    "nnmpc": "mixed_traffic.controllers.deeplcc.bench:main_nnmpc",
}


def _median_rate(fn, frames: int, repeats: int) -> tuple[float, list[float]]:
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(frames / (time.perf_counter() - t0))
    return statistics.median(rates), rates


def tanh_normal_actor(env):
    """A small TanhNormal actor over the env's observation, as used in training."""
    from tensordict.nn import NormalParamExtractor, TensorDictModule
    from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

    spec = env.action_spec_unbatched
    n_obs = env.observation_spec["observation"].shape[-1]
    net = torch.nn.Sequential(MLP(in_features=n_obs, out_features=2 * spec.shape[-1], num_cells=[64, 64]),
                              NormalParamExtractor())
    module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(module, in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
                              distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
                              return_log_prob=True)


def bench_torch(scenario: str, batch_sizes: list[int], steps: int, repeats: int, collector_steps: int | None
                ) -> list[dict]:
    from torchrl.collectors import Collector

    from mixed_traffic import make_env

    rows = []
    for B in batch_sizes:
        env = make_env(scenario, batch_size=B, seed=0)
        T = steps
        env.rollout(5, break_when_any_done=False)
        med, _ = _median_rate(lambda env=env, T=T: env.rollout(T, break_when_any_done=False), B * T, repeats)
        row = {"backend": "torch", "scenario": scenario, "batch": B, "rollout_fps": med}
        if collector_steps:
            actor = tanh_normal_actor(env)
            fpb = B * collector_steps
            col = Collector(env, actor, frames_per_batch=fpb, total_frames=-1, auto_register_policy_transforms=False)
            it = iter(col)
            next(it)
            med_c, _ = _median_rate(lambda it=it: next(it), fpb, repeats)
            col.shutdown()
            row["collector_fps"] = med_c
        rows.append(row)
        print(f"  torch B={B:5d}: rollout {row['rollout_fps']:,.0f} frames/s"
              + (f", collector {row['collector_fps']:,.0f} frames/s" if collector_steps else ""), file=sys.stderr)
    return rows


def bench_sumo(steps: int, repeats: int, workers: tuple[int, ...] = (1, 2)) -> list[dict]:
    from torchrl.envs import ParallelEnv

    from mixed_traffic import make_env

    rows = []
    for w in workers:
        if w == 1:
            env = make_env("ring", backend="sumo", seed=0)
        else:
            env = ParallelEnv(w, partial(make_env, "ring", backend="sumo"), mp_start_method="spawn")
            env.set_seed(0)
        env.rollout(5, break_when_any_done=False)
        med, _ = _median_rate(lambda env=env: env.rollout(steps, break_when_any_done=False), w * steps, repeats)
        env.close()
        rows.append({"backend": "sumo", "scenario": "ring", "workers": w, "rollout_fps": med})
        print(f"  sumo workers={w}: rollout {med:,.0f} frames/s", file=sys.stderr)
    return rows


def profile_rollout(scenario: str, batch: int, steps: int) -> str:
    from mixed_traffic import make_env

    env = make_env(scenario, batch_size=batch, seed=0)
    env.rollout(5, break_when_any_done=False)
    prof = cProfile.Profile()
    prof.enable()
    env.rollout(steps, break_when_any_done=False)
    prof.disable()
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(15)
    return buf.getvalue()


def markdown(rows: list[dict]) -> str:
    lines = ["| backend | B / workers | rollout frames/s | collector frames/s |", "|---|---|---|---|"]
    for r in rows:
        size = r.get("batch", r.get("workers"))
        col = f"{r['collector_fps']:,.0f}" if "collector_fps" in r else "-"
        lines.append(f"| {r['backend']} | {size} | {r['rollout_fps']:,.0f} | {col} |")
    return "\n".join(lines)


def main_env(argv: list[str]) -> dict:
    p = argparse.ArgumentParser(prog="mt-bench env", description="Environment throughput (frames/s).")
    p.add_argument("--scenario", default="ring", choices=["ring", "deeplcc"])
    p.add_argument("--backend", default="torch", choices=["torch", "sumo", "both"])
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 64, 1024, 4096])
    p.add_argument("--steps", type=int, default=200, help="env steps per timed rollout / collector batch (torch)")
    p.add_argument("--collector-steps", type=int, default=32, help="env steps per collector batch (frames = B x this)")
    p.add_argument("--sumo-steps", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-collector", action="store_true")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--profile", action="store_true", help="print where the time goes at the largest B")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    a = p.parse_args(argv)
    for name in ("repeats", "steps", "collector_steps", "sumo_steps", "threads"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if any(b < 1 for b in a.batch_sizes):
        p.error(f"--batch-sizes must all be >= 1, got {a.batch_sizes}")
    torch.set_num_threads(a.threads)
    rows: list[dict] = []
    if a.backend in ("torch", "both"):
        rows += bench_torch(a.scenario, a.batch_sizes, a.steps, a.repeats,
                            None if a.no_collector else a.collector_steps)
    if a.backend in ("sumo", "both"):
        rows += bench_sumo(a.sumo_steps, a.repeats)
    result = {"command": "mt-bench env " + " ".join(argv), "rows": rows, "torch": torch.__version__}
    torch_1024 = [r for r in rows if r["backend"] == "torch" and r.get("batch") == 1024]
    sumo_1 = [r for r in rows if r["backend"] == "sumo" and r["workers"] == 1]
    print(markdown(rows))
    if torch_1024 and sumo_1:
        result["torch_over_sumo"] = torch_1024[0]["rollout_fps"] / sumo_1[0]["rollout_fps"]
        print(f"\ntorch (B=1024) / SUMO (1 process) rollout ratio: {result['torch_over_sumo']:,.0f}x")
    if a.profile and a.backend != "sumo":
        result["profile"] = profile_rollout(a.scenario, max(a.batch_sizes), 100)
        print(result["profile"])
    if a.out:
        with open(a.out, "w") as f:
            json.dump(result, f, indent=2)
    return result


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    commands = ["env", *EXTERNAL]
    if not argv or argv[0] not in commands:
        print(__doc__)
        raise SystemExit(f"mt-bench: choose a subcommand from {commands}" if argv else 0)
    if argv[0] == "env":
        main_env(argv[1:])
        return
    module, fn = EXTERNAL[argv[0]].split(":")
    getattr(importlib.import_module(module), fn)(argv[1:])


if __name__ == "__main__":
    main()
