"""Evaluate any intersection policy on a fixed, seeded test set and report per-behaviour metrics.

Every controller (NMPC, LPPO actors, residual MPC) is a TensorDict module reading
``observation`` (plus whatever its transforms need) and writing ``action``; this harness
runs it on the same test episodes (``make_test_set``: 80 episodes of each of straight, left,
right and the held-out zig-zag by default, 320 in all), one batch row per episode, until
every episode has ended once.

>>> from mixed_traffic.intersection.evaluate import evaluate_policy
>>> from mixed_traffic.intersection.nmpc import make_nmpc_policy
>>> res = evaluate_policy(make_nmpc_policy(), n_per_behaviour=2)
>>> sorted(res.table["overall"])[:3]
['collision_rate', 'crossing_time_s', 'episodes']
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from mixed_traffic.envs.intersection import IntersectionEnv
from mixed_traffic.envs.intersection_agents import (
    BEHAVIOUR_NAMES,
    BEHAVIOURS,
    TRAIN_BEHAVIOURS,
    AgentTrajectories,
    make_test_set,
)

METRICS = ("episodes", "success_rate", "collision_rate", "timeout_rate", "out_of_bounds_rate",
           "crossing_time_s", "return", "cost")


@dataclass
class EvalResult:
    """Per-episode outcomes and the aggregated per-behaviour ``table`` (``{name: {metric: value}}``)."""

    behaviour: np.ndarray
    success: np.ndarray
    collision: np.ndarray
    timeout: np.ndarray
    out_of_bounds: np.ndarray
    steps: np.ndarray
    ret: np.ndarray
    cost: np.ndarray
    table: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    frames: dict = field(default_factory=dict)  # episode -> dict of arrays for rendering

    def to_json(self) -> str:
        return json.dumps({"table": self.table, "extra": self.extra}, indent=2)


def summarise(behaviour, success, collision, timeout, oob, steps, ret, cost, dt=0.1) -> dict:
    """The per-behaviour table: rates, mean crossing time of the successful episodes, mean return."""
    table = {}
    groups = [(BEHAVIOUR_NAMES[b], behaviour == b) for b in sorted(set(behaviour.tolist()))]
    groups.append(("overall", np.ones_like(behaviour, dtype=bool)))
    for name, m in groups:
        n = int(m.sum())
        succ = m & success
        table[name] = {
            "episodes": n,
            "success_rate": float(success[m].mean()),
            "collision_rate": float(collision[m].mean()),
            "timeout_rate": float(timeout[m].mean()),
            "out_of_bounds_rate": float(oob[m].mean()),
            "crossing_time_s": float(steps[succ].mean() * dt) if succ.any() else float("nan"),
            "return": float(ret[m].mean()),
            "cost": float(cost[m].mean()),
        }
    return table


def make_eval_env(test_set: AgentTrajectories, transform=None, max_steps: int = 500) -> EnvBase:
    """The env the harness runs: one row per test episode, episodes assigned in order."""
    env = IntersectionEnv(batch_size=len(test_set), agent_trajectories=test_set, agent_sampling="sequential",
                          max_steps=max_steps, start_noise=0.0)
    if transform is not None:
        env = TransformedEnv(env, transform)
    return env


@torch.no_grad()
def evaluate_policy(policy, *, n_per_behaviour: int = 80, seed: int = 2024, behaviours=BEHAVIOURS,
                    test_set: AgentTrajectories | None = None, transform=None, max_steps: int = 500,
                    record: list[int] | None = None, chunk: int | None = None) -> EvalResult:
    """Run ``policy`` once on every test episode (deterministic exploration) and aggregate.

    Args:
        policy: a TensorDict module writing ``action`` (e.g. ``make_nmpc_policy()`` or an actor).
        n_per_behaviour, seed, behaviours: define the test set (ignored if ``test_set`` is given).
        transform: a TorchRL transform to wrap the env with (e.g. the residual-action or
            barrier-force transform the policy was trained with).
        record: test-episode indices whose trajectories are kept in ``result.frames`` for GIFs.
        chunk: evaluate this many episodes at a time (default: all at once).
    """
    if test_set is None:
        test_set = make_test_set(n_per_behaviour, seed=seed, horizon=max_steps, behaviours=behaviours)
    n = len(test_set)
    chunk = chunk or n
    outs = {k: np.zeros(n, dtype=bool) for k in ("success", "collision", "timeout", "out_of_bounds")}
    steps, ret, cost = np.zeros(n), np.zeros(n), np.zeros(n)
    frames = {}
    record = set(record or [])
    for start in range(0, n, chunk):
        idx = torch.arange(start, min(n, start + chunk))
        sub = test_set.subset(idx)
        env = make_eval_env(sub, transform=transform, max_steps=max_steps)
        ctrl = getattr(policy, "module", None)
        if hasattr(ctrl, "reset"):
            ctrl.reset()
        if hasattr(ctrl, "set_rows"):
            ctrl.set_rows(None)
        m = len(idx)
        done = torch.zeros(m, dtype=torch.bool)
        rec = {int(i): {"ego": [], "agent": [], "agent_obs": [], "sigma": []} for i in idx.tolist() if int(i) in record}
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            td = env.reset()
            for i in rec:
                _record(rec[i], td, i - start)
            for _ in range(max_steps):
                alive_idx = torch.nonzero(~done).squeeze(-1)
                if hasattr(ctrl, "set_rows"):
                    ctrl.set_rows(alive_idx.tolist())
                if len(alive_idx) < m:  # only the running episodes ask the policy
                    sub_td = policy(td[alive_idx].clone())
                    action = torch.zeros_like(td["action"]) if "action" in td.keys() else torch.zeros(
                        m, *sub_td["action"].shape[1:], dtype=sub_td["action"].dtype)
                    action[alive_idx] = sub_td["action"]
                    td.set("action", action)
                else:
                    td = policy(td)
                td = env.step(td)
                nxt = td["next"]
                alive = ~done
                r = nxt["reward"].squeeze(-1)
                c = nxt["cost"].squeeze(-1)
                ret[start:start + m][alive.numpy()] += r[alive].numpy()
                cost[start:start + m][alive.numpy()] += c[alive].numpy()
                new_done = nxt["done"].squeeze(-1) & alive
                for i in rec:
                    if alive[i - start]:
                        _record(rec[i], nxt, i - start)
                if new_done.any():
                    nd = new_done.numpy()
                    sl = slice(start, start + m)
                    outs["success"][sl][nd] = nxt["success"].squeeze(-1).numpy()[nd]
                    outs["collision"][sl][nd] = nxt["collision"].squeeze(-1).numpy()[nd]
                    outs["out_of_bounds"][sl][nd] = nxt["out_of_bounds"].squeeze(-1).numpy()[nd]
                    outs["timeout"][sl][nd] = nxt["truncated"].squeeze(-1).numpy()[nd]
                    steps[sl][nd] = nxt["step_count"].squeeze(-1).numpy()[nd]
                done = done | new_done
                if done.all():
                    break
                td = step_mdp(td, keep_other=True)
        for i, r in rec.items():
            frames[i] = {k: np.asarray(v) for k, v in r.items()}
            frames[i]["behaviour"] = BEHAVIOUR_NAMES[int(test_set.behaviour[i])]
    beh = test_set.behaviour.numpy()
    table = summarise(beh, outs["success"], outs["collision"], outs["timeout"], outs["out_of_bounds"], steps, ret, cost)
    res = EvalResult(beh, outs["success"], outs["collision"], outs["timeout"], outs["out_of_bounds"], steps, ret, cost,
                     table=table, frames=frames)
    ctrl = getattr(policy, "module", None)
    if hasattr(ctrl, "stats"):
        res.extra["nmpc"] = ctrl.stats.summary()
    return res


def _record(buf: dict, td: TensorDictBase, row: int):
    buf["ego"].append(td["ego", "pos"][row].numpy().copy())
    buf["agent"].append(td["agent", "true_pos"][row].numpy().copy())
    buf["agent_obs"].append(td["observation"][row, 2:4].numpy().copy())
    buf["sigma"].append(td["observation"][row, 6:8].numpy().copy())


def format_table(table: dict, title: str = "") -> str:
    """Markdown table of :func:`summarise` output."""
    head = "| behaviour | episodes | success | collision | timeout | out of bounds | crossing time (s) | return | cost |"
    lines = ([f"**{title}**", ""] if title else []) + [head, "|" + "---|" * 9]
    for name, row in table.items():
        lines.append(f"| {name} | {row['episodes']} | {row['success_rate']:.1%} | {row['collision_rate']:.1%} | "
                     f"{row['timeout_rate']:.1%} | {row['out_of_bounds_rate']:.1%} | {row['crossing_time_s']:.2f} | "
                     f"{row['return']:.1f} | {row['cost']:.1f} |")
    return "\n".join(lines)


def write_gifs(result: EvalResult, out_dir: str | Path, prefix: str = "episode") -> list[Path]:
    """Write one GIF per recorded episode of ``result`` (see :mod:`mixed_traffic.intersection.render`)."""
    from mixed_traffic.intersection.render import episode_gif

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, fr in sorted(result.frames.items()):
        outcome = ("success" if result.success[i] else "collision" if result.collision[i]
                   else "timeout" if result.timeout[i] else "out of bounds")
        p = out_dir / f"{prefix}_{i:03d}_{fr['behaviour']}.gif"
        episode_gif(fr, p, title=f"{prefix} {i} ({fr['behaviour']}): {outcome}")
        paths.append(p)
    return paths


def outcomes(res: EvalResult) -> dict:
    """Per-episode outcome codes: ``S`` success, ``C`` collision, ``T`` timeout, ``O`` out of bounds."""
    codes = np.where(res.success, "S", np.where(res.collision, "C", np.where(res.timeout, "T", "O")))
    return {"codes": "".join(codes.tolist()), "steps": res.steps.astype(int).tolist()}


def test_sets(eval_cfg) -> dict[str, AgentTrajectories]:
    """The test sets of an evaluation config (``n = eval.episodes``, seeds from ``eval.seed``; test split).

    * ``standard``: ``n`` episodes of each of straight, left, right and the held-out zig-zag (4n);
    * ``reactive``: agents that answer the ego's motion, ``ceil(2.5 n / 3)`` per training route (>= 2.5n);
    * ``stop_in_zone``: agents that stop with their centre just past the ego's line for 2-8 s before
      going on, ``ceil(2.5 n / 2)`` per crossing route (straight, left); never used in training.
    """
    n, seed = int(eval_cfg.episodes), int(eval_cfg.seed)
    return {"standard": make_test_set(n, seed=seed),
            "reactive": make_test_set(math.ceil(2.5 * n / 3), seed=seed + 1, behaviours=TRAIN_BEHAVIOURS,
                                      style="reactive"),
            "stop_in_zone": make_test_set(math.ceil(2.5 * n / 2), seed=seed + 2, behaviours=("straight", "left"),
                                          style="stop_in_zone")}


def load_policy(checkpoint):
    """``(policy, make_transform, run_cfg)`` of a trained run: the actor and a factory of the
    run's env-side transforms without the training-only ones (``None`` when it has none)."""
    from torchrl.envs import Compose

    from mixed_traffic.evaluation.policies import checkpoint_config, policy_factory_from_state
    from mixed_traffic.training.builders import TRAINING_ONLY, TRANSFORMS, make_transformed_env

    run_cfg, state = checkpoint_config(checkpoint)
    env = make_transformed_env(run_cfg, num_envs=1, seed=0, without=TRAINING_ONLY)
    policy = policy_factory_from_state(run_cfg, state)(env)
    chain = [n for n in run_cfg.transforms.chain if n not in TRAINING_ONLY]
    make = (lambda: Compose(*[TRANSFORMS[n](run_cfg.transforms, None) for n in chain])) if chain else (lambda: None)
    return policy, make, run_cfg


