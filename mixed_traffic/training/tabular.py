"""Tabular Q-learning on the discretised ring (the seed's first baseline).

The table is sparse: only visited states get a row. A state is the observation binned
into ``state_bins`` per dimension (uniform over [0, 1]: the seed observation
``[v/30, p/L]``), packed into one int64 key; rows are kept sorted by key so a batch
of lookups is one ``searchsorted``. Actions are ``action_bins`` accelerations evenly
spaced over the CAV bounds. Per collected batch (``num_envs x rollout_len``
transitions, in time order)::

    Q(s, a) <- (1 - alpha) Q(s, a) + alpha (r + gamma (1 - terminated) max_a' Q(s', a'))

Exploration: epsilon-greedy, epsilon linear from ``eps_start`` to ``eps_end`` over
``eps_decay_frames``; greedy ties are broken at random.
"""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from mixed_traffic.training import checkpoint as ck
from mixed_traffic.training.builders import action_levels, make_collector, make_transformed_env
from mixed_traffic.training.metrics import batch_metrics
from mixed_traffic.training.run import Run


class QTable(nn.Module):
    """Sparse Q-table over binned observations (keys sorted, rows grown on demand)."""

    def __init__(self, obs_dim: int, state_bins: int, n_actions: int):
        super().__init__()
        if state_bins ** obs_dim >= 2**62:
            raise ValueError(f"state_bins={state_bins} ** obs_dim={obs_dim} does not fit an int64 key; "
                             "allowed: fewer bins or a smaller observation")
        self.obs_dim, self.state_bins, self.n_actions = obs_dim, state_bins, n_actions
        self.register_buffer("keys", torch.zeros(0, dtype=torch.long))
        self.register_buffer("q", torch.zeros(0, n_actions))
        self.register_buffer("radix", state_bins ** torch.arange(obs_dim, dtype=torch.long))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the table grows: take the stored sizes
        self.keys = state_dict[prefix + "keys"].clone()
        self.q = state_dict[prefix + "q"].clone()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def state_key(self, obs: torch.Tensor) -> torch.Tensor:
        b = (obs.clamp(0.0, 1.0) * self.state_bins).long().clamp_max(self.state_bins - 1)
        return (b * self.radix).sum(-1)

    def rows(self, key: torch.Tensor, insert: bool) -> torch.Tensor:
        """Row index of each key; -1 where absent (or inserted with zeros when ``insert``)."""
        flat = key.reshape(-1)
        if insert:
            new = flat[~self._contains(flat)].unique()
            if new.numel():
                keys = torch.cat([self.keys, new])
                order = keys.argsort()
                self.keys = keys[order]
                self.q = torch.cat([self.q, torch.zeros(new.numel(), self.n_actions)])[order]
        pos = torch.searchsorted(self.keys, flat).clamp_max(max(len(self.keys) - 1, 0))
        found = self._contains(flat)
        return torch.where(found, pos, torch.full_like(pos, -1)).reshape(key.shape)

    def _contains(self, flat: torch.Tensor) -> torch.Tensor:
        if len(self.keys) == 0:
            return torch.zeros_like(flat, dtype=torch.bool)
        pos = torch.searchsorted(self.keys, flat).clamp_max(len(self.keys) - 1)
        return self.keys[pos] == flat

    def values(self, obs: torch.Tensor) -> torch.Tensor:
        """Q-values ``[..., n_actions]`` (zeros for unseen states)."""
        r = self.rows(self.state_key(obs), insert=False)
        q = self.q[r.clamp_min(0)] if len(self.keys) else torch.zeros(*r.shape, self.n_actions)
        return torch.where((r >= 0).unsqueeze(-1), q, torch.zeros_like(q))


class TablePolicy(nn.Module):
    """Epsilon-greedy (random ties) over a :class:`QTable`; writes the action index and acceleration."""

    def __init__(self, table: QTable, levels: torch.Tensor, eps: float = 0.0):
        super().__init__()
        self.table = table
        self.register_buffer("levels", levels)
        self.eps = eps

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        q = self.table.values(obs)
        noise = torch.rand_like(q) * 1e-6  # random tie-breaking
        greedy = (q + noise).argmax(-1)
        if self.eps > 0:
            rand = torch.randint(0, q.shape[-1], greedy.shape)
            greedy = torch.where(torch.rand(greedy.shape) < self.eps, rand, greedy)
        return greedy.unsqueeze(-1), self.levels[greedy].unsqueeze(-1)


