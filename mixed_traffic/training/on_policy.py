"""On-policy loop: PPO and Lagrangian PPO (TorchRL Collector + GAE + ClipPPOLoss).

One iteration, CleanRL style::

    batch = collector.next()                        # [num_envs, rollout_len]
    penalty(batch)                                  # lagrangian_ppo: r <- r - lambda * c
    gae(batch)                                      # advantage, value_target (bootstraps on truncation)
    for epoch, minibatch in shuffled(batch):        # `epochs` passes
        loss = sum(loss_module(minibatch) terms)    # clipped surrogate + critic (+ value clip) - entropy
        loss.backward(); clip_grad_norm_; optim.step()
    penalty.update(batch)                           # dual ascent on lambda from the mean cost
"""

from __future__ import annotations

import functools
import time

import torch
from omegaconf import DictConfig
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from mixed_traffic.training import checkpoint as ck
from mixed_traffic.training.builders import collector_rows, make_actor_critic, make_collector, make_transformed_env
from mixed_traffic.training.metrics import batch_metrics
from mixed_traffic.training.run import Run


def build_ppo(cfg: DictConfig, env):
    """Actor, critic, loss, GAE and (Lagrangian PPO) the reward penalty holding lambda.

    ``lagrangian_ppo`` is the seed's scheme: the batch reward is penalised in the main
    process by :class:`transforms.LagrangianPenalty` (``r - lambda c``) before GAE, and the
    loss is :class:`losses.LagrangianPPOLoss` in its single-critic ("ring") form sharing
    that multiplier (plain clipped PPO, reporting lambda).
    """
    lc = cfg.loss
    if lc.name not in ("ppo", "lagrangian_ppo"):
        raise ValueError(f"loss.name={lc.name!r} is invalid for trainer 'on_policy'; allowed: 'ppo', 'lagrangian_ppo'")
    actor, critic = make_actor_critic(cfg, env)
    kw = dict(clip_epsilon=lc.clip_epsilon, entropy_coeff=lc.entropy_coeff, critic_coeff=lc.critic_coeff,
              loss_critic_type=lc.loss_critic_type, normalize_advantage=lc.normalize_advantage,
              clip_value=lc.clip_value)
    penalty = None
    if lc.name == "lagrangian_ppo":
        from losses import LagrangianPPOLoss
        from transforms import LagrangianPenalty

        penalty = LagrangianPenalty(lambda_init=lc.lambda_init, lambda_lr=lc.lambda_lr, lambda_max=lc.lambda_max,
                                    cost_limit=lc.violation_tolerance, method=lc.lambda_method,
                                    kp=lc.lambda_kp, kd=lc.lambda_kd)
        loss = LagrangianPPOLoss(actor, critic, None, multiplier=penalty.multiplier, **kw)
    else:
        loss = ClipPPOLoss(actor, critic, **kw)
    gae = GAE(gamma=lc.gamma, lmbda=lc.gae_lambda, value_network=critic, average_gae=False)
    return actor, critic, loss, gae, penalty


def restore_collection(cfg: DictConfig, env, collector, resume: dict) -> None:
    """Put the collection side of a checkpoint back, as far as it can be; say what cannot.

    The torch backend in one process (``trainer.collector=single``) restores exactly: the
    simulator tensors and the collector's carrier, so episodes in flight continue. A SUMO
    simulation's state lives inside SUMO and is not saved, and past one process the envs
    live in the workers: then the episodes in flight are lost and collection restarts
    from fresh episodes (the workers are seeded from the run seed and the iteration).
    """
    sumo = cfg.env.get("backend") == "sumo"
    single = cfg.trainer.get("collector", "single") == "single"
    if single and not sumo and resume.get("env") is not None and resume.get("collector") is not None:
        ck.load_env_runtime_state(env, resume["env"])
        ck.load_collector_state(collector, resume["collector"])
        return
    if single and sumo and resume.get("env"):  # its random generator: the next episodes draw as they would have
        ck.load_env_runtime_state(env, {k: v for k, v in resume["env"].items()
                                        if isinstance(v, tuple) and v and v[0] == "generator"})
    why = ("a SUMO simulation's state (vehicles, SUMO's clock) cannot be saved" if sumo else
           f"trainer.collector={cfg.trainer.collector}: the envs live in the collector's workers"
           if not single else "the checkpoint was written by a multi-process collector")
    print(f"resume: restored the learner, optimiser, Lagrange multiplier, counters and RNG; not the episodes in "
          f"flight ({why}): collection restarts from fresh episodes")


