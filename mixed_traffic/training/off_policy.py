"""Off-policy loop: double DQN (TorchRL DQNLoss + SoftUpdate + ReplayBuffer + EGreedyModule).

The env keeps its continuous action; the policy chooses one of ``action_bins``
accelerations (one-hot ``"action_onehot"``, what DQNLoss reads) and maps it to ``"action"``::

    batch = collector.next()                  # epsilon-greedy, num_envs x rollout_len
    buffer.extend(batch); egreedy.step(n)     # linear epsilon decay in frames
    for _ in range(updates_per_batch):        # once the buffer holds start_learning_after
        loss = dqn_loss(buffer.sample())      # Huber on r + gamma Q_target(s', argmax_a Q(s', a))
        backward; clip_grad_norm_; step; soft target update (tau)
"""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import LazyTensorStorage, OneHot, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler
from torchrl.modules import MLP, EGreedyModule, QValueModule
from torchrl.objectives import DQNLoss, SoftUpdate

from mixed_traffic.training import checkpoint as ck
from mixed_traffic.training.builders import (
    DiscreteToContinuous,
    _activation,
    action_levels,
    make_collector,
    make_transformed_env,
)
from mixed_traffic.training.metrics import batch_metrics
from mixed_traffic.training.run import Run

KEEP = ["observation", "action_onehot", ("next", "observation"), ("next", "reward"), ("next", "done"),
        ("next", "terminated")]


def make_qvalue(cfg: DictConfig, env) -> tuple[TensorDictSequential, TensorDictModule, OneHot]:
    p = cfg.policy
    if p.kind != "qnet":
        raise ValueError(f"policy.kind={p.kind!r} is invalid for loss 'dqn'; allowed: 'qnet'")
    n_bins = int(cfg.transforms.discretizer.action_bins)
    obs_dim = env.observation_spec["observation"].shape[-1]
    net = MLP(in_features=obs_dim, out_features=n_bins, num_cells=list(p.hidden),
              activation_class=_activation(p.activation))
    spec = OneHot(n_bins)
    qvalue = TensorDictSequential(
        TensorDictModule(net, in_keys=["observation"], out_keys=["action_value"]),
        QValueModule(spec=spec, action_value_key="action_value",
                     out_keys=["action_onehot", "action_value", "chosen_action_value"]),
    )
    to_accel = TensorDictModule(DiscreteToContinuous(action_levels(env, n_bins)), in_keys=["action_onehot"],
                                out_keys=["action"])
    return qvalue, to_accel, spec


def build_dqn_policy(cfg: DictConfig, env, state: dict):
    """Greedy policy of a trained Q-network (for evaluation)."""
    qvalue, to_accel, _ = make_qvalue(cfg, env)
    qvalue.load_state_dict(state["qvalue"])
    return TensorDictSequential(qvalue, to_accel)


def train_off_policy(cfg: DictConfig, out_dir, resume: dict | None = None) -> dict:
    tc, lc = cfg.trainer, cfg.loss
    if lc.name != "dqn":
        raise ValueError(f"loss.name={lc.name!r} is invalid for trainer 'off_policy'; allowed: 'dqn'")
    torch.manual_seed(cfg.seed)
    env = make_transformed_env(cfg, num_envs=tc.num_envs, seed=cfg.seed)
    qvalue, to_accel, spec = make_qvalue(cfg, env)
    egreedy = EGreedyModule(spec=spec, eps_init=tc.eps_start, eps_end=tc.eps_end,
                            annealing_num_steps=tc.eps_decay_frames, action_key="action_onehot")
    policy = TensorDictSequential(qvalue, egreedy, to_accel)
    loss_module = DQNLoss(qvalue, loss_function=lc.loss_function, delay_value=True, double_dqn=lc.double_dqn,
                          action_space=spec)
    loss_module.set_keys(action="action_onehot")
    loss_module.make_value_estimator(gamma=lc.gamma)
    target = SoftUpdate(loss_module, tau=lc.tau)
    optim = torch.optim.Adam(loss_module.parameters(), lr=tc.lr)
    buffer = ReplayBuffer(storage=LazyTensorStorage(tc.buffer_size), sampler=RandomSampler(),
                          batch_size=tc.batch_size)
    collector, fpb, n_iters = make_collector(cfg, env, policy, resume=resume)
    run = Run.start(cfg, out_dir, n_iters, fpb)
    start_iter, frames, n_updates = 0, 0, 0
    if resume is not None:
        loss_module.load_state_dict(resume["model"])
        egreedy.load_state_dict(resume["egreedy"])
        optim.load_state_dict(resume["optim"])
        buffer.load_state_dict(resume["buffer"])
        ck.load_env_runtime_state(env, resume["env"])
        ck.load_collector_state(collector, resume["collector"])
        ck.load_rng_state(resume["rng"])
        start_iter, frames, n_updates = resume["iteration"], resume["frames"], resume["updates"]
        run.elapsed_before = resume["wall_seconds"]

    def payload():
        return {"model": loss_module.state_dict(), "egreedy": egreedy.state_dict(), "optim": optim.state_dict(),
                "buffer": buffer.state_dict(), "env": ck.env_runtime_state(env),
                "collector": ck.collector_state(collector), "rng": ck.rng_state(), "frames": frames,
                "updates": n_updates, "kind": "dqn"}

    run.open_bar(start_iter)
    data = iter(collector)
    t_start, frames_start, it, stopped_early, last = time.perf_counter(), frames, start_iter, False, {}
    try:
        for it in range(start_iter, n_iters):
            batch = next(data)
            frames += batch.numel()
            m = batch_metrics(batch)
            buffer.extend(batch.reshape(-1).select(*KEEP))
            egreedy.step(batch.numel())
            m["epsilon"] = float(egreedy.eps)
            if len(buffer) >= tc.start_learning_after:
                losses = []
                for _ in range(tc.updates_per_batch):
                    out = loss_module(buffer.sample())
                    optim.zero_grad(set_to_none=True)
                    out["loss"].backward()
                    torch.nn.utils.clip_grad_norm_(loss_module.parameters(), tc.max_grad_norm)
                    optim.step()
                    n_updates += 1
                    if n_updates % tc.target_update_every == 0:
                        target.step()
                    losses.append(float(out["loss"].detach()))
                m["loss"] = sum(losses) / len(losses)
            m["updates"] = n_updates
            m["fps"] = (frames - frames_start) / max(time.perf_counter() - t_start, 1e-9)
            m["wall_seconds"] = run.wall()
            last = m
            if (it + 1) % tc.log_every == 0 or it + 1 == n_iters:
                run.log(m, frames, {"R/step": m["reward_per_step"], "eps": m["epsilon"], "coll": m["collisions"]})
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
    summary = {"name": cfg.name, "seed": cfg.seed, "algo": "dqn", "frames": frames, "iterations": it + 1,
               "updates": n_updates, "wall_seconds": run.wall(), "completed": not stopped_early,
               "final": {k: float(v) for k, v in last.items() if v is not None}}
    if not stopped_early:
        run.save_final({"qvalue": qvalue.state_dict(), "kind": "dqn", "frames": frames}, summary)
    return {"summary": summary, "actor": TensorDictSequential(qvalue, to_accel), "env": env, "out_dir": run.out_dir,
            "stopped_early": stopped_early, "model": loss_module}