def make_table(cfg: DictConfig, env) -> tuple[QTable, TensorDictModule, TablePolicy]:
    if cfg.policy.kind != "q_table":
        raise ValueError(f"policy.kind={cfg.policy.kind!r} is invalid for loss 'q_learning'; allowed: 'q_table'")
    d = cfg.transforms.discretizer
    obs_dim = env.observation_spec["observation"].shape[-1]
    table = QTable(obs_dim, int(d.state_bins), int(d.action_bins))
    pol = TablePolicy(table, action_levels(env, int(d.action_bins)))
    return table, TensorDictModule(pol, in_keys=["observation"], out_keys=["action_index", "action"]), pol


def build_table_policy(cfg: DictConfig, env, state: dict):
    table, module, _ = make_table(cfg, env)
    table.load_state_dict(state["table"])
    return module


@torch.no_grad()
def td_update(table: QTable, batch: TensorDictBase, alpha: float, gamma: float) -> float:
    """TD(0) updates of a ``[B, T]`` batch, step by step in time order; returns the mean |TD error|."""
    errs = []
    for t in range(batch.shape[-1]):
        step = batch[..., t]
        s = table.rows(table.state_key(step["observation"]), insert=True)
        s2 = table.rows(table.state_key(step["next", "observation"]), insert=True)
        a = step["action_index"].reshape(-1)
        r = step["next", "reward"].reshape(-1)
        term = step["next", "terminated"].reshape(-1).float()
        target = r + gamma * (1.0 - term) * table.q[s2].max(-1).values
        old = table.q[s, a]
        table.q[s, a] = old + alpha * (target - old)
        errs.append((target - old).abs().mean())
    return float(torch.stack(errs).mean())


def train_tabular(cfg: DictConfig, out_dir, resume: dict | None = None) -> dict:
    tc, lc = cfg.trainer, cfg.loss
    if lc.name != "q_learning":
        raise ValueError(f"loss.name={lc.name!r} is invalid for trainer 'tabular'; allowed: 'q_learning'")
    torch.manual_seed(cfg.seed)
    env = make_transformed_env(cfg, num_envs=tc.num_envs, seed=cfg.seed)
    table, module, pol = make_table(cfg, env)
    collector, fpb, n_iters = make_collector(cfg, env, module, resume=resume)
    run = Run.start(cfg, out_dir, n_iters, fpb)
    start_iter, frames = 0, 0
    if resume is not None:
        table.load_state_dict(resume["table"])
        ck.load_env_runtime_state(env, resume["env"])
        ck.load_collector_state(collector, resume["collector"])
        ck.load_rng_state(resume["rng"])
        start_iter, frames = resume["iteration"], resume["frames"]
        run.elapsed_before = resume["wall_seconds"]

    def eps_at(f):
        return tc.eps_start + min(f / max(tc.eps_decay_frames, 1), 1.0) * (tc.eps_end - tc.eps_start)

    def payload():
        return {"table": table.state_dict(), "env": ck.env_runtime_state(env),
                "collector": ck.collector_state(collector), "rng": ck.rng_state(), "frames": frames,
                "kind": "q_table"}

    run.open_bar(start_iter)
    data = iter(collector)
    t_start, frames_start, it, stopped_early, last = time.perf_counter(), frames, start_iter, False, {}
    try:
        for it in range(start_iter, n_iters):
            pol.eps = eps_at(frames)
            batch = next(data)
            frames += batch.numel()
            m = batch_metrics(batch)
            m["td_error"] = td_update(table, batch, lc.alpha, lc.gamma)
            m["epsilon"] = pol.eps
            m["states"] = len(table.keys)
            m["fps"] = (frames - frames_start) / max(time.perf_counter() - t_start, 1e-9)
            m["wall_seconds"] = run.wall()
            last = m
            if (it + 1) % tc.log_every == 0 or it + 1 == n_iters:
                run.log(m, frames, {"R/step": m["reward_per_step"], "eps": m["epsilon"], "states": m["states"]})
            done_iters = it + 1
            if run.end_iteration(done_iters, start_iter, payload):
                stopped_early = True
                break
    except KeyboardInterrupt:
        print(f"\ninterrupted: the last checkpoint is in {run.ckpt_dir}; resume with resume={run.out_dir}")
        raise
    finally:
        collector.shutdown()
        run.close()
    pol.eps = 0.0
    summary = {"name": cfg.name, "seed": cfg.seed, "algo": "q_learning", "frames": frames, "iterations": it + 1,
               "wall_seconds": run.wall(), "completed": not stopped_early,
               "final": {k: float(v) for k, v in last.items() if v is not None}}
    if not stopped_early:
        run.save_final({"table": table.state_dict(), "kind": "q_table", "frames": frames}, summary)
    return {"summary": summary, "actor": module, "env": env, "out_dir": run.out_dir, "stopped_early": stopped_early,
            "model": table}