def evaluate_run(cfg, out_dir: str | Path, *, checkpoint=None, controller: str | None = None) -> dict:
    """``mt-eval`` / ``mt-train`` evaluation of an intersection policy: every test set, ``eval.json`` + ``report.md``.

    ``checkpoint`` (a run's ``final.pt`` or directory) or ``controller="nmpc"``.
    """
    from mixed_traffic.intersection.nmpc import make_nmpc_policy

    if controller is not None and controller != "nmpc":
        raise ValueError(f"controller: {controller!r} is invalid for the intersection; allowed: 'nmpc'")
    if checkpoint is not None:
        policy, make_transform, _ = load_policy(checkpoint)
        label = str(checkpoint)
    else:
        policy, make_transform, label = make_nmpc_policy(), (lambda: None), "nmpc"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    report = {"name": str(cfg.name), "policy": label, "sets": {}}
    md = [f"# {cfg.name}: {label}", ""]
    for name, ts in test_sets(cfg.eval).items():
        res = evaluate_policy(policy, test_set=ts, transform=make_transform())
        report["sets"][name] = {"table": res.table, "outcomes": outcomes(res), **res.extra}
        md += [format_table(res.table, title=f"{name} ({len(ts)} episodes)"), ""]
    report["eval"] = report["sets"]["standard"]["table"]
    report["outcomes"] = report["sets"]["standard"]["outcomes"]
    paths = {"json": out_dir / "eval.json", "md": out_dir / "report.md"}
    paths["json"].write_text(json.dumps(report, indent=2))
    paths["md"].write_text("\n".join(md))
    report["paths"] = paths
    return report


__all__ = ["EvalResult", "evaluate_run", "load_policy", "test_sets", "outcomes", "evaluate_policy", "summarise", "format_table", "write_gifs", "make_eval_env", "METRICS"]