def train_on_policy(cfg: DictConfig, out_dir, resume: dict | None = None) -> dict:
    tc = cfg.trainer
    torch.manual_seed(cfg.seed)
    single = tc.get("collector", "single") == "single"
    # past one process the workers build their own envs; this one gives the specs
    env = make_transformed_env(cfg, num_envs=collector_rows(cfg), seed=cfg.seed)
    actor, critic, loss_module, gae, penalty = build_ppo(cfg, env)
    ws = cfg.policy.get("warm_start")
    if ws is not None and ws.nnmpc and resume is None:  # Warm Start RL: the actor starts as the NNMPC
        from mixed_traffic.controllers.deeplcc.rlmpc import warm_start_actor

        warm_start_actor(actor, env, ws.nnmpc, frames=ws.frames, epochs=ws.epochs, lr=ws.lr, seed=cfg.seed)
    optim = torch.optim.Adam(loss_module.parameters(), lr=tc.lr)
    collector, fpb, n_iters = make_collector(cfg, env, actor, resume=resume)
    if not single:
        env.close()  # only its specs were needed; a SUMO one would hold this process's libsumo
    run = Run.start(cfg, out_dir, n_iters, fpb)
    start_iter, frames = 0, 0
    if resume is not None:
        loss_module.load_state_dict(resume["model"])
        optim.load_state_dict(resume["optim"])
        if penalty is not None:
            penalty.multiplier.load_state_dict(resume["lagrange"])
        restore_collection(cfg, env, collector, resume)
        ck.load_rng_state(resume["rng"])
        start_iter, frames = resume["iteration"], resume["frames"]
        run.elapsed_before = resume["wall_seconds"]

    def payload(it):
        return {"model": loss_module.state_dict(), "optim": optim.state_dict(),
                "lagrange": penalty.multiplier.state_dict() if penalty is not None else None,
                "env": ck.env_runtime_state(env) if single else None,
                "collector": ck.collector_state(collector) if single else None,
                "rng": ck.rng_state(), "frames": frames, "kind": "ppo"}

    run.open_bar(start_iter)
    data = iter(collector)
    t_start, frames_start, it = time.perf_counter(), frames, start_iter
    stopped_early = False
    last, last_ret = {}, float("nan")
    try:
        for it in range(start_iter, n_iters):
            if tc.anneal_lr:
                for g in optim.param_groups:
                    g["lr"] = tc.lr * (1.0 - it / n_iters)
            batch = next(data)
            if batch.ndim > 2:  # multi_sync / ray: [workers, rows, T] -> [num_envs, T]
                batch = batch.reshape(-1, batch.shape[-1])
            frames += batch.numel()
            m = batch_metrics(batch)
            if penalty is not None:
                m["lambda"] = penalty.lam
                penalty(batch)  # r <- r - lambda * c (the multiplier of this batch)
            with torch.no_grad():
                gae(batch)
            flat = batch.reshape(-1)
            n = flat.numel()
            mb = min(tc.minibatch_size, n)
            sums = {}
            n_updates = 0
            for _ in range(tc.epochs):
                perm = torch.randperm(n)
                for s in range(0, n - mb + 1, mb):
                    out = loss_module(flat[perm[s:s + mb]])
                    loss = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                    optim.zero_grad(set_to_none=True)
                    loss.backward()
                    gn = torch.nn.utils.clip_grad_norm_(loss_module.parameters(), tc.max_grad_norm)
                    optim.step()
                    n_updates += 1
                    for k in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "clip_fraction",
                              "kl_approx"):
                        if k in out.keys():
                            sums[k] = sums.get(k, 0.0) + float(out[k].detach().mean())
                    sums["grad_norm"] = sums.get("grad_norm", 0.0) + float(gn)
            if not single:  # the workers' policy copies change only through TorchRL's weight sync
                collector.update_policy_weights_(actor)
            m.update({k: v / max(n_updates, 1) for k, v in sums.items()})
            if penalty is not None:
                m["lambda_next"] = penalty.update(m["mean_violation"])
            m["lr"] = optim.param_groups[0]["lr"]
            m["fps"] = (frames - frames_start) / max(time.perf_counter() - t_start, 1e-9)
            m["wall_seconds"] = run.wall()
            last = m
            if (it + 1) % tc.log_every == 0 or it + 1 == n_iters:
                run.log(m, frames, {"R/step": m["reward_per_step"], "return": m.get("episode_return", last_ret),
                                    "lam": m.get("lambda", 0.0), "coll": m["collisions"]})
            last_ret = m.get("episode_return", last_ret)
            done_iters = it + 1
            if run.end_iteration(done_iters, start_iter, functools.partial(payload, done_iters)):
                stopped_early = True
                break
    except KeyboardInterrupt:
        print(f"\ninterrupted: the last checkpoint is in {run.ckpt_dir}; resume with resume={run.out_dir}")
        raise
    finally:
        collector.shutdown()
        run.close()
    summary = {"name": cfg.name, "seed": cfg.seed, "algo": cfg.loss.name, "frames": frames,
               "iterations": it + 1, "wall_seconds": run.wall(), "completed": not stopped_early,
               "final": {k: float(v) for k, v in last.items() if v is not None}}
    if not stopped_early:
        run.save_final({"model": loss_module.state_dict(), "actor": actor.state_dict(), "kind": "ppo",
                        "lagrange": penalty.lam if penalty is not None else None, "frames": frames}, summary)
    return {"summary": summary, "actor": actor, "env": env, "out_dir": run.out_dir, "stopped_early": stopped_early,
            "model": loss_module}
