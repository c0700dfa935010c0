"""``mt-bench``: throughput benchmarks of the project's environments and controllers.

Subcommands:
  env     frames/s of the car-following envs: bare ``rollout`` with random actions and a
          TorchRL ``Collector`` with a TanhNormal actor, for several batch sizes;
          ``--backend sumo`` or ``both`` adds the SUMO ring (1 process and a 2-worker
          ``ParallelEnv``) and the torch/SUMO ratio.
  qp      DeeP-LCC QP solve time against a dense interior-point reference.
  nnmpc   NNMPC inference time against the QP.
  apg     seconds of one analytic-gradient window (forward through the env, backward) of an experiment,
          and the autograd nodes a step adds: what ``make run``'s first phase is made of.
  gauge   the machine's speed: a plain-torch IDM ring (22 cars, float32) stepped alone, at B = 1 and 1024.
          Timings of the other commands on two days compare only beside it.

Every figure is a median over ``--repeats`` runs measured in one process. Results are
printed as a Markdown table and, with ``--out``, written to JSON.

    mt-bench env --batch-sizes 1 64 1024 4096 --repeats 5
    mt-bench apg --windows 3 --repeats 3      # the default experiment (mt-main's)
    mt-bench gauge
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


def write_json(path: str | None, result: dict) -> None:
    """``result`` as JSON at ``path`` (``--out``), nothing where it is None."""
    if path:
        with open(path, "w") as f:
            json.dump(result, f, indent=2)


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
    write_json(a.out, result)
    return result


def autograd_nodes(loss: torch.Tensor) -> int:
    """The number of nodes of ``loss``'s backward graph (what ``backward`` walks)."""
    seen, stack = set(), [loss.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        stack.extend(f for f, _ in node.next_functions)
    return len(seen)


def bench_apg(overrides: list[str], windows: int, repeats: int) -> dict:
    """Median seconds of one analytic-gradient window of ``policy.apg.horizon`` steps (forward through the env and
    the chain, then backward), as :func:`~mixed_traffic.training.apg.apg_pretrain` runs it on the experiment's own
    env and rows, without the optimizer's step (its cost is a few small tensors); the first window of each repeat is
    a warm-up. Also the backward graph's nodes per env step."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mixed_traffic.config import compose
    from mixed_traffic.training.apg import apg_env, cut_graph, window_loss, window_settings
    from mixed_traffic.training.builders import make_transformed_env
    from mixed_traffic.training.on_policy import build_ppo

    cfg = compose([*overrides, "trainer.progress=false"])
    a = cfg.policy.apg
    window = window_settings(a)
    actor = build_ppo(cfg, make_transformed_env(cfg, num_envs=2, seed=int(cfg.seed)))[0]
    fwd, bwd, nodes = [], [], None
    for _ in range(repeats):
        env, j_ref = apg_env(cfg)
        td = env.reset()
        env.base_env.differentiable = True
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            for w in range(windows + 1):
                cut_graph(env)
                td = td.detach()
                t0 = time.perf_counter()
                loss, td, ended = window_loss(env, actor, td, a.horizon, j_ref, a.cost_coeff, **window)
                t1 = time.perf_counter()
                if nodes is None:
                    nodes = autograd_nodes(loss) / a.horizon
                loss.backward()
                t2 = time.perf_counter()
                actor.zero_grad(set_to_none=True)
                if w:
                    fwd.append(t1 - t0)
                    bwd.append(t2 - t1)
                if ended:
                    cut_graph(env)
                    td = env.reset()
        env.base_env.differentiable = False
        cut_graph(env)
        env.close()
    f, b = statistics.median(fwd), statistics.median(bwd)
    return {"experiment": cfg.name, "rows": a.num_envs, "horizon": a.horizon, "forward_s": f, "backward_s": b,
            "window_s": f + b, "nodes_per_step": nodes, "windows": len(fwd)}


def _idm_ring_step(x: torch.Tensor, v: torch.Tensor, length: float = 260.0, dt: float = 0.1):
    """One explicit-Euler step of 22 IDM humans on a ring (v0 30, T 1, a 1, b 1.5, s0 2, 5-m cars).

    Written out here rather than through :mod:`mixed_traffic.physics`: the gauge measures the machine, so it must
    stay the same operations whatever the project's laws become."""
    gap = (torch.roll(x, -1, 1) - x) % length - 5.0
    dv = v - torch.roll(v, -1, 1)
    s_star = 2.0 + v * 1.0 + v * dv / (2.0 * 1.5 ** 0.5)
    a = 1.0 - (v / 30.0) ** 4 - (s_star / gap) ** 2
    v_next = (v + a * dt).clamp_min(0.0)
    return (x + v_next * dt) % length, v_next


def bench_gauge(batch_sizes: list[int], steps: int, repeats: int) -> list[dict]:
    """Steps per second of :func:`_idm_ring_step` alone (plain torch, float32, one thread): a gauge of how fast the
    machine runs small tensor operations today, which is what the ring's training and evaluation are made of."""
    rows = []
    for batch in batch_sizes:
        x0 = torch.linspace(0.0, 250.0, 22).repeat(batch, 1)
        v0 = torch.full((batch, 22), 4.0)

        def run(x=x0, v=v0):
            for _ in range(steps):
                x, v = _idm_ring_step(x, v)

        median, rates = _median_rate(run, steps, repeats)
        rows.append({"batch": batch, "steps_per_s": median, "runs": rates})
    return rows


def main_apg(argv: list[str]) -> dict:
    p = argparse.ArgumentParser(prog="mt-bench apg", description="Seconds of one analytic-gradient window.")
    p.add_argument("overrides", nargs="*", help="Hydra overrides (default: mt-main's experiment)")
    p.add_argument("--windows", type=int, default=3, help="timed windows per repeat (after one warm-up)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--out", default=None, help="write the result as JSON here")
    a = p.parse_args(argv)
    for name in ("windows", "repeats", "threads"):
        if getattr(a, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(a, name)}")
    torch.set_num_threads(a.threads)
    from mixed_traffic.apps.main_job import with_default_experiment

    r = bench_apg(with_default_experiment(a.overrides), a.windows, a.repeats)
    r["command"] = "mt-bench apg " + " ".join(argv)
    print(f"| experiment | rows x steps | forward s | backward s | window s | nodes per step |\n|---|---|---|---|---|---|\n"
          f"| {r['experiment']} | {r['rows']} x {r['horizon']} | {r['forward_s']:.3f} | {r['backward_s']:.3f} | "
          f"{r['window_s']:.3f} | {r['nodes_per_step']:.0f} |")
    write_json(a.out, r)
    return r


def main_gauge(argv: list[str]) -> dict:
    p = argparse.ArgumentParser(prog="mt-bench gauge", description="The machine's speed at small tensor operations.")
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 1024])
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default=None, help="write the results as JSON here")
    a = p.parse_args(argv)
    for name in ("steps", "repeats"):
        if getattr(a, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(a, name)}")
    if any(b < 1 for b in a.batch_sizes):
        p.error(f"--batch-sizes must all be >= 1, got {a.batch_sizes}")
    torch.set_num_threads(1)
    rows = bench_gauge(a.batch_sizes, a.steps, a.repeats)
    print("| B | IDM ring steps/s |\n|---|---|\n" + "\n".join(f"| {r['batch']} | {r['steps_per_s']:,.0f} |" for r in rows))
    result = {"command": "mt-bench gauge " + " ".join(argv), "rows": rows, "torch": torch.__version__}
    write_json(a.out, result)
    return result


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    local = {"env": main_env, "apg": main_apg, "gauge": main_gauge}
    commands = [*local, *EXTERNAL]
    if not argv or argv[0] not in commands:
        print(__doc__)
        raise SystemExit(f"mt-bench: choose a subcommand from {commands}" if argv else 0)
    if argv[0] in local:
        local[argv[0]](argv[1:])
        return
    module, fn = EXTERNAL[argv[0]].split(":")
    getattr(importlib.import_module(module), fn)(argv[1:])


if __name__ == "__main__":
    main()
